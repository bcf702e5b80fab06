//! The linearised similarity step: weighted point-to-plane normal equations in f64, their
//! eigen-decomposition (conditioning, undetermined directions) and the solved update.
//!
//! About the weighted centroid `c` of the moved points, a small similarity is
//! `δ(x) = c + e^σ·R(ω)·(x − c) + τ ≈ x + σ·(x − c) + ω × (x − c) + τ`, so the residual
//! `r = n·(δ(x) − q)` has the Jacobian row `[n·a, a × n, n]` in the unknowns
//! `(σL, ωL, τ)` with `a = (x − c)/L`, `L` the weighted RMS radius: every column is O(1),
//! which makes the eigenvalues of `JᵀWJ / Σw` comparable across scenes and units.
use glam::{DMat3, DQuat, DVec3};

use super::{Conditioning, Match};
use crate::alignment::Similarity;
use crate::alignment::jacobi_eigen;

/// Accumulated normal equations of one iteration.
pub(super) struct Normal7 {
    /// `JᵀWJ / Σw` and `JᵀWr / Σw`, in the scaled unknowns (7, or 6 without scale).
    h: [[f64; 7]; 7],
    g: [f64; 7],
    centre: DVec3,
    /// Weighted RMS radius about `centre` (the unknowns' length scale).
    radius: f64,
    /// Largest distance of a weighted point from `centre`: bounds how far a step moves a point.
    reach: f64,
    scale: bool,
}

/// A solved step.
pub(super) struct Solution {
    /// The similarity to apply after the current estimate.
    pub step: Similarity,
    /// Upper bound of the step's displacement of any weighted point.
    pub motion: f64,
    /// Directions left out as undetermined (eigenvalue ratio below the threshold).
    pub dropped: usize,
}

impl Normal7 {
    /// The weighted system, or `None` when the weights sum to zero or fewer than 7 points
    /// carry weight.
    #[allow(clippy::needless_range_loop)] // a symmetric matrix: (i, j) and (j, i)
    pub(super) fn accumulate(matches: &[Match], weights: &[f64], scale: bool) -> Option<Normal7> {
        let wsum: f64 = weights.iter().sum();
        if wsum.is_nan() || wsum <= 0.0 || weights.iter().filter(|w| **w > 0.0).count() < 7 {
            return None;
        }
        let centre = matches
            .iter()
            .zip(weights)
            .fold(DVec3::ZERO, |acc, (m, w)| acc + *w * m.x)
            / wsum;
        let mut r2 = 0.0;
        let mut reach = 0.0f64;
        for (m, w) in matches.iter().zip(weights) {
            if *w > 0.0 {
                let d2 = (m.x - centre).length_squared();
                r2 += w * d2;
                reach = reach.max(d2);
            }
        }
        let radius = (r2 / wsum).sqrt().max(1e-12);
        let mut h = [[0.0; 7]; 7];
        let mut g = [0.0; 7];
        for (m, w) in matches.iter().zip(weights) {
            if *w <= 0.0 {
                continue;
            }
            let a = (m.x - centre) / radius;
            let c = a.cross(m.n);
            let row = [
                if scale { m.n.dot(a) } else { 0.0 },
                c.x,
                c.y,
                c.z,
                m.n.x,
                m.n.y,
                m.n.z,
            ];
            for i in 0..7 {
                let wi = w * row[i];
                g[i] += wi * m.r;
                for j in i..7 {
                    h[i][j] += wi * row[j];
                }
            }
        }
        for i in 0..7 {
            g[i] /= wsum;
            for j in i..7 {
                h[i][j] /= wsum;
                h[j][i] = h[i][j];
            }
        }
        Some(Normal7 {
            h,
            g,
            centre,
            radius,
            reach: reach.sqrt(),
            scale,
        })
    }

