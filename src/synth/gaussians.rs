//! A growing set of simulated Gaussians (SH degree 1) with one truth row per Gaussian,
//! built in a local metric frame (metres, georeferenced origin subtracted) and mapped to the
//! scene frame at the end with the true alignment.
use glam::{DMat3, DQuat, DVec3};

use crate::splat::Gaussians;

/// SH band-0 constant (INRIA).
pub const SH_C0: f64 = 0.282_094_791_773_878_1;
/// SH band-1 constant (INRIA).
pub const SH_C1: f64 = 0.488_602_511_902_919_9;

/// Truth of one Gaussian: `[class, instance, feature, surface, part]` (−1 = none).
pub type Truth = [i32; 5];

/// Gaussians plus their truth.
#[derive(Debug, Clone, Default)]
pub struct Builder {
    pub g: Gaussians,
    pub truth: Vec<Truth>,
}

/// One Gaussian to add.
pub struct Splat {
    pub pos: DVec3,
    /// Columns: the Gaussian's axes (right-handed, orthonormal).
    pub frame: DMat3,
    /// Activated standard deviations along the frame's axes, metres.
    pub sigma: [f64; 3],
    /// Linear RGB-ish colour in 0..1 (what SH band 0 reproduces).
    pub rgb: [f64; 3],
    pub opacity: f64,
    /// View-dependent term: the colour changes by `reflect_gain · (d · reflect_dir)` per
    /// channel, `d` the unit direction from the camera to the Gaussian (SH band 1).
    pub reflect: Option<(DVec3, [f64; 3])>,
    pub truth: Truth,
}

impl Builder {
    pub fn new() -> Self {
        Builder {
            g: Gaussians {
                sh_degree: 1,
                ..Default::default()
            },
            truth: Vec::new(),
        }
    }

    pub fn len(&self) -> usize {
        self.truth.len()
    }

    pub fn is_empty(&self) -> bool {
        self.truth.is_empty()
    }

    pub fn push(&mut self, s: Splat) {
        let g = &mut self.g;
        g.positions
            .push([s.pos.x as f32, s.pos.y as f32, s.pos.z as f32]);
        g.f_dc
            .push(s.rgb.map(|c| ((c.clamp(0.0, 1.0) - 0.5) / SH_C0) as f32));
        let mut rest = [0.0f32; 9];
        if let Some((t, gain)) = s.reflect {
            // colour += SH_C1·(−y·c1 + z·c2 − x·c3)  ⇒  c1 = −k·t.y, c2 = k·t.z, c3 = −k·t.x.
            for (c, k) in gain.iter().enumerate() {
                let k = k / SH_C1;
                rest[c * 3] = (-k * t.y) as f32;
                rest[c * 3 + 1] = (k * t.z) as f32;
                rest[c * 3 + 2] = (-k * t.x) as f32;
            }
        }
        g.f_rest.extend_from_slice(&rest);
        let o = s.opacity.clamp(1e-4, 1.0 - 1e-4);
        g.opacity.push((o / (1.0 - o)).ln() as f32);
        g.scale.push(s.sigma.map(|v| v.max(1e-6).ln() as f32));
        let q = DQuat::from_mat3(&s.frame).normalize();
        let q = if q.w < 0.0 { -q } else { q };
        g.rotation
            .push([q.w as f32, q.x as f32, q.y as f32, q.z as f32]);
        self.truth.push(s.truth);
    }

