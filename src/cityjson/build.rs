//! CityJSON objects, semantic surfaces and boundaries → the typed [`CityModel`].
use std::collections::{BTreeMap, HashMap, HashSet};
use std::io::BufRead;
use std::path::Path;

use glam::DVec3;
use serde_json::{Map, Value};

use super::CityJsonError;
use crate::citygml::{CityModel, CityObject, Class, Polygon, ReadStats, Ring, Version, Warning};

/// A surface whose points lie farther from its plane than this share of its bounding-box
/// diagonal, and farther than [`PLANARITY_MIN`], is refused as non-planar: folded, not merely
/// imprecise (the real LoD3 data of the project deviate by at most 7 mm).
pub const PLANARITY_TOLERANCE: f64 = 0.02;
/// The absolute part of the planarity test, in the file's units (metres in a projected CRS).
pub const PLANARITY_MIN: f64 = 0.05;

/// Where a problem lies: the file and, in a CityJSONSeq, the line.
#[derive(Clone, Copy)]
struct At<'a> {
    path: &'a Path,
    line: Option<u64>,
}

impl At<'_> {
    fn err(&self, object: Option<&str>, message: impl Into<String>) -> CityJsonError {
        CityJsonError::Content {
            path: self.path.to_path_buf(),
            line: self.line,
            object: object.map(str::to_string),
            message: message.into(),
        }
    }
}

/// What the header (a CityJSON document, or a CityJSONSeq's first line) fixes.
struct Header {
    version: Version,
    /// `scale`, `translate`; `None` only in CityJSON 1.0 without a transform.
    transform: Option<([f64; 3], [f64; 3])>,
    srs: Option<String>,
}

fn json_err(path: &Path, line: u64, e: serde_json::Error) -> CityJsonError {
    CityJsonError::Json {
        path: path.to_path_buf(),
        line: line + e.line() as u64 - 1,
        message: e.to_string(),
    }
}

/// A CityJSON document.
pub(super) fn read_document(path: &Path, bytes: &[u8]) -> Result<CityModel, CityJsonError> {
    let at = At { path, line: None };
    let doc: Value = serde_json::from_slice(crate::fsutil::strip_bom(bytes))
        .map_err(|e| json_err(path, 1, e))?;
    let root = doc
        .as_object()
        .ok_or_else(|| at.err(None, "the top level is not a JSON object"))?;
    if root.get("type").and_then(Value::as_str) == Some("CityJSONFeature") {
        return Err(at.err(
            None,
            "a CityJSONFeature alone: a CityJSONSeq stream is read from a .city.jsonl file whose first line is the CityJSON header",
        ));
    }
    let header = header(at, root)?;
    let mut b = Builder::new(path, header, bytes.len() as u64);
    b.add(at, root)?;
    Ok(b.finish())
}

/// A CityJSONSeq stream, line by line: the header, then one `CityJSONFeature` per line.
pub(super) fn read_seq(path: &Path) -> Result<CityModel, CityJsonError> {
    let open_err = |err| CityJsonError::Open {
        path: path.to_path_buf(),
        err,
    };
    let file = std::fs::File::open(path).map_err(open_err)?;
    let mut reader = std::io::BufReader::new(file);
    let mut text = String::new();
    let mut line = 0u64;
    let mut builder: Option<Builder> = None;
    loop {
        text.clear();
        let n = reader.read_line(&mut text).map_err(open_err)?;
        if n == 0 {
            break;
        }
        line += 1;
        if text.trim().is_empty() {
            continue;
        }
        let at = At {
            path,
            line: Some(line),
        };
        let body = if line == 1 {
            text.trim_start_matches('\u{feff}')
        } else {
            &text
        };
        let v: Value = serde_json::from_str(body).map_err(|e| json_err(path, line, e))?;
        let obj = v
            .as_object()
            .ok_or_else(|| at.err(None, "the line is not a JSON object"))?;
        match &mut builder {
            None => {
                if obj.get("type").and_then(Value::as_str) != Some("CityJSON") {
                    return Err(at.err(
                        None,
                        "the first line of a CityJSONSeq must be the CityJSON header (\"type\": \"CityJSON\")",
                    ));
                }
                let header = header(at, obj)?;
                let mut b = Builder::new(path, header, 0);
                b.add(at, obj)?;
                builder = Some(b);
            }
            Some(b) => {
                match obj.get("type").and_then(Value::as_str) {
                    Some("CityJSONFeature") => {}
                    other => {
                        return Err(at.err(
                            None,
                            format!(
                                "\"type\" is {}, expected \"CityJSONFeature\" (every line after the header is one feature)",
                                other.map(|t| format!("\"{t}\"")).unwrap_or("missing".into())
                            ),
                        ));
                    }
                }
                if let Some(id) = obj.get("id") {
                    let id = id
                        .as_str()
                        .ok_or_else(|| at.err(None, "the feature's \"id\" is not a string"))?;
                    let known = obj
                        .get("CityObjects")
                        .and_then(Value::as_object)
                        .is_some_and(|c| c.contains_key(id));
                    if !known {
                        return Err(at.err(
                            Some(id),
                            "the feature's \"id\" names no CityObject of the feature",
                        ));
                    }
                }
                b.add(at, obj)?;
            }
        }
    }
    let mut b = builder
        .ok_or_else(|| At { path, line: None }.err(None, "empty CityJSONSeq: no header line"))?;
    b.stats.bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
    Ok(b.finish())
}

