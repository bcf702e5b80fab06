//! SPZ v2 (Niantic's compressed Gaussian splat format) writer, as `KHR_gaussian_splatting_compression_spz_2`
//! embeds it in glTF (docs/export.md).
//!
//! Layout (all little-endian), gzip-compressed as a whole:
//! - header, 16 bytes: magic `0x5053474E` ("NGSP"), version `2` (u32 each), number of points
//!   (u32), SH degree, fractional bits, flags, reserved (u8 each);
//! - positions: 3 × 24-bit signed fixed point per point (`round(x · 2^fractionalBits)`);
//! - alphas: `round(255 · opacity)` (the opacity after the sigmoid);
//! - colours: the SH DC coefficients, `round(255 · (0.15 · dc + 0.5))`;
//! - scales: the log scales, `round(16 · (s + 10))`;
//! - rotations: the unit quaternion with `w ≥ 0`, its `x, y, z` as `round(127.5 · q + 127.5)`
//!   (the reader derives `w = √(1 − x² − y² − z²)`);
//! - SH: per point, per coefficient (degree 1 first), the three channels as
//!   `round(128 · c) + 128` rounded to a bucket of 8 (degree 1, 5 bits) or 16 (higher, 4 bits).
//!
//! Every byte is clamped to 0–255. Positions are written in the caller's frame (no axis
//! change, what CesiumJS's loader reads: it unpacks with no coordinate conversion).
use std::io::Write;

/// "NGSP".
pub const MAGIC: u32 = 0x5053_474E;
/// The format version written.
pub const VERSION: u32 = 2;
/// Fractional bits of the 24-bit positions (1/4096 m steps, ±2048 m range).
pub const FRACTIONAL_BITS: u8 = 12;
/// The colour scale of the DC term.
pub const COLOR_SCALE: f32 = 0.15;

/// Errors of the SPZ writer.
#[derive(Debug, thiserror::Error)]
pub enum SpzError {
    #[error(
        "SPZ: Gaussian {index}: position {value} m is outside the 24-bit fixed-point range ±{limit} m: split the content"
    )]
    OutOfRange {
        index: usize,
        value: f32,
        limit: f32,
    },
    #[error("SPZ: Gaussian {index}: non-finite value")]
    NotFinite { index: usize },
    #[error("SPZ: {0}")]
    Shape(String),
    /// The gzip stream's error (its message only: not also exposed as the error's source, so
    /// an error chain prints the operating system's reason once).
    #[error("SPZ: gzip: {0}")]
    Io(std::io::Error),
}

impl From<std::io::Error> for SpzError {
    fn from(e: std::io::Error) -> SpzError {
        SpzError::Io(e)
    }
}

/// Gaussians to pack, in the frame they are to be stored in.
#[derive(Debug, Clone, Copy)]
pub struct Cloud<'a> {
    pub positions: &'a [[f32; 3]],
    /// Opacity after the sigmoid (0–1).
    pub alphas: &'a [f32],
    /// SH DC coefficients.
    pub colors: &'a [[f32; 3]],
    /// Log scales.
    pub scales: &'a [[f32; 3]],
    /// Unit quaternions `x, y, z, w`.
    pub rotations: &'a [[f32; 4]],
    /// SH degree 0–3.
    pub sh_degree: u8,
    /// Per point `(sh_degree + 1)² − 1` coefficients × 3 channels, coefficient-major.
    pub sh: &'a [f32],
}

/// `x` rounded and clamped to a byte.
fn to_u8(x: f32) -> u8 {
    crate::fastmath::round_u8(x)
}

/// One SH coefficient quantised to `bits` bits (module docs).
fn quantize_sh(x: f32, bits: u32) -> u8 {
    let bucket = 1i32 << (8 - bits);
    let q = (x * 128.0).round() as i32 + 128;
    let q = (q + bucket / 2) / bucket * bucket;
    q.clamp(0, 255) as u8
}

/// The SH coefficients per point (excluding DC) of degree `d`.
pub fn sh_dim(d: u8) -> usize {
    let d = usize::from(d);
    (d + 1) * (d + 1) - 1
}

