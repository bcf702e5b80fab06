//! `gs4city train`: per-Gaussian identity codes and a classifier learned from the per-view
//! labels through the contributions cache (paper §3.3), starting from the vote.
use std::path::PathBuf;

use clap::Args;

use super::groups::{ConfigArg, SplitArgs, TrainTuning, VoteTuning, merged};
use crate::train;

#[derive(Debug, Args)]
pub struct TrainArgs {
    #[command(flatten, next_help_heading = "Inputs")]
    src: super::lift::LabelSourceArgs,
    #[command(flatten)]
    split: SplitArgs,
    #[command(flatten)]
    config: ConfigArg,
    #[command(flatten, next_help_heading = "Training (config [train])")]
    train: TrainTuning,
    #[command(flatten, next_help_heading = "The initial vote (config [vote])")]
    vote: VoteTuning,
    /// Output folder.
    #[arg(long, help_heading = "Outputs")]
    out: PathBuf,
}

pub fn run(args: &TrainArgs) -> anyhow::Result<()> {
    let cfg = args.config.load()?;
    let opts = merged(&cfg.train, &args.train).options(&merged(&cfg.vote, &args.vote))?;
    let l = args.src.load(&args.split)?;
    let s = train::run(&l.inputs(&args.src.ply), &opts, &args.out)?;
    let last = s.history.last().map_or(0.0, |p| p.ce + p.kl);
    println!(
        "trained {} Gaussians ({} labelled, {} changed from the vote, {} classes) in {} iterations ({}), final loss {last:.4}: read {:.1} s, vote {:.1} s, kNN {:.1} s, train {:.1} s, label {:.1} s, write {:.1} s, predict {:.1} s; {} test-view maps → {}",
        s.gaussians,
        s.labelled,
        s.changed_from_vote,
        s.classes,
        s.iterations,
        s.stopped,
        s.timing.read_s,
        s.timing.vote_s,
        s.timing.knn_s,
        s.timing.train_s,
        s.timing.label_s,
        s.timing.write_s,
        s.timing.predict_s,
        s.test_views.len(),
        args.out.display()
    );
    Ok(())
}
