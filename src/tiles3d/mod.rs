//! The georeferenced 3D Tiles 1.1 export (`gs4city export --format 3dtiles`, docs/export.md):
//! a set of Gaussians with their CityGML semantics as a tileset of glTF 2.0 tiles. The
//! caller (`query`) selects and colours the Gaussians; this module writes them.
//!
//! - **Content** ([`gltf`]): one glTF 2.0 binary per tile, the splats as a `POINTS`
//!   primitive with `KHR_gaussian_splatting` as its current text (Release Candidate) defines
//!   it — `POSITION`, `:ROTATION` (unit quaternion x, y, z, w), `:SCALE` (linear), `:OPACITY`
//!   (in [0, 1]), `:SH_DEGREE_ℓ_COEF_n` (complete degrees, turned with the Gaussians), the
//!   required `kernel` and `colorSpace` — and `COLOR_0` (the fallback colour), or one SPZ v2
//!   blob per tile ([`crate::spz`], `KHR_gaussian_splatting_compression_spz_2`, a draft);
//!   `EXT_mesh_features` building / surface / part / class feature ids per splat and
//!   `EXT_structural_metadata` property tables of the entities.
//! - **Georeference**: a Gaussian's scene position goes back to the city model's CRS through
//!   the run's alignment (`Alignment::unapply`, f64), then through PROJ to ECEF
//!   ([`crate::crs`]); a tile's content holds f32 offsets in the east-north-up frame at the
//!   tile's centre (glTF's Y up: `(east, up, −north)`), and the tile carries the f64 transform
//!   of that frame (the root: ENU → ECEF; a child: relative to its parent). Orientations, scales
//!   and SH bands are turned by the frame change at the tile's centre (the CRS → ENU Jacobian,
//!   by central differences through PROJ, split into its rotation and its scale).
//! - **Hierarchy and level of detail** ([`lod`]): a quadtree over the CRS ground plane; a node
//!   holding more than `max_splats` Gaussians is split in four (empty quadrants dropped). The
//!   leaves hold the Gaussians; every inner node holds a coarse set of at most `max_splats`
//!   splats (and at most a quarter of its children's) merged from its children's, and
//!   `refine: REPLACE`, so a client draws coarse to fine. A leaf's geometric error is 0, an
//!   inner node's the largest distance of an input Gaussian from the coarse splat that stands
//!   for it (metres). Each bounding volume is a `box` in the node's own ENU frame around the
//!   Gaussians of its subtree, padded by three standard deviations of the largest splat of its
//!   subtree (coarse ones included).
//!
//! The tileset is written into a temporary folder beside `out` and renamed to `out` only when
//! complete.
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DMat4, DVec3};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::alignment::Alignment;
use crate::crs::{self, Georef};
use crate::fsutil;
use crate::semantics::Entity;
use crate::splat::Gaussians;
use crate::splat::transform::{self, Motion};

pub mod gltf;
pub mod lod;

use lod::{SplatSet, Tags};

/// The default largest number of splats in one tile (a leaf's Gaussians, an inner node's coarse
/// set); the root holds at most this many.
pub const MAX_SPLATS: usize = 65_536;
/// The deepest quadtree level (a node there is a leaf whatever its count).
pub const MAX_DEPTH: u32 = 16;
/// The smallest geometric error of an inner node (metres): a coarse set that merged nothing
/// apart still asks to be refined.
pub const MIN_INNER_ERROR: f64 = 1e-3;

