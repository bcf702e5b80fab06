//! `gs4city export --format 3dtiles`: a selection of a finished run as a georeferenced
//! 3D Tiles 1.1 tileset (docs/export.md).
//!
//! - **Content**: one glTF 2.0 binary per leaf tile, the Gaussians as a `POINTS` primitive with
//!   `KHR_gaussian_splatting` (`POSITION`, `KHR_gaussian_splatting:ROTATION` (x, y, z, w),
//!   `:SCALE` (log), `:OPACITY` (after the sigmoid), `:SH_DEGREE_ℓ_COEF_n` (the 3DGS SH,
//!   turned with the Gaussians) and `COLOR_0` (the diffuse colour, made linear as glTF's
//!   vertex colours are, and the opacity: what a renderer without splats shows).
//! - **SPZ** (`spz`): the splats as one SPZ v2 blob ([`crate::spz`]) per tile,
//!   `KHR_gaussian_splatting_compression_spz_2`, the attributes declared by accessors without
//!   buffer views, the tileset declaring the extensions as `3DTILES_content_gltf` requires.
//! - **Semantics**: `EXT_mesh_features` feature ids per splat — `_FEATURE_ID_0` building,
//!   `_FEATURE_ID_1` surface, `_FEATURE_ID_2` part (rows of the tile's property tables of the
//!   same names, absent levels `nullFeatureId`), `_FEATURE_ID_3` the evaluation class (rows of
//!   the `category` table, one per class id) — and `EXT_structural_metadata` property tables
//!   holding each entity's gml:id, CityGML class, entity id, parent and building gml:ids and
//!   its CityGML attributes (JSON text).
//! - **Georeference**: a Gaussian's scene position goes back to the city model's CRS through
//!   the run's alignment (`Alignment::unapply`, f64), then through PROJ to ECEF
//!   ([`crate::crs`]); a tile's content holds f32 offsets in the east-north-up frame at the
//!   tile's centre (glTF's Y up: `(east, up, −north)`), and the tile carries the f64 transform
//!   of that frame (the root: ENU → ECEF; a child: relative to its parent). Orientations, scales
//!   and SH bands are turned by the frame change at the tile's centre (the CRS → ENU Jacobian,
//!   by central differences through PROJ, split into its rotation and its scale).
//! - **Hierarchy**: a quadtree over the CRS ground plane; a node holding more than
//!   `max_splats` Gaussians is split in four (empty quadrants dropped); only leaves hold
//!   content (refine `ADD`); a node's geometric error is its box diagonal, a leaf's 0; each
//!   bounding volume is a `box` in the node's own ENU frame around its Gaussians, padded by
//!   three standard deviations of the largest Gaussian.
//!
//! The tileset is written into a temporary folder beside `out` and renamed to `out` only when
//! complete.
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DMat4, DVec3};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use super::QueryError;
use super::export::{ColorBy, subset};
use crate::alignment::Alignment;
use crate::crs::{self, Georef};
use crate::glb;
use crate::selection::SemanticRun;
use crate::semantics::Entity;
use crate::splat::transform::{self, Motion};
use crate::splat::{self, Gaussians};
use crate::{classes, fsutil, spz};

/// The default largest number of Gaussians in one tile.
pub const MAX_SPLATS: usize = 200_000;
/// The deepest quadtree level (a node there is a leaf whatever its count).
pub const MAX_DEPTH: u32 = 16;

/// Options of the export.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TilesOptions {
    /// The splats' colours (`class`/`building`: the DC term and `COLOR_0` show the palette).
    pub color_by: ColorBy,
    /// A node with more Gaussians than this is split.
    pub max_splats: usize,
    /// The splats SPZ-compressed (`KHR_gaussian_splatting_compression_spz_2`).
    #[serde(default)]
    pub spz: bool,
}

impl Default for TilesOptions {
    fn default() -> Self {
        TilesOptions {
            color_by: ColorBy::Rgb,
            max_splats: MAX_SPLATS,
            spz: false,
        }
    }
}

