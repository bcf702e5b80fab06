//! The `openings` stage (beyond the paper; its future work "weaker priors such as LoD2 models"
//! and "the semantic completeness of the city model"): windows and doors from the images where
//! the city model has none, and the model's completeness report (`docs/completeness.md`).
//!
//! Per training view, a SAM mask that the masks stage **dropped as building** (any rule after
//! the area rule) whose best prompt is a window or door prompt (the decision's `class` score,
//! the CLIP-space argmax the masks stage computed; without features there is none):
//! * **supports** a model opening when ≥ `part_share` of its pixels carry that opening in the
//!   raycast part channel;
//! * else is a **candidate** when ≥ `min_wall_share` of its pixels lie on one wall surface
//!   (surface channel) and those pixels, back-projected through the raycast depth onto the
//!   wall's plane ([`plane::WallFrame`]: u horizontal, v up), span a rectangle (the `trim` and
//!   `1 − trim` quantiles of u and v) of plausible size (`size_m`, metres × the alignment scale).
//!   A mask the quality rule dropped with `predicted_iou ≥ support_floor` is a *weak* candidate.
//!
//! **Cross-view consistency**: per wall, strong candidates (in view order) join the cluster whose
//! median rectangle they overlap most with IoU ≥ `join_iou`, else found one; weak candidates
//! then join (never found, never move the rectangle). A cluster seen in ≥ `m_view` distinct
//! views is **accepted**; its rectangle is the per-side median of its strong members, clipped to
//! the wall; its class the members' majority (window on ties).
//!
//! **Completeness**: an accepted cluster that overlaps no model opening lying on its wall's
//! plane (mean vertex distance ≤ `plane_tol_m`; intersection over the smaller rectangle ≥
//! `match_overlap`) is **missing in the model**; a model opening supported in ≥ `m_view` views
//! is **confirmed**; one seen (≥ `seen_px_frac`·H·W part pixels) in ≥ `m_view` views and
//! supported in none is **unsupported**.
//!
//! **Model completion** (`add: missing`, the default): every missing opening becomes a part
//! entity under its wall (`source: "image"`, object id `gs4city-opening-<hash>` of the wall's
//! object id and the rectangle's georeferenced corners in centimetres) and two triangles on the
//! wall plane in the mesh; the run raycasts that mesh again, so `M_city`, the fusion, the vote,
//! `query` and the exports see the opening as an LoD3 one. When nothing is missing the model is
//! left as it is.
//!
//! Reads only what `docs/design.md` allows: the masks stage's decisions, the scene's SAM lists,
//! the raycast and the city mesh; never `gt/`.
pub mod plane;
mod recess;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::alignment::Alignment;
use crate::camera::View;
use crate::citygml::{CityModel, CityObject, Polygon, ReadStats, Ring, Version};
use crate::fsutil::{self, FsError};
use crate::idmap;
use crate::maskfile::{self, Rule};
use crate::mesh::{FaceLabel, TriMesh};
use crate::progress::Bar;
use crate::sam;
use crate::semantics::{self, Class, Entity, Level};
use plane::{Rect, WallFrame, wall_frames};

