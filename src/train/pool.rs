//! The training pixels, read once: one pass over the training views loads each view's cached
//! contribution lists and label map, adds them to the closed-form vote (`lift::Votes`, the
//! initialisation) and keeps the pixels on a grid of stride `stride` that something covers
//! (α ≥ 1e-3) with their lists and target labels. Label ids are mapped to dense classes:
//! class 0 = background (−1), classes `1..C` = the label ids present in the training maps, in
//! increasing order.
use std::borrow::Cow;
use std::collections::BTreeSet;
use std::time::Instant;

use super::TrainError;
use crate::cache::{Cache, ViewContrib};
use crate::camera::View;
use crate::idmap::LabelMaps;
use crate::labels::LabelTable;
use crate::progress::Bar;
use crate::vote::{self, Votes};

/// Pixels of one view kept for training.
#[derive(Debug, Clone, Default)]
pub struct ViewPool {
    pub stem: String,
    /// `offsets[r]..offsets[r + 1]` are pixel `r`'s entries.
    pub offsets: Vec<u32>,
    pub ids: Vec<u32>,
    pub weights: Vec<f32>,
    /// Label id per kept pixel (−1 background); mapped to classes after the pass.
    pub labels: Vec<i32>,
    /// Target class per kept pixel.
    pub targets: Vec<u32>,
    /// The classes present among the view's kept pixels (sorted).
    pub classes: Vec<u32>,
}

impl ViewPool {
    /// Number of kept pixels.
    pub fn len(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// Whether no pixel was kept.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Pixel `r`'s `(ids, weights)`.
    pub fn pixel(&self, r: usize) -> (&[u32], &[f32]) {
        let (a, b) = (self.offsets[r] as usize, self.offsets[r + 1] as usize);
        (&self.ids[a..b], &self.weights[a..b])
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        (self.offsets.len() + self.ids.len() + self.weights.len() + 2 * self.labels.len()) * 4
    }
}

/// Everything read from the training views.
pub struct Pool {
    pub views: Vec<ViewPool>,
    /// Label id per class (`class_ids[0] = −1`).
    pub class_ids: Vec<i32>,
    /// The vote's assignment per Gaussian.
    pub vote: Vec<vote::Assignment>,
    pub load_s: f64,
    pub vote_s: f64,
}

impl Pool {
    /// The class of a label id (`None` for an id absent from the training maps).
    pub fn class_of_label(&self, label: i32) -> Option<u32> {
        if label < 0 {
            return Some(0);
        }
        self.class_ids[1..]
            .binary_search(&label)
            .ok()
            .map(|i| i as u32 + 1)
    }

    /// Pixels kept over all views.
    pub fn pixels(&self) -> usize {
        self.views.iter().map(ViewPool::len).sum()
    }

    /// Bytes held by the pixel lists.
    pub fn bytes(&self) -> usize {
        self.views.iter().map(ViewPool::bytes).sum()
    }
}

/// The view with each list cut to its `k` largest weights, kept in depth order (ties: the nearer
/// entry), the dropped mass added to the residual: the list a top-`k` cache would hold, since
/// top-`k` lists are nested. `k = 0` or `k ≥` the cache's bound keeps the view.
pub fn truncate(c: &ViewContrib, k: usize) -> Cow<'_, ViewContrib> {
    if k == 0 || (c.k != 0 && k >= c.k) {
        return Cow::Borrowed(c);
    }
    let mut out = c.clone();
    // The median depth of the full lists is not that of the shortened ones.
    out.median.clear();
    let l = &mut out.lists;
    l.ids.clear();
    l.weights.clear();
    l.offsets.clear();
    l.offsets.push(0);
    let mut order: Vec<usize> = Vec::new();
    for p in 0..c.pixels() {
        let (ids, ws) = c.pixel(p);
        if ids.len() <= k {
            l.ids.extend_from_slice(ids);
            l.weights.extend_from_slice(ws);
        } else {
            order.clear();
            order.extend(0..ids.len());
            order.sort_by(|&a, &b| ws[b].total_cmp(&ws[a]).then(a.cmp(&b)));
            order.truncate(k);
            order.sort_unstable();
            let kept: f32 = order.iter().map(|&i| ws[i]).sum();
            let all: f32 = ws.iter().sum();
            l.residual[p] += (all - kept).max(0.0);
            for &i in &order {
                l.ids.push(ids[i]);
                l.weights.push(ws[i]);
            }
        }
        l.offsets.push(l.ids.len() as u64);
    }
    out.k = k;
    Cow::Owned(out)
}

/// Keeps the covered pixels of `c` on the stride grid.
fn extract(stem: &str, c: &ViewContrib, labels: &[i32], stride: usize) -> ViewPool {
    let mut v = ViewPool {
        stem: stem.to_string(),
        offsets: vec![0],
        ..Default::default()
    };
    for y in (0..c.height).step_by(stride) {
        for x in (0..c.width).step_by(stride) {
            let p = y * c.width + x;
            if c.alpha[p] < crate::cache::DEPTH_MIN_ALPHA {
                continue;
            }
            let (ids, ws) = c.pixel(p);
            v.ids.extend_from_slice(ids);
            v.weights.extend_from_slice(ws);
            v.offsets.push(v.ids.len() as u32);
            v.labels.push(labels[p]);
        }
    }
    v
}

