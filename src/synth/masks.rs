//! **Simulated** SAM masks and **simulated** CLIP features for the synthetic benchmark.
//!
//! Nothing here runs Segment-Anything or CLIP (no weights are available): masks are derived
//! from ground-truth instance/class maps by a documented noise model ([`MaskNoise`]), and
//! "CLIP" features are class prototypes plus Gaussian noise ([`FeatureNoise`]). The mask
//! files are written in SAM's own JSON format, which has no room for provenance, so a
//! sidecar ([`PROVENANCE_FILE`], built by [`provenance`]) says that they are simulated, and
//! [`write_simulation_truth`] records, per mask, the instances it came from. Everything is
//! seeded: the same inputs and seed give identical output on any number of threads (each
//! instance, pair and mask draws from its own RNG, keyed by the seed and its ids).
//!
//! The noise model, in order (`docs/sam.md` has the details):
//! 1. **missed small objects**: an instance with fewer than `small_area_px` pixels is dropped
//!    with probability `miss_small_prob`;
//! 2. **under-segmentation**: instances within `merge_gap_px` of each other (a window and
//!    its wall, neighbouring windows) are merged with probability `merge_prob` per pair, at
//!    most `merge_max_instances` per mask;
//! 3. **over-segmentation**: a mask of at least `split_min_area_px` is cut with probability
//!    `split_prob` into 2..=`split_max_parts` pieces by random lines through the centroid;
//! 4. **boundary error**: with probability `boundary_prob` a mask is eroded or dilated
//!    (OpenCV, elliptical kernel) by a radius in `boundary_radius_px`;
//! 5. **false positives**: on every instance of a class in `false_positive_classes` (façade
//!    walls) a Poisson(`false_positive_rate`) number of elliptical blobs, clipped to it;
//! 6. masks below `min_area_px` are dropped; scores fall with the damage
//!    `d = 1 − max_i IoU(mask, GT instance i)`: `predicted_iou = 1 − iou_slope·d + N(0,
//!    iou_jitter²)` and `stability_score = 1 − stability_slope·d + N(0, stability_jitter²)`,
//!    clamped to `[0, 1]` and rounded to 6 decimals.
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use ndarray::{Array2, ArrayView2, s};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

pub use super::features::{
    FeatureNoise, PROMPTS, class_prototype, simulate_features, simulate_prompts,
};
use crate::classes;
use crate::fsutil;
use crate::imageio::{self, Morph};
use crate::sam::{Rle, SamError, SamMask};

/// The dimension of the simulated CLIP features (as CLIP ViT-B/16 and ViT-B/32).
pub const FEATURE_DIM: usize = 512;

/// Name of the provenance sidecar in a scene's `masks/` folder.
pub const PROVENANCE_FILE: &str = "README.json";

/// The noise model of [`simulate_masks`]. `MaskNoise::none()` turns every effect off (masks
/// equal the ground-truth instances, scores are 1); `Default` is a moderately noisy SAM.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MaskNoise {
    /// Probability that an instance smaller than `small_area_px` is missed (no mask).
    pub miss_small_prob: f64,
    /// Area threshold (pixels) of "small" instances for `miss_small_prob`.
    pub small_area_px: usize,
    /// Probability that a pair of neighbouring instances is merged into one mask.
    pub merge_prob: f64,
    /// Two instances are neighbours when a pixel of one lies within this many pixels of the
    /// other, straight right or down (1 = touching).
    pub merge_gap_px: usize,
    /// At most this many instances end up in one merged mask.
    pub merge_max_instances: usize,
    /// Probability that a mask is split (over-segmentation).
    pub split_prob: f64,
    /// Masks smaller than this (pixels) are never split.
    pub split_min_area_px: usize,
    /// A split mask becomes 2..=`split_max_parts` pieces (uniform), each cut being a random
    /// line through the centroid of the largest piece so far.
    pub split_max_parts: usize,
    /// Probability that a mask's boundary is eroded or dilated.
    pub boundary_prob: f64,
    /// Radius range `[min, max]` (pixels, inclusive, uniform) of the elliptical kernel.
    pub boundary_radius_px: [usize; 2],
    /// Given a boundary error, the probability that it is a dilation (else an erosion).
    pub dilate_prob: f64,
    /// Expected number of false-positive blobs per instance of `false_positive_classes`
    /// (Poisson).
    pub false_positive_rate: f64,
    /// Class ids whose instances receive false-positive blobs (default: wall).
    pub false_positive_classes: Vec<i32>,
    /// Semi-axis range `[min, max]` (pixels, inclusive, uniform, drawn per axis) of a blob.
    pub false_positive_radius_px: [usize; 2],
    /// Masks smaller than this (pixels) after all effects are dropped (at least 1: SAM emits
    /// no empty masks).
    pub min_area_px: usize,
    /// `predicted_iou = 1 − iou_slope · damage + N(0, iou_jitter²)`, clamped to [0, 1].
    pub iou_slope: f64,
    /// Standard deviation of the `predicted_iou` noise.
    pub iou_jitter: f64,
    /// `stability_score = 1 − stability_slope · damage + N(0, stability_jitter²)`, clamped.
    pub stability_slope: f64,
    /// Standard deviation of the `stability_score` noise.
    pub stability_jitter: f64,
}