/// Errors of the openings stage; each names its file.
#[derive(Debug, thiserror::Error)]
pub enum OpeningsError {
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error(transparent)]
    IdMap(#[from] idmap::IdMapError),
    #[error(transparent)]
    MaskFile(#[from] maskfile::MaskFileError),
    #[error(transparent)]
    Sam(#[from] sam::SamError),
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error(transparent)]
    Semantics(#[from] semantics::SemanticsError),
    #[error(transparent)]
    Mesh(#[from] crate::mesh::MeshError),
    #[error(transparent)]
    Cache(#[from] crate::cache::CacheError),
}

/// Which accepted openings enter the semantic table and the mesh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Add {
    /// Openings the model lacks (the completeness rule).
    Missing,
    /// None: the completeness report only.
    Off,
}

impl std::str::FromStr for Add {
    type Err = String;
    fn from_str(s: &str) -> Result<Add, String> {
        match s {
            "missing" => Ok(Add::Missing),
            "off" => Ok(Add::Off),
            _ => Err(format!("{s:?} is not one of missing, off")),
        }
    }
}

/// Where candidates come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Cues {
    /// Dropped building masks whose best prompt is a window or door prompt (needs features).
    Features,
    /// Regions recessed behind the wall plane in the 3DGS depth (`recess.rs`; needs the cache).
    Geometry,
    /// Both, clustered together.
    Both,
}

impl Cues {
    fn features(self) -> bool {
        matches!(self, Cues::Features | Cues::Both)
    }
    /// Whether the stage reads the contributions cache and the Gaussians.
    pub fn geometry(self) -> bool {
        matches!(self, Cues::Geometry | Cues::Both)
    }
}

impl std::str::FromStr for Cues {
    type Err = String;
    fn from_str(s: &str) -> Result<Cues, String> {
        match s {
            "features" => Ok(Cues::Features),
            "geometry" => Ok(Cues::Geometry),
            "both" => Ok(Cues::Both),
            _ => Err(format!("{s:?} is not one of features, geometry, both")),
        }
    }
}

/// Options of the stage (module docs; defaults in `docs/completeness.md`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OpeningsOptions {
    pub add: Add,
    /// Where candidates come from.
    pub cues: Cues,
    /// Distinct views a cluster needs to be accepted.
    pub m_view: usize,
    /// Share of a candidate's pixels on its wall.
    pub min_wall_share: f64,
    /// Masks dropped by the quality rule with at least this `predicted_iou` are weak
    /// candidates: they join clusters, never found one (the masks stage's support floor).
    pub support_floor: f64,
    /// Quantile trimmed at each side of the back-projected u and v.
    pub trim: f64,
    /// Plausible opening width and height, metres (× alignment scale).
    pub size_m: [f64; 2],
    /// IoU with a cluster's rectangle for a candidate to join it.
    pub join_iou: f64,
    /// Intersection over the smaller rectangle for a cluster to be a model opening.
    pub match_overlap: f64,
    /// A candidate with this share of its pixels on one model opening supports that opening
    /// (and is no candidate for a new one).
    pub part_share: f64,
    /// A model opening's vertices within this mean distance (metres × scale) of a wall's
    /// plane lie on that wall (window reveals and recesses are a few decimetres deep).
    pub plane_tol_m: f64,
    /// A model opening is seen in a view with at least this share of the image's pixels.
    pub seen_px_frac: f64,
    /// Walls whose normal makes more than this with the horizontal are not walls (cosine of
    /// the normal with up).
    pub max_tilt_cos: f64,
    /// Geometric cue: how far behind its wall's own offset (metres × scale) the 3DGS must
    /// stand for a pixel to be recessed, `[min, max]`.
    pub recess_m: [f64; 2],
    /// Geometric cue: the fewest pixels of a recessed component.
    pub min_px: usize,
    /// Geometric cue: a pixel counts only when the pixels this far up, down, left and right
    /// hit the same wall (no blur across silhouettes).
    pub guard_px: usize,
    /// Geometric cue: the longer side of a rectangle at most this many times the shorter.
    pub max_aspect: f64,
    /// Geometric cue: a rectangle whose bottom lies within this height (metres × scale) of
    /// its wall's bottom, and at least `door_height_m` tall, is a door.
    pub door_sill_m: f64,
    pub door_height_m: f64,
}

impl Default for OpeningsOptions {
    fn default() -> Self {
        OpeningsOptions {
            add: Add::Missing,
            cues: Cues::Both,
            m_view: 3,
            min_wall_share: 0.8,
            support_floor: 0.3,
            trim: 0.02,
            size_m: [0.3, 6.0],
            join_iou: 0.5,
            match_overlap: 0.5,
            part_share: 0.3,
            plane_tol_m: 0.5,
            seen_px_frac: 1e-4,
            max_tilt_cos: 0.3,
            recess_m: [0.06, 1.0],
            min_px: 12,
            guard_px: 2,
            max_aspect: 5.0,
            door_sill_m: 0.6,
            door_height_m: 1.7,
        }
    }
}

impl OpeningsOptions {
    /// Range checks (one wording, `crate::check`).
    pub fn validate(&self) -> Result<(), OpeningsError> {
        use crate::check::{End, at_least, positive, range, unit};
        at_least("m_view", self.m_view, 1)?;
        unit("min_wall_share", self.min_wall_share)?;
        unit("support_floor", self.support_floor)?;
        range("trim", self.trim, End::Closed(0.0), End::Open(0.5))?;
        unit("join_iou", self.join_iou)?;
        unit("match_overlap", self.match_overlap)?;
        unit("part_share", self.part_share)?;
        positive("plane_tol_m", self.plane_tol_m)?;
        unit("seen_px_frac", self.seen_px_frac)?;
        unit("max_tilt_cos", self.max_tilt_cos)?;
        for (name, [lo, hi]) in [("size_m", self.size_m), ("recess_m", self.recess_m)] {
            positive(&format!("{name}[1]"), hi)?;
            range(&format!("{name}[0]"), lo, End::Open(0.0), End::Open(hi))?;
        }
        positive("door_sill_m", self.door_sill_m)?;
        positive("door_height_m", self.door_height_m)?;
        range(
            "max_aspect",
            self.max_aspect,
            End::Closed(1.0),
            End::Open(f64::INFINITY),
        )?;
        Ok(())
    }
}

/// What the stage reads (typed; the run hands them over).
pub struct OpeningsInputs<'a> {
    /// The training views.
    pub views: &'a [View],
    /// The raycast folder (`<stem>.ids.npy`, `<stem>.depth.npy`) of `mesh`.
    pub raycast: &'a Path,
    /// The masks stage's folder (`<stem>.decisions.json`).
    pub masks: &'a Path,
    /// The scene's SAM lists (`masks/`); `None`: no candidates (mask-free source).
    pub sam: Option<&'a Path>,
    pub entities: &'a [Entity],
    pub mesh: &'a TriMesh,
    pub alignment: &'a Alignment,
    /// The city model's CRS (srsName), for the CityJSON's `referenceSystem`.
    pub srs_name: Option<String>,
    /// The contributions cache and the Gaussian centres (the geometric cue); `None`: none.
    pub geometry: Option<Geometry<'a>>,
}

/// What the geometric cue reads: the contributions cache of the views (their median depth),
/// and for a cache without the median-depth plane the centres of the Gaussians it was built
/// for ([`crate::cache::Cache::median_depth`]).
#[derive(Clone, Copy)]
pub struct Geometry<'a> {
    pub cache: &'a crate::cache::Cache,
    pub positions: Option<&'a [[f32; 3]]>,
}

/// One view's raycast maps (row-major `h×w`).
struct ViewMaps<'a> {
    view: &'a View,
    index: usize,
    surface: &'a [i32],
    part: &'a [i32],
    /// The city model's z-depth (NaN: no hit).
    city: &'a [f32],
}

