//! The `eval` subcommand: arguments and the call into [`crate::eval::run`]; writes
//! `metrics.json` and `summary.json` and prints the paper-shaped tables. With `--by-query R`,
//! the paper's query-driven evaluation of a run instead ([`crate::eval::by_query`]):
//! `metrics_by_query.json`, printed next to the run's class-map evaluation.
use std::path::PathBuf;

use anyhow::{Context, bail};

use crate::eval;
use crate::layout::{Mode, Summary};
use crate::selection::{MaskRule, TextOptions};

/// Evaluate predicted class maps against ground truth (coarse and fine, paper and dataset level).
#[derive(Debug, Clone, clap::Args)]
pub struct EvalArgs {
    /// Folder of predictions `<stem>.class.npy` (int32 H×W, −1 = no class).
    #[arg(long, value_name = "DIR", required_unless_present = "by_query")]
    pub pred: Option<PathBuf>,
    /// Folder of ground truth `<stem>.class.npy` (int32 H×W, −1 = ignore); with --by-query,
    /// default: the run's scene's gt/.
    #[arg(long, value_name = "DIR", required_unless_present = "by_query")]
    pub gt: Option<PathBuf>,
    /// Only these views (stems, comma-separated), e.g. the test views; default: every GT view
    /// (with --by-query: the run's test views).
    #[arg(long, value_delimiter = ',')]
    pub views: Vec<String>,
    /// Query-driven evaluation of the run given with --run (paper §4): the coarse level from
    /// the mask of the "building" selection, each fine class from the mask of its own selection.
    #[arg(long, conflicts_with = "pred", requires = "run")]
    pub by_query: bool,
    /// With --by-query: the run (`gs4city run --scene S --out R`).
    #[arg(long, value_name = "R", requires = "by_query")]
    pub run: Option<PathBuf>,
    /// With --by-query: the scene folder; default: the one in R/run.json.
    #[arg(long, value_name = "S", requires = "by_query")]
    pub scene: Option<PathBuf>,
    /// With --by-query: vote (R/lift) or learned (R/train); default: learned when R/train exists.
    #[arg(long, requires = "by_query")]
    pub mode: Option<Mode>,
    /// With --by-query: the pixel rule of the masks.
    #[arg(long, default_value = "argmax")]
    pub mask_rule: MaskRule,
    /// Output folder (metrics.json, summary.json; with --by-query: metrics_by_query.json).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

/// Runs the evaluation, writes `summary.json`, prints warnings and the tables.
pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    if let (true, Some(r)) = (args.by_query, &args.run) {
        return run_by_query(args, r);
    }
    let (Some(pred), Some(gt)) = (&args.pred, &args.gt) else {
        bail!("give --pred and --gt (or --by-query R)");
    };
    for (flag, dir) in [("--pred", pred), ("--gt", gt)] {
        if !dir.is_dir() {
            bail!("{flag} {}: not a directory", dir.display());
        }
    }
    let stems = (!args.views.is_empty()).then_some(args.views.as_slice());
    let (summary, _) = eval::run_for(pred, gt, &args.out, stems, None).context("evaluating")?;
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

fn run_by_query(args: &EvalArgs, run: &std::path::Path) -> anyhow::Result<()> {
    let t = std::time::Instant::now();
    let _lock = super::query::lock_run(run)?;
    let sr = super::query::open_run(
        &super::groups::RunRef {
            run: run.to_path_buf(),
            scene: args.scene.clone(),
            mode: args.mode,
        },
        true,
    )?;
    let gt =
        match &args.gt {
            Some(g) => g.clone(),
            None => sr.scene.gt.clone().with_context(|| {
                format!("scene {} has no gt/: give --gt", sr.scene.root.display())
            })?,
        };
    let stems = if args.views.is_empty() {
        sr.test_views()?
    } else {
        args.views.clone()
    };
    if stems.is_empty() {
        bail!(
            "no views to evaluate: {} holds no test-view predictions; give --views",
            run.join(sr.mode.dir()).display()
        );
    }
    let cache = sr.cache()?;
    let r = eval::by_query::evaluate(
        &sr,
        &cache,
        &gt,
        &stems,
        args.mask_rule,
        TextOptions::default(),
    )?;
    crate::fsutil::create_dir(&args.out)?;
    let path = args.out.join("metrics_by_query.json");
    crate::fsutil::write_json(&path, &r)?;
    match eval::EvalSummary::read(&run.join("eval")) {
        Ok(s) => println!(
            "class-map evaluation ({}):\n{}",
            run.join("eval").display(),
            s.tables
        ),
        Err(_) => println!(
            "(no class-map evaluation in {})",
            run.join("eval").display()
        ),
    }
    println!(
        "query-driven evaluation ({} views; queries: {}):",
        stems.len(),
        {
            r.queries
                .iter()
                .map(|(k, v)| format!("{k}: {v}"))
                .collect::<Vec<_>>()
                .join("; ")
        }
    );
    print!("{}", r.tables);
    println!("→ {} in {:.2} s", path.display(), t.elapsed().as_secs_f64());
    Ok(())
}
