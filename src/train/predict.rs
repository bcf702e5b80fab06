//! What a trained model says: the label of each Gaussian (the classifier's argmax of its code),
//! per-pixel predictions of a cached view (rendered code → classifier → argmax), and the
//! classifier file.
use std::path::Path;

use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::model::{CHUNK, Model};
use crate::render::cache::ViewContrib;

/// `classifier.json` (DESIGN.md): the linear classifier over the label ids, background first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Classifier {
    /// Code dimension `D`.
    pub dim: usize,
    /// Label id per row (`labels[0] = −1`, background).
    pub labels: Vec<i32>,
    /// `K × D` (K rows including the background row).
    pub weights: Vec<Vec<f32>>,
    /// `K`.
    pub bias: Vec<f32>,
}

impl Classifier {
    /// The classifier of a model with classes `class_ids`.
    pub fn of(m: &Model<f32>, class_ids: &[i32]) -> Classifier {
        Classifier {
            dim: m.dim,
            labels: class_ids.to_vec(),
            weights: m.weights.rows().into_iter().map(|r| r.to_vec()).collect(),
            bias: m.bias.clone(),
        }
    }

    /// Reads `classifier.json`, checking its shapes.
    pub fn read(path: &Path) -> Result<Classifier, super::TrainError> {
        let c: Classifier = crate::fsutil::read_json(path)?;
        let k = c.labels.len();
        if c.bias.len() != k || c.weights.len() != k || c.weights.iter().any(|r| r.len() != c.dim) {
            return Err(super::TrainError::Labels {
                path: path.to_path_buf(),
                why: format!(
                    "{k} labels, {} bias values, {} weight rows: shapes disagree (dim {})",
                    c.bias.len(),
                    c.weights.len(),
                    c.dim
                ),
            });
        }
        Ok(c)
    }
}

/// Index of the largest value (ties: the first).
fn argmax(z: &[f32]) -> usize {
    let mut b = 0;
    for (i, &x) in z.iter().enumerate() {
        if x > z[b] {
            b = i;
        }
    }
    b
}

/// Per Gaussian, the class with the largest logit `W e + b` over every class (exact; blocked
/// matrix products, parallel over fixed blocks).
pub fn gaussian_classes(m: &Model<f32>) -> Vec<u32> {
    let n = m.gaussians();
    let block = 4 * CHUNK;
    (0..n)
        .step_by(block)
        .collect::<Vec<_>>()
        .into_par_iter()
        .flat_map_iter(|a| {
            let b = (a + block).min(n);
            let e = ArrayView2::from_shape((b - a, m.dim), &m.codes[a * m.dim..b * m.dim])
                .expect("codes shape");
            let mut z = e.dot(&m.weights.t());
            for mut row in z.rows_mut() {
                for (x, &bb) in row.iter_mut().zip(&m.bias) {
                    *x += bb;
                }
            }
            z.rows()
                .into_iter()
                .map(|r| argmax(r.as_slice().expect("contiguous")) as u32)
                .collect::<Vec<_>>()
        })
        .collect()
}

/// The classes a view's prediction is evaluated over: the background and the class of every
/// Gaussian in the view's lists (out of `classes`).
pub fn view_candidates(c: &ViewContrib, gaussian_class: &[u32], classes: usize) -> Vec<u32> {
    let mut seen = vec![false; classes.max(1)];
    seen[0] = true;
    for &g in &c.lists.ids {
        seen[gaussian_class[g as usize] as usize] = true;
    }
    (0..seen.len() as u32)
        .filter(|&i| seen[i as usize])
        .collect()
}

/// Per-pixel `(class map, label map)` of a cached view: the rendered code `Σ w_i e_i` goes
/// through the classifier restricted to `candidates` (sorted classes); the label map holds the
/// label id of the largest logit (ties: the first candidate) and the class map its evaluation
/// class. Pixels nothing covers (α < 1e-3) are −1 in both.
pub fn predict_view(
    c: &ViewContrib,
    m: &Model<f32>,
    candidates: &[u32],
    class_ids: &[i32],
    eval_class: &dyn Fn(i32) -> i32,
) -> (Vec<i32>, Vec<i32>) {
    let npx = c.pixels();
    let d = m.dim;
    let mut w = Array2::<f32>::zeros((candidates.len(), d));
    let mut bias = Vec::with_capacity(candidates.len());
    for (j, &k) in candidates.iter().enumerate() {
        w.row_mut(j).assign(&m.weights.row(k as usize));
        bias.push(m.bias[k as usize]);
    }
    let cand_label: Vec<i32> = candidates.iter().map(|&k| class_ids[k as usize]).collect();
    let cand_eval: Vec<i32> = cand_label.iter().map(|&l| eval_class(l)).collect();
    let block = 4 * CHUNK;
    let rows: Vec<(i32, i32)> = (0..npx)
        .step_by(block)
        .collect::<Vec<_>>()
        .into_par_iter()
        .flat_map_iter(|a| {
            let b = (a + block).min(npx);
            let mut e = Array2::<f32>::zeros((b - a, d));
            for p in a..b {
                let (ids, ws) = c.pixel(p);
                let mut row = e.row_mut(p - a);
                let row = row.as_slice_mut().expect("contiguous");
                for (&g, &wt) in ids.iter().zip(ws) {
                    for (o, &x) in row.iter_mut().zip(m.code(g as usize)) {
                        *o += wt * x;
                    }
                }
            }
            let mut z = e.dot(&w.t());
            let mut out = Vec::with_capacity(b - a);
            for (r, mut zr) in z.rows_mut().into_iter().enumerate() {
                if c.alpha[a + r] < crate::render::DEPTH_MIN_ALPHA {
                    out.push((-1, -1));
                    continue;
                }
                let zs = zr.as_slice_mut().expect("contiguous");
                for (x, &bb) in zs.iter_mut().zip(&bias) {
                    *x += bb;
                }
                let best = argmax(zs);
                out.push((cand_eval[best], cand_label[best]));
            }
            out
        })
        .collect();
    rows.into_iter().unzip()
}