/// The `trim`-quantile rectangle on `fr`'s plane of the pixels `px` that hit `wall`,
/// back-projected through the raycast depth; `None` with fewer than 4 such pixels.
fn plane_rect(
    vm: &ViewMaps<'_>,
    fr: &WallFrame,
    wall: i32,
    px: &[usize],
    trim: f64,
) -> Option<Rect> {
    let cam = &vm.view.camera;
    let w = cam.intrinsics.width as usize;
    let centre = cam.pose.center();
    let to_world = cam.pose.rotation.transpose();
    let (mut us, mut vs) = (Vec::with_capacity(px.len()), Vec::with_capacity(px.len()));
    for &p in px {
        let d = vm.city[p];
        if vm.surface[p] != wall || !d.is_finite() {
            continue;
        }
        let ray = cam.pixel_ray((p % w) as f64 + 0.5, (p / w) as f64 + 0.5);
        if ray.z <= 0.0 {
            continue;
        }
        let q = centre + to_world * ray * (d as f64 / ray.z);
        let [u, v] = fr.to_plane(q);
        us.push(u);
        vs.push(v);
    }
    if us.len() < 4 {
        return None;
    }
    us.sort_by(f64::total_cmp);
    vs.sort_by(f64::total_cmp);
    Some(Rect([
        quantile(&us, trim),
        quantile(&vs, trim),
        quantile(&us, 1.0 - trim),
        quantile(&vs, 1.0 - trim),
    ]))
}

/// One candidate mask on a wall.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    view: usize,
    wall: i32,
    rect: Rect,
    class: i32,
    /// From the geometric cue (a recessed region), not a mask.
    recess: bool,
    /// Passed the masks stage's quality rule; a weak candidate (`support_floor ≤
    /// predicted_iou < τ_q`) only joins clusters (like the associate stage's support-only
    /// masks): it never founds one nor moves its rectangle.
    strong: bool,
}

/// An opening on a wall plane: an accepted cluster, or a model opening.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Opening {
    /// The entity id it has in the completed semantic table (−1: not added).
    pub entity: i32,
    pub object_id: String,
    /// "Window" or "Door".
    pub class: String,
    pub wall: i32,
    pub wall_object_id: String,
    pub building: i32,
    pub building_object_id: String,
    /// "image" (found in the images) or "model".
    pub source: String,
    /// Distinct views with a candidate on it.
    pub views: usize,
    /// Rectangle on the wall plane `[u0, v0, u1, v1]`, metres from the wall's centroid.
    pub rect_m: [f64; 4],
    /// Corners in the city model's CRS (f64), counter-clockwise seen from the wall's front.
    pub polygon: Vec<[f64; 3]>,
}

/// Per building: the counts of the completeness report.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct BuildingCompleteness {
    pub building: i32,
    pub object_id: String,
    pub model_openings: usize,
    /// Model openings the images confirm (a candidate overlaps them in ≥ `m_view` views).
    pub confirmed: usize,
    /// Accepted image openings the model lacks.
    pub missing_in_model: usize,
    /// Model openings seen in ≥ `m_view` views with no candidate on them.
    pub unsupported: usize,
}

/// `completeness.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Completeness {
    pub buildings: Vec<BuildingCompleteness>,
    /// Openings the images show consistently but the model lacks.
    pub missing_in_model: Vec<Opening>,
    /// Model openings no image supports.
    pub unsupported: Vec<Opening>,
}

/// `summary.json` of the stage.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct OpeningsSummary {
    pub options: OpeningsOptions,
    pub views: usize,
    pub walls: usize,
    pub candidates: usize,
    pub clusters: usize,
    pub accepted: usize,
    pub confirmed: usize,
    pub missing_in_model: usize,
    pub unsupported: usize,
    /// Entities added to the semantic table (0: the run keeps the model's raycast).
    pub added: usize,
    pub warnings: Vec<String>,
    pub seconds: f64,
}

/// What the stage returns: the summary, the report, and — when openings were added — the
/// completed semantic table and mesh.
pub struct OpeningsOutput {
    pub summary: OpeningsSummary,
    pub completeness: Completeness,
    pub completed: Option<(Vec<Entity>, TriMesh)>,
    /// `completeness.city.json` (CityJSON 2.0).
    pub cityjson: serde_json::Value,
}

/// Per view: candidates, the model parts seen (part id → pixels) and the model parts that
/// a window/door mask lies on (part ids).
struct ViewScan {
    candidates: Vec<Candidate>,
    /// The view's masks carry prompt classes (features): its supports are evidence.
    judged: bool,
    seen: BTreeMap<i32, u64>,
    supports: BTreeSet<i32>,
}

fn pixels_of(m: &sam::SamMask) -> Vec<usize> {
    let mut px = Vec::new();
    // Validated by read_sam_json_sized.
    let _ = m.segmentation.for_each_pixel(|p| px.push(p));
    px
}

