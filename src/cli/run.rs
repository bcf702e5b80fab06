//! `gs4city run`: a scene folder through every stage (citymodel → raycast → lift → eval).
use std::path::PathBuf;

use anyhow::bail;
use clap::Args;

use crate::lift::LiftOptions;
use crate::run::{self, RunOptions};

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Scene folder (DESIGN.md): images/, sparse/0/, point_cloud.ply, citymodel/*.gml (+ alignment.json), optional gt/.
    #[arg(long)]
    pub scene: PathBuf,
    /// Part-pass depth tolerance τ in metres.
    #[arg(long, default_value_t = 0.5)]
    pub tau: f64,
    /// Single-pass raycasting (no part pass), for comparison.
    #[arg(long)]
    pub single_pass: bool,
    /// Background bias γ of the vote, in [-1, 1].
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub gamma: f32,
    /// Contributions per pixel kept for the vote; 0 = all.
    #[arg(long, default_value_t = 16)]
    pub top_k: usize,
    /// Every N-th view (by name) is a test view (3DGS --eval: 8).
    #[arg(long, default_value_t = 8)]
    pub test_every: usize,
    /// Rerun every stage even when its output is complete.
    #[arg(long)]
    pub force: bool,
    /// Output folder (one sub-folder per stage).
    #[arg(long)]
    pub out: PathBuf,
}

impl RunArgs {
    /// Validated options.
    pub fn options(&self) -> anyhow::Result<RunOptions> {
        if !(self.tau.is_finite() && self.tau >= 0.0) {
            bail!(
                "--tau must be a finite number ≥ 0 (metres), got {}",
                self.tau
            );
        }
        if !(-1.0..=1.0).contains(&self.gamma) {
            bail!("--gamma must lie in [-1, 1], got {}", self.gamma);
        }
        Ok(RunOptions {
            tau_m: self.tau,
            single_pass: self.single_pass,
            lift: LiftOptions::new(self.top_k, self.gamma),
            test_every: self.test_every,
            force: self.force,
        })
    }
}

/// Prints the stage table and the headline metrics of a run.
pub fn print_run(reports: &[run::StageReport], metrics: Option<&serde_json::Value>) {
    println!("{:<10} {:>9}  output", "stage", "seconds");
    for r in reports {
        println!(
            "{:<10} {:>9.2}  {}{}",
            r.stage,
            r.seconds,
            r.out.display(),
            if r.resumed { "  (resumed)" } else { "" }
        );
    }
    if let Some(m) = metrics {
        let p = |v: &serde_json::Value| {
            v.as_f64()
                .map_or("   –".to_string(), |x| format!("{:5.1}", 100.0 * x))
        };
        let (pa, d) = (&m["paper"], &m["dataset"]);
        println!(
            "\n{:<18} | {:>5} {:>5} {:>5} {:>5} | {:>5} | {:>5} {:>5} {:>5} {:>6} {:>5} {:>6} {:>5}",
            "metrics (%)",
            "IoU",
            "Acc",
            "Prec",
            "Rec",
            "mIoU",
            "Door",
            "Roof",
            "Wall",
            "Window",
            "Car",
            "Person",
            "Tree"
        );
        let classes = ["door", "roof", "wall", "window", "car", "person", "tree"];
        let mut row = format!(
            "{:<18} | {} {} {} {} | {} |",
            "paper (per image)",
            p(&pa["coarse"]["iou"]["mean"]),
            p(&pa["coarse"]["accuracy"]["mean"]),
            p(&pa["coarse"]["precision"]["mean"]),
            p(&pa["coarse"]["recall"]["mean"]),
            p(&pa["miou"]["mean"])
        );
        for c in classes {
            row.push_str(&format!(" {:>5}", p(&pa["iou"][c]["mean"])));
        }
        println!("{row}");
        let cm = &d["coarse"];
        let mut row = format!(
            "{:<18} | {} {} {} {} | {} |",
            "dataset",
            p(&cm["iou"]),
            p(&cm["accuracy"]),
            p(&cm["precision"]),
            p(&cm["recall"]),
            p(&d["fine"]["miou"])
        );
        for c in classes {
            row.push_str(&format!(" {:>5}", p(&d["fine"]["iou"][c])));
        }
        println!("{row}");
    }
}

pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    let opts = args.options()?;
    let (reports, metrics) = run::run(&args.scene, &args.out, &opts)?;
    print_run(&reports, metrics.as_ref());
    Ok(())
}