impl Default for MaskNoise {
    fn default() -> Self {
        MaskNoise {
            miss_small_prob: 0.5,
            small_area_px: 64,
            merge_prob: 0.05,
            merge_gap_px: 3,
            merge_max_instances: 3,
            split_prob: 0.1,
            split_min_area_px: 400,
            split_max_parts: 3,
            boundary_prob: 0.7,
            boundary_radius_px: [1, 2],
            dilate_prob: 0.5,
            false_positive_rate: 0.3,
            false_positive_classes: vec![classes::WALL],
            false_positive_radius_px: [3, 10],
            min_area_px: 1,
            iou_slope: 1.0,
            iou_jitter: 0.02,
            stability_slope: 0.5,
            stability_jitter: 0.01,
        }
    }
}

impl MaskNoise {
    /// Every effect off: one exact mask per ground-truth instance, scores 1.
    pub fn none() -> Self {
        MaskNoise {
            miss_small_prob: 0.0,
            merge_prob: 0.0,
            split_prob: 0.0,
            boundary_prob: 0.0,
            false_positive_rate: 0.0,
            iou_jitter: 0.0,
            stability_jitter: 0.0,
            ..MaskNoise::default()
        }
    }
}

/// How a simulated mask relates to the ground truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MaskKind {
    /// One instance (possibly with a boundary error).
    Instance,
    /// Several instances merged (under-segmentation).
    Merged,
    /// One piece of a split instance or merged group (over-segmentation).
    Split,
    /// A blob on a façade that matches no instance.
    FalsePositive,
}

/// A simulated SAM mask with the ground truth it was made from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimulatedMask {
    /// The mask as SAM's automatic generator would write it.
    pub mask: SamMask,
    /// The ground-truth instance ids it was made from, ascending (empty for false positives).
    pub source_instances: Vec<i32>,
    /// Ground-truth class: the majority class of the source instances' pixels (for a false
    /// positive: the class of the instance it lies on).
    pub class: i32,
    /// Which effect made it.
    pub kind: MaskKind,
    /// `1 − max_i IoU(mask, GT instance i)` (0 = exact).
    pub damage: f64,
}

/// The provenance sidecar of simulated masks/features (written as [`PROVENANCE_FILE`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimulationProvenance {
    /// Always `true`: these are not outputs of SAM or CLIP.
    pub simulated: bool,
    /// A plain sentence saying what the files are.
    pub what: String,
    /// The code that made them.
    pub generator: String,
    /// The mask file format.
    pub format: String,
    /// The base seed.
    pub seed: u64,
    /// The mask noise model used.
    pub mask_noise: MaskNoise,
    /// The feature noise model used, if features were simulated.
    pub feature_noise: Option<FeatureNoise>,
}