    /// Eigenvalues (ascending) and unit eigenvectors (7-vectors; without scale the scale
    /// component is 0 and that direction is not listed).
    fn eigen(&self) -> Vec<(f64, [f64; 7])> {
        let mut out: Vec<(f64, [f64; 7])> = if self.scale {
            let (vals, vecs) = jacobi_eigen::<7>(self.h);
            (0..7)
                .map(|k| (vals[k], std::array::from_fn(|i| vecs[i][k])))
                .collect()
        } else {
            let mut h6 = [[0.0; 6]; 6];
            for (i, row) in h6.iter_mut().enumerate() {
                for (j, v) in row.iter_mut().enumerate() {
                    *v = self.h[i + 1][j + 1];
                }
            }
            let (vals, vecs) = jacobi_eigen::<6>(h6);
            (0..6)
                .map(|k| {
                    let mut v = [0.0; 7];
                    for i in 0..6 {
                        v[i + 1] = vecs[i][k];
                    }
                    (vals[k], v)
                })
                .collect()
        };
        out.sort_by(|a, b| a.0.total_cmp(&b.0));
        out
    }

    /// The Gauss–Newton step restricted to the directions whose eigenvalue is at least
    /// `min_ratio` × the largest (the others are left unchanged and counted as dropped).
    pub(super) fn solve(&self, min_ratio: f64) -> Solution {
        let eig = self.eigen();
        let lmax = eig.last().map_or(0.0, |e| e.0);
        let mut eta = [0.0; 7];
        let mut dropped = 0;
        for (l, v) in &eig {
            if l.is_nan() || *l <= 0.0 || *l < min_ratio * lmax {
                dropped += 1;
                continue;
            }
            let proj: f64 = (0..7).map(|i| v[i] * self.g[i]).sum::<f64>() / l;
            for i in 0..7 {
                eta[i] -= proj * v[i];
            }
        }
        let sigma = eta[0] / self.radius;
        let omega = DVec3::new(eta[1], eta[2], eta[3]) / self.radius;
        let tau = DVec3::new(eta[4], eta[5], eta[6]);
        let s = sigma.exp();
        let rot = DMat3::from_quat(DQuat::from_scaled_axis(omega));
        let step = Similarity {
            scale: s,
            rotation: rot,
            translation: self.centre + tau - s * (rot * self.centre),
        };
        Solution {
            step,
            motion: tau.length() + self.reach * (omega.length() + sigma.abs()),
            dropped,
        }
    }

    /// Eigenvalues, their ratio and the weakest direction in words.
    pub(super) fn conditioning(&self) -> Conditioning {
        let eig = self.eigen();
        let lmin = eig.first().map_or(0.0, |e| e.0);
        let lmax = eig.last().map_or(0.0, |e| e.0);
        let ratio = if lmax > 0.0 {
            (lmin / lmax).max(0.0)
        } else {
            0.0
        };
        Conditioning {
            eigenvalues: eig.iter().map(|e| e.0).collect(),
            ratio,
            weakest: eig
                .first()
                .map_or_else(|| "anything".into(), |e| describe(&e.1)),
        }
    }
}

