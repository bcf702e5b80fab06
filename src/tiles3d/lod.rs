//! Level of detail of the 3D Tiles export: the coarse splat set of an inner quadtree node,
//! built from its children's splats by a moment-matching merge of neighbouring Gaussians
//! (docs/export.md, "Level of detail").
//!
//! - **Neighbours**: the splats are binned into cubic cells of one size, the smallest size
//!   (found by bisection of its logarithm) at which at most `target` cells are occupied; the
//!   splats of one cell merge into one.
//! - **Weights**: a splat's weight is its mass as seen from the front of its largest section,
//!   `w = α · π · s₁ · s₂` (α its opacity, `s₁ ≥ s₂` its two largest linear scales).
//! - **Moments**: the merged Gaussian keeps the weighted first and second moments of the
//!   mixture: `μ = Σ wᵢ μᵢ / W`, `Σ = Σ wᵢ (Σᵢ + (μᵢ − μ)(μᵢ − μ)ᵀ) / W` with `W = Σ wᵢ`
//!   and `Σᵢ = Rᵢ diag(sᵢ²) Rᵢᵀ`; its scales and rotation are `Σ`'s eigen-decomposition;
//!   its colour (every SH coefficient) is the weighted mean; its opacity spreads the mass
//!   over its own largest section, `α = min(1, W / (π s₁ s₂))`.
//! - **Semantics**: the building / surface / part / class of the merged splat are those of
//!   its heaviest member (the dominant one).
//! - **Error**: each splat carries how far the centres it stands for lie from it (0 for an
//!   input Gaussian): a merged splat's is `max (|μᵢ − μ| + eᵢ)` over its members. A node's
//!   geometric error is the largest over its coarse set.
//!
//! A cell with one splat keeps it unchanged.
use glam::{DMat3, DQuat, DVec3};
use rustc_hash::FxHashSet;

use crate::splat::{Gaussians, sigmoid};

/// The semantics a splat carries through merges: building, surface, part entity ids and the
/// evaluation class (−1 none).
pub type Tags = [i32; 4];

/// A set of splats with their semantics and the distance error each stands for.
#[derive(Debug, Clone)]
pub struct SplatSet {
    /// The splats (scene frame; log scales, logit opacities, as [`Gaussians`] holds them).
    pub g: Gaussians,
    pub tags: Vec<Tags>,
    /// Per splat: the largest distance from it of an input Gaussian centre it stands for
    /// (scene units; 0 for an input Gaussian).
    pub error: Vec<f64>,
}

impl SplatSet {
    /// The largest error of the set (0 when empty).
    pub fn max_error(&self) -> f64 {
        self.error.iter().copied().fold(0.0, f64::max)
    }

    /// The sets of `parts` one after the other.
    pub fn concat(parts: &[&SplatSet]) -> SplatSet {
        let sh_degree = parts.iter().map(|p| p.g.sh_degree).max().unwrap_or(0);
        let mut g = Gaussians {
            sh_degree,
            ..Gaussians::default()
        };
        let rest = g.rest_per_gaussian();
        let (mut tags, mut error) = (Vec::new(), Vec::new());
        for p in parts {
            g.positions.extend_from_slice(&p.g.positions);
            g.f_dc.extend_from_slice(&p.g.f_dc);
            g.opacity.extend_from_slice(&p.g.opacity);
            g.scale.extend_from_slice(&p.g.scale);
            g.rotation.extend_from_slice(&p.g.rotation);
            let pr = p.g.rest_per_gaussian();
            for i in 0..p.g.len() {
                let src = &p.g.f_rest[i * pr..(i + 1) * pr];
                // Channel-major: the lower degree's coefficients first in each channel.
                for ch in 0..3 {
                    let (k, pk) = (rest / 3, pr / 3);
                    for j in 0..k {
                        g.f_rest.push(if j < pk { src[ch * pk + j] } else { 0.0 });
                    }
                }
            }
            tags.extend_from_slice(&p.tags);
            error.extend_from_slice(&p.error);
        }
        SplatSet { g, tags, error }
    }
}

/// The covariance `R diag(s²) Rᵀ` of linear scales `s` and unit quaternion `q` (w, x, y, z).
pub fn covariance(s: [f64; 3], q: [f64; 4]) -> DMat3 {
    let r = DMat3::from_quat(DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize());
    r * DMat3::from_diagonal(DVec3::from_array(s.map(|v| v * v))) * r.transpose()
}

