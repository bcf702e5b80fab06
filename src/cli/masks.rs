//! `gs4city masks`: foundation-mask filtering against the city model (paper §3.2), with the
//! model-free depth test and the mask-free source.
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;

use crate::alignment::Alignment;
use crate::cache::Cache;
use crate::colmap;
use crate::masks::{self, GsDepth, MasksInputs, MasksOptions, Source, Test};
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
    /// Mask source: auto (SAM lists when the scene has masks/, else depth), sam, depth.
    #[arg(long, default_value = "auto")]
    source: Source,
    /// Disambiguation of high-overlap masks: auto (both with features and a cache, else the one
    /// available, else overlap), features, geometry, both, overlap.
    #[arg(long, default_value = "auto")]
    test: Test,
    /// τ_q: minimum predicted_iou.
    #[arg(long, default_value_t = MasksOptions::default().tau_q)]
    tau_q: f64,
    /// Support-only floor: a mask with floor ≤ predicted_iou < τ_q that passes every other rule
    /// is recorded as `low_quality_support` (the associate stage may let it join a group).
    #[arg(long, default_value_t = MasksOptions::default().support_floor.unwrap_or(0.0))]
    support_floor: f64,
    /// No support-only masks: every predicted_iou < τ_q is `quality` (as in the paper).
    #[arg(long)]
    no_support_floor: bool,
    /// τ_a as a fraction of the image's pixels (τ_a = ⌈f·H·W⌉).
    #[arg(long, default_value_t = MasksOptions::default().area_frac)]
    area_frac: f64,
    /// ρ: building-support overlap from which a mask is disambiguated.
    #[arg(long, default_value_t = MasksOptions::default().rho)]
    rho: f64,
    /// δ: margin of S_fore over S_city.
    #[arg(long, default_value_t = MasksOptions::default().delta, allow_negative_numbers = true)]
    delta: f64,
    /// 3DGS depth of the depth test: median (of the cache's lists, stored by the render stage;
    /// a cache before version 4: from its lists and point_cloud.ply's centres) or expected (the
    /// cache's Σw·z/(1−T)).
    #[arg(long, default_value = "median")]
    gs_depth: GsDepth,
    /// τ_occ in metres (× the alignment scale): how far in front of the city surface the 3DGS
    /// must be.
    #[arg(long, default_value_t = MasksOptions::default().tau_occ_m)]
    tau_occ: f64,
    /// Relative depth tolerance (fraction of the city depth) added to τ_occ.
    #[arg(long, default_value_t = MasksOptions::default().tau_rel)]
    tau_rel: f64,
    /// Radius (pixels) of the local city surface the 3DGS depth is compared with.
    #[arg(long, default_value_t = MasksOptions::default().surface_radius_px)]
    surface_radius: usize,
    /// Do not subtract each city surface's median 3DGS − city depth offset (it absorbs most of
    /// a misalignment).
    #[arg(long)]
    no_surface_bias: bool,
    /// Pixels a surface needs for its own depth offset (else its building's, else none).
    #[arg(long, default_value_t = MasksOptions::default().bias_min_px)]
    bias_min_px: usize,
    /// The surface offsets are clamped to ± this many metres (× the alignment scale).
    #[arg(long, default_value_t = MasksOptions::default().bias_max_m)]
    bias_max: f64,
    /// Share of a mask's depth-evidence pixels that must be in front to call it an occluder.
    #[arg(long, default_value_t = MasksOptions::default().occluder_share)]
    occluder_share: f64,
    /// Share of a mask's pixels that need depth evidence for the depth test to decide.
    #[arg(long, default_value_t = MasksOptions::default().min_evidence)]
    min_evidence: f64,
    /// Keep every low-overlap mask unchecked (the paper's rule); by default low-overlap masks
    /// that the features or the depth show to be building are dropped.
    #[arg(long)]
    keep_low_overlap: bool,
    /// Mask-free source: minimum 3DGS alpha of a pixel.
    #[arg(long, default_value_t = MasksOptions::default().min_alpha)]
    min_alpha: f64,
    /// Mask-free source: relative depth jump that splits two neighbouring pixels.
    #[arg(long, default_value_t = MasksOptions::default().split_rel)]
    split_rel: f64,
    /// Mask-free source: radius (pixels) of the morphological opening of the candidate pixels.
    #[arg(long, default_value_t = MasksOptions::default().open_px)]
    open_px: usize,
    /// Overlay PNGs (kept masks coloured by rule) for this many views.
    #[arg(long, default_value_t = MasksOptions::default().overlays)]
    overlays: usize,
    /// Only these views (comma-separated stems); default: every view of the COLMAP model.
    #[arg(long, value_delimiter = ',')]
    views: Vec<String>,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: &MasksArgs) -> anyhow::Result<()> {
    let opts = MasksOptions {
        source: args.source,
        test: args.test,
        tau_q: args.tau_q,
        support_floor: (!args.no_support_floor).then_some(args.support_floor),
        area_frac: args.area_frac,
        rho: args.rho,
        delta: args.delta,
        gs_depth: args.gs_depth,
        tau_occ_m: args.tau_occ,
        tau_rel: args.tau_rel,
        surface_radius_px: args.surface_radius,
        surface_bias: !args.no_surface_bias,
        bias_min_px: args.bias_min_px,
        bias_max_m: args.bias_max,
        occluder_share: args.occluder_share,
        min_evidence: args.min_evidence,
        low_overlap_check: !args.keep_low_overlap,
        min_alpha: args.min_alpha,
        split_rel: args.split_rel,
        open_px: args.open_px,
        overlays: args.overlays,
    };
    opts.validate()?;
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
