//! `gs4city masks`: foundation-mask filtering against the city model (paper §3.2), with the
//! model-free depth test and the mask-free source.
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;

use super::groups::{ConfigArg, MasksTuning, merged};
use crate::alignment::Alignment;
use crate::cache::Cache;
use crate::colmap;
use crate::masks::{self, MasksInputs};
use crate::scene::Scene;

#[derive(Debug, Args)]
pub struct MasksArgs {
    /// Scene folder (masks/<stem>.json SAM lists, optional features/, images/, sparse/0).
    #[arg(long)]
    scene: PathBuf,
    /// Output folder of `gs4city raycast` (<stem>.ids.npy, <stem>.depth.npy).
    #[arg(long)]
    raycast: PathBuf,
    /// Contributions cache (`gs4city render --cache`, or a run's `render/`): the 3DGS depth of
    /// the geometric test and the mask-free source.
    #[arg(long)]
    cache: Option<PathBuf>,
    /// Output folder of `gs4city citymodel` (its alignment.json gives the scale of τ_occ);
    /// default: the scene's citymodel/alignment.json, else scale 1.
    #[arg(long)]
    citymodel: Option<PathBuf>,
    #[command(flatten)]
    config: ConfigArg,
    #[command(flatten, next_help_heading = "Filtering (config [masks])")]
    tuning: MasksTuning,
    /// Only these views (comma-separated stems); default: every view of the COLMAP model.
    #[arg(long, value_delimiter = ',')]
    views: Vec<String>,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: &MasksArgs) -> anyhow::Result<()> {
    let opts = merged(&args.config.load()?.masks, &args.tuning).options()?;
    let scene = Scene::open(&args.scene)?;
    let mut views = colmap::read_model(&scene.sparse)?;
    if !args.views.is_empty() {
        for s in &args.views {
            if !views.iter().any(|v| &v.stem() == s) {
                bail!("--views: no view {s:?} in {}", scene.sparse.display());
            }
        }
        views.retain(|v| args.views.contains(&v.stem()));
    }
    let cache = match &args.cache {
        Some(c) => Some(
            Cache::open(c)
                .with_context(|| format!("opening the contributions cache {}", c.display()))?,
        ),
        None => None,
    };
    // The views the cache holds, at its resolution (a run's lower work resolution).
    if let Some(c) = &cache {
        views = c.views_as_cached(&views)?;
    }
    let align = args
        .citymodel
        .as_ref()
        .map(|d| d.join("alignment.json"))
        .or_else(|| scene.alignment.clone());
    let scale = match &align {
        Some(p) => Alignment::read(p)?.scale,
        None => 1.0,
    };
    let s = masks::run(
        &MasksInputs {
            scene: &scene,
            views: &views,
            raycast: &args.raycast,
            cache: cache.as_ref(),
            alignment_scale: scale,
        },
        &opts,
        &args.out,
    )?;
    let rules: Vec<String> = s.rules.iter().map(|(k, n)| format!("{k} {n}")).collect();
    println!(
        "kept {} of {} masks in {} views ({:?} source, {:?} test) in {:.2} s; rules: {}; → {}",
        s.kept,
        s.input,
        s.views.len(),
        s.source,
        s.test,
        s.timing.total_s,
        rules.join(", "),
        args.out.display()
    );
    Ok(())
}
