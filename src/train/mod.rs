//! The `train` stage (paper §3.3): per-Gaussian identity codes and a linear classifier learned
//! on the CPU from the contributions cache, with the geometry frozen.
//!
//! Each Gaussian `i` carries a code `e_i ∈ R^D` (D = 16). A pixel's rendered code is the fixed
//! sparse sum `E(p) = Σ_{i ∈ list(p)} w_i e_i` over its cached list (`w_i = α_i T_i`), and a
//! linear classifier `z = W E + b` maps it to `C = K + 1` classes (background and the `K` label
//! ids of the training maps, city entities or fused labels alike). The loss is
//!
//! * 2D: the cross-entropy of `z` against the label maps over the sampled pixels, averaged over
//!   all of them (not a mean of unequal chunk means) and divided by `ln C`;
//! * 3D, every `kl_every` iterations: `λ/(m k C) Σ_j Σ_{n ∈ kNN(j)} KL(p_j ‖ p_n)` over `m`
//!   Gaussians drawn uniformly, `p = softmax(W e + b)`, the kNN graph built once over centres.
//!
//! Training starts from the closed-form vote (`lift`'s, without its city-model prior): every voted label gets a random unit
//! direction `u`, its Gaussians the code `u`, the classifier `W = β u`, `b = 0`, and the
//! background `W = 0`, `b = β/2` (so a Gaussian's argmax is its vote and a pixel needs half its
//! opacity from a label to show it). Each iteration takes one training view (epochs in a seeded
//! random order), samples pixels of it, and evaluates the softmax over the view's classes plus
//! sampled negatives (see `model`); Adam updates only the rows that got a gradient. A run stops
//! after `iterations`, or earlier when the windowed loss stops falling by `tol`.
//!
//! Everything random comes from one seeded generator used in a fixed order, and parallel work
//! is cut into fixed chunks added in order: the same inputs and seed give the same outputs for
//! any number of threads.
mod kl;
pub mod knn;
pub mod model;
pub mod pool;
pub mod predict;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use ndarray::Array2;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::cache;
use crate::classes;
use crate::idmap::LabelMaps;
use crate::prediction;
use crate::prediction::{GaussianLabels, PredictionError};
use crate::progress::Bar;
use crate::vote::{VoteError, VoteInputs, VoteOptions};
use model::{Active, Grads, Model, Optimiser, PixelBatch};
use pool::Pool;

/// Errors of the train stage.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Cache(#[from] crate::cache::CacheError),
    #[error(transparent)]
    Vote(#[from] VoteError),
    #[error(transparent)]
    Prediction(#[from] PredictionError),
    #[error(transparent)]
    IdMap(#[from] crate::idmap::IdMapError),
    #[error(transparent)]
    Npy(#[from] crate::npy::NpyError),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Fs(#[from] crate::fsutil::FsError),
    #[error("{path}: {why}")]
    Labels { path: PathBuf, why: String },
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error("no training views (every view is a test view)")]
    NoTrainingViews,
}

/// How the softmax over the classes is evaluated during training.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Softmax {
    /// Over every class (cost per pixel grows with K).
    Exact,
    /// Over the classes present in the batch plus `negatives` uniformly sampled others, each
    /// standing for `|rest| / negatives` classes (cost independent of K).
    Sampled { negatives: usize },
}

/// Where training starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Init {
    /// From the closed-form vote (the classifier's argmax of each code is its vote).
    Vote,
    /// Small random codes and classifier (the reference's start; for comparison).
    Random,
}

