//! `gs4city fuse`: image-priority fusion of the associated groups with the city-model ids, the
//! fused label table and per-label features (paper §3.2); optional city-part snapping.
use std::path::PathBuf;

use anyhow::bail;
use clap::Args;

use super::groups::{ConfigArg, FuseTuning, SplitArgs, merged};
use crate::fuse;
use crate::{colmap, semantics};

#[derive(Debug, Args)]
pub struct FuseArgs {
    /// The associate stage's folder (`<stem>.ids.npy`, groups.json, features.npy).
    #[arg(long)]
    associate: PathBuf,
    /// The raycast stage's folder (`<stem>.ids.npy`, 4×H×W).
    #[arg(long)]
    raycast: PathBuf,
    /// Output folder of `gs4city citymodel` (semantics.json).
    #[arg(long)]
    citymodel: PathBuf,
    /// COLMAP sparse model folder.
    #[arg(long)]
    colmap: PathBuf,
    /// The scene's SAM lists (`masks/<stem>.json`): city-entity features and snapping.
    #[arg(long)]
    sam: Option<PathBuf>,
    /// The scene's per-mask features (`features/<stem>.npy`).
    #[arg(long)]
    features: Option<PathBuf>,
    /// The masks stage's folder (kept masks; snapping only considers masks it dropped).
    #[arg(long)]
    masks: Option<PathBuf>,
    #[command(flatten)]
    split: SplitArgs,
    #[command(flatten)]
    config: ConfigArg,
    #[command(flatten, next_help_heading = "Fusion (config [fuse])")]
    tuning: FuseTuning,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: &FuseArgs) -> anyhow::Result<()> {
    let opts = merged(&args.config.load()?.fuse, &args.tuning).options();
    if opts.snap && (args.sam.is_none() || args.masks.is_none()) {
        bail!(
            "city-part snapping needs --sam (the scene's SAM lists) and --masks (the kept masks); \
             give both, or --no-snap"
        );
    }
    let split = args.split.split(colmap::read_model(&args.colmap)?)?;
    // The training views the raycast traced, at its resolution (a run's lower work
    // resolution and its choice of training views).
    let rc: crate::raycast::RaycastSummary = crate::layout::Summary::read(&args.raycast)?;
    let sizes: std::collections::HashMap<&str, (usize, usize)> = rc
        .per_view
        .iter()
        .map(|v| (v.name.as_str(), (v.width as usize, v.height as usize)))
        .collect();
    let train =
        crate::camera::views_at_sizes(&split.train, |v| sizes.get(v.name.as_str()).copied())
            .map_err(|(stem, found, camera)| {
                anyhow::anyhow!(
                    "{}: view {stem} was traced at {}×{}, its camera is {}×{}",
                    args.raycast.display(),
                    found.0,
                    found.1,
                    camera.0,
                    camera.1
                )
            })?;
    let entities = semantics::read(&args.citymodel.join("semantics.json"))?;
    let s = fuse::run(
        &fuse::FuseInputs {
            views: &train,
            associate: &args.associate,
            raycast: &args.raycast,
            entities: &entities,
            sam: args.sam.as_deref(),
            features: args.features.as_deref(),
            kept: args.masks.as_deref(),
        },
        &opts,
        &args.out,
    )?;
    for w in &s.warnings {
        eprintln!("warning: {w}");
    }
    println!(
        "fused {} views: {} labels ({} city, {} image, Δ = {}){} in {:.1} s → {}",
        s.views,
        s.labels,
        s.city_labels,
        s.image_labels,
        s.delta,
        match &s.snap {
            Some(st) => format!(
                ", {} masks snapped ({} px to parts, {} px to surfaces)",
                st.snapped, st.pixels_to_part, st.pixels_to_surface
            ),
            None => String::new(),
        },
        s.timing.total_s,
        args.out.display()
    );
    Ok(())
}
