//! `gs4city associate`: scene-consistent groups of the kept masks across views, through the
//! Gaussians (paper §3.2, cross-view association).
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;

use super::groups::{AssociateTuning, ConfigArg, SplitArgs, merged};
use crate::alignment::Alignment;
use crate::associate;
use crate::cache::Cache;
use crate::colmap;

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
    #[command(flatten)]
    split: SplitArgs,
    #[command(flatten)]
    config: ConfigArg,
    #[command(flatten, next_help_heading = "Association (config [associate])")]
    tuning: AssociateTuning,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: &AssociateArgs) -> anyhow::Result<()> {
    let opts = merged(&args.config.load()?.associate, &args.tuning).options()?;
    if !args.masks.is_dir() {
        bail!("--masks {}: not a directory", args.masks.display());
    }
    let split = args.split.split(colmap::read_model(&args.colmap)?)?;
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
