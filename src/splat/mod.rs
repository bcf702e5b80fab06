//! 3D Gaussian Splatting scenes: the per-Gaussian parameters of an INRIA-layout PLY
//! (`x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*` plus any extra per-vertex
//! scalars), stored raw so that a read → write round trip is bit-exact, with the INRIA
//! activations (`exp` scale, `sigmoid` opacity, normalised quaternion) available on demand.
//!
//! This is a reader module: it depends on no pipeline stage. The 3DGS layout lives in [`ply`],
//! on top of the shared PLY format layer [`crate::ply`]; the other splat formats users have
//! (`.splat`, `.spz`, SuperSplat's compressed PLY) are read into the same Gaussians by
//! [`formats`] and [`compressed`], and [`read_ply`] takes any of them.
pub mod compressed;
pub mod formats;
pub mod ply;
pub mod transform;

pub use formats::SplatFormat;
pub use ply::{
    InvalidPolicy, LOG_SCALE_RANGE, MAX_ABS_SH, PlyEncoding, PlyError, PlyReport, ReadOptions,
    ScalarKind, read_count, read_ply, read_ply_bytes, write_ply,
};

/// Number of `f_rest_*` coefficients (all three colour channels) for SH degree 0..=3.
pub const REST_COUNTS: [usize; 4] = [0, 9, 24, 45];

/// The SH degree whose `f_rest_*` count is `rest`, if any (0, 9, 24, 45 → 0..=3).
pub fn sh_degree_for_rest_count(rest: usize) -> Option<u8> {
    REST_COUNTS.iter().position(|&n| n == rest).map(|d| d as u8)
}

/// An extra per-vertex scalar property (e.g. `obj_dc_0`, `semantic_id`), preserved on write.
///
/// Values are held as `f64`, which represents every PLY scalar type (8–32-bit integers,
/// `float`, `double`) exactly, so the round trip is bit-exact.
#[derive(Debug, Clone, PartialEq)]
pub struct ExtraProperty {
    pub name: String,
    pub kind: ScalarKind,
    pub values: Vec<f64>,
}

/// A set of 3D Gaussians in structure-of-arrays form, raw (pre-activation) values.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Gaussians {
    /// Centres `x y z`.
    pub positions: Vec<[f32; 3]>,
    /// `nx ny nz` when the file has them (INRIA writes zeros).
    pub normals: Option<Vec<[f32; 3]>>,
    /// Spherical-harmonics degree, 0..=3.
    pub sh_degree: u8,
    /// DC coefficients `f_dc_0..2` (R, G, B).
    pub f_dc: Vec<[f32; 3]>,
    /// `f_rest_*` in file order, `rest_per_gaussian()` values per Gaussian: channel-major,
    /// i.e. value `c·K + (k−1)` is coefficient `k ≥ 1` of channel `c`, with `K = (deg+1)²−1`.
    pub f_rest: Vec<f32>,
    /// Raw opacity (a logit): the activated opacity is `sigmoid(opacity)`.
    pub opacity: Vec<f32>,
    /// Raw scales (log): the activated scale is `exp(scale)`.
    pub scale: Vec<[f32; 3]>,
    /// Raw quaternion `(w, x, y, z)`, not necessarily unit length.
    pub rotation: Vec<[f32; 4]>,
    /// Extra per-vertex scalar properties in file order.
    pub extras: Vec<ExtraProperty>,
}

/// Errors of building or checking a [`Gaussians`] value in memory.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SplatError {
    #[error("Gaussian field {field} has {found} entries, expected {expected}")]
    Length {
        field: String,
        found: usize,
        expected: usize,
    },
    #[error("SH degree {0} is not in 0..=3")]
    ShDegree(u8),
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// `f_rest_*` values per Gaussian (all channels): 0, 9, 24 or 45.
    pub fn rest_per_gaussian(&self) -> usize {
        REST_COUNTS[usize::from(self.sh_degree.min(3))]
    }

    /// Checks that every field has one entry per Gaussian.
    pub fn check(&self) -> Result<(), SplatError> {
        if self.sh_degree > 3 {
            return Err(SplatError::ShDegree(self.sh_degree));
        }
        let n = self.len();
        let mut lens = vec![
            ("f_dc", self.f_dc.len(), n),
            ("f_rest", self.f_rest.len(), n * self.rest_per_gaussian()),
            ("opacity", self.opacity.len(), n),
            ("scale", self.scale.len(), n),
            ("rotation", self.rotation.len(), n),
        ];
        if let Some(normals) = &self.normals {
            lens.push(("normals", normals.len(), n));
        }
        for (field, found, expected) in lens {
            if found != expected {
                return Err(SplatError::Length {
                    field: field.into(),
                    found,
                    expected,
                });
            }
        }
        for e in &self.extras {
            if e.values.len() != n {
                return Err(SplatError::Length {
                    field: e.name.clone(),
                    found: e.values.len(),
                    expected: n,
                });
            }
        }
        Ok(())
    }

    /// Activated opacity `sigmoid(opacity[i])`.
    pub fn activated_opacity(&self, i: usize) -> f32 {
        sigmoid(self.opacity[i])
    }

    /// Activated scales `exp(scale[i])`.
    pub fn activated_scale(&self, i: usize) -> [f32; 3] {
        self.scale[i].map(f32::exp)
    }

    /// Unit quaternion `(w, x, y, z)` of Gaussian `i`, normalised in `f64`; `None` for a zero
    /// or non-finite quaternion.
    pub fn normalized_rotation(&self, i: usize) -> Option<[f32; 4]> {
        normalize_quat(self.rotation[i])
    }

    /// The extra property called `name`.
    pub fn extra(&self, name: &str) -> Option<&ExtraProperty> {
        self.extras.iter().find(|e| e.name == name)
    }
}

/// The logistic function, as INRIA's opacity activation.
pub fn sigmoid(x: f32) -> f32 {
    (1.0 / (1.0 + (-f64::from(x)).exp())) as f32
}

/// Normalises a quaternion in `f64`; `None` when it is zero or not finite.
pub fn normalize_quat(q: [f32; 4]) -> Option<[f32; 4]> {
    let q64 = q.map(f64::from);
    let n = q64.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !n.is_finite() || n == 0.0 {
        return None;
    }
    Some(q64.map(|v| (v / n) as f32))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn activations_and_checks() {
        assert!((sigmoid(0.0) - 0.5).abs() < 1e-7);
        assert!(sigmoid(-200.0) >= 0.0 && sigmoid(200.0) <= 1.0);
        assert_eq!(normalize_quat([0.0; 4]), None);
        assert_eq!(
            normalize_quat([2.0, 0.0, 0.0, 0.0]),
            Some([1.0, 0.0, 0.0, 0.0])
        );
        assert_eq!(sh_degree_for_rest_count(45), Some(3));
        assert_eq!(sh_degree_for_rest_count(10), None);
        let mut g = Gaussians {
            positions: vec![[0.0; 3]],
            f_dc: vec![[0.0; 3]],
            opacity: vec![0.0],
            scale: vec![[0.0; 3]],
            rotation: vec![[1.0, 0.0, 0.0, 0.0]],
            ..Default::default()
        };
        assert!(g.check().is_ok());
        assert_eq!(g.activated_scale(0), [1.0; 3]);
        g.sh_degree = 1;
        assert!(matches!(g.check(), Err(SplatError::Length { .. })));
    }
}
