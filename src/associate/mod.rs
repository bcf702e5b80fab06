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
//! Transfer back runs in two passes over the views: pass A makes each map over the unfiltered
//! groups (masks composited, the fill) and finds the view support; after the filters, pass B
//! turns the maps, held in memory, into the kept groups' ids (−1 for dropped groups) and
//! writes them.
//!
//! Outputs (`docs/design.md`, "Stage contract"): per view `<stem>.ids.npy` (int32 H×W, group id ≥ 0,
//! −1 none), `groups.json` ([`GroupsFile`]), `features.npy` (float32 G×D, the unit mean feature
//! of each group, when the masks have features) and `summary.json` (last).
//!
//! Deterministic: views are visited in name order (or a seeded shuffle, for robustness
//! measurements), masks in file order; per-view work runs in parallel but is consumed in order.
//!
//! [`run`] calls the steps in the paper's order; the code of each lives in a submodule: reading
//! the views and pass 1 of the bank (`views.rs`), the bank and its consolidation ([`bank`]),
//! candidate Gaussians ([`candidates`]), view support and support-only masks (`support.rs`),
//! the filters and numbering (`filters.rs`), transfer back with the fill (`transfer.rs`).
pub mod bank;
pub mod calibrate;
pub mod candidates;
mod filters;
mod support;
mod transfer;
mod views;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

pub use bank::{BankOptions, Consolidation};
pub use candidates::{CandidateMode, ProjectedLimits, WeightedLimits};

use crate::cache::{Cache, CacheError};
use crate::camera::View;
use crate::classes;
use crate::fsutil::{self, FsError};
use crate::groups::{GroupsError, GroupsFile};
use crate::idmap::IdMapError;
use crate::maskfile::MaskFileError;
use crate::npy::{self, NpyError};

/// Errors of the associate stage. Each names the file at fault.
#[derive(Debug, thiserror::Error)]
pub enum AssociateError {
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error("two views share the stem `{0}`")]
    SharedStem(String),
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error("{path}: mask {index}: bad RLE: {err}")]
    Rle {
        path: PathBuf,
        index: usize,
        err: crate::sam::RleError,
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
    /// Feature cosine a mask needs to join a group, when both have features: the cap of the
    /// calibrated value ([`calibrate`]), or the value itself with `calibrate` off.
    pub tau_sim: f64,
    /// Choose `τ_sim` from the scene's own statistics ([`calibrate`]; on by default).
    #[serde(default = "yes")]
    pub calibrate: bool,
    /// Groups seen in fewer views are dropped (`m_view`). Default 2 (the paper's 3 is
    /// `--min-views 3`): measured on four simulated perceptions, 2 wins on each (person +3.5 to
    /// +14 IoU), 1 wins more on harder ones but admits false groups on `street` (car precision
    /// 99.6 → 95.0); BENCHMARKS.md's git history, "m_view".
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

fn yes() -> bool {
    true
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
            calibrate: true,
            min_views: 2,
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
        use crate::check::{End, at_least, non_negative, range};
        range("tau_geo", self.tau_geo, End::Closed(0.0), End::Open(1.0))?;
        range("tau_sim", self.tau_sim, End::Closed(-1.0), End::Open(1.0))?;
        range(
            "far_field_m",
            self.far_field_m,
            End::Open(0.0),
            End::Unbounded,
        )?;
        let w = &self.weighted;
        range(
            "weighted.min_share",
            w.min_share,
            End::Closed(0.0),
            End::Open(1.0),
        )?;
        non_negative("weighted.min_mass", w.min_mass)?;
        at_least("join_views", self.join_views as usize, 1)?;
        at_least("min_views", self.min_views, 1)?;
        if let Some(f) = self.fill {
            range("fill", f, End::Open(0.0), End::Closed(1.0))?;
        }
        let p = &self.projected;
        range(
            "projected.front_fraction",
            p.front_fraction,
            End::Open(0.0),
            End::Closed(1.0),
        )?;
        range(
            "projected.grid",
            p.grid,
            End::Closed(1.0),
            End::Closed(4096.0),
        )?;
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
    /// Calibrating τ_sim ([`calibrate`]).
    #[serde(default)]
    pub calibrate_s: f64,
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
    /// How τ_sim was chosen ([`calibrate`]).
    #[serde(default)]
    pub calibration: Option<calibrate::Calibration>,
}

impl crate::layout::Summary for AssociateSummary {}
/// What the steps share: the inputs, the options, the views in name order (canonical view
/// index = position), the Gaussian centres and the output folder.
struct Stage<'a> {
    inp: &'a AssociateInputs<'a>,
    opts: &'a AssociateOptions,
    views: &'a [&'a View],
    centres: &'a [[f32; 3]],
    out: &'a Path,
}