/// Options of the stage (defaults: `docs/design.md`, "Stage contract", and the measurements in
/// docs/train.md).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrainOptions {
    /// Code dimension D.
    pub dim: usize,
    /// Most iterations.
    pub iterations: usize,
    /// Pixels sampled per iteration (from one view).
    pub pixels: usize,
    /// Training pixels lie on a grid of this stride (1 = every pixel; 2 = a quarter).
    pub stride: usize,
    /// Contribution lists cut to their `top_k` largest weights (0 = as cached), for training
    /// and prediction.
    pub top_k: usize,
    pub softmax: Softmax,
    pub lr_codes: f64,
    pub lr_classifier: f64,
    /// λ of the 3D term (0 = off).
    pub kl_lambda: f64,
    /// The 3D term is added every this many iterations (0 = never).
    pub kl_every: usize,
    /// Neighbours per Gaussian (k).
    pub kl_k: usize,
    /// Gaussians sampled per 3D step (m).
    pub kl_samples: usize,
    pub init: Init,
    /// Logit scale β of the vote initialisation.
    pub init_scale: f64,
    /// Background bias γ of the initial vote (as `lift`; `None`: by the label source).
    #[serde(default)]
    pub gamma: Option<f32>,
    /// Depth gate of the initial vote's city votes, metres (as `lift`; 0 = off).
    #[serde(default = "default_city_gate")]
    pub city_gate_m: f32,
    /// The centre gate of the initial vote's city votes (as `lift`).
    #[serde(default = "yes")]
    pub centre_gate: bool,
    /// Iterations per loss window (progress, history, stopping rule).
    pub window: usize,
    /// Stop when the mean loss of two consecutive windows fell by less than this fraction
    /// (0 = run all iterations).
    pub tol: f64,
    pub seed: u64,
    /// Predict test views over every class instead of the classes of the view's Gaussians.
    pub exact_predict: bool,
    /// How the test views are predicted from the model.
    pub rule: predict::Rule,
    /// Weight μ of the class-level term of the 2D loss (0 = labels only; see
    /// `model::cross_entropy_mixed`).
    pub class_weight: f64,
}

fn yes() -> bool {
    true
}

fn default_city_gate() -> f32 {
    crate::vote::CITY_GATE_M
}

impl Default for TrainOptions {
    fn default() -> Self {
        TrainOptions {
            dim: 16,
            iterations: 3000,
            pixels: 8192,
            stride: 2,
            top_k: 0,
            softmax: Softmax::Sampled { negatives: 64 },
            lr_codes: 2.5e-3,
            lr_classifier: 5e-4,
            kl_lambda: 2.0,
            kl_every: 5,
            kl_k: 5,
            kl_samples: 1000,
            init: Init::Vote,
            init_scale: 8.0,
            gamma: None,
            city_gate_m: crate::vote::CITY_GATE_M,
            centre_gate: true,
            window: 200,
            tol: 0.005,
            seed: 0,
            exact_predict: false,
            rule: predict::Rule::Gaussians,
            class_weight: 0.0,
        }
    }
}

impl TrainOptions {
    /// Checks the options.
    pub fn validate(&self) -> Result<(), TrainError> {
        use crate::check::{End, at_least, range};
        range("dim", self.dim, End::Closed(1.0), End::Closed(256.0))?;
        at_least("pixels", self.pixels, 1)?;
        at_least("stride", self.stride, 1)?;
        for (name, v) in [
            ("lr_codes", self.lr_codes),
            ("lr_classifier", self.lr_classifier),
            ("kl_lambda", self.kl_lambda),
            ("init_scale", self.init_scale),
            ("tol", self.tol),
            ("class_weight", self.class_weight),
        ] {
            crate::check::non_negative(name, v)?;
        }
        crate::check::unit("class_weight", self.class_weight)?;
        if let Softmax::Sampled { negatives } = self.softmax {
            at_least("negatives", negatives, 1)?;
        }
        at_least("window", self.window, 1)?;
        VoteOptions {
            gamma: self.gamma,
            city_gate_m: self.city_gate_m,
            centre_gate: self.centre_gate,
            ..Default::default()
        }
        .validate()?;
        Ok(())
    }
}

/// The stage reads what the vote reads.
pub type TrainInputs<'a> = VoteInputs<'a>;