    /// Maps every Gaussian from the local metric frame to the scene frame:
    /// `p ↦ s·R·p + t`, axes rotated by `R`, sizes scaled by `s`; band-1 SH rotated with `R`.
    pub fn transform(&mut self, s: f64, r: DMat3, t: DVec3) {
        let g = &mut self.g;
        let rq = DQuat::from_mat3(&r).normalize();
        for i in 0..g.positions.len() {
            let p = DVec3::from_array(g.positions[i].map(f64::from));
            let q = s * (r * p) + t;
            g.positions[i] = [q.x as f32, q.y as f32, q.z as f32];
            let [w, x, y, z] = g.rotation[i].map(f64::from);
            let nq = (rq * DQuat::from_xyzw(x, y, z, w)).normalize();
            let nq = if nq.w < 0.0 { -nq } else { nq };
            g.rotation[i] = [nq.w as f32, nq.x as f32, nq.y as f32, nq.z as f32];
            g.scale[i] = g.scale[i].map(|v| (f64::from(v) + s.ln()) as f32);
            // Band 1 is linear in the direction: coefficients (−c1, c3?…) form a vector
            // v with colour += SH_C1·(v · d) where v = (−c3, −c1, c2).
            for c in 0..3 {
                let rest = &mut g.f_rest[i * 9 + c * 3..i * 9 + c * 3 + 3];
                let v = DVec3::new(-f64::from(rest[2]), -f64::from(rest[0]), f64::from(rest[1]));
                if v != DVec3::ZERO {
                    let w = r * v;
                    rest[0] = (-w.y) as f32;
                    rest[1] = w.z as f32;
                    rest[2] = (-w.x) as f32;
                }
            }
        }
    }
}

/// A right-handed orthonormal frame whose third axis is `n` (unit).
pub fn frame_from_normal(n: DVec3) -> DMat3 {
    let a = if n.z.abs() < 0.9 { DVec3::Z } else { DVec3::X };
    let t1 = a.cross(n).normalize();
    let t2 = n.cross(t1);
    DMat3::from_cols(t1, t2, n)
}

/// A deterministic hash of integers to `[0, 1)` (procedural variation).
pub fn hash01(a: u64, b: u64) -> f64 {
    let mut x = a
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(b.wrapping_mul(0xC2B2_AE3D_27D4_EB4F));
    x ^= x >> 31;
    x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x ^= x >> 29;
    (x >> 11) as f64 / (1u64 << 53) as f64
}

/// Smooth value noise in `[-1, 1]` over 3D positions, cell size `cell` metres.
pub fn value_noise(p: DVec3, cell: f64, salt: u64) -> f64 {
    let q = p / cell;
    let f = q.floor();
    let t = q - f;
    let s = t * t * (DVec3::splat(3.0) - 2.0 * t);
    let corner = |dx: i64, dy: i64, dz: i64| {
        let k = ((f.x as i64 + dx) as u64).wrapping_mul(73_856_093)
            ^ ((f.y as i64 + dy) as u64).wrapping_mul(19_349_663)
            ^ ((f.z as i64 + dz) as u64).wrapping_mul(83_492_791);
        hash01(k, salt) * 2.0 - 1.0
    };
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), s.x);
    let x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), s.x);
    let x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), s.x);
    let x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), s.x);
    lerp(lerp(x00, x10, s.y), lerp(x01, x11, s.y), s.z)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::project::sh_color;

    #[test]
    fn reflection_term_survives_rotation() {
        let mut b = Builder::new();
        let t = DVec3::new(0.3, -0.2, 0.9);
        b.push(Splat {
            pos: DVec3::ZERO,
            frame: frame_from_normal(DVec3::X),
            sigma: [0.1, 0.1, 0.01],
            rgb: [0.5; 3],
            opacity: 0.9,
            reflect: Some((t, [0.2, 0.2, 0.2])),
            truth: [0; 5],
        });
        let col = |b: &Builder, d: DVec3| {
            let c: Vec<[f32; 3]> = (0..4)
                .map(|k| {
                    if k == 0 {
                        b.g.f_dc[0]
                    } else {
                        [0, 1, 2].map(|c| b.g.f_rest[c * 3 + k - 1])
                    }
                })
                .collect();
            sh_color(&c, 1, d)[0]
        };
        let d = DVec3::new(0.0, 0.6, 0.8);
        let expect = 0.5 + 0.2 * d.dot(t);
        assert!((f64::from(col(&b, d)) - expect).abs() < 1e-5);
        let r = DMat3::from_rotation_z(0.7);
        b.transform(2.0, r, DVec3::new(1.0, 2.0, 3.0));
        assert!((f64::from(col(&b, r * d)) - expect).abs() < 1e-5);
        assert!((f64::from(b.g.scale[0][0]) - (0.2f64).ln()).abs() < 1e-6);
    }
}