fn three_numbers(v: Option<&Value>) -> Option<[f64; 3]> {
    let a = v?.as_array()?;
    if a.len() != 3 {
        return None;
    }
    let mut out = [0.0; 3];
    for (o, x) in out.iter_mut().zip(a) {
        *o = x.as_f64().filter(|f| f.is_finite())?;
    }
    Some(out)
}

fn header(at: At, root: &Map<String, Value>) -> Result<Header, CityJsonError> {
    match root.get("type").and_then(Value::as_str) {
        Some("CityJSON") => {}
        other => {
            return Err(at.err(
                None,
                format!(
                    "not a CityJSON file: \"type\" is {}, expected \"CityJSON\"",
                    other
                        .map(|t| format!("\"{t}\""))
                        .unwrap_or("missing".into())
                ),
            ));
        }
    }
    let version = match root.get("version").and_then(Value::as_str) {
        Some("1.0") => Version::CityJson10,
        Some("1.1") => Version::CityJson11,
        Some(v) if v == "2.0" || v.starts_with("2.0.") => Version::CityJson20,
        Some(v) => {
            return Err(at.err(
                None,
                format!("CityJSON version \"{v}\" is not read (1.0, 1.1 and 2.0 are)"),
            ));
        }
        None => return Err(at.err(None, "no \"version\" string")),
    };
    let transform = match root.get("transform") {
        None if version == Version::CityJson10 => None,
        None => {
            return Err(at.err(
                None,
                "no \"transform\": CityJSON 1.1 and 2.0 store vertices as integers that the transform (scale, translate) decodes",
            ));
        }
        Some(t) => {
            let t = t
                .as_object()
                .ok_or_else(|| at.err(None, "\"transform\" is not an object"))?;
            let scale = three_numbers(t.get("scale")).ok_or_else(|| {
                at.err(
                    None,
                    format!(
                        "\"transform\".\"scale\" must be 3 finite numbers, got {}",
                        t.get("scale")
                            .map(|v| v.to_string())
                            .unwrap_or("nothing".into())
                    ),
                )
            })?;
            if scale.contains(&0.0) {
                return Err(at.err(
                    None,
                    format!(
                        "\"transform\".\"scale\" {scale:?} has a zero: every vertex would collapse"
                    ),
                ));
            }
            let translate = three_numbers(t.get("translate")).ok_or_else(|| {
                at.err(
                    None,
                    format!(
                        "\"transform\".\"translate\" must be 3 finite numbers, got {}",
                        t.get("translate")
                            .map(|v| v.to_string())
                            .unwrap_or("nothing".into())
                    ),
                )
            })?;
            Some((scale, translate))
        }
    };
    let srs = match root.get("metadata").and_then(|m| m.get("referenceSystem")) {
        None => None,
        Some(Value::String(s)) => Some(s.clone()),
        Some(other) => {
            return Err(at.err(
                None,
                format!("\"metadata\".\"referenceSystem\" is not a string: {other}"),
            ));
        }
    };
    Ok(Header {
        version,
        transform,
        srs,
    })
}

