//! What the CityGML reader returns: city objects with their classes, parents, attributes
//! and georeferenced (f64) polygons, plus appearance data and read statistics.
use std::collections::BTreeMap;
use std::path::PathBuf;

use glam::DVec3;
use serde::Serialize;

/// Encoding and version of a city-model file: CityGML from its namespaces, CityJSON from
/// its `version`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Version {
    #[serde(rename = "1.0")]
    V1,
    #[serde(rename = "2.0")]
    V2,
    #[serde(rename = "3.0")]
    V3,
    /// Read by `crate::cityjson` (the same typed model from CityJSON).
    #[serde(rename = "CityJSON 1.0")]
    CityJson10,
    #[serde(rename = "CityJSON 1.1")]
    CityJson11,
    #[serde(rename = "CityJSON 2.0")]
    CityJson20,
}

/// The level of the GS4City hierarchy an object belongs to.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Level {
    Feature,
    Surface,
    Part,
}

impl Level {
    /// The level's name, as in `semantics.json`.
    pub fn name(self) -> &'static str {
        match self {
            Level::Feature => "feature",
            Level::Surface => "surface",
            Level::Part => "part",
        }
    }
}

/// The city-object classes gs4city understands (CityGML 1.0/2.0 `bldg:`, 3.0 `bldg:`/`con:`/core).
/// Serialised by its CityGML name (as in `semantics.json`).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, serde::Deserialize,
)]
pub enum Class {
    Building,
    BuildingPart,
    BuildingInstallation,
    /// CityGML 3.0 `bldg:BuildingConstructiveElement` (balconies, chimneys…): an installation.
    BuildingConstructiveElement,
    WallSurface,
    RoofSurface,
    GroundSurface,
    ClosureSurface,
    OuterCeilingSurface,
    OuterFloorSurface,
    Window,
    Door,
    /// CityGML 3.0 `con:WindowSurface`.
    WindowSurface,
    /// CityGML 3.0 `con:DoorSurface`.
    DoorSurface,
}

impl Class {
    /// Maps a CityGML element local name to a class.
    pub fn from_local_name(name: &str) -> Option<Class> {
        Some(match name {
            "Building" => Class::Building,
            "BuildingPart" => Class::BuildingPart,
            "BuildingInstallation" => Class::BuildingInstallation,
            "BuildingConstructiveElement" => Class::BuildingConstructiveElement,
            "WallSurface" => Class::WallSurface,
            "RoofSurface" => Class::RoofSurface,
            "GroundSurface" => Class::GroundSurface,
            "ClosureSurface" => Class::ClosureSurface,
            "OuterCeilingSurface" => Class::OuterCeilingSurface,
            "OuterFloorSurface" => Class::OuterFloorSurface,
            "Window" => Class::Window,
            "Door" => Class::Door,
            "WindowSurface" => Class::WindowSurface,
            "DoorSurface" => Class::DoorSurface,
            _ => return None,
        })
    }

    /// The class name as written in CityGML.
    pub fn name(self) -> &'static str {
        match self {
            Class::Building => "Building",
            Class::BuildingPart => "BuildingPart",
            Class::BuildingInstallation => "BuildingInstallation",
            Class::BuildingConstructiveElement => "BuildingConstructiveElement",
            Class::WallSurface => "WallSurface",
            Class::RoofSurface => "RoofSurface",
            Class::GroundSurface => "GroundSurface",
            Class::ClosureSurface => "ClosureSurface",
            Class::OuterCeilingSurface => "OuterCeilingSurface",
            Class::OuterFloorSurface => "OuterFloorSurface",
            Class::Window => "Window",
            Class::Door => "Door",
            Class::WindowSurface => "WindowSurface",
            Class::DoorSurface => "DoorSurface",
        }
    }

    /// The hierarchy level (`docs/design.md`): buildings, parts and installations are features,
    /// thematic surfaces are surfaces, openings are parts.
    pub fn level(self) -> Level {
        match self {
            Class::Building
            | Class::BuildingPart
            | Class::BuildingInstallation
            | Class::BuildingConstructiveElement => Level::Feature,
            Class::WallSurface
            | Class::RoofSurface
            | Class::GroundSurface
            | Class::ClosureSurface
            | Class::OuterCeilingSurface
            | Class::OuterFloorSurface => Level::Surface,
            Class::Window | Class::Door | Class::WindowSurface | Class::DoorSurface => Level::Part,
        }
    }

    /// Window-like (2.0 Window, 3.0 WindowSurface).
    pub fn is_window(self) -> bool {
        matches!(self, Class::Window | Class::WindowSurface)
    }

    /// Door-like (2.0 Door, 3.0 DoorSurface).
    pub fn is_door(self) -> bool {
        matches!(self, Class::Door | Class::DoorSurface)
    }

    /// Installation-like (2.0 BuildingInstallation, 3.0 BuildingConstructiveElement).
    pub fn is_installation(self) -> bool {
        matches!(
            self,
            Class::BuildingInstallation | Class::BuildingConstructiveElement
        )
    }
}

/// A closed ring; the closing duplicate of the first point is removed.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Ring {
    pub id: Option<String>,
    pub points: Vec<DVec3>,
}

/// A planar surface patch (gml:Polygon, Triangle, PolygonPatch, Rectangle) in the file's CRS (f64).
#[derive(Debug, Clone, PartialEq)]
pub struct Polygon {
    /// gml:id, if the file gives one.
    pub id: Option<String>,
    pub exterior: Ring,
    pub interiors: Vec<Ring>,
    /// Owning object (index into [`CityModel::objects`]); `None` when the polygon lies outside
    /// any understood object's geometry.
    pub owner: Option<usize>,
    /// LoD of the geometry property it was found in (0–4), `None` outside any.
    pub lod: Option<u8>,
    /// Reversed by an `OrientableSurface orientation="-"`.
    pub reversed: bool,
    /// Line of the polygon's start tag.
    pub line: u64,
    /// Ordinal among all polygons of the file (document order).
    pub ordinal: usize,
}

