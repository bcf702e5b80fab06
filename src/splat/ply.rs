//! The 3DGS layout of a PLY file (INRIA): one `vertex` element of scalars, read and written
//! through the shared PLY layer [`crate::ply`] (ASCII, binary little- and big-endian).
//! Binary little-endian files whose vertex properties are all `float` take the layer's
//! fast path (measured in `benches/ply.rs`); every path feeds the same row assembler, so
//! they accept and reject exactly the same files.
//!
//! Always errors (the file is unusable): I/O failure, a bad header or payload (see
//! [`crate::ply`]), no `vertex` element, a missing core property (`x y z f_dc_0..2 opacity
//! scale_0..2 rot_0..3`; normals are optional), a list property on `vertex`, an `f_rest_*`
//! count other than 0/9/24/45 or a gap in their numbering, data after the last element.
//!
//! Per-Gaussian defects are checked once here, at load, so that no later stage meets them
//! (the ranges are [`LOG_SCALE_RANGE`], [`MAX_ABS_SH`] and the scene frame's
//! [`crate::camera::SCENE_COORD_LIMIT`]):
//! * every core value (position, normal, SH, opacity, scale, rotation) is finite;
//! * `|x|, |y|, |z| ≤ SCENE_COORD_LIMIT` (the f32 scene frame; see `camera`);
//! * `scale_i ∈ LOG_SCALE_RANGE` = [−40, 20]: the activated scale `exp(scale)` stays a finite,
//!   non-zero `f32` and the projected covariance `exp(2·scale)·(f/z)²` cannot overflow;
//! * `|f_dc_*|, |f_rest_*| ≤ MAX_ABS_SH` = 10⁶: the SH colour sum (≤ 48 terms) stays far from
//!   `f32` overflow (real models hold |f_dc| ≲ 5, |f_rest| ≲ 1);
//! * the opacity logit may be any finite number (`sigmoid` saturates, it cannot overflow);
//! * the quaternion `rot_0..3` is not all zero.
//!
//! Under [`InvalidPolicy::Error`] (the default) such a Gaussian is an error naming the file,
//! the vertex (and line in ASCII) and the property. Under [`InvalidPolicy::Drop`] it is
//! dropped and counted in [`PlyReport`]; this is safe because a Gaussian has no links to
//! others. Under [`InvalidPolicy::Keep`] (the pipeline's policy) it is kept in place, as read,
//! and counted: Gaussian `i` of the file stays Gaussian `i`, the pipeline never draws it
//! ([`is_valid`] is false, [`hide_invalid`]) and `semantic.ply` labels it −1. Extra properties are never checked
//! (NaN there is kept as is).
//!
//! Core properties are stored as `f32` (INRIA's type); extras keep their PLY type.
//! Only the `vertex` element is written back; other elements are checked and ignored on
//! reading.
use std::io::Write;
use std::path::{Path, PathBuf};

use super::{ExtraProperty, Gaussians, sh_degree_for_rest_count};
use crate::camera::SCENE_COORD_LIMIT;
use crate::fsutil::{self, FsError};
use crate::ply::{self, ElementDef, PropertyDef, PropertyKind, Reader, Row, RowWriter, at_line};
pub use crate::ply::{Encoding as PlyEncoding, ScalarKind};

/// Accepted raw (log) scales `scale_i`, inclusive.
pub const LOG_SCALE_RANGE: (f32, f32) = (-40.0, 20.0);
/// Largest accepted `|f_dc_*|`, `|f_rest_*|`.
pub const MAX_ABS_SH: f32 = 1e6;