/// One window of the loss history.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LossPoint {
    /// Iterations done at the end of the window.
    pub iteration: usize,
    /// Mean 2D loss (CE / ln C) over the window.
    pub ce: f64,
    /// Mean 3D loss (λ-weighted) over the window's 3D steps (0 without any).
    pub kl: f64,
}

/// Timing of the stage.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TrainTiming {
    /// Reading the views, the vote and the training pixels.
    pub read_s: f64,
    pub vote_s: f64,
    pub knn_s: f64,
    pub train_s: f64,
    /// Per-Gaussian argmax over every class.
    pub label_s: f64,
    pub write_s: f64,
    pub predict_s: f64,
    pub total_s: f64,
}

/// The stage's `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainSummary {
    pub gaussians: usize,
    /// Gaussians with a label.
    pub labelled: usize,
    /// Gaussians whose label differs from the vote's.
    pub changed_from_vote: usize,
    /// Classifier rows (background + label ids of the training maps).
    pub classes: usize,
    pub gaussians_per_class: BTreeMap<String, usize>,
    /// Training pixels kept (all views) and the bytes their lists take.
    pub pool_pixels: usize,
    pub pool_bytes: usize,
    pub iterations: usize,
    /// `"iterations"` or `"converged"` (the stopping rule).
    pub stopped: String,
    pub history: Vec<LossPoint>,
    pub train_views: Vec<String>,
    pub test_views: Vec<String>,
    pub options: TrainOptions,
    pub labels_source: LabelMaps,
    pub timing: TrainTiming,
    /// Where the training time went.
    pub step_times: StepTimes,
    /// Peak resident memory of the process when the stage ended (MB).
    pub peak_rss_mb: Option<f64>,
}

impl crate::layout::Summary for TrainSummary {}

/// The initial model: see the module docs. `vote_class[i]` is Gaussian `i`'s voted class
/// (0 = background / no vote).
pub fn init_model(n: usize, classes: usize, vote_class: &[u32], opts: &TrainOptions) -> Model<f32> {
    let d = opts.dim;
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed ^ 0x1d3e_17a1_c0de);
    let gauss = |rng: &mut ChaCha8Rng| -> f64 {
        // Box–Muller: a standard normal from two uniforms.
        let u1: f64 = rng.random_range(f64::EPSILON..1.0);
        let u2: f64 = rng.random();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    };
    match opts.init {
        Init::Vote => {
            let beta = opts.init_scale;
            let mut dirs = Array2::<f32>::zeros((classes, d));
            for c in 1..classes {
                let v: Vec<f64> = (0..d).map(|_| gauss(&mut rng)).collect();
                let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-12);
                for j in 0..d {
                    dirs[[c, j]] = (v[j] / norm) as f32;
                }
            }
            spread_directions(&mut dirs, beta);
            let mut codes = vec![0.0f32; n * d];
            for (i, &c) in vote_class.iter().enumerate() {
                if c > 0 {
                    codes[i * d..(i + 1) * d]
                        .copy_from_slice(dirs.row(c as usize).as_slice().expect("row"));
                }
            }
            let mut bias = vec![0.0f32; classes];
            bias[0] = (beta / 2.0) as f32;
            Model {
                dim: d,
                codes,
                weights: dirs.mapv(|x| x * beta as f32),
                bias,
            }
        }
        Init::Random => Model {
            dim: d,
            codes: (0..n * d).map(|_| (0.1 * gauss(&mut rng)) as f32).collect(),
            weights: Array2::from_shape_fn((classes, d), |_| {
                (gauss(&mut rng) / (d as f64).sqrt()) as f32
            }),
            bias: vec![0.0; classes],
        },
    }
}