/// The building classes that are CityObjects in CityJSON.
fn object_class(t: &str) -> Option<Class> {
    match t {
        "Building" | "BuildingPart" | "BuildingInstallation" | "BuildingConstructiveElement" => {
            Class::from_local_name(t)
        }
        _ => None,
    }
}

/// The semantic surface types gs4city understands (CityJSON names Windows and Doors plainly).
fn surface_class(t: &str) -> Option<Class> {
    match t {
        "WallSurface"
        | "RoofSurface"
        | "GroundSurface"
        | "ClosureSurface"
        | "OuterCeilingSurface"
        | "OuterFloorSurface"
        | "Window"
        | "Door" => Class::from_local_name(t),
        _ => None,
    }
}

/// Attributes: `{"value": v, "uom": u}` → `name` = v, `name.uom` = u; everything else as is.
fn attributes<'a>(
    members: impl Iterator<Item = (&'a String, &'a Value)>,
) -> BTreeMap<String, Value> {
    let mut out = BTreeMap::new();
    for (k, v) in members {
        if let Some(o) = v.as_object()
            && o.len() == 2
            && let (Some(value), Some(Value::String(uom))) = (o.get("value"), o.get("uom"))
        {
            out.insert(k.clone(), value.clone());
            out.insert(format!("{k}.uom"), Value::String(uom.clone()));
            continue;
        }
        out.insert(k.clone(), v.clone());
    }
    out
}

/// The surface-carrying geometry types and how many array levels lie above a surface list.
fn surface_depth(t: &str) -> Option<usize> {
    match t {
        "MultiSurface" | "CompositeSurface" => Some(0),
        "Solid" => Some(1),
        "MultiSolid" | "CompositeSolid" => Some(2),
        _ => None,
    }
}

/// A geometry's LoD: `"2.2"` (1.1/2.0) or `2.2` (1.0) → (`"2.2"`, 2).
fn lod_of(g: &Map<String, Value>) -> Option<(String, u8)> {
    let s = match g.get("lod")? {
        Value::String(s) => s.clone(),
        Value::Number(n) => n.to_string(),
        _ => return None,
    };
    let level = s.split('.').next()?.parse::<u8>().ok()?;
    Some((s, level))
}

struct Builder<'a> {
    path: &'a Path,
    file: String,
    header: Header,
    objects: Vec<CityObject>,
    polygons: Vec<Polygon>,
    stats: ReadStats,
    warnings: Vec<Warning>,
    taken: HashSet<String>,
    siblings: HashMap<(usize, Class), usize>,
}

/// A kept CityObject in visiting order, before its geometry is read.
struct Planned<'v> {
    id: &'v str,
    class: Class,
    parent: Option<usize>,
    root: usize,
    co: &'v Map<String, Value>,
}