/// The counts and times of the summary, gathered step by step.
#[derive(Default)]
struct Tally {
    views: usize,
    gaussians: usize,
    // Pass 1.
    counts: views::MaskCounts,
    dim: Option<usize>,
    offered: usize,
    // Support-only masks, view support.
    joined_gaussians: usize,
    support_masks: usize,
    joined_masks: usize,
    // Filters.
    dropped_views: usize,
    dropped_far: usize,
    supported: usize,
    masks_dropped: usize,
    // Transfer back.
    labelled_pixels: u64,
    filled_pixels: u64,
    timing: AssociateTiming,
    calibration: Option<calibrate::Calibration>,
}

/// Runs the stage: association, filters, per-view group maps, `groups.json`, `features.npy`,
/// and `summary.json` (last).
pub fn run(
    inp: &AssociateInputs<'_>,
    opts: &AssociateOptions,
    out: &Path,
) -> Result<AssociateSummary, AssociateError> {
    let t0 = Instant::now();
    let views = views_in_order(inp, opts)?;
    fsutil::create_dir(out)?;
    let _ = std::fs::remove_file(out.join("summary.json"));
    let mut tally = Tally {
        views: views.len(),
        ..Tally::default()
    };
    let centres = read_centres(inp, &mut tally)?;
    let st = Stage {
        inp,
        opts,
        views: &views,
        centres: &centres,
        out,
    };

    // Per view: the kept masks composited, their candidate Gaussians; τ_sim from the scene's
    // statistics; pass 1 of the memory bank. Every later step uses the calibrated τ_sim.
    let pass1 = views::pass_one(&st, &mut tally)?;
    let given = *opts;
    let calibrated = AssociateOptions {
        tau_sim: pass1.calibration.tau_sim,
        ..*opts
    };
    let opts = &calibrated;
    let st = Stage { opts, ..st };
    tally.calibration = Some(pass1.calibration.clone());

    // Consolidation; fill members and weak groups (pre-filter group indices); support-only
    // masks join their groups' fill members.
    let t = Instant::now();
    let fin = pass1.bank.finish();
    let far = filters::FarField::new(&fin, &views, opts.far_field_m * inp.scale);
    let mut members = transfer::members(opts, &fin, &pass1.visible, views.len());
    let targets = support::Targets::new(&fin, &far, opts);
    tally.joined_gaussians = support::join_support_masks(
        &st,
        &fin,
        &targets,
        &pass1.visible,
        pass1.join_masks,
        &mut members,
    )?;
    drop(pass1.visible);
    let per_view = transfer::masks_per_view(&fin, views.len());
    tally.timing.finish_s = t.elapsed().as_secs_f64();

    // Transfer back, pass A, with the view support; the m_view and far-field filters; pass B.
    let t = Instant::now();
    let (support, maps) = transfer::pass_a(&st, &fin, &per_view, &targets, &members, &mut tally)?;
    let kept = filters::keep_groups(&st, &fin, &support, &far, &mut tally);
    transfer::pass_b(&st, maps, &kept.id, &mut tally)?;
    let groups = write_groups(out, tally.dim, kept)?;
    tally.timing.write_s = t.elapsed().as_secs_f64();

    write_summary(&given, fin.consolidation, &groups, tally, t0, out)
}

/// Checks the options and the alignment scale, and returns the views in name order (an error
/// when two share a stem).
fn views_in_order<'a>(
    inp: &AssociateInputs<'a>,
    opts: &AssociateOptions,
) -> Result<Vec<&'a View>, AssociateError> {
    opts.validate()?;
    crate::check::positive("the alignment scale", inp.scale)?;
    let mut views: Vec<&View> = inp.views.iter().collect();
    views.sort_by(|a, b| a.name.cmp(&b.name));
    for w in views.windows(2) {
        if w[0].stem() == w[1].stem() {
            return Err(AssociateError::SharedStem(w[0].stem()));
        }
    }
    Ok(views)
}

/// Reads the Gaussian centres from the PLY and checks their count against the contributions
/// cache (sets the Gaussian count and the PLY time of `tally`).
fn read_centres(
    inp: &AssociateInputs<'_>,
    tally: &mut Tally,
) -> Result<Vec<[f32; 3]>, AssociateError> {
    let t = Instant::now();
    let centres = crate::splat::read_ply(inp.ply, &crate::splat::ReadOptions::KEEP)?
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
    tally.gaussians = n;
    tally.timing.ply_s = t.elapsed().as_secs_f64();
    Ok(centres)
}