/// Spreads the label directions (rows `1..` of `dirs`, unit vectors) over the sphere by
/// gradient steps on `Σ_a log Σ_{b≠a} exp(β u_a·u_b)`: the log-partition that the other labels
/// add to a pixel showing only label `a`. Random directions in 16 dimensions leave a few
/// close pairs whose `exp(β cos)` dominates that sum; spreading lowers the initial loss without
/// changing which label a code prefers (each code is its label's direction). The cost is
/// `O(K² D)` per step; the number of steps shrinks for large `K` (≤ 2·10¹⁰ multiply-adds in
/// all).
fn spread_directions(dirs: &mut Array2<f32>, beta: f64) {
    let k = dirs.nrows().saturating_sub(1);
    let d = dirs.ncols();
    if k < 2 || beta <= 0.0 {
        return;
    }
    let work = 2.0 * (k as f64).powi(2) * d as f64;
    let steps = ((2e10 / work) as usize).clamp(1, 100);
    let b = beta as f32;
    let mut u = dirs.slice(ndarray::s![1.., ..]).to_owned();
    for step in 0..steps {
        let g = u.dot(&u.t());
        // Row-wise softmax over b ≠ a of β·cos.
        let mut sm = g.mapv(|x| b * x);
        for (a, mut row) in sm.rows_mut().into_iter().enumerate() {
            row[a] = f32::NEG_INFINITY;
            let mx = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let mut sum = 0.0f32;
            for x in row.iter_mut() {
                *x = (*x - mx).exp();
                sum += *x;
            }
            row.mapv_inplace(|x| x / sum);
        }
        let sym = &sm + &sm.t();
        let grad = sym.dot(&u);
        let eta = 0.1 * (1.0 - step as f32 / steps as f32) + 0.01;
        for (mut row, gr) in u.rows_mut().into_iter().zip(grad.rows()) {
            let gn = gr.dot(&gr).sqrt().max(1e-12);
            row.zip_mut_with(&gr, |x, &g| *x -= eta * g / gn);
            let n = row.dot(&row).sqrt().max(1e-12);
            row.mapv_inplace(|x| x / n);
        }
    }
    dirs.slice_mut(ndarray::s![1.., ..]).assign(&u);
}

/// The training state, for the stage and for benchmarks that look inside it.
pub struct Trainer<'a> {
    pub pool: &'a Pool,
    pub knn: &'a knn::KnnGraph,
    pub opts: TrainOptions,
    pub model: Model<f32>,
    pub grads: Grads<f32>,
    pub opt: Optimiser<f32>,
    /// Per Gaussian, the class it was last seen to prefer (the sampled 3D term's candidates).
    pub hint: Vec<u32>,
    /// Per class, its group for the class-level loss term (empty: no such term).
    pub group: Vec<u32>,
    pub rng: ChaCha8Rng,
    pub times: StepTimes,
    order: Vec<usize>,
    pos: usize,
    pub iteration: usize,
}

/// Seconds spent per phase of the iterations so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct StepTimes {
    /// Sampling pixels and classes (and the 3D term's Gaussians).
    pub sample_s: f64,
    pub ce_s: f64,
    pub kl_s: f64,
    pub adam_s: f64,
}

/// Losses of one iteration.
#[derive(Debug, Clone, Copy, Default)]
pub struct StepLoss {
    pub ce: f64,
    pub kl: Option<f64>,
}

