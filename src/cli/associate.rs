//! `gs4city associate`: scene-consistent groups of the kept masks across views, through the
//! Gaussians (paper §3.2, cross-view association).
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};

use crate::alignment::Alignment;
use crate::associate::{self, AssociateOptions, CandidateMode};
use crate::cache::Cache;
use crate::colmap;
use crate::scene::Split;

/// Candidate Gaussians of a mask.
#[derive(Debug, Clone, Copy, ValueEnum)]
enum Candidates {
    /// The Gaussians contributing to the mask's pixels, weighted by α·T (contributions cache).
    Weighted,
    /// Projected Gaussian centres, front 20 % by depth per cell of an 8×8 grid (the reference).
    Projected,
}

#[derive(Debug, Args)]
pub struct AssociateArgs {
    /// The masks stage's folder (`<stem>.json`: kept masks per view).
    #[arg(long)]
    masks: PathBuf,
    /// The scene's per-mask features (`features/<stem>.npy`); without them no feature check.
    #[arg(long)]
    features: Option<PathBuf>,
    /// The scene's SAM lists (`masks/<stem>.json`): a group seen in fewer than --min-views views
    /// also counts views where a mask the masks stage dropped for quality or area only matches it.
    #[arg(long)]
    sam: Option<PathBuf>,
    /// No view support from dropped masks (the paper's rule: only kept masks count).
    #[arg(long)]
    no_support: bool,
    /// With the view support, also match dropped masks against groups seen often enough and label
    /// a matching mask's unlabelled pixels with its group (off by default: the dropped masks'
    /// outlines are poor).
    #[arg(long)]
    support_pixels: bool,
    /// Support-only masks (`low_quality_support` in the masks stage's decisions) do not join
    /// groups: they add no Gaussians to the fill (they still count as view support).
    #[arg(long)]
    no_support_masks: bool,
    /// Plain-mass ownership: a Gaussian belongs to the group whose masks put the most α·T mass
    /// on it (without this, the mass of each mask counts per mask pixel, so a small object's mask
    /// beats a large mask that swallows it in more views).
    #[arg(long)]
    mass_owner: bool,
    /// The fill labels only pixels no kept mask labels (without this, it also relabels a kept
    /// mask's pixel dominated by the Gaussians of a group that has no kept mask in the view).
    #[arg(long)]
    no_fill_over_masks: bool,
    /// Joining support-only masks also label their own unlabelled pixels with the group.
    #[arg(long)]
    support_mask_pixels: bool,
    /// Contributions cache (`gs4city render --cache`, or a run's `render/`).
    #[arg(long)]
    cache: PathBuf,
    /// Pre-trained 3DGS scene (INRIA PLY) the cache was built from.
    #[arg(long)]
    ply: PathBuf,
    /// COLMAP sparse model folder.
    #[arg(long)]
    colmap: PathBuf,
    /// Output folder of `gs4city citymodel` (its alignment.json scales the far-field distance).
    #[arg(long)]
    citymodel: PathBuf,
    /// How a mask's candidate Gaussians are found.
    #[arg(long, value_enum, default_value = "weighted")]
    candidates: Candidates,
    /// Geometric overlap R_geo a mask needs to join a group.
    #[arg(long, default_value_t = 0.2)]
    tau_geo: f64,
    /// Feature cosine a mask needs to join a group (when features exist): the cap of the value
    /// calibrated on the scene's own mask pairs, or the value itself with --no-calibrate.
    #[arg(long, default_value_t = 0.7)]
    tau_sim: f64,
    /// Use --tau-sim as given instead of calibrating it (docs/associate.md, "Calibration").
    #[arg(long)]
    no_calibrate: bool,
    /// Groups seen in fewer views are dropped (m_view).
    #[arg(long, default_value_t = crate::associate::AssociateOptions::default().min_views)]
    min_views: usize,
    /// Groups farther than this many metres (× alignment scale) from every camera are dropped.
    #[arg(long, default_value_t = 80.0)]
    far_field: f64,
    /// Skip the consolidation pass (the paper's single pass, order-dependent).
    #[arg(long)]
    no_consolidate: bool,
    /// Visit the views in this seeded random order (to measure order robustness).
    #[arg(long)]
    shuffle_seed: Option<u64>,
    /// Every N-th view (sorted by name) is a test view and is not associated (3DGS --eval: 8).
    #[arg(long, default_value_t = 8)]
    test_every: usize,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: &AssociateArgs) -> anyhow::Result<()> {
    let opts = AssociateOptions {
        candidates: match args.candidates {
            Candidates::Weighted => CandidateMode::Weighted,
            Candidates::Projected => CandidateMode::Projected,
        },
        tau_geo: args.tau_geo,
        tau_sim: args.tau_sim,
        calibrate: !args.no_calibrate,
        min_views: args.min_views,
        far_field_m: args.far_field,
        consolidate: !args.no_consolidate,
        shuffle_seed: args.shuffle_seed,
        support: !args.no_support,
        support_pixels: args.support_pixels,
        support_masks: !args.no_support_masks,
        specific_owner: !args.mass_owner,
        fill_over_masks: !args.no_fill_over_masks,
        support_mask_pixels: args.support_mask_pixels,
        ..Default::default()
    };
    opts.validate()?;
    if !args.masks.is_dir() {
        bail!("--masks {}: not a directory", args.masks.display());
    }
    let split = Split::new(colmap::read_model(&args.colmap)?, args.test_every);
    if split.train.is_empty() {
        bail!("no training views: every view is a test view (--test-every 1?)");
    }
    let alignment = Alignment::read(&args.citymodel.join("alignment.json"))?;
    let cache = Cache::open(&args.cache)
        .with_context(|| format!("opening the contributions cache {}", args.cache.display()))?;
    // The training views the cache holds, at its resolution (a run's lower work resolution).
    let train = cache.views_as_cached(&split.train)?;
    let s = associate::run(
        &associate::AssociateInputs {
            views: &train,
            masks: &args.masks,
            features: args.features.as_deref(),
            sam: args.sam.as_deref(),
            cache: &cache,
            ply: &args.ply,
            scale: alignment.scale,
        },
        &opts,
        &args.out,
    )?;
    println!(
        "associated {} masks of {} views into {} groups ({} merged by consolidation, {} dropped in < {} views, {} far field) in {:.1} s → {}",
        s.masks_associated,
        s.views,
        s.groups,
        s.consolidation.merges,
        s.dropped_min_views,
        opts.min_views,
        s.dropped_far_field,
        s.timing.total_s,
        args.out.display()
    );
    Ok(())
}
