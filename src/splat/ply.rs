//! Reading and writing 3DGS PLY files (ASCII, binary little- and big-endian).
//!
//! The header (and every non-fast case) goes through `ply-rs`. Binary little-endian files
//! whose `vertex` element comes first and holds only scalars take a direct byte-decoding
//! fast path (measured in `benches/render.rs`); both paths feed the same row assembler, so
//! they accept and reject exactly the same files.
//!
//! Always errors (the file is unusable): I/O failure, bad header, no `vertex` element, a
//! missing core property (`x y z f_dc_0..2 opacity scale_0..2 rot_0..3`; normals are
//! optional), a list property on `vertex`, an `f_rest_*` count other than 0/9/24/45 or a
//! gap in their numbering, a truncated or unparsable payload (with the vertex index).
//!
//! Per-Gaussian defects — a NaN/±Inf core value or an all-zero quaternion — are errors
//! naming the file and vertex index under [`InvalidPolicy::Error`] (the default). Under
//! [`InvalidPolicy::Drop`] such a Gaussian is dropped and counted in [`PlyReport`]; this is
//! safe because a Gaussian has no links to others. Extra properties are never checked
//! (NaN there is kept as is).
//!
//! Core properties are stored as `f32` (INRIA's type); extras keep their PLY type.
//! Only the `vertex` element is written back; other elements are ignored on reading.
use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};

use ply_rs::parser::Parser;
use ply_rs::ply::{
    DefaultElement, ElementDef, Encoding, Header, Property, PropertyType, ScalarType,
};

use super::{ExtraProperty, Gaussians, ScalarKind, sh_degree_for_rest_count};
use crate::fsutil::{self, FsError};

/// Errors of 3DGS PLY reading and writing; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum PlyError {
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: bad PLY header: {why}")]
    Header { path: PathBuf, why: String },
    #[error("{path}: no `vertex` element")]
    NoVertex { path: PathBuf },
    #[error("{path}: vertex property `{name}` is missing")]
    MissingProperty { path: PathBuf, name: String },
    #[error("{path}: vertex property `{name}` is a list; 3DGS vertices hold scalars only")]
    ListProperty { path: PathBuf, name: String },
    #[error("{path}: {found} `f_rest_*` properties; SH degree 0/1/2/3 needs 0/9/24/45")]
    ShCount { path: PathBuf, found: usize },
    #[error("{path}: payload ends at vertex {vertex} of {count}")]
    Truncated {
        path: PathBuf,
        vertex: usize,
        count: usize,
    },
    #[error("{path}: vertex {vertex}: cannot parse: {why}")]
    Parse {
        path: PathBuf,
        vertex: usize,
        why: String,
    },
    #[error("{path}: vertex {vertex}: property `{name}` is {value} (not finite)")]
    NonFinite {
        path: PathBuf,
        vertex: usize,
        name: String,
        value: f64,
    },
    #[error("{path}: vertex {vertex}: zero quaternion (rot_0..3 all 0)")]
    ZeroQuaternion { path: PathBuf, vertex: usize },
    #[error("cannot write {path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// What to do with a Gaussian that has a NaN/Inf core value or a zero quaternion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub enum InvalidPolicy {
    /// Fail with [`PlyError::NonFinite`] / [`PlyError::ZeroQuaternion`].
    #[default]
    Error,
    /// Drop the Gaussian and count it in [`PlyReport`].
    Drop,
}

/// Reading options.
#[derive(Debug, Clone, Copy, Default)]
pub struct ReadOptions {
    pub invalid: InvalidPolicy,
    /// Use `ply-rs` for every payload, even where the fast path applies (for benchmarks).
    pub force_general_path: bool,
}

/// PLY payload encodings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum PlyEncoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

/// What reading found besides the Gaussians.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PlyReport {
    pub encoding: PlyEncoding,
    /// Vertices in the file.
    pub vertices: usize,
    pub sh_degree: u8,
    pub dropped_non_finite: usize,
    pub dropped_zero_quaternion: usize,
    /// Whether the binary little-endian fast path decoded the payload.
    pub fast_path: bool,
}

/// Where a vertex property goes.
#[derive(Debug, Clone, Copy)]
enum Slot {
    Pos(usize),
    Normal(usize),
    Dc(usize),
    Rest(usize),
    Opacity,
    Scale(usize),
    Rot(usize),
    Extra(usize),
}

struct Layout {
    names: Vec<String>,
    kinds: Vec<ScalarKind>,
    slots: Vec<Slot>,
    has_normals: bool,
    sh_degree: u8,
    rest: usize,
    extras: Vec<(String, ScalarKind)>,
}

