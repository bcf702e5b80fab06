//! `gs4city lift`: closed-form weighted vote of city-model labels into the Gaussians.
use std::path::PathBuf;

use anyhow::bail;
use clap::Args;

use crate::lift::{self, LiftConfig, LiftOptions};

#[derive(Debug, Args)]
pub struct LiftArgs {
    /// Pre-trained 3DGS scene (INRIA PLY).
    #[arg(long)]
    ply: PathBuf,
    /// COLMAP sparse model folder.
    #[arg(long)]
    colmap: PathBuf,
    /// Output folder of `gs4city raycast` (per view <stem>.ids.npy).
    #[arg(long)]
    raycast: PathBuf,
    /// Output folder of `gs4city citymodel` (semantics.json).
    #[arg(long)]
    citymodel: PathBuf,
    /// Background bias γ in [-1, 1] (FlashSplat), added to the normalised background vote.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    gamma: f32,
    /// Contributions per pixel kept for the vote (top-k by weight); 0 = all.
    #[arg(long, default_value_t = 16)]
    top_k: usize,
    /// Every N-th view (sorted by name) is a test view, not voted on (3DGS --eval: 8); 0 = none.
    #[arg(long, default_value_t = 8)]
    test_every: usize,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: &LiftArgs) -> anyhow::Result<()> {
    if !(-1.0..=1.0).contains(&args.gamma) {
        bail!("--gamma must lie in [-1, 1], got {}", args.gamma);
    }
    let cfg = LiftConfig {
        ply: args.ply.clone(),
        colmap: args.colmap.clone(),
        raycast: args.raycast.clone(),
        citymodel: args.citymodel.clone(),
        out: args.out.clone(),
        options: LiftOptions::new(args.top_k, args.gamma),
        test_every: args.test_every,
        predict_k: 16,
    };
    let s = lift::run(&cfg)?;
    let t = &s["timing"];
    println!(
        "lifted labels into {} Gaussians ({} assigned) from {} training views: render {:.2} s, accumulate {:.2} s, assign {:.3} s; {} test-view maps → {}",
        s["gaussians"],
        s["assigned"],
        s["train_views"].as_array().map_or(0, |v| v.len()),
        t["render_s"].as_f64().unwrap_or(0.0),
        t["accumulate_s"].as_f64().unwrap_or(0.0),
        t["assign_s"].as_f64().unwrap_or(0.0),
        s["test_views"].as_array().map_or(0, |v| v.len()),
        args.out.display()
    );
    Ok(())
}