/// The `q`-quantile of a sorted slice (nearest rank).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Candidates and seen parts of one view.
fn scan_view(
    ins: &OpeningsInputs<'_>,
    frames: &BTreeMap<i32, WallFrame>,
    vi: usize,
    opts: &OpeningsOptions,
) -> Result<ViewScan, OpeningsError> {
    let view = &ins.views[vi];
    let cam = &view.camera;
    let (w, h) = (
        cam.intrinsics.width as usize,
        cam.intrinsics.height as usize,
    );
    let stem = view.stem();
    let ids = idmap::read_raycast(ins.raycast, &stem, w, h)?;
    let n = w * h;
    let (surface, part) = (&ids[n..2 * n], &ids[2 * n..3 * n]);
    let mut seen = BTreeMap::new();
    for &p in part {
        if p >= 0 {
            *seen.entry(p).or_insert(0u64) += 1;
        }
    }
    let mut scan = ViewScan {
        candidates: Vec::new(),
        judged: false,
        seen,
        supports: BTreeSet::new(),
    };
    let masks = match ins.sam.filter(|_| opts.cues.features()) {
        Some(sam_dir) => {
            let (judged, masks) = window_masks(ins, sam_dir, &stem, [h, w], opts)?;
            scan.judged = judged;
            masks
        }
        None => Vec::new(),
    };
    let geometry = ins.geometry.filter(|_| opts.cues.geometry());
    if masks.is_empty() && geometry.is_none() {
        return Ok(scan);
    }
    let city = idmap::read_depth(ins.raycast, &stem, w, h)?;
    let vm = ViewMaps {
        view,
        index: vi,
        surface,
        part,
        city: &city,
    };
    let scale = ins.alignment.scale;
    for (px, class, strong) in masks {
        if px.is_empty() {
            continue;
        }
        // On a model opening: it supports that opening (the image confirms the model).
        let mut parts: BTreeMap<i32, usize> = BTreeMap::new();
        for &p in &px {
            if part[p] >= 0 {
                *parts.entry(part[p]).or_insert(0) += 1;
            }
        }
        if let Some((&pt, &k)) = parts.iter().max_by_key(|(_, k)| **k)
            && k as f64 >= opts.part_share * px.len() as f64
        {
            scan.supports.insert(pt);
            continue;
        }
        let Some(wall) = dominant_wall(surface, &px, opts.min_wall_share) else {
            continue;
        };
        let Some(frame) = frames.get(&wall) else {
            continue;
        };
        let Some(rect) = plane_rect(&vm, frame, wall, &px, opts.trim) else {
            continue;
        };
        let [lo, hi] = opts.size_m;
        let ok = |x: f64| (lo * scale..=hi * scale).contains(&x);
        if !(ok(rect.width()) && ok(rect.height())) {
            continue;
        }
        scan.candidates.push(Candidate {
            view: vi,
            wall,
            rect,
            class,
            recess: false,
            strong,
        });
    }
    if let Some(g) = geometry {
        let (c, gs) = g.cache.median_depth(&stem, g.positions, &cam.pose)?;
        g.cache.check_size(&stem, (c.width, c.height), (w, h))?;
        scan.candidates
            .extend(recess::candidates(&vm, &gs, frames, opts, scale)?);
    }
    Ok(scan)
}

/// A window/door mask: its pixels, class and strength (strong: passed the quality rule).
type WindowMask = (Vec<usize>, i32, bool);

/// The pixels, class and strength of the view's masks that the masks stage dropped as
/// building and whose best prompt is a window or door prompt (module docs), and whether the
/// masks stage had prompt classes at all (features).
fn window_masks(
    ins: &OpeningsInputs<'_>,
    sam_dir: &Path,
    stem: &str,
    [h, w]: [usize; 2],
    opts: &OpeningsOptions,
) -> Result<(bool, Vec<WindowMask>), OpeningsError> {
    let dpath = maskfile::decisions_file(ins.masks, stem);
    let decisions = maskfile::read_decisions(&dpath)?;
    let judged = decisions.iter().any(|d| d.scores.contains_key("class"));
    let want: Vec<(usize, i32, bool)> = decisions
        .iter()
        .filter(|d| !d.kept && d.source_index >= 0 && d.rule != Rule::Area)
        .filter_map(|d| {
            let c = d.scores.get("class").copied()? as i32;
            let q = d.scores.get("predicted_iou").copied().unwrap_or(0.0);
            let strong = !matches!(d.rule, Rule::Quality | Rule::LowQualitySupport);
            ((c == crate::classes::WINDOW || c == crate::classes::DOOR)
                && (strong || q >= opts.support_floor))
                .then_some((d.source_index as usize, c, strong))
        })
        .collect();
    if want.is_empty() {
        return Ok((judged, Vec::new()));
    }
    let spath = sam_dir.join(format!("{stem}.json"));
    let list = sam::read_sam_json_sized(&spath, Some([h, w]))?;
    let masks = want
        .into_iter()
        .map(|(i, class, strong)| match list.get(i) {
            Some(m) => Ok((pixels_of(m), class, strong)),
            None => Err(OpeningsError::Invalid {
                path: dpath.clone(),
                why: format!(
                    "decision for mask {i}, but {} has {} masks (stale masks stage?)",
                    spath.display(),
                    list.len()
                ),
            }),
        })
        .collect::<Result<_, _>>()?;
    Ok((judged, masks))
}

/// A cluster of candidates on one wall.
struct Cluster {
    members: Vec<Candidate>,
    rect: Rect,
}

impl Cluster {
    fn views(&self) -> usize {
        self.members
            .iter()
            .map(|c| c.view)
            .collect::<BTreeSet<_>>()
            .len()
    }

    fn update(&mut self) {
        let mut r = [0.0; 4];
        for (k, x) in r.iter_mut().enumerate() {
            let mut v: Vec<f64> = self
                .members
                .iter()
                .filter(|c| c.strong)
                .map(|c| c.rect.0[k])
                .collect();
            *x = median(&mut v);
        }
        self.rect = Rect(r);
    }

    /// The majority class of the mask members (appearance tells a door from a window better
    /// than the recess's height above the wall's bottom), else of the recess members.
    fn class(&self) -> i32 {
        let masks = self.members.iter().any(|c| !c.recess);
        let voters: Vec<&Candidate> = self.members.iter().filter(|c| c.recess != masks).collect();
        let doors = voters
            .iter()
            .filter(|c| c.class == crate::classes::DOOR)
            .count();
        if 2 * doors > voters.len() {
            crate::classes::DOOR
        } else {
            crate::classes::WINDOW
        }
    }
}

/// The cluster a rectangle overlaps most with IoU ≥ `join_iou` (the first on ties).
fn best_cluster(clusters: &[Cluster], r: &Rect, join_iou: f64) -> Option<usize> {
    clusters
        .iter()
        .enumerate()
        .map(|(i, k)| (i, k.rect.iou(r)))
        .filter(|(_, x)| *x >= join_iou)
        .max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)))
        .map(|(i, _)| i)
}