impl<'a> Trainer<'a> {
    /// A trainer starting from `model`.
    pub fn new(
        pool: &'a Pool,
        knn: &'a knn::KnnGraph,
        model: Model<f32>,
        hint: Vec<u32>,
        opts: &TrainOptions,
    ) -> Trainer<'a> {
        Trainer {
            pool,
            knn,
            opts: *opts,
            grads: Grads::new(&model),
            opt: Optimiser::new(&model, opts.lr_codes, opts.lr_classifier),
            model,
            hint,
            group: Vec::new(),
            rng: ChaCha8Rng::seed_from_u64(opts.seed),
            times: StepTimes::default(),
            order: Vec::new(),
            pos: 0,
            iteration: 0,
        }
    }

    /// The next view (epochs in a seeded random order over non-empty views).
    fn next_view(&mut self) -> usize {
        if self.pos >= self.order.len() {
            self.order = (0..self.pool.views.len())
                .filter(|&v| !self.pool.views[v].is_empty())
                .collect();
            self.order.shuffle(&mut self.rng);
            self.pos = 0;
        }
        self.pos += 1;
        self.order[self.pos - 1]
    }

    /// Samples the next iteration's pixels and their active classes.
    pub fn sample_batch(&mut self) -> (PixelBatch, Active) {
        let v = &self.pool.views[self.next_view()];
        let p = self.opts.pixels.min(v.len());
        let mut idx = rand::seq::index::sample(&mut self.rng, v.len(), p).into_vec();
        idx.sort_unstable();
        let mut b = PixelBatch::default();
        for r in idx {
            let (ids, ws) = v.pixel(r);
            b.push(ids, ws, v.targets[r]);
        }
        let c = self.model.classes();
        let active = match self.opts.softmax {
            Softmax::Exact => Active::full(c),
            Softmax::Sampled { negatives } => {
                let mut members = v.classes.clone();
                members.push(0);
                Active::sampled(c, members, negatives, &mut self.rng)
            }
        };
        (b, active)
    }

    /// Samples the 3D term's Gaussians, their neighbours and active classes: every class
    /// (exact), or per anchor the classes its `k + 1` Gaussians were last seen to prefer, the
    /// background, and a shared uniform sample of negatives (sampled).
    pub fn sample_kl(&mut self) -> (Vec<u32>, Vec<u32>, Vec<Active>) {
        let n = self.model.gaussians();
        let k = self.knn.k;
        let m = self.opts.kl_samples.min(n);
        let anchors: Vec<u32> = rand::seq::index::sample(&mut self.rng, n, m)
            .into_iter()
            .map(|i| i as u32)
            .collect();
        let neighbours: Vec<u32> = anchors
            .iter()
            .flat_map(|&a| self.knn.of(a as usize).iter().copied())
            .collect();
        let c = self.model.classes();
        let actives = match self.opts.softmax {
            Softmax::Exact => vec![Active::full(c)],
            Softmax::Sampled { negatives } => {
                let mut sample: Vec<u32> =
                    rand::seq::index::sample(&mut self.rng, c, negatives.min(c))
                        .into_iter()
                        .map(|i| i as u32)
                        .collect();
                sample.sort_unstable();
                (0..anchors.len())
                    .map(|j| {
                        let mut members = vec![0, self.hint[anchors[j] as usize]];
                        members.extend(
                            neighbours[j * k..(j + 1) * k]
                                .iter()
                                .map(|&g| self.hint[g as usize]),
                        );
                        Active::from_sample(c, members, &sample)
                    })
                    .collect()
            }
        };
        (anchors, neighbours, actives)
    }

    /// Whether iteration `it` (0-based) adds the 3D term.
    fn kl_due(&self, it: usize) -> bool {
        self.opts.kl_every > 0
            && self.opts.kl_lambda > 0.0
            && self.knn.k > 0
            && self.opts.kl_samples > 0
            && (it + 1) % self.opts.kl_every == 0
    }

    /// One iteration: losses, gradients, Adam step.
    pub fn step(&mut self) -> StepLoss {
        let c = self.model.classes() as f64;
        let t = Instant::now();
        let (batch, active) = self.sample_batch();
        self.times.sample_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let ce = if batch.is_empty() {
            0.0
        } else {
            let scale = 1.0 / (batch.len() as f64 * c.ln());
            model::cross_entropy_mixed(
                &self.model,
                &batch,
                &active,
                &self.group,
                self.opts.class_weight,
                scale,
                &mut self.grads,
            )
        };
        self.times.ce_s += t.elapsed().as_secs_f64();
        let mut kl = None;
        if self.kl_due(self.iteration) {
            let t = Instant::now();
            let (anchors, neighbours, actives) = self.sample_kl();
            self.times.sample_s += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let k = self.knn.k;
            let scale = self.opts.kl_lambda / (anchors.len() as f64 * k as f64 * c);
            let (l, best) = model::knn_kl(
                &self.model,
                &anchors,
                &neighbours,
                k,
                &actives,
                scale,
                &mut self.grads,
            );
            for (j, &a) in anchors.iter().enumerate() {
                self.hint[a as usize] = best[j * (k + 1)];
                for i in 0..k {
                    self.hint[neighbours[j * k + i] as usize] = best[j * (k + 1) + 1 + i];
                }
            }
            kl = Some(l);
            self.times.kl_s += t.elapsed().as_secs_f64();
        }
        let t = Instant::now();
        self.opt.step(&mut self.model, &mut self.grads);
        self.times.adam_s += t.elapsed().as_secs_f64();
        self.iteration += 1;
        StepLoss { ce, kl }
    }
}

