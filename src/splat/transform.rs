//! Rigid and similarity transforms of a set of Gaussians, and the two colour rewrites of the
//! viewer-ready exports: every Gaussian moved by `p ↦ s·M·p + t` (`M` a rotation) keeps its
//! look: centres moved, log-scales shifted by `ln s`, orientations turned by `M`, and the
//! view-dependent colour turned with them (each SH band `l ≥ 1` multiplied by its rotation
//! matrix, found by least squares over a fixed set of directions: the band of degree `l` is
//! closed under rotation, so the fit is exact to rounding).
//!
//! The SH basis is INRIA's (`computeColorFromSH`: signs and order of the real spherical
//! harmonics as 3DGS files store them).
use glam::{DMat3, DQuat, DVec3};

use super::Gaussians;

/// The zeroth-band SH constant: a DC coefficient `f` shows the colour `C0·f + 0.5`.
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
/// INRIA's SH constants of bands 1–3 (`auxiliary.h`).
pub const SH_C1: f64 = 0.488_602_511_902_919_9;
pub const SH_C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
pub const SH_C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// The real SH basis of bands 1..=3 at unit direction `d`, in 3DGS coefficient order (index
/// `k − 1` for coefficient `k`).
fn basis(d: DVec3) -> [f64; 15] {
    let (x, y, z) = (d.x, d.y, d.z);
    let (xx, yy, zz) = (x * x, y * y, z * z);
    [
        -SH_C1 * y,
        SH_C1 * z,
        -SH_C1 * x,
        SH_C2[0] * x * y,
        SH_C2[1] * y * z,
        SH_C2[2] * (2.0 * zz - xx - yy),
        SH_C2[3] * x * z,
        SH_C2[4] * (xx - yy),
        SH_C3[0] * y * (3.0 * xx - yy),
        SH_C3[1] * x * y * z,
        SH_C3[2] * y * (4.0 * zz - xx - yy),
        SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        SH_C3[4] * x * (4.0 * zz - xx - yy),
        SH_C3[5] * z * (xx - yy),
        SH_C3[6] * x * (xx - 3.0 * yy),
    ]
}

/// `n` directions spread over the sphere (a Fibonacci lattice): enough, for `n ≥ 16`, to fix
/// every band up to 3.
fn directions(n: usize) -> Vec<DVec3> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            DVec3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect()
}

/// Solves the `m×m` system `a·x = b` (row-major `a`) for several right-hand sides (the columns
/// of `b`, row-major `m×m`) by Gaussian elimination with partial pivoting.
fn solve(mut a: Vec<f64>, mut b: Vec<f64>, m: usize) -> Vec<f64> {
    for c in 0..m {
        let p = (c..m)
            .max_by(|&i, &j| a[i * m + c].abs().total_cmp(&a[j * m + c].abs()))
            .unwrap_or(c);
        for k in 0..m {
            a.swap(c * m + k, p * m + k);
            b.swap(c * m + k, p * m + k);
        }
        let piv = a[c * m + c];
        for r in (0..m).filter(|&r| r != c) {
            let f = a[r * m + c] / piv;
            if f != 0.0 {
                for k in 0..m {
                    a[r * m + k] -= f * a[c * m + k];
                    b[r * m + k] -= f * b[c * m + k];
                }
            }
        }
    }
    for r in 0..m {
        let piv = a[r * m + r];
        for k in 0..m {
            b[r * m + k] /= piv;
        }
    }
    b
}

/// The matrices `D_l` (bands 1..=`degree`, row-major `(2l+1)²`) with `c′ = D_l·c`: the
/// coefficients of band `l` after the rotation `m`, so that the colour seen along `m·d` after
/// equals the colour seen along `d` before.
pub fn sh_rotation(m: DMat3, degree: u8) -> Vec<Vec<f64>> {
    let dirs = directions(64);
    let inv = m.transpose();
    let before: Vec<[f64; 15]> = dirs.iter().map(|&d| basis(d)).collect();
    let after: Vec<[f64; 15]> = dirs.iter().map(|&d| basis(inv * d)).collect();
    (1..=usize::from(degree.min(3)))
        .map(|l| {
            let (lo, w) = (l * l - 1, 2 * l + 1);
            // Least squares B·D = A over the directions: (BᵀB)·D = BᵀA, with B the basis at
            // d and A the basis at Mᵀd; f′(d) = f(Mᵀd) ⇒ Σ c′ₘ Bₘ = Σ cₖ Aₖ = Σ cₖ Σ Dₘₖ Bₘ.
            let mut btb = vec![0.0; w * w];
            let mut bta = vec![0.0; w * w];
            for (b, a) in before.iter().zip(&after) {
                for i in 0..w {
                    for j in 0..w {
                        btb[i * w + j] += b[lo + i] * b[lo + j];
                        bta[i * w + j] += b[lo + i] * a[lo + j];
                    }
                }
            }
            solve(btb, bta, w)
        })
        .collect()
}

