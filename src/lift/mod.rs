//! The `lift` stage: the closed-form weighted vote (FlashSplat) that lifts per-view label maps —
//! the fused maps of the `fuse` stage, or `M_city` of the raycast alone — into the Gaussians,
//! through the contributions cache.
//!
//! For every Gaussian `i` and label `n` (a fused label id, or background −1 for pixels no label
//! covers) the vote accumulates `A[i][n] = Σ_views Σ_pixels α_i·T_i · [M(p) = n]` (in `f64`) over
//! the pixels whose cached list holds the Gaussian. The votes are L1-normalised per Gaussian, a
//! bias `γ` is added to the background entry, and the argmax is taken (ties: the smaller id).
//! Views are processed in name order and pixels in raster order, so the result does not depend
//! on the thread count. Test views are predicted per pixel from the same cache: the label whose
//! Gaussians carry the most weight, where the transmitted remainder `1 − α` and the truncated mass
//! vote for "none".
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::cache::{CacheError, ViewContrib, predict};
use crate::classes;
use crate::idmap::LabelMaps;
use crate::prediction::{GaussianLabels, PredictionError, write_gaussians, write_prediction};
use crate::vote::{VoteError, VoteStats, vote};

/// The stage's options are the vote's (`γ`).
pub type LiftOptions = crate::vote::VoteOptions;

/// Errors of the lift stage.
#[derive(Debug, thiserror::Error)]
pub enum LiftError {
    #[error(transparent)]
    Cache(#[from] CacheError),
    #[error(transparent)]
    Npy(#[from] crate::npy::NpyError),
    #[error("{path}: {why}")]
    Labels { path: PathBuf, why: String },
    #[error("no training views (every view is a test view)")]
    NoTrainingViews,
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Fs(#[from] crate::fsutil::FsError),
    #[error(transparent)]
    Image(#[from] crate::imageio::ImageError),
    #[error(transparent)]
    Vote(#[from] VoteError),
    #[error(transparent)]
    Prediction(#[from] PredictionError),
}

/// Everything the stage reads (what the vote reads).
pub type LiftInputs<'a> = crate::vote::VoteInputs<'a>;

/// Timing of the stage.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LiftTiming {
    pub vote_s: f64,
    pub write_s: f64,
    pub predict_s: f64,
    pub total_s: f64,
}

/// The stage's `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LiftSummary {
    pub gaussians: usize,
    /// Gaussians with a label.
    pub assigned: usize,
    /// Invalid Gaussians of the input PLY (non-finite or out-of-range values, zero
    /// quaternion): kept in place in `semantic.ply` and `gaussians.npy`, labelled −1.
    #[serde(default)]
    pub invalid: usize,
    pub gaussians_per_class: BTreeMap<String, usize>,
    pub train_views: Vec<String>,
    pub test_views: Vec<String>,
    pub options: LiftOptions,
    pub labels_source: LabelMaps,
    pub stats: VoteStats,
    pub timing: LiftTiming,
}

impl crate::layout::Summary for LiftSummary {}

/// Runs the stage: the vote over the training views, `gaussians.npy`, `semantic.ply`, the
/// test-view predictions, and `summary.json` (last).
pub fn run(inp: &LiftInputs<'_>, opts: &LiftOptions, out: &Path) -> Result<LiftSummary, LiftError> {
    let t0 = Instant::now();
    if inp.train.is_empty() {
        return Err(LiftError::NoTrainingViews);
    }
    crate::fsutil::create_dir(out)?;
    let _ = std::fs::remove_file(out.join("summary.json"));
    let gate = crate::vote::CityGate::for_inputs(inp, opts.city_gate_m, opts.centre_gate)?;
    let prior = crate::vote::ModelPrior::for_inputs(inp, opts, gate.as_ref().map(|g| g.centres()))?;
    let (assignments, stats) = vote(
        inp.cache,
        inp.train,
        inp.maps,
        gate.as_ref(),
        prior.as_ref(),
        opts,
    )?;
    let t_vote = t0.elapsed().as_secs_f64();
    let label: Vec<i32> = assignments.iter().map(|a| a.label).collect();
    let class: Vec<i32> = label.iter().map(|&l| inp.labels.class_of(l)).collect();
    if let Some(l) = label
        .iter()
        .find(|&&l| l >= 0 && inp.labels.get(l).is_none())
    {
        // Only on this error path: find the first map and pixel holding it, to name them.
        let at = inp.train.iter().find_map(|v| {
            // The size the vote read the map at: its cache view's.
            let c = inp.cache.load(&v.stem()).ok()?;
            let (w, h) = (c.width, c.height);
            let map = inp.maps.read(&v.stem(), w, h).ok()?;
            let p = map.iter().position(|&x| x == *l)?;
            Some((inp.maps.file(&v.stem()), p % w, p / w))
        });
        return Err(match at {
            Some((path, x, y)) => LiftError::Labels {
                path,
                why: format!("label {l} at pixel (x {x}, y {y}) is not in the label table"),
            },
            None => LiftError::Labels {
                path: inp.maps.dir().to_path_buf(),
                why: format!("label {l} of a label map is not in the label table"),
            },
        });
    }
    // The labelled PLY and the test views' predictions are independent (each serial work):
    // side by side.
    let (written, predicted) = rayon::join(
        || {
            let t = Instant::now();
            let invalid = write_gaussians(
                inp.ply,
                out,
                &GaussianLabels {
                    label: &label,
                    class: &class,
                    extra: vec![(
                        "label_confidence".into(),
                        assignments.iter().map(|a| a.confidence).collect(),
                    )],
                },
                inp.labels,
                inp.entities,
            )?;
            Ok::<_, LiftError>((invalid, t.elapsed().as_secs_f64()))
        },
        || {
            let t = Instant::now();
            let (mut c, mut buf) = (ViewContrib::empty(), Vec::new());
            for v in inp.test {
                inp.cache.load_into(&v.stem(), &mut c, &mut buf)?;
                crate::vote::check_view_size(inp.cache, v, &c)?;
                let (cm, lm) = predict(&c, &label, &class);
                write_prediction(out, &v.stem(), c.width, c.height, &cm, &lm)?;
            }
            Ok::<_, LiftError>(t.elapsed().as_secs_f64())
        },
    );
    let (invalid, write_s) = written?;
    let predict_s = predicted?;
    let mut per_class = BTreeMap::new();
    for &c in &class {
        *per_class
            .entry(classes::name(c).to_string())
            .or_insert(0usize) += 1;
    }
    let summary = LiftSummary {
        gaussians: label.len(),
        assigned: label.iter().filter(|&&l| l >= 0).count(),
        invalid,
        gaussians_per_class: per_class,
        train_views: inp.train.iter().map(|v| v.stem()).collect(),
        test_views: inp.test.iter().map(|v| v.stem()).collect(),
        options: *opts,
        labels_source: inp.maps.clone(),
        stats,
        timing: LiftTiming {
            vote_s: t_vote,
            write_s,
            predict_s,
            total_s: t0.elapsed().as_secs_f64(),
        },
    };
    crate::layout::Summary::write(&summary, out)?;
    crate::progress::done(
        "lift",
        &format!(
            "{} of {} Gaussians labelled from {} views, {} test views predicted",
            summary.assigned,
            summary.gaussians,
            inp.train.len(),
            inp.test.len()
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}