/// Per class (label id `class_ids[c]`), its evaluation class as a group number (class + 1;
/// 0 for the background and labels without a class).
pub fn eval_groups(class_ids: &[i32], table: &crate::labels::LabelTable) -> Vec<u32> {
    class_ids
        .iter()
        .map(|&l| (table.class_of(l) + 1).max(0) as u32)
        .collect()
}

/// The classes of the vote per Gaussian.
pub fn vote_classes(pool: &Pool) -> Vec<u32> {
    pool.vote
        .iter()
        .map(|a| pool.class_of_label(a.label).unwrap_or(0))
        .collect()
}

/// Runs the training loop to its end (iterations or the stopping rule); returns the history
/// and why it stopped.
pub fn train_loop(tr: &mut Trainer<'_>, bar: &Bar) -> (Vec<LossPoint>, String) {
    let opts = tr.opts;
    let mut history: Vec<LossPoint> = Vec::new();
    let (mut ce_sum, mut kl_sum, mut kl_n, mut n) = (0.0, 0.0, 0usize, 0usize);
    let mut flat = 0;
    let mut stopped = "iterations".to_string();
    for it in 0..opts.iterations {
        let l = tr.step();
        ce_sum += l.ce;
        n += 1;
        if let Some(k) = l.kl {
            kl_sum += k;
            kl_n += 1;
        }
        bar.inc(1);
        if (it + 1) % 10 == 0 {
            bar.message(format!("loss {:.4}", ce_sum / n as f64));
        }
        if (it + 1) % opts.window == 0 || it + 1 == opts.iterations {
            let p = LossPoint {
                iteration: it + 1,
                ce: ce_sum / n as f64,
                kl: if kl_n > 0 { kl_sum / kl_n as f64 } else { 0.0 },
            };
            if opts.tol > 0.0
                && let Some(prev) = history.last()
            {
                let prev_total = prev.ce + prev.kl;
                let total = p.ce + p.kl;
                if prev_total - total < opts.tol * prev_total {
                    flat += 1;
                } else {
                    flat = 0;
                }
            }
            history.push(p);
            (ce_sum, kl_sum, kl_n, n) = (0.0, 0.0, 0, 0);
            if flat >= 2 {
                stopped = "converged".to_string();
                break;
            }
        }
    }
    (history, stopped)
}