impl<'a> Builder<'a> {
    fn new(path: &'a Path, header: Header, bytes: u64) -> Builder<'a> {
        Builder {
            path,
            file: path.display().to_string(),
            header,
            objects: Vec::new(),
            polygons: Vec::new(),
            stats: ReadStats {
                bytes,
                ..Default::default()
            },
            warnings: Vec::new(),
            taken: HashSet::new(),
            siblings: HashMap::new(),
        }
    }

    /// Counts something skipped (a CityObject or semantic surface type not used).
    fn skipped(&mut self, what: String) {
        *self.stats.unknown_elements.entry(what).or_default() += 1;
    }

    fn warn(&mut self, line: Option<u64>, id: Option<String>, message: String) {
        self.warnings.push(Warning {
            file: self.file.clone(),
            line: line.unwrap_or(0),
            id,
            message,
        });
    }

    fn finish(self) -> CityModel {
        CityModel {
            path: self.path.to_path_buf(),
            version: self.header.version,
            srs_name: self.header.srs,
            objects: self.objects,
            polygons: self.polygons,
            textures: Vec::new(),
            materials: Vec::new(),
            stats: self.stats,
            warnings: self.warnings,
        }
    }

    /// The vertices of a document or feature, decoded with the transform (f64).
    fn vertices(&self, at: At, v: Option<&Value>) -> Result<Vec<DVec3>, CityJsonError> {
        let Some(v) = v else {
            return Err(at.err(None, "no \"vertices\" array"));
        };
        let list = v
            .as_array()
            .ok_or_else(|| at.err(None, "\"vertices\" is not an array"))?;
        let mut out = Vec::with_capacity(list.len());
        for (i, p) in list.iter().enumerate() {
            let bad = |why: &str| at.err(None, format!("vertex {i} {p}: {why}"));
            let a = p
                .as_array()
                .filter(|a| a.len() == 3)
                .ok_or_else(|| bad("not an array of 3 numbers"))?;
            let mut q = [0.0f64; 3];
            match self.header.transform {
                Some((scale, translate)) => {
                    for k in 0..3 {
                        let n = a[k].as_i64().ok_or_else(|| {
                            bad("not integers, but the file has a \"transform\" (quantised vertices are integers)")
                        })?;
                        q[k] = n as f64 * scale[k] + translate[k];
                    }
                }
                None => {
                    for k in 0..3 {
                        q[k] = a[k]
                            .as_f64()
                            .filter(|f| f.is_finite())
                            .ok_or_else(|| bad("not 3 finite numbers"))?;
                    }
                }
            }
            out.push(DVec3::from_array(q));
        }
        Ok(out)
    }

    /// Adds the `CityObjects` (with their `vertices`) of a document or a CityJSONSeq line.
    fn add(&mut self, at: At, root: &Map<String, Value>) -> Result<(), CityJsonError> {
        let cos = match root.get("CityObjects") {
            None => return Err(at.err(None, "no \"CityObjects\" object")),
            Some(Value::Object(m)) => m,
            Some(_) => return Err(at.err(None, "\"CityObjects\" is not an object")),
        };
        let verts = self.vertices(at, root.get("vertices"))?;
        let plan = self.plan(at, cos)?;
        // LoD per root: 3, else 2, else 1, over the root and every kept descendant.
        let mut present: BTreeMap<usize, [bool; 4]> = BTreeMap::new();
        for p in &plan {
            let entry = present.entry(p.root).or_default();
            for g in geometries(at, p)? {
                if let Some((_, l)) = lod_of(g)
                    && (1..=3).contains(&l)
                    && g.get("type")
                        .and_then(Value::as_str)
                        .and_then(surface_depth)
                        .is_some()
                {
                    entry[l as usize] = true;
                }
            }
        }
        let mut pick: BTreeMap<usize, u8> = BTreeMap::new();
        for (&r, lods) in &present {
            match [3u8, 2, 1].into_iter().find(|&l| lods[l as usize]) {
                Some(l) => {
                    pick.insert(r, l);
                    if l != 3 {
                        self.warn(
                            at.line,
                            Some(plan[r].id.to_string()),
                            format!("no LoD3 geometry: using LoD{l}"),
                        );
                    }
                }
                None => self.warn(
                    at.line,
                    Some(plan[r].id.to_string()),
                    "no LoD1–3 surface geometry: nothing to triangulate".into(),
                ),
            }
        }
        let mut index: Vec<usize> = Vec::with_capacity(plan.len());
        for p in &plan {
            let lod = pick.get(&p.root).copied();
            let parent = p.parent.map(|q| index[q]);
            let idx = self.object(at, p, parent, lod);
            index.push(idx);
            self.geometry(at, p, idx, lod, &verts)?;
        }
        Ok(())
    }

    /// The kept CityObjects in visiting order (roots sorted by id, then down `children`),
    /// after checking types, `parents` and `children`.
    fn plan<'v>(
        &mut self,
        at: At,
        cos: &'v Map<String, Value>,
    ) -> Result<Vec<Planned<'v>>, CityJsonError> {
        let mut roots = Vec::new();
        for (id, co) in cos {
            let o = co
                .as_object()
                .ok_or_else(|| at.err(Some(id), "not a JSON object"))?;
            if o.get("type").and_then(Value::as_str).is_none() {
                return Err(at.err(Some(id), "no \"type\" string"));
            }
            for key in ["parents", "children"] {
                if let Some(list) = o.get(key) {
                    let list = list
                        .as_array()
                        .ok_or_else(|| at.err(Some(id), format!("\"{key}\" is not an array")))?;
                    for x in list {
                        let x = x.as_str().ok_or_else(|| {
                            at.err(Some(id), format!("\"{key}\" holds a non-string: {x}"))
                        })?;
                        if !cos.contains_key(x) {
                            return Err(at.err(
                                Some(id),
                                format!(
                                    "\"{key}\" names \"{x}\", which is not a CityObject of the file"
                                ),
                            ));
                        }
                    }
                }
            }
            let has_parent = o
                .get("parents")
                .and_then(Value::as_array)
                .is_some_and(|p| !p.is_empty());
            if !has_parent {
                roots.push(id.as_str());
            }
        }
        let mut plan: Vec<Planned> = Vec::new();
        let mut visited: HashSet<&str> = HashSet::new();
        // Depth first, children in the order listed (explicit stack, no recursion limit).
        for r in roots {
            let mut stack: Vec<(&str, Option<usize>, Option<usize>)> = vec![(r, None, None)];
            while let Some((id, parent, root)) = stack.pop() {
                if !visited.insert(id) {
                    self.warn(
                        at.line,
                        Some(id.to_string()),
                        "this CityObject is reached from two parents: it is kept under the first"
                            .into(),
                    );
                    continue;
                }
                let co = cos[id].as_object().expect("checked above");
                let t = co["type"].as_str().expect("checked above");
                let Some(class) = object_class(t) else {
                    self.skipped(format!("CityObject {t}"));
                    // Its subtree goes with it (marked reached, so that it is not taken for
                    // a cycle below).
                    let mut below = 0usize;
                    let mut sub: Vec<&str> = vec![id];
                    while let Some(x) = sub.pop() {
                        let kids = cos[x].get("children").and_then(Value::as_array);
                        for c in kids.into_iter().flatten().filter_map(Value::as_str) {
                            if visited.insert(c) {
                                below += 1;
                                sub.push(c);
                            }
                        }
                    }
                    if below > 0 {
                        self.warn(
                            at.line,
                            Some(id.to_string()),
                            format!(
                                "a CityObject of type \"{t}\", which gs4city does not read: \
                                 its {below} descendant(s) are skipped with it"
                            ),
                        );
                    }
                    continue;
                };
                let me = plan.len();
                plan.push(Planned {
                    id,
                    class,
                    parent,
                    root: root.unwrap_or(me),
                    co,
                });
                if let Some(children) = co.get("children").and_then(Value::as_array) {
                    for c in children.iter().rev() {
                        let c = c.as_str().expect("checked above");
                        stack.push((c, Some(me), Some(root.unwrap_or(me))));
                    }
                }
            }
        }
        if let Some(lost) = cos.keys().find(|k| !visited.contains(k.as_str())) {
            return Err(at.err(
                Some(lost),
                "its \"parents\" never lead to a root: the hierarchy has a cycle",
            ));
        }
        Ok(plan)
    }

    /// A unique object id: `id` itself, or `id~2`, `id~3`… with a warning.
    fn unique(&mut self, at: At, id: String, class: Class) -> String {
        if self.taken.insert(id.clone()) {
            return id;
        }
        let u = crate::citygml::unique_id(&id, |c| self.taken.contains(c));
        self.taken.insert(u.clone());
        self.warn(
            at.line,
            Some(id.clone()),
            format!(
                "the id \"{id}\" is used twice; this {} is called \"{u}\" in the hierarchy table",
                class.name()
            ),
        );
        u
    }

    fn object(&mut self, at: At, p: &Planned, parent: Option<usize>, lod: Option<u8>) -> usize {
        let object_id = self.unique(at, p.id.to_string(), p.class);
        let attrs =
            p.co.get("attributes")
                .and_then(Value::as_object)
                .map(|a| attributes(a.iter()))
                .unwrap_or_default();
        self.objects.push(CityObject {
            class: p.class,
            object_id,
            has_gml_id: true,
            parent,
            attributes: attrs,
            line: at.line.unwrap_or(0),
            offset: 0,
            lod_used: lod,
        });
        self.objects.len() - 1
    }

    /// Reads every geometry of a planned object; those of the chosen LoD make polygons
    /// (owned by the semantic surface objects they name), the others are counted unused.
    fn geometry(
        &mut self,
        at: At,
        p: &Planned,
        owner: usize,
        lod: Option<u8>,
        verts: &[DVec3],
    ) -> Result<(), CityJsonError> {
        let geoms = geometries(at, p)?;
        // The geometry used: of the chosen level, the highest LoD string, the first of it.
        let chosen = lod.and_then(|l| {
            geoms
                .iter()
                .enumerate()
                .filter(|(_, g)| {
                    g.get("type")
                        .and_then(Value::as_str)
                        .and_then(surface_depth)
                        .is_some()
                })
                .filter_map(|(i, g)| lod_of(g).filter(|(_, gl)| *gl == l).map(|(s, _)| (i, s)))
                .max_by(|a, b| a.1.cmp(&b.1).then(b.0.cmp(&a.0)))
                .map(|(i, _)| i)
        });
        for (gi, g) in geoms.iter().enumerate() {
            let what = |m: String| at.err(Some(p.id), format!("geometry {gi}: {m}"));
            let t = g
                .get("type")
                .and_then(Value::as_str)
                .ok_or_else(|| what("no \"type\" string".into()))?;
            let depth = match t {
                "MultiPoint" | "MultiLineString" => {
                    self.stats.curves_skipped += 1;
                    continue;
                }
                "GeometryInstance" => {
                    self.stats.implicit_skipped += 1;
                    continue;
                }
                _ => surface_depth(t).ok_or_else(|| what(format!("unknown type \"{t}\"")))?,
            };
            let (_, level) = lod_of(g).ok_or_else(|| {
                what(format!(
                    "\"lod\" must be a string such as \"2.2\", got {}",
                    g.get("lod")
                        .map(|v| v.to_string())
                        .unwrap_or("nothing".into())
                ))
            })?;
            let used = chosen == Some(gi);
            let sem_objects = match (used, g.get("semantics")) {
                (true, Some(s)) => {
                    let s = s
                        .as_object()
                        .ok_or_else(|| what("\"semantics\" is not an object".into()))?;
                    self.semantic_objects(at, p.id, gi, s, owner, lod)?
                }
                _ => Vec::new(),
            };
            let boundaries = g
                .get("boundaries")
                .ok_or_else(|| what("no \"boundaries\"".into()))?;
            let values = g.get("semantics").and_then(|s| s.get("values"));
            let n_sem = g
                .get("semantics")
                .and_then(|s| s.get("surfaces"))
                .and_then(Value::as_array)
                .map_or(0, Vec::len);
            let mut surfaces = Vec::new();
            collect_surfaces(boundaries, values, depth, String::new(), &mut surfaces)
                .map_err(what)?;
            for (surface, value, where_) in surfaces {
                let sem = match value {
                    None | Some(Value::Null) => None,
                    Some(v) => {
                        let i = v.as_u64().filter(|&i| (i as usize) < n_sem).ok_or_else(|| {
                            what(format!(
                                "surface {where_}: semantic value {v} is not an index of \"semantics\".\"surfaces\" ({n_sem} surfaces)"
                            ))
                        })?;
                        Some(i as usize)
                    }
                };
                let rings =
                    rings(surface, verts).map_err(|m| what(format!("surface {where_}: {m}")))?;
                let poly_owner = if used {
                    match sem {
                        Some(i) => sem_objects.get(i).copied().flatten(),
                        None => Some(owner),
                    }
                } else {
                    None
                };
                let mut rings = rings.into_iter();
                let exterior = rings.next().expect("rings() returns at least one");
                let interiors: Vec<Ring> = rings.collect();
                if let Some(dev) = non_planar(&exterior, &interiors) {
                    return Err(what(format!(
                        "surface {where_} is not planar: a point lies {dev:.3} from the surface's plane (more than {:.0} % of its extent and {PLANARITY_MIN})",
                        PLANARITY_TOLERANCE * 100.0
                    )));
                }
                self.stats.polygons += 1;
                self.stats.holes += interiors.len();
                if poly_owner.is_none() {
                    self.stats.polygons_unused += 1;
                }
                let ordinal = self.polygons.len();
                self.polygons.push(Polygon {
                    id: Some(format!("{}:geometry[{gi}]{where_}", p.id)),
                    exterior,
                    interiors,
                    owner: poly_owner,
                    lod: Some(level),
                    reversed: false,
                    line: at.line.unwrap_or(0),
                    ordinal,
                });
            }
        }
        Ok(())
    }

    /// The semantic surfaces of the used geometry as objects, parents first (a surface's
    /// `parent` before it); the index → object map (`None`: a type gs4city does not use).
    fn semantic_objects(
        &mut self,
        at: At,
        co_id: &str,
        gi: usize,
        sem: &Map<String, Value>,
        owner: usize,
        lod: Option<u8>,
    ) -> Result<Vec<Option<usize>>, CityJsonError> {
        let what = |m: String| at.err(Some(co_id), format!("geometry {gi}: semantics: {m}"));
        let Some(list) = sem.get("surfaces") else {
            return Ok(Vec::new());
        };
        let list = list
            .as_array()
            .ok_or_else(|| what("\"surfaces\" is not an array".into()))?;
        let n = list.len();
        let mut parent_of = Vec::with_capacity(n);
        for (i, s) in list.iter().enumerate() {
            let o = s
                .as_object()
                .ok_or_else(|| what(format!("surface {i} is not an object")))?;
            if o.get("type").and_then(Value::as_str).is_none() {
                return Err(what(format!("surface {i} has no \"type\" string")));
            }
            let parent = match o.get("parent") {
                None | Some(Value::Null) => None,
                Some(v) => Some(
                    v.as_u64()
                        .map(|x| x as usize)
                        .filter(|&x| x < n && x != i)
                        .ok_or_else(|| {
                            what(format!("surface {i}: \"parent\" {v} is not another surface's index (0..{n})"))
                        })?,
                ),
            };
            if let Some(c) = o.get("children") {
                let ok = c.as_array().is_some_and(|c| {
                    c.iter()
                        .all(|x| x.as_u64().is_some_and(|x| (x as usize) < n))
                });
                if !ok {
                    return Err(what(format!(
                        "surface {i}: \"children\" {c} are not surface indices (0..{n})"
                    )));
                }
            }
            parent_of.push(parent);
        }
        // Visit each surface after its parent (a parent chain that loops is an error).
        let mut out: Vec<Option<usize>> = vec![None; n];
        let mut done = vec![false; n];
        for start in 0..n {
            let mut chain = vec![start];
            while let Some(p) = parent_of[*chain.last().expect("non-empty")] {
                if done[p] {
                    break;
                }
                if chain.contains(&p) {
                    return Err(what(format!("surface {start}: its \"parent\" chain loops")));
                }
                chain.push(p);
            }
            for &i in chain.iter().rev() {
                if done[i] {
                    continue;
                }
                done[i] = true;
                let o = list[i].as_object().expect("checked above");
                let t = o["type"].as_str().expect("checked above");
                let Some(class) = surface_class(t) else {
                    self.skipped(format!("semantic surface {t}"));
                    continue;
                };
                let parent = parent_of[i].and_then(|p| out[p]).unwrap_or(owner);
                let k = self.siblings.entry((parent, class)).or_default();
                *k += 1;
                let k = *k;
                let (id, has_id) = match o.get("id").and_then(Value::as_str) {
                    Some(id) => (id.to_string(), true),
                    None => (
                        format!("{}/{}[{k}]", self.objects[parent].object_id, class.name()),
                        false,
                    ),
                };
                let object_id = self.unique(at, id, class);
                let attrs =
                    attributes(o.iter().filter(|(k, _)| {
                        !matches!(k.as_str(), "type" | "parent" | "children" | "id")
                    }));
                self.objects.push(CityObject {
                    class,
                    object_id,
                    has_gml_id: has_id,
                    parent: Some(parent),
                    attributes: attrs,
                    line: at.line.unwrap_or(0),
                    offset: 0,
                    lod_used: lod,
                });
                out[i] = Some(self.objects.len() - 1);
            }
        }
        Ok(out)
    }
}

