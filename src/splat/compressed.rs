//! SuperSplat's compressed PLY (PlayCanvas; written by SuperSplat and `splat-transform`, read
//! here as `@playcanvas/splat-transform` 2.7.1 reads and writes it), read into INRIA
//! [`Gaussians`]. A binary little-endian PLY with the elements
//!
//! * `chunk`, one row per 256 splats (`⌈n / 256⌉` rows): `float` `min_x min_y min_z max_x max_y
//!   max_z min_scale_x … max_scale_z` and, in newer files, `min_r min_g min_b max_r max_g max_b`;
//! * `vertex`, one row per splat: `uint` `packed_position packed_rotation packed_scale
//!   packed_color`;
//! * optionally `sh`, one row per splat: `uchar` `f_rest_0 … f_rest_{N−1}`, N = 9, 24 or 45.
//!
//! Splat `i` belongs to chunk `⌊i / 256⌋`. Position and log scale: 11, 10 and 11 bits for
//! `x, y, z` from the top bit down, each `u / (2^bits − 1)` between the chunk's minimum and
//! maximum. Rotation: the top 2 bits name the largest component of `rot_0..3` (made positive,
//! `= √(1 − a² − b² − c²)`), the other three follow in order, 10 bits each, `(u / 1023 − 0.5)·√2`.
//! Colour: bytes `r g b a` from the top; `r g b` between the chunk's colour bounds where it has
//! them (else as they are), `f_dc = (c − 0.5) / C0`; `a` the opacity after the sigmoid (its
//! logit as in [`super::formats`]). SH: byte `b` → `(n − 0.5)·8` with `n = 0` for 0, 1 for 255,
//! else `(b + 0.5) / 256`.
use std::path::Path;

use super::Gaussians;
use super::formats::{SplatFormat, opacity_logit};
use super::ply::{PlyError, PlyReport, ReadOptions, assemble};
use crate::ply::{Encoding, Header, PropertyKind, Reader, ScalarKind};

/// Splats per chunk.
pub const CHUNK: usize = 256;
const SH_C0: f64 = 0.282_094_791_773_878_14;
const CHUNK_BOUNDS: [&str; 12] = [
    "min_x",
    "min_y",
    "min_z",
    "max_x",
    "max_y",
    "max_z",
    "min_scale_x",
    "min_scale_y",
    "min_scale_z",
    "max_scale_x",
    "max_scale_y",
    "max_scale_z",
];
const CHUNK_COLORS: [&str; 6] = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"];
const PACKED: [&str; 4] = [
    "packed_position",
    "packed_rotation",
    "packed_scale",
    "packed_color",
];

/// Whether a PLY header is a compressed PLY's (a `chunk` element and a `vertex` element with
/// `packed_position`).
pub fn is_compressed(h: &Header) -> bool {
    h.element("chunk").is_some()
        && h.element("vertex")
            .is_some_and(|v| h.elements[v].property("packed_position").is_some())
}

fn bad(path: &Path, why: impl Into<String>) -> PlyError {
    PlyError::Decode {
        path: path.into(),
        why: why.into(),
    }
}

/// The property indices of `names` in element `e`, each of scalar type `kind`.
fn columns(
    path: &Path,
    h: &Header,
    e: usize,
    names: &[&str],
    kind: ScalarKind,
) -> Result<Vec<usize>, PlyError> {
    let def = &h.elements[e];
    names
        .iter()
        .map(|n| {
            let p = def.property(n).ok_or_else(|| {
                bad(
                    path,
                    format!(
                        "compressed PLY: element `{}` has no property `{n}`",
                        def.name
                    ),
                )
            })?;
            if def.properties[p].kind != PropertyKind::Scalar(kind) {
                return Err(bad(
                    path,
                    format!(
                        "compressed PLY: `{}.{n}` is not of type {}",
                        def.name,
                        kind.ply_name()
                    ),
                ));
            }
            Ok(p)
        })
        .collect()
}

/// `u`'s `bits` low bits as a fraction of their largest value.
fn unorm(u: u32, bits: u32) -> f64 {
    let m = (1u32 << bits) - 1;
    f64::from(u & m) / f64::from(m)
}

fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a * (1.0 - t) + b * t
}