/// Errors of the export.
#[derive(Debug, thiserror::Error)]
pub enum TilesError {
    #[error("{0}")]
    Inputs(String),
    #[error(transparent)]
    Crs(#[from] crate::crs::CrsError),
    #[error(transparent)]
    Glb(#[from] crate::glb::GlbError),
    #[error(transparent)]
    Spz(#[from] crate::spz::SpzError),
    #[error(transparent)]
    Fs(#[from] fsutil::FsError),
}

/// Options of the export.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TilesOptions {
    /// A node with more Gaussians than this is split; no tile holds more splats.
    pub max_splats: usize,
    /// The splats SPZ-compressed (`KHR_gaussian_splatting_compression_spz_2`).
    #[serde(default)]
    pub spz: bool,
}

impl Default for TilesOptions {
    fn default() -> Self {
        TilesOptions {
            max_splats: MAX_SPLATS,
            spz: false,
        }
    }
}

/// What to export: Gaussians (scene frame, valid values, already coloured) and their semantics.
#[derive(Debug)]
pub struct Splats<'a> {
    pub gaussians: Gaussians,
    /// Per Gaussian: building, surface and part entity ids and the evaluation class (−1 none).
    pub tags: Vec<Tags>,
    /// The rows the entity ids index (`semantics.json`).
    pub entities: &'a [Entity],
    /// The selection, canonical text (for the summary).
    pub query: String,
    /// Selected Gaussians left out because their values are invalid.
    pub invalid: usize,
    /// The colouring (for the summary): `rgb`, `class` or `building`.
    pub color_by: String,
    /// Seconds the caller spent reading and selecting.
    pub read_s: f64,
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
    /// Building the coarse sets and writing every tile.
    pub write_s: f64,
    /// Of which the coarse sets' merges.
    pub lod_s: f64,
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
    /// Exported Gaussians (the selection's valid Gaussians), held by the leaves.
    pub splats: usize,
    /// Selected Gaussians left out because their values are invalid (NaN, zero quaternion…).
    pub invalid: usize,
    pub tiles: usize,
    pub leaves: usize,
    pub depth: u32,
    /// Splats of the inner nodes' coarse sets, all together.
    pub coarse_splats: usize,
    /// Splats of the root tile.
    pub root_splats: usize,
    /// The root's geometric error (metres; 0 when the root is a leaf).
    pub root_geometric_error: f64,
    pub sh_degree: u8,
    pub root: RootPlace,
    /// Bytes of `tileset.json` and every tile.
    pub bytes: u64,
    /// `rgb`, `class` or `building`.
    pub color_by: String,
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

/// Exports `splats` as a 3D Tiles tileset in `out` (module docs). `alignment`: the run's
/// (scene ← CRS); `georef`: the CRS's operations.
pub fn write(
    splats: &Splats<'_>,
    alignment: &Alignment,
    georef: &Georef,
    opts: &TilesOptions,
    out: &Path,
) -> Result<TilesSummary, TilesError> {
    let t0 = Instant::now();
    if out.exists() && !out.join("tileset.json").is_file() {
        let empty = std::fs::read_dir(out)
            .map(|mut d| d.next().is_none())
            .unwrap_or(false);
        if !empty {
            return Err(TilesError::Inputs(format!(
                "--out {}: exists and holds no tileset.json; give a new folder (an earlier export is replaced, any other folder is left alone)",
                out.display()
            )));
        }
    }
    let g = &splats.gaussians;
    if g.is_empty() {
        return Err(TilesError::Inputs(format!(
            "the selection `{}` holds no Gaussian: nothing to export",
            splats.query
        )));
    }
    if splats.tags.len() != g.len() {
        return Err(TilesError::Inputs(format!(
            "{} Gaussians but {} semantic rows",
            g.len(),
            splats.tags.len()
        )));
    }
    let max_splats = opts.max_splats.max(1);

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
    let mut nodes = quadtree(&xy, max_splats);
    // Every node's members (leaves hold theirs; inner nodes the union of their subtree).
    let mut all: Vec<Vec<u32>> = nodes.iter().map(|n| n.members.clone()).collect();
    for i in (0..nodes.len()).rev() {
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
    let ctx = Context {
        nodes: &nodes,
        all: &all,
        splats,
        ecef: &ecef,
        alignment,
        georef,
        max_splats,
        spz: opts.spz,
    };
    let written = match write_tiles(&tmp, &ctx) {
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
        query: splats.query.clone(),
        crs: georef.crs.clone(),
        splats: g.len(),
        invalid: splats.invalid,
        tiles: nodes.len(),
        leaves: nodes.iter().filter(|n| n.children.is_empty()).count(),
        depth: written.depth,
        coarse_splats: written.coarse_splats,
        root_splats: written.root_splats,
        root_geometric_error: written.root_error,
        sh_degree: g.sh_degree,
        root: RootPlace {
            crs: root.centre_crs.to_array(),
            lon,
            lat,
            height: root.centre_crs.z,
            ecef: root.centre.to_array(),
        },
        bytes: written.tileset_bytes + written.tile_bytes,
        color_by: splats.color_by.clone(),
        options: TilesOptions {
            max_splats,
            spz: opts.spz,
        },
        timing: TilesTiming {
            read_s: splats.read_s,
            georef_s,
            write_s: t.elapsed().as_secs_f64(),
            lod_s: written.lod_s,
            total_s: t0.elapsed().as_secs_f64() + splats.read_s,
        },
    };
    let finish = || -> Result<(), TilesError> {
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
            TilesError::Fs(fsutil::FsError::Write {
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
            "{} Gaussians in {} tiles ({} leaves, depth {}, {} coarse splats), {:.1} MB → {}",
            summary.splats,
            summary.tiles,
            summary.leaves,
            summary.depth,
            summary.coarse_splats,
            summary.bytes as f64 / 1e6,
            out.display()
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}

/// What the tile writer reads.
struct Context<'a> {
    nodes: &'a [Node],
    all: &'a [Vec<u32>],
    splats: &'a Splats<'a>,
    ecef: &'a [DVec3],
    alignment: &'a Alignment,
    georef: &'a Georef,
    max_splats: usize,
    spz: bool,
}

/// What [`write_tiles`] wrote.
struct Written {
    tileset_bytes: u64,
    tile_bytes: u64,
    depth: u32,
    coarse_splats: usize,
    root_splats: usize,
    root_error: f64,
    lod_s: f64,
}

/// The motion from the scene frame into node `node`'s tile frame (Y up), positions aside: the
/// alignment's rotation and scale back to the CRS, then the CRS → ENU Jacobian at the node's
/// centre (central differences of 1 m through PROJ) split into a rotation and a scale.
fn tile_motion(node: &Node, ctx: &Context<'_>) -> Result<Motion, TilesError> {
    let local = |p: DVec3| -> Result<DVec3, TilesError> {
        Ok(node.frame.transpose() * (ctx.georef.ecef(p)? - node.centre))
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
    Ok(Motion {
        scale: k / ctx.alignment.scale,
        rotation: y_up() * rot * ctx.alignment.rotation.transpose(),
        translation: DVec3::ZERO,
    })
}

/// Three standard deviations of the largest splat of `g` (scene units).
fn three_sigma(g: &Gaussians) -> f64 {
    g.scale
        .iter()
        .map(|s| 3.0 * f64::from(s[0].max(s[1]).max(s[2])).exp())
        .fold(0.0, f64::max)
}

/// Builds every node's splat set bottom-up (a leaf: its Gaussians; an inner node: the coarse
/// set of its children's sets), writes each as `tiles/<path>.glb`, then `tileset.json`.
fn write_tiles(dir: &Path, ctx: &Context<'_>) -> Result<Written, TilesError> {
    let nodes = ctx.nodes;
    let g = &ctx.splats.gaussians;
    let bar = crate::progress::Bar::new("export", nodes.len() as u64, "tiles");
    let mut sets: Vec<Option<SplatSet>> = (0..nodes.len()).map(|_| None).collect();
    // Per node: the geometric error (metres) and the padding of its subtree's splats (metres).
    let mut errors = vec![0.0f64; nodes.len()];
    let mut pads = vec![0.0f64; nodes.len()];
    let (mut tile_bytes, mut coarse_splats, mut root_splats) = (0u64, 0usize, 0usize);
    let mut lod_s = 0.0;
    // Children come after their parent in `nodes`: in reverse, every child is done first.
    for i in (0..nodes.len()).rev() {
        let node = &nodes[i];
        let (set, local): (SplatSet, Vec<DVec3>) = if node.children.is_empty() {
            let idx: Vec<usize> = node.members.iter().map(|&m| m as usize).collect();
            let set = SplatSet {
                g: g.select(&idx),
                tags: idx.iter().map(|&m| ctx.splats.tags[m]).collect(),
                error: vec![0.0; idx.len()],
            };
            let local = idx
                .iter()
                .map(|&m| node.frame.transpose() * (ctx.ecef[m] - node.centre))
                .collect();
            (set, local)
        } else {
            let t = Instant::now();
            let parts: Vec<SplatSet> = node
                .children
                .iter()
                .map(|&c| sets[c].take().expect("children are built before parents"))
                .collect();
            let refs: Vec<&SplatSet> = parts.iter().collect();
            let merged = SplatSet::concat(&refs);
            drop(parts);
            let target = ctx.max_splats.min(merged.g.len().div_ceil(4)).max(1);
            let set = lod::coarsen(&merged, target);
            lod_s += t.elapsed().as_secs_f64();
            let mut local = Vec::with_capacity(set.g.len());
            for p in &set.g.positions {
                let geo = ctx.alignment.unapply(DVec3::from_array(p.map(f64::from)));
                local.push(node.frame.transpose() * (ctx.georef.ecef(geo)? - node.centre));
            }
            coarse_splats += set.g.len();
            let child_error = node.children.iter().map(|&c| errors[c]).fold(0.0, f64::max);
            errors[i] = (set.max_error() / ctx.alignment.scale)
                .max(child_error)
                .max(MIN_INNER_ERROR);
            (set, local)
        };
        pads[i] = node
            .children
            .iter()
            .map(|&c| pads[c])
            .fold(three_sigma(&set.g) / ctx.alignment.scale, f64::max);
        let mut tile = set.g.clone();
        transform::apply(&mut tile, &tile_motion(node, ctx)?);
        for (p, l) in tile.positions.iter_mut().zip(&local) {
            *p = (y_up() * *l).to_array().map(|x| x as f32);
        }
        let bytes = gltf::tile_glb(&tile, &set.tags, ctx.splats.entities, ctx.spz)?;
        tile_bytes += bytes.len() as u64;
        fsutil::write_bytes(&dir.join(format!("tiles/{}.glb", node.path)), &bytes)?;
        if i == 0 {
            root_splats = set.g.len();
        } else {
            sets[i] = Some(set);
        }
        bar.inc(1);
    }
    bar.finish();

    // tileset.json: boxes in each node's frame around its subtree's Gaussians, padded.
    let mut depth = 0;
    let mut tiles: Vec<Option<Value>> = vec![None; nodes.len()];
    let mut root_diag = 0.0;
    for i in (0..nodes.len()).rev() {
        let node = &nodes[i];
        depth = depth.max(node.depth);
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for &m in &ctx.all[i] {
            let l = node.frame.transpose() * (ctx.ecef[m as usize] - node.centre);
            lo = lo.min(l);
            hi = hi.max(l);
        }
        let bv = bounding_box(lo, hi, pads[i]);
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
        if i == 0 {
            root_diag = (hi - lo).length() + 2.0 * pads[i];
        }
        let mut t = json!({
            "boundingVolume": {"box": bv},
            "geometricError": errors[i],
            "transform": transform.to_cols_array().to_vec(),
            "content": {"uri": format!("tiles/{}.glb", node.path)},
        });
        if node.depth == 0 {
            t["refine"] = json!("REPLACE");
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
    let mut tileset = json!({
        "asset": {
            "version": "1.1",
            "generator": format!("gs4city {}", env!("CARGO_PKG_VERSION")),
        },
        // Not drawing the tileset at all misses everything in it: its size.
        "geometricError": root_diag.max(2.0 * errors[0]).max(1.0),
        "root": root,
    });
    if ctx.spz {
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
    Ok(Written {
        tileset_bytes: text.len() as u64,
        tile_bytes,
        depth,
        coarse_splats,
        root_splats,
        root_error: errors[0],
        lod_s,
    })
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