/// Where the root tile lands.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RootPlace {
    /// The root's centre in the CRS (easting, northing, height).
    pub crs: [f64; 3],
    /// Its longitude and latitude (degrees, WGS 84) and ellipsoidal height (metres).
    pub lon: f64,
    pub lat: f64,
    pub height: f64,
    /// Its ECEF position (EPSG:4978, metres): the translation of the root transform.
    pub ecef: [f64; 3],
}

/// Timings of the export (seconds).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TilesTiming {
    pub read_s: f64,
    pub georef_s: f64,
    pub write_s: f64,
    pub total_s: f64,
}

/// `T/summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TilesSummary {
    pub format: String,
    /// The selection, canonical text.
    pub query: String,
    /// The CRS the coordinates were read in (as PROJ accepted it).
    pub crs: String,
    /// Exported Gaussians (the selection's valid Gaussians).
    pub splats: usize,
    /// Selected Gaussians left out because their values are invalid (NaN, zero quaternion…).
    pub invalid: usize,
    pub tiles: usize,
    pub leaves: usize,
    pub depth: u32,
    pub sh_degree: u8,
    pub root: RootPlace,
    /// Bytes of `tileset.json` and every tile.
    pub bytes: u64,
    pub options: TilesOptions,
    pub timing: TilesTiming,
}

/// One quadtree node.
struct Node {
    /// `r`, then one digit 0–3 per level (the content file's name).
    path: String,
    depth: u32,
    /// The Gaussians (indices into the exported set), in input order.
    members: Vec<u32>,
    children: Vec<usize>,
    /// The ENU frame at the node's centre: columns east, north, up; and the centre (ECEF).
    frame: DMat3,
    centre: DVec3,
    /// The centre in the CRS.
    centre_crs: DVec3,
}

/// The quadtree over `xy` (CRS ground coordinates) of the members.
fn quadtree(xy: &[[f64; 2]], max_splats: usize) -> Vec<Node> {
    let n = xy.len();
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for p in xy {
        for k in 0..2 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let size = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1e-3);
    let mut nodes = vec![Node {
        path: "r".into(),
        depth: 0,
        members: (0..n as u32).collect(),
        children: Vec::new(),
        frame: DMat3::IDENTITY,
        centre: DVec3::ZERO,
        centre_crs: DVec3::ZERO,
    }];
    // (node, square origin, square size)
    let mut todo = vec![(0usize, lo, size)];
    while let Some((i, o, s)) = todo.pop() {
        if nodes[i].members.len() <= max_splats || nodes[i].depth >= MAX_DEPTH {
            continue;
        }
        let h = s / 2.0;
        let mut quads: [Vec<u32>; 4] = Default::default();
        for m in std::mem::take(&mut nodes[i].members) {
            let p = xy[m as usize];
            let q = usize::from(p[0] >= o[0] + h) + 2 * usize::from(p[1] >= o[1] + h);
            quads[q].push(m);
        }
        for (q, members) in quads.into_iter().enumerate() {
            if members.is_empty() {
                continue;
            }
            let child = Node {
                path: format!("{}{q}", nodes[i].path),
                depth: nodes[i].depth + 1,
                members,
                children: Vec::new(),
                frame: DMat3::IDENTITY,
                centre: DVec3::ZERO,
                centre_crs: DVec3::ZERO,
            };
            nodes.push(child);
            let c = nodes.len() - 1;
            nodes[i].children.push(c);
            let co = [
                o[0] + if q & 1 == 1 { h } else { 0.0 },
                o[1] + if q & 2 == 2 { h } else { 0.0 },
            ];
            todo.push((c, co, h));
        }
    }
    nodes
}

/// The 4×4 (column-major, f64) of frame `f` at `c`: local → ECEF.
fn frame_matrix(f: DMat3, c: DVec3) -> DMat4 {
    DMat4::from_cols(
        f.x_axis.extend(0.0),
        f.y_axis.extend(0.0),
        f.z_axis.extend(0.0),
        c.extend(1.0),
    )
}

/// glTF's Y-up axes from ENU: `(e, n, u) ↦ (e, u, −n)`.
fn y_up() -> DMat3 {
    DMat3::from_cols(
        DVec3::new(1.0, 0.0, 0.0),
        DVec3::new(0.0, 0.0, -1.0),
        DVec3::new(0.0, 1.0, 0.0),
    )
}