fn geometries<'v>(at: At, p: &Planned<'v>) -> Result<Vec<&'v Map<String, Value>>, CityJsonError> {
    let Some(g) = p.co.get("geometry") else {
        return Ok(Vec::new());
    };
    let list = g
        .as_array()
        .ok_or_else(|| at.err(Some(p.id), "\"geometry\" is not an array"))?;
    list.iter()
        .enumerate()
        .map(|(i, g)| {
            g.as_object()
                .ok_or_else(|| at.err(Some(p.id), format!("geometry {i} is not an object")))
        })
        .collect()
}

type Surface<'v> = (&'v Value, Option<&'v Value>, String);

/// The surfaces of a boundary array `depth` levels above the surface lists, each with its
/// semantic value and its index path (`[shell][surface]`).
fn collect_surfaces<'v>(
    b: &'v Value,
    values: Option<&'v Value>,
    depth: usize,
    path: String,
    out: &mut Vec<Surface<'v>>,
) -> Result<(), String> {
    let list = b
        .as_array()
        .ok_or_else(|| format!("boundaries{path} is not an array"))?;
    let vals = match values {
        None | Some(Value::Null) => None,
        Some(Value::Array(v)) if v.len() == list.len() => Some(v),
        Some(v) => {
            return Err(format!(
                "semantics values{path} {} do not match the {} boundaries",
                shorten(v),
                list.len()
            ));
        }
    };
    for (i, x) in list.iter().enumerate() {
        let p = format!("{path}[{i}]");
        let v = vals.map(|v| &v[i]);
        if depth == 0 {
            out.push((x, v, p));
        } else {
            collect_surfaces(x, v, depth - 1, p, out)?;
        }
    }
    Ok(())
}

