//! The streaming CityGML reader (quick-xml events; no DOM is built).
//!
//! One pass collects objects, polygons, xlink references, attributes and appearances with a
//! stack of open elements; references, the LoD choice and derived ids are resolved after EOF.
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use glam::DVec3;
use quick_xml::XmlVersion;
use quick_xml::events::{BytesStart, Event};
use quick_xml::name::ResolveResult;
use quick_xml::reader::NsReader;

use super::CityGmlError;
use super::model::*;

/// Maps byte offsets of the text to 1-based line numbers with a forward cursor: offsets
/// arrive in increasing order while the XML streams, so the whole file costs one pass and
/// no memory per line (a step back recounts from the start).
struct Lines<'a> {
    text: &'a [u8],
    pos: usize,
    line: u64,
}

impl Lines<'_> {
    fn line_of(&mut self, offset: u64) -> u64 {
        let offset = (offset as usize).min(self.text.len());
        if offset < self.pos {
            self.pos = 0;
            self.line = 1;
        }
        self.line += self.text[self.pos..offset]
            .iter()
            .filter(|&&b| b == b'\n')
            .count() as u64;
        self.pos = offset;
        self.line
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Ns {
    Gml,
    City(Module),
    Xlink,
    Other,
    None,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Module {
    Core,
    Building,
    Construction,
    Generics,
    Appearance,
    Other,
}

fn classify_ns(s: &str) -> (Ns, Option<Version>) {
    if s.starts_with("http://www.opengis.net/gml") {
        return (Ns::Gml, None);
    }
    if s == "http://www.w3.org/1999/xlink" {
        return (Ns::Xlink, None);
    }
    if let Some(rest) = s.strip_prefix("http://www.opengis.net/citygml/") {
        let version = if rest.ends_with("1.0") {
            Some(Version::V1)
        } else if rest.ends_with("2.0") {
            Some(Version::V2)
        } else if rest.ends_with("3.0") {
            Some(Version::V3)
        } else {
            None
        };
        let module = match rest.split('/').next().unwrap_or("") {
            "1.0" | "2.0" | "3.0" => Module::Core,
            "building" => Module::Building,
            "construction" => Module::Construction,
            "generics" => Module::Generics,
            "appearance" => Module::Appearance,
            _ => Module::Other,
        };
        // `citygml/profiles/base/1.0` is a profile namespace, not core.
        let module = if rest.starts_with("profiles") {
            Module::Other
        } else {
            module
        };
        return (Ns::City(module), version);
    }
    (Ns::Other, None)
}

/// What an open element means; popped on its end tag.
#[derive(Debug)]
enum Tag {
    Plain,
    /// An element we do not understand (root of an unknown subtree, or inside one).
    Unknown,
    Object,
    /// `lodNxxx` geometry property; restores the previous LoD on end.
    GeomProp(Option<u8>),
    /// A geometry container; `true` when it pushed an id, second when it reversed orientation.
    Container(bool, bool),
    Polygon,
    RingRole,
    Ring,
    Coords(CoordKind),
    Curve,
    Implicit,
    Attr(String),
    GenAttr,
    GenName,
    GenValue,
    Texture,
    Material,
    TexCoords,
    AppTarget,
    AppText(AppField),
}

#[derive(Debug, Clone, Copy)]
enum CoordKind {
    Pos,
    PosList,
    Coordinates,
}

#[derive(Debug, Clone, Copy)]
enum AppField {
    ImageUri,
    Theme,
    Diffuse,
    Transparency,
}

struct PolyBuilder {
    id: Option<String>,
    exterior: Option<Ring>,
    interiors: Vec<Ring>,
    line: u64,
    owner: Option<usize>,
    lod: Option<u8>,
    reversed: bool,
    bad: Option<String>,
}

struct GenAttrBuilder {
    kind: String,
    name: Option<String>,
    value: Option<String>,
    uom: Option<String>,
}

struct Reference {
    href: String,
    owner: Option<usize>,
    lod: Option<u8>,
    reversed: bool,
    line: u64,
}

const GEOM_CONTAINERS: &[&str] = &[
    "MultiSurface",
    "CompositeSurface",
    "Solid",
    "CompositeSolid",
    "MultiSolid",
    "Shell",
    "Surface",
    "OrientableSurface",
    "TriangulatedSurface",
    "Tin",
    "PolyhedralSurface",
    "MultiGeometry",
    "GeometricComplex",
    "surfaceMember",
    "surfaceMembers",
    "solidMember",
    "geometryMember",
    "geometryMembers",
    "baseSurface",
    "patches",
    "trianglePatches",
    "polygonPatches",
    "exterior",
    "interior",
    "member",
];
const CURVES: &[&str] = &[
    "LineString",
    "Curve",
    "MultiCurve",
    "CompositeCurve",
    "OrientableCurve",
    "Point",
    "MultiPoint",
    "LineStringSegment",
    "Arc",
];
const PATCHES: &[&str] = &["Polygon", "Triangle", "PolygonPatch", "Rectangle"];
const SIMPLE_ATTRS: &[&str] = &[
    "measuredHeight",
    "function",
    "usage",
    "class",
    "roofType",
    "storeysAboveGround",
    "storeysBelowGround",
    "storeyHeightsAboveGround",
    "storeyHeightsBelowGround",
    "yearOfConstruction",
    "yearOfDemolition",
    "creationDate",
    "terminationDate",
    "relativeToTerrain",
    "relativeToWater",
    "name",
    "description",
];
const CONTAINMENT: &[&str] = &[
    "boundedBy",
    "boundary",
    "opening",
    "outerBuildingInstallation",
    "buildingInstallation",
    "consistsOfBuildingPart",
    "buildingPart",
    "fillingSurface",
    "filling",
    "buildingConstructiveElement",
    "cityObjectMember",
    "featureMember",
];

/// Streaming state.
struct Parser {
    path: PathBuf,
    file: String,
    version: Option<Version>,
    root_seen: bool,
    srs_name: Option<String>,
    stack: Vec<Tag>,
    unknown_depth: usize,
    curve_depth: usize,
    objects: Vec<CityObject>,
    object_stack: Vec<usize>,
    /// Children count per (parent, class) for derived ids.
    lod: Option<u8>,
    container_ids: Vec<String>,
    reversed_depth: usize,
    poly: Option<PolyBuilder>,
    ring_is_interior: Option<bool>,
    ring: Option<Ring>,
    dim_stack: Vec<(usize, usize)>,
    coord_dim: usize,
    coord_cs: String,
    coord_ts: String,
    text: String,
    collecting: bool,
    polygons: Vec<Polygon>,
    /// id → polygon indices (a polygon's own id and ids of containers around it).
    geometry_ids: HashMap<String, Vec<usize>>,
    references: Vec<Reference>,
    gen_attrs: Vec<GenAttrBuilder>,
    gen_set: Vec<String>,
    textures: Vec<Texture>,
    materials: Vec<Material>,
    app_theme: Option<String>,
    in_material: bool,
    tex_ring: Option<String>,
    stats: ReadStats,
    warnings: Vec<Warning>,
    /// gml:id → line of its first use.
    ids: HashMap<String, u64>,
    /// Entity names declared in the document type (reported, never expanded).
    dtd_entities: Vec<String>,
}

/// Reads one CityGML file (1.0, 2.0 or 3.0). The file is read whole and decoded to UTF-8
/// first ([`decode_text`]), so line numbers count the file's own lines in every encoding.
pub fn read(path: &Path) -> Result<CityModel, CityGmlError> {
    let bytes = std::fs::read(path).map_err(|err| CityGmlError::Open {
        path: path.to_path_buf(),
        err,
    })?;
    read_bytes(path, &bytes)
}

/// Reads CityGML from bytes (`path` names the source in messages).
pub fn read_bytes(path: &Path, bytes: &[u8]) -> Result<CityModel, CityGmlError> {
    let text = decode_text(path, bytes)?;
    parse(path, &text)
}

/// The 1-based line of byte `offset` of `bytes`.
fn line_at(bytes: &[u8], offset: usize) -> u64 {
    1 + bytes[..offset.min(bytes.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count() as u64
}

/// The `encoding` of the XML declaration, if the text starts with one.
fn declared_encoding(bytes: &[u8]) -> Option<String> {
    let head = &bytes[..bytes.len().min(1024)];
    if !head.starts_with(b"<?xml") {
        return None;
    }
    let end = head.windows(2).position(|w| w == b"?>")?;
    let decl = std::str::from_utf8(&head[..end]).ok()?;
    let at = decl.find("encoding")?;
    let rest = decl[at + 8..].trim_start().strip_prefix('=')?.trim_start();
    let quote = rest.chars().next().filter(|c| *c == '"' || *c == '\'')?;
    let value = &rest[1..];
    Some(value[..value.find(quote)?].to_string())
}

/// windows-1252 code points of bytes 0x80..=0x9F (the WHATWG table; the five unassigned
/// bytes map to the C1 controls of the same value).
const CP1252_HIGH: [u16; 32] = [
    0x20AC, 0x81, 0x201A, 0x0192, 0x201E, 0x2026, 0x2020, 0x2021, 0x02C6, 0x2030, 0x0160, 0x2039,
    0x0152, 0x8D, 0x017D, 0x8F, 0x90, 0x2018, 0x2019, 0x201C, 0x201D, 0x2022, 0x2013, 0x2014,
    0x02DC, 0x2122, 0x0161, 0x203A, 0x0153, 0x9D, 0x017E, 0x0178,
];

/// The text of a CityGML file as UTF-8: UTF-8 (with or without BOM) as is, UTF-16 with a
/// BOM, and ISO-8859-1 / windows-1252 when the XML declaration names them, transcoded
/// (newlines are kept, so line numbers stay the file's own). Invalid UTF-8 is an error that
/// names the line of the first bad byte; an encoding the reader does not know is an error.
pub fn decode_text<'a>(
    path: &Path,
    bytes: &'a [u8],
) -> Result<std::borrow::Cow<'a, [u8]>, CityGmlError> {
    use std::borrow::Cow;
    let err = |line: u64, message: String| CityGmlError::Encoding {
        path: path.to_path_buf(),
        line,
        message,
    };
    let utf16 = |body: &[u8], big: bool| -> Result<Cow<'a, [u8]>, CityGmlError> {
        let units = body.chunks(2).map(|c| match (c, big) {
            ([a, b], true) => u16::from_be_bytes([*a, *b]),
            ([a, b], false) => u16::from_le_bytes([*a, *b]),
            _ => 0xDC00, // an odd trailing byte: a lone surrogate, reported below
        });
        let mut out = String::with_capacity(body.len() / 2);
        for c in char::decode_utf16(units) {
            match c {
                Ok(c) => out.push(c),
                Err(_) => {
                    let line = 1 + out.matches('\n').count() as u64;
                    return Err(err(line, "the file is not valid UTF-16".into()));
                }
            }
        }
        Ok(Cow::Owned(out.into_bytes()))
    };
    if let Some(body) = bytes.strip_prefix(b"\xFF\xFE") {
        return utf16(body, false);
    }
    if let Some(body) = bytes.strip_prefix(b"\xFE\xFF") {
        return utf16(body, true);
    }
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let declared = declared_encoding(bytes);
    let norm = declared
        .as_deref()
        .map(|e| e.trim().to_ascii_lowercase().replace('_', "-"));
    match norm.as_deref() {
        None | Some("utf-8" | "utf8" | "us-ascii" | "ascii") => match std::str::from_utf8(bytes) {
            Ok(_) => Ok(Cow::Borrowed(bytes)),
            Err(e) => {
                let at = e.valid_up_to();
                Err(err(
                    line_at(bytes, at),
                    format!(
                        "the file is not valid UTF-8 (byte {:#04x}); if it is in another encoding, name it in the XML declaration, e.g. encoding=\"ISO-8859-1\"",
                        bytes[at]
                    ),
                ))
            }
        },
        Some("iso-8859-1" | "iso8859-1" | "latin1" | "latin-1" | "l1" | "iso-ir-100") => {
            Ok(Cow::Owned(
                bytes
                    .iter()
                    .map(|&b| char::from(b))
                    .collect::<String>()
                    .into_bytes(),
            ))
        }
        Some("windows-1252" | "cp1252" | "x-cp1252") => Ok(Cow::Owned(
            bytes
                .iter()
                .map(|&b| match b {
                    0x80..=0x9F => char::from_u32(u32::from(CP1252_HIGH[usize::from(b - 0x80)]))
                        .unwrap_or('\u{FFFD}'),
                    _ => char::from(b),
                })
                .collect::<String>()
                .into_bytes(),
        )),
        Some(_) => Err(err(
            1,
            format!(
                "the XML declaration names encoding \"{}\"; gs4city reads UTF-8, UTF-16 (with a byte-order mark), ISO-8859-1 and windows-1252",
                declared.unwrap_or_default()
            ),
        )),
    }
}

fn parse(path: &Path, text: &[u8]) -> Result<CityModel, CityGmlError> {
    let mut reader = NsReader::from_reader(text);
    let mut lines = Lines {
        text,
        pos: 0,
        line: 1,
    };
    reader.config_mut().expand_empty_elements = true;
    reader.config_mut().check_end_names = true;
    let mut p = Parser {
        path: path.to_path_buf(),
        file: path.display().to_string(),
        version: None,
        root_seen: false,
        srs_name: None,
        stack: Vec::with_capacity(64),
        unknown_depth: 0,
        curve_depth: 0,
        objects: Vec::new(),
        object_stack: Vec::new(),
        lod: None,
        container_ids: Vec::new(),
        reversed_depth: 0,
        poly: None,
        ring_is_interior: None,
        ring: None,
        dim_stack: Vec::new(),
        coord_dim: 3,
        coord_cs: ",".into(),
        coord_ts: " ".into(),
        text: String::new(),
        collecting: false,
        polygons: Vec::new(),
        geometry_ids: HashMap::new(),
        references: Vec::new(),
        gen_attrs: Vec::new(),
        gen_set: Vec::new(),
        textures: Vec::new(),
        materials: Vec::new(),
        app_theme: None,
        in_material: false,
        tex_ring: None,
        stats: ReadStats::default(),
        warnings: Vec::new(),
        ids: HashMap::new(),
        dtd_entities: Vec::new(),
    };
    let mut buf = Vec::with_capacity(1 << 16);
    loop {
        let offset = reader.buffer_position();
        let ev = reader.read_resolved_event_into(&mut buf);
        let (ns, event) = match ev {
            Ok(x) => x,
            Err(e) => {
                let pos = reader.error_position();
                let line = lines.line_of(pos);
                return Err(CityGmlError::Xml {
                    path: p.path.clone(),
                    line,
                    message: e.to_string(),
                });
            }
        };
        let ns = match ns {
            ResolveResult::Bound(n) => classify_ns(n.as_ref()),
            _ => (Ns::None, None),
        };
        match event {
            Event::Start(e) => {
                let line = lines.line_of(offset);
                let attrs = Attrs::read(&reader, &e);
                p.start(ns, &e, attrs, line)?;
            }
            Event::End(_) => {
                let line = lines.line_of(offset);
                p.end(line)?;
            }
            Event::Text(t) if p.collecting => p.text.push_str(&t.xml10_content()),
            Event::CData(t) if p.collecting => p.text.push_str(&t.xml10_content()),
            Event::GeneralRef(r) => {
                let name = r.xml10_content();
                let s = match r.resolve_char_ref() {
                    Ok(Some(c)) => c.to_string(),
                    Err(_) => {
                        let line = lines.line_of(offset);
                        return Err(CityGmlError::Content {
                            path: p.path.clone(),
                            line,
                            message: format!("&{name}; is not a valid character reference"),
                        });
                    }
                    Ok(None) => match name.as_ref() {
                        "lt" => "<".into(),
                        "gt" => ">".into(),
                        "amp" => "&".into(),
                        "apos" => "'".into(),
                        "quot" => "\"".into(),
                        other => {
                            let line = lines.line_of(offset);
                            let message = if p.dtd_entities.iter().any(|e| e == other) {
                                format!(
                                    "entity &{other}; is declared in the document type, but gs4city does not expand document-type entities"
                                )
                            } else {
                                format!(
                                    "undefined XML entity &{other}; (XML predefines only &lt; &gt; &amp; &apos; &quot;)"
                                )
                            };
                            return Err(CityGmlError::Content {
                                path: p.path.clone(),
                                line,
                                message,
                            });
                        }
                    },
                };
                if p.collecting {
                    p.text.push_str(&s);
                }
            }
            Event::DocType(d) => {
                // Remember declared entity names (they are reported, never expanded).
                let text: &str = d.as_ref();
                for decl in text.split("<!ENTITY").skip(1) {
                    let mut words = decl.split_whitespace();
                    let name = match words.next() {
                        Some("%") => words.next(),
                        n => n,
                    };
                    if let Some(n) = name {
                        p.dtd_entities.push(n.to_string());
                    }
                }
            }
            Event::Eof => {
                let open = p.stack.len();
                if open > 0 {
                    let line = lines.line_of(offset);
                    return Err(CityGmlError::Truncated {
                        path: p.path.clone(),
                        line,
                        open,
                    });
                }
                break;
            }
            _ => {}
        }
        buf.clear();
    }
    p.stats.bytes = text.len() as u64;
    p.finish()
}

/// The attributes of a start tag that the reader uses.
#[derive(Default)]
struct Attrs {
    gml_id: Option<String>,
    href: Option<String>,
    srs_name: Option<String>,
    srs_dimension: Option<String>,
    orientation: Option<String>,
    name: Option<String>,
    uom: Option<String>,
    uri: Option<String>,
    ring: Option<String>,
    cs: Option<String>,
    ts: Option<String>,
    /// Why a used attribute's value could not be read (e.g. an undefined entity).
    error: Option<String>,
}

impl Attrs {
    fn read<R>(reader: &NsReader<R>, e: &BytesStart) -> Attrs {
        let mut a = Attrs::default();
        for attr in e.attributes().with_checks(false).flatten() {
            let (ns, local) = reader.resolver().resolve_attribute(attr.key);
            let mut error = None;
            let mut value = || match attr.normalized_value(XmlVersion::Implicit1_0) {
                Ok(v) => Some(v.into_owned()),
                Err(e) => {
                    error = Some(format!(
                        "attribute {}: {e}",
                        AsRef::<str>::as_ref(&attr.key)
                    ));
                    None
                }
            };
            let is_gml = matches!(&ns, ResolveResult::Bound(n) if n.as_ref().starts_with("http://www.opengis.net/gml"));
            let is_xlink = matches!(&ns, ResolveResult::Bound(n) if n.as_ref() == "http://www.w3.org/1999/xlink");
            match local.as_ref() {
                "id" if is_gml || matches!(ns, ResolveResult::Unbound) => a.gml_id = value(),
                "href" if is_xlink => a.href = value(),
                "srsName" => a.srs_name = value(),
                "srsDimension" => a.srs_dimension = value(),
                "orientation" => a.orientation = value(),
                "name" => a.name = value(),
                "uom" => a.uom = value(),
                "uri" => a.uri = value(),
                "ring" => a.ring = value(),
                "cs" => a.cs = value(),
                "ts" => a.ts = value(),
                _ => {}
            }
            if a.error.is_none() {
                a.error = error;
            }
        }
        a
    }
}

fn lod_property(local: &str) -> Option<u8> {
    let rest = local.strip_prefix("lod")?;
    let d = rest.chars().next()?.to_digit(10)?;
    let kind = &rest[1..];
    if kind.is_empty() {
        return None;
    }
    Some(d as u8)
}

impl Parser {
    fn warn(&mut self, line: u64, id: Option<String>, message: String) {
        self.warnings.push(Warning {
            file: self.file.clone(),
            line,
            id,
            message,
        });
    }

    /// A gml:id used a second time: a warning; a city object gets a unique name so the
    /// hierarchy table stays unambiguous.
    fn duplicate_id(&mut self, id: &str, first: u64, line: u64, is_object: bool) {
        if !is_object {
            self.warn(
                line,
                Some(id.to_string()),
                format!("gml:id \"{id}\" is already used at line {first}; gml:ids must be unique in a file, so references to it are ambiguous"),
            );
            return;
        }
        let o = self.objects.len() - 1;
        let mut n = 2;
        let mut unique = format!("{id}~{n}");
        while self.ids.contains_key(&unique) {
            n += 1;
            unique = format!("{id}~{n}");
        }
        self.ids.insert(unique.clone(), line);
        let class = self.objects[o].class.name();
        self.objects[o].object_id = unique.clone();
        self.warn(
            line,
            Some(id.to_string()),
            format!("gml:id \"{id}\" is already used at line {first}; this {class} is called \"{unique}\" in the hierarchy table"),
        );
    }

    fn current_object(&self) -> Option<usize> {
        self.object_stack.last().copied()
    }

    fn start(
        &mut self,
        (ns, version): (Ns, Option<Version>),
        e: &BytesStart,
        a: Attrs,
        line: u64,
    ) -> Result<(), CityGmlError> {
        let local_bytes = e.local_name();
        let local: &str = local_bytes.as_ref();
        if !self.root_seen {
            self.root_seen = true;
            if !(matches!(ns, Ns::City(Module::Core)) && local == "CityModel") {
                let qname = e.name().as_ref().to_string();
                return Err(CityGmlError::NotCityGml {
                    path: self.path.clone(),
                    line,
                    root: qname,
                });
            }
            self.version = version;
        }
        if let Some(why) = &a.error {
            return Err(CityGmlError::Content {
                path: self.path.clone(),
                line,
                message: why.clone(),
            });
        }
        if let Some(d) = a.srs_dimension.as_deref() {
            let Some(d) = d
                .trim()
                .parse::<usize>()
                .ok()
                .filter(|d| (1..=3).contains(d))
            else {
                return Err(CityGmlError::Content {
                    path: self.path.clone(),
                    line,
                    message: format!(
                        "srsDimension=\"{d}\" is not a valid dimension (gs4city reads 2 or 3)"
                    ),
                });
            };
            self.dim_stack.push((self.stack.len(), d));
        }
        let duplicate_of = match &a.gml_id {
            Some(id) => match self.ids.get(id) {
                Some(&first) => Some(first),
                None => {
                    self.ids.insert(id.clone(), line);
                    None
                }
            },
            None => None,
        };
        if self.srs_name.is_none() {
            self.srs_name = a.srs_name.clone();
        }
        let parent_is_object = matches!(self.stack.last(), Some(Tag::Object));
        let tag = self.classify(ns, local, &a, parent_is_object, line)?;
        if let (Some(first), Some(id)) = (duplicate_of, &a.gml_id) {
            self.duplicate_id(id, first, line, matches!(tag, Tag::Object));
        }
        if matches!(tag, Tag::Unknown) {
            if self.unknown_depth == 0 {
                let prefix = match ns {
                    Ns::Gml => "gml:",
                    Ns::City(_) => "citygml:",
                    Ns::Xlink => "xlink:",
                    Ns::Other => "other:",
                    Ns::None => "",
                };
                *self
                    .stats
                    .unknown_elements
                    .entry(format!("{prefix}{local}"))
                    .or_default() += 1;
            }
            self.unknown_depth += 1;
        }
        self.stack.push(tag);
        Ok(())
    }

    fn classify(
        &mut self,
        ns: Ns,
        local: &str,
        a: &Attrs,
        parent_is_object: bool,
        line: u64,
    ) -> Result<Tag, CityGmlError> {
        // Appearance (CityGML app: module), anywhere.
        if let Ns::City(Module::Appearance) = ns {
            return Ok(self.appearance_start(local, a));
        }
        if let Ns::City(module) = ns {
            if matches!(
                module,
                Module::Building | Module::Construction | Module::Core
            ) && let Some(class) = Class::from_local_name(local)
            {
                let parent = self.current_object();
                let idx = self.objects.len();
                self.objects.push(CityObject {
                    class,
                    object_id: a.gml_id.clone().unwrap_or_default(),
                    has_gml_id: a.gml_id.is_some(),
                    parent,
                    attributes: BTreeMap::new(),
                    line,
                    lod_used: None,
                });
                self.object_stack.push(idx);
                return Ok(Tag::Object);
            }
            if let Some(lod) = lod_property(local) {
                if local.contains("Implicit") {
                    self.stats.implicit_skipped += 1;
                    self.warn(
                        line,
                        self.current_object()
                            .map(|o| self.objects[o].object_id.clone()),
                        format!("{local}: implicit geometry is not supported, skipped"),
                    );
                    return Ok(Tag::Implicit);
                }
                let prev = self.lod;
                self.lod = Some(lod);
                if let Some(href) = &a.href {
                    self.add_reference(href, line);
                }
                return Ok(Tag::GeomProp(prev));
            }
            if parent_is_object {
                if SIMPLE_ATTRS.contains(&local) {
                    self.begin_text();
                    if let (Some(uom), Some(o)) = (&a.uom, self.current_object()) {
                        self.objects[o]
                            .attributes
                            .insert(format!("{local}.uom"), uom.clone().into());
                    }
                    return Ok(Tag::Attr(local.to_string()));
                }
                if local == "genericAttribute" || local == "height" {
                    return Ok(Tag::Plain);
                }
            }
            if module == Module::Generics || (module == Module::Construction && local == "Height") {
                return Ok(self.generic_start(local, a));
            }
            if matches!(local, "value" | "highReference" | "lowReference" | "status")
                && !self.gen_attrs.is_empty()
            {
                return Ok(self.generic_start(local, a));
            }
            if CONTAINMENT.contains(&local) || local == "CityModel" {
                return Ok(Tag::Plain);
            }
            return Ok(Tag::Unknown);
        }
        if ns == Ns::Gml {
            return Ok(self.gml_start(local, a, parent_is_object, line));
        }
        Ok(Tag::Unknown)
    }

    fn gml_start(&mut self, local: &str, a: &Attrs, parent_is_object: bool, line: u64) -> Tag {
        if self.curve_depth > 0 {
            // Everything inside a skipped curve/point geometry is part of it.
            self.curve_depth += 1;
            return Tag::Curve;
        }
        if let Some(href) = &a.href
            && self.lod.is_some()
        {
            self.add_reference(href, line);
            return Tag::Plain;
        }
        if PATCHES.contains(&local) {
            if self.poly.is_some() {
                self.warn(
                    line,
                    a.gml_id.clone(),
                    format!("nested gml:{local} inside a polygon ignored"),
                );
                return Tag::Unknown;
            }
            self.stats.polygons += 1;
            self.poly = Some(PolyBuilder {
                id: a.gml_id.clone(),
                exterior: None,
                interiors: Vec::new(),
                line,
                owner: if self.lod.is_some() {
                    self.current_object()
                } else {
                    None
                },
                lod: self.lod,
                reversed: self.reversed_depth % 2 == 1,
                bad: None,
            });
            return Tag::Polygon;
        }
        if self.poly.is_some() {
            match local {
                "exterior" | "outerBoundaryIs" => {
                    self.ring_is_interior = Some(false);
                    return Tag::RingRole;
                }
                "interior" | "innerBoundaryIs" => {
                    self.ring_is_interior = Some(true);
                    self.stats.holes += 1;
                    return Tag::RingRole;
                }
                "LinearRing" => {
                    self.ring = Some(Ring {
                        id: a.gml_id.clone(),
                        points: Vec::new(),
                    });
                    return Tag::Ring;
                }
                "pos" | "posList" | "coordinates" if self.ring.is_some() => {
                    self.coord_dim = a
                        .srs_dimension
                        .as_deref()
                        .and_then(|d| d.trim().parse().ok())
                        .or_else(|| self.dim_stack.last().map(|&(_, d)| d))
                        .unwrap_or(3);
                    self.coord_cs = a.cs.clone().unwrap_or_else(|| ",".into());
                    self.coord_ts = a.ts.clone().unwrap_or_else(|| " ".into());
                    self.begin_text();
                    return Tag::Coords(match local {
                        "pos" => CoordKind::Pos,
                        "posList" => CoordKind::PosList,
                        _ => CoordKind::Coordinates,
                    });
                }
                "Ring" | "curveMember" => {
                    if let Some(pb) = self.poly.as_mut()
                        && pb.bad.is_none()
                    {
                        pb.bad = Some("gml:Ring made of curve members is not supported".into());
                    }
                    return Tag::Plain;
                }
                _ => {}
            }
        }
        if CURVES.contains(&local) || (local == "curveMember" && self.poly.is_none()) {
            if self.poly.is_none() && local != "curveMember" {
                self.stats.curves_skipped += 1;
            }
            self.curve_depth += 1;
            return Tag::Curve;
        }
        if GEOM_CONTAINERS.contains(&local) {
            let reversed = local == "OrientableSurface" && a.orientation.as_deref() == Some("-");
            if reversed {
                self.reversed_depth += 1;
            }
            let has_id = if let Some(id) = &a.gml_id {
                self.container_ids.push(id.clone());
                true
            } else {
                false
            };
            return Tag::Container(has_id, reversed);
        }
        if parent_is_object && matches!(local, "name" | "description") {
            self.begin_text();
            return Tag::Attr(local.to_string());
        }
        match local {
            "boundedBy" | "Envelope" | "lowerCorner" | "upperCorner" | "featureMember" => {
                Tag::Plain
            }
            _ => Tag::Unknown,
        }
    }

    fn appearance_start(&mut self, local: &str, a: &Attrs) -> Tag {
        match local {
            "ParameterizedTexture" => {
                self.in_material = false;
                self.textures.push(Texture {
                    theme: self.app_theme.clone(),
                    ..Default::default()
                });
                Tag::Texture
            }
            "X3DMaterial" => {
                self.in_material = true;
                self.materials.push(Material::default());
                Tag::Material
            }
            "imageURI" => {
                self.begin_text();
                Tag::AppText(AppField::ImageUri)
            }
            "theme" => {
                self.begin_text();
                Tag::AppText(AppField::Theme)
            }
            "diffuseColor" => {
                self.begin_text();
                Tag::AppText(AppField::Diffuse)
            }
            "transparency" => {
                self.begin_text();
                Tag::AppText(AppField::Transparency)
            }
            "textureCoordinates" => {
                self.tex_ring = a
                    .ring
                    .as_ref()
                    .map(|r| r.trim_start_matches('#').to_string());
                self.begin_text();
                Tag::TexCoords
            }
            "target" => {
                self.begin_text();
                Tag::AppTarget
            }
            _ => Tag::Plain,
        }
    }

    fn generic_start(&mut self, local: &str, a: &Attrs) -> Tag {
        match local {
            "genericAttributeSet" | "GenericAttributeSet" => {
                if let Some(n) = &a.name {
                    self.gen_set.push(n.clone());
                }
                Tag::Plain
            }
            "name" if !self.gen_attrs.is_empty() => {
                self.begin_text();
                Tag::GenName
            }
            "value" | "highReference" | "lowReference" | "status" if !self.gen_attrs.is_empty() => {
                if let Some(g) = self.gen_attrs.last_mut()
                    && a.uom.is_some()
                {
                    g.uom = a.uom.clone();
                }
                self.begin_text();
                if local == "value" {
                    Tag::GenValue
                } else {
                    Tag::Attr(format!("height.{local}"))
                }
            }
            _ if local.ends_with("Attribute") || local == "Height" => {
                let name = if local == "Height" {
                    Some("height".to_string())
                } else {
                    a.name.clone()
                };
                self.gen_attrs.push(GenAttrBuilder {
                    kind: local.to_string(),
                    name,
                    value: None,
                    uom: a.uom.clone(),
                });
                Tag::GenAttr
            }
            _ => Tag::Unknown,
        }
    }

    fn begin_text(&mut self) {
        self.text.clear();
        self.collecting = true;
    }

    fn take_text(&mut self) -> String {
        self.collecting = false;
        std::mem::take(&mut self.text)
    }

    fn add_reference(&mut self, href: &str, line: u64) {
        self.references.push(Reference {
            href: href.trim_start_matches('#').to_string(),
            owner: self.current_object(),
            lod: self.lod,
            reversed: self.reversed_depth % 2 == 1,
            line,
        });
    }

    fn set_attr(&mut self, key: String, value: serde_json::Value) {
        let Some(o) = self.current_object() else {
            return;
        };
        let attrs = &mut self.objects[o].attributes;
        match attrs.get_mut(&key) {
            None => {
                attrs.insert(key, value);
            }
            Some(serde_json::Value::Array(v)) => v.push(value),
            Some(old) => {
                let prev = old.take();
                *old = serde_json::Value::Array(vec![prev, value]);
            }
        }
    }

    fn end(&mut self, line: u64) -> Result<(), CityGmlError> {
        let depth = self.stack.len();
        let Some(tag) = self.stack.pop() else {
            return Ok(());
        };
        while self.dim_stack.last().is_some_and(|&(d, _)| d + 1 >= depth) {
            self.dim_stack.pop();
        }
        match tag {
            Tag::Plain | Tag::Implicit => {}
            Tag::Curve => self.curve_depth -= 1,
            Tag::Unknown => self.unknown_depth -= 1,
            Tag::Object => {
                self.object_stack.pop();
            }
            Tag::GeomProp(prev) => self.lod = prev,
            Tag::Container(has_id, reversed) => {
                if has_id {
                    self.container_ids.pop();
                }
                if reversed {
                    self.reversed_depth -= 1;
                }
            }
            Tag::RingRole => self.ring_is_interior = None,
            Tag::Ring => {
                let ring = self.ring.take().unwrap_or_default();
                if let Some(pb) = self.poly.as_mut() {
                    match self.ring_is_interior {
                        Some(true) => pb.interiors.push(ring),
                        _ if pb.exterior.is_none() => pb.exterior = Some(ring),
                        _ => {
                            if pb.bad.is_none() {
                                pb.bad = Some("second exterior ring".into());
                            }
                        }
                    }
                }
            }
            Tag::Coords(kind) => self.finish_coords(kind, line)?,
            Tag::Polygon => self.finish_polygon(),
            Tag::Attr(key) => {
                let text = self.take_text();
                let text = text.trim();
                if !text.is_empty() {
                    let value = typed_value(&key, text);
                    self.set_attr(key, value);
                }
            }
            Tag::GenName => {
                let t = self.take_text();
                if let Some(g) = self.gen_attrs.last_mut() {
                    g.name = Some(t.trim().to_string());
                }
            }
            Tag::GenValue => {
                let t = self.take_text();
                if let Some(g) = self.gen_attrs.last_mut() {
                    g.value = Some(t.trim().to_string());
                }
            }
            Tag::GenAttr => {
                if let Some(g) = self.gen_attrs.pop()
                    && let (Some(name), Some(value)) = (g.name, g.value)
                {
                    let mut key = self
                        .gen_set
                        .iter()
                        .map(|s| format!("{s}/"))
                        .collect::<String>();
                    key.push_str(&name);
                    let kind = g.kind.to_ascii_lowercase();
                    let v = if kind.starts_with("int") {
                        value
                            .parse::<i64>()
                            .map(Into::into)
                            .unwrap_or_else(|_| value.clone().into())
                    } else if kind.starts_with("double")
                        || kind.starts_with("measure")
                        || kind == "height"
                    {
                        value
                            .parse::<f64>()
                            .ok()
                            .and_then(serde_json::Number::from_f64)
                            .map(Into::into)
                            .unwrap_or_else(|| value.clone().into())
                    } else {
                        value.clone().into()
                    };
                    if let Some(uom) = g.uom {
                        self.set_attr(format!("{key}.uom"), uom.into());
                    }
                    self.set_attr(key, v);
                }
            }
            Tag::Texture | Tag::Material => {}
            Tag::AppText(field) => {
                let t = self.take_text();
                let t = t.trim();
                match field {
                    AppField::ImageUri => {
                        if let Some(tex) = self.textures.last_mut() {
                            tex.image_uri = t.to_string();
                        }
                    }
                    AppField::Theme => self.app_theme = Some(t.to_string()),
                    AppField::Diffuse => {
                        let v: Vec<f64> = t
                            .split_whitespace()
                            .filter_map(|x| x.parse().ok())
                            .collect();
                        if let (Some(m), [r, g, b]) = (self.materials.last_mut(), v.as_slice()) {
                            m.diffuse = Some([*r, *g, *b]);
                        }
                    }
                    AppField::Transparency => {
                        if let Some(m) = self.materials.last_mut() {
                            m.transparency = t.parse().ok();
                        }
                    }
                }
            }
            Tag::AppTarget => {
                let t = self.take_text();
                let t = t.trim().trim_start_matches('#');
                if !t.is_empty()
                    && self.in_material
                    && let Some(m) = self.materials.last_mut()
                {
                    m.targets.push(t.to_string());
                }
            }
            Tag::TexCoords => {
                let t = self.take_text();
                let vals: Vec<f64> = t
                    .split_whitespace()
                    .filter_map(|x| x.parse().ok())
                    .collect();
                let mut uv: Vec<[f64; 2]> = vals.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
                if uv.len() > 1 && uv.first() == uv.last() {
                    uv.pop();
                }
                if let (Some(ring), Some(tex)) = (self.tex_ring.take(), self.textures.last_mut()) {
                    tex.rings.insert(ring, uv);
                }
            }
        }
        Ok(())
    }

    fn finish_coords(&mut self, kind: CoordKind, line: u64) -> Result<(), CityGmlError> {
        let text = self.take_text();
        let dim = self.coord_dim;
        if !(2..=3).contains(&dim) {
            return Err(CityGmlError::Geometry {
                path: self.path.clone(),
                line,
                id: self.poly.as_ref().and_then(|p| p.id.clone()),
                message: format!("srsDimension {dim} is not supported (2 or 3)"),
            });
        }
        let mut values = Vec::new();
        let parse = |tok: &str| -> Result<f64, CityGmlError> {
            tok.parse::<f64>().map_err(|_| CityGmlError::Geometry {
                path: self.path.clone(),
                line,
                id: self.poly.as_ref().and_then(|p| p.id.clone()),
                message: format!("'{tok}' is not a number"),
            })
        };
        match kind {
            CoordKind::Pos | CoordKind::PosList => {
                for tok in text.split_ascii_whitespace() {
                    values.push(parse(tok)?);
                }
            }
            CoordKind::Coordinates => {
                let ts = self.coord_ts.clone();
                let cs = self.coord_cs.clone();
                let tuples: Vec<&str> = if ts.trim().is_empty() {
                    text.split_ascii_whitespace().collect()
                } else {
                    text.split(ts.as_str())
                        .filter(|s| !s.trim().is_empty())
                        .collect()
                };
                for tuple in tuples {
                    let parts: Vec<&str> = tuple.split(cs.as_str()).map(str::trim).collect();
                    if parts.len() != dim {
                        return Err(CityGmlError::Geometry {
                            path: self.path.clone(),
                            line,
                            id: self.poly.as_ref().and_then(|p| p.id.clone()),
                            message: format!(
                                "coordinate tuple '{tuple}' does not have {dim} values"
                            ),
                        });
                    }
                    for t in parts {
                        values.push(parse(t)?);
                    }
                }
            }
        }
        if values.len() % dim != 0 {
            return Err(CityGmlError::Geometry {
                path: self.path.clone(),
                line,
                id: self.poly.as_ref().and_then(|p| p.id.clone()),
                message: format!(
                    "{} coordinate values are not a multiple of srsDimension {dim}",
                    values.len()
                ),
            });
        }
        if let Some(ring) = self.ring.as_mut() {
            for c in values.chunks_exact(dim) {
                let z = if dim == 3 { c[2] } else { 0.0 };
                ring.points.push(DVec3::new(c[0], c[1], z));
            }
        }
        Ok(())
    }

    fn finish_polygon(&mut self) {
        let Some(mut pb) = self.poly.take() else {
            return;
        };
        let ordinal = self.polygons.len();
        let exterior = pb.exterior.take().unwrap_or_default();
        if pb.bad.is_none() && exterior.points.is_empty() {
            pb.bad = Some("no exterior ring".into());
        }
        let mut poly = Polygon {
            id: pb.id.clone(),
            exterior,
            interiors: pb.interiors,
            owner: pb.owner,
            lod: pb.lod,
            reversed: pb.reversed,
            line: pb.line,
            ordinal,
        };
        for ring in std::iter::once(&mut poly.exterior).chain(poly.interiors.iter_mut()) {
            if ring.points.len() > 1 && ring.points.first() == ring.points.last() {
                ring.points.pop();
            }
        }
        if let Some(why) = pb.bad {
            // The warning names the file, line and gml:id already.
            let what = if poly.id.is_some() {
                "polygon".to_string()
            } else {
                poly.name()
            };
            self.warn(pb.line, pb.id.clone(), format!("{what} skipped: {why}"));
            poly.owner = None;
        }
        if let Some(id) = &poly.id {
            self.geometry_ids
                .entry(id.clone())
                .or_default()
                .push(ordinal);
        }
        for cid in &self.container_ids {
            self.geometry_ids
                .entry(cid.clone())
                .or_default()
                .push(ordinal);
        }
        self.polygons.push(poly);
    }

    fn finish(mut self) -> Result<CityModel, CityGmlError> {
        let Some(version) = self.version else {
            return Err(CityGmlError::NotCityGml {
                path: self.path.clone(),
                line: 1,
                root: "(no CityGML version in the CityModel namespace)".into(),
            });
        };
        // xlink references: geometry owned inline is the same geometry, counted once.
        for r in std::mem::take(&mut self.references) {
            match self.geometry_ids.get(&r.href) {
                None => {
                    self.stats.xlinks_dangling += 1;
                    let id = r.owner.map(|o| self.objects[o].object_id.clone());
                    self.warn(r.line, id, format!("dangling xlink:href=\"#{}\": no geometry with that gml:id, reference skipped", r.href));
                }
                Some(targets) => {
                    for &t in targets {
                        let poly = &mut self.polygons[t];
                        if poly.owner.is_some() || r.owner.is_none() {
                            self.stats.xlinks_shared += 1;
                        } else {
                            poly.owner = r.owner;
                            poly.lod = r.lod;
                            poly.reversed ^= r.reversed;
                            self.stats.xlinks_adopted += 1;
                        }
                    }
                }
            }
        }
        self.derive_ids();
        self.choose_lods();
        self.stats.polygons_unused = self
            .polygons
            .iter()
            .filter(|p| match (p.owner, p.lod) {
                (Some(o), Some(l)) => self.objects[o].lod_used != Some(l),
                _ => true,
            })
            .count();
        Ok(CityModel {
            path: self.path,
            version,
            srs_name: self.srs_name,
            objects: self.objects,
            polygons: self.polygons,
            textures: self.textures,
            materials: self.materials,
            stats: self.stats,
            warnings: self.warnings,
        })
    }

    /// Objects without gml:id get `<parent id>/<Class>[k]` (k counts siblings of that class
    /// in document order), or `<file stem>/<Class>[k]` at top level; made unique if needed.
    fn derive_ids(&mut self) {
        let stem = self
            .path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let mut taken: std::collections::HashSet<String> = self
            .objects
            .iter()
            .filter(|o| o.has_gml_id)
            .map(|o| o.object_id.clone())
            .collect();
        let mut sibling: HashMap<(Option<usize>, Class), usize> = HashMap::new();
        for i in 0..self.objects.len() {
            let (parent, class) = (self.objects[i].parent, self.objects[i].class);
            let k = sibling.entry((parent, class)).or_default();
            *k += 1;
            if self.objects[i].has_gml_id {
                continue;
            }
            let base = match parent {
                Some(p) => self.objects[p].object_id.clone(),
                None => stem.clone(),
            };
            let mut id = format!("{base}/{}[{}]", class.name(), *k);
            let mut n = 1;
            while taken.contains(&id) {
                n += 1;
                id = format!("{base}/{}[{}]~{n}", class.name(), *k);
            }
            taken.insert(id.clone());
            self.objects[i].object_id = id;
        }
    }

    /// Per top-level object (building): use LoD3 geometry; where the building has none,
    /// fall back to LoD2, then LoD1, and say so. LoD0 and LoD4 are never used.
    fn choose_lods(&mut self) {
        let n = self.objects.len();
        let mut root = vec![0usize; n];
        for (i, o) in self.objects.iter().enumerate() {
            root[i] = match o.parent {
                Some(p) => root[p],
                None => i,
            };
        }
        let mut present: BTreeMap<usize, [bool; 5]> = BTreeMap::new();
        for poly in &self.polygons {
            if let (Some(o), Some(l)) = (poly.owner, poly.lod) {
                present.entry(root[o]).or_default()[l.min(4) as usize] = true;
            }
        }
        let mut chosen: BTreeMap<usize, u8> = BTreeMap::new();
        for (&r, lods) in &present {
            let pick = [3u8, 2, 1].into_iter().find(|&l| lods[l as usize]);
            if let Some(l) = pick {
                chosen.insert(r, l);
                if l != 3 {
                    let id = self.objects[r].object_id.clone();
                    let line = self.objects[r].line;
                    self.warn(line, Some(id), format!("no LoD3 geometry: using LoD{l}"));
                }
            } else {
                let id = self.objects[r].object_id.clone();
                let line = self.objects[r].line;
                self.warn(
                    line,
                    Some(id),
                    "no LoD1–3 geometry (only LoD0/LoD4): nothing to triangulate".into(),
                );
            }
        }
        for (o, r) in self.objects.iter_mut().zip(&root) {
            o.lod_used = chosen.get(r).copied();
        }
    }
}

/// Numbers stay numbers (measuredHeight, storeys, years); everything else is text.
fn typed_value(key: &str, text: &str) -> serde_json::Value {
    let numeric = matches!(
        key,
        "measuredHeight"
            | "storeysAboveGround"
            | "storeysBelowGround"
            | "yearOfConstruction"
            | "yearOfDemolition"
    );
    if numeric {
        if let Ok(i) = text.parse::<i64>() {
            return i.into();
        }
        if let Some(n) = text
            .parse::<f64>()
            .ok()
            .and_then(serde_json::Number::from_f64)
        {
            return n.into();
        }
    }
    text.to_string().into()
}