/// The provenance object of simulated masks (and features) made with `seed`.
pub fn provenance(
    mask_noise: &MaskNoise,
    feature_noise: Option<&FeatureNoise>,
    seed: u64,
) -> SimulationProvenance {
    SimulationProvenance {
        simulated: true,
        what: "SIMULATED Segment-Anything masks (and simulated CLIP features) derived from \
               ground-truth instance maps by a noise model; no SAM or CLIP model was run"
            .into(),
        generator: format!("gs4city {} synth::masks", env!("CARGO_PKG_VERSION")),
        format: "SAM automatic mask generator JSON (output_mode=coco_rle), one file per view; \
                 features: float32 N×512 .npy, one row per mask in file order"
            .into(),
        seed,
        mask_noise: mask_noise.clone(),
        feature_noise: feature_noise.cloned(),
    }
}

/// Writes the provenance sidecar `dir/README.json`, atomically.
pub fn write_provenance(dir: &Path, prov: &SimulationProvenance) -> Result<(), SamError> {
    fsutil::write_json(&dir.join(PROVENANCE_FILE), prov)?;
    Ok(())
}

/// One row of the per-view ground-truth sidecar of simulated masks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimulationTruth {
    /// Index of the mask in the SAM JSON list.
    pub index: usize,
    pub source_instances: Vec<i32>,
    pub class: i32,
    pub kind: MaskKind,
    pub damage: f64,
}