fn shorten(v: &Value) -> String {
    let s = v.to_string();
    if s.len() > 60 {
        let cut = (0..=60).rev().find(|&i| s.is_char_boundary(i)).unwrap_or(0);
        format!("{}…", &s[..cut])
    } else {
        s
    }
}

/// A surface's rings (exterior first) as points; a closing repeat of the first index dropped.
fn rings(surface: &Value, verts: &[DVec3]) -> Result<Vec<Ring>, String> {
    let list = surface
        .as_array()
        .ok_or_else(|| format!("not an array of rings: {}", shorten(surface)))?;
    if list.is_empty() {
        return Err("empty surface: it has no ring".into());
    }
    let mut out = Vec::with_capacity(list.len());
    for (r, ring) in list.iter().enumerate() {
        let idx = ring
            .as_array()
            .ok_or_else(|| format!("ring {r} is not an array of vertex indices"))?;
        let mut ids: Vec<usize> = Vec::with_capacity(idx.len());
        for v in idx {
            let i = v
                .as_u64()
                .ok_or_else(|| format!("ring {r}: {v} is not a vertex index"))?
                as usize;
            if i >= verts.len() {
                return Err(format!(
                    "ring {r}: vertex index {i} does not exist (the vertex list has {} vertices)",
                    verts.len()
                ));
            }
            ids.push(i);
        }
        if ids.len() > 1 && ids.first() == ids.last() {
            ids.pop();
        }
        // A ring of 1 or 2 vertices is degenerate, not malformed: kept, so that the
        // triangulator skips it with its reason (as a zero-area CityGML ring).
        if ids.is_empty() {
            return Err(format!("ring {r} is empty: it has no vertex"));
        }
        out.push(Ring {
            id: None,
            points: ids.iter().map(|&i| verts[i]).collect(),
        });
    }
    Ok(out)
}