fn scalar_kind(t: &ScalarType) -> ScalarKind {
    match t {
        ScalarType::Char => ScalarKind::I8,
        ScalarType::UChar => ScalarKind::U8,
        ScalarType::Short => ScalarKind::I16,
        ScalarType::UShort => ScalarKind::U16,
        ScalarType::Int => ScalarKind::I32,
        ScalarType::UInt => ScalarKind::U32,
        ScalarType::Float => ScalarKind::F32,
        ScalarType::Double => ScalarKind::F64,
    }
}

fn core_slot(name: &str) -> Option<Slot> {
    let idx = |prefix: &str, n: usize| -> Option<usize> {
        name.strip_prefix(prefix)
            .and_then(|s| s.parse::<usize>().ok())
            .filter(|&i| i < n && name == format!("{prefix}{i}"))
    };
    Some(match name {
        "x" => Slot::Pos(0),
        "y" => Slot::Pos(1),
        "z" => Slot::Pos(2),
        "nx" => Slot::Normal(0),
        "ny" => Slot::Normal(1),
        "nz" => Slot::Normal(2),
        "opacity" => Slot::Opacity,
        _ => {
            if let Some(i) = idx("f_dc_", 3) {
                Slot::Dc(i)
            } else if let Some(i) = idx("f_rest_", usize::MAX) {
                Slot::Rest(i)
            } else if let Some(i) = idx("scale_", 3) {
                Slot::Scale(i)
            } else if let Some(i) = idx("rot_", 4) {
                Slot::Rot(i)
            } else {
                return None;
            }
        }
    })
}

fn layout(path: &Path, def: &ElementDef) -> Result<Layout, PlyError> {
    let mut names = Vec::new();
    let mut kinds = Vec::new();
    let mut slots = Vec::new();
    let mut extras = Vec::new();
    let mut seen_rest = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for (name, p) in &def.properties {
        let kind = match &p.data_type {
            PropertyType::Scalar(t) => scalar_kind(t),
            PropertyType::List(..) => {
                return Err(PlyError::ListProperty {
                    path: path.into(),
                    name: name.clone(),
                });
            }
        };
        let slot = match core_slot(name) {
            Some(s) => {
                if let Slot::Rest(i) = s {
                    seen_rest.push(i);
                }
                seen.insert(name.clone());
                s
            }
            None => {
                extras.push((name.clone(), kind));
                Slot::Extra(extras.len() - 1)
            }
        };
        names.push(name.clone());
        kinds.push(kind);
        slots.push(slot);
    }
    let rest = seen_rest.len();
    let sh_degree = sh_degree_for_rest_count(rest).ok_or_else(|| PlyError::ShCount {
        path: path.into(),
        found: rest,
    })?;
    let mut required: Vec<String> = ["x", "y", "z", "opacity"].map(String::from).to_vec();
    required.extend((0..3).map(|i| format!("f_dc_{i}")));
    required.extend((0..3).map(|i| format!("scale_{i}")));
    required.extend((0..4).map(|i| format!("rot_{i}")));
    required.extend((0..rest).map(|i| format!("f_rest_{i}")));
    for name in required {
        if !seen.contains(&name) {
            return Err(PlyError::MissingProperty {
                path: path.into(),
                name,
            });
        }
    }
    let n_normals = ["nx", "ny", "nz"]
        .iter()
        .filter(|n| seen.contains(**n))
        .count();
    if n_normals != 0 && n_normals != 3 {
        let name = ["nx", "ny", "nz"].into_iter().find(|n| !seen.contains(*n));
        return Err(PlyError::MissingProperty {
            path: path.into(),
            name: name.unwrap_or("nx").into(),
        });
    }
    Ok(Layout {
        names,
        kinds,
        slots,
        has_normals: n_normals == 3,
        sh_degree,
        rest,
        extras,
    })
}

/// Collects rows into [`Gaussians`], checking core values.
struct Assembler<'a> {
    path: &'a Path,
    layout: &'a Layout,
    policy: InvalidPolicy,
    g: Gaussians,
    normals: Vec<[f32; 3]>,
    dropped_non_finite: usize,
    dropped_zero_quaternion: usize,
    // Scratch for one Gaussian.
    pos: [f32; 3],
    nrm: [f32; 3],
    dc: [f32; 3],
    rest: Vec<f32>,
    opacity: f32,
    scale: [f32; 3],
    rot: [f32; 4],
    extra: Vec<f64>,
}

