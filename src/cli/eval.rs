//! The `eval` subcommand: arguments and the call into [`crate::eval::run`]; writes
//! `metrics.json` and `summary.json` and prints the paper-shaped tables.
use std::path::PathBuf;

use anyhow::{Context, bail};

use crate::eval;

/// Evaluate predicted class maps against ground truth (coarse and fine, paper and dataset level).
#[derive(Debug, Clone, clap::Args, serde::Serialize)]
pub struct EvalArgs {
    /// Folder of predictions `<stem>.class.npy` (int32 H×W, −1 = no class).
    #[arg(long, value_name = "DIR")]
    pub pred: PathBuf,
    /// Folder of ground truth `<stem>.class.npy` (int32 H×W, −1 = ignore).
    #[arg(long, value_name = "DIR")]
    pub gt: PathBuf,
    /// Only these views (stems, comma-separated), e.g. the test views; default: every GT view.
    #[arg(long, value_delimiter = ',')]
    pub views: Vec<String>,
    /// Output folder (metrics.json, summary.json).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

/// Runs the evaluation, writes `summary.json`, prints warnings and the tables.
pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    for (flag, dir) in [("--pred", &args.pred), ("--gt", &args.gt)] {
        if !dir.is_dir() {
            bail!("{flag} {}: not a directory", dir.display());
        }
    }
    let stems = (!args.views.is_empty()).then_some(args.views.as_slice());
    let (summary, _) =
        eval::run_for(&args.pred, &args.gt, &args.out, stems, None).context("evaluating")?;
    for w in &summary.warnings {
        eprintln!("warning: {w}");
    }
    println!(
        "{} views evaluated ({} coarse, {} fine; {} resized) in {:.3} s → {}",
        summary.images,
        summary.images - summary.coarse_skipped_no_valid_gt,
        summary.images - summary.fine_skipped_no_fine_gt,
        summary.resized_predictions,
        summary.seconds,
        args.out.join("metrics.json").display()
    );
    print!("{}", summary.tables);
    Ok(())
}
