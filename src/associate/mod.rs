//! The `associate` stage (paper §3.2, cross-view association): the masks each view kept are
//! view-specific; this stage links them into scene-consistent groups through the pre-trained
//! Gaussians, used only as a geometric bridge, and transfers the group ids back to every view.
//!
//! Per view, the kept masks are composited into one label image ([`candidates::composite`]) and
//! each mask gets its candidate Gaussians `C(s)` ([`CandidateMode`]). The memory bank
//! ([`bank`]) groups the masks (the paper's rule, `τ_geo`, `τ_sim`, running-mean features,
//! exclusive Gaussian ownership) and a consolidation pass makes the result robust to the
//! visiting order. Groups seen in fewer than `m_view` views, and groups whose centroid lies
//! farther than the far-field distance (80 m × alignment scale) from every camera, are dropped.
//! Beyond the paper, the **view support** ([`AssociateOptions::support`]): a group below
//! `m_view` also counts the views where a SAM mask that the masks stage dropped *only* for
//! quality or area (`predicted_iou < τ_q`, `|s| < τ_a` — small objects such as persons lose most
//! of their masks there) matches it by the paper's rule (`R_geo > τ_geo` of the mask's own α·T
//! candidates, feature cosine `> τ_sim`). Such masks never start a group.
//!
//! Transfer back runs in two passes over the views: pass A writes each map over the unfiltered
//! groups (masks composited, the fill) and finds the view support; after the filters, pass B
//! rewrites the maps with the kept groups' ids (−1 for dropped groups).
//!
//! Outputs (`docs/design.md`, "Wave 2 contract"): per view `<stem>.ids.npy` (int32 H×W, group id ≥ 0,
//! −1 none), `groups.json` ([`GroupsFile`]), `features.npy` (float32 G×D, the unit mean feature
//! of each group, when the masks have features) and `summary.json` (last).
//!
//! Deterministic: views are visited in name order (or a seeded shuffle, for robustness
//! measurements), masks in file order; per-view work runs in parallel but is consumed in order.
pub mod bank;
pub mod candidates;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rand::SeedableRng;
use rand::seq::SliceRandom;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

pub use bank::{BankOptions, Consolidation};
pub use candidates::{CandidateMode, ProjectedLimits, WeightedLimits};

use crate::cache::{Cache, CacheError};
use crate::camera::View;
use crate::classes;
use crate::fsutil::{self, FsError};
use crate::groups::{GroupRecord, GroupsError, GroupsFile};
use crate::idmap::{self, IdMapError};
use crate::maskfile::{self, KeptMask, MaskFileError, Rule};
use crate::npy::{self, NpyError};
use crate::progress::Bar;