/// The mass weight `α π s₁ s₂` of opacity `alpha` and linear scales `s` (module docs).
pub fn mass(alpha: f64, s: [f64; 3]) -> f64 {
    let mut v = s;
    v.sort_by(|a, b| b.total_cmp(a));
    alpha * std::f64::consts::PI * v[0] * v[1]
}

/// One Gaussian's moments: mean, covariance, weight.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Moments {
    pub mean: DVec3,
    pub cov: DMat3,
    pub weight: f64,
}

/// The moment-matching merge of `items` (weights ≥ 0, at least one positive): the weighted
/// mean, the weighted second central moment of the mixture and the summed weight.
pub fn merge_moments(items: &[Moments]) -> Moments {
    let w: f64 = items.iter().map(|m| m.weight).sum();
    let mean = items.iter().map(|m| m.mean * m.weight).sum::<DVec3>() / w;
    let mut cov = DMat3::ZERO;
    for m in items {
        let d = m.mean - mean;
        let outer = DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        cov += (m.cov + outer) * m.weight;
    }
    Moments {
        mean,
        cov: cov * (1.0 / w),
        weight: w,
    }
}

/// Linear scales and a unit quaternion (w, x, y, z) of covariance `cov` (symmetric, positive
/// semi-definite): its eigen-decomposition, eigenvalues floored at 10⁻¹² of the largest (a
/// flat or needle-like merge keeps a finite, tiny thickness).
pub fn scales_rotation(cov: DMat3) -> ([f64; 3], [f64; 4]) {
    let norm = cov.x_axis.x.abs() + cov.y_axis.y.abs() + cov.z_axis.z.abs();
    if !(norm.is_finite() && norm > 0.0) {
        return ([0.0; 3], [1.0, 0.0, 0.0, 0.0]);
    }
    let c = cov * (1.0 / norm);
    let a = [
        [c.x_axis.x, c.y_axis.x, c.z_axis.x],
        [c.x_axis.y, c.y_axis.y, c.z_axis.y],
        [c.x_axis.z, c.y_axis.z, c.z_axis.z],
    ];
    let (vals, vecs) = crate::alignment::jacobi_eigen(a);
    let top = vals.iter().copied().fold(0.0f64, f64::max);
    let floor = top * 1e-12;
    let col = |k: usize| DVec3::new(vecs[0][k], vecs[1][k], vecs[2][k]);
    let (x, y) = (col(0).normalize(), col(1).normalize());
    // A right-handed frame: the third axis from the first two.
    let z = x.cross(y).normalize();
    let y = z.cross(x);
    let q = DQuat::from_mat3(&DMat3::from_cols(x, y, z)).normalize();
    let s = [0, 1, 2].map(|k| (vals[k].max(floor) * norm).sqrt());
    (s, [q.w, q.x, q.y, q.z])
}

/// The cell of each point at cell size `c` from corner `lo`.
fn cell(p: DVec3, lo: DVec3, c: f64) -> [i64; 3] {
    ((p - lo) / c).floor().to_array().map(|v| v as i64)
}

/// The number of occupied cells of size `c`.
fn occupied(points: &[DVec3], lo: DVec3, c: f64) -> usize {
    let mut seen: FxHashSet<[i64; 3]> = FxHashSet::default();
    for &p in points {
        seen.insert(cell(p, lo, c));
    }
    seen.len()
}

/// Groups `points` into at most `target` (≥ 1) groups of one cubic cell each (module docs):
/// the cell size and, per point, its group (0‥groups, in order of first appearance).
pub fn cluster(points: &[DVec3], target: usize) -> (f64, Vec<u32>) {
    let target = target.max(1);
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for &p in points {
        lo = lo.min(p);
        hi = hi.max(p);
    }
    let extent = (hi - lo).max_element().max(1e-9);
    // One cell holds everything at `extent · 1.001`; bisect the logarithm of the size down to
    // 2⁻⁴⁰ of it for the smallest size with at most `target` cells.
    let (mut c_hi, mut c_lo) = (extent * 1.001, extent * 1.001 / 2f64.powi(40));
    if points.len() > target {
        for _ in 0..24 {
            let mid = (c_hi * c_lo).sqrt();
            if occupied(points, lo, mid) <= target {
                c_hi = mid;
            } else {
                c_lo = mid;
            }
        }
    } else {
        c_hi = c_lo;
    }
    let mut ids: rustc_hash::FxHashMap<[i64; 3], u32> = rustc_hash::FxHashMap::default();
    let groups = points
        .iter()
        .map(|&p| {
            let n = ids.len() as u32;
            *ids.entry(cell(p, lo, c_hi)).or_insert(n)
        })
        .collect();
    (c_hi, groups)
}