/// Reads the training views (in the given order; lists cut to `top_k`, 0 = as cached), votes,
/// and keeps the training pixels.
// The vote's inputs (cache, views, maps, table, gate) and the pool's own three knobs.
#[allow(clippy::too_many_arguments)]
pub fn build(
    cache: &Cache,
    views: &[View],
    maps: &LabelMaps,
    table: &LabelTable,
    gate: Option<&vote::CityGate>,
    stride: usize,
    top_k: usize,
    gamma: f32,
) -> Result<Pool, TrainError> {
    let n = cache.summary.gaussians;
    let mut votes = Votes::new(n);
    let bar = Bar::new("train", views.len() as u64, "views read");
    type Loaded = (ViewContrib, Vec<i32>, Option<vote::GateView>);
    let load = |v: &View| -> Result<Loaded, TrainError> {
        let c = cache.load(&v.stem())?;
        let c = truncate(&c, top_k).into_owned();
        let labels = maps.read(&v.stem(), c.width, c.height)?;
        let path = || match maps {
            LabelMaps::City(d) | LabelMaps::Fused(d) => d.join(format!("{}.ids.npy", v.stem())),
        };
        for (p, &l) in labels.iter().enumerate() {
            if l < -1 || (l >= 0 && table.get(l).is_none()) {
                return Err(TrainError::Labels {
                    path: path(),
                    why: format!(
                        "pixel ({}, {}) holds label {l}, which the label table does not list",
                        p % c.width,
                        p / c.width
                    ),
                });
            }
        }
        let g = gate.map(|g| g.view(v, &c, &labels)).transpose()?;
        Ok((c, labels, g))
    };
    let (mut load_s, mut vote_s) = (0.0, 0.0);
    let t = Instant::now();
    let mut next = views.first().map(&load).transpose()?;
    load_s += t.elapsed().as_secs_f64();
    let mut out = Vec::with_capacity(views.len());
    let mut present: BTreeSet<i32> = BTreeSet::new();
    for i in 0..views.len() {
        let (c, labels, g) = next.take().expect("loaded");
        let t = Instant::now();
        let (loaded, (pool, acc_s)) = rayon::join(
            || views.get(i + 1).map(&load).transpose(),
            || {
                let t = Instant::now();
                votes.accumulate_gated(&c, &labels, g.as_ref());
                let s = t.elapsed().as_secs_f64();
                let mut seen: Vec<i32> = labels.iter().copied().filter(|&l| l >= 0).collect();
                seen.sort_unstable();
                seen.dedup();
                present.extend(seen);
                (extract(&views[i].stem(), &c, &labels, stride), s)
            },
        );
        vote_s += acc_s;
        load_s += t.elapsed().as_secs_f64() - acc_s;
        next = loaded?;
        out.push(pool);
        bar.inc(1);
    }
    bar.finish();
    let t = Instant::now();
    let vote = vote::assign(&votes, n, gamma);
    vote_s += t.elapsed().as_secs_f64();
    drop(votes);
    let mut class_ids = vec![-1];
    class_ids.extend(present);
    let mut pool = Pool {
        views: out,
        class_ids,
        vote,
        load_s,
        vote_s,
    };
    let class_ids = pool.class_ids.clone();
    for v in &mut pool.views {
        v.targets = v
            .labels
            .iter()
            .map(|&l| {
                if l < 0 {
                    0
                } else {
                    class_ids[1..].binary_search(&l).expect("present") as u32 + 1
                }
            })
            .collect();
        let set: BTreeSet<u32> = v.targets.iter().copied().collect();
        v.classes = set.into_iter().collect();
        v.labels = Vec::new();
    }
    Ok(pool)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache::Contributions;

    #[test]
    fn truncation_keeps_the_largest_weights_in_depth_order() {
        let c = ViewContrib {
            width: 2,
            height: 1,
            k: 4,
            gaussians: 10,
            lists: Contributions {
                offsets: vec![0, 4, 5],
                ids: vec![1, 2, 3, 4, 9],
                weights: vec![0.1, 0.4, 0.2, 0.2, 0.5],
                residual: vec![0.05, 0.0],
            },
            alpha: vec![0.95, 0.5],
            depth: vec![1.0, 2.0],
            median: Vec::new(),
        };
        let t = truncate(&c, 2);
        // 0.4 first, then the nearer of the two 0.2 entries; depth order kept.
        assert_eq!(t.pixel(0), (&[2u32, 3][..], &[0.4f32, 0.2][..]));
        assert_eq!(t.pixel(1), (&[9u32][..], &[0.5f32][..]));
        assert!((t.lists.residual[0] - 0.35).abs() < 1e-6);
        assert_eq!(t.k, 2);
        assert!(matches!(truncate(&c, 0), Cow::Borrowed(_)));
        assert!(matches!(truncate(&c, 4), Cow::Borrowed(_)));
    }
}