impl<'a> Assembler<'a> {
    fn new(path: &'a Path, layout: &'a Layout, policy: InvalidPolicy, capacity: usize) -> Self {
        let g = Gaussians {
            positions: Vec::with_capacity(capacity),
            normals: None,
            sh_degree: layout.sh_degree,
            f_dc: Vec::with_capacity(capacity),
            f_rest: Vec::with_capacity(capacity * layout.rest),
            opacity: Vec::with_capacity(capacity),
            scale: Vec::with_capacity(capacity),
            rotation: Vec::with_capacity(capacity),
            extras: layout
                .extras
                .iter()
                .map(|(name, kind)| ExtraProperty {
                    name: name.clone(),
                    kind: *kind,
                    values: Vec::with_capacity(capacity),
                })
                .collect(),
        };
        Assembler {
            path,
            layout,
            policy,
            g,
            normals: Vec::new(),
            dropped_non_finite: 0,
            dropped_zero_quaternion: 0,
            pos: [0.0; 3],
            nrm: [0.0; 3],
            dc: [0.0; 3],
            rest: vec![0.0; layout.rest],
            opacity: 0.0,
            scale: [0.0; 3],
            rot: [0.0; 4],
            extra: vec![0.0; layout.extras.len()],
        }
    }

    /// Stores property `p` (index in header order) of the current vertex.
    #[inline]
    fn set(&mut self, p: usize, v: f64) {
        let f = v as f32;
        match self.layout.slots[p] {
            Slot::Pos(i) => self.pos[i] = f,
            Slot::Normal(i) => self.nrm[i] = f,
            Slot::Dc(i) => self.dc[i] = f,
            Slot::Rest(i) => self.rest[i] = f,
            Slot::Opacity => self.opacity = f,
            Slot::Scale(i) => self.scale[i] = f,
            Slot::Rot(i) => self.rot[i] = f,
            Slot::Extra(i) => self.extra[i] = v,
        }
    }

    /// Finishes vertex `vertex`: checks it, then keeps or drops it.
    fn finish(&mut self, vertex: usize) -> Result<(), PlyError> {
        if let Some(p) = self.first_non_finite() {
            if self.policy == InvalidPolicy::Drop {
                self.dropped_non_finite += 1;
                return Ok(());
            }
            let (name, value) = p;
            return Err(PlyError::NonFinite {
                path: self.path.into(),
                vertex,
                name,
                value,
            });
        }
        if self.rot.iter().all(|&r| r == 0.0) {
            if self.policy == InvalidPolicy::Drop {
                self.dropped_zero_quaternion += 1;
                return Ok(());
            }
            return Err(PlyError::ZeroQuaternion {
                path: self.path.into(),
                vertex,
            });
        }
        self.g.positions.push(self.pos);
        if self.layout.has_normals {
            self.normals.push(self.nrm);
        }
        self.g.f_dc.push(self.dc);
        self.g.f_rest.extend_from_slice(&self.rest);
        self.g.opacity.push(self.opacity);
        self.g.scale.push(self.scale);
        self.g.rotation.push(self.rot);
        for (e, &v) in self.g.extras.iter_mut().zip(&self.extra) {
            e.values.push(v);
        }
        Ok(())
    }

    fn first_non_finite(&self) -> Option<(String, f64)> {
        let all_finite = self.pos.iter().all(|v| v.is_finite())
            && self.nrm.iter().all(|v| v.is_finite())
            && self.dc.iter().all(|v| v.is_finite())
            && self.rest.iter().all(|v| v.is_finite())
            && self.opacity.is_finite()
            && self.scale.iter().all(|v| v.is_finite())
            && self.rot.iter().all(|v| v.is_finite());
        if all_finite {
            return None;
        }
        // Slow path: name the property.
        for (p, slot) in self.layout.slots.iter().enumerate() {
            let v = match *slot {
                Slot::Pos(i) => self.pos[i],
                Slot::Normal(i) => self.nrm[i],
                Slot::Dc(i) => self.dc[i],
                Slot::Rest(i) => self.rest[i],
                Slot::Opacity => self.opacity,
                Slot::Scale(i) => self.scale[i],
                Slot::Rot(i) => self.rot[i],
                Slot::Extra(_) => continue,
            };
            if !v.is_finite() {
                return Some((self.layout.names[p].clone(), f64::from(v)));
            }
        }
        None
    }

    fn into_gaussians(mut self) -> (Gaussians, usize, usize) {
        if self.layout.has_normals {
            self.g.normals = Some(self.normals);
        }
        (
            self.g,
            self.dropped_non_finite,
            self.dropped_zero_quaternion,
        )
    }
}

fn property_value(p: &Property) -> Option<f64> {
    Some(match *p {
        Property::Char(v) => f64::from(v),
        Property::UChar(v) => f64::from(v),
        Property::Short(v) => f64::from(v),
        Property::UShort(v) => f64::from(v),
        Property::Int(v) => f64::from(v),
        Property::UInt(v) => f64::from(v),
        Property::Float(v) => f64::from(v),
        Property::Double(v) => v,
        _ => return None,
    })
}

