//! The splat formats other than the INRIA PLY, read into the same [`Gaussians`] (raw INRIA
//! values: log scales, opacity logits, SH coefficients, quaternions `w x y z`), so every stage
//! that takes a 3DGS scene takes them (docs/splat-formats.md):
//!
//! * **`.splat`** (antimatter15's web viewer format; no header): 32-byte little-endian records,
//!   position `3 × f32`, linear scale `3 × f32`, colour `r g b a` bytes (`c = 0.5 + C0·dc`,
//!   `a` = the opacity after the sigmoid), rotation `w x y z` bytes (`q·128 + 128`). Read as
//!   `dc = (c/255 − 0.5)/C0`, `scale = ln s`, `rot = (b − 128)/128`. Recognised by its
//!   extension (it has no magic), the file's or its link target's.
//! * **`.spz`** (Niantic's format, versions 2 and 3, [`crate::spz`]): stored in the format's
//!   right-up-back axes (as the SPZ README says and Niantic's and splat-transform's readers
//!   assume), turned here into the PLY's right-down-front (`y, z` negated; the quaternion's
//!   `y, z` negated; SH coefficients negated where their basis function is odd in `y` and
//!   `z` together); SH coefficient-major → INRIA's channel-major `f_rest_*`.
//! * **SuperSplat's compressed PLY** ([`super::compressed`]): recognised by its header.
//!
//! Byte opacities become logits of `clamp(a, 10⁻⁶, 1 − 10⁻⁶)`: 0 and 255 stay finite (a byte
//! 0 is then sigmoid 10⁻⁶, invisible; 255 is 1 − 10⁻⁶). Every record then passes the PLY
//! reader's per-Gaussian checks ([`super::ply`]): a bad record is named as the vertex of that
//! index, and the reading policy keeps, drops or refuses it as it does a PLY vertex.
use std::path::Path;

use super::ply::{PlyError, PlyReport, ReadOptions, assemble};
use super::{Gaussians, REST_COUNTS};

/// The SH DC constant `C0 = 1/(2√π)`.
const SH_C0: f64 = 0.282_094_791_773_878_14;
/// The byte opacities' clamp before the logit.
const ALPHA_EPS: f64 = 1e-6;
/// Bytes of one `.splat` record.
pub const SPLAT_RECORD: usize = 32;

/// The format of a splat file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SplatFormat {
    /// INRIA's 3DGS PLY.
    #[default]
    Ply,
    /// SuperSplat's / PlayCanvas's chunked, quantised PLY.
    CompressedPly,
    /// antimatter15's 32-byte records.
    Splat,
    /// Niantic's SPZ (versions 2 and 3).
    Spz,
}

impl SplatFormat {
    /// The format's usual name.
    pub fn name(self) -> &'static str {
        match self {
            SplatFormat::Ply => "PLY",
            SplatFormat::CompressedPly => "compressed PLY",
            SplatFormat::Splat => ".splat",
            SplatFormat::Spz => "SPZ",
        }
    }
}

/// Whether `path` (or the file its link points to) is named `*.<ext>`.
fn named(path: &Path, ext: &str) -> bool {
    let has = |p: &Path| {
        p.extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case(ext))
    };
    has(path) || std::fs::canonicalize(path).is_ok_and(|p| has(&p))
}

/// The format of a splat file from its name and first bytes: `.splat` and `.spz` by name
/// (a `.splat` file has no magic), else SPZ by its gzip or NGSP magic, else PLY (an INRIA or
/// a compressed PLY, told apart by the header; anything else fails as a PLY, naming the file).
pub fn detect(path: &Path, head: &[u8]) -> SplatFormat {
    if named(path, "splat") {
        SplatFormat::Splat
    } else if named(path, "spz") || crate::spz::looks_like_spz(head) {
        SplatFormat::Spz
    } else {
        SplatFormat::Ply
    }
}

fn bad(path: &Path, why: impl Into<String>) -> PlyError {
    PlyError::Decode {
        path: path.into(),
        why: why.into(),
    }
}

/// The logit of a byte opacity in `0..=1` (module docs).
pub(super) fn opacity_logit(a: f64) -> f64 {
    let a = a.clamp(ALPHA_EPS, 1.0 - ALPHA_EPS);
    (a / (1.0 - a)).ln()
}

/// The number of records of a `.splat` file of `len` bytes.
pub fn splat_count(path: &Path, len: u64) -> Result<usize, PlyError> {
    if len % SPLAT_RECORD as u64 != 0 {
        return Err(bad(
            path,
            format!(
                "{len} bytes is not a whole number of 32-byte .splat records (record {} is cut after {} bytes)",
                len / SPLAT_RECORD as u64,
                len % SPLAT_RECORD as u64
            ),
        ));
    }
    if len == 0 {
        return Err(bad(path, "an empty .splat file (no records)"));
    }
    Ok((len / SPLAT_RECORD as u64) as usize)
}

/// Reads a `.splat` file's bytes (module docs).
pub fn read_splat(
    path: &Path,
    bytes: &[u8],
    options: &ReadOptions,
) -> Result<(Gaussians, PlyReport), PlyError> {
    let n = splat_count(path, bytes.len() as u64)?;
    assemble(path, SplatFormat::Splat, 0, n, options, |i, row| {
        let r = &bytes[i * SPLAT_RECORD..(i + 1) * SPLAT_RECORD];
        let f = |k: usize| {
            f64::from(f32::from_le_bytes(
                r[4 * k..4 * k + 4].try_into().expect("4 bytes"),
            ))
        };
        row.extend([f(0), f(1), f(2)]);
        row.extend((0..3).map(|c| (f64::from(r[24 + c]) / 255.0 - 0.5) / SH_C0));
        row.push(opacity_logit(f64::from(r[27]) / 255.0));
        row.extend([f(3).ln(), f(4).ln(), f(5).ln()]);
        row.extend((0..4).map(|k| (f64::from(r[28 + k]) - 128.0) / 128.0));
    })
}