/// Runs the stage: reads the training views (vote + training pixels), builds the kNN graph,
/// trains, and writes `gaussians.npy`, `semantic.ply` (with `obj_dc_*`), `classifier.json`,
/// the test-view predictions and `summary.json` (last).
pub fn run(
    inp: &TrainInputs<'_>,
    opts: &TrainOptions,
    out: &Path,
) -> Result<TrainSummary, TrainError> {
    let t0 = Instant::now();
    opts.validate()?;
    if inp.train.is_empty() {
        return Err(TrainError::NoTrainingViews);
    }
    crate::fsutil::create_dir(out)?;
    let _ = std::fs::remove_file(out.join("summary.json"));
    let n = inp.cache.summary.gaussians;
    let mut timing = TrainTiming::default();

    let t = Instant::now();
    let gate = crate::vote::CityGate::for_inputs(inp, opts.city_gate_m, opts.centre_gate)?;
    let pool = pool::build(
        inp.cache,
        inp.train,
        inp.maps,
        inp.labels,
        gate.as_ref(),
        opts.stride,
        opts.top_k,
        crate::vote::gamma_for(opts.gamma, inp.maps),
    )?;
    timing.read_s = t.elapsed().as_secs_f64() - pool.vote_s;
    timing.vote_s = pool.vote_s;
    let classes = pool.class_ids.len();
    if classes < 2 {
        return Err(TrainError::Labels {
            path: inp.maps.dir().to_path_buf(),
            why: "the training views' label maps hold no label (only background)".into(),
        });
    }

    let t = Instant::now();
    let (gaussians, _) = crate::splat::read_ply(inp.ply, &crate::splat::ReadOptions::KEEP)?;
    if gaussians.len() != n {
        return Err(TrainError::Labels {
            path: inp.ply.to_path_buf(),
            why: format!(
                "{} Gaussians in the PLY, the cache was built for {n}: the cache is stale",
                gaussians.len()
            ),
        });
    }
    // Invalid Gaussians (kept in place, never drawn) sit far outside the scene frame, where
    // they neighbour only each other.
    let far = [4.0 * crate::camera::SCENE_COORD_LIMIT as f32; 3];
    let positions: Vec<[f32; 3]> = (0..n)
        .map(|i| {
            if crate::splat::ply::is_valid(&gaussians, i) {
                gaussians.positions[i]
            } else {
                far
            }
        })
        .collect();
    let knn = knn::build(&positions, opts.kl_k);
    drop(gaussians);
    timing.knn_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let vote_class = vote_classes(&pool);
    let model = init_model(n, classes, &vote_class, opts);
    let mut tr = Trainer::new(&pool, &knn, model, vote_class.clone(), opts);
    tr.group = eval_groups(&pool.class_ids, inp.labels);
    let bar = Bar::new("train", opts.iterations as u64, "it");
    let (history, stopped) = train_loop(&mut tr, &bar);
    bar.finish();
    let iterations = tr.iteration;
    let step_times = tr.times;
    let model = tr.model;
    drop(tr.grads);
    drop(tr.opt);
    timing.train_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let gclass = predict::gaussian_classes(&model);
    let label: Vec<i32> = gclass.iter().map(|&c| pool.class_ids[c as usize]).collect();
    let class: Vec<i32> = label.iter().map(|&l| inp.labels.class_of(l)).collect();
    timing.label_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let d = model.dim;
    let extra = (0..d)
        .map(|j| {
            (
                format!("obj_dc_{j}"),
                (0..n).map(|i| model.codes[i * d + j]).collect(),
            )
        })
        .collect();
    let _invalid = prediction::write_gaussians(
        inp.ply,
        out,
        &GaussianLabels {
            label: &label,
            class: &class,
            extra,
        },
        inp.labels,
        inp.entities,
    )?;
    crate::fsutil::write_json(
        &out.join("classifier.json"),
        &predict::Classifier::of(&model, &pool.class_ids),
    )?;
    timing.write_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let eval_class = |l: i32| inp.labels.class_of(l);
    for v in inp.test {
        let c = inp.cache.load(&v.stem())?;
        let c = pool::truncate(&c, opts.top_k);
        let (cm, lm) = if opts.rule == predict::Rule::Gaussians {
            cache::predict(&c, &label, &class)
        } else {
            let cand = if opts.exact_predict {
                (0..classes as u32).collect()
            } else {
                predict::view_candidates(&c, &gclass, classes)
            };
            let by_class = opts.rule == predict::Rule::Class;
            predict::predict_view(&c, &model, &cand, &pool.class_ids, &eval_class, by_class)
        };
        prediction::write_prediction(out, &v.stem(), c.width, c.height, &cm, &lm)?;
    }
    timing.predict_s = t.elapsed().as_secs_f64();

    let mut per_class = BTreeMap::new();
    for &c in &class {
        *per_class
            .entry(classes::name(c).to_string())
            .or_insert(0usize) += 1;
    }
    timing.total_s = t0.elapsed().as_secs_f64();
    let summary = TrainSummary {
        gaussians: n,
        labelled: label.iter().filter(|&&l| l >= 0).count(),
        changed_from_vote: label
            .iter()
            .zip(&pool.vote)
            .filter(|(l, a)| **l != a.label)
            .count(),
        classes,
        gaussians_per_class: per_class,
        pool_pixels: pool.pixels(),
        pool_bytes: pool.bytes(),
        iterations,
        stopped,
        history,
        train_views: inp.train.iter().map(|v| v.stem()).collect(),
        test_views: inp.test.iter().map(|v| v.stem()).collect(),
        options: *opts,
        labels_source: inp.maps.clone(),
        timing,
        step_times,
        peak_rss_mb: crate::progress::peak_rss_mb(),
    };
    crate::layout::Summary::write(&summary, out)?;
    crate::progress::done(
        "train",
        &format!(
            "{} iterations ({}), {} of {} Gaussians labelled ({} changed from the vote), {} test views predicted",
            summary.iterations,
            summary.stopped,
            summary.labelled,
            summary.gaussians,
            summary.changed_from_vote,
            inp.test.len()
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `Σ_a log Σ_{b≠a} exp(β u_a·u_b)` computed directly.
    fn energy(u: &Array2<f32>, beta: f64) -> f64 {
        let k = u.nrows();
        (1..k)
            .map(|a| {
                (1..k)
                    .filter(|&b| b != a)
                    .map(|b| (beta * f64::from(u.row(a).dot(&u.row(b)))).exp())
                    .sum::<f64>()
                    .ln()
            })
            .sum()
    }

    #[test]
    fn vote_initialisation_reproduces_the_vote_and_spreading_lowers_the_partition() {
        let opts = TrainOptions {
            dim: 4,
            init_scale: 8.0,
            ..TrainOptions::default()
        };
        let classes = 30;
        let vote: Vec<u32> = (0..90).map(|i| (i % classes) as u32).collect();
        let m = init_model(vote.len(), classes, &vote, &opts);
        // Every code's argmax over all classes is its voted class (0: background, zero code).
        for (i, &v) in vote.iter().enumerate() {
            let z: Vec<f32> = (0..classes)
                .map(|c| m.weights.row(c).dot(&ndarray::aview1(m.code(i))) + m.bias[c])
                .collect();
            let best = (0..classes).fold(0, |b, c| if z[c] > z[b] { c } else { b });
            assert_eq!(best as u32, v, "Gaussian {i}");
        }
        // Rows are unit vectors times β, and spreading lowered the energy of random ones.
        let dirs = m.weights.mapv(|x| x / 8.0);
        for r in 1..classes {
            assert!((dirs.row(r).dot(&dirs.row(r)) - 1.0).abs() < 1e-5);
        }
        let mut rng = ChaCha8Rng::seed_from_u64(opts.seed ^ 0x1d3e_17a1_c0de);
        let mut random = Array2::<f32>::zeros((classes, 4));
        for c in 1..classes {
            let v: Vec<f64> = (0..4)
                .map(|_| {
                    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
                    let u2: f64 = rng.random();
                    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
                })
                .collect();
            let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
            for j in 0..4 {
                random[[c, j]] = (v[j] / n) as f32;
            }
        }
        let (before, after) = (energy(&random, 8.0), energy(&dirs, 8.0));
        assert!(after < before - 1.0, "energy {before} → {after}");
    }
}