/// A direction of the scaled unknowns `(σL, ωL, τ)` in words, dominant part first.
fn describe(v: &[f64; 7]) -> String {
    let w = DVec3::new(v[1], v[2], v[3]);
    let t = DVec3::new(v[4], v[5], v[6]);
    let f = |d: DVec3| {
        let d = d.normalize_or_zero();
        format!("({:.2}, {:.2}, {:.2})", d.x, d.y, d.z)
    };
    let mut parts = [
        (t.length(), format!("the translation along {}", f(t))),
        (w.length(), format!("the rotation about {}", f(w))),
        (v[0].abs(), "the scale".to_string()),
    ];
    parts.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut s = parts[0].1.clone();
    for p in &parts[1..] {
        if p.0 > 0.3 {
            s.push_str(&format!(" coupled with {}", p.1));
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m(x: DVec3, n: DVec3, r: f64) -> Match {
        Match {
            x,
            n,
            bin: crate::refine::bin_of(n),
            r,
            d: r.abs(),
        }
    }

    /// Points on the six faces of a box, displaced by a known small similarity: one step
    /// recovers it to first order, and the conditioning is good.
    #[test]
    fn one_step_recovers_a_small_similarity_on_a_box() {
        let truth = Similarity {
            scale: 1.0 + 2e-4,
            rotation: DMat3::from_quat(DQuat::from_scaled_axis(DVec3::new(1e-4, -2e-4, 3e-4))),
            translation: DVec3::new(1e-3, -2e-3, 5e-4),
        };
        // Surface points of the box [0,4]×[0,3]×[0,2]; the "Gaussians" are the truth's
        // inverse applied to them, so the step must recover `truth`.
        let mut matches = Vec::new();
        let faces = [
            (DVec3::X, 4.0),
            (-DVec3::X, 0.0),
            (DVec3::Y, 3.0),
            (-DVec3::Y, 0.0),
            (DVec3::Z, 2.0),
            (-DVec3::Z, 0.0),
        ];
        let inv = truth.inverse();
        for (n, off) in faces {
            for i in 0..10 {
                for j in 0..10 {
                    let (u, v) = ((i as f64 + 0.5) / 10.0, (j as f64 + 0.5) / 10.0);
                    let p = if n.x != 0.0 {
                        DVec3::new(off, 3.0 * u, 2.0 * v)
                    } else if n.y != 0.0 {
                        DVec3::new(4.0 * u, off, 2.0 * v)
                    } else {
                        DVec3::new(4.0 * u, 3.0 * v, off)
                    };
                    let x = inv.apply(p);
                    // Closest point on the face plane: residual n·x − off.
                    let r = n.dot(x) - n.dot(p);
                    matches.push(m(x, n, r));
                }
            }
        }
        let w = vec![1.0; matches.len()];
        let sys = Normal7::accumulate(&matches, &w, true).unwrap();
        let c = sys.conditioning();
        assert!(c.ratio > 0.01, "{c:?}");
        let sol = sys.solve(1e-3);
        assert_eq!(sol.dropped, 0);
        for p in [
            DVec3::ZERO,
            DVec3::new(4.0, 3.0, 2.0),
            DVec3::new(2.0, 0.0, 1.0),
        ] {
            let err = (sol.step.apply(inv.apply(p)) - p).length();
            assert!(err < 2e-6, "{err}"); // second-order remainder of a 1e-3 step
        }
        // Rigid: the scale stays 1.
        let rigid = Normal7::accumulate(&matches, &w, false)
            .unwrap()
            .solve(1e-3);
        assert_eq!(rigid.step.scale, 1.0);
    }

    #[test]
    fn a_single_plane_is_degenerate_and_named() {
        // z = 0 plane, random-ish points, pure offset along z.
        let matches: Vec<Match> = (0..200)
            .map(|i| {
                let x = DVec3::new((i % 20) as f64 * 0.37, (i / 20) as f64 * 0.51, 0.02);
                m(x, DVec3::Z, 0.02)
            })
            .collect();
        let w = vec![1.0; matches.len()];
        let sys = Normal7::accumulate(&matches, &w, true).unwrap();
        let c = sys.conditioning();
        assert!(c.ratio < 1e-12, "{c:?}");
        let sol = sys.solve(1e-3);
        // Determined: translation along z, rotations about x and y. Undetermined: x/y
        // translation, rotation about z, scale (about the centroid in the plane).
        assert_eq!(sol.dropped, 4);
        let moved = sol.step.apply(DVec3::new(1.0, 1.0, 0.02));
        assert!((moved.z).abs() < 1e-9 && (moved.x - 1.0).abs() < 1e-9);
        assert!(
            c.weakest.contains("translation")
                || c.weakest.contains("rotation")
                || c.weakest.contains("scale")
        );
    }
}
