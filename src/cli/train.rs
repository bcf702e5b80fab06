//! `gs4city train`: per-Gaussian identity codes and a classifier learned from the per-view
//! labels through the contributions cache (paper §3.3), starting from the vote.
use std::path::PathBuf;

use clap::Args;

use crate::train::predict::Rule;
use crate::train::{self, Init, Softmax, TrainOptions};

#[derive(Debug, Args)]
pub struct TrainArgs {
    #[command(flatten)]
    src: super::lift::LabelSourceArgs,
    /// Every N-th view (sorted by name) is a test view, not trained on; 0 = none.
    #[arg(long, default_value_t = 8)]
    test_every: usize,
    /// Most iterations (one view and --pixels pixels each).
    #[arg(long, default_value_t = TrainOptions::default().iterations)]
    iterations: usize,
    /// Pixels sampled per iteration.
    #[arg(long, default_value_t = TrainOptions::default().pixels)]
    pixels: usize,
    /// Training pixels lie on a grid of this stride (1 = every pixel, 2 = a quarter, …).
    #[arg(long, default_value_t = TrainOptions::default().stride)]
    stride: usize,
    /// Cut the cached contribution lists to their K largest weights (0 = as cached).
    #[arg(long, default_value_t = 0)]
    top_k: usize,
    /// Sampled negative classes per softmax (cost independent of the number of labels).
    #[arg(long, default_value_t = 64, conflicts_with = "exact_softmax")]
    negatives: usize,
    /// Evaluate the softmax over every class during training (exact; cost grows with K).
    #[arg(long)]
    exact_softmax: bool,
    /// Predict test views over every class (exact; slower with many labels).
    #[arg(long)]
    exact_predict: bool,
    /// How test views are predicted: `gaussians` (each Gaussian's learned label rendered with the
    /// vote's pixel rule; best measured, docs/train.md), `label` (rendered code → classifier →
    /// the label of the largest logit, the paper's rule) or `class` (the class of largest total
    /// probability).
    #[arg(long, value_enum, default_value_t = RuleArg::Gaussians)]
    rule: RuleArg,
    /// Weight μ ∈ [0, 1] of the class-level term of the 2D loss (the right class, whichever of
    /// its labels); 0 = the label cross-entropy alone.
    #[arg(long, default_value_t = TrainOptions::default().class_weight)]
    class_weight: f64,
    /// Code dimension D.
    #[arg(long, default_value_t = TrainOptions::default().dim)]
    dim: usize,
    /// Adam learning rate of the codes.
    #[arg(long, default_value_t = TrainOptions::default().lr_codes)]
    lr_codes: f64,
    /// Adam learning rate of the classifier.
    #[arg(long, default_value_t = TrainOptions::default().lr_classifier)]
    lr_classifier: f64,
    /// Weight λ of the 3D KNN-KL term (0 = off).
    #[arg(long, default_value_t = TrainOptions::default().kl_lambda)]
    kl_lambda: f64,
    /// The 3D term every N iterations (0 = never).
    #[arg(long, default_value_t = TrainOptions::default().kl_every)]
    kl_every: usize,
    /// Neighbours per Gaussian in the 3D term.
    #[arg(long, default_value_t = TrainOptions::default().kl_k)]
    kl_k: usize,
    /// Gaussians sampled per 3D step.
    #[arg(long, default_value_t = TrainOptions::default().kl_samples)]
    kl_samples: usize,
    /// Start from random codes instead of the vote.
    #[arg(long)]
    random_init: bool,
    /// Background bias γ of the initial vote, in [-1, 1].
    /// Default: −1 with fused (mask) supervision, −0.5 with the city model alone.
    #[arg(long, allow_negative_numbers = true)]
    gamma: Option<f32>,
    /// Depth gate of the initial vote's city votes, metres (as `lift`); 0 = off.
    #[arg(long, default_value_t = crate::vote::CITY_GATE_M)]
    city_gate_m: f32,
    /// No centre gate of the initial vote's city votes (as `lift`).
    #[arg(long)]
    no_centre_gate: bool,
    /// Stop when the windowed loss falls by less than this fraction twice in a row (0 = never).
    #[arg(long, default_value_t = TrainOptions::default().tol)]
    tol: f64,
    /// Iterations per loss window.
    #[arg(long, default_value_t = TrainOptions::default().window)]
    window: usize,
    /// Random seed (same seed and inputs → same outputs, any thread count).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum RuleArg {
    Label,
    Class,
    Gaussians,
}

pub fn run(args: &TrainArgs) -> anyhow::Result<()> {
    let opts = TrainOptions {
        dim: args.dim,
        iterations: args.iterations,
        pixels: args.pixels,
        stride: args.stride,
        top_k: args.top_k,
        softmax: if args.exact_softmax {
            Softmax::Exact
        } else {
            Softmax::Sampled {
                negatives: args.negatives,
            }
        },
        lr_codes: args.lr_codes,
        lr_classifier: args.lr_classifier,
        kl_lambda: args.kl_lambda,
        kl_every: args.kl_every,
        kl_k: args.kl_k,
        kl_samples: args.kl_samples,
        init: if args.random_init {
            Init::Random
        } else {
            Init::Vote
        },
        gamma: args.gamma,
        city_gate_m: args.city_gate_m,
        centre_gate: !args.no_centre_gate,
        window: args.window,
        tol: args.tol,
        seed: args.seed,
        exact_predict: args.exact_predict,
        rule: match args.rule {
            RuleArg::Label => Rule::Label,
            RuleArg::Class => Rule::Class,
            RuleArg::Gaussians => Rule::Gaussians,
        },
        class_weight: args.class_weight,
        ..TrainOptions::default()
    };
    opts.validate()?;
    let l = args.src.load(args.test_every)?;
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
