//! One tile's glTF 2.0 binary (docs/export.md): the splats as a `POINTS` primitive with
//! `KHR_gaussian_splatting` — uncompressed accessors, or one SPZ blob
//! (`KHR_gaussian_splatting_compression_spz_2`) with the attributes it maps to declared by
//! accessors without buffer views — and their semantics as `EXT_mesh_features` feature ids
//! indexing `EXT_structural_metadata` property tables.
use serde_json::{Value, json};

use super::TilesError;
use super::lod::Tags;
use crate::semantics::Entity;
use crate::splat::{Gaussians, transform};
use crate::{classes, glb, spz};

/// Writes a string column of a property table: values and `UINT32` offsets.
fn string_property(b: &mut glb::Builder, values: &[String]) -> Value {
    let mut bytes = Vec::new();
    let mut offsets: Vec<u8> = Vec::with_capacity(4 * (values.len() + 1));
    offsets.extend_from_slice(&0u32.to_le_bytes());
    for v in values {
        bytes.extend_from_slice(v.as_bytes());
        offsets.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
    }
    let values = b.view(&bytes, None);
    let offsets = b.view(&offsets, None);
    json!({"values": values, "stringOffsets": offsets, "stringOffsetType": "UINT32"})
}

/// Writes an `INT32` column of a property table.
fn int_property(b: &mut glb::Builder, values: &[i32]) -> Value {
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    json!({"values": b.view(&bytes, None)})
}

/// The metadata schema every tile carries (module docs).
fn schema() -> Value {
    let entity = |what: &str| {
        json!({
            "name": what,
            "description": format!("CityGML {what} entities of the run's semantics.json"),
            "properties": {
                "gml_id": {"type": "STRING", "description": "gml:id (or the stable derived id)"},
                "citygml_class": {"type": "STRING"},
                "entity": {"type": "SCALAR", "componentType": "INT32", "description": "row of semantics.json"},
                "parent_gml_id": {"type": "STRING", "description": "the parent entity's gml:id (empty for a root)"},
                "building_gml_id": {"type": "STRING"},
                "attributes": {"type": "STRING", "description": "the CityGML attributes as a JSON object"}
            }
        })
    };
    json!({
        "id": "gs4city",
        "name": "gs4city semantic Gaussians",
        "classes": {
            "building": entity("building"),
            "surface": entity("surface"),
            "part": entity("part"),
            "category": {
                "name": "category",
                "description": "evaluation classes (docs/design.md)",
                "properties": {
                    "class_id": {"type": "SCALAR", "componentType": "INT32"},
                    "name": {"type": "STRING"}
                }
            }
        }
    })
}

/// The property table of `rows` (entity ids) at one level.
fn entity_table(b: &mut glb::Builder, class: &str, rows: &[i32], ents: &[Entity]) -> Value {
    let e = |i: i32| &ents[i as usize];
    let gml: Vec<String> = rows.iter().map(|&i| e(i).object_id.clone()).collect();
    let cls: Vec<String> = rows
        .iter()
        .map(|&i| e(i).class.name().to_string())
        .collect();
    let ids: Vec<i32> = rows.to_vec();
    let parent: Vec<String> = rows
        .iter()
        .map(|&i| {
            e(i).parent
                .and_then(|p| ents.get(p as usize))
                .map(|p| p.object_id.clone())
                .unwrap_or_default()
        })
        .collect();
    let building: Vec<String> = rows
        .iter()
        .map(|&i| {
            ents.get(e(i).building as usize)
                .map(|p| p.object_id.clone())
                .unwrap_or_default()
        })
        .collect();
    let attrs: Vec<String> = rows
        .iter()
        .map(|&i| serde_json::to_string(&e(i).attributes).expect("JSON values serialise"))
        .collect();
    json!({
        "class": class,
        "count": rows.len(),
        "properties": {
            "gml_id": string_property(b, &gml),
            "citygml_class": string_property(b, &cls),
            "entity": int_property(b, &ids),
            "parent_gml_id": string_property(b, &parent),
            "building_gml_id": string_property(b, &building),
            "attributes": string_property(b, &attrs),
        }
    })
}

