//! The CityJSON 2.0 writer: a [`CityModel`] (of either encoding) → one CityJSON document that
//! [`super::read`] reads back to the same objects, hierarchy, attributes and used polygons.
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use glam::DVec3;
use serde_json::{Map, Value, json};

use crate::citygml::{CityModel, Class, Level};
use crate::fsutil::{self, FsError};

/// Quantisation step of the written vertices (file units; 1 mm in a projected CRS).
pub const WRITE_SCALE: f64 = 0.001;

/// The CityJSON name of a class: CityGML 3.0 WindowSurface/DoorSurface are Window/Door.
fn cityjson_type(c: Class) -> &'static str {
    match c {
        Class::WindowSurface => "Window",
        Class::DoorSurface => "Door",
        c => c.name(),
    }
}

/// `name` + `name.uom` → `{"value": v, "uom": u}` (the reader's inverse).
fn attributes_out(a: &BTreeMap<String, Value>) -> Map<String, Value> {
    let mut out = Map::new();
    for (k, v) in a {
        if let Some(base) = k.strip_suffix(".uom")
            && a.contains_key(base)
        {
            continue;
        }
        match a.get(&format!("{k}.uom")) {
            Some(u) => out.insert(k.clone(), json!({"value": v, "uom": u})),
            None => out.insert(k.clone(), v.clone()),
        };
    }
    out
}

/// An OGC CRS URL for `metadata.referenceSystem` from a CityGML srsName naming an EPSG code.
fn crs_url(srs: &str) -> Option<String> {
    if srs.starts_with("http://www.opengis.net/def/crs/")
        || srs.starts_with("https://www.opengis.net/def/crs/")
    {
        return Some(srs.to_string());
    }
    let i = srs.to_ascii_uppercase().find("EPSG")?;
    let code: String = srs[i + 4..]
        .trim_start_matches(|c: char| !c.is_ascii_digit())
        .chars()
        .take_while(char::is_ascii_digit)
        .collect();
    (!code.is_empty()).then(|| format!("https://www.opengis.net/def/crs/EPSG/0/{code}"))
}