/// Most points a polygon may have, all its rings together; the pipeline skips a longer one
/// with a warning that names it. The largest ring of the real LoD3 samples has 73 points. A
/// constrained Delaunay triangulation of points on one circle takes a time that grows with
/// the square of their number (40,000 points took 5 s, 150,000 over a minute), and so does the
/// scene check's distance query on a fan of such a ring.
pub const MAX_POLYGON_POINTS: usize = 10_000;

impl Polygon {
    /// Its points, all rings together.
    pub fn points(&self) -> usize {
        self.exterior.points.len() + self.interiors.iter().map(|r| r.points.len()).sum::<usize>()
    }

    /// A name for messages that already give the line: `polygon <gml:id>`, or
    /// `polygon #<ordinal> (no gml:id)`.
    pub fn name(&self) -> String {
        match &self.id {
            Some(id) => format!("polygon {id}"),
            None => format!("polygon #{} (no gml:id)", self.ordinal),
        }
    }

    /// A name for messages: the gml:id, or the ordinal and line.
    pub fn label(&self) -> String {
        match &self.id {
            Some(id) => format!("polygon {id} (line {})", self.line),
            None => format!("polygon #{} (line {}, no gml:id)", self.ordinal, self.line),
        }
    }
}

/// One understood city object.
#[derive(Debug, Clone, PartialEq)]
pub struct CityObject {
    pub class: Class,
    /// The gml:id, or a stable id derived from the parent's id, the class and the ordinal.
    pub object_id: String,
    /// Whether `object_id` came from the file.
    pub has_gml_id: bool,
    /// Parent object (index into [`CityModel::objects`]).
    pub parent: Option<usize>,
    /// Attributes: numbers or strings; units as `"<name>.uom"`, repeated values as arrays.
    pub attributes: BTreeMap<String, serde_json::Value>,
    /// Line of the object's start tag.
    pub line: u64,
    /// Byte offset of the object's start tag in the file's text as read (UTF-8, after a
    /// byte-order mark; transcoded files: in the transcoded text); 0 in CityJSON.
    pub offset: u64,
    /// The LoD whose geometry is used (chosen per building: 3, else 2, else 1).
    pub lod_used: Option<u8>,
}

/// A `ParameterizedTexture`: the image and the texture coordinates of each target ring.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Texture {
    pub image_uri: String,
    pub theme: Option<String>,
    /// ring gml:id (without `#`) → texture coordinates, one per ring point (closing point removed).
    pub rings: BTreeMap<String, Vec<[f64; 2]>>,
}

/// An `X3DMaterial` with the polygon/surface ids it targets.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Material {
    pub diffuse: Option<[f64; 3]>,
    pub transparency: Option<f64>,
    pub targets: Vec<String>,
}

/// A warning that names what it is about.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Warning {
    pub file: String,
    pub line: u64,
    /// gml:id (or derived id) of the object or polygon concerned, if any.
    pub id: Option<String>,
    pub message: String,
}

impl std::fmt::Display for Warning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}: ", self.file, self.line)?;
        if let Some(id) = &self.id {
            write!(f, "{id}: ")?;
        }
        f.write_str(&self.message)
    }
}

/// Counts the reader keeps while it streams.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ReadStats {
    pub bytes: u64,
    /// Surface patches read (gml:Polygon, Triangle, PolygonPatch, Rectangle).
    pub polygons: usize,
    /// Interior rings read.
    pub holes: usize,
    /// Curve and point geometries skipped (LineString, Curve, MultiCurve, Point…).
    pub curves_skipped: usize,
    /// xlink references that pointed at geometry already owned inline (counted once).
    pub xlinks_shared: usize,
    /// xlink references whose target geometry was adopted by the referencing object.
    pub xlinks_adopted: usize,
    /// xlink references to ids the file does not define.
    pub xlinks_dangling: usize,
    /// Polygons not used: outside understood objects, LoD 0/4, or of a LoD not chosen.
    pub polygons_unused: usize,
    /// Implicit geometries (not supported) skipped.
    pub implicit_skipped: usize,
    /// Unknown elements (subtree roots) by qualified name.
    pub unknown_elements: BTreeMap<String, usize>,
}

/// One CityGML file, read.
#[derive(Debug, Clone)]
pub struct CityModel {
    pub path: PathBuf,
    pub version: Version,
    /// srsName of the root envelope (or the first geometry that names one).
    pub srs_name: Option<String>,
    pub objects: Vec<CityObject>,
    pub polygons: Vec<Polygon>,
    pub textures: Vec<Texture>,
    pub materials: Vec<Material>,
    pub stats: ReadStats,
    pub warnings: Vec<Warning>,
}

impl CityModel {
    /// Polygons used for the mesh: owned by an object, of the LoD chosen for it.
    pub fn used_polygons(&self) -> impl Iterator<Item = &Polygon> {
        self.polygons
            .iter()
            .filter(move |p| match (p.owner, p.lod) {
                (Some(o), Some(l)) => self.objects[o].lod_used == Some(l),
                _ => false,
            })
    }

    /// Number of objects of a class.
    pub fn count(&self, class: Class) -> usize {
        self.objects.iter().filter(|o| o.class == class).count()
    }
}