/// Errors of the associate stage. Each names the file at fault.
#[derive(Debug, thiserror::Error)]
pub enum AssociateError {
    #[error("invalid option: {0}")]
    Options(String),
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error("{path}: mask {index}: bad RLE: {source}")]
    Rle {
        path: PathBuf,
        index: usize,
        source: crate::sam::RleError,
    },
    #[error(transparent)]
    MaskFile(#[from] MaskFileError),
    #[error(transparent)]
    Groups(#[from] GroupsError),
    #[error(transparent)]
    IdMap(#[from] IdMapError),
    #[error(transparent)]
    Sam(#[from] crate::sam::SamError),
    #[error(transparent)]
    Cache(#[from] CacheError),
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// Options of the stage (defaults: the paper's / reference's values).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AssociateOptions {
    pub candidates: CandidateMode,
    /// Geometric overlap a mask needs to join a group (`R_geo > τ_geo`).
    pub tau_geo: f64,
    /// Feature cosine a mask needs to join a group, when both have features.
    pub tau_sim: f64,
    /// Groups seen in fewer views are dropped (`m_view`).
    pub min_views: usize,
    /// Groups whose centroid is farther than this (metres, × alignment scale) from every
    /// camera are dropped.
    pub far_field_m: f64,
    pub weighted: WeightedLimits,
    pub projected: ProjectedLimits,
    /// Run the consolidation pass (order robustness, [`bank`]).
    pub consolidate: bool,
    /// Masks from distinct views needed to merge two groups in the consolidation pass …
    pub merge_support: usize,
    /// … and at least this share of the smaller group's views.
    pub merge_fraction: f64,
    /// Histogram intersection of two masks' normalised candidate weights above which they stay
    /// linked when pass-1 groups are split.
    pub tau_link: f64,
    /// Visit the views in a seeded random order instead of by name (only to measure how much
    /// the order matters).
    pub shuffle_seed: Option<u64>,
    /// Fill (beyond the paper): a pixel no kept mask labels takes the group whose Gaussians
    /// make at least this share of its colour (α·T), where some group does; `None` = off.
    pub fill: Option<f32>,
    /// View support (beyond the paper): a group seen in fewer than `min_views` views also counts
    /// the views where a mask that the masks stage dropped ONLY for quality or area
    /// (`predicted_iou < τ_q`, `|s| < τ_a`) matches it — its α·T candidates have more than
    /// `τ_geo` of their mass on the group's Gaussians and its feature passes `τ_sim` (needs
    /// [`AssociateInputs::sam`]). Such masks never start a group.
    pub support: bool,
    /// With `support`: match the dropped masks against every group (not only those below
    /// `min_views`) in the views where the group has no kept mask, and label a matching mask's
    /// pixels that no kept mask labels with its group (before the fill). Off by default: on
    /// `street` it gains person +2.5 and car +2.5 IoU but loses window −2.0 and purity
    /// (0.956 → 0.938): the dropped masks' outlines are poor (docs/associate.md).
    pub support_pixels: bool,
    /// Support-only masks (beyond the paper): a mask the masks stage recorded as
    /// `low_quality_support` (dropped only for `predicted_iou < τ_q`, above its floor; it passed
    /// area, the city-model filter and the depth/feature tests) that matches a group by the
    /// paper's rule (`R_geo > τ_geo`, cosine `> τ_sim`) joins it: its α·T candidates that no
    /// other group owns become fill members of the group (where the support-only masks of that
    /// group contain them in at least half of the views that see them and have such a mask, and
    /// no other group's support-only mask claims them), so the fill labels them in every view.
    /// It never starts a group; it counts towards `min_views` through the view support
    /// (`support`), as every quality/area drop does. Needs [`AssociateInputs::sam`] and the fill.
    #[serde(default)]
    pub support_masks: bool,
    /// With `support_masks`: also label a joining mask's pixels that no kept mask labels with
    /// its group (before the fill).
    #[serde(default)]
    pub support_mask_pixels: bool,
    /// With `support_masks`: a Gaussian joins only when support-only masks of the group in at
    /// least this many views contain it (one poor outline is not enough).
    #[serde(default = "default_join_views")]
    pub join_views: u32,
    /// Specific ownership ([`BankOptions::specific_owner`], beyond the paper): after the
    /// consolidation, a Gaussian belongs to the group whose masks put the most mass per mask
    /// pixel on it — a small object's mask beats a large mask that swallows it in more views.
    #[serde(default)]
    pub specific_owner: bool,
    /// The fill also relabels a kept mask's pixel (beyond the paper): where the member Gaussians
    /// of another group that has no kept mask in the view make at least the fill share of the
    /// pixel's colour, the pixel takes that group (the mask swallowed an object whose own mask
    /// was dropped in this view).
    #[serde(default)]
    pub fill_over_masks: bool,
}

fn default_join_views() -> u32 {
    2
}

impl Default for AssociateOptions {
    fn default() -> Self {
        AssociateOptions {
            candidates: CandidateMode::Weighted,
            tau_geo: 0.2,
            tau_sim: 0.7,
            min_views: 3,
            far_field_m: 80.0,
            weighted: WeightedLimits::default(),
            projected: ProjectedLimits::default(),
            consolidate: true,
            merge_support: 2,
            merge_fraction: 0.3,
            tau_link: 0.25,
            shuffle_seed: None,
            fill: Some(0.5),
            support: true,
            support_pixels: false,
            support_masks: true,
            support_mask_pixels: false,
            join_views: default_join_views(),
            specific_owner: true,
            fill_over_masks: true,
        }
    }
}

impl AssociateOptions {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<(), AssociateError> {
        use crate::check::{End, range};
        let bad = |s: String| Err(AssociateError::Options(s));
        range("tau_geo", self.tau_geo, End::Closed(0.0), End::Open(1.0))
            .and_then(|_| range("tau_sim", self.tau_sim, End::Closed(-1.0), End::Open(1.0)))
            .and_then(|_| {
                range(
                    "far_field_m",
                    self.far_field_m,
                    End::Open(0.0),
                    End::Unbounded,
                )
            })
            .map_err(AssociateError::Options)?;
        let w = &self.weighted;
        if !((0.0..1.0).contains(&w.min_share) && w.min_mass >= 0.0 && w.min_mass.is_finite()) {
            return bad(format!(
                "weighted limits out of range: min_share {} (0 ≤ · < 1), min_mass {} (≥ 0)",
                w.min_share, w.min_mass
            ));
        }
        let p = &self.projected;
        if self.join_views == 0 {
            return bad("join_views must be ≥ 1".into());
        }
        if let Some(f) = self.fill {
            range("fill", f, End::Open(0.0), End::Closed(1.0)).map_err(AssociateError::Options)?;
        }
        if !(p.front_fraction > 0.0 && p.front_fraction <= 1.0) || p.grid == 0 || p.grid > 4096 {
            return bad(format!(
                "projected limits out of range: front_fraction {} (0 < · ≤ 1), grid {} (1–4096)",
                p.front_fraction, p.grid
            ));
        }
        Ok(())
    }
}

/// Everything the stage reads.
pub struct AssociateInputs<'a> {
    /// The views to associate (the training views); visited in name order.
    pub views: &'a [View],
    /// The masks stage's folder (`<stem>.json`: the kept masks of each view).
    pub masks: &'a Path,
    /// The scene's `features/` folder (`<stem>.npy`, one row per SAM mask), when it exists.
    pub features: Option<&'a Path>,
    /// The scene's SAM lists (`masks/<stem>.json`), for the view support from masks the masks
    /// stage dropped for quality or area only (read with its `<stem>.decisions.json`); `None`:
    /// no view support.
    pub sam: Option<&'a Path>,
    /// The contributions cache (read by the α·T candidates).
    pub cache: &'a Cache,
    /// The pre-trained 3DGS PLY the cache was built from (Gaussian centres).
    pub ply: &'a Path,
    /// The alignment scale (scene units per metre, `alignment.json`).
    pub scale: f64,
}

/// Time per step.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct AssociateTiming {
    /// Reading the PLY (Gaussian centres).
    pub ply_s: f64,
    /// Reading masks, features and cache views, compositing and candidate sets (wall time of
    /// the parallel phase).
    pub views_s: f64,
    /// Pass 1 of the memory bank.
    pub bank_s: f64,
    /// Consolidation, filters, numbering.
    pub finish_s: f64,
    /// Per-view maps (with the view support and the fill), groups.json, features.npy.
    pub write_s: f64,
    pub total_s: f64,
}

/// The stage's `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AssociateSummary {
    pub views: usize,
    /// Kept masks read.
    pub masks: usize,
    /// Masks offered to the bank (visible, with candidates).
    pub masks_associated: usize,
    /// Masks hidden by smaller masks on top of them.
    pub masks_hidden: usize,
    /// Visible masks without candidate Gaussians.
    pub masks_without_candidates: usize,
    /// Masks with a feature (None: no features at all).
    pub masks_with_features: Option<usize>,
    pub feature_dim: Option<usize>,
    pub gaussians: usize,
    pub options: AssociateOptions,
    pub consolidation: Consolidation,
    pub dropped_min_views: usize,
    pub dropped_far_field: usize,
    /// Masks dropped for quality or area only that matched a group seen in fewer than
    /// `min_views` views (view support) …
    #[serde(default)]
    pub support_masks: usize,
    /// … and the groups that reach `min_views` with that support.
    #[serde(default)]
    pub supported_groups: usize,
    /// Support-only masks (`low_quality_support`) that joined a group and labelled their pixels
    /// ([`AssociateOptions::support_masks`]).
    #[serde(default)]
    pub joined_masks: usize,
    /// Gaussians those masks added to their groups' fill members.
    #[serde(default)]
    pub joined_gaussians: usize,
    /// Masks whose group was dropped.
    pub masks_dropped: usize,
    pub groups: usize,
    pub groups_per_class: BTreeMap<String, usize>,
    /// Gaussians owned by a kept group.
    pub gaussians_in_groups: usize,
    /// Pixels labelled with a group, over all views (filled ones included).
    pub labelled_pixels: u64,
    /// Of those, pixels labelled by the fill.
    pub filled_pixels: u64,
    pub timing: AssociateTiming,
    pub warnings: Vec<String>,
}

impl crate::layout::Summary for AssociateSummary {}

/// One view's kept masks (checked against the image size) and their composite.
struct MaskView {
    stem: String,
    w: usize,
    h: usize,
    kept: Vec<KeptMask>,
    vm: candidates::ViewMasks,
}

/// Reads `view`'s kept-mask file from `masks_dir` and composites it.
fn mask_view(masks_dir: &Path, view: &View) -> Result<MaskView, AssociateError> {
    let stem = view.stem();
    let (w, h) = (
        view.camera.intrinsics.width as usize,
        view.camera.intrinsics.height as usize,
    );
    let path = maskfile::kept_file(masks_dir, &stem);
    if !path.is_file() {
        return Err(AssociateError::Invalid {
            path,
            why: "missing: the masks stage wrote no kept-mask file for this view".into(),
        });
    }
    let kept = maskfile::read_kept(&path)?;
    for (i, k) in kept.iter().enumerate() {
        if k.sam.segmentation.size != [h, w] {
            return Err(AssociateError::Invalid {
                path,
                why: format!(
                    "mask {i}: size {:?} differs from the image size [{h}, {w}]",
                    k.sam.segmentation.size
                ),
            });
        }
    }
    let rles: Vec<&crate::sam::Rle> = kept.iter().map(|k| &k.sam.segmentation).collect();
    let vm = candidates::composite(&rles, w, h).map_err(|(index, source)| AssociateError::Rle {
        path: path.clone(),
        index,
        source,
    })?;
    Ok(MaskView {
        stem,
        w,
        h,
        kept,
        vm,
    })
}

/// Dimension, per-mask unit features (None: no feature), count of all-zero rows.
pub(crate) type MaskFeatures = (usize, Vec<Option<Vec<f32>>>, usize);

/// Per-mask features of a view (`features/<stem>.npy`), rows at the kept masks' source indices,
/// normalised. Returns the dimension, the features and the count of zero rows (no feature).
pub(crate) fn mask_features(path: &Path, sources: &[i64]) -> Result<MaskFeatures, AssociateError> {
    let (rows, d, data) = crate::sam::read_features(path, None)?;
    let bad = |why: String| AssociateError::Invalid {
        path: path.to_path_buf(),
        why,
    };
    if d == 0 {
        return Err(bad(format!(
            "shape [{rows}, 0], expected [masks, D] with D ≥ 1"
        )));
    }
    let mut zero = 0;
    let mut out = Vec::with_capacity(sources.len());
    for &s in sources {
        if s < 0 {
            out.push(None);
            continue;
        }
        let r = s as usize;
        if r >= rows {
            return Err(bad(format!(
                "{rows} feature rows, but a kept mask has source_index {s}"
            )));
        }
        let row = &data[r * d..(r + 1) * d];
        let norm = row
            .iter()
            .map(|&x| f64::from(x) * f64::from(x))
            .sum::<f64>()
            .sqrt();
        if norm < 1e-12 {
            zero += 1;
            out.push(None);
        } else {
            out.push(Some(
                row.iter().map(|&x| (f64::from(x) / norm) as f32).collect(),
            ));
        }
    }
    Ok((d, out, zero))
}

/// What the per-view phase yields for the bank.
struct ViewWork {
    /// Gaussians visible in the view (only for the fill).
    visible: Option<Vec<u64>>,
    observations: Vec<bank::Observation>,
    masks: usize,
    hidden: usize,
    without_candidates: usize,
    with_features: usize,
    zero_features: usize,
    dim: Option<usize>,
}

/// Loads a cache view and checks its size against the camera.
fn load_cache_view(
    inp: &AssociateInputs<'_>,
    stem: &str,
    w: usize,
    h: usize,
) -> Result<crate::cache::ViewContrib, AssociateError> {
    let c = inp.cache.load(stem)?;
    if (c.width, c.height) != (w, h) {
        return Err(AssociateError::Invalid {
            path: crate::cache::cache_file(&inp.cache.dir, stem),
            why: format!(
                "{}×{} pixels, the camera has {w}×{h}: the cache is stale",
                c.width, c.height
            ),
        });
    }
    Ok(c)
}

/// Reads one view and computes its observations.
fn view_work(
    inp: &AssociateInputs<'_>,
    opts: &AssociateOptions,
    centres: &[[f32; 3]],
    view: &View,
    canonical: u32,
) -> Result<ViewWork, AssociateError> {
    let MaskView {
        stem,
        w,
        h,
        kept,
        vm,
    } = mask_view(inp.masks, view)?;
    let (dim, feats, zero) = match inp.features {
        Some(dir) if !kept.is_empty() => {
            let fp = dir.join(format!("{stem}.npy"));
            let sources: Vec<i64> = kept.iter().map(|k| k.source_index).collect();
            let (d, f, z) = mask_features(&fp, &sources)?;
            (Some(d), f, z)
        }
        _ => (None, vec![None; kept.len()], 0),
    };
    // The cache view (α·T candidates, and the visible Gaussians for the fill).
    let need_cache = opts.candidates == CandidateMode::Weighted || opts.fill.is_some();
    let cache_view = if need_cache {
        Some(load_cache_view(inp, &stem, w, h)?)
    } else {
        None
    };
    let total = cache_view.as_ref().map(candidates::view_mass);
    let cands = match (opts.candidates, &cache_view, &total) {
        (CandidateMode::Weighted, Some(c), Some(t)) => {
            let centre = opts
                .weighted
                .centre_inside
                .then(|| candidates::centre_masks(centres, &view.camera, &vm));
            candidates::weighted(c, t, centre.as_deref(), &vm, &opts.weighted)
        }
        _ => candidates::projected(centres, &view.camera, &vm, &opts.projected),
    };
    let visible = match (&total, opts.fill) {
        (Some(t), Some(_)) => Some(candidates::visible_set(t, opts.weighted.min_mass)),
        _ => None,
    };
    let mut out = ViewWork {
        visible,
        observations: Vec::new(),
        masks: kept.len(),
        hidden: 0,
        without_candidates: 0,
        with_features: feats.iter().filter(|f| f.is_some()).count(),
        zero_features: zero,
        dim,
    };
    for (i, (cand, feature)) in cands.into_iter().zip(feats).enumerate() {
        if vm.visible[i] == 0 {
            out.hidden += 1;
            continue;
        }
        if cand.ids.is_empty() {
            out.without_candidates += 1;
            continue;
        }
        let (mut cs, mut ws) = ([0.0f64; 3], 0.0f64);
        for (&g, &wt) in cand.ids.iter().zip(&cand.weights) {
            let p = centres[g as usize];
            let wt = f64::from(wt);
            for k in 0..3 {
                cs[k] += wt * f64::from(p[k]);
            }
            ws += wt;
        }
        out.observations.push(bank::Observation {
            view: canonical,
            mask: i as u32,
            feature,
            class: kept[i].class,
            pixels: vm.visible[i],
            candidate: cand,
            centroid_sum: cs,
            weight_sum: ws,
        });
    }
    Ok(out)
}

/// Members of the groups for the fill: Gaussian `g` of owner `k` (vote ownership) is a member
/// when, over the views where `g` is visible and `k` has a mask, `g` lies in `k`'s mask in at
/// least half. A Gaussian a group absorbed by accident — a wall Gaussian seen through a tree
/// once, a road Gaussian under an under-segmented mask — lies outside the group's masks in most
/// views that see both, and is not a member.
fn fill_members(fin: &bank::Finished, visible: &[Option<Vec<u64>>], views: usize) -> Vec<i32> {
    let n = fin.owner.len();
    let mut inside = vec![0u16; n];
    let mut seen = vec![0u16; n];
    let mut present: Vec<Vec<usize>> = vec![Vec::new(); views];
    for (o, &gi) in fin.observations.iter().zip(&fin.group_of) {
        present[o.view as usize].push(gi);
        for &g in &o.candidate.ids {
            if fin.owner[g as usize] == gi as i32 {
                inside[g as usize] = inside[g as usize].saturating_add(1);
            }
        }
    }
    for (v, bits) in visible.iter().enumerate() {
        let Some(bits) = bits else { continue };
        let groups: std::collections::HashSet<usize> = present[v].iter().copied().collect();
        for (word, &b) in bits.iter().enumerate() {
            let mut b = b;
            while b != 0 {
                let g = word * 64 + b.trailing_zeros() as usize;
                b &= b - 1;
                let k = fin.owner[g];
                if k >= 0 && groups.contains(&(k as usize)) {
                    seen[g] = seen[g].saturating_add(1);
                }
            }
        }
    }
    (0..n)
        .map(|g| {
            let k = fin.owner[g];
            if k >= 0 && inside[g] > 0 && 2 * u32::from(inside[g]) >= u32::from(seen[g]) {
                k
            } else {
                -1
            }
        })
        .collect()
}

/// The fill: every pixel of `map` still −1 takes the group `k` whose member Gaussians carry at
/// least `share` of the pixel's α·T mass (the largest such group; ties: the smaller index),
/// written as `−2 − k` (a filled pixel). With `over` (the groups that have a kept mask in the
/// view, [`AssociateOptions::fill_over_masks`]), a pixel of a kept mask's group also takes such
/// a `k` when `k` is another group and not in `over`. Returns the number of pixels filled.
fn fill(
    map: &mut [i32],
    c: &crate::cache::ViewContrib,
    owner: &[i32],
    share: f32,
    over: Option<&std::collections::HashSet<i32>>,
) -> u64 {
    let mut filled = 0;
    let mut acc: Vec<(i32, f32)> = Vec::with_capacity(16);
    for (p, m) in map.iter_mut().enumerate() {
        if *m >= 0 && over.is_none() {
            continue;
        }
        acc.clear();
        let (ids, ws) = c.pixel(p);
        for (&g, &w) in ids.iter().zip(ws) {
            let k = owner[g as usize];
            if k < 0 {
                continue;
            }
            match acc.iter_mut().find(|e| e.0 == k) {
                Some(e) => e.1 += w,
                None => acc.push((k, w)),
            }
        }
        let best = acc
            .iter()
            .copied()
            .fold(None::<(i32, f32)>, |b, x| match b {
                Some(b) if b.1 > x.1 || (b.1 == x.1 && b.0 < x.0) => Some(b),
                _ => Some(x),
            });
        if let Some((k, w)) = best
            && w >= share
            && (*m < 0 || (k != *m && over.is_some_and(|o| !o.contains(&k))))
        {
            *m = -2 - k;
            filled += 1;
        }
    }
    filled
}

/// A dropped mask that matched a pre-filter group.
struct Hit {
    group: usize,
    /// It adds a view to the group (view support: the group has no kept mask in the view).
    view: bool,
    /// A support-only mask that joined the group.
    joined: bool,
    /// Its α·T candidates (support-only masks only).
    gaussians: Vec<u32>,
}

/// Adds the Gaussians of joining support-only masks to the fill members
/// ([`AssociateOptions::support_masks`]): `joins[v]` = (group, candidates) per joining mask of
/// view `v`, `visible[v]` the view's visible Gaussians. Gaussian `g` becomes a member of `k`
/// when it is no member yet, no other group owns it, only `k`'s support-only masks claim it,
/// and they contain it in at least half of the views that see it and have a joining mask of
/// `k`, and in at least `min_views` views. Returns the number of Gaussians added. Order-free: counts only.
fn join_members(
    members: &mut [i32],
    owner: &[i32],
    joins: &[Vec<(usize, Vec<u32>)>],
    visible: &[Vec<u64>],
    min_views: u32,
) -> usize {
    // Per claimed Gaussian: (group, views containing it), or a conflict (usize::MAX).
    let mut claim: std::collections::HashMap<u32, (usize, u32)> = Default::default();
    for view in joins {
        let mut here: std::collections::HashSet<(u32, usize)> = Default::default();
        for (k, ids) in view {
            for &g in ids {
                if here.insert((g, *k)) {
                    let e = claim.entry(g).or_insert((*k, 0));
                    if e.0 != *k {
                        e.0 = usize::MAX;
                    }
                    e.1 += 1;
                }
            }
        }
    }
    let mut seen: std::collections::HashMap<u32, u32> = Default::default();
    for (view, bits) in joins.iter().zip(visible) {
        let groups: std::collections::HashSet<usize> = view.iter().map(|(k, _)| *k).collect();
        for (&g, &(k, _)) in &claim {
            let vis = bits
                .get(g as usize / 64)
                .is_some_and(|w| w >> (g % 64) & 1 == 1);
            if k != usize::MAX && vis && groups.contains(&k) {
                *seen.entry(g).or_insert(0) += 1;
            }
        }
    }
    let mut added = 0;
    for (&g, &(k, n)) in &claim {
        let gi = g as usize;
        if k == usize::MAX || members[gi] >= 0 || (owner[gi] >= 0 && owner[gi] != k as i32) {
            continue;
        }
        if n >= min_views && 2 * n >= seen.get(&g).copied().unwrap_or(0) {
            members[gi] = k as i32;
            added += 1;
        }
    }
    added
}

/// The view support of the groups seen in fewer than `min_views` views
/// ([`AssociateOptions::support`]).
struct Support<'a> {
    fin: &'a bank::Finished,
    /// Per pre-filter group: whether dropped masks are matched against it (not far field; and
    /// seen in fewer than `min_views` views unless `support_pixels`).
    eligible: &'a [bool],
    /// Per pre-filter group: not far field (what support-only masks may join).
    near: &'a [bool],
    /// Label the pixels of joining support-only masks (else only record their candidates).
    paint_joined: bool,
    /// Match only the support-only masks.
    joined_only: bool,
    /// Gaussian ownership the masks are matched against (the bank's).
    owner: &'a [i32],
    centres: &'a [[f32; 3]],
}

