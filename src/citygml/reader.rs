//! The streaming CityGML reader (quick-xml events; no DOM is built).
//!
//! One pass collects objects, polygons, xlink references, attributes and appearances with a
//! stack of open elements; references, the LoD choice and derived ids are resolved after EOF.
//! This file is the parser and driver (events, namespaces, element dispatch, line numbers);
//! the bytes are decoded first by `encoding`, and the elements' meaning is built by
//! `geometry`, `hierarchy` and `appearance`.
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use quick_xml::XmlVersion;
use quick_xml::events::{BytesStart, Event};
use quick_xml::name::ResolveResult;
use quick_xml::reader::NsReader;

use super::CityGmlError;
use super::appearance::AppField;
use super::encoding::decode_text;
use super::geometry::{CoordKind, PolyBuilder, Reference, lod_property};
use super::hierarchy::{CONTAINMENT, GenAttrBuilder, SIMPLE_ATTRS};
use super::model::*;

/// City objects nested deeper than this are refused: real models nest a handful of levels
/// (building → part → surface → opening), and the ids derived for objects without a gml:id
/// grow with the depth (`<parent id>/<Class>[k]`), so thousands of levels would cost memory
/// quadratic in the depth.
pub(super) const MAX_OBJECT_NESTING: usize = 32;

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
pub(super) enum Tag {
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

/// Streaming state.
pub(super) struct Parser {
    pub(super) path: PathBuf,
    pub(super) file: String,
    pub(super) version: Option<Version>,
    pub(super) root_seen: bool,
    pub(super) srs_name: Option<String>,
    pub(super) stack: Vec<Tag>,
    pub(super) unknown_depth: usize,
    pub(super) curve_depth: usize,
    pub(super) objects: Vec<CityObject>,
    pub(super) object_stack: Vec<usize>,
    /// Children count per (parent, class) for derived ids.
    pub(super) lod: Option<u8>,
    pub(super) container_ids: Vec<String>,
    pub(super) reversed_depth: usize,
    pub(super) poly: Option<PolyBuilder>,
    pub(super) ring_is_interior: Option<bool>,
    pub(super) ring: Option<Ring>,
    pub(super) dim_stack: Vec<(usize, usize)>,
    pub(super) coord_dim: usize,
    pub(super) coord_cs: String,
    pub(super) coord_ts: String,
    pub(super) text: String,
    pub(super) collecting: bool,
    pub(super) polygons: Vec<Polygon>,
    /// id → polygon indices (a polygon's own id and ids of containers around it).
    pub(super) geometry_ids: HashMap<String, Vec<usize>>,
    /// Container id → the hrefs of its xlink members (a `CompositeSurface` of references).
    pub(super) container_refs: HashMap<String, Vec<String>>,
    pub(super) references: Vec<Reference>,
    pub(super) gen_attrs: Vec<GenAttrBuilder>,
    pub(super) gen_set: Vec<String>,
    pub(super) textures: Vec<Texture>,
    pub(super) materials: Vec<Material>,
    pub(super) app_theme: Option<String>,
    pub(super) in_material: bool,
    pub(super) tex_ring: Option<String>,
    pub(super) stats: ReadStats,
    pub(super) warnings: Vec<Warning>,
    /// gml:id → line of its first use.
    pub(super) ids: HashMap<String, u64>,
    /// Entity names declared in the document type (reported, never expanded).
    pub(super) dtd_entities: Vec<String>,
    /// Byte offset of the start tag being read.
    pub(super) tag_offset: u64,
}

/// Reads one CityGML file (1.0, 2.0 or 3.0). The file is read whole and decoded to UTF-8
/// first (`encoding::decode_text`), so line numbers count the file's own lines in every encoding.
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
        container_refs: HashMap::new(),
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
        tag_offset: 0,
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
                p.tag_offset = offset;
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
pub(super) struct Attrs {
    pub(super) gml_id: Option<String>,
    pub(super) href: Option<String>,
    pub(super) srs_name: Option<String>,
    pub(super) srs_dimension: Option<String>,
    pub(super) orientation: Option<String>,
    pub(super) name: Option<String>,
    pub(super) uom: Option<String>,
    pub(super) uri: Option<String>,
    pub(super) ring: Option<String>,
    pub(super) cs: Option<String>,
    pub(super) ts: Option<String>,
    /// Why a used attribute's value could not be read (e.g. an undefined entity).
    pub(super) error: Option<String>,
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

impl Parser {
    pub(super) fn warn(&mut self, line: u64, id: Option<String>, message: String) {
        self.warnings.push(Warning {
            file: self.file.clone(),
            line,
            id,
            message,
        });
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
                if self.object_stack.len() >= MAX_OBJECT_NESTING {
                    return Err(CityGmlError::Content {
                        path: self.path.clone(),
                        line,
                        message: format!(
                            "{local}{} is nested in {} other city objects (buildings, parts, \
                             installations, surfaces, openings); gs4city reads at most \
                             {MAX_OBJECT_NESTING} levels",
                            a.gml_id
                                .as_deref()
                                .map(|id| format!(" gml:id \"{id}\""))
                                .unwrap_or_default(),
                            self.object_stack.len()
                        ),
                    });
                }
                return Ok(self.begin_object(class, a, line));
            }
            if let Some(lod) = lod_property(local) {
                return Ok(self.geometry_property(local, lod, a, line));
            }
            if parent_is_object {
                if SIMPLE_ATTRS.contains(&local) {
                    return Ok(self.attribute_start(local, a));
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

    pub(super) fn begin_text(&mut self) {
        self.text.clear();
        self.collecting = true;
    }

    pub(super) fn take_text(&mut self) -> String {
        self.collecting = false;
        std::mem::take(&mut self.text)
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
            Tag::Ring => self.finish_ring(),
            Tag::Coords(kind) => self.finish_coords(kind, line)?,
            Tag::Polygon => self.finish_polygon(),
            Tag::Attr(key) => self.finish_attr(key),
            Tag::GenName => self.finish_gen_name(),
            Tag::GenValue => self.finish_gen_value(),
            Tag::GenAttr => self.finish_generic_attribute(),
            Tag::Texture | Tag::Material => {}
            Tag::AppText(field) => self.finish_app_text(field),
            Tag::AppTarget => self.finish_app_target(),
            Tag::TexCoords => self.finish_tex_coords(),
        }
        Ok(())
    }

    fn finish(mut self) -> Result<CityModel, CityGmlError> {
        let Some(version) = self.version else {
            return Err(CityGmlError::NotCityGml {
                path: self.path.clone(),
                line: 1,
                root: "(no CityGML version in the CityModel namespace)".into(),
            });
        };
        self.resolve_references();
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
}