/// Writes `groups.json` and `features.npy` (removed when the masks have no features).
fn write_groups(
    out: &Path,
    dim: Option<usize>,
    kept: filters::Kept,
) -> Result<GroupsFile, AssociateError> {
    let group_features = kept.features;
    let groups_file = GroupsFile {
        feature_dim: dim,
        groups: kept.records,
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
    Ok(groups_file)
}

/// The one loud line of a collapse: masks went in, no group came out (the fused supervision
/// falls back to the city model alone), with the likely cause and the option to change.
fn collapse_warning(opts: &AssociateOptions, tally: &Tally, groups: usize) -> String {
    let cause = if tally.dropped_views > 0 && tally.dropped_far == 0 {
        format!(
            "{} of {} masks are in groups seen in fewer than {} views ({} groups dropped): the masks are not linked across views — features that do not match ({}), masks too fragmented for R_geo > τ_geo = {}, or too few views of each object; try --min-views 2, a lower --tau-geo, or the feature calibration (on by default)",
            tally.masks_dropped,
            tally.offered,
            opts.min_views,
            tally.dropped_views,
            tally
                .calibration
                .as_ref()
                .map_or("no calibration".to_string(), |c| format!(
                    "τ_sim {}: {}",
                    c.tau_sim, c.mode
                )),
            opts.tau_geo
        )
    } else if tally.dropped_far > 0 {
        format!(
            "{} groups lie farther than {} m from every camera (far field): check the alignment scale or raise --far-field",
            tally.dropped_far, opts.far_field_m
        )
    } else {
        "no mask joined or founded a group".to_string()
    };
    format!(
        "associate COLLAPSED: {} masks of {} views → {groups} groups; the fused supervision is (almost) the city model alone (no tree, car, person). Cause: {cause}",
        tally.offered, tally.views
    )
}

/// The summary from the counts of every step, written last (`summary.json`), and the closing
/// progress line.
fn write_summary(
    opts: &AssociateOptions,
    consolidation: Consolidation,
    groups_file: &GroupsFile,
    tally: Tally,
    t0: Instant,
    out: &Path,
) -> Result<AssociateSummary, AssociateError> {
    let mut per_class = BTreeMap::new();
    for g in &groups_file.groups {
        *per_class
            .entry(classes::name(g.class).to_string())
            .or_insert(0usize) += 1;
    }
    let mut warnings = Vec::new();
    let zero_f = tally.counts.zero_features;
    if zero_f > 0 {
        warnings.push(format!(
            "{zero_f} kept masks have an all-zero feature row: associated without a feature"
        ));
    }
    if let Some(c) = tally
        .calibration
        .as_ref()
        .filter(|c| c.mode == calibrate::CalibrationMode::GeometryOnly)
    {
        warnings.push(format!("associate: {}", c.why));
    }
    // (Almost) nothing: no group, or 90 % of the masks in groups the filters dropped.
    if tally.offered > 0
        && (groups_file.groups.is_empty() || tally.masks_dropped * 10 >= tally.offered * 9)
    {
        warnings.push(collapse_warning(opts, &tally, groups_file.groups.len()));
    }
    for w in &warnings {
        log::warn!("{w}");
    }
    let summary = AssociateSummary {
        views: tally.views,
        masks: tally.counts.masks,
        masks_associated: tally.offered,
        masks_hidden: tally.counts.hidden,
        masks_without_candidates: tally.counts.without_candidates,
        masks_with_features: tally.dim.map(|_| tally.counts.with_features),
        feature_dim: tally.dim,
        gaussians: tally.gaussians,
        options: *opts,
        consolidation,
        dropped_min_views: tally.dropped_views,
        dropped_far_field: tally.dropped_far,
        support_masks: tally.support_masks,
        joined_masks: tally.joined_masks,
        joined_gaussians: tally.joined_gaussians,
        supported_groups: tally.supported,
        masks_dropped: tally.masks_dropped,
        groups: groups_file.groups.len(),
        groups_per_class: per_class,
        gaussians_in_groups: groups_file.groups.iter().map(|g| g.gaussians).sum(),
        labelled_pixels: tally.labelled_pixels,
        filled_pixels: tally.filled_pixels,
        timing: AssociateTiming {
            total_s: t0.elapsed().as_secs_f64(),
            ..tally.timing
        },
        warnings,
        calibration: tally.calibration,
    };
    crate::layout::Summary::write(&summary, out)?;
    crate::progress::done(
        "associate",
        &format!(
            "{} masks of {} views → {} groups ({} dropped: {} in < {} views, {} far field)",
            summary.masks_associated,
            summary.views,
            summary.groups,
            summary.dropped_min_views + summary.dropped_far_field,
            summary.dropped_min_views,
            opts.min_views,
            summary.dropped_far_field
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}