impl Support<'_> {
    /// The eligible groups that masks of view `vi` dropped for quality or area only match (one
    /// entry per matching mask; only groups without a kept mask in the view). With
    /// `support_pixels`, a matching mask's pixels where `map` is −1 (or another dropped mask
    /// painted them: larger masks first, so the smaller wins) take its group.
    fn hits(
        &self,
        inp: &AssociateInputs<'_>,
        opts: &AssociateOptions,
        view: &View,
        vi: u32,
        c: &crate::cache::ViewContrib,
        map: &mut [i32],
    ) -> Result<Vec<Hit>, AssociateError> {
        let Some(sam_dir) = inp.sam else {
            return Ok(Vec::new());
        };
        let stem = view.stem();
        let (w, h) = (c.width, c.height);
        let dpath = maskfile::decisions_file(inp.masks, &stem);
        if !dpath.is_file() {
            return Err(AssociateError::Invalid {
                path: dpath,
                why: "missing: the view support needs the masks stage's decisions".into(),
            });
        }
        // (SAM index, support-only) of the masks dropped for quality or area only.
        let (sources, only): (Vec<i64>, Vec<bool>) = maskfile::read_decisions(&dpath)?
            .iter()
            .filter(|d| {
                !d.kept
                    && d.source_index >= 0
                    && matches!(d.rule, Rule::Quality | Rule::Area | Rule::LowQualitySupport)
            })
            .map(|d| {
                let joins = opts.support_masks && d.rule == Rule::LowQualitySupport;
                (d.source_index, joins)
            })
            .unzip();
        if sources.is_empty() {
            return Ok(Vec::new());
        }
        let spath = sam_dir.join(format!("{stem}.json"));
        let sam = crate::sam::read_sam_json_sized(&spath, Some([h, w]))?;
        if let Some(&s) = sources.iter().find(|&&s| s as usize >= sam.len()) {
            return Err(AssociateError::Invalid {
                path: dpath,
                why: format!(
                    "a decision has source_index {s}, {} lists {} masks",
                    spath.display(),
                    sam.len()
                ),
            });
        }
        let feats = match inp.features {
            Some(dir) => mask_features(&dir.join(format!("{stem}.npy")), &sources)?.1,
            None => vec![None; sources.len()],
        };
        let owner = self.owner;
        let weak = |k: usize| self.eligible[k] && !self.fin.groups[k].views.contains(&vi);
        // A support-only mask may join any group that is not far field.
        let wants = |k: usize, joins: bool| (joins && self.near[k]) || weak(k);
        // Larger masks first (ties: file order), so a smaller one paints over them.
        let mut order: Vec<usize> = (0..sources.len()).collect();
        order.sort_by(|&a, &b| {
            sam[sources[b] as usize]
                .area
                .cmp(&sam[sources[a] as usize].area)
                .then(a.cmp(&b))
        });
        let mut painted = vec![false; w * h];
        let total = candidates::view_mass(c);
        let mut acc = vec![0f32; c.gaussians];
        let mut in_mask = vec![false; w * h];
        let mut px: Vec<u32> = Vec::new();
        let mut hits = Vec::new();
        for j in order {
            if self.joined_only && !only[j] {
                continue;
            }
            let si = sources[j];
            px.clear();
            for_each_pixel_checked(&sam[si as usize].segmentation, &spath, si as usize, |p| {
                px.push(p as u32)
            })?;
            // Only masks on some weak group's Gaussians are worth their candidates.
            let touches = px.iter().any(|&p| {
                c.pixel(p as usize).0.iter().any(|&g| {
                    let o = owner[g as usize];
                    o >= 0 && wants(o as usize, only[j])
                })
            });
            if !touches {
                continue;
            }
            for &p in &px {
                in_mask[p as usize] = true;
            }
            let cand = candidates::weighted_one(
                c,
                &total,
                candidates::MaskPixels {
                    list: &px,
                    inside: &in_mask,
                },
                self.centres,
                &view.camera,
                &opts.weighted,
                &mut acc,
            );
            for &p in &px {
                in_mask[p as usize] = false;
            }
            let (shares, mass) = bank::shares_under(owner, &cand);
            let best = bank::best_share(&shares);
            if let Some((k, m)) = best
                && mass > 0.0
                && m / mass > opts.tau_geo
                && wants(k as usize, only[j])
            {
                let similar = feats[j].as_deref().is_none_or(|f| {
                    bank::cosine(f, &self.fin.groups[k as usize].feature_mean)
                        .is_none_or(|c| c > opts.tau_sim)
                });
                if similar {
                    // A view of the group only where it has no kept mask (view support).
                    hits.push(Hit {
                        group: k as usize,
                        view: weak(k as usize),
                        joined: only[j],
                        gaussians: if only[j] {
                            cand.ids.clone()
                        } else {
                            Vec::new()
                        },
                    });
                    if opts.support_pixels || (only[j] && self.paint_joined) {
                        for &p in &px {
                            let p = p as usize;
                            if map[p] == -1 || painted[p] {
                                map[p] = k as i32;
                                painted[p] = true;
                            }
                        }
                    }
                }
            }
        }
        Ok(hits)
    }
}