/// Greedy clustering of one wall's candidates (module docs): the strong ones first, then the
/// weak ones join.
fn cluster(cands: &[Candidate], join_iou: f64) -> Vec<Cluster> {
    let mut out: Vec<Cluster> = Vec::new();
    for c in cands.iter().filter(|c| c.strong) {
        match best_cluster(&out, &c.rect, join_iou) {
            Some(i) => {
                out[i].members.push(*c);
                out[i].update();
            }
            None => out.push(Cluster {
                members: vec![*c],
                rect: c.rect,
            }),
        }
    }
    for c in cands.iter().filter(|c| !c.strong) {
        if let Some(i) = best_cluster(&out, &c.rect, join_iou) {
            out[i].members.push(*c);
        }
    }
    out
}

/// The stable object id of an image opening: SplitMix64 over the wall's object id and the
/// rectangle's georeferenced corners in centimetres.
fn opening_id(wall_object_id: &str, polygon: &[[f64; 3]]) -> String {
    let mut h = 0u64;
    for b in wall_object_id.bytes() {
        h = crate::hash::splitmix64(h ^ b as u64);
    }
    for p in polygon {
        for x in p {
            h = crate::hash::splitmix64(h ^ ((x * 100.0).round() as i64 as u64));
        }
    }
    format!("gs4city-opening-{h:016x}")
}