/// Writes what the simulation knows about each mask (sources, class, kind, damage), in the
/// order of the SAM JSON list, as a JSON list, atomically.
pub fn write_simulation_truth(path: &Path, masks: &[SimulatedMask]) -> Result<(), SamError> {
    let rows: Vec<SimulationTruth> = masks
        .iter()
        .enumerate()
        .map(|(index, m)| SimulationTruth {
            index,
            source_instances: m.source_instances.clone(),
            class: m.class,
            kind: m.kind,
            damage: m.damage,
        })
        .collect();
    fsutil::write_json(path, &rows)?;
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Seeding: every random decision has its own RNG keyed by (seed, purpose, ids).

const TAG_MISS: u64 = 1;
const TAG_MERGE: u64 = 2;
const TAG_SPLIT: u64 = 3;
const TAG_BOUNDARY: u64 = 4;
const TAG_FP: u64 = 5;
const TAG_SCORE: u64 = 6;
pub(super) const TAG_PROTO: u64 = 7;
pub(super) const TAG_BUILDING: u64 = 8;
pub(super) const TAG_FEATURE: u64 = 9;
pub(super) const TAG_PROMPT: u64 = 10;

use crate::hash::splitmix64 as splitmix;

pub(super) fn rng_for(seed: u64, tag: u64, ids: &[u64]) -> ChaCha8Rng {
    let mut h = splitmix(seed ^ splitmix(tag));
    for &i in ids {
        h = splitmix(h ^ i);
    }
    ChaCha8Rng::seed_from_u64(h)
}

pub(super) fn id_key(id: i32) -> u64 {
    id as u32 as u64
}

/// A standard normal sample (Box–Muller).
pub(super) fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    let u1 = 1.0 - rng.random::<f64>(); // (0, 1]
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// A Poisson sample (Knuth; fine for the small rates used here).
fn poisson(rng: &mut ChaCha8Rng, lambda: f64) -> usize {
    if lambda <= 0.0 {
        return 0;
    }
    let l = (-lambda).exp();
    let (mut k, mut p) = (0usize, 1.0f64);
    loop {
        p *= rng.random::<f64>();
        if p <= l || k >= 1000 {
            return k;
        }
        k += 1;
    }
}

fn range_incl(rng: &mut ChaCha8Rng, r: [usize; 2]) -> usize {
    let (a, b) = (r[0].min(r[1]), r[0].max(r[1]));
    rng.random_range(a..=b)
}

// ---------------------------------------------------------------------------------------
// Masks as windows of the image.

/// A binary mask that is zero outside the window at `(y0, x0)`.
#[derive(Debug, Clone)]
struct Region {
    y0: usize,
    x0: usize,
    m: Array2<bool>,
}

impl Region {
    fn area(&self) -> usize {
        self.m.iter().filter(|&&v| v).count()
    }

    fn pixels(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.m
            .indexed_iter()
            .filter(|(_, v)| **v)
            .map(|((y, x), _)| (self.y0 + y, self.x0 + x))
    }

    /// The union of two regions.
    fn union(&self, o: &Region) -> Region {
        let (ah, aw) = self.m.dim();
        let (bh, bw) = o.m.dim();
        let y0 = self.y0.min(o.y0);
        let x0 = self.x0.min(o.x0);
        let y1 = (self.y0 + ah).max(o.y0 + bh);
        let x1 = (self.x0 + aw).max(o.x0 + bw);
        let mut m = Array2::from_elem((y1 - y0, x1 - x0), false);
        for r in [self, o] {
            let (h, w) = r.m.dim();
            let (oy, ox) = (r.y0 - y0, r.x0 - x0);
            m.slice_mut(s![oy..oy + h, ox..ox + w])
                .zip_mut_with(&r.m, |a, &b| *a |= b);
        }
        Region { y0, x0, m }
    }

    /// The same mask in a window grown by `r` on every side (clipped to `h×w`).
    fn padded(&self, r: usize, h: usize, w: usize) -> Region {
        let (rh, rw) = self.m.dim();
        let y0 = self.y0.saturating_sub(r);
        let x0 = self.x0.saturating_sub(r);
        let y1 = (self.y0 + rh + r).min(h);
        let x1 = (self.x0 + rw + r).min(w);
        let mut m = Array2::from_elem((y1 - y0, x1 - x0), false);
        let (oy, ox) = (self.y0 - y0, self.x0 - x0);
        m.slice_mut(s![oy..oy + rh, ox..ox + rw]).assign(&self.m);
        Region { y0, x0, m }
    }

    /// Shrinks the window to the set pixels; `None` when there are none.
    fn tight(self) -> Option<Region> {
        let (mut ya, mut yb, mut xa, mut xb) = (usize::MAX, 0, usize::MAX, 0);
        for ((y, x), &v) in self.m.indexed_iter() {
            if v {
                ya = ya.min(y);
                yb = yb.max(y);
                xa = xa.min(x);
                xb = xb.max(x);
            }
        }
        if ya == usize::MAX {
            return None;
        }
        Some(Region {
            y0: self.y0 + ya,
            x0: self.x0 + xa,
            m: self.m.slice(s![ya..=yb, xa..=xb]).to_owned(),
        })
    }

    /// Cuts by a random line through the centroid; `None` if one side would be empty.
    fn split(&self, rng: &mut ChaCha8Rng) -> Option<(Region, Region)> {
        let (mut sy, mut sx, mut n) = (0.0f64, 0.0f64, 0usize);
        for (y, x) in self.pixels() {
            sy += y as f64;
            sx += x as f64;
            n += 1;
        }
        if n < 2 {
            return None;
        }
        let (cy, cx) = (sy / n as f64, sx / n as f64);
        let theta = rng.random_range(0.0..std::f64::consts::PI);
        let (ny, nx) = theta.sin_cos();
        let side = |y: usize, x: usize| {
            ((self.y0 + y) as f64 - cy) * ny + ((self.x0 + x) as f64 - cx) * nx >= 0.0
        };
        let a = Array2::from_shape_fn(self.m.dim(), |(y, x)| self.m[[y, x]] && side(y, x));
        let b = Array2::from_shape_fn(self.m.dim(), |(y, x)| self.m[[y, x]] && !side(y, x));
        let a = Region { m: a, ..*self }.tight()?;
        let b = Region { m: b, ..*self }.tight()?;
        Some((a, b))
    }
}

/// Per-instance statistics from one pass over the maps.
#[derive(Debug, Clone)]
struct Inst {
    y0: usize,
    x0: usize,
    y1: usize,
    x1: usize,
    area: usize,
    class_px: BTreeMap<i32, usize>,
}

impl Inst {
    fn majority_class(&self) -> i32 {
        majority(&self.class_px)
    }
}

/// The class with the most pixels (ties: the smaller id); −1 when empty.
fn majority(px: &BTreeMap<i32, usize>) -> i32 {
    let mut best = (classes::NONE, 0usize);
    for (&c, &n) in px {
        if n > best.1 {
            best = (c, n);
        }
    }
    best.0
}

fn instance_stats(instance: ArrayView2<i32>, class: ArrayView2<i32>) -> BTreeMap<i32, Inst> {
    let mut out: BTreeMap<i32, Inst> = BTreeMap::new();
    for ((y, x), &id) in instance.indexed_iter() {
        if id < 0 {
            continue;
        }
        let e = out.entry(id).or_insert(Inst {
            y0: y,
            x0: x,
            y1: y,
            x1: x,
            area: 0,
            class_px: BTreeMap::new(),
        });
        e.y0 = e.y0.min(y);
        e.x0 = e.x0.min(x);
        e.y1 = e.y1.max(y);
        e.x1 = e.x1.max(x);
        e.area += 1;
        *e.class_px.entry(class[[y, x]]).or_insert(0) += 1;
    }
    out
}

fn instance_region(instance: ArrayView2<i32>, id: i32, st: &Inst) -> Region {
    let win = instance.slice(s![st.y0..=st.y1, st.x0..=st.x1]);
    Region {
        y0: st.y0,
        x0: st.x0,
        m: win.map(|&v| v == id),
    }
}

/// Pairs `(a, b)`, `a < b`, of kept instances within `gap` pixels straight right or down.
fn neighbour_pairs(
    instance: ArrayView2<i32>,
    kept: &BTreeSet<i32>,
    gap: usize,
) -> BTreeSet<(i32, i32)> {
    let (h, w) = instance.dim();
    let mut pairs = BTreeSet::new();
    for y in 0..h {
        for x in 0..w {
            let a = instance[[y, x]];
            if a < 0 || !kept.contains(&a) {
                continue;
            }
            for k in 1..=gap {
                for (yy, xx) in [(y, x + k), (y + k, x)] {
                    if yy < h && xx < w {
                        let b = instance[[yy, xx]];
                        if b >= 0 && b != a && kept.contains(&b) {
                            pairs.insert((a.min(b), a.max(b)));
                        }
                    }
                }
            }
        }
    }
    pairs
}

fn find(parent: &mut BTreeMap<i32, i32>, a: i32) -> i32 {
    let p = parent[&a];
    if p == a {
        return a;
    }
    let r = find(parent, p);
    parent.insert(a, r);
    r
}

/// A mask before it becomes a [`SimulatedMask`].
struct Piece {
    region: Region,
    sources: Vec<i32>,
    class: i32,
    kind: MaskKind,
    /// RNG key of the piece (stable across thread counts).
    key: [u64; 2],
}

/// Simulates SAM's automatic masks for one view from ground-truth `instance` and `class`
/// maps (`H×W`, −1 = none) with the noise model `cfg` (module docs) and `seed`. The result is
/// sorted by (kind, source instances, bbox, RLE) and is the same for any thread count.
///
/// # Panics
/// If the maps differ in shape, or if OpenCV fails on a morphology call.
pub fn simulate_masks(
    instance: ArrayView2<i32>,
    class: ArrayView2<i32>,
    cfg: &MaskNoise,
    seed: u64,
) -> Vec<SimulatedMask> {
    assert_eq!(
        instance.dim(),
        class.dim(),
        "simulate_masks: instance and class maps differ in shape"
    );
    let (h, w) = instance.dim();
    let stats = instance_stats(instance, class);

    // 1. Missed small objects.
    let kept: BTreeSet<i32> = stats
        .iter()
        .filter(|(id, st)| {
            !(st.area < cfg.small_area_px
                && cfg.miss_small_prob > 0.0
                && rng_for(seed, TAG_MISS, &[id_key(**id)])
                    .random_bool(cfg.miss_small_prob.clamp(0.0, 1.0)))
        })
        .map(|(id, _)| *id)
        .collect();

    // 2. Under-segmentation: merge neighbouring pairs (union-find, capped group size).
    let mut parent: BTreeMap<i32, i32> = kept.iter().map(|&i| (i, i)).collect();
    let mut size: BTreeMap<i32, usize> = kept.iter().map(|&i| (i, 1)).collect();
    if cfg.merge_prob > 0.0 && cfg.merge_max_instances >= 2 {
        for (a, b) in neighbour_pairs(instance, &kept, cfg.merge_gap_px.max(1)) {
            let mut rng = rng_for(seed, TAG_MERGE, &[id_key(a), id_key(b)]);
            if !rng.random_bool(cfg.merge_prob.clamp(0.0, 1.0)) {
                continue;
            }
            let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
            if ra == rb || size[&ra] + size[&rb] > cfg.merge_max_instances {
                continue;
            }
            let (lo, hi) = (ra.min(rb), ra.max(rb));
            parent.insert(hi, lo);
            let n = size[&ra] + size[&rb];
            size.insert(lo, n);
        }
    }
    let mut groups: BTreeMap<i32, Vec<i32>> = BTreeMap::new();
    for &i in &kept {
        let r = find(&mut parent, i);
        groups.entry(r).or_default().push(i);
    }
    let groups: Vec<Vec<i32>> = groups.into_values().collect();

    // 3. Over-segmentation, per group (in parallel; each group has its own RNG).
    let mut pieces: Vec<Piece> = groups
        .par_iter()
        .flat_map_iter(|members| {
            let mut region = instance_region(instance, members[0], &stats[&members[0]]);
            let mut class_px = stats[&members[0]].class_px.clone();
            for &m in &members[1..] {
                region = region.union(&instance_region(instance, m, &stats[&m]));
                for (&c, &n) in &stats[&m].class_px {
                    *class_px.entry(c).or_insert(0) += n;
                }
            }
            let class = majority(&class_px);
            let key = id_key(members[0]);
            let kind = if members.len() > 1 {
                MaskKind::Merged
            } else {
                MaskKind::Instance
            };
            let mut parts = vec![region];
            let mut rng = rng_for(seed, TAG_SPLIT, &[key]);
            let area: usize = members.iter().map(|m| stats[m].area).sum();
            let split = cfg.split_prob > 0.0
                && area >= cfg.split_min_area_px
                && rng.random_bool(cfg.split_prob.clamp(0.0, 1.0));
            if split {
                let k = rng.random_range(2..=cfg.split_max_parts.max(2));
                while parts.len() < k {
                    let (li, _) = parts
                        .iter()
                        .enumerate()
                        .max_by_key(|(i, p)| (p.area(), usize::MAX - i))
                        .expect("parts is never empty");
                    match parts[li].split(&mut rng) {
                        Some((a, b)) => {
                            parts[li] = a;
                            parts.push(b);
                        }
                        None => break,
                    }
                }
            }
            let kind = if parts.len() > 1 {
                MaskKind::Split
            } else {
                kind
            };
            parts
                .into_iter()
                .enumerate()
                .map(move |(j, region)| Piece {
                    region,
                    sources: members.clone(),
                    class,
                    kind,
                    key: [key, j as u64],
                })
                .collect::<Vec<_>>()
        })
        .collect();

    // 5. False positives on façade instances (before the boundary error, which they get too).
    if cfg.false_positive_rate > 0.0 {
        let fp: Vec<Piece> = stats
            .par_iter()
            .filter(|(_, st)| cfg.false_positive_classes.contains(&st.majority_class()))
            .flat_map_iter(|(&id, st)| {
                let mut rng = rng_for(seed, TAG_FP, &[id_key(id)]);
                let n = poisson(&mut rng, cfg.false_positive_rate);
                let base = instance_region(instance, id, st);
                let px: Vec<(usize, usize)> = base.pixels().collect();
                let mut out = Vec::new();
                for j in 0..n {
                    let (cy, cx) = px[rng.random_range(0..px.len())];
                    let ry = range_incl(&mut rng, cfg.false_positive_radius_px).max(1) as f64;
                    let rx = range_incl(&mut rng, cfg.false_positive_radius_px).max(1) as f64;
                    let m = Array2::from_shape_fn(base.m.dim(), |(y, x)| {
                        let dy = (base.y0 + y) as f64 - cy as f64;
                        let dx = (base.x0 + x) as f64 - cx as f64;
                        base.m[[y, x]] && (dy / ry).powi(2) + (dx / rx).powi(2) <= 1.0
                    });
                    if let Some(region) = (Region { m, ..base.clone() }).tight() {
                        out.push(Piece {
                            region,
                            sources: Vec::new(),
                            class: st.majority_class(),
                            kind: MaskKind::FalsePositive,
                            key: [id_key(id), (1u64 << 32) + j as u64],
                        });
                    }
                }
                out
            })
            .collect();
        pieces.extend(fp);
    }

    // 4 + 6. Boundary error, area filter, scores.
    let min_area = cfg.min_area_px.max(1);
    let mut out: Vec<SimulatedMask> = pieces
        .into_par_iter()
        .filter_map(|p| {
            let mut rng = rng_for(seed, TAG_BOUNDARY, &p.key);
            let mut region = p.region;
            if cfg.boundary_prob > 0.0 && rng.random_bool(cfg.boundary_prob.clamp(0.0, 1.0)) {
                let r = range_incl(&mut rng, cfg.boundary_radius_px);
                let op = if rng.random_bool(cfg.dilate_prob.clamp(0.0, 1.0)) {
                    Morph::Dilate
                } else {
                    Morph::Erode
                };
                if r > 0 {
                    let pad = region.padded(r, h, w);
                    let m = imageio::morphology(&pad.m, op, r)
                        .expect("OpenCV morphology on a valid mask");
                    region = Region { m, ..pad }.tight()?;
                }
            }
            let area = region.area();
            if area < min_area {
                return None;
            }
            let damage = damage(&region, area, instance, &stats);
            let mut rng = rng_for(seed, TAG_SCORE, &p.key);
            let score = |slope: f64, jitter: f64, rng: &mut ChaCha8Rng| {
                let noise = if jitter > 0.0 {
                    jitter * gauss(rng)
                } else {
                    0.0
                };
                // Six decimals (SAM's scores are float32, about seven digits) so that a
                // JSON write and read gives back the same f64.
                ((1.0 - slope * damage + noise).clamp(0.0, 1.0) * 1e6).round() / 1e6
            };
            let predicted_iou = score(cfg.iou_slope, cfg.iou_jitter, &mut rng);
            let stability_score = score(cfg.stability_slope, cfg.stability_jitter, &mut rng);
            let k = rng.random_range(0..area);
            let (py, px) = region.pixels().nth(k).expect("k < area");
            let rle = Rle::encode_region(h, w, region.y0, region.x0, region.m.view());
            let mask = SamMask::from_rle(
                rle,
                predicted_iou,
                stability_score,
                vec![[px as f64, py as f64]],
            )
            .expect("a freshly encoded RLE is valid");
            Some(SimulatedMask {
                mask,
                source_instances: p.sources,
                class: p.class,
                kind: p.kind,
                damage,
            })
        })
        .collect();
    out.sort_by(|a, b| {
        (a.kind, &a.source_instances, a.mask.bbox)
            .cmp(&(b.kind, &b.source_instances, b.mask.bbox))
            .then_with(|| {
                format!("{:?}", a.mask.segmentation.counts)
                    .cmp(&format!("{:?}", b.mask.segmentation.counts))
            })
            .then_with(|| a.mask.predicted_iou.total_cmp(&b.mask.predicted_iou))
    });
    out
}

/// `1 − max_i IoU(region, instance i)` over all ground-truth instances.
fn damage(
    region: &Region,
    area: usize,
    instance: ArrayView2<i32>,
    stats: &BTreeMap<i32, Inst>,
) -> f64 {
    let mut inter: BTreeMap<i32, usize> = BTreeMap::new();
    for (y, x) in region.pixels() {
        let id = instance[[y, x]];
        if id >= 0 {
            *inter.entry(id).or_insert(0) += 1;
        }
    }
    let best = inter
        .iter()
        .map(|(id, &i)| i as f64 / (area + stats[id].area - i) as f64)
        .fold(0.0f64, f64::max);
    1.0 - best
}