/// The splats as uncompressed `KHR_gaussian_splatting` attributes into `attrs`: `POSITION`,
/// `:ROTATION` (unit quaternion x, y, z, w), `:SCALE` (linear: the exponential of the stored
/// log scales), `:OPACITY` (after the sigmoid, in [0, 1]), `:SH_DEGREE_0_COEF_0` and every
/// coefficient of each higher degree the splats have, and `COLOR_0` (the fallback colour).
fn plain_splats(b: &mut glb::Builder, g: &Gaussians, attrs: &mut serde_json::Map<String, Value>) {
    let n = g.len();
    let flat3 = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    attrs.insert(
        "POSITION".into(),
        json!(b.floats(&flat3(&g.positions), 3, true)),
    );
    // COLOR_0 is linear (glTF §3.7.2.1); the splats' diffuse colour is sRGB-encoded.
    let c0 = transform::SH_C0 as f32;
    let linear = |c: f32| {
        if c <= 0.040_45 {
            c / 12.92
        } else {
            ((c + 0.055) / 1.055).powf(2.4)
        }
    };
    let color: Vec<f32> = (0..n)
        .flat_map(|i| {
            let [r, gg, bb] = g.f_dc[i].map(|f| linear((c0 * f + 0.5).clamp(0.0, 1.0)));
            [r, gg, bb, g.activated_opacity(i).clamp(0.0, 1.0)]
        })
        .collect();
    attrs.insert("COLOR_0".into(), json!(b.floats(&color, 4, false)));
    let rot: Vec<f32> = (0..n)
        .flat_map(|i| {
            let [w, x, y, z] = g.normalized_rotation(i).unwrap_or([1.0, 0.0, 0.0, 0.0]);
            [x, y, z, w]
        })
        .collect();
    attrs.insert(
        "KHR_gaussian_splatting:ROTATION".into(),
        json!(b.floats(&rot, 4, false)),
    );
    // Linear scales (the extension's text: "Scale values are linear and MUST NOT be
    // negative"); the Gaussians hold them as logarithms.
    let scale: Vec<f32> = g.scale.iter().flatten().map(|v| v.exp()).collect();
    attrs.insert(
        "KHR_gaussian_splatting:SCALE".into(),
        json!(b.floats(&scale, 3, false)),
    );
    let opacity: Vec<f32> = (0..n)
        .map(|i| g.activated_opacity(i).clamp(0.0, 1.0))
        .collect();
    attrs.insert(
        "KHR_gaussian_splatting:OPACITY".into(),
        json!(b.floats(&opacity, 1, false)),
    );
    attrs.insert(
        "KHR_gaussian_splatting:SH_DEGREE_0_COEF_0".into(),
        json!(b.floats(&flat3(&g.f_dc), 3, false)),
    );
    // INRIA's f_rest: per Gaussian the channel-major coefficients (k per channel).
    let rest = g.rest_per_gaussian();
    let k = rest / 3;
    for l in 1..=usize::from(g.sh_degree) {
        for m in 0..2 * l + 1 {
            let j = l * l - 1 + m;
            let v: Vec<f32> = (0..n)
                .flat_map(|i| {
                    let c = &g.f_rest[i * rest..(i + 1) * rest];
                    [c[j], c[k + j], c[2 * k + j]]
                })
                .collect();
            attrs.insert(
                format!("KHR_gaussian_splatting:SH_DEGREE_{l}_COEF_{m}"),
                json!(b.floats(&v, 3, false)),
            );
        }
    }
}

