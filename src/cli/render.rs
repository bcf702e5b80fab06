//! `gs4city render`: render a 3DGS PLY into every (or selected) COLMAP view.
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;

use super::groups::{CacheTuning, ConfigArg, merged};
use crate::render::{self, PreparedScene, RenderOptions};
use crate::splat::{self, InvalidPolicy, ReadOptions};
use crate::{colmap, fsutil};

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// Pre-trained 3DGS scene (INRIA PLY layout).
    #[arg(long)]
    ply: PathBuf,
    /// COLMAP sparse model folder (cameras, images: .bin or .txt).
    #[arg(long)]
    colmap: PathBuf,
    /// Only these views (image names or stems, comma-separated). Default: every view.
    #[arg(long, value_delimiter = ',')]
    views: Vec<String>,
    /// Background colour, three numbers in 0..1.
    #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = [0.0, 0.0, 0.0])]
    background: Vec<f32>,
    /// Antialiased mode (opacity × √(det Σ / det(Σ + 0.3 I)), as gsplat).
    #[arg(long)]
    antialiased: bool,
    /// Drop Gaussians with NaN/Inf values or a zero quaternion (counted) instead of failing.
    #[arg(long)]
    drop_invalid: bool,
    /// Also render per-Gaussian feature channels: the PLY properties `<PREFIX>0`, `<PREFIX>1`, …
    /// (e.g. `obj_dc_` of a trained `semantic.ply`) → `<stem>.features.npy` (float32 C×H×W).
    #[arg(long, value_name = "PREFIX", conflicts_with = "cache")]
    features: Option<String>,
    /// Write the contributions cache instead of images: per view `<stem>.contrib` with the
    /// per-pixel top-k (Gaussian id, α·T) lists, alpha and expected depth.
    #[arg(long)]
    cache: bool,
    #[command(flatten)]
    config: ConfigArg,
    #[command(flatten, next_help_heading = "The cache (--cache; config [cache])")]
    tuning: CacheTuning,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    // Validate.
    if args.background.iter().any(|c| !(0.0..=1.0).contains(c)) {
        bail!(
            "--background needs three numbers in 0..1, got {:?}",
            args.background
        );
    }
    let cache_options = merged(&args.config.load()?.cache, &args.tuning).options();
    if args.cache {
        cache_options.validate()?;
    }
    let mut views = colmap::read_model(&args.colmap)?;
    if !args.views.is_empty() {
        let wanted: Vec<&str> = args.views.iter().map(|s| s.trim()).collect();
        views.retain(|v| wanted.iter().any(|w| *w == v.name || *w == v.stem()));
        for w in &wanted {
            if !views.iter().any(|v| *w == v.name || *w == v.stem()) {
                bail!("--views: no image named '{w}' in {}", args.colmap.display());
            }
        }
    }
    let policy = if args.drop_invalid {
        InvalidPolicy::Drop
    } else {
        InvalidPolicy::Error
    };
    let (gaussians, report) = splat::read_ply(
        &args.ply,
        &ReadOptions {
            invalid: policy,
            ..Default::default()
        },
    )?;
    let options = RenderOptions {
        background: [args.background[0], args.background[1], args.background[2]],
        antialiased: args.antialiased,
        ..Default::default()
    };
    let mut channels = Vec::new();
    if let Some(prefix) = &args.features {
        while let Some(p) = gaussians.extra(&format!("{prefix}{}", channels.len())) {
            channels.push(p);
        }
        if channels.is_empty() {
            bail!(
                "--features {prefix}: {} has no property {prefix}0",
                args.ply.display()
            );
        }
    }
    // Run.
    let mut scene = PreparedScene::new(&gaussians)
        .with_context(|| format!("preparing {}", args.ply.display()))?;
    render::check_inputs(&scene, &views).with_context(|| {
        format!(
            "{} with the views of {}",
            args.ply.display(),
            args.colmap.display()
        )
    })?;
    if args.cache {
        let s = render::cache::build(&scene, &views, &cache_options, &args.out)?;
        println!(
            "cached the contributions of {} views ({}, {:.0} MB) in {:.2} s → {}",
            s.views.len(),
            s.options.describe(),
            s.bytes as f64 / 1e6,
            s.total_s,
            args.out.display()
        );
        return Ok(());
    }
    if !channels.is_empty() {
        let n = gaussians.len();
        let mut data = vec![0.0f32; n * channels.len()];
        for (c, p) in channels.iter().enumerate() {
            for (i, v) in p.values.iter().enumerate() {
                data[i * channels.len() + c] = *v as f32;
            }
        }
        scene = scene.with_features(channels.len(), data)?;
    }
    let summary = render::render_to_dir(&scene, &views, &args.out, &options)?;
    let mut json = serde_json::to_value(&summary)?;
    json["ply"] = serde_json::to_value(&report)?;
    fsutil::write_json(&args.out.join("summary.json"), &json)?;
    println!(
        "rendered {} views of {} Gaussians in {:.2} s ({:.2e} Gaussians/s) → {}",
        views.len(),
        summary.gaussians,
        summary.render_s,
        summary.gaussians_per_s,
        args.out.display()
    );
    if report.dropped_non_finite + report.dropped_zero_quaternion > 0 {
        println!(
            "dropped {} non-finite and {} zero-quaternion Gaussians",
            report.dropped_non_finite, report.dropped_zero_quaternion
        );
    }
    Ok(())
}