/// Runs the stage (module docs): candidates per view, clusters per wall, the completeness
/// report and, with `add: missing`, the completed table and mesh.
pub fn run(
    ins: &OpeningsInputs<'_>,
    opts: &OpeningsOptions,
) -> Result<OpeningsOutput, OpeningsError> {
    opts.validate()?;
    let t0 = Instant::now();
    let ents = ins.entities;
    let walls: Vec<i32> = ents
        .iter()
        .filter(|e| e.class == Class::WallSurface)
        .map(|e| e.id)
        .collect();
    let a = ins.alignment;
    let up = (a.apply(a.origin + DVec3::Z) - a.apply(a.origin))
        .try_normalize()
        .unwrap_or(DVec3::Z);
    let frames = wall_frames(ins.mesh, &walls, up, opts.max_tilt_cos);
    let bar = Bar::new("openings", ins.views.len() as u64, "views");
    let scans = (0..ins.views.len())
        .into_par_iter()
        .map(|vi| {
            let s = scan_view(ins, &frames, vi, opts);
            bar.inc(1);
            s
        })
        .collect::<Result<Vec<_>, _>>()?;
    bar.finish();
    // Unsupported needs mask evidence: window/door masks (features) that could have lain on
    // a model opening.
    let judged = scans.iter().any(|s| s.judged);
    // Per wall, candidates in view order.
    let mut by_wall: BTreeMap<i32, Vec<Candidate>> = BTreeMap::new();
    let mut n_cand = 0;
    for s in &scans {
        for c in &s.candidates {
            by_wall.entry(c.wall).or_default().push(*c);
            n_cand += 1;
        }
    }
    // Model openings (the part entities directly under a surface) with their mesh vertices.
    let opening_of = |p: i32| -> Option<i32> {
        let mut e = p;
        loop {
            let ent = ents.get(e as usize)?;
            let parent = ent.parent?;
            if ents.get(parent as usize)?.level == Level::Surface {
                return Some(e);
            }
            e = parent;
        }
    };
    let mut model_pts: BTreeMap<i32, Vec<DVec3>> = BTreeMap::new();
    for (f, l) in ins.mesh.labels.iter().enumerate() {
        if let Some(o) = (l.part >= 0).then(|| opening_of(l.part)).flatten() {
            let v = model_pts.entry(o).or_default();
            for &vi in &ins.mesh.faces[f] {
                let p = ins.mesh.vertices[vi as usize];
                v.push(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64));
            }
        }
    }
    let mut model_by_building: BTreeMap<i32, Vec<i32>> = BTreeMap::new();
    for &o in model_pts.keys() {
        model_by_building
            .entry(ents[o as usize].building)
            .or_default()
            .push(o);
    }
    let tol = opts.plane_tol_m * a.scale;
    // A model opening's rectangle on a wall plane, when it lies on that plane.
    let rect_on = |fr: &WallFrame, pts: &[DVec3]| -> Option<Rect> {
        let mean = pts.iter().map(|p| (*p - fr.c).dot(fr.n).abs()).sum::<f64>() / pts.len() as f64;
        (mean <= tol).then(|| {
            let mut r = Rect::empty();
            for p in pts {
                r.grow(fr.to_plane(*p));
            }
            r
        })
    };
    // Per model opening: views in which it is seen, and views whose masks support it.
    let mut seen_views: BTreeMap<i32, usize> = BTreeMap::new();
    let mut support_views: BTreeMap<i32, usize> = BTreeMap::new();
    for (vi, s) in scans.iter().enumerate() {
        let c = &ins.views[vi].camera.intrinsics;
        let min_px = (opts.seen_px_frac * c.width as f64 * c.height as f64).ceil() as u64;
        let mut here: BTreeMap<i32, u64> = BTreeMap::new();
        for (&p, &k) in &s.seen {
            if let Some(o) = opening_of(p) {
                *here.entry(o).or_insert(0) += k;
            }
        }
        for (o, k) in here {
            if k >= min_px.max(1) {
                *seen_views.entry(o).or_insert(0) += 1;
            }
        }
        let sup: BTreeSet<i32> = s.supports.iter().filter_map(|&p| opening_of(p)).collect();
        for o in sup {
            *support_views.entry(o).or_insert(0) += 1;
        }
    }
    let scale = a.scale;
    let corners_geo = |fr: &WallFrame, r: &Rect| -> Vec<[f64; 3]> {
        r.corners()
            .iter()
            .map(|uv| a.unapply(fr.to_scene(*uv)).to_array())
            .collect()
    };
    let name = |c: i32| {
        if c == crate::classes::DOOR {
            "Door"
        } else {
            "Window"
        }
    };
    let mut n_clusters = 0;
    let mut accepted = 0;
    let mut missing: Vec<(Opening, Rect)> = Vec::new();
    let mut unsupported = Vec::new();
    let mut per_building: BTreeMap<i32, BuildingCompleteness> = BTreeMap::new();
    let building_entry = |per: &mut BTreeMap<i32, BuildingCompleteness>, b: i32| {
        per.entry(b).or_insert_with(|| BuildingCompleteness {
            building: b,
            object_id: ents[b as usize].object_id.clone(),
            ..Default::default()
        });
    };
    let mut confirmed_total = 0;
    for (&o, pts) in &model_pts {
        let oe = &ents[o as usize];
        building_entry(&mut per_building, oe.building);
        let bc = per_building.get_mut(&oe.building).expect("inserted");
        bc.model_openings += 1;
        let sup = support_views.get(&o).copied().unwrap_or(0);
        if sup >= opts.m_view {
            bc.confirmed += 1;
            confirmed_total += 1;
        } else if judged && sup == 0 && seen_views.get(&o).copied().unwrap_or(0) >= opts.m_view {
            bc.unsupported += 1;
            let wall = oe.parent.unwrap_or(-1);
            let went = &ents[wall as usize];
            // Its rectangle on its own wall's plane when that wall has a frame, else on the
            // plane of the nearest framed wall of its building it lies on.
            let on = frames
                .get(&wall)
                .and_then(|fr| rect_on(fr, pts).map(|r| (wall, fr, r)))
                .or_else(|| {
                    frames
                        .iter()
                        .filter(|(w, _)| ents[**w as usize].building == oe.building)
                        .find_map(|(w, fr)| rect_on(fr, pts).map(|r| (*w, fr, r)))
                });
            let (rect_m, polygon, wall_oid) = match on {
                Some((w, fr, r)) => (
                    r.0.map(|x| x / scale),
                    corners_geo(fr, &r),
                    ents[w as usize].object_id.clone(),
                ),
                None => (
                    [0.0; 4],
                    pts.iter().map(|p| a.unapply(*p).to_array()).collect(),
                    went.object_id.clone(),
                ),
            };
            unsupported.push(Opening {
                entity: o,
                object_id: oe.object_id.clone(),
                class: if oe.class.is_door() { "Door" } else { "Window" }.into(),
                wall,
                wall_object_id: wall_oid,
                building: oe.building,
                building_object_id: ents[oe.building as usize].object_id.clone(),
                source: "model".into(),
                views: 0,
                rect_m,
                polygon,
            });
        }
    }
    for (&wall, fr) in &frames {
        let went = &ents[wall as usize];
        let bent = &ents[went.building as usize];
        let cands = by_wall.get(&wall).map(Vec::as_slice).unwrap_or(&[]);
        if cands.is_empty() {
            continue;
        }
        building_entry(&mut per_building, went.building);
        let clusters = cluster(cands, opts.join_iou);
        n_clusters += clusters.len();
        // The model's openings on this wall's plane.
        let model: Vec<Rect> = model_by_building
            .get(&went.building)
            .map(Vec::as_slice)
            .unwrap_or(&[])
            .iter()
            .filter_map(|o| rect_on(fr, &model_pts[o]))
            .collect();
        // Accepted clusters, most views first; one opening per place.
        let mut acc: Vec<&Cluster> = clusters
            .iter()
            .filter(|k| k.views() >= opts.m_view)
            .collect();
        accepted += acc.len();
        acc.sort_by_key(|k| std::cmp::Reverse(k.views()));
        let mut placed: Vec<Rect> = Vec::new();
        for k in acc {
            let rect = k.rect.intersect(&fr.extent);
            if rect.area() <= 0.0
                || model
                    .iter()
                    .any(|r| rect.overlap_min(r) >= opts.match_overlap)
                || placed
                    .iter()
                    .any(|r| rect.overlap_min(r) >= opts.match_overlap)
            {
                continue;
            }
            placed.push(rect);
            per_building
                .get_mut(&went.building)
                .expect("inserted")
                .missing_in_model += 1;
            let polygon = corners_geo(fr, &rect);
            missing.push((
                Opening {
                    entity: -1,
                    object_id: opening_id(&went.object_id, &polygon),
                    class: name(k.class()).into(),
                    wall,
                    wall_object_id: went.object_id.clone(),
                    building: went.building,
                    building_object_id: bent.object_id.clone(),
                    source: "image".into(),
                    views: k.views(),
                    rect_m: rect.0.map(|x| x / scale),
                    polygon,
                },
                rect,
            ));
        }
    }
    // Deterministic order: wall, then the rectangle's lower-left corner.
    missing.sort_by(|x, y| {
        x.0.wall
            .cmp(&y.0.wall)
            .then(x.1.0[1].total_cmp(&y.1.0[1]))
            .then(x.1.0[0].total_cmp(&y.1.0[0]))
    });
    let completed = if opts.add == Add::Missing && !missing.is_empty() {
        let mut e2 = ents.to_vec();
        let mut mesh = ins.mesh.clone();
        for (o, rect) in missing.iter_mut() {
            let id = e2.len() as i32;
            o.entity = id;
            let mut attributes = BTreeMap::new();
            attributes.insert("views".to_string(), serde_json::json!(o.views));
            attributes.insert(
                "width".to_string(),
                serde_json::json!((o.rect_m[2] - o.rect_m[0]).abs()),
            );
            attributes.insert(
                "height".to_string(),
                serde_json::json!((o.rect_m[3] - o.rect_m[1]).abs()),
            );
            e2.push(Entity {
                id,
                object_id: o.object_id.clone(),
                class: if o.class == "Door" {
                    Class::Door
                } else {
                    Class::Window
                },
                level: Level::Part,
                parent: Some(o.wall),
                building: o.building,
                source: "image".into(),
                lod: None,
                attributes,
            });
            let fr = &frames[&o.wall];
            let base = mesh.vertices.len() as u32;
            for uv in rect.corners() {
                let p = fr.to_scene(uv);
                mesh.vertices.push([p.x as f32, p.y as f32, p.z as f32]);
            }
            let label = FaceLabel {
                feature: fr.feature,
                surface: o.wall,
                part: id,
            };
            mesh.faces.push([base, base + 1, base + 2]);
            mesh.faces.push([base, base + 2, base + 3]);
            mesh.labels.extend([label, label]);
        }
        Some((e2, mesh))
    } else {
        None
    };
    let missing: Vec<Opening> = missing.into_iter().map(|(o, _)| o).collect();
    let completeness = Completeness {
        buildings: per_building.into_values().collect(),
        missing_in_model: missing,
        unsupported,
    };
    let cityjson = completeness_cityjson(&completeness, ins.srs_name.clone());
    // Loud only where the stage was needed: a model without openings that got none.
    let mut warnings = Vec::new();
    if model_pts.is_empty() && completeness.missing_in_model.is_empty() {
        warnings.push(format!(
            "openings: the model has no windows or doors and the images gave {n_cand} candidates ({}), none seen in {} views",
            cue_words(ins, opts),
            opts.m_view
        ));
    }
    if !model_pts.is_empty() && !judged {
        warnings.push(format!(
            "openings: the model's {} openings were not judged (unsupported needs SAM masks with features; {})",
            model_pts.len(),
            cue_words(ins, opts)
        ));
    }
    let summary = OpeningsSummary {
        options: *opts,
        views: ins.views.len(),
        walls: frames.len(),
        candidates: n_cand,
        clusters: n_clusters,
        accepted,
        confirmed: confirmed_total,
        missing_in_model: completeness.missing_in_model.len(),
        unsupported: completeness.unsupported.len(),
        added: completed.as_ref().map_or(0, |(e, _)| e.len() - ents.len()),
        warnings,
        seconds: t0.elapsed().as_secs_f64(),
    };
    Ok(OpeningsOutput {
        summary,
        completeness,
        completed,
        cityjson,
    })
}