/// The rotation nearest to `m` (a near-orthogonal matrix times a scale), by Newton's polar
/// iteration `R ← (R + R⁻ᵀ)/2`.
fn nearest_rotation(m: DMat3) -> DMat3 {
    let mut r = m;
    for _ in 0..8 {
        r = (r + r.inverse().transpose()) * 0.5;
    }
    r
}

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

/// The per-Gaussian semantics of the exported set: entity ids per level and the class.
struct Semantics<'a> {
    /// building / surface / part entity id per exported Gaussian (−1 none).
    levels: [Vec<i32>; 3],
    class: Vec<i32>,
    entities: &'a [Entity],
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

/// The splats as uncompressed `KHR_gaussian_splatting` attributes (module docs) into `attrs`.
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
    attrs.insert(
        "KHR_gaussian_splatting:SCALE".into(),
        json!(b.floats(&flat3(&g.scale), 3, false)),
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
) -> Result<usize, QueryError> {
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

/// One leaf's glTF binary: `g` already in the leaf's frame (Y up), `idx` the exported indices
/// of its Gaussians (for their semantics).
fn tile_glb(
    g: &Gaussians,
    idx: &[u32],
    sem: &Semantics<'_>,
    spz: bool,
) -> Result<Vec<u8>, QueryError> {
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
        let ids: Vec<i32> = idx.iter().map(|&i| sem.levels[level][i as usize]).collect();
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
        tables.push(entity_table(&mut b, name, &rows, sem.entities));
    }
    let classes: Vec<i32> = idx.iter().map(|&i| sem.class[i as usize]).collect();
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

/// A box (3D Tiles `box`: centre, then three half-axes) around local points `p` padded by
/// `pad` metres.
fn bounding_box(lo: DVec3, hi: DVec3, pad: f64) -> Value {
    let c = (lo + hi) / 2.0;
    let h = (hi - lo) / 2.0 + DVec3::splat(pad);
    json!([c.x, c.y, c.z, h.x, 0.0, 0.0, 0.0, h.y, 0.0, 0.0, 0.0, h.z])
}

/// The folder the export is built in before it becomes `out`.
fn partial_dir(out: &Path) -> PathBuf {
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "tiles".into());
    out.with_file_name(format!(".{name}.partial-{}", std::process::id()))
}

