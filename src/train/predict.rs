//! What a trained model says: the label of each Gaussian (the classifier's argmax of its code),
//! per-pixel predictions of a cached view (rendered code → classifier → argmax), and the
//! classifier file.
use std::path::Path;

use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::model::{CHUNK, Model};
use crate::cache::ViewContrib;

/// `classifier.json` (`docs/design.md`): the linear classifier over the label ids, background first.
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

/// How the test views' pixels are read from a trained model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Rule {
    /// The rendered code through the classifier; the label of the largest logit, and its class
    /// (the paper's rule).
    Label,
    /// The rendered code through the classifier; the evaluation class with the largest total
    /// probability (the softmax summed over the labels of each class), and the most probable
    /// label of that class. With thousands of instance labels a pixel's probability is spread
    /// over the labels of one class (neighbouring wall surfaces, say): this reads the class the
    /// metric scores instead of the single strongest label.
    Class,
    /// Each Gaussian's own label (the classifier's argmax of its code) rendered with the vote's
    /// pixel rule (`cache::predict`): the plurality of weight per class, the untracked mass
    /// counting for "none".
    Gaussians,
}

/// Per-pixel `(class map, label map)` of a cached view: the rendered code `Σ w_i e_i` goes
/// through the classifier restricted to `candidates` (sorted classes), read with `Rule::Class`
/// when `by_class`, else `Rule::Label` (ties: the first candidate). Pixels nothing covers
/// (α < 1e-3) are −1 in both.
pub fn predict_view(
    c: &ViewContrib,
    m: &Model<f32>,
    candidates: &[u32],
    class_ids: &[i32],
    eval_class: &dyn Fn(i32) -> i32,
    by_class: bool,
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
    // Evaluation classes (−1 included) as dense slots for the class rule.
    let mut slots: Vec<i32> = cand_eval.clone();
    slots.sort_unstable();
    slots.dedup();
    let cand_slot: Vec<usize> = cand_eval
        .iter()
        .map(|e| slots.binary_search(e).expect("slot"))
        .collect();
    let block = 4 * CHUNK;
    let rows: Vec<(i32, i32)> = (0..npx)
        .step_by(block)
        .collect::<Vec<_>>()
        .into_par_iter()
        .flat_map_iter(|a| {
            let b = (a + block).min(npx);
            let mut mass = vec![0.0f32; slots.len()];
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
                if c.alpha[a + r] < crate::cache::DEPTH_MIN_ALPHA {
                    out.push((-1, -1));
                    continue;
                }
                let zs = zr.as_slice_mut().expect("contiguous");
                for (x, &bb) in zs.iter_mut().zip(&bias) {
                    *x += bb;
                }
                let best = if !by_class {
                    argmax(zs)
                } else {
                    let mx = zs.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                    mass.iter_mut().for_each(|x| *x = 0.0);
                    for (&z, &s) in zs.iter().zip(&cand_slot) {
                        mass[s] += (z - mx).exp();
                    }
                    let top = argmax(&mass);
                    // The strongest label of the winning class.
                    let mut best = usize::MAX;
                    for (j, &s) in cand_slot.iter().enumerate() {
                        if s == top && (best == usize::MAX || zs[j] > zs[best]) {
                            best = j;
                        }
                    }
                    best
                };
                out.push((cand_eval[best], cand_label[best]));
            }
            out
        })
        .collect();
    rows.into_iter().unzip()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache::Contributions;

    /// One pixel whose rendered code gives logits (bg −5, wall A 1, wall B 1, wall C 1,
    /// window 1.5): the strongest single label is the window, but the three wall labels hold
    /// 3e / (3e + e^1.5) ≈ 0.65 of the probability.
    #[test]
    fn class_rule_reads_the_most_probable_class_label_rule_the_strongest_label() {
        // D = 5 one-hot codes; a single Gaussian with code (1, 1, 1, 1, 1.5) and weight 1.
        let d = 5;
        let m = Model {
            dim: d,
            codes: vec![1.0, 1.0, 1.0, 1.0, 1.5],
            weights: Array2::from_shape_fn((5, d), |(r, c)| if r == c { 1.0 } else { 0.0 }),
            bias: vec![-6.0, 0.0, 0.0, 0.0, 0.0],
        };
        let c = ViewContrib {
            width: 2,
            height: 1,
            k: 4,
            gaussians: 1,
            lists: Contributions {
                offsets: vec![0, 1, 1],
                ids: vec![0],
                weights: vec![1.0],
                residual: vec![0.0, 0.0],
            },
            alpha: vec![1.0, 0.0],
            depth: vec![1.0, f32::NAN],
            median: Vec::new(),
        };
        // Labels 10, 11, 12 are walls (class 0), 20 a window (class 2).
        let class_ids = [-1, 10, 11, 12, 20];
        let eval = |l: i32| match l {
            10..=12 => 0,
            20 => 2,
            _ => -1,
        };
        let cand = [0u32, 1, 2, 3, 4];
        let (cm, lm) = predict_view(&c, &m, &cand, &class_ids, &eval, false);
        assert_eq!((cm[0], lm[0]), (2, 20));
        let (cm, lm) = predict_view(&c, &m, &cand, &class_ids, &eval, true);
        // The wall class wins; its first strongest label (ties: the first candidate) is 10.
        assert_eq!((cm[0], lm[0]), (0, 10));
        // Uncovered pixels stay −1 under both rules.
        assert_eq!((cm[1], lm[1]), (-1, -1));
    }
}