#[inline]
fn decode_le(kind: ScalarKind, b: &[u8]) -> f64 {
    match kind {
        ScalarKind::I8 => f64::from(b[0] as i8),
        ScalarKind::U8 => f64::from(b[0]),
        ScalarKind::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
        ScalarKind::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
        ScalarKind::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        ScalarKind::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        ScalarKind::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        ScalarKind::F64 => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
    }
}

/// Reads a 3DGS PLY file.
pub fn read_ply(path: &Path, options: &ReadOptions) -> Result<(Gaussians, PlyReport), PlyError> {
    let bytes = std::fs::read(path).map_err(|source| PlyError::Io {
        path: path.into(),
        source,
    })?;
    read_ply_bytes(path, &bytes, options)
}

/// Reads a 3DGS PLY from memory; `path` only names it in errors.
pub fn read_ply_bytes(
    path: &Path,
    bytes: &[u8],
    options: &ReadOptions,
) -> Result<(Gaussians, PlyReport), PlyError> {
    let parser = Parser::<DefaultElement>::new();
    let mut cursor: &[u8] = bytes;
    let header: Header = parser
        .read_header(&mut cursor)
        .map_err(|e| PlyError::Header {
            path: path.into(),
            why: e.to_string(),
        })?;
    let vertex_pos = header
        .elements
        .keys()
        .position(|k| k == "vertex")
        .ok_or_else(|| PlyError::NoVertex { path: path.into() })?;
    let def = header.elements.get("vertex").expect("position found it");
    let layout = layout(path, def)?;
    let count = def.count;
    let encoding = match header.encoding {
        Encoding::Ascii => PlyEncoding::Ascii,
        Encoding::BinaryLittleEndian => PlyEncoding::BinaryLittleEndian,
        Encoding::BinaryBigEndian => PlyEncoding::BinaryBigEndian,
    };
    // Cap the preallocation by what the payload could hold (a lying header must not OOM).
    let capacity = count.min(cursor.len() / layout.kinds.len().max(1));
    let mut asm = Assembler::new(path, &layout, options.invalid, capacity);
    let fast = encoding == PlyEncoding::BinaryLittleEndian
        && vertex_pos == 0
        && !options.force_general_path;
    if fast {
        let offsets: Vec<usize> = layout
            .kinds
            .iter()
            .scan(0, |acc, k| {
                let o = *acc;
                *acc += k.size();
                Some(o)
            })
            .collect();
        let stride: usize = layout.kinds.iter().map(|k| k.size()).sum();
        let all_f32 = layout.kinds.iter().all(|&k| k == ScalarKind::F32);
        for vertex in 0..count {
            let start = vertex * stride;
            let row = cursor
                .get(start..start + stride)
                .ok_or_else(|| PlyError::Truncated {
                    path: path.into(),
                    vertex,
                    count,
                })?;
            if all_f32 {
                for (p, b) in row.chunks_exact(4).enumerate() {
                    asm.set(p, f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])));
                }
            } else {
                for (p, (&o, &k)) in offsets.iter().zip(&layout.kinds).enumerate() {
                    asm.set(p, decode_le(k, &row[o..o + k.size()]));
                }
            }
            asm.finish(vertex)?;
        }
    } else {
        let io_err = |e: std::io::Error| PlyError::Io {
            path: path.into(),
            source: e,
        };
        // Skip elements before `vertex`.
        for (name, e) in header.elements.iter().take(vertex_pos) {
            if header.encoding == Encoding::Ascii {
                for _ in 0..e.count {
                    let mut skip = String::new();
                    cursor.read_line(&mut skip).map_err(io_err)?;
                }
                continue;
            }
            parser
                .read_payload_for_element(&mut cursor, e, &header)
                .map_err(|e| PlyError::Parse {
                    path: path.into(),
                    vertex: 0,
                    why: format!("element `{name}` before `vertex`: {e}"),
                })?;
        }
        let mut line = String::new();
        for vertex in 0..count {
            let elem = match header.encoding {
                Encoding::Ascii => {
                    // Own tokenizer: ply-rs' ASCII grammar rejects `nan`/`inf`, which must be
                    // reported as NonFinite (core) or kept (extras).
                    line.clear();
                    let n = cursor.read_line(&mut line).map_err(io_err)?;
                    if n == 0 {
                        return Err(PlyError::Truncated {
                            path: path.into(),
                            vertex,
                            count,
                        });
                    }
                    let mut tokens = line.split_ascii_whitespace();
                    for (p, &kind) in layout.kinds.iter().enumerate() {
                        let tok = tokens.next().ok_or_else(|| PlyError::Parse {
                            path: path.into(),
                            vertex,
                            why: format!("no value for `{}`", layout.names[p]),
                        })?;
                        let v = match kind {
                            ScalarKind::F32 => tok.parse::<f32>().map(f64::from).ok(),
                            ScalarKind::F64 => tok.parse::<f64>().ok(),
                            _ => tok.parse::<i64>().ok().map(|v| v as f64),
                        };
                        let v = v.ok_or_else(|| PlyError::Parse {
                            path: path.into(),
                            vertex,
                            why: format!(
                                "`{tok}` is not a {} (`{}`)",
                                kind.ply_name(),
                                layout.names[p]
                            ),
                        })?;
                        asm.set(p, v);
                    }
                    if tokens.next().is_some() {
                        return Err(PlyError::Parse {
                            path: path.into(),
                            vertex,
                            why: "more values than properties".into(),
                        });
                    }
                    asm.finish(vertex)?;
                    continue;
                }
                Encoding::BinaryLittleEndian => parser.read_little_endian_element(&mut cursor, def),
                Encoding::BinaryBigEndian => parser.read_big_endian_element(&mut cursor, def),
            };
            let elem = elem.map_err(|e| {
                if e.kind() == std::io::ErrorKind::UnexpectedEof {
                    PlyError::Truncated {
                        path: path.into(),
                        vertex,
                        count,
                    }
                } else {
                    PlyError::Parse {
                        path: path.into(),
                        vertex,
                        why: e.to_string(),
                    }
                }
            })?;
            for (p, name) in layout.names.iter().enumerate() {
                let v = elem
                    .get(name)
                    .and_then(property_value)
                    .ok_or_else(|| PlyError::Parse {
                        path: path.into(),
                        vertex,
                        why: format!("no value for `{name}`"),
                    })?;
                asm.set(p, v);
            }
            asm.finish(vertex)?;
        }
    }
    let (g, dropped_non_finite, dropped_zero_quaternion) = asm.into_gaussians();
    let report = PlyReport {
        encoding,
        vertices: count,
        sh_degree: g.sh_degree,
        dropped_non_finite,
        dropped_zero_quaternion,
        fast_path: fast,
    };
    Ok((g, report))
}