/// The document: building objects (features) keyed by object id with `parents`/`children`;
/// per feature one MultiSurface of its LoD holding its used polygons, the surface and opening
/// objects below it as semantic surfaces (with their `id` and attributes); vertices quantised
/// by [`WRITE_SCALE`] from the minimum corner.
pub fn to_json(model: &CityModel) -> Value {
    let objs = &model.objects;
    // The feature each object belongs to (itself for a feature).
    let mut feature = vec![0usize; objs.len()];
    for (i, o) in objs.iter().enumerate() {
        feature[i] = match (o.class.level(), o.parent) {
            (Level::Feature, _) | (_, None) => i,
            (_, Some(p)) => feature[p],
        };
    }
    let used: Vec<_> = model.used_polygons().collect();
    let mut lo = DVec3::splat(f64::INFINITY);
    for p in &used {
        for q in p.exterior.points.iter() {
            lo = lo.min(*q);
        }
    }
    let translate = if lo.is_finite() {
        lo.floor()
    } else {
        DVec3::ZERO
    };
    let mut vertices: Vec<[i64; 3]> = Vec::new();
    let mut index: HashMap<[i64; 3], usize> = HashMap::new();
    let mut vid = |q: DVec3| -> usize {
        let k = ((q - translate) / WRITE_SCALE).round();
        let k = [k.x as i64, k.y as i64, k.z as i64];
        *index.entry(k).or_insert_with(|| {
            vertices.push(k);
            vertices.len() - 1
        })
    };
    let mut by_feature: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (pi, p) in used.iter().enumerate() {
        if let Some(o) = p.owner {
            by_feature.entry(feature[o]).or_default().push(pi);
        }
    }
    let mut city_objects = Map::new();
    for (i, o) in objs.iter().enumerate() {
        if feature[i] != i {
            continue;
        }
        let mut co = Map::new();
        co.insert("type".into(), cityjson_type(o.class).into());
        if !o.attributes.is_empty() {
            co.insert(
                "attributes".into(),
                Value::Object(attributes_out(&o.attributes)),
            );
        }
        if let Some(p) = o.parent {
            co.insert("parents".into(), json!([objs[feature[p]].object_id]));
        }
        let children: Vec<&str> = objs
            .iter()
            .enumerate()
            .filter(|(j, c)| feature[*j] == *j && c.parent.is_some_and(|p| feature[p] == i))
            .map(|(_, c)| c.object_id.as_str())
            .collect();
        if !children.is_empty() {
            co.insert("children".into(), json!(children));
        }
        let mut geometry = Vec::new();
        if let Some(lod) = o.lod_used {
            // Semantic surfaces: the non-feature objects of this feature, in object order.
            let members: Vec<usize> = (0..objs.len())
                .filter(|&j| j != i && feature[j] == i)
                .collect();
            let pos: HashMap<usize, usize> =
                members.iter().enumerate().map(|(k, &j)| (j, k)).collect();
            let surfaces: Vec<Value> = members
                .iter()
                .map(|&j| {
                    let s = &objs[j];
                    let mut m = attributes_out(&s.attributes);
                    m.insert("type".into(), cityjson_type(s.class).into());
                    m.insert("id".into(), s.object_id.clone().into());
                    if let Some(p) = s.parent.and_then(|p| pos.get(&p)) {
                        m.insert("parent".into(), (*p).into());
                    }
                    let kids: Vec<usize> = members
                        .iter()
                        .filter(|&&c| objs[c].parent == Some(j))
                        .map(|c| pos[c])
                        .collect();
                    if !kids.is_empty() {
                        m.insert("children".into(), json!(kids));
                    }
                    Value::Object(m)
                })
                .collect();
            let mut boundaries = Vec::new();
            let mut values = Vec::new();
            for &pi in by_feature.get(&i).map(Vec::as_slice).unwrap_or(&[]) {
                let p = used[pi];
                let ring = |r: &[DVec3], vid: &mut dyn FnMut(DVec3) -> usize| -> Vec<usize> {
                    let mut ids: Vec<usize> = r.iter().map(|q| vid(*q)).collect();
                    if p.reversed {
                        ids.reverse();
                    }
                    ids
                };
                let mut rings = vec![ring(&p.exterior.points, &mut vid)];
                for h in &p.interiors {
                    rings.push(ring(&h.points, &mut vid));
                }
                boundaries.push(json!(rings));
                let owner = p.owner.expect("used polygons have owners");
                values.push(pos.get(&owner).map_or(Value::Null, |k| (*k).into()));
            }
            if !boundaries.is_empty() || !surfaces.is_empty() {
                let mut g = json!({"type": "MultiSurface", "lod": lod.to_string(), "boundaries": boundaries});
                if !surfaces.is_empty() {
                    g["semantics"] = json!({"surfaces": surfaces, "values": values});
                }
                geometry.push(g);
            }
        }
        co.insert("geometry".into(), Value::Array(geometry));
        city_objects.insert(o.object_id.clone(), Value::Object(co));
    }
    let mut metadata = Map::new();
    if let Some(url) = model.srs_name.as_deref().and_then(crs_url) {
        metadata.insert("referenceSystem".into(), url.into());
    }
    json!({
        "type": "CityJSON",
        "version": "2.0",
        "transform": {"scale": [WRITE_SCALE, WRITE_SCALE, WRITE_SCALE], "translate": translate.to_array()},
        "metadata": metadata,
        "CityObjects": city_objects,
        "vertices": vertices,
    })
}

/// Writes [`to_json`] to `path` (temp file + rename).
pub fn write(path: &Path, model: &CityModel) -> Result<(), FsError> {
    fsutil::write_json(path, &to_json(model))
}
