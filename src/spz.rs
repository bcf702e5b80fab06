//! SPZ (Niantic's compressed Gaussian splat format): the version 2 writer, as
//! `KHR_gaussian_splatting_compression_spz_2` embeds it in glTF (docs/export.md), and the reader
//! of versions 2 and 3 ([`unpack`], docs/splat-formats.md), after the format's README and
//! `load-spz.cc` in github.com/nianticlabs/spz (version 3 current there).
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
//!
//! Version 3 differs in the rotations only: 4 bytes, a little-endian `u32` whose top 2 bits
//! name the largest component of the unit quaternion `x, y, z, w` (made positive) and whose
//! other 30 bits hold the remaining three in order, the last in the lowest bits, each as a
//! sign bit and a 9-bit magnitude `round(511 · |q| · √2)` (a quaternion's second-largest
//! component is at most 1/√2). The reader takes a stream with the extensions flag (`0x2`)
//! as unreadable: its records are not bounded in a version 2/3 stream. Version 4 (ZSTD
//! streams behind a plain 32-byte header, `@adobe/spz`) is refused with one line.
use std::io::{Read, Write};

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
    #[error("SPZ: gzip: {0}")]
    Io(#[from] std::io::Error),
    /// A file that cannot be read as SPZ; `why` names the part at fault.
    #[error("SPZ: {why}")]
    Read { why: String },
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

/// The version 4 header's first bytes ("NGSP" not gzip-compressed).
const V4_MAGIC: [u8; 4] = *b"NGSP";
/// The gzip magic.
const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];
/// The header's extensions flag.
const FLAG_EXTENSIONS: u8 = 0x2;
/// gzip cannot expand more than ≈ 1032:1; a header that claims more data than that is
/// refused before anything is allocated.
const MAX_DEFLATE_RATIO: u64 = 1032;

/// An SPZ file decoded, in the file's own frame and the format's parameters: what a
/// renderer reads, before any change of axes.
#[derive(Debug, Clone, PartialEq)]
pub struct Unpacked {
    /// The header's version (2 or 3).
    pub version: u32,
    /// Whether the header's antialiasing flag (`0x1`) is set.
    pub antialiased: bool,
    pub positions: Vec<[f32; 3]>,
    /// Opacities after the sigmoid, `byte / 255`.
    pub alphas: Vec<f32>,
    /// SH DC coefficients, `(byte / 255 − 0.5) / 0.15`.
    pub colors: Vec<[f32; 3]>,
    /// Log scales, `byte / 16 − 10`.
    pub scales: Vec<[f32; 3]>,
    /// Unit quaternions `x, y, z, w`.
    pub rotations: Vec<[f32; 4]>,
    /// SH degree 0–3.
    pub sh_degree: u8,
    /// Per point `(sh_degree + 1)² − 1` coefficients × 3 channels, coefficient-major (the
    /// channel fastest), `(byte − 128) / 128`.
    pub sh: Vec<f32>,
}

/// Whether `bytes` start like an SPZ file (gzip, or version 4's plain "NGSP").
pub fn looks_like_spz(bytes: &[u8]) -> bool {
    bytes.starts_with(&GZIP_MAGIC) || bytes.starts_with(&V4_MAGIC)
}

/// The number of points an SPZ file's header declares (only the header is decompressed).
pub fn read_count(bytes: &[u8]) -> Result<usize, SpzError> {
    let mut head = [0u8; 16];
    open_stream(bytes)?
        .read_exact(&mut head)
        .map_err(|e| read_err(format!("the 16-byte header: {e}")))?;
    Ok(header(&head)?.2 as usize)
}

fn read_err(why: impl Into<String>) -> SpzError {
    SpzError::Read { why: why.into() }
}

/// A gzip decoder over `bytes`, or the one-line reason why this is not an SPZ 2/3 file.
fn open_stream(bytes: &[u8]) -> Result<flate2::read::GzDecoder<&[u8]>, SpzError> {
    if bytes.starts_with(&V4_MAGIC) {
        let v = bytes
            .get(4..8)
            .map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")));
        return Err(read_err(format!(
            "version {} (the ZSTD container of @adobe/spz) is not read; write version 3 (splat-transform --spz-version 3) or a PLY",
            v.map_or("?".to_string(), |v| v.to_string())
        )));
    }
    if !bytes.starts_with(&GZIP_MAGIC) {
        return Err(read_err(
            "not an SPZ file: neither gzip-compressed (versions 2, 3) nor an NGSP header",
        ));
    }
    Ok(flate2::read::GzDecoder::new(bytes))
}