/// The logit of `a` clamped to [10⁻⁷, 1 − 10⁻⁷].
fn logit(a: f64) -> f32 {
    let a = a.clamp(1e-7, 1.0 - 1e-7);
    (a / (1.0 - a)).ln() as f32
}

/// The coarse set of `set`: at most `target` splats, each the moment-matching merge of the
/// splats of one cell (module docs).
pub fn coarsen(set: &SplatSet, target: usize) -> SplatSet {
    let g = &set.g;
    let n = g.len();
    let points: Vec<DVec3> = g
        .positions
        .iter()
        .map(|p| DVec3::from_array(p.map(f64::from)))
        .collect();
    let (_, group) = cluster(&points, target);
    let groups = group.iter().map(|&k| k as usize + 1).max().unwrap_or(0);
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); groups];
    for (i, &k) in group.iter().enumerate() {
        members[k as usize].push(i);
    }
    let rest = g.rest_per_gaussian();
    let mut out = SplatSet {
        g: Gaussians {
            positions: Vec::with_capacity(groups),
            normals: None,
            sh_degree: g.sh_degree,
            f_dc: Vec::with_capacity(groups),
            f_rest: Vec::with_capacity(groups * rest),
            opacity: Vec::with_capacity(groups),
            scale: Vec::with_capacity(groups),
            rotation: Vec::with_capacity(groups),
            extras: Vec::new(),
        },
        tags: Vec::with_capacity(groups),
        error: Vec::with_capacity(groups),
    };
    let moments = |i: usize| -> Moments {
        let s = g.scale[i].map(|v| f64::from(v).exp());
        let q = crate::splat::normalize_quat(g.rotation[i])
            .unwrap_or([1.0, 0.0, 0.0, 0.0])
            .map(f64::from);
        let alpha = f64::from(sigmoid(g.opacity[i]));
        Moments {
            mean: points[i],
            cov: covariance(s, q),
            weight: mass(alpha, s),
        }
    };
    for m in &members {
        if let [i] = m[..] {
            out.g.positions.push(g.positions[i]);
            out.g.f_dc.push(g.f_dc[i]);
            out.g
                .f_rest
                .extend_from_slice(&g.f_rest[i * rest..(i + 1) * rest]);
            out.g.opacity.push(g.opacity[i]);
            out.g.scale.push(g.scale[i]);
            out.g.rotation.push(g.rotation[i]);
            out.tags.push(set.tags[i]);
            out.error.push(set.error[i]);
            continue;
        }
        let mut items: Vec<Moments> = m.iter().map(|&i| moments(i)).collect();
        // Transparent or flat members alone: weigh them equally (the merge still spans them).
        if items
            .iter()
            .all(|x| x.weight <= 0.0 || !x.weight.is_finite())
        {
            for x in &mut items {
                x.weight = 1.0;
            }
        }
        let all_equal = items.iter().all(|x| x.weight == 1.0);
        let merged = merge_moments(&items);
        let (s, q) = scales_rotation(merged.cov);
        let mut sorted = s;
        sorted.sort_by(|a, b| b.total_cmp(a));
        let section = std::f64::consts::PI * sorted[0] * sorted[1];
        let alpha = if all_equal {
            m.iter()
                .map(|&i| f64::from(sigmoid(g.opacity[i])))
                .fold(0.0, f64::max)
        } else if section > 0.0 {
            (merged.weight / section).min(1.0)
        } else {
            1.0
        };
        let w_total = merged.weight;
        let mut dc = [0.0f64; 3];
        let mut sh = vec![0.0f64; rest];
        let mut heaviest = (f64::NEG_INFINITY, m[0]);
        let mut err = 0.0f64;
        for (x, &i) in items.iter().zip(m) {
            let f = x.weight / w_total;
            for (d, &v) in dc.iter_mut().zip(&g.f_dc[i]) {
                *d += f * f64::from(v);
            }
            for (d, &v) in sh.iter_mut().zip(&g.f_rest[i * rest..(i + 1) * rest]) {
                *d += f * f64::from(v);
            }
            if x.weight > heaviest.0 {
                heaviest = (x.weight, i);
            }
            err = err.max((x.mean - merged.mean).length() + set.error[i]);
        }
        out.g
            .positions
            .push(merged.mean.to_array().map(|v| v as f32));
        out.g.f_dc.push(dc.map(|v| v as f32));
        out.g.f_rest.extend(sh.iter().map(|&v| v as f32));
        out.g.opacity.push(logit(alpha));
        out.g
            .scale
            .push(s.map(|v| v.max(f64::from(f32::MIN_POSITIVE)).ln() as f32));
        out.g.rotation.push(q.map(|v| v as f32));
        out.tags.push(set.tags[heaviest.1]);
        out.error.push(err);
    }
    debug_assert!(out.g.len() <= target.max(1) || n <= target);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hash::splitmix64;

    /// Uniform numbers in [0, 1) from SplitMix64 of a counter.
    struct Uniform(u64);
    impl Uniform {
        fn next(&mut self) -> f64 {
            self.0 += 1;
            (splitmix64(self.0) >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    fn set(points: &[([f32; 3], [f32; 3], f32)]) -> SplatSet {
        let n = points.len();
        SplatSet {
            g: Gaussians {
                positions: points.iter().map(|p| p.0).collect(),
                normals: None,
                sh_degree: 0,
                f_dc: (0..n).map(|i| [i as f32, 0.0, -(i as f32)]).collect(),
                f_rest: Vec::new(),
                opacity: points.iter().map(|p| logit(f64::from(p.2))).collect(),
                scale: points.iter().map(|p| p.1.map(f32::ln)).collect(),
                rotation: vec![[1.0, 0.0, 0.0, 0.0]; n],
                extras: Vec::new(),
            },
            tags: (0..n as i32).map(|i| [i, i, i, i]).collect(),
            error: vec![0.0; n],
        }
    }

    /// Two axis-aligned Gaussians of equal weight 1 m apart along x, by hand: the mean
    /// halfway, the x variance σ² + 0.25, the others σ².
    #[test]
    fn two_equal_gaussians_merge_by_hand() {
        let s = set(&[
            ([0.0, 0.0, 0.0], [0.1, 0.1, 0.1], 0.5),
            ([1.0, 0.0, 0.0], [0.1, 0.1, 0.1], 0.5),
        ]);
        let c = coarsen(&s, 1);
        assert_eq!(c.g.len(), 1);
        let p = c.g.positions[0];
        assert!((p[0] - 0.5).abs() < 1e-6 && p[1].abs() < 1e-6 && p[2].abs() < 1e-6);
        let mut sc: Vec<f64> = c.g.scale[0].iter().map(|&v| f64::from(v).exp()).collect();
        sc.sort_by(f64::total_cmp);
        assert!((sc[0] - 0.1).abs() < 1e-6 && (sc[1] - 0.1).abs() < 1e-6);
        assert!((sc[2] - (0.01f64 + 0.25).sqrt()).abs() < 1e-6, "{sc:?}");
        // Mass 2 · 0.5 · π · 0.01 over the merged section π · 0.51 · 0.1.
        let alpha = f64::from(sigmoid(c.g.opacity[0]));
        let want = 2.0 * 0.5 * 0.01 / (0.26f64.sqrt() * 0.1);
        assert!((alpha - want).abs() < 1e-5, "{alpha} vs {want}");
        assert_eq!(c.g.f_dc[0], [0.5, 0.0, -0.5]);
        assert!((c.error[0] - 0.5).abs() < 1e-6);
    }

    /// The merge's moments equal those of samples drawn from the weighted mixture of its
    /// members (Monte Carlo, 400 000 samples, seeded): an independent computation of the
    /// mean and covariance the merge must keep.
    #[test]
    fn merged_moments_match_samples_of_the_mixture() {
        let mut rng = Uniform(7 << 40);
        let mut u = || rng.next();
        let mut items = Vec::new();
        for _ in 0..5 {
            let mean = DVec3::new(u() * 2.0, u() - 0.5, u() * 0.3);
            let s = [0.05 + u() * 0.3, 0.05 + u() * 0.2, 0.01 + u() * 0.05];
            let q = DQuat::from_euler(glam::EulerRot::XYZ, u() * 3.0, u() * 3.0, u() * 3.0);
            let q = [q.w, q.x, q.y, q.z];
            items.push((mean, s, q, 0.2 + u() * 0.8));
        }
        let moments: Vec<Moments> = items
            .iter()
            .map(|&(mean, s, q, a)| Moments {
                mean,
                cov: covariance(s, q),
                weight: mass(a, s),
            })
            .collect();
        let merged = merge_moments(&moments);
        // Sampling: pick a member by weight, then x = μ + R diag(s) z with z ~ N(0, I).
        let total: f64 = moments.iter().map(|m| m.weight).sum();
        let mut normal = || {
            let (a, b) = (u().max(1e-300), u());
            (-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
        };
        let n = 400_000;
        let (mut sum, mut sum2) = (DVec3::ZERO, DMat3::ZERO);
        let mut samples = Vec::with_capacity(n);
        let mut pick_rng = Uniform(11 << 40);
        for _ in 0..n {
            let mut t = pick_rng.next() * total;
            let mut k = 0;
            while k + 1 < moments.len() && t >= moments[k].weight {
                t -= moments[k].weight;
                k += 1;
            }
            let (mean, s, q, _) = items[k];
            let r = DMat3::from_quat(DQuat::from_xyzw(q[1], q[2], q[3], q[0]));
            let z = DVec3::new(normal() * s[0], normal() * s[1], normal() * s[2]);
            let x = mean + r * z;
            sum += x;
            samples.push(x);
        }
        let mean = sum / n as f64;
        for x in &samples {
            let d = *x - mean;
            sum2 += DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        }
        let cov = sum2 * (1.0 / n as f64);
        assert!(
            (mean - merged.mean).length() < 0.01,
            "{mean} vs {}",
            merged.mean
        );
        let scale = merged.cov.x_axis.x + merged.cov.y_axis.y + merged.cov.z_axis.z;
        let diff = (cov - merged.cov).to_cols_array();
        let worst = diff.iter().map(|v| v.abs()).fold(0.0, f64::max);
        assert!(worst < 0.01 * scale, "{cov} vs {}", merged.cov);
        // And the merge's Gaussian reproduces that covariance from its scales and rotation.
        let (s, q) = scales_rotation(merged.cov);
        let back = covariance(s, q);
        let d = (back - merged.cov).to_cols_array();
        assert!(
            d.iter().all(|v| v.abs() < 1e-9 * scale),
            "{back} vs {}",
            merged.cov
        );
    }

    #[test]
    fn clusters_respect_the_target_and_keep_singletons() {
        let pts: Vec<DVec3> = (0..1000)
            .map(|i| {
                DVec3::new(
                    f64::from(i % 10),
                    f64::from(i / 10 % 10),
                    f64::from(i / 100),
                )
            })
            .collect();
        for target in [1, 7, 100, 999, 1000, 5000] {
            let (_, g) = cluster(&pts, target);
            let k = g.iter().copied().max().unwrap() as usize + 1;
            assert!(k <= target, "{k} > {target}");
            if target >= 1000 {
                assert_eq!(k, 1000);
            }
        }
        // A degenerate cloud (every point the same) is one cell.
        let (_, g) = cluster(&vec![DVec3::ONE; 50], 10);
        assert!(g.iter().all(|&k| k == 0));
    }

    #[test]
    fn dominant_member_gives_the_tags_and_errors_accumulate() {
        let mut s = set(&[
            ([0.0, 0.0, 0.0], [0.5, 0.5, 0.5], 0.9),
            ([0.2, 0.0, 0.0], [0.01, 0.01, 0.01], 0.9),
        ]);
        s.error = vec![0.0, 0.3];
        let c = coarsen(&s, 1);
        assert_eq!(c.tags[0], [0, 0, 0, 0]);
        let mean = f64::from(c.g.positions[0][0]);
        assert!(
            (c.error[0] - ((0.2 - mean) + 0.3)).abs() < 1e-6,
            "{:?}",
            c.error
        );
    }

    #[test]
    fn near_singular_merges_stay_finite() {
        // Needles along x at the same place: the merge is a needle with a tiny thickness.
        let s = set(&[
            ([0.0, 0.0, 0.0], [1.0, 1e-9, 1e-9], 1.0),
            ([0.0, 0.0, 0.0], [2.0, 1e-9, 1e-9], 1.0),
        ]);
        let c = coarsen(&s, 1);
        assert!(c.g.scale[0].iter().all(|v| v.is_finite()));
        assert!(c.g.rotation[0].iter().all(|v| v.is_finite()));
        assert!(sigmoid(c.g.opacity[0]).is_finite());
    }
}
