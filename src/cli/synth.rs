//! `gs4city synth`: write a SIMULATED scene folder with exact ground truth from real CityGML.
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crate::synth::{self, Preset, SynthConfig};

#[derive(Debug, Args)]
pub struct SynthArgs {
    /// Preset: `small` (bundled data/, ~14 views) or `street` (27-building Ingolstadt block).
    #[arg(long, value_enum)]
    preset: Option<Preset>,
    /// TOML configuration (docs/synth.md); its keys override the preset's.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Random seed (overrides the config's `seed`).
    #[arg(long)]
    seed: Option<u64>,
    /// CityGML files or folders (override the preset's / config's `citygml`).
    #[arg(long, num_args = 1..)]
    citygml: Vec<PathBuf>,
    /// Output scene folder.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    let base = match args.preset {
        Some(p) => SynthConfig::preset(p),
        None => SynthConfig::default(),
    };
    let mut cfg = match &args.config {
        Some(path) => SynthConfig::load(path, base)?,
        None => base,
    };
    if let Some(s) = args.seed {
        cfg.seed = s;
    }
    if !args.citygml.is_empty() {
        cfg.citygml = args.citygml.clone();
    }
    if cfg.citygml.is_empty() {
        anyhow::bail!(
            "no CityGML input: give --citygml FILES…, a --preset, or `citygml` in --config"
        );
    }
    cfg.validate(std::path::Path::new("<command line>"))?;
    let s = synth::run(&cfg, &args.out)
        .with_context(|| format!("synth into {}", args.out.display()))?;
    println!(
        "gs4city synth (SIMULATED scene): {} Gaussians, {} views ({} test), {} objects, {:.1} s → {}",
        s["gaussians"],
        s["views"],
        s["test_views"].as_array().map_or(0, |a| a.len()),
        s["objects"].as_array().map_or(0, |a| a.len()),
        s["timings"]["total_s"].as_f64().unwrap_or(0.0),
        args.out.display()
    );
    Ok(())
}