/// The uncompressed SPZ bytes of `c` (header and arrays, before gzip).
pub fn pack(c: &Cloud<'_>) -> Result<Vec<u8>, SpzError> {
    let n = c.positions.len();
    let dim = sh_dim(c.sh_degree);
    if c.sh_degree > 3 {
        return Err(SpzError::Shape(format!(
            "SH degree {} (at most 3)",
            c.sh_degree
        )));
    }
    if c.alphas.len() != n
        || c.colors.len() != n
        || c.scales.len() != n
        || c.rotations.len() != n
        || c.sh.len() != n * dim * 3
    {
        return Err(SpzError::Shape(format!(
            "array lengths differ ({n} positions)"
        )));
    }
    let n32 = u32::try_from(n).map_err(|_| SpzError::Shape(format!("{n} points")))?;
    let mut out = Vec::with_capacity(16 + n * (9 + 1 + 3 + 3 + 3 + 3 * dim));
    out.extend_from_slice(&MAGIC.to_le_bytes());
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&n32.to_le_bytes());
    out.extend_from_slice(&[c.sh_degree, FRACTIONAL_BITS, 0, 0]);
    let step = (1u32 << FRACTIONAL_BITS) as f32;
    let limit = (1u32 << 23) as f32 / step;
    for (i, p) in c.positions.iter().enumerate() {
        for &v in p {
            if !v.is_finite() {
                return Err(SpzError::NotFinite { index: i });
            }
            let f = (v * step).round();
            if f.abs() >= (1u32 << 23) as f32 {
                return Err(SpzError::OutOfRange {
                    index: i,
                    value: v,
                    limit,
                });
            }
            let f = f as i32;
            out.extend_from_slice(&f.to_le_bytes()[..3]);
        }
    }
    out.extend(c.alphas.iter().map(|&a| to_u8(a * 255.0)));
    for col in c.colors {
        out.extend(
            col.iter()
                .map(|&v| to_u8(v * (COLOR_SCALE * 255.0) + 127.5)),
        );
    }
    for s in c.scales {
        out.extend(s.iter().map(|&v| to_u8((v + 10.0) * 16.0)));
    }
    for (i, q) in c.rotations.iter().enumerate() {
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        if !(norm.is_finite() && norm > 0.0) {
            return Err(SpzError::NotFinite { index: i });
        }
        let sign = if q[3] < 0.0 { -1.0 } else { 1.0 };
        out.extend(
            q[..3]
                .iter()
                .map(|&v| to_u8(sign * v / norm * 127.5 + 127.5)),
        );
    }
    for point in
        c.sh.chunks_exact((dim * 3).max(1))
            .take(if dim == 0 { 0 } else { n })
    {
        for (j, &v) in point.iter().enumerate() {
            out.push(quantize_sh(v, if j < 9 { 5 } else { 4 }));
        }
    }
    Ok(out)
}

/// The SPZ file of `c`: [`pack`] gzip-compressed.
pub fn write(c: &Cloud<'_>) -> Result<Vec<u8>, SpzError> {
    let raw = pack(c)?;
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    gz.write_all(&raw)?;
    Ok(gz.finish()?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_and_fixed_point_bytes_follow_the_layout() {
        let c = Cloud {
            positions: &[[1.0, -1.0, 0.5 / 4096.0 * 3.0]],
            alphas: &[1.0],
            colors: &[[0.0; 3]],
            scales: &[[-10.0, 0.0, 5.9375]],
            rotations: &[[0.0, 0.0, 0.0, -1.0]],
            sh_degree: 0,
            sh: &[],
        };
        let b = pack(&c).unwrap();
        assert_eq!(&b[..4], b"NGSP");
        assert_eq!(u32::from_le_bytes(b[4..8].try_into().unwrap()), 2);
        assert_eq!(u32::from_le_bytes(b[8..12].try_into().unwrap()), 1);
        assert_eq!(&b[12..16], &[0, 12, 0, 0]);
        // 1.0 m = 4096 = 0x001000; −1.0 m = 0xFFF000 (two's complement, 24 bits).
        assert_eq!(&b[16..22], &[0x00, 0x10, 0x00, 0x00, 0xF0, 0xFF]);
        assert_eq!(b[25], 255); // alpha
        assert_eq!(&b[26..29], &[128, 128, 128]); // colour 0 → 127.5 rounds up
        assert_eq!(&b[29..32], &[0, 160, 255]); // scales
        assert_eq!(&b[32..35], &[128, 128, 128]); // −w flipped to +w, xyz 0
        assert_eq!(b.len(), 35);
        let big = Cloud {
            positions: &[[3000.0, 0.0, 0.0]],
            ..c
        };
        assert!(matches!(
            pack(&big),
            Err(SpzError::OutOfRange { index: 0, .. })
        ));
    }

    #[test]
    fn sh_buckets_are_five_then_four_bits() {
        assert_eq!(quantize_sh(0.0, 5), 128);
        // 0.03 · 128 → 4 → 132: to 136 in buckets of 8, to 128 in buckets of 16.
        assert_eq!(quantize_sh(0.03, 5), 136);
        assert_eq!(quantize_sh(0.03, 4), 128);
        assert_eq!(quantize_sh(-2.0, 4), 0);
    }
}
