//! The KNN-KL term of identity learning (paper §3.3): for each anchor code, the KL divergence
//! between its class distribution and those of its K nearest neighbours (graph built once by
//! `knn`), over the bucketed [`Active`] set, with its gradient.
use rayon::prelude::*;

use ndarray::{Array2, Axis};

use super::model::{Active, CHUNK, Grads, Model, Real, backprop, logits, lse};

/// One code's distribution over an [`Active`] set, bucketed: members one bucket each,
/// negatives one shared "rest" bucket.
struct RowDist<T> {
    /// `p̃_u = ω_u e^{z_u} / Ẑ` for every column.
    p: Vec<T>,
    /// Bucket log-masses: members, then the rest bucket (−∞ when there are no negatives).
    lb: Vec<T>,
    /// Within-rest shares `s_u = e^{z̃_u} / Σ_neg e^{z̃}` of the negatives.
    share: Vec<T>,
}

fn row_dist<T: Real>(z: &[T], members: usize) -> RowDist<T> {
    let lz = lse(z);
    let p: Vec<T> = z.iter().map(|&x| (x - lz).exp()).collect();
    let lneg = lse(&z[members..]);
    let mut lb: Vec<T> = z[..members].iter().map(|&x| x - lz).collect();
    lb.push(lneg - lz);
    let share = z[members..].iter().map(|&x| (x - lneg).exp()).collect();
    RowDist { p, lb, share }
}

/// Adds `∂KL(p_a ‖ p_n)/∂z` of one pair into `dza` and `dzn` (scaled by `s`); returns the KL.
///
/// With bucket masses `P_b`, `Q_b`: `KL = Σ_b P_b (ln P_b − ln Q_b)`;
/// `∂KL/∂z^a_u = g_{b(u)} s^a_u − p̃^a_u Σ_b g_b` with `g_b = P_b (ln P_b − ln Q_b + 1)`, and
/// `∂KL/∂z^n_u = q̃^n_u Σ_b P_b − P_{b(u)} s^n_u` (`s = 1` for members).
fn kl_pair<T: Real>(
    da: &RowDist<T>,
    dn: &RowDist<T>,
    nm: usize,
    s: T,
    dza: &mut [T],
    dzn: &mut [T],
) -> T {
    let nb = da.lb.len();
    let mut kl = T::zero();
    let mut gsum = T::zero();
    let mut psum = T::zero();
    let mut gb = vec![T::zero(); nb];
    let mut pb = vec![T::zero(); nb];
    for b in 0..nb {
        let pm = da.lb[b].exp();
        pb[b] = pm;
        psum += pm;
        if pm > T::zero() {
            let d = da.lb[b] - dn.lb[b];
            kl += pm * d;
            gb[b] = pm * (d + T::one());
            gsum += gb[b];
        }
    }
    for u in 0..dza.len() {
        let (b, sa, sn) = if u < nm {
            (u, T::one(), T::one())
        } else {
            (nm, da.share[u - nm], dn.share[u - nm])
        };
        dza[u] += (gb[b] * sa - da.p[u] * gsum) * s;
        dzn[u] += (dn.p[u] * psum - pb[b] * sn) * s;
    }
    kl
}