/// The splats SPZ-compressed (`KHR_gaussian_splatting_compression_spz_2`): the SPZ bytes as
/// one buffer view (returned) and the attributes it maps to declared as accessors without
/// buffer views (`POSITION` with bounds, `COLOR_0` as normalised bytes (the DC colour and the
/// opacity), `:SCALE`, `:ROTATION`, `:SH_DEGREE_ℓ_COEF_n` for ℓ ≥ 1) into `attrs`.
fn spz_splats(
    b: &mut glb::Builder,
    g: &Gaussians,
    attrs: &mut serde_json::Map<String, Value>,
) -> Result<usize, TilesError> {
    let n = g.len();
    let alphas: Vec<f32> = (0..n)
        .map(|i| g.activated_opacity(i).clamp(0.0, 1.0))
        .collect();
    let rotations: Vec<[f32; 4]> = (0..n)
        .map(|i| {
            let [w, x, y, z] = g.normalized_rotation(i).unwrap_or([1.0, 0.0, 0.0, 0.0]);
            [x, y, z, w]
        })
        .collect();
    let dim = spz::sh_dim(g.sh_degree);
    let rest = g.rest_per_gaussian();
    let k = rest / 3;
    let mut sh = Vec::with_capacity(n * dim * 3);
    for i in 0..n {
        let c = &g.f_rest[i * rest..(i + 1) * rest];
        for j in 0..dim {
            sh.extend([c[j], c[k + j], c[2 * k + j]]);
        }
    }
    let bytes = spz::write(&spz::Cloud {
        positions: &g.positions,
        alphas: &alphas,
        colors: &g.f_dc,
        scales: &g.scale,
        rotations: &rotations,
        sh_degree: g.sh_degree,
        sh: &sh,
    })?;
    let view = b.view(&bytes, None);
    let (mut lo, mut hi) = (vec![f32::INFINITY; 3], vec![f32::NEG_INFINITY; 3]);
    for p in &g.positions {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let bounds = (n > 0).then_some((lo, hi));
    attrs.insert(
        "POSITION".into(),
        json!(b.declared(glb::FLOAT, 3, n, false, bounds)),
    );
    attrs.insert(
        "COLOR_0".into(),
        json!(b.declared(glb::UNSIGNED_BYTE, 4, n, true, None)),
    );
    attrs.insert(
        "KHR_gaussian_splatting:SCALE".into(),
        json!(b.declared(glb::FLOAT, 3, n, false, None)),
    );
    attrs.insert(
        "KHR_gaussian_splatting:ROTATION".into(),
        json!(b.declared(glb::FLOAT, 4, n, false, None)),
    );
    for l in 1..=usize::from(g.sh_degree) {
        for m in 0..2 * l + 1 {
            attrs.insert(
                format!("KHR_gaussian_splatting:SH_DEGREE_{l}_COEF_{m}"),
                json!(b.declared(glb::FLOAT, 3, n, false, None)),
            );
        }
    }
    Ok(view)
}

/// Adds one `EXT_mesh_features` feature id set: the attribute `_FEATURE_ID_<slot>` holding
/// `fid` and its entry `(featureCount, propertyTable, nullFeatureId, label)` in `feature_ids`.
fn add_feature_ids(
    b: &mut glb::Builder,
    attrs: &mut serde_json::Map<String, serde_json::Value>,
    feature_ids: &mut Vec<serde_json::Value>,
    fid: &[f32],
    (count, table, null_id, label): (usize, usize, usize, &str),
) {
    let slot = feature_ids.len();
    attrs.insert(
        format!("_FEATURE_ID_{slot}"),
        json!(b.floats(fid, 1, false)),
    );
    feature_ids.push(json!({
        "featureCount": count,
        "attribute": slot,
        "propertyTable": table,
        "nullFeatureId": null_id,
        "label": label,
    }));
}

/// One tile's glTF binary: `g` already in the tile's frame (Y up), `tags` the building,
/// surface, part and class of each splat, `entities` the rows the tags index.
pub(super) fn tile_glb(
    g: &Gaussians,
    tags: &[Tags],
    entities: &[Entity],
    spz: bool,
) -> Result<Vec<u8>, TilesError> {
    let mut b = glb::Builder::new();
    let mut attrs = serde_json::Map::new();
    let spz_view = if spz {
        Some(spz_splats(&mut b, g, &mut attrs)?)
    } else {
        plain_splats(&mut b, g, &mut attrs);
        None
    };

    // Semantics: one feature id set and one property table per level present.
    let mut feature_ids = Vec::new();
    let mut tables = Vec::new();
    for (level, name) in ["building", "surface", "part"].into_iter().enumerate() {
        let ids: Vec<i32> = tags.iter().map(|t| t[level]).collect();
        let mut rows: Vec<i32> = ids.iter().copied().filter(|&e| e >= 0).collect();
        rows.sort_unstable();
        rows.dedup();
        if rows.is_empty() {
            continue;
        }
        let none_row = rows.len();
        let fid: Vec<f32> = ids
            .iter()
            .map(|&e| rows.binary_search(&e).unwrap_or(none_row) as f32)
            .collect();
        let table = tables.len();
        let set = (rows.len(), table, none_row, name);
        add_feature_ids(&mut b, &mut attrs, &mut feature_ids, &fid, set);
        tables.push(entity_table(&mut b, name, &rows, entities));
    }
    let classes: Vec<i32> = tags.iter().map(|t| t[3]).collect();
    let n_classes = classes::NAMES.len();
    let present: std::collections::BTreeSet<i32> =
        classes.iter().copied().filter(|&c| c >= 0).collect();
    if !present.is_empty() {
        let fid: Vec<f32> = classes
            .iter()
            .map(|&c| if c >= 0 { c as f32 } else { n_classes as f32 })
            .collect();
        let set = (present.len(), tables.len(), n_classes, "category");
        add_feature_ids(&mut b, &mut attrs, &mut feature_ids, &fid, set);
        let ids: Vec<i32> = (0..n_classes as i32).collect();
        let names: Vec<String> = ids.iter().map(|&c| classes::name(c).to_string()).collect();
        tables.push(json!({
            "class": "category",
            "count": n_classes,
            "properties": {
                "class_id": int_property(&mut b, &ids),
                "name": string_property(&mut b, &names),
            }
        }));
    }
    let mut prim_ext = json!({
        "KHR_gaussian_splatting": {
            "kernel": "ellipse",
            "colorSpace": "srgb_rec709_display",
            "projection": "perspective",
            "sortingMethod": "cameraDistance"
        }
    });
    let mut used = vec!["KHR_gaussian_splatting"];
    let mut required = Vec::new();
    if let Some(view) = spz_view {
        prim_ext["KHR_gaussian_splatting"]["extensions"] =
            json!({"KHR_gaussian_splatting_compression_spz_2": {"bufferView": view}});
        used.push("KHR_gaussian_splatting_compression_spz_2");
        required.extend([
            "KHR_gaussian_splatting",
            "KHR_gaussian_splatting_compression_spz_2",
        ]);
    }
    let mut root_ext = serde_json::Map::new();
    if !feature_ids.is_empty() {
        prim_ext["EXT_mesh_features"] = json!({ "featureIds": feature_ids });
        root_ext.insert(
            "EXT_structural_metadata".into(),
            json!({"schema": schema(), "propertyTables": tables}),
        );
        used.extend(["EXT_mesh_features", "EXT_structural_metadata"]);
    }
    let mut doc = json!({
        "asset": {"version": "2.0", "generator": format!("gs4city {}", env!("CARGO_PKG_VERSION"))},
        "extensionsUsed": used,
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attrs, "mode": 0, "extensions": prim_ext}]}],
    });
    if !required.is_empty() {
        doc["extensionsRequired"] = json!(required);
    }
    if !root_ext.is_empty() {
        doc["extensions"] = Value::Object(root_ext);
    }
    Ok(b.finish(doc)?)
}