/// The property names and kinds written for `g`, in INRIA order, extras last.
fn written_properties(g: &Gaussians) -> Vec<(String, ScalarKind)> {
    let f = |s: String| (s, ScalarKind::F32);
    let mut props: Vec<(String, ScalarKind)> = ["x", "y", "z"].map(|s| f(s.into())).to_vec();
    if g.normals.is_some() {
        props.extend(["nx", "ny", "nz"].map(|s| f(s.into())));
    }
    props.extend((0..3).map(|i| f(format!("f_dc_{i}"))));
    props.extend((0..g.rest_per_gaussian()).map(|i| f(format!("f_rest_{i}"))));
    props.push(f("opacity".into()));
    props.extend((0..3).map(|i| f(format!("scale_{i}"))));
    props.extend((0..4).map(|i| f(format!("rot_{i}"))));
    props.extend(g.extras.iter().map(|e| (e.name.clone(), e.kind)));
    props
}

fn row_values(g: &Gaussians, i: usize, out: &mut Vec<f64>) {
    out.clear();
    out.extend(g.positions[i].map(f64::from));
    if let Some(n) = &g.normals {
        out.extend(n[i].map(f64::from));
    }
    out.extend(g.f_dc[i].map(f64::from));
    let r = g.rest_per_gaussian();
    out.extend(g.f_rest[i * r..(i + 1) * r].iter().map(|&v| f64::from(v)));
    out.push(f64::from(g.opacity[i]));
    out.extend(g.scale[i].map(f64::from));
    out.extend(g.rotation[i].map(f64::from));
    out.extend(g.extras.iter().map(|e| e.values[i]));
}

fn encode_le(kind: ScalarKind, v: f64, out: &mut Vec<u8>) {
    match kind {
        ScalarKind::I8 => out.extend((v as i8).to_le_bytes()),
        ScalarKind::U8 => out.extend((v as u8).to_le_bytes()),
        ScalarKind::I16 => out.extend((v as i16).to_le_bytes()),
        ScalarKind::U16 => out.extend((v as u16).to_le_bytes()),
        ScalarKind::I32 => out.extend((v as i32).to_le_bytes()),
        ScalarKind::U32 => out.extend((v as u32).to_le_bytes()),
        ScalarKind::F32 => out.extend((v as f32).to_le_bytes()),
        ScalarKind::F64 => out.extend(v.to_le_bytes()),
    }
}