/// The KL term: `scale · Σ_j Σ_i KL(p_j ‖ p_{n_i(j)})` over the bucketed distributions (exact
/// when the active set holds every class). `anchors[j]`'s neighbours are
/// `neighbours[j·k .. (j+1)·k]`; `actives[j]` is the active set of anchor `j` and its
/// neighbours (or `actives` has one set, shared by all). Adds its gradient (through both
/// distributions) into `g`; returns the loss times `scale` and, per anchor and neighbour row,
/// the member class of largest probability.
pub fn knn_kl<T: Real>(
    m: &Model<T>,
    anchors: &[u32],
    neighbours: &[u32],
    k: usize,
    actives: &[Active],
    scale: f64,
    g: &mut Grads<T>,
) -> (f64, Vec<u32>) {
    assert_eq!(neighbours.len(), anchors.len() * k);
    assert!(actives.len() == 1 || actives.len() == anchors.len());
    let shared = (actives.len() == 1).then(|| actives[0].gather(m));
    let d = m.dim;
    let s = T::of(scale);
    let group = (CHUNK / (k + 1)).max(1);
    let chunks: Vec<std::ops::Range<usize>> = (0..anchors.len())
        .step_by(group)
        .map(|a| a..(a + group).min(anchors.len()))
        .collect();
    let row_gaussian = |j: usize, i: usize| -> u32 {
        if i == 0 {
            anchors[j]
        } else {
            neighbours[j * k + i - 1]
        }
    };
    // Per chunk: the loss, per row ∂L/∂e, the classifier gradient per anchor group, the best
    // member per row.
    type Out<T> = (f64, Vec<Array2<T>>, Vec<(Array2<T>, Vec<T>)>, Vec<u32>);
    let parts: Vec<Out<T>> = chunks
        .par_iter()
        .map(|js| {
            let mut loss = 0.0;
            let mut des = Vec::with_capacity(js.len());
            let mut cls = Vec::with_capacity(js.len());
            let mut best = Vec::with_capacity(js.len() * (k + 1));
            for j in js.clone() {
                let active = if actives.len() == 1 {
                    &actives[0]
                } else {
                    &actives[j]
                };
                let local;
                let (w, b) = match &shared {
                    Some(x) => (&x.0, &x.1),
                    None => {
                        local = active.gather(m);
                        (&local.0, &local.1)
                    }
                };
                let nm = active.members.len();
                let mut e = Array2::zeros((k + 1, d));
                for i in 0..=k {
                    e.row_mut(i)
                        .as_slice_mut()
                        .expect("contiguous")
                        .copy_from_slice(m.code(row_gaussian(j, i) as usize));
                }
                let z = logits(&e, w, b);
                let dists: Vec<RowDist<T>> = z
                    .rows()
                    .into_iter()
                    .map(|r| row_dist(r.as_slice().expect("contiguous"), nm))
                    .collect();
                for dd in &dists {
                    let mut bi = 0;
                    for (i, &x) in dd.lb[..nm].iter().enumerate() {
                        if x > dd.lb[bi] {
                            bi = i;
                        }
                    }
                    best.push(active.members[bi]);
                }
                let mut dz = Array2::<T>::zeros((k + 1, active.len()));
                for i in 1..=k {
                    let (mut top, mut rest) = dz.view_mut().split_at(Axis(0), i);
                    let mut za = top.row_mut(0);
                    let mut zn = rest.row_mut(0);
                    let kl = kl_pair(
                        &dists[0],
                        &dists[i],
                        nm,
                        s,
                        za.as_slice_mut().expect("contiguous"),
                        zn.as_slice_mut().expect("contiguous"),
                    );
                    loss += kl.f64();
                }
                let (de, dw, db) = backprop(&dz, &e, w);
                des.push(de);
                cls.push((dw, db));
            }
            (loss, des, cls, best)
        })
        .collect();
    let mut total = 0.0;
    let mut best = Vec::with_capacity(anchors.len() * (k + 1));
    for (js, (loss, des, cls, bst)) in chunks.iter().zip(&parts) {
        total += loss;
        for (jj, j) in js.clone().enumerate() {
            for i in 0..=k {
                let de = des[jj].row(i);
                g.add_code(
                    row_gaussian(j, i),
                    T::one(),
                    de.as_slice().expect("contiguous"),
                );
            }
            let active = if actives.len() == 1 {
                &actives[0]
            } else {
                &actives[j]
            };
            g.add_classes(active, &cls[jj].0, &cls[jj].1);
        }
        best.extend_from_slice(bst);
    }
    (total * scale, best)
}