/// Which cues ran, in words (the stage's warnings).
fn cue_words(ins: &OpeningsInputs<'_>, opts: &OpeningsOptions) -> String {
    let f = match (opts.cues.features(), ins.sam.is_some()) {
        (false, _) => "features off",
        (true, false) => "no SAM lists (mask-free source)",
        (true, true) => "window/door masks",
    };
    let g = match (opts.cues.geometry(), ins.geometry.is_some()) {
        (false, _) => "geometry off",
        (true, false) => "no cache for the geometric cue",
        (true, true) => "recessed regions",
    };
    format!("{f}; {g}")
}

/// A wall's findings with what each is (`missing_in_model` / `unsupported`).
type Findings<'a> = Vec<(&'a Opening, &'a str)>;

/// `completeness.city.json`: per building with findings, a CityJSON Building whose geometry
/// holds its walls' openings of the report as Window/Door semantic surfaces under a
/// WallSurface of the wall's object id (attributes `source` = image|model and `completeness`
/// = missing_in_model|unsupported); each wall is represented by the hull rectangle of its
/// findings on its plane (the editor has the wall itself in its model).
pub fn completeness_cityjson(c: &Completeness, srs_name: Option<String>) -> serde_json::Value {
    let mut objects: Vec<CityObject> = Vec::new();
    let mut polygons: Vec<Polygon> = Vec::new();
    let all: Vec<(&Opening, &str)> = c
        .missing_in_model
        .iter()
        .map(|o| (o, "missing_in_model"))
        .chain(c.unsupported.iter().map(|o| (o, "unsupported")))
        .collect();
    let mut by_building: BTreeMap<&str, BTreeMap<&str, Findings<'_>>> = BTreeMap::new();
    for (o, what) in &all {
        by_building
            .entry(&o.building_object_id)
            .or_default()
            .entry(&o.wall_object_id)
            .or_default()
            .push((o, what));
    }
    let obj = |class, id: &str, parent, attributes| CityObject {
        class,
        object_id: id.to_string(),
        has_gml_id: true,
        parent,
        attributes,
        line: 0,
        offset: 0,
        lod_used: Some(3),
    };
    let poly = |pts: Vec<DVec3>, owner: usize, ordinal: usize| Polygon {
        id: None,
        exterior: Ring {
            id: None,
            points: pts,
        },
        interiors: Vec::new(),
        owner: Some(owner),
        lod: Some(3),
        reversed: false,
        line: 0,
        ordinal,
    };
    for (b, walls) in by_building {
        let bi = objects.len();
        objects.push(obj(Class::Building, b, None, BTreeMap::new()));
        for (w, list) in walls {
            let wi = objects.len();
            let mut wattr = BTreeMap::new();
            wattr.insert("source".to_string(), serde_json::json!("model"));
            objects.push(obj(Class::WallSurface, w, Some(bi), wattr));
            // The wall: the hull of its findings' corners (a placeholder ring on its plane).
            let pts: Vec<DVec3> = list
                .iter()
                .flat_map(|(o, _)| o.polygon.iter().map(|p| DVec3::from_array(*p)))
                .collect();
            if let Some(h) = hull_on_plane(&pts, list[0].0) {
                let n = polygons.len();
                polygons.push(poly(h, wi, n));
            }
            for (o, what) in list {
                let oi = objects.len();
                let mut attr = BTreeMap::new();
                attr.insert("source".to_string(), serde_json::json!(o.source));
                attr.insert("completeness".to_string(), serde_json::json!(what));
                attr.insert("views".to_string(), serde_json::json!(o.views));
                let class = if o.class == "Door" {
                    Class::Door
                } else {
                    Class::Window
                };
                objects.push(obj(class, &o.object_id, Some(wi), attr));
                let n = polygons.len();
                polygons.push(poly(
                    o.polygon.iter().map(|p| DVec3::from_array(*p)).collect(),
                    oi,
                    n,
                ));
            }
        }
    }
    let model = CityModel {
        path: PathBuf::from("completeness.city.json"),
        version: Version::V3,
        srs_name,
        objects,
        polygons,
        textures: Vec::new(),
        materials: Vec::new(),
        stats: ReadStats::default(),
        warnings: Vec::new(),
    };
    crate::cityjson::to_json(&model)
}