/// The header's (version, SH degree, point count, fractional bits, flags), checked.
fn header(h: &[u8; 16]) -> Result<(u32, u8, u32, u8, u8), SpzError> {
    let word = |i: usize| u32::from_le_bytes(h[i..i + 4].try_into().expect("4 bytes"));
    if word(0) != MAGIC {
        return Err(read_err(format!(
            "header: magic {:#010x}, not {MAGIC:#010x} (\"NGSP\")",
            word(0)
        )));
    }
    let version = word(4);
    if !(2..=3).contains(&version) {
        return Err(read_err(format!(
            "header: version {version}; versions 2 and 3 are read"
        )));
    }
    let (degree, bits, flags) = (h[12], h[13], h[14]);
    if degree > 3 {
        return Err(read_err(format!(
            "header: SH degree {degree}; degrees 0–3 are read"
        )));
    }
    if bits > 23 {
        return Err(read_err(format!(
            "header: {bits} fractional bits of a 24-bit coordinate"
        )));
    }
    if flags & FLAG_EXTENSIONS != 0 {
        return Err(read_err(
            "header: the extensions flag is set; extension records in a version 2/3 stream are not read (write the file without extensions)",
        ));
    }
    Ok((version, degree, word(8), bits, flags))
}

/// Decodes an SPZ file of version 2 or 3 (module docs). Sizes are checked before anything is
/// allocated for the points: the header's count must match the decompressed length exactly.
pub fn unpack(bytes: &[u8]) -> Result<Unpacked, SpzError> {
    let mut stream = open_stream(bytes)?;
    let mut head = [0u8; 16];
    stream
        .read_exact(&mut head)
        .map_err(|e| read_err(format!("the 16-byte header: {e}")))?;
    let (version, sh_degree, n, bits, flags) = header(&head)?;
    let dim = sh_dim(sh_degree);
    let rot_bytes: u64 = if version >= 3 { 4 } else { 3 };
    let per_point = 9 + 1 + 3 + 3 + rot_bytes + 3 * dim as u64;
    let want = u64::from(n) * per_point;
    let limit = (bytes.len() as u64).saturating_mul(MAX_DEFLATE_RATIO);
    if want > limit {
        return Err(read_err(format!(
            "header: {n} points need {want} bytes, more than {} compressed bytes can hold",
            bytes.len()
        )));
    }
    let mut data = Vec::new();
    stream
        .take(want + 1)
        .read_to_end(&mut data)
        .map_err(|e| read_err(format!("the point data: {e}")))?;
    if data.len() as u64 != want {
        return Err(read_err(format!(
            "the point data holds {} bytes, the header's {n} points need {want}{}",
            data.len(),
            if (data.len() as u64) < want {
                " (truncated)"
            } else {
                " (trailing data)"
            }
        )));
    }
    let n = n as usize;
    let (pos, rest) = data.split_at(9 * n);
    let (alpha, rest) = rest.split_at(n);
    let (color, rest) = rest.split_at(3 * n);
    let (scale, rest) = rest.split_at(3 * n);
    let (rot, sh) = rest.split_at(rot_bytes as usize * n);
    let step = 1.0 / (1u32 << bits) as f32;
    let positions = pos
        .chunks_exact(9)
        .map(|p| {
            std::array::from_fn(|k| {
                let b = &p[3 * k..3 * k + 3];
                // 24-bit two's complement: shift into the top of an i32 and back
                let v = i32::from_le_bytes([0, b[0], b[1], b[2]]) >> 8;
                v as f32 * step
            })
        })
        .collect();
    let rotations = if version >= 3 {
        rot.chunks_exact(4)
            .map(|r| smallest_three(u32::from_le_bytes(r.try_into().expect("4 bytes"))))
            .collect()
    } else {
        rot.chunks_exact(3)
            .map(|r| {
                let xyz = [0, 1, 2].map(|k| f32::from(r[k]) / 127.5 - 1.0);
                let w = (1.0 - xyz.iter().map(|v| v * v).sum::<f32>())
                    .max(0.0)
                    .sqrt();
                [xyz[0], xyz[1], xyz[2], w]
            })
            .collect()
    };
    Ok(Unpacked {
        version,
        antialiased: flags & 0x1 != 0,
        positions,
        alphas: alpha.iter().map(|&a| f32::from(a) / 255.0).collect(),
        colors: color
            .chunks_exact(3)
            .map(|c| [0, 1, 2].map(|k| (f32::from(c[k]) / 255.0 - 0.5) / COLOR_SCALE))
            .collect(),
        scales: scale
            .chunks_exact(3)
            .map(|s| [0, 1, 2].map(|k| f32::from(s[k]) / 16.0 - 10.0))
            .collect(),
        rotations,
        sh_degree,
        sh: sh.iter().map(|&b| (f32::from(b) - 128.0) / 128.0).collect(),
    })
}