/// The sign of each SH coefficient (degrees 1–3, INRIA's order within a channel) when `y` and
/// `z` are negated: the parity of its basis function in `y` and `z` together.
const SH_FLIP_YZ: [f64; 15] = [
    -1.0, -1.0, 1.0, // y, z, x
    -1.0, 1.0, 1.0, -1.0, 1.0, // xy, yz, 3z²−1, xz, x²−y²
    -1.0, 1.0, -1.0, -1.0, 1.0, -1.0,
    1.0, // y(3x²−y²), xyz, y(5z²−1), z(5z²−3), x(5z²−1), z(x²−y²), x(x²−3y²)
];

/// Reads an SPZ file's bytes (versions 2 and 3; module docs).
pub fn read_spz(
    path: &Path,
    bytes: &[u8],
    options: &ReadOptions,
) -> Result<(Gaussians, PlyReport), PlyError> {
    let u = crate::spz::unpack(bytes).map_err(|e| bad(path, e.to_string()))?;
    let k = crate::spz::sh_dim(u.sh_degree);
    debug_assert_eq!(REST_COUNTS[usize::from(u.sh_degree)], 3 * k);
    assemble(
        path,
        SplatFormat::Spz,
        u.sh_degree,
        u.positions.len(),
        options,
        |i, row| {
            let p = u.positions[i];
            row.extend([f64::from(p[0]), -f64::from(p[1]), -f64::from(p[2])]);
            row.extend(u.colors[i].map(f64::from));
            let sh = &u.sh[i * 3 * k..(i + 1) * 3 * k];
            for c in 0..3 {
                row.extend((0..k).map(|j| SH_FLIP_YZ[j] * f64::from(sh[3 * j + c])));
            }
            row.push(opacity_logit(f64::from(u.alphas[i])));
            row.extend(u.scales[i].map(f64::from));
            let q = u.rotations[i];
            row.extend([
                f64::from(q[3]),
                f64::from(q[0]),
                -f64::from(q[1]),
                -f64::from(q[2]),
            ]);
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The SH flips are the basis functions' own signs: each real SH polynomial (INRIA's
    /// `eval_sh` terms) evaluated at a direction and at its image with `y, z` negated.
    #[test]
    fn sh_flips_are_the_parities_of_the_basis_functions() {
        let basis = |x: f64, y: f64, z: f64| -> [f64; 15] {
            [
                y,
                z,
                x,
                x * y,
                y * z,
                2.0 * z * z - x * x - y * y,
                x * z,
                x * x - y * y,
                y * (3.0 * x * x - y * y),
                x * y * z,
                y * (4.0 * z * z - x * x - y * y),
                z * (2.0 * z * z - 3.0 * x * x - 3.0 * y * y),
                x * (4.0 * z * z - x * x - y * y),
                z * (x * x - y * y),
                x * (x * x - 3.0 * y * y),
            ]
        };
        let (x, y, z) = (0.3, -0.5, 0.81);
        let a = basis(x, y, z);
        let b = basis(x, -y, -z);
        for k in 0..15 {
            assert!(
                (b[k] - SH_FLIP_YZ[k] * a[k]).abs() < 1e-12,
                "coefficient {k}"
            );
        }
    }

    #[test]
    fn splat_records_become_inria_values() {
        let mut rec = Vec::new();
        for v in [1.0f32, -2.0, 3.5, 0.5, 1.0, 2.0] {
            rec.extend_from_slice(&v.to_le_bytes());
        }
        rec.extend_from_slice(&[255, 0, 128, 255]);
        rec.extend_from_slice(&[255, 128, 128, 0]);
        let (g, r) = read_splat(Path::new("t.splat"), &rec, &ReadOptions::default()).unwrap();
        assert_eq!((g.len(), r.format, g.sh_degree), (1, SplatFormat::Splat, 0));
        assert_eq!(g.positions[0], [1.0, -2.0, 3.5]);
        let dc = |c: f64| ((c / 255.0 - 0.5) / SH_C0) as f32;
        assert_eq!(g.f_dc[0], [dc(255.0), dc(0.0), dc(128.0)]);
        assert_eq!(g.scale[0], [0.5f64.ln() as f32, 0.0, 2f64.ln() as f32]);
        assert_eq!(g.rotation[0], [127.0 / 128.0, 0.0, 0.0, -1.0]);
        // opacity 255 → 1 − 10⁻⁶: finite
        assert!((g.activated_opacity(0) - (1.0 - 1e-6) as f32).abs() < 1e-6);
        let e = read_splat(Path::new("t.splat"), &rec[..31], &ReadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("t.splat") && e.contains("record 0"), "{e}");
        // a zero scale is the log of zero: refused, naming the record
        let mut zero = rec.clone();
        zero[12..16].copy_from_slice(&0f32.to_le_bytes());
        let mut two = rec.clone();
        two.extend_from_slice(&zero);
        let e = read_splat(Path::new("t.splat"), &two, &ReadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("vertex 1") && e.contains("scale_0"), "{e}");
    }
}