/// Errors of 3DGS PLY reading and writing; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum PlyError {
    #[error(transparent)]
    Format(#[from] ply::PlyError),
    #[error("{path}: no `vertex` element")]
    NoVertex { path: PathBuf },
    #[error("{path}: vertex property `{name}` is missing")]
    MissingProperty { path: PathBuf, name: String },
    #[error("{path}: vertex property `{name}` is a list; 3DGS vertices hold scalars only")]
    ListProperty { path: PathBuf, name: String },
    #[error("{path}: {found} `f_rest_*` properties; SH degree 0/1/2/3 needs 0/9/24/45")]
    ShCount { path: PathBuf, found: usize },
    #[error("{path}: vertex {vertex}{}: `{name}` is {value:?}, not a finite number", at_line(*line))]
    NonFinite {
        path: PathBuf,
        vertex: usize,
        line: Option<usize>,
        name: String,
        value: f32,
    },
    #[error("{path}: vertex {vertex}{}: `{name}` is {value:?}, outside {range}", at_line(*line))]
    OutOfRange {
        path: PathBuf,
        vertex: usize,
        line: Option<usize>,
        name: String,
        value: f32,
        range: &'static str,
    },
    #[error("{path}: vertex {vertex}{}: zero quaternion (rot_0..3 all 0)", at_line(*line))]
    ZeroQuaternion {
        path: PathBuf,
        vertex: usize,
        line: Option<usize>,
    },
    #[error("cannot write {path}: {why}")]
    Invalid { path: PathBuf, why: String },
    /// A splat file of another format ([`super::formats`]) that cannot be read.
    #[error("{path}: {why}")]
    Decode { path: PathBuf, why: String },
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// What to do with a Gaussian that fails a per-Gaussian check (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub enum InvalidPolicy {
    /// Fail with [`PlyError::NonFinite`] / [`PlyError::OutOfRange`] / [`PlyError::ZeroQuaternion`].
    #[default]
    Error,
    /// Drop the Gaussian and count it in [`PlyReport`].
    Drop,
    /// Keep the Gaussian as read, in its place, and count it in [`PlyReport`] (the first few
    /// with the message [`InvalidPolicy::Error`] would give).
    Keep,
}

/// How many invalid Gaussians [`PlyReport::invalid_examples`] describes.
pub const INVALID_EXAMPLES: usize = 5;

/// Reading options.
#[derive(Debug, Clone, Copy, Default)]
pub struct ReadOptions {
    pub invalid: InvalidPolicy,
    /// Decode every property one by one even where the all-`float` little-endian fast path
    /// applies (for benchmarks and cross-checks).
    pub force_general_path: bool,
}

impl ReadOptions {
    /// The pipeline's reading: every Gaussian kept in file order ([`InvalidPolicy::Keep`]).
    pub const KEEP: ReadOptions = ReadOptions {
        invalid: InvalidPolicy::Keep,
        force_general_path: false,
    };
}

/// What reading found besides the Gaussians.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PlyReport {
    pub encoding: PlyEncoding,
    /// Vertices in the file.
    pub vertices: usize,
    pub sh_degree: u8,
    pub dropped_non_finite: usize,
    /// Dropped for a value outside its range (position, log scale, SH; module docs).
    pub dropped_out_of_range: usize,
    pub dropped_zero_quaternion: usize,
    /// Invalid Gaussians kept in place ([`InvalidPolicy::Keep`]).
    #[serde(default)]
    pub kept_invalid: usize,
    /// Of those, the ones with a non-finite position (`x`, `y` or `z` NaN or infinite).
    #[serde(default)]
    pub kept_non_finite_position: usize,
    /// The first [`INVALID_EXAMPLES`] invalid Gaussians (kept or dropped), each as the one-line
    /// error [`InvalidPolicy::Error`] would give (file, vertex, property).
    #[serde(default)]
    pub invalid_examples: Vec<String>,
    /// Whether the binary little-endian all-`float` fast path decoded the payload.
    pub fast_path: bool,
    /// The file's format (an INRIA PLY, or one of the formats converted to its Gaussians).
    #[serde(default)]
    pub format: super::formats::SplatFormat,
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
    slots: Vec<Slot>,
    has_normals: bool,
    sh_degree: u8,
    rest: usize,
    extras: Vec<(String, ScalarKind)>,
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
    let mut slots = Vec::new();
    let mut extras = Vec::new();
    let mut seen_rest = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for p in &def.properties {
        let name = &p.name;
        let kind = match p.kind {
            PropertyKind::Scalar(k) => k,
            PropertyKind::List { .. } => {
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
        slots,
        has_normals: n_normals == 3,
        sh_degree,
        rest,
        extras,
    })
}