/// A version 3 rotation word → the unit quaternion `x, y, z, w` (module docs).
fn smallest_three(word: u32) -> [f32; 4] {
    let largest = (word >> 30) as usize;
    let mut q = [0f32; 4];
    let mut rest = word;
    let mut sum = 0f32;
    for i in (0..4).rev().filter(|&i| i != largest) {
        let mag = (rest & 511) as f32 / 511.0 * std::f32::consts::FRAC_1_SQRT_2;
        q[i] = if rest & 512 != 0 { -mag } else { mag };
        sum += q[i] * q[i];
        rest >>= 10;
    }
    q[largest] = (1.0 - sum).max(0.0).sqrt();
    q
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

    #[test]
    fn version_2_files_read_back_within_the_quantisation() {
        let c = Cloud {
            positions: &[[1.25, -2.5, 0.001], [-100.0, 7.0, 3.3]],
            alphas: &[0.5, 0.9],
            colors: &[[0.3, -0.2, 1.0], [0.0, 0.5, -1.5]],
            scales: &[[-3.0, -1.5, 0.25], [-9.0, 0.0, 5.0]],
            rotations: &[[0.0, 0.0, 0.0, 1.0], [0.5, -0.5, 0.5, 0.5]],
            sh_degree: 1,
            sh: &[
                0.1, -0.2, 0.3, 0.0, 0.05, -0.5, 0.9, -0.9, 0.2, 0.0, 0.0, 0.0, 0.4, 0.4, 0.4,
                -0.1, 0.1, 0.0,
            ],
        };
        let u = unpack(&write(&c).unwrap()).unwrap();
        assert_eq!((u.version, u.sh_degree, u.positions.len()), (2, 1, 2));
        for (a, b) in u
            .positions
            .iter()
            .flatten()
            .zip(c.positions.iter().flatten())
        {
            assert!((a - b).abs() <= 0.5 / 4096.0 + 1e-6, "{a} {b}");
        }
        for (a, b) in u.alphas.iter().zip(c.alphas) {
            assert!((a - b).abs() <= 0.5 / 255.0 + 1e-6);
        }
        for (a, b) in u.colors.iter().flatten().zip(c.colors.iter().flatten()) {
            assert!((a - b).abs() <= 0.5 / 255.0 / COLOR_SCALE + 1e-5);
        }
        for (a, b) in u.scales.iter().flatten().zip(c.scales.iter().flatten()) {
            assert!((a - b).abs() <= 0.5 / 16.0 + 1e-6);
        }
        for (a, b) in u.rotations.iter().zip(c.rotations) {
            let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
            assert!(dot.abs() > 0.9995, "{a:?} {b:?}");
        }
        // degree 1 buckets of 8/128 = 1/16 (rounding to the nearest: ≤ 1/32 + 1/256)
        for (a, b) in u.sh.iter().zip(c.sh) {
            assert!((a - b).abs() <= 1.0 / 32.0 + 1.0 / 256.0 + 1e-6, "{a} {b}");
        }
        assert_eq!(read_count(&write(&c).unwrap()).unwrap(), 2);
    }

    #[test]
    fn version_3_rotations_are_the_smallest_three() {
        // largest w (index 3) positive; then x, y, z from the high bits down: x = +511
        // (1/√2), y = the sign bit and 0 (−0), z = 0
        let word = (3u32 << 30) | (511 << 20) | (512 << 10);
        let q = smallest_three(word);
        assert!((q[0] - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
        assert!(q[1] == 0.0 && q[1].is_sign_negative());
        assert!(q[2] == 0.0 && q[2].is_sign_positive());
        assert!((q[3] - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
        // largest x (index 0); y, z, w in order, w in the lowest bits: w = −256/511/√2
        let word = (256u32 << 20) | (512 | 256);
        let q = smallest_three(word);
        let m = 256.0 / 511.0 * std::f32::consts::FRAC_1_SQRT_2;
        assert!((q[1] - m).abs() < 1e-6 && q[2] == 0.0 && (q[3] + m).abs() < 1e-6);
        assert!((q.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn damaged_files_are_refused_in_one_line() {
        let c = Cloud {
            positions: &[[1.0, 2.0, 3.0]; 4],
            alphas: &[0.5; 4],
            colors: &[[0.0; 3]; 4],
            scales: &[[0.0; 3]; 4],
            rotations: &[[0.0, 0.0, 0.0, 1.0]; 4],
            sh_degree: 0,
            sh: &[],
        };
        let raw = pack(&c).unwrap();
        let gz = |b: &[u8]| {
            let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            e.write_all(b).unwrap();
            e.finish().unwrap()
        };
        let msg = |b: &[u8]| unpack(b).unwrap_err().to_string();
        assert!(msg(&gz(&raw[..raw.len() - 3])).contains("truncated"));
        let mut more = raw.clone();
        more.push(0);
        assert!(msg(&gz(&more)).contains("trailing"));
        // a header that claims 2³² − 1 points: refused before allocating
        let mut lie = raw.clone();
        lie[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(msg(&gz(&lie)).contains("more than"));
        let mut v5 = raw.clone();
        v5[4] = 5;
        assert!(msg(&gz(&v5)).contains("version 5"));
        let mut ext = raw.clone();
        ext[14] = 2;
        assert!(msg(&gz(&ext)).contains("extensions"));
        assert!(msg(b"NGSP\x04\0\0\0rest").contains("version 4"));
        assert!(msg(b"ply\n").contains("not an SPZ file"));
        assert!(msg(&gz(&raw)[..20]).contains("gzip") || msg(&gz(&raw)[..20]).contains("header"));
    }
}
