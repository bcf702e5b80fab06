//! `gs4city synth`: write a SIMULATED scene folder with exact ground truth from real CityGML.
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crate::synth::{self, Preset, SynthConfig};

/// The presets on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PresetArg {
    /// The 2 bundled buildings, 14 views.
    Small,
    /// The 27-building Ingolstadt block, 128 views.
    Street,
}

impl From<PresetArg> for Preset {
    fn from(p: PresetArg) -> Preset {
        match p {
            PresetArg::Small => Preset::Small,
            PresetArg::Street => Preset::Street,
        }
    }
}

#[derive(Debug, Args)]
pub struct SynthArgs {
    /// Preset: `small` (the 2 bundled buildings, 14 views) or `street` (27-building Ingolstadt block).
    #[arg(long, value_enum)]
    preset: Option<PresetArg>,
    /// TOML configuration (docs/synth.md); its keys override the preset's.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Random seed (overrides the config's `seed`).
    #[arg(long)]
    seed: Option<u64>,
    /// CityGML files or folders (override the preset's / config's `citygml`).
    #[arg(long, num_args = 1..)]
    citygml: Vec<PathBuf>,
    /// Share of windows and doors removed from the city model handed to the pipeline (0–1;
    /// 1 = an LoD2 model), drawn with the seed; the ground truth keeps them (config key
    /// `model.drop_openings`; the dropped ids go to the SIMULATED `gt/model_edit.json`).
    #[arg(long)]
    drop_openings: Option<f64>,
    /// A SIMULATED city: NXxNY copies of the input blocks side by side (e.g. `2x2`; config key
    /// `city.blocks`, gap `city.spacing`), ids suffixed `_r<copy>`, objects and views per copy,
    /// every image rendered from the whole city.
    #[arg(long, value_parser = parse_blocks)]
    blocks: Option<[usize; 2]>,
    /// Output scene folder.
    #[arg(long)]
    out: PathBuf,
}

/// `NXxNY` (e.g. `4x4`) → `[NX, NY]`.
fn parse_blocks(s: &str) -> Result<[usize; 2], String> {
    let bad = || format!("`{s}`: give copies along x and y as NXxNY, e.g. 2x2");
    let (a, b) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    Ok([
        a.trim().parse().map_err(|_| bad())?,
        b.trim().parse().map_err(|_| bad())?,
    ])
}

pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    let base = match args.preset {
        Some(p) => SynthConfig::preset(p.into()),
        None => SynthConfig::default(),
    };
    let mut cfg = match &args.config {
        Some(path) => SynthConfig::load(path, base)?,
        None => base,
    };
    if let Some(s) = args.seed {
        cfg.seed = s;
    }
    if let Some(d) = args.drop_openings {
        cfg.model.drop_openings = d;
    }
    if !args.citygml.is_empty() {
        cfg.citygml = args.citygml.clone();
    }
    if let Some(b) = args.blocks {
        cfg.city.blocks = b;
    }
    if cfg.citygml.is_empty() {
        if args.preset == Some(PresetArg::Street) {
            anyhow::bail!(
                "the street preset reads the 27-building Ingolstadt block, found neither at \
                 ../shared/data/citygml/ingolstadt_north nor beside the executable: give --citygml DIR"
            );
        }
        if args.preset == Some(PresetArg::Small) {
            crate::bundled::citygml_dir()?;
        }
        anyhow::bail!(
            "no CityGML input: give --citygml FILES…, a --preset, or `citygml` in --config"
        );
    }
    cfg.validate(std::path::Path::new("<command line>"))?;
    let s = synth::run(&cfg, &args.out)
        .with_context(|| format!("synth into {}", args.out.display()))?;
    println!(
        "gs4city synth (SIMULATED scene): {} Gaussians, {} views ({} test), {} objects, {:.1} s → {}",
        s.gaussians,
        s.views,
        s.test_views.len(),
        s.objects.as_array().map_or(0, |a| a.len()),
        s.timing.get("total_s").copied().unwrap_or(0.0),
        args.out.display()
    );
    Ok(())
}