fn format_ascii(kind: ScalarKind, v: f64, out: &mut String) {
    use std::fmt::Write as _;
    // Debug formatting of floats is the shortest text that parses back to the same value.
    let _ = match kind {
        ScalarKind::F32 => write!(out, "{:?}", v as f32),
        ScalarKind::F64 => write!(out, "{v:?}"),
        _ => write!(out, "{}", v as i64),
    };
}

/// Writes `g` as a 3DGS PLY (atomically), INRIA property order, extras after `rot_3`.
/// `encoding` must be ASCII or binary little-endian.
pub fn write_ply(path: &Path, g: &Gaussians, encoding: PlyEncoding) -> Result<(), PlyError> {
    g.check().map_err(|e| PlyError::Invalid {
        path: path.into(),
        why: e.to_string(),
    })?;
    let props = written_properties(g);
    let format = match encoding {
        PlyEncoding::Ascii => "ascii",
        PlyEncoding::BinaryLittleEndian => "binary_little_endian",
        PlyEncoding::BinaryBigEndian => {
            return Err(PlyError::Invalid {
                path: path.into(),
                why: "writing binary big-endian is not supported".into(),
            });
        }
    };
    let mut head = format!("ply\nformat {format} 1.0\nelement vertex {}\n", g.len());
    for (name, kind) in &props {
        head.push_str(&format!("property {} {name}\n", kind.ply_name()));
    }
    head.push_str("end_header\n");
    let werr = |source| FsError::Write {
        path: path.into(),
        source,
    };
    fsutil::atomic_write(path, |w| -> Result<(), PlyError> {
        w.write_all(head.as_bytes()).map_err(werr)?;
        let mut row = Vec::new();
        let mut buf = Vec::with_capacity(1 << 16);
        let mut text = String::new();
        for i in 0..g.len() {
            row_values(g, i, &mut row);
            match encoding {
                PlyEncoding::Ascii => {
                    text.clear();
                    for (j, (&v, (_, kind))) in row.iter().zip(&props).enumerate() {
                        if j > 0 {
                            text.push(' ');
                        }
                        format_ascii(*kind, v, &mut text);
                    }
                    text.push('\n');
                    buf.extend_from_slice(text.as_bytes());
                }
                _ => {
                    for (&v, (_, kind)) in row.iter().zip(&props) {
                        encode_le(*kind, v, &mut buf);
                    }
                }
            }
            if buf.len() > 1 << 16 {
                w.write_all(&buf).map_err(werr)?;
                buf.clear();
            }
        }
        w.write_all(&buf).map_err(werr)?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("gs4city-ply-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    fn sample(n: usize, degree: u8, seed: u64) -> Gaussians {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut r = || rng.random_range(-3.0f32..3.0);
        let rest = crate::splat::REST_COUNTS[degree as usize];
        let mut g = Gaussians {
            sh_degree: degree,
            normals: Some(Vec::new()),
            ..Default::default()
        };
        for _ in 0..n {
            g.positions.push([r(), r(), r()]);
            g.normals.as_mut().unwrap().push([0.0, r(), 0.0]);
            g.f_dc.push([r(), r(), r()]);
            for _ in 0..rest {
                g.f_rest.push(r() * 1e-3);
            }
            g.opacity.push(r());
            g.scale.push([r(), r(), r()]);
            g.rotation.push([r(), r(), r(), 1.0]);
        }
        let ramp = |k: f64| (0..n).map(|i| (i as f64) * k + 0.0).collect::<Vec<_>>();
        g.extras = vec![
            ExtraProperty {
                name: "obj_dc_0".into(),
                kind: ScalarKind::F32,
                values: (0..n).map(|i| f64::from(0.1f32 * i as f32)).collect(),
            },
            ExtraProperty {
                name: "semantic_id".into(),
                kind: ScalarKind::I32,
                values: ramp(-7.0),
            },
            ExtraProperty {
                name: "label".into(),
                kind: ScalarKind::U8,
                values: ramp(1.0).iter().map(|v| v % 256.0).collect(),
            },
            ExtraProperty {
                name: "weight".into(),
                kind: ScalarKind::F64,
                values: ramp(std::f64::consts::PI),
            },
            ExtraProperty {
                name: "maybe".into(),
                kind: ScalarKind::F32,
                values: vec![f64::NAN; n],
            },
        ];
        g
    }

    fn bits(g: &Gaussians) -> Vec<u64> {
        let mut out = Vec::new();
        let mut row = Vec::new();
        for i in 0..g.len() {
            row_values(g, i, &mut row);
            out.extend(row.iter().map(|v| v.to_bits()));
        }
        out
    }

    #[test]
    fn round_trip_is_bit_exact_with_extras_all_degrees_and_encodings() {
        for degree in 0..=3u8 {
            let g = sample(37, degree, u64::from(degree));
            for enc in [PlyEncoding::BinaryLittleEndian, PlyEncoding::Ascii] {
                let p = tmp(&format!("rt{degree}{enc:?}.ply"));
                write_ply(&p, &g, enc).unwrap();
                for force_general_path in [false, true] {
                    let opts = ReadOptions {
                        force_general_path,
                        ..Default::default()
                    };
                    let (back, report) = read_ply(&p, &opts).unwrap();
                    assert_eq!(report.sh_degree, degree);
                    assert_eq!(
                        report.fast_path,
                        enc == PlyEncoding::BinaryLittleEndian && !force_general_path
                    );
                    let (a, b) = (bits(&back), bits(&g));
                    assert_eq!(a.len(), b.len());
                    let diff = a.iter().zip(&b).position(|(x, y)| x != y);
                    assert_eq!(
                        diff,
                        None,
                        "degree {degree} {enc:?} general={force_general_path}: {:?}",
                        diff.map(|d| (f64::from_bits(a[d]), f64::from_bits(b[d])))
                    );
                    assert_eq!(
                        back.extras.iter().map(|e| e.kind).collect::<Vec<_>>(),
                        g.extras.iter().map(|e| e.kind).collect::<Vec<_>>()
                    );
                    assert!(
                        back.extra("maybe")
                            .unwrap()
                            .values
                            .iter()
                            .all(|v| v.is_nan())
                    );
                }
            }
        }
    }

    fn header(props: &[&str], n: usize, format: &str) -> String {
        let mut h = format!("ply\nformat {format} 1.0\nelement vertex {n}\n");
        for p in props {
            h.push_str(&format!("property float {p}\n"));
        }
        h + "end_header\n"
    }

    const CORE: [&str; 14] = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ];

    fn ascii_file(name: &str, props: &[&str], rows: &[Vec<&str>], n: usize) -> PathBuf {
        let mut text = header(props, n, "ascii");
        for r in rows {
            text.push_str(&r.join(" "));
            text.push('\n');
        }
        let p = tmp(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn good_row() -> Vec<&'static str> {
        vec![
            "0", "0", "1", "0.1", "0.2", "0.3", "0", "-1", "-1", "-1", "1", "0", "0", "0",
        ]
    }

    #[test]
    fn missing_property_is_named() {
        let props: Vec<&str> = CORE.iter().copied().filter(|&p| p != "scale_1").collect();
        let p = ascii_file("missing.ply", &props, &[], 0);
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(
            matches!(&e, PlyError::MissingProperty { name, .. } if name == "scale_1"),
            "{e}"
        );
        assert!(e.to_string().contains("missing.ply"));
    }

    #[test]
    fn wrong_sh_count_is_rejected() {
        let mut props = CORE.to_vec();
        let rest: Vec<String> = (0..10).map(|i| format!("f_rest_{i}")).collect();
        props.extend(rest.iter().map(String::as_str));
        let p = ascii_file("sh.ply", &props, &[], 0);
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(matches!(e, PlyError::ShCount { found: 10, .. }), "{e}");
        // 9 values but with a gap in the numbering: f_rest_9 instead of f_rest_8.
        let mut props = CORE.to_vec();
        let rest: Vec<String> = (0..8).chain([9]).map(|i| format!("f_rest_{i}")).collect();
        props.extend(rest.iter().map(String::as_str));
        let p = ascii_file("shgap.ply", &props, &[], 0);
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(
            matches!(&e, PlyError::MissingProperty { name, .. } if name == "f_rest_8"),
            "{e}"
        );
    }

    #[test]
    fn truncated_payload_names_the_vertex() {
        let g = sample(10, 1, 5);
        let p = tmp("trunc_src.ply");
        write_ply(&p, &g, PlyEncoding::BinaryLittleEndian).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let cut = tmp("trunc.ply");
        std::fs::write(&cut, &bytes[..bytes.len() - 10]).unwrap();
        for force_general_path in [false, true] {
            let opts = ReadOptions {
                force_general_path,
                ..Default::default()
            };
            let e = read_ply(&cut, &opts).unwrap_err();
            assert!(
                matches!(
                    e,
                    PlyError::Truncated {
                        vertex: 9,
                        count: 10,
                        ..
                    }
                ),
                "{e}"
            );
        }
        let rows = vec![good_row(), good_row()];
        let p = ascii_file("trunc_ascii.ply", &CORE, &rows, 3);
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(matches!(e, PlyError::Truncated { vertex: 2, .. }), "{e}");
        let mut short = good_row();
        short.pop();
        let p = ascii_file("short_ascii.ply", &CORE, &[good_row(), short], 2);
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(matches!(e, PlyError::Parse { vertex: 1, .. }), "{e}");
    }

    #[test]
    fn non_finite_and_zero_quaternion_error_or_drop() {
        let mut nan = good_row();
        nan[4] = "nan";
        let mut inf = good_row();
        inf[8] = "inf";
        let mut zero = good_row();
        zero[10] = "0";
        let rows = vec![good_row(), nan, good_row(), inf, zero, good_row()];
        let p = ascii_file("bad.ply", &CORE, &rows, rows.len());
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(
            matches!(&e, PlyError::NonFinite { vertex: 1, name, .. } if name == "f_dc_1"),
            "{e}"
        );
        assert!(e.to_string().contains("bad.ply"));
        let rows = vec![
            good_row(),
            good_row(),
            good_row(),
            good_row(),
            rows[4].clone(),
        ];
        let p = ascii_file("zeroq.ply", &CORE, &rows, rows.len());
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(
            matches!(e, PlyError::ZeroQuaternion { vertex: 4, .. }),
            "{e}"
        );

        // Binary, dropped and counted.
        let mut g = sample(6, 0, 9);
        g.scale[1][2] = f32::INFINITY;
        g.positions[2][0] = f32::NAN;
        g.rotation[4] = [0.0; 4];
        let p = tmp("drop.ply");
        write_ply(&p, &g, PlyEncoding::BinaryLittleEndian).unwrap();
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(
            matches!(&e, PlyError::NonFinite { vertex: 1, name, .. } if name == "scale_2"),
            "{e}"
        );
        let opts = ReadOptions {
            invalid: InvalidPolicy::Drop,
            ..Default::default()
        };
        let (back, report) = read_ply(&p, &opts).unwrap();
        assert_eq!(
            (report.dropped_non_finite, report.dropped_zero_quaternion),
            (2, 1)
        );
        assert_eq!(back.len(), 3);
        assert_eq!(back.positions[2], g.positions[5]);
        assert_eq!(back.extras[1].values, vec![0.0, -21.0, -35.0]);
    }

    #[test]
    fn big_endian_and_leading_elements_go_through_the_general_path() {
        let mut text = header(&CORE, 2, "binary_big_endian")
            .replace("end_header", "property int semantic_id\nend_header");
        // A leading element that the reader must skip.
        text = text.replace(
            "element vertex",
            "element camera 1\nproperty uchar k\nelement vertex",
        );
        let mut bytes = text.into_bytes();
        bytes.push(7); // the camera element
        for v in 0..2i32 {
            for (j, _) in CORE.iter().enumerate() {
                let x: f32 = if j == 10 {
                    1.0
                } else {
                    v as f32 + j as f32 * 0.25
                };
                bytes.extend(x.to_be_bytes());
            }
            bytes.extend((-v - 5).to_be_bytes());
        }
        let p = tmp("be.ply");
        std::fs::write(&p, &bytes).unwrap();
        let (g, report) = read_ply(&p, &ReadOptions::default()).unwrap();
        assert_eq!(report.encoding, PlyEncoding::BinaryBigEndian);
        assert!(!report.fast_path);
        assert_eq!(g.positions, vec![[0.0, 0.25, 0.5], [1.0, 1.25, 1.5]]);
        assert_eq!(g.rotation[1], [1.0, 3.75, 4.0, 4.25]);
        let e = g.extra("semantic_id").unwrap();
        assert_eq!(
            (e.kind, e.values.clone()),
            (ScalarKind::I32, vec![-5.0, -6.0])
        );
        std::fs::write(&p, &bytes[..bytes.len() - 3]).unwrap();
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(matches!(e, PlyError::Truncated { vertex: 1, .. }), "{e}");
    }

    #[test]
    fn garbage_and_list_properties_are_errors_not_panics() {
        let p = tmp("garbage.ply");
        std::fs::write(&p, b"not a ply at all").unwrap();
        assert!(matches!(
            read_ply(&p, &ReadOptions::default()),
            Err(PlyError::Header { .. })
        ));
        let mut text = header(&CORE, 0, "binary_little_endian");
        text = text.replace("end_header", "property list uchar int idx\nend_header");
        std::fs::write(&p, text).unwrap();
        assert!(matches!(
            read_ply(&p, &ReadOptions::default()),
            Err(PlyError::ListProperty { .. })
        ));
        // A header that promises 10^12 vertices must fail cleanly, not allocate.
        let text = header(&CORE, 1_000_000_000_000, "binary_little_endian");
        std::fs::write(&p, text).unwrap();
        assert!(matches!(
            read_ply(&p, &ReadOptions::default()),
            Err(PlyError::Truncated { vertex: 0, .. })
        ));
        assert!(matches!(
            read_ply(&tmp("nope.ply"), &ReadOptions::default()),
            Err(PlyError::Io { .. })
        ));
    }
}