/// A similarity `p ↦ scale · rotation · p + translation` in f64 (`rotation` a proper rotation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    pub scale: f64,
    pub rotation: DMat3,
    pub translation: DVec3,
}

/// Moves every Gaussian of `g` by `motion` (module docs): positions and normals, log-scales,
/// quaternions and the SH bands above the DC term. Extra properties are left as they are.
pub fn apply(g: &mut Gaussians, motion: &Motion) {
    let m = motion.rotation;
    let q = DQuat::from_mat3(&m);
    let log_s = motion.scale.ln();
    for p in &mut g.positions {
        let v = motion.scale * (m * DVec3::from_array(p.map(f64::from))) + motion.translation;
        *p = v.to_array().map(|x| x as f32);
    }
    if let Some(ns) = &mut g.normals {
        for n in ns {
            *n = (m * DVec3::from_array(n.map(f64::from)))
                .to_array()
                .map(|x| x as f32);
        }
    }
    for s in &mut g.scale {
        *s = s.map(|x| (f64::from(x) + log_s) as f32);
    }
    for r in &mut g.rotation {
        // (w, x, y, z) → glam's (x, y, z, w); the rotated frame is M·R.
        let old = DQuat::from_xyzw(
            f64::from(r[1]),
            f64::from(r[2]),
            f64::from(r[3]),
            f64::from(r[0]),
        );
        let new = q * old;
        *r = [new.w, new.x, new.y, new.z].map(|x| x as f32);
    }
    let rest = g.rest_per_gaussian();
    if rest == 0 {
        return;
    }
    let bands = sh_rotation(m, g.sh_degree);
    let k = rest / 3;
    let mut c = vec![0.0f64; k];
    for chunk in g.f_rest.chunks_exact_mut(rest) {
        for ch in 0..3 {
            let coeffs = &mut chunk[ch * k..(ch + 1) * k];
            for (l, d) in bands.iter().enumerate() {
                let (lo, w) = ((l + 1) * (l + 1) - 1, 2 * l + 3);
                for (i, ci) in c[lo..lo + w].iter_mut().enumerate() {
                    *ci = (0..w)
                        .map(|j| d[i * w + j] * f64::from(coeffs[lo + j]))
                        .sum();
                }
            }
            for (dst, &src) in coeffs.iter_mut().zip(&c) {
                *dst = src as f32;
            }
        }
    }
}

/// The DC coefficient that shows colour `rgb` (0–255): `(rgb/255 − 0.5)/C0`.
pub fn dc_of_color(rgb: [u8; 3]) -> [f32; 3] {
    rgb.map(|v| ((f64::from(v) / 255.0 - 0.5) / SH_C0) as f32)
}

/// Paints Gaussian `i` in `rgb` seen from every side: its DC term shows `rgb`, its higher SH
/// bands are zeroed (the SH degree and the file layout stay).
pub fn paint(g: &mut Gaussians, i: usize, rgb: [u8; 3]) {
    g.f_dc[i] = dc_of_color(rgb);
    let rest = g.rest_per_gaussian();
    g.f_rest[i * rest..(i + 1) * rest].fill(0.0);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn band_matrices_are_orthogonal_and_identity_for_no_rotation() {
        for (l, d) in sh_rotation(DMat3::IDENTITY, 3).iter().enumerate() {
            let w = 2 * l + 3;
            for i in 0..w {
                for j in 0..w {
                    let e = if i == j { 1.0 } else { 0.0 };
                    assert!((d[i * w + j] - e).abs() < 1e-9, "band {} ({i},{j})", l + 1);
                }
            }
        }
        let m = DMat3::from_euler(glam::EulerRot::ZYX, 0.3, -1.1, 2.0);
        for (l, d) in sh_rotation(m, 3).iter().enumerate() {
            let w = 2 * l + 3;
            // The real SH of one band are orthonormal up to a common factor: Dᵀ·D = I.
            for i in 0..w {
                for j in 0..w {
                    let dot: f64 = (0..w).map(|k| d[k * w + i] * d[k * w + j]).sum();
                    let e = if i == j { 1.0 } else { 0.0 };
                    assert!((dot - e).abs() < 1e-9, "band {} ({i},{j}) {dot}", l + 1);
                }
            }
        }
    }

    #[test]
    fn dc_shows_the_colour() {
        let dc = dc_of_color([255, 0, 128]);
        let shown = dc.map(|f| SH_C0 * f64::from(f) + 0.5);
        assert!((shown[0] - 1.0).abs() < 1e-6);
        assert!(shown[1].abs() < 1e-6);
        assert!((shown[2] - 128.0 / 255.0).abs() < 1e-6);
    }
}