/// The largest distance of a ring point from the exterior's plane (Newell normal through the
/// exterior's centroid), when it exceeds [`PLANARITY_TOLERANCE`] of the bounding-box
/// diagonal and [`PLANARITY_MIN`]. Degenerate (zero-area) rings are left to the triangulator.
fn non_planar(exterior: &Ring, interiors: &[Ring]) -> Option<f64> {
    let pts = &exterior.points;
    if pts.len() < 3 {
        return None;
    }
    let o = pts[0];
    let mut n = DVec3::ZERO;
    let mut c = DVec3::ZERO;
    for (i, a) in pts.iter().enumerate() {
        let a = *a - o;
        let b = pts[(i + 1) % pts.len()] - o;
        n += a.cross(b);
        c += a;
    }
    c /= pts.len() as f64;
    let len = n.length();
    let all = || {
        pts.iter()
            .chain(interiors.iter().flat_map(|r| r.points.iter()))
    };
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for p in all() {
        lo = lo.min(*p - o);
        hi = hi.max(*p - o);
    }
    let diag = (hi - lo).length();
    if len <= 1e-12 * diag * diag || len.is_nan() {
        return None;
    }
    let n = n / len;
    let dev = all()
        .map(|p| (*p - o - c).dot(n).abs())
        .fold(0.0f64, f64::max);
    (dev > PLANARITY_TOLERANCE * diag && dev > PLANARITY_MIN).then_some(dev)
}