/// Reads a compressed PLY whose header `reader` has parsed (module docs).
pub fn read(
    path: &Path,
    mut reader: Reader<'_>,
    options: &ReadOptions,
) -> Result<(Gaussians, PlyReport), PlyError> {
    let h = reader.header().clone();
    if h.encoding != Encoding::BinaryLittleEndian {
        return Err(bad(
            path,
            format!(
                "compressed PLY in {} (binary_little_endian expected)",
                h.encoding.keyword()
            ),
        ));
    }
    let (ce, ve) = (
        h.element("chunk").expect("is_compressed"),
        h.element("vertex").expect("is_compressed"),
    );
    let bounds = columns(path, &h, ce, &CHUNK_BOUNDS, ScalarKind::F32)?;
    let has_colors = h.elements[ce].property("min_r").is_some();
    let colors = if has_colors {
        columns(path, &h, ce, &CHUNK_COLORS, ScalarKind::F32)?
    } else {
        Vec::new()
    };
    let packed = columns(path, &h, ve, &PACKED, ScalarKind::U32)?;
    let n = h.elements[ve].count;
    let chunks = h.elements[ce].count;
    if chunks != n.div_ceil(CHUNK) {
        return Err(bad(
            path,
            format!(
                "compressed PLY: {chunks} chunks for {n} splats (⌈n / 256⌉ = {} expected)",
                n.div_ceil(CHUNK)
            ),
        ));
    }
    let she = h.element("sh");
    let sh_names: Vec<String> = she.map_or(Vec::new(), |e| {
        h.elements[e]
            .properties
            .iter()
            .map(|p| p.name.clone())
            .collect()
    });
    let rest = sh_names.len();
    let sh_degree = super::sh_degree_for_rest_count(rest).ok_or_else(|| {
        bad(
            path,
            format!("compressed PLY: {rest} `sh` properties; 9, 24 or 45 expected"),
        )
    })?;
    let sh_cols = match she {
        Some(e) => {
            if h.elements[e].count != n {
                return Err(bad(
                    path,
                    format!(
                        "compressed PLY: {} `sh` rows for {n} splats",
                        h.elements[e].count
                    ),
                ));
            }
            let want: Vec<String> = (0..rest).map(|i| format!("f_rest_{i}")).collect();
            let refs: Vec<&str> = want.iter().map(String::as_str).collect();
            columns(path, &h, e, &refs, ScalarKind::U8)?
        }
        None => Vec::new(),
    };
    // Every element in file order (the header checked the sizes against the payload).
    let mut chunk_rows: Vec<[f64; 18]> = Vec::with_capacity(chunks);
    let mut words: Vec<[u32; 4]> = Vec::with_capacity(n);
    let mut sh: Vec<u8> = Vec::with_capacity(n * rest);
    let mut order: Vec<usize> = vec![ce, ve];
    order.extend(she);
    order.sort_unstable();
    for e in order {
        let name = h.elements[e].name.clone();
        reader.read_element::<PlyError>(&name, |row| {
            if e == ce {
                let mut c = [0f64; 18];
                for (k, &p) in bounds.iter().chain(&colors).enumerate() {
                    c[k] = row.get(p);
                }
                chunk_rows.push(c);
            } else if e == ve {
                words.push([0, 1, 2, 3].map(|k| row.get(packed[k]) as u32));
            } else {
                sh.extend(sh_cols.iter().map(|&p| row.get(p) as u8));
            }
            Ok(())
        })?;
    }
    reader.finish()?;
    assemble(
        path,
        SplatFormat::CompressedPly,
        sh_degree,
        n,
        options,
        |i, out| {
            let c = &chunk_rows[i / CHUNK];
            let [pos, rot, scale, col] = words[i];
            let t = [unorm(pos >> 21, 11), unorm(pos >> 11, 10), unorm(pos, 11)];
            out.extend((0..3).map(|k| lerp(c[k], c[3 + k], t[k])));
            let rgba = [24, 16, 8].map(|s| unorm(col >> s, 8));
            for k in 0..3 {
                let v = if has_colors {
                    lerp(c[12 + k], c[15 + k], rgba[k])
                } else {
                    rgba[k]
                };
                out.push((v - 0.5) / SH_C0);
            }
            out.extend(sh[i * rest..(i + 1) * rest].iter().map(|&b| {
                let v = match b {
                    0 => 0.0,
                    255 => 1.0,
                    _ => (f64::from(b) + 0.5) / 256.0,
                };
                (v - 0.5) * 8.0
            }));
            out.push(opacity_logit(unorm(col, 8)));
            let s = [
                unorm(scale >> 21, 11),
                unorm(scale >> 11, 10),
                unorm(scale, 11),
            ];
            out.extend((0..3).map(|k| lerp(c[6 + k], c[9 + k], s[k])));
            let abc = [20, 10, 0].map(|s| (unorm(rot >> s, 10) - 0.5) * std::f64::consts::SQRT_2);
            let largest = (rot >> 30) as usize;
            let m = (1.0 - abc.iter().map(|v| v * v).sum::<f64>())
                .max(0.0)
                .sqrt();
            let mut q = [0f64; 4];
            let mut rest_abc = abc.iter();
            for (k, v) in q.iter_mut().enumerate() {
                *v = if k == largest {
                    m
                } else {
                    *rest_abc.next().expect("three components")
                };
            }
            out.extend(q);
        },
    )
}