/// Why a Gaussian is refused (module docs).
enum Defect {
    NonFinite(usize, f32),
    OutOfRange(usize, f32, &'static str),
    ZeroQuaternion,
}

/// Collects rows into [`Gaussians`], checking core values.
struct Assembler<'a> {
    path: &'a Path,
    layout: &'a Layout,
    policy: InvalidPolicy,
    g: Gaussians,
    normals: Vec<[f32; 3]>,
    dropped_non_finite: usize,
    dropped_out_of_range: usize,
    dropped_zero_quaternion: usize,
    kept_invalid: usize,
    kept_non_finite_position: usize,
    examples: Vec<String>,
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
            normals: Vec::with_capacity(if layout.has_normals { capacity } else { 0 }),
            dropped_non_finite: 0,
            dropped_out_of_range: 0,
            dropped_zero_quaternion: 0,
            kept_invalid: 0,
            kept_non_finite_position: 0,
            examples: Vec::new(),
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

    /// Takes one row (all properties in header order), checks it, then keeps or drops it.
    #[inline]
    fn row(&mut self, row: &Row) -> Result<(), PlyError> {
        self.values(row.index, row.line, row.values())
    }

    /// [`Assembler::row`] on the values of vertex `index` (at `line` of an ASCII file).
    #[inline]
    fn values(
        &mut self,
        index: usize,
        line: Option<usize>,
        values: &[f64],
    ) -> Result<(), PlyError> {
        for (&slot, &v) in self.layout.slots.iter().zip(values) {
            let f = v as f32;
            match slot {
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
        if let Some(defect) = self.defect() {
            let (path, vertex) = (self.path.into(), index);
            let name = |p: usize| self.layout.names[p].clone();
            let err = match defect {
                Defect::NonFinite(p, value) => PlyError::NonFinite {
                    path,
                    vertex,
                    line,
                    name: name(p),
                    value,
                },
                Defect::OutOfRange(p, value, range) => PlyError::OutOfRange {
                    path,
                    vertex,
                    line,
                    name: name(p),
                    value,
                    range,
                },
                Defect::ZeroQuaternion => PlyError::ZeroQuaternion { path, vertex, line },
            };
            match self.policy {
                InvalidPolicy::Error => return Err(err),
                InvalidPolicy::Drop | InvalidPolicy::Keep => {
                    if self.examples.len() < INVALID_EXAMPLES {
                        self.examples.push(err.to_string());
                    }
                }
            }
            if self.policy == InvalidPolicy::Drop {
                match defect {
                    Defect::NonFinite(..) => self.dropped_non_finite += 1,
                    Defect::OutOfRange(..) => self.dropped_out_of_range += 1,
                    Defect::ZeroQuaternion => self.dropped_zero_quaternion += 1,
                }
                return Ok(());
            }
            self.kept_invalid += 1;
            if self.pos.iter().any(|v| !v.is_finite()) {
                self.kept_non_finite_position += 1;
            }
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

    /// The first defect of the current Gaussian, if any (fast check first, then the slow
    /// path names the property).
    #[inline]
    fn defect(&self) -> Option<Defect> {
        let ok = core_valid(
            &self.pos,
            &self.nrm,
            &self.dc,
            &self.rest,
            self.opacity,
            &self.scale,
            &self.rot,
        );
        if ok {
            return None;
        }
        // Non-finite values first (a NaN is not "out of range", it is not a number).
        let lim = SCENE_COORD_LIMIT as f32;
        let (lo, hi) = LOG_SCALE_RANGE;
        let mut out_of_range = None;
        for (p, slot) in self.layout.slots.iter().enumerate() {
            let (v, range_ok, range) = match *slot {
                Slot::Pos(i) => (
                    self.pos[i],
                    self.pos[i].abs() <= lim,
                    "±1e6, the f32 scene frame's limit (camera::SCENE_COORD_LIMIT)",
                ),
                Slot::Normal(i) => (self.nrm[i], true, ""),
                Slot::Dc(i) => (
                    self.dc[i],
                    self.dc[i].abs() <= MAX_ABS_SH,
                    "±1e6 (MAX_ABS_SH)",
                ),
                Slot::Rest(i) => (
                    self.rest[i],
                    self.rest[i].abs() <= MAX_ABS_SH,
                    "±1e6 (MAX_ABS_SH)",
                ),
                Slot::Opacity => (self.opacity, true, ""),
                Slot::Scale(i) => (
                    self.scale[i],
                    (lo..=hi).contains(&self.scale[i]),
                    "the log-scale range −40..20 (exp(scale) must stay a finite, non-zero f32)",
                ),
                Slot::Rot(i) => (self.rot[i], true, ""),
                Slot::Extra(_) => continue,
            };
            if !v.is_finite() {
                return Some(Defect::NonFinite(p, v));
            }
            if !range_ok && out_of_range.is_none() {
                out_of_range = Some(Defect::OutOfRange(p, v, range));
            }
        }
        out_of_range.or(Some(Defect::ZeroQuaternion))
    }

    fn finish(mut self) -> (Gaussians, [usize; 5], Vec<String>) {
        if self.layout.has_normals {
            self.g.normals = Some(self.normals);
        }
        (
            self.g,
            [
                self.dropped_non_finite,
                self.dropped_out_of_range,
                self.dropped_zero_quaternion,
                self.kept_invalid,
                self.kept_non_finite_position,
            ],
            self.examples,
        )
    }
}

/// The per-Gaussian checks of the module docs on one Gaussian's core values.
#[inline]
fn core_valid(
    pos: &[f32; 3],
    nrm: &[f32; 3],
    dc: &[f32; 3],
    rest: &[f32],
    opacity: f32,
    scale: &[f32; 3],
    rot: &[f32; 4],
) -> bool {
    let lim = SCENE_COORD_LIMIT as f32;
    let (lo, hi) = LOG_SCALE_RANGE;
    pos.iter().all(|v| v.abs() <= lim)
        && nrm.iter().all(|v| v.is_finite())
        && dc.iter().all(|v| v.abs() <= MAX_ABS_SH)
        && rest.iter().all(|v| v.abs() <= MAX_ABS_SH)
        && opacity.is_finite()
        && scale.iter().all(|v| (lo..=hi).contains(v))
        && rot.iter().all(|v| v.is_finite())
        && rot.iter().any(|&r| r != 0.0)
}

/// Makes every invalid Gaussian ([`is_valid`] false) undrawable, in place: its opacity becomes
/// NaN, which the renderer skips. Returns how many. The pipeline's renderer input.
pub fn hide_invalid(g: &mut Gaussians) -> usize {
    let bad: Vec<usize> = (0..g.len()).filter(|&i| !is_valid(g, i)).collect();
    for &i in &bad {
        g.opacity[i] = f32::NAN;
    }
    bad.len()
}

/// Whether Gaussian `i` of `g` passes the per-Gaussian checks of the module docs (false only
/// for Gaussians kept by [`InvalidPolicy::Keep`], or built in memory).
pub fn is_valid(g: &Gaussians, i: usize) -> bool {
    let rest = g.rest_per_gaussian();
    let nrm = g.normals.as_ref().map_or([0.0; 3], |n| n[i]);
    core_valid(
        &g.positions[i],
        &nrm,
        &g.f_dc[i],
        &g.f_rest[i * rest..(i + 1) * rest],
        g.opacity[i],
        &g.scale[i],
        &g.rotation[i],
    )
}

/// The number of Gaussians a splat file declares (a PLY's `vertex` rows from its checked
/// header alone, 0 without a `vertex` element; a `.splat` file's size / 32; an SPZ header's
/// count): the payload is not read.
pub fn read_count(path: &Path) -> Result<usize, PlyError> {
    use super::formats::{self, SplatFormat};
    let io = |err| FsError::Read {
        path: path.into(),
        err,
    };
    let mut head = [0u8; 4];
    let n = std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read(&mut f, &mut head))
        .map_err(io)?;
    match formats::detect(path, &head[..n]) {
        SplatFormat::Splat => {
            let len = std::fs::metadata(path).map_err(io)?.len();
            formats::splat_count(path, len)
        }
        SplatFormat::Spz => {
            let bytes = ply::read_file(path)?;
            crate::spz::read_count(&bytes).map_err(|e| PlyError::Decode {
                path: path.into(),
                why: e.to_string(),
            })
        }
        SplatFormat::Ply | SplatFormat::CompressedPly => {
            let (header, _) = ply::read_header(path)?;
            Ok(header
                .element("vertex")
                .map_or(0, |e| header.elements[e].count))
        }
    }
}

/// Reads a splat file: an INRIA 3DGS PLY, or a compressed PLY, `.splat` or `.spz` file into
/// the same Gaussians ([`super::formats`]; the report's `format` says which).
pub fn read_ply(path: &Path, options: &ReadOptions) -> Result<(Gaussians, PlyReport), PlyError> {
    let bytes = ply::read_file(path)?;
    read_ply_bytes(path, &bytes, options)
}

/// [`read_ply`] from memory; `path` names the file in errors (and its extension tells a
/// `.splat` file, which has no magic).
pub fn read_ply_bytes(
    path: &Path,
    bytes: &[u8],
    options: &ReadOptions,
) -> Result<(Gaussians, PlyReport), PlyError> {
    use super::formats::{self, SplatFormat};
    match formats::detect(path, bytes) {
        SplatFormat::Splat => return formats::read_splat(path, bytes, options),
        SplatFormat::Spz => return formats::read_spz(path, bytes, options),
        SplatFormat::Ply | SplatFormat::CompressedPly => {}
    }
    let mut reader = Reader::new(path, bytes)?;
    if super::compressed::is_compressed(reader.header()) {
        return super::compressed::read(path, reader, options);
    }
    reader.set_generic(options.force_general_path);
    let header = reader.header();
    let vertex = header
        .element("vertex")
        .ok_or_else(|| PlyError::NoVertex { path: path.into() })?;
    let def = header.elements[vertex].clone();
    let encoding = header.encoding;
    let layout = layout(path, &def)?;
    let fast = reader.fast_path(vertex);
    // The header check bounds `count` by the payload size, so this capacity is backed by data.
    let mut asm = Assembler::new(path, &layout, options.invalid, def.count);
    reader.read_element("vertex", |row| asm.row(row))?;
    reader.finish()?;
    let (g, counts, examples) = asm.finish();
    let report = PlyReport::new(encoding, def.count, g.sh_degree, counts, examples, fast);
    Ok((g, report))
}

impl PlyReport {
    /// The report of `vertices` read (the assembler's counts: dropped non-finite, out of
    /// range, zero quaternion, kept invalid, kept with a non-finite position), of an INRIA PLY.
    fn new(
        encoding: PlyEncoding,
        vertices: usize,
        sh_degree: u8,
        counts: [usize; 5],
        invalid_examples: Vec<String>,
        fast_path: bool,
    ) -> PlyReport {
        let [
            dropped_non_finite,
            dropped_out_of_range,
            dropped_zero_quaternion,
            kept_invalid,
            kept_non_finite_position,
        ] = counts;
        PlyReport {
            encoding,
            vertices,
            sh_degree,
            dropped_non_finite,
            dropped_out_of_range,
            dropped_zero_quaternion,
            kept_invalid,
            kept_non_finite_position,
            invalid_examples,
            fast_path,
            format: super::formats::SplatFormat::Ply,
        }
    }
}

/// Gaussians of another splat format, checked as a PLY's are: `values(i, row)` fills the
/// INRIA values of record `i` (`x y z f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3`), and
/// each record passes the per-Gaussian checks of the module docs under `options.invalid`;
/// errors name the file and the record (as its vertex).
pub(super) fn assemble(
    path: &Path,
    format: super::formats::SplatFormat,
    sh_degree: u8,
    count: usize,
    options: &ReadOptions,
    mut values: impl FnMut(usize, &mut Vec<f64>),
) -> Result<(Gaussians, PlyReport), PlyError> {
    let rest = super::REST_COUNTS[usize::from(sh_degree.min(3))];
    let mut names: Vec<String> = ["x", "y", "z"].map(String::from).to_vec();
    names.extend((0..3).map(|i| format!("f_dc_{i}")));
    names.extend((0..rest).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    let def = ElementDef {
        name: "vertex".into(),
        count,
        properties: names
            .into_iter()
            .map(|n| PropertyDef::scalar(n, ScalarKind::F32))
            .collect(),
    };
    let layout = layout(path, &def)?;
    let mut asm = Assembler::new(path, &layout, options.invalid, count);
    let mut row = Vec::with_capacity(def.properties.len());
    for i in 0..count {
        row.clear();
        values(i, &mut row);
        debug_assert_eq!(row.len(), def.properties.len());
        asm.values(i, None, &row)?;
    }
    let (g, counts, examples) = asm.finish();
    let report = PlyReport {
        format,
        ..PlyReport::new(
            PlyEncoding::BinaryLittleEndian,
            count,
            sh_degree,
            counts,
            examples,
            false,
        )
    };
    Ok((g, report))
}

/// The property names and kinds written for `g`, in INRIA order, extras last.
fn written_properties(g: &Gaussians) -> Vec<PropertyDef> {
    let f = |s: String| PropertyDef::scalar(s, ScalarKind::F32);
    let mut props: Vec<PropertyDef> = ["x", "y", "z"].map(|s| f(s.into())).to_vec();
    if g.normals.is_some() {
        props.extend(["nx", "ny", "nz"].map(|s| f(s.into())));
    }
    props.extend((0..3).map(|i| f(format!("f_dc_{i}"))));
    props.extend((0..g.rest_per_gaussian()).map(|i| f(format!("f_rest_{i}"))));
    props.push(f("opacity".into()));
    props.extend((0..3).map(|i| f(format!("scale_{i}"))));
    props.extend((0..4).map(|i| f(format!("rot_{i}"))));
    props.extend(
        g.extras
            .iter()
            .map(|e| PropertyDef::scalar(e.name.clone(), e.kind)),
    );
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

/// Writes `g` as a 3DGS PLY (atomically), INRIA property order, extras after `rot_3`.
pub fn write_ply(path: &Path, g: &Gaussians, encoding: PlyEncoding) -> Result<(), PlyError> {
    g.check().map_err(|e| PlyError::Invalid {
        path: path.into(),
        why: e.to_string(),
    })?;
    let props = written_properties(g);
    let kinds: Vec<ScalarKind> = props
        .iter()
        .map(|p| match p.kind {
            PropertyKind::Scalar(k) => k,
            PropertyKind::List { .. } => unreachable!("3DGS properties are scalars"),
        })
        .collect();
    let element = ElementDef {
        name: "vertex".into(),
        count: g.len(),
        properties: props,
    };
    let werr = |err| FsError::Write {
        path: path.into(),
        err,
    };
    fsutil::atomic_write(path, |w| -> Result<(), PlyError> {
        let mut out = RowWriter::new(encoding, &[], std::slice::from_ref(&element));
        let mut row = Vec::new();
        for i in 0..g.len() {
            row_values(g, i, &mut row);
            for (&v, &kind) in row.iter().zip(&kinds) {
                out.scalar(kind, v);
            }
            out.end_row();
            if out.len() > 1 << 16 {
                out.drain_to(w).map_err(werr)?;
            }
        }
        out.drain_to(w).map_err(werr)?;
        w.flush().map_err(werr)?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn tmp(name: &str) -> PathBuf {
        let dir =
            crate::fsutil::test_temp_dir().join(format!("gs4city-ply-{}", std::process::id()));
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
            for mixed in [true, false] {
                let mut g = sample(37, degree, u64::from(degree));
                if !mixed {
                    // Only `float` properties: binary little-endian takes the fast path.
                    g.extras.retain(|e| e.kind == ScalarKind::F32);
                }
                for enc in [
                    PlyEncoding::BinaryLittleEndian,
                    PlyEncoding::BinaryBigEndian,
                    PlyEncoding::Ascii,
                ] {
                    let p = tmp(&format!("rt{degree}{mixed}{enc:?}.ply"));
                    write_ply(&p, &g, enc).unwrap();
                    for force_general_path in [false, true] {
                        let opts = ReadOptions {
                            force_general_path,
                            ..Default::default()
                        };
                        let (back, report) = read_ply(&p, &opts).unwrap();
                        assert_eq!(report.sh_degree, degree);
                        assert_eq!(report.encoding, enc);
                        assert_eq!(
                            report.fast_path,
                            enc == PlyEncoding::BinaryLittleEndian && !force_general_path && !mixed
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
                    PlyError::Format(ply::PlyError::Truncated {
                        row: 9,
                        count: 10,
                        ..
                    })
                ),
                "{e}"
            );
            assert!(e.to_string().contains("vertex 9 of 10"), "{e}");
        }
        // ASCII: 3 rows declared, 2 given. Too few bytes for 3 rows: refused from the header.
        let rows = vec![good_row(), good_row()];
        let p = ascii_file("trunc_ascii.ply", &CORE, &rows, 3);
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(
            matches!(e, PlyError::Format(ply::PlyError::Size { .. })),
            "{e}"
        );
        assert!(e.to_string().contains("3 `vertex` rows"), "{e}");
        // Enough bytes (blank lines) but only 2 rows: the reader names row 2 and its line.
        let mut text = std::fs::read_to_string(&p).unwrap();
        text.push_str(&"\n".repeat(60));
        std::fs::write(&p, text).unwrap();
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(
            matches!(e, PlyError::Format(ply::PlyError::Truncated { row: 2, .. })),
            "{e}"
        );
        let mut short = good_row();
        short.pop();
        let p = ascii_file("short_ascii.ply", &CORE, &[good_row(), short], 2);
        let e = read_ply(&p, &ReadOptions::default()).unwrap_err();
        assert!(
            matches!(e, PlyError::Format(ply::PlyError::Row { row: 1, .. })),
            "{e}"
        );
        // Header: ply, format, element, 14 properties, end_header = 18 lines; row 1 is line 20.
        assert!(
            e.to_string()
                .ends_with("short_ascii.ply: vertex 1 (line 20): no value for `rot_3`"),
            "{e}"
        );
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
        assert!(
            matches!(e, PlyError::Format(ply::PlyError::Truncated { row: 1, .. })),
            "{e}"
        );
    }

    #[test]
    fn garbage_and_list_properties_are_errors_not_panics() {
        let p = tmp("garbage.ply");
        std::fs::write(&p, b"not a ply at all").unwrap();
        assert!(matches!(
            read_ply(&p, &ReadOptions::default()),
            Err(PlyError::Format(ply::PlyError::Header { .. }))
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
            Err(PlyError::Format(ply::PlyError::Truncated { row: 0, .. }))
        ));
        let e = read_ply(&tmp("nope.ply"), &ReadOptions::default()).unwrap_err();
        assert!(matches!(e, PlyError::Format(ply::PlyError::Io { .. })));
        // The OS reason appears once.
        let mut msg = e.to_string();
        let mut src = std::error::Error::source(&e);
        while let Some(s) = src {
            msg.push_str(&format!(": {s}"));
            src = s.source();
        }
        assert_eq!(msg.matches("os error 2").count(), 1, "{msg}");
    }
}