/// [`crate::sam::Rle::for_each_pixel`] with the file and mask index in the error.
fn for_each_pixel_checked(
    rle: &crate::sam::Rle,
    path: &Path,
    index: usize,
    f: impl FnMut(usize),
) -> Result<(), AssociateError> {
    rle.for_each_pixel(f).map_err(|source| AssociateError::Rle {
        path: path.to_path_buf(),
        index,
        source,
    })
}

/// Runs the stage: association, filters, per-view group maps, `groups.json`, `features.npy`,
/// and `summary.json` (last).
pub fn run(
    inp: &AssociateInputs<'_>,
    opts: &AssociateOptions,
    out: &Path,
) -> Result<AssociateSummary, AssociateError> {
    let t0 = Instant::now();
    opts.validate()?;
    if !(inp.scale.is_finite() && inp.scale > 0.0) {
        return Err(AssociateError::Options(format!(
            "the alignment scale must be finite and > 0, got {}",
            inp.scale
        )));
    }
    let mut views: Vec<&View> = inp.views.iter().collect();
    views.sort_by(|a, b| a.name.cmp(&b.name));
    for w in views.windows(2) {
        if w[0].stem() == w[1].stem() {
            return Err(AssociateError::Options(format!(
                "two views share the stem `{}`",
                w[0].stem()
            )));
        }
    }
    fsutil::create_dir(out)?;
    let _ = std::fs::remove_file(out.join("summary.json"));

    let t = Instant::now();
    let centres = crate::splat::read_ply(inp.ply, &Default::default())?
        .0
        .positions;
    let n = centres.len();
    if n != inp.cache.summary.gaussians {
        return Err(AssociateError::Invalid {
            path: inp.ply.to_path_buf(),
            why: format!(
                "{n} Gaussians, the contributions cache {} indexes {}: the cache is stale",
                inp.cache.dir.display(),
                inp.cache.summary.gaussians
            ),
        });
    }
    let ply_s = t.elapsed().as_secs_f64();

    // Visiting order: by name, or a seeded shuffle.
    let mut order: Vec<u32> = (0..views.len() as u32).collect();
    if let Some(seed) = opts.shuffle_seed {
        order.shuffle(&mut rand_chacha::ChaCha8Rng::seed_from_u64(seed));
    }
    let mut bank = bank::Bank::new(
        n,
        BankOptions {
            tau_geo: opts.tau_geo,
            tau_sim: opts.tau_sim,
            consolidate: opts.consolidate,
            merge_support: opts.merge_support,
            merge_fraction: opts.merge_fraction,
            tau_link: opts.tau_link,
            specific_owner: opts.specific_owner,
        },
    );
    let bar = Bar::new("associate", views.len() as u64, "views");
    let (mut views_s, mut bank_s) = (0.0, 0.0);
    let (mut masks_total, mut hidden, mut no_cand, mut with_f, mut zero_f) = (0, 0, 0, 0, 0);
    let mut dim: Option<usize> = None;
    let mut offered = 0usize;
    let mut visible: Vec<Option<Vec<u64>>> = vec![None; views.len()];
    let chunk = rayon::current_num_threads().max(1) * 2;
    for block in order.chunks(chunk) {
        let t = Instant::now();
        let works: Vec<Result<ViewWork, AssociateError>> = block
            .par_iter()
            .map(|&vi| view_work(inp, opts, &centres, views[vi as usize], vi))
            .collect();
        views_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        for (wk, &vi) in works.into_iter().zip(block) {
            let wk = wk?;
            if let (Some(a), Some(b)) = (dim, wk.dim)
                && a != b
            {
                return Err(AssociateError::Invalid {
                    path: inp
                        .features
                        .map(|d| d.join(format!("{}.npy", views[vi as usize].stem())))
                        .unwrap_or_default(),
                    why: format!("features of dimension {b}, other views have {a}"),
                });
            }
            dim = dim.or(wk.dim);
            masks_total += wk.masks;
            hidden += wk.hidden;
            no_cand += wk.without_candidates;
            with_f += wk.with_features;
            zero_f += wk.zero_features;
            visible[vi as usize] = wk.visible;
            for o in wk.observations {
                bank.offer(o);
                offered += 1;
            }
            bar.inc(1);
        }
        bank_s += t.elapsed().as_secs_f64();
    }
    bar.finish();

    // Consolidation; fill members and weak groups (pre-filter group indices).
    let t = Instant::now();
    let fin = bank.finish();
    let cams: Vec<glam::DVec3> = views.iter().map(|v| v.camera.pose.center()).collect();
    let far = opts.far_field_m * inp.scale;
    let nearest: Vec<f64> = fin
        .groups
        .iter()
        .map(|g| {
            let c = glam::DVec3::from_array(g.centroid);
            cams.iter()
                .map(|k| (*k - c).length())
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    let is_far = |gi: usize| nearest[gi].is_nan() || nearest[gi] > far;
    let mut members: Vec<i32> = if opts.fill.is_some() {
        fill_members(&fin, &visible, views.len())
    } else {
        Vec::new()
    };
    drop(visible);
    let eligible: Vec<bool> = (0..fin.groups.len())
        .map(|gi| {
            opts.support
                && !is_far(gi)
                && (opts.support_pixels || fin.groups[gi].views.len() < opts.min_views)
        })
        .collect();
    let near: Vec<bool> = (0..fin.groups.len()).map(|gi| !is_far(gi)).collect();
    let support_on = inp.sam.is_some()
        && ((opts.support && eligible.iter().any(|&w| w))
            || (opts.support_masks && near.iter().any(|&w| w)));
    // Support-only masks join their groups' fill members (a pass over the views first, so that
    // every view's fill sees the joins of all views).
    let mut joined_gaussians = 0;
    if opts.support_masks && opts.fill.is_some() && inp.sam.is_some() && near.iter().any(|&w| w) {
        let sup = Support {
            fin: &fin,
            eligible: &eligible,
            near: &near,
            centres: &centres,
            paint_joined: false,
            joined_only: true,
            owner: &fin.owner,
        };
        type Joins = (Vec<(usize, Vec<u32>)>, Vec<u64>);
        let per: Vec<Result<Joins, AssociateError>> = views
            .par_iter()
            .enumerate()
            .map(|(vi, v)| {
                let stem = v.stem();
                let (w, h) = (
                    v.camera.intrinsics.width as usize,
                    v.camera.intrinsics.height as usize,
                );
                let c = load_cache_view(inp, &stem, w, h)?;
                let mut scratch = vec![-1i32; w * h];
                let joins: Vec<(usize, Vec<u32>)> = sup
                    .hits(inp, opts, v, vi as u32, &c, &mut scratch)?
                    .into_iter()
                    .filter(|h| h.joined)
                    .map(|h| (h.group, h.gaussians))
                    .collect();
                let vis = if joins.is_empty() {
                    Vec::new()
                } else {
                    candidates::visible_set(&candidates::view_mass(&c), opts.weighted.min_mass)
                };
                Ok((joins, vis))
            })
            .collect();
        let (mut joins, mut vis) = (Vec::new(), Vec::new());
        for r in per {
            let (j, v) = r?;
            joins.push(j);
            vis.push(v);
        }
        joined_gaussians = join_members(&mut members, &fin.owner, &joins, &vis, opts.join_views);
    }
    // Group index per (canonical view, mask index).
    let mut per_view: Vec<Vec<(u32, usize)>> = vec![Vec::new(); views.len()];
    for (o, &gi) in fin.observations.iter().zip(&fin.group_of) {
        per_view[o.view as usize].push((o.mask, gi));
    }
    let finish_s = t.elapsed().as_secs_f64();

    // Transfer back, pass A: per view, the map over pre-filter group indices (a filled pixel is
    // written as −2 − index) and the view support's matches.
    let t = Instant::now();
    let pass_a: Vec<Result<Vec<Hit>, AssociateError>> = views
        .par_iter()
        .zip(&per_view)
        .enumerate()
        .map(|(vi, (v, assigned))| {
            let MaskView {
                stem,
                w,
                h,
                kept,
                vm,
            } = mask_view(inp.masks, v)?;
            let mut gi_of = vec![-1i32; kept.len()];
            for &(m, gi) in assigned {
                gi_of[m as usize] = gi as i32;
            }
            let mut map: Vec<i32> = vm
                .label
                .iter()
                .map(|&l| if l >= 0 { gi_of[l as usize] } else { -1 })
                .collect();
            let mut hits = Vec::new();
            if opts.fill.is_some() || support_on {
                let c = load_cache_view(inp, &stem, w, h)?;
                if support_on {
                    let sup = Support {
                        fin: &fin,
                        eligible: &eligible,
                        near: &near,
                        centres: &centres,
                        paint_joined: opts.support_mask_pixels,
                        joined_only: false,
                        owner: &fin.owner,
                    };
                    hits = sup.hits(inp, opts, v, vi as u32, &c, &mut map)?;
                }
                if let Some(share) = opts.fill {
                    let present: std::collections::HashSet<i32> =
                        assigned.iter().map(|&(_, gi)| gi as i32).collect();
                    let over = opts.fill_over_masks.then_some(&present);
                    fill(&mut map, &c, &members, share, over);
                }
            }
            idmap::write_ids(out, &stem, w, h, &map)?;
            Ok(hits)
        })
        .collect();
    let mut support: Vec<std::collections::BTreeSet<u32>> =
        vec![Default::default(); fin.groups.len()];
    let (mut support_masks, mut joined_masks) = (0, 0);
    for (vi, r) in pass_a.into_iter().enumerate() {
        for hit in r? {
            if hit.view {
                support[hit.group].insert(vi as u32);
                support_masks += 1;
            }
            joined_masks += usize::from(hit.joined);
        }
    }

    // Filters and numbering.
    let (mut dropped_views, mut dropped_far, mut supported) = (0, 0, 0);
    let mut keep_id: Vec<i32> = vec![-1; fin.groups.len()];
    let mut records = Vec::new();
    let mut group_features: Vec<f32> = Vec::new();
    for (gi, g) in fin.groups.iter().enumerate() {
        if g.views.len() + support[gi].len() < opts.min_views {
            dropped_views += 1;
            continue;
        }
        if is_far(gi) {
            dropped_far += 1;
            continue;
        }
        if g.views.len() < opts.min_views {
            supported += 1;
        }
        let id = records.len() as i32;
        keep_id[gi] = id;
        if let Some(d) = dim {
            let norm = g.feature_mean.iter().map(|x| x * x).sum::<f64>().sqrt();
            if g.feature_mean.len() == d && norm > 0.0 {
                group_features.extend(g.feature_mean.iter().map(|&x| (x / norm) as f32));
            } else {
                group_features.extend(std::iter::repeat_n(0.0f32, d));
            }
        }
        records.push(GroupRecord {
            id,
            views: g.views.iter().map(|&v| views[v as usize].stem()).collect(),
            support_views: support[gi]
                .iter()
                .map(|&v| views[v as usize].stem())
                .collect(),
            masks: g.members.len(),
            pixels: g.pixels,
            gaussians: g.gaussians,
            class: g.class,
            centroid: g.centroid,
            nearest_camera_distance: nearest[gi],
        });
    }
    let masks_dropped = fin.group_of.iter().filter(|&&gi| keep_id[gi] < 0).count();

    // Transfer back, pass B: pre-filter indices → kept group ids (−1 for dropped groups).
    let labelled: Vec<Result<(u64, u64), AssociateError>> = views
        .par_iter()
        .map(|v| {
            let stem = v.stem();
            let (w, h) = (
                v.camera.intrinsics.width as usize,
                v.camera.intrinsics.height as usize,
            );
            let mut map = idmap::read_ids(out, &stem, w, h)?;
            let (mut lab, mut filled) = (0u64, 0u64);
            for m in map.iter_mut() {
                let (gi, by_fill) = match *m {
                    x if x >= 0 => (x as usize, false),
                    -1 => continue,
                    x => ((-2 - x) as usize, true),
                };
                *m = keep_id[gi];
                if *m >= 0 {
                    lab += 1;
                    filled += u64::from(by_fill);
                }
            }
            idmap::write_ids(out, &stem, w, h, &map)?;
            Ok((lab, filled))
        })
        .collect();
    let (mut labelled_pixels, mut filled_pixels) = (0, 0);
    for l in labelled {
        let (a, b) = l?;
        labelled_pixels += a;
        filled_pixels += b;
    }
    let groups_file = GroupsFile {
        feature_dim: dim,
        groups: records,
    };
    fsutil::write_json(&out.join("groups.json"), &groups_file)?;
    let features_path = out.join("features.npy");
    match dim {
        Some(d) => npy::write(
            &features_path,
            &[groups_file.groups.len(), d],
            &group_features,
        )?,
        None => {
            let _ = std::fs::remove_file(&features_path);
        }
    }
    let write_s = t.elapsed().as_secs_f64();

    let mut per_class = BTreeMap::new();
    for g in &groups_file.groups {
        *per_class
            .entry(classes::name(g.class).to_string())
            .or_insert(0usize) += 1;
    }
    let mut warnings = Vec::new();
    if zero_f > 0 {
        warnings.push(format!(
            "{zero_f} kept masks have an all-zero feature row: associated without a feature"
        ));
    }
    let summary = AssociateSummary {
        views: views.len(),
        masks: masks_total,
        masks_associated: offered,
        masks_hidden: hidden,
        masks_without_candidates: no_cand,
        masks_with_features: dim.map(|_| with_f),
        feature_dim: dim,
        gaussians: n,
        options: *opts,
        consolidation: fin.consolidation,
        dropped_min_views: dropped_views,
        dropped_far_field: dropped_far,
        support_masks,
        joined_masks,
        joined_gaussians,
        supported_groups: supported,
        masks_dropped,
        groups: groups_file.groups.len(),
        groups_per_class: per_class,
        gaussians_in_groups: groups_file.groups.iter().map(|g| g.gaussians).sum(),
        labelled_pixels,
        filled_pixels,
        timing: AssociateTiming {
            ply_s,
            views_s,
            bank_s,
            finish_s,
            write_s,
            total_s: t0.elapsed().as_secs_f64(),
        },
        warnings,
    };
    crate::layout::Summary::write(&summary, out)?;
    crate::progress::done(
        "associate",
        &format!(
            "{} masks of {} views → {} groups ({} dropped: {} in < {} views, {} far field)",
            summary.masks_associated,
            summary.views,
            summary.groups,
            dropped_views + dropped_far,
            dropped_views,
            opts.min_views,
            dropped_far
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache::Contributions;
    use crate::cache::ViewContrib;

    /// 1×4 view; Gaussian 0 is a member of group 0 (the road), Gaussian 1 of group 1 (a person).
    fn view() -> ViewContrib {
        ViewContrib {
            width: 4,
            height: 1,
            k: 0,
            gaussians: 2,
            lists: Contributions {
                offsets: vec![0, 2, 4, 6, 8],
                ids: vec![1, 0, 1, 0, 1, 0, 1, 0],
                weights: vec![0.8, 0.1, 0.8, 0.1, 0.6, 0.1, 0.4, 0.5],
                residual: vec![0.0; 4],
            },
            alpha: vec![0.9, 0.9, 0.7, 0.9],
            depth: vec![1.0; 4],
        }
    }

    #[test]
    fn fill_over_masks_relabels_only_pixels_of_a_group_absent_from_the_view() {
        let members = [0, 1];
        // Pixels 0, 1, 3 lie in a kept mask of group 0; pixel 2 in none.
        let kept = [0, 0, -1, 0];
        // Without `over`: only the unlabelled pixel 2 is filled (0.6 of group 1 ≥ 0.5).
        let mut map = kept.to_vec();
        assert_eq!(fill(&mut map, &view(), &members, 0.5, None), 1);
        assert_eq!(map, vec![0, 0, -3, 0]);
        // Group 1 has no kept mask in the view: pixels 0 and 1 (0.8 of group 1) take it too;
        // pixel 3 (0.4 < 0.5) keeps its mask's group.
        let present: std::collections::HashSet<i32> = [0].into_iter().collect();
        let mut map = kept.to_vec();
        assert_eq!(fill(&mut map, &view(), &members, 0.5, Some(&present)), 3);
        assert_eq!(map, vec![-3, -3, -3, 0]);
        // Group 1 has a kept mask in the view: its mask already says where it is.
        let present: std::collections::HashSet<i32> = [0, 1].into_iter().collect();
        let mut map = kept.to_vec();
        assert_eq!(fill(&mut map, &view(), &members, 0.5, Some(&present)), 1);
        assert_eq!(map, vec![0, 0, -3, 0]);
    }
}