/// The rectangle on the opening's wall plane that bounds `pts`, 0.1 of its size larger on
/// each side (so the wall ring contains its openings), as four georeferenced corners.
fn hull_on_plane(pts: &[DVec3], first: &Opening) -> Option<Vec<DVec3>> {
    let p = &first.polygon;
    if p.len() != 4 {
        return None;
    }
    let (p0, p1, p3) = (
        DVec3::from_array(p[0]),
        DVec3::from_array(p[1]),
        DVec3::from_array(p[3]),
    );
    let u = (p1 - p0).try_normalize()?;
    let v = (p3 - p0).try_normalize()?;
    let mut r = Rect::empty();
    for q in pts {
        let d = *q - p0;
        r.grow([d.dot(u), d.dot(v)]);
    }
    let m = 0.1 * r.width().max(r.height()).max(1.0);
    let r = Rect([r.0[0] - m, r.0[1] - m, r.0[2] + m, r.0[3] + m]);
    Some(
        r.corners()
            .iter()
            .map(|c| p0 + u * c[0] + v * c[1])
            .collect(),
    )
}

/// Writes the stage's files into `dir`: `completeness.json`, `completeness.city.json` and, when openings were added,
/// `semantics.json` + `mesh.ply` of the completed model.
pub fn write(out: &OpeningsOutput, dir: &Path) -> Result<(), OpeningsError> {
    fsutil::write_json(&dir.join("completeness.json"), &out.completeness)?;
    fsutil::write_json(&dir.join("completeness.city.json"), &out.cityjson)?;
    if let Some((e, m)) = &out.completed {
        semantics::write(&dir.join("semantics.json"), e)?;
        m.write_ply(&dir.join("mesh.ply"))?;
    }
    Ok(())
}

/// The raycast surface (a wall id ≥ 0) that most of the pixels `px` hit, when it holds at
/// least `min_share` of them (ties: the larger id); `None` otherwise. One rule for the mask
/// candidates and the recess cue.
fn dominant_wall(surface: &[i32], px: &[usize], min_share: f64) -> Option<i32> {
    let mut count: BTreeMap<i32, usize> = BTreeMap::new();
    for &p in px {
        *count.entry(surface[p]).or_insert(0) += 1;
    }
    let (&wall, &k) = count
        .iter()
        .filter(|(s, _)| **s >= 0)
        .max_by_key(|(_, k)| **k)?;
    ((k as f64) >= min_share * px.len() as f64).then_some(wall)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cand(view: usize, r: [f64; 4], strong: bool) -> Candidate {
        Candidate {
            view,
            wall: 0,
            rect: Rect(r),
            class: crate::classes::WINDOW,
            recess: false,
            strong,
        }
    }

    #[test]
    fn clusters_join_by_iou_and_weak_candidates_never_found_one() {
        let c = [
            cand(0, [0.0, 0.0, 1.0, 1.0], true),
            cand(1, [0.1, 0.0, 1.1, 1.0], true),
            // Another window 2 m to the right.
            cand(1, [2.0, 0.0, 3.0, 1.0], true),
            cand(2, [0.0, 0.1, 1.0, 1.1], false),
            // A weak candidate alone: no cluster.
            cand(3, [5.0, 0.0, 6.0, 1.0], false),
        ];
        let k = cluster(&c, 0.5);
        assert_eq!(k.len(), 2);
        assert_eq!(k[0].views(), 3);
        assert_eq!(k[1].views(), 1);
        // The rectangle: medians of the strong members only ([0, 0, 1, 1] and [0.1, 0, 1.1, 1]).
        assert!((k[0].rect.0[0] - 0.05).abs() < 1e-12 && (k[0].rect.0[3] - 1.0).abs() < 1e-12);
    }

    #[test]
    fn mask_members_decide_a_clusters_class_over_recess_members() {
        let door = |view, recess| Candidate {
            class: crate::classes::DOOR,
            recess,
            ..cand(view, [0.0, 0.0, 1.0, 2.0], true)
        };
        let window = |view, recess| Candidate {
            recess,
            ..cand(view, [0.0, 0.0, 1.0, 2.0], true)
        };
        // Three recess windows and one door mask: a door.
        let k = cluster(
            &[
                window(0, true),
                window(1, true),
                window(2, true),
                door(3, false),
            ],
            0.5,
        );
        assert_eq!(k.len(), 1);
        assert_eq!(k[0].class(), crate::classes::DOOR);
        // Recess members alone: their majority.
        let k = cluster(&[window(0, true), door(1, true), door(2, true)], 0.5);
        assert_eq!(k[0].class(), crate::classes::DOOR);
        let k = cluster(&[window(0, true), window(1, true), door(2, true)], 0.5);
        assert_eq!(k[0].class(), crate::classes::WINDOW);
    }

    #[test]
    fn opening_ids_are_stable_and_differ_by_place() {
        let p = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]];
        let q = [[1.0, 2.0, 3.0], [4.0, 5.2, 6.0]];
        assert_eq!(opening_id("w", &p), opening_id("w", &p));
        assert_ne!(opening_id("w", &p), opening_id("w", &q));
        assert_ne!(opening_id("w", &p), opening_id("v", &p));
        assert!(opening_id("w", &p).starts_with("gs4city-opening-"));
    }
}
