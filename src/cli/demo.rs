//! `gs4city demo`: the bundled data through the whole pipeline — synth (small preset, a
//! SIMULATED scene on real CityGML) → run → report.html — ending with the metrics and the path.
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crate::run::{self, RunOptions};
use crate::synth::{self, Preset, SynthConfig};

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Output folder (scene/, run/ with report.html).
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Random seed of the simulated scene.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    let mut cfg = SynthConfig::preset(Preset::Small);
    if cfg.citygml.is_empty() {
        crate::bundled::citygml_dir()?;
    }
    cfg.seed = args.seed;
    cfg.validate(std::path::Path::new("<demo>"))?;
    let scene_dir = args.out.join("scene");
    let s = synth::run(&cfg, &scene_dir)
        .with_context(|| format!("synth into {}", scene_dir.display()))?;
    println!(
        "1/2 synth: SIMULATED scene on the real CityGML of {}: {} Gaussians, {} views ({} test) → {}",
        cfg.citygml
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", "),
        s.gaussians,
        s.views,
        s.test_views.len(),
        scene_dir.display()
    );
    let run_dir = args.out.join("run");
    let r = run::run(
        &scene_dir,
        &run_dir,
        &RunOptions {
            force: true,
            ..Default::default()
        },
    )?;
    println!("2/2 run: every stage, then report.html\n");
    super::run::print_run(&r);
    Ok(())
}