/// Exports the Gaussians `selected` of run `sr` as a 3D Tiles tileset in `out` (module docs).
/// `alignment`: the run's (scene ← CRS); `georef`: the CRS's operations; `query`: the
/// selection's text for the summary.
pub fn export(
    sr: &SemanticRun,
    selected: &[bool],
    query: &str,
    alignment: &Alignment,
    georef: &Georef,
    opts: &TilesOptions,
    out: &Path,
) -> Result<TilesSummary, QueryError> {
    let t0 = Instant::now();
    if out.exists() && !out.join("tileset.json").is_file() {
        let empty = std::fs::read_dir(out)
            .map(|mut d| d.next().is_none())
            .unwrap_or(false);
        if !empty {
            return Err(QueryError::Inputs(format!(
                "--out {}: exists and holds no tileset.json; give a new folder (an earlier export is replaced, any other folder is left alone)",
                out.display()
            )));
        }
    }
    if !selected.iter().any(|&s| s) {
        return Err(QueryError::Inputs(format!(
            "the selection `{query}` holds no Gaussian: nothing to export"
        )));
    }
    let ply = &sr.scene.ply;
    let (mut g, _) = splat::read_ply(ply, &splat::ReadOptions::KEEP)?;
    if g.len() != selected.len() {
        return Err(QueryError::Inputs(format!(
            "{} holds {} Gaussians, the run's labels have {}: the PLY is not the one the run was made from",
            ply.display(),
            g.len(),
            selected.len()
        )));
    }
    let cols = super::columns(sr);
    let keep: Vec<bool> = (0..g.len())
        .map(|i| selected[i] && splat::ply::is_valid(&g, i))
        .collect();
    let invalid = selected.iter().filter(|&&s| s).count() - keep.iter().filter(|&&k| k).count();
    if !keep.iter().any(|&k| k) {
        return Err(QueryError::Inputs(format!(
            "the selection `{query}` holds only invalid Gaussians (NaN or degenerate values in {}): nothing to export",
            ply.display()
        )));
    }
    match opts.color_by {
        ColorBy::Rgb => {}
        ColorBy::Class => {
            for i in (0..g.len()).filter(|&i| keep[i]) {
                transform::paint(&mut g, i, classes::color(cols.values[1][i]));
            }
        }
        ColorBy::Building => {
            for i in (0..g.len()).filter(|&i| keep[i]) {
                transform::paint(&mut g, i, classes::building_color(cols.building[i]));
            }
        }
    }
    let g = subset(&g, &keep, true);
    let picked: Vec<usize> = (0..keep.len()).filter(|&i| keep[i]).collect();
    let sem = Semantics {
        levels: [2, 3, 4].map(|c| picked.iter().map(|&i| cols.values[c][i]).collect()),
        class: picked.iter().map(|&i| cols.values[1][i]).collect(),
        entities: &sr.entities,
    };
    let read_s = t0.elapsed().as_secs_f64();

    // Georeference: CRS positions (f64), ECEF of every Gaussian.
    let t = Instant::now();
    let geo: Vec<DVec3> = g
        .positions
        .iter()
        .map(|p| alignment.unapply(DVec3::from_array(p.map(f64::from))))
        .collect();
    let bar = crate::progress::Bar::new("export", geo.len() as u64, "Gaussians");
    let mut ecef = Vec::with_capacity(geo.len());
    for (i, p) in geo.iter().enumerate() {
        ecef.push(georef.ecef(*p)?);
        if i % 65_536 == 65_535 {
            bar.inc(65_536);
        }
    }
    bar.finish();
    let xy: Vec<[f64; 2]> = geo.iter().map(|p| [p.x, p.y]).collect();
    let mut nodes = quadtree(&xy, opts.max_splats.max(1));
    // Every node's members (leaves hold theirs; inner nodes the union of their subtree).
    let order: Vec<usize> = (0..nodes.len()).rev().collect();
    let mut all: Vec<Vec<u32>> = nodes.iter().map(|n| n.members.clone()).collect();
    for &i in &order {
        if !nodes[i].children.is_empty() {
            let mut m: Vec<u32> = nodes[i]
                .children
                .iter()
                .flat_map(|&c| all[c].iter().copied())
                .collect();
            m.sort_unstable();
            all[i] = m;
        }
    }
    for (i, node) in nodes.iter_mut().enumerate() {
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for &m in &all[i] {
            lo = lo.min(geo[m as usize]);
            hi = hi.max(geo[m as usize]);
        }
        let c = (lo + hi) / 2.0;
        let (lon, lat) = georef.lon_lat(c.x, c.y)?;
        node.centre_crs = c;
        node.centre = georef.ecef(c)?;
        node.frame = crs::enu_frame(lon, lat);
    }
    let georef_s = t.elapsed().as_secs_f64();

    // Write into the partial folder.
    let t = Instant::now();
    let tmp = partial_dir(out);
    let _ = std::fs::remove_dir_all(&tmp);
    fsutil::create_dir(&tmp.join("tiles"))?;
    let result = write_tiles(
        &tmp, &nodes, &all, &g, &ecef, &sem, alignment, georef, opts.spz,
    );
    let (tileset, bytes, depth) = match result {
        Ok(r) => r,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
    };
    let root = &nodes[0];
    let (lon, lat) = georef.lon_lat(root.centre_crs.x, root.centre_crs.y)?;
    let summary = TilesSummary {
        format: "3dtiles".into(),
        query: query.to_string(),
        crs: georef.crs.clone(),
        splats: g.len(),
        invalid,
        tiles: nodes.len(),
        leaves: nodes.iter().filter(|n| n.children.is_empty()).count(),
        depth,
        sh_degree: g.sh_degree,
        root: RootPlace {
            crs: root.centre_crs.to_array(),
            lon,
            lat,
            height: root.centre_crs.z,
            ecef: root.centre.to_array(),
        },
        bytes: bytes + tileset,
        options: *opts,
        timing: TilesTiming {
            read_s,
            georef_s,
            write_s: t.elapsed().as_secs_f64(),
            total_s: t0.elapsed().as_secs_f64() + sr.load_s,
        },
    };
    let finish = || -> Result<(), QueryError> {
        fsutil::write_json(&tmp.join("summary.json"), &summary)?;
        let old = out.with_file_name(format!(
            ".{}.old-{}",
            out.file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            std::process::id()
        ));
        let had = out.exists();
        let io = |e: std::io::Error| {
            QueryError::Fs(fsutil::FsError::Write {
                path: out.to_path_buf(),
                err: e,
            })
        };
        if had {
            std::fs::rename(out, &old).map_err(io)?;
        }
        std::fs::rename(&tmp, out).map_err(io)?;
        if had {
            let _ = std::fs::remove_dir_all(&old);
        }
        Ok(())
    };
    if let Err(e) = finish() {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    crate::progress::done(
        "export",
        &format!(
            "{} Gaussians in {} tiles ({} leaves, depth {}), {:.1} MB → {}",
            summary.splats,
            summary.tiles,
            summary.leaves,
            summary.depth,
            summary.bytes as f64 / 1e6,
            out.display()
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}

/// Writes every leaf's `.glb` and `tileset.json` into `dir`; returns the tileset's bytes, the
/// tiles' bytes and the depth.
#[allow(clippy::too_many_arguments)]
fn write_tiles(
    dir: &Path,
    nodes: &[Node],
    all: &[Vec<u32>],
    g: &Gaussians,
    ecef: &[DVec3],
    sem: &Semantics<'_>,
    alignment: &Alignment,
    georef: &Georef,
    spz: bool,
) -> Result<(u64, u64, u32), QueryError> {
    let leaves: Vec<usize> = (0..nodes.len())
        .filter(|&i| nodes[i].children.is_empty())
        .collect();
    let bar = crate::progress::Bar::new("export", leaves.len() as u64, "tiles");
    let mut bytes = 0u64;
    let max_scale: Vec<f64> = g
        .scale
        .iter()
        .map(|s| f64::from(s[0].max(s[1]).max(s[2])).exp())
        .collect();
    let mut contents: Vec<Option<String>> = vec![None; nodes.len()];
    for &i in &leaves {
        let node = &nodes[i];
        let members = &all[i];
        // The CRS → ENU Jacobian at the centre (central differences of 1 m through PROJ).
        let local = |p: DVec3| -> Result<DVec3, QueryError> {
            Ok(node.frame.transpose() * (georef.ecef(p)? - node.centre))
        };
        let mut cols = [DVec3::ZERO; 3];
        for (k, col) in cols.iter_mut().enumerate() {
            let mut d = DVec3::ZERO;
            d[k] = 1.0;
            *col = (local(node.centre_crs + d)? - local(node.centre_crs - d)?) / 2.0;
        }
        let jac = DMat3::from_cols(cols[0], cols[1], cols[2]);
        let k = jac.determinant().cbrt();
        let rot = nearest_rotation(jac / k);
        let motion = Motion {
            scale: k / alignment.scale,
            rotation: y_up() * rot * alignment.rotation.transpose(),
            translation: DVec3::ZERO,
        };
        let mut sel = vec![false; g.len()];
        for &m in members {
            sel[m as usize] = true;
        }
        let mut tile = subset(g, &sel, true);
        transform::apply(&mut tile, &motion);
        for (p, &m) in tile.positions.iter_mut().zip(members) {
            let l = y_up() * (node.frame.transpose() * (ecef[m as usize] - node.centre));
            *p = l.to_array().map(|x| x as f32);
        }
        let bytes_glb = tile_glb(&tile, members, sem, spz)?;
        bytes += bytes_glb.len() as u64;
        let name = format!("tiles/{}.glb", node.path);
        fsutil::write_bytes(&dir.join(&name), &bytes_glb)?;
        contents[i] = Some(name);
        bar.inc(1);
    }
    bar.finish();

    // tileset.json: boxes in each node's frame around its Gaussians, 3σ of the largest padded.
    let mut depth = 0;
    let mut tiles: Vec<Option<Value>> = vec![None; nodes.len()];
    for i in (0..nodes.len()).rev() {
        let node = &nodes[i];
        depth = depth.max(node.depth);
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        let mut pad = 0.0f64;
        for &m in &all[i] {
            let l = node.frame.transpose() * (ecef[m as usize] - node.centre);
            lo = lo.min(l);
            hi = hi.max(l);
            pad = pad.max(3.0 * max_scale[m as usize] / alignment.scale);
        }
        let bv = bounding_box(lo, hi, pad);
        let transform = match node.depth {
            0 => frame_matrix(node.frame, node.centre),
            _ => {
                let parent = nodes
                    .iter()
                    .position(|p| p.children.contains(&i))
                    .expect("every non-root node has a parent");
                frame_matrix(nodes[parent].frame, nodes[parent].centre).inverse()
                    * frame_matrix(node.frame, node.centre)
            }
        };
        let diag = ((hi - lo).length() + 2.0 * pad).max(0.0);
        let mut t = json!({
            "boundingVolume": {"box": bv},
            "geometricError": if node.children.is_empty() { 0.0 } else { diag },
            "transform": transform.to_cols_array().to_vec(),
        });
        if let Some(uri) = &contents[i] {
            t["content"] = json!({"uri": uri});
        }
        if node.depth == 0 {
            t["refine"] = json!("ADD");
        }
        if !node.children.is_empty() {
            let children: Vec<Value> = node
                .children
                .iter()
                .map(|&c| tiles[c].take().expect("children are built before parents"))
                .collect();
            t["children"] = Value::Array(children);
        }
        tiles[i] = Some(t);
    }
    let root = tiles[0].take().expect("the root tile");
    let root_error = root["geometricError"].as_f64().unwrap_or(0.0);
    let mut tileset = json!({
        "asset": {
            "version": "1.1",
            "generator": format!("gs4city {}", env!("CARGO_PKG_VERSION")),
        },
        "geometricError": (2.0 * root_error).max(1.0),
        "root": root,
    });
    if spz {
        // The glTF extensions the content needs, declared at the tileset (what CesiumJS reads
        // to load the tiles as Gaussian splats).
        tileset["extensionsUsed"] = json!(["3DTILES_content_gltf"]);
        tileset["extensions"] = json!({"3DTILES_content_gltf": {
            "extensionsUsed": ["KHR_gaussian_splatting", "KHR_gaussian_splatting_compression_spz_2",
                "EXT_mesh_features", "EXT_structural_metadata"],
            "extensionsRequired": ["KHR_gaussian_splatting", "KHR_gaussian_splatting_compression_spz_2"],
        }});
    }
    let text = serde_json::to_vec_pretty(&tileset).expect("JSON values serialise");
    fsutil::write_bytes(&dir.join("tileset.json"), &text)?;
    Ok((text.len() as u64, bytes, depth))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quadtree_splits_until_leaves_are_small_and_keeps_every_point_once() {
        let xy: Vec<[f64; 2]> = (0..1000)
            .map(|i| [f64::from(i % 37) * 3.1, f64::from(i / 37) * 1.7])
            .collect();
        let nodes = quadtree(&xy, 100);
        let mut seen = vec![0; xy.len()];
        for n in nodes.iter().filter(|n| n.children.is_empty()) {
            assert!(n.members.len() <= 100 || n.depth == MAX_DEPTH);
            for &m in &n.members {
                seen[m as usize] += 1;
            }
        }
        assert!(seen.iter().all(|&s| s == 1));
        assert!(nodes.len() > 4);
    }

    #[test]
    fn nearest_rotation_removes_the_scale_and_keeps_the_rotation() {
        let r = DMat3::from_rotation_z(0.03);
        let m = nearest_rotation(r * 1.0004);
        assert!((m - r).abs_diff_eq(DMat3::ZERO, 1e-12));
    }
}
