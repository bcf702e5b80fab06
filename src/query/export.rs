//! `extract.ply` (the selected Gaussians) and `remove.ply` (the rest): the input 3DGS PLY split
//! in two, so any 3DGS viewer opens both and together they hold every input Gaussian exactly once.
//! Every record gains the run's per-Gaussian semantics as `int` columns ([`COLUMNS`]: `label`,
//! `class` and the city hierarchy `feature_id surface_id part_id`, as in `semantic.ply`).
//!
//! A binary little-endian input whose `vertex` element comes first and holds scalars only (every
//! INRIA file), exported without colour or frame change, is split **byte for byte**: both outputs
//! keep the input's header (vertex count changed, the five columns added, elements after
//! `vertex` dropped) and copy the selected vertex records unchanged, in input order, each followed
//! by its five columns. Any other input or option goes through the typed reader and writer
//! ([`crate::splat`]): INRIA property order, binary little endian, every property kept.
//!
//! The viewer-ready options ([`ExportOptions`]): `color_by` paints every Gaussian in its class
//! or building colour (the DC term set to the colour, higher SH bands zeroed, so SuperSplat and
//! other viewers show the semantics from every side); `up` moves the Gaussians from the scene
//! frame into the run's georeferenced frame minus its origin (CityGML is Z-up; `y` turns it
//! Y-up as glTF and most viewers expect: `(x, y, z) ↦ (x, z, −y)`), SH bands turned with them;
//! `split_by` writes the selected Gaussians once more, one file per class or per building.
use std::path::Path;

use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};

use crate::alignment::Alignment;
use crate::fsutil;
use crate::ply::{self, Encoding, Header};
use crate::splat::transform::{self, Motion};
use crate::splat::{self, ExtraProperty, Gaussians, PlyEncoding, ScalarKind};

/// The semantic columns every exported record carries, in this order.
pub const COLUMNS: [&str; 5] = ["label", "class", "feature_id", "surface_id", "part_id"];

/// The run's semantics per Gaussian (−1 where none), in input order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Columns {
    /// `label`, `class`, `feature_id`, `surface_id`, `part_id` ([`COLUMNS`]).
    pub values: [Vec<i32>; 5],
    /// The building (the root entity id of the hierarchy) per Gaussian.
    pub building: Vec<i32>,
    /// The gml:id of each entity id (file names of the per-building split).
    pub gml_ids: Vec<String>,
}

/// What colour the exported Gaussians show.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ColorBy {
    /// The input's colours.
    #[default]
    Rgb,
    /// The class palette (`classes::color`; unlabelled black).
    Class,
    /// One colour per building (`classes::building_color`; outside buildings grey).
    Building,
}

impl std::fmt::Display for ColorBy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ColorBy::Rgb => "rgb",
            ColorBy::Class => "class",
            ColorBy::Building => "building",
        })
    }
}

impl std::str::FromStr for ColorBy {
    type Err = String;
    fn from_str(s: &str) -> Result<ColorBy, String> {
        match s {
            "rgb" => Ok(ColorBy::Rgb),
            "class" => Ok(ColorBy::Class),
            "building" => Ok(ColorBy::Building),
            _ => Err(format!("{s:?} is not one of rgb, class, building")),
        }
    }
}

/// The up axis of an export in the georeferenced frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum UpAxis {
    /// `(east, up, −north)`: glTF, SuperSplat, three.js.
    Y,
    /// `(east, north, up)` as the CityGML CRS.
    Z,
}

impl std::str::FromStr for UpAxis {
    type Err = String;
    fn from_str(s: &str) -> Result<UpAxis, String> {
        match s {
            "y" | "Y" => Ok(UpAxis::Y),
            "z" | "Z" => Ok(UpAxis::Z),
            _ => Err(format!("{s:?} is not one of y, z")),
        }
    }
}

/// How the per-group batch export groups the selected Gaussians.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SplitBy {
    /// `split/class_<name>.ply` per evaluation class (`class_none.ply`: unlabelled).
    Class,
    /// `split/building_<entity id>_<gml:id>.ply` per building (`building_none.ply`: outside).
    Building,
}

impl std::str::FromStr for SplitBy {
    type Err = String;
    fn from_str(s: &str) -> Result<SplitBy, String> {
        match s {
            "class" => Ok(SplitBy::Class),
            "building" => Ok(SplitBy::Building),
            _ => Err(format!("{s:?} is not one of class, building")),
        }
    }
}

/// The viewer-ready options of an export (module docs).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ExportOptions {
    pub color_by: ColorBy,
    pub up: Option<UpAxis>,
    pub split_by: Option<SplitBy>,
}

/// One file of the per-group batch export.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SplitFile {
    /// The file name under `split/`.
    pub file: String,
    /// The class name, or the building's gml:id (`none`: no class / outside buildings).
    pub group: String,
    pub gaussians: usize,
}

/// The motion from the scene frame into the georeferenced frame minus its origin, with `up`
/// up: `p_out = A·Rᵀ·(p − t)/s` (`A` the axis change of [`UpAxis`]), in f64.
pub fn frame_motion(a: &Alignment, up: UpAxis) -> Motion {
    let axes = match up {
        UpAxis::Z => DMat3::IDENTITY,
        UpAxis::Y => DMat3::from_cols(
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(0.0, 0.0, -1.0),
            DVec3::new(0.0, 1.0, 0.0),
        ),
    };
    let rotation = axes * a.rotation.transpose();
    Motion {
        scale: 1.0 / a.scale,
        rotation,
        translation: -(rotation * a.translation) / a.scale,
    }
}

/// Counts of an export.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ExportCounts {
    pub extracted: usize,
    pub removed: usize,
}

fn count_mismatch(ply: &Path, found: usize, expected: usize) -> super::QueryError {
    super::QueryError::Inputs(format!(
        "{} holds {found} Gaussians, the run's labels have {expected}: the PLY is not the one the run was made from",
        ply.display()
    ))
}

/// A binary little-endian PLY whose first element is a scalar-only `vertex`: the layout the
/// byte-level split of the module docs copies records from.
pub struct RawVertices<'a> {
    header: String,
    records: &'a [u8],
    stride: usize,
    count: usize,
}

impl<'a> RawVertices<'a> {
    /// The file's vertex records, or `None` when its layout needs the typed path (another
    /// encoding, another first element, list properties, or a column of [`COLUMNS`] already
    /// present).
    pub fn parse(
        path: &Path,
        bytes: &'a [u8],
    ) -> Result<Option<RawVertices<'a>>, super::QueryError> {
        let header = Header::parse(path, bytes).map_err(splat::PlyError::from)?;
        let Some(def) = header.elements.first() else {
            return Err(splat::PlyError::from(ply::PlyError::Layout {
                path: path.into(),
                why: "no element in the header (a 3DGS PLY starts with `element vertex`)".into(),
            })
            .into());
        };
        if header.encoding != Encoding::BinaryLittleEndian
            || def.name != "vertex"
            || def
                .properties
                .iter()
                .any(|p| COLUMNS.contains(&p.name.as_str()))
        {
            return Ok(None);
        }
        let Some(stride) = def.fixed_stride().filter(|&s| s > 0) else {
            return Ok(None);
        };
        let cursor = &bytes[header.len..];
        if cursor.len() < def.count * stride {
            return Err(splat::PlyError::from(ply::PlyError::Truncated {
                path: path.into(),
                element: "vertex".into(),
                row: cursor.len() / stride,
                count: def.count,
                line: None,
            })
            .into());
        }
        Ok(Some(RawVertices {
            header: String::from_utf8_lossy(&bytes[..header.len]).into_owned(),
            records: &cursor[..def.count * stride],
            stride,
            count: def.count,
        }))
    }

    /// Number of vertex records.
    pub fn len(&self) -> usize {
        self.count
    }

    /// Whether the file holds no vertex.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The header with the vertex count `n`, the [`COLUMNS`] appended to `vertex` when `cols`,
    /// and later elements dropped.
    fn head(&self, n: usize, cols: bool) -> Vec<u8> {
        let mut out = String::new();
        let (mut dropped, mut in_vertex) = (false, false);
        let extra: String = if cols {
            COLUMNS
                .iter()
                .map(|c| format!("property int {c}\n"))
                .collect()
        } else {
            String::new()
        };
        for line in self.header.split_inclusive('\n') {
            let words: Vec<&str> = line.split_whitespace().collect();
            match words.first().copied() {
                Some("element") | Some("end_header") if in_vertex => {
                    out.push_str(&extra);
                    in_vertex = false;
                }
                _ => {}
            }
            match words.first().copied() {
                Some("element") if words.get(1) == Some(&"vertex") => {
                    dropped = false;
                    in_vertex = true;
                    out.push_str(&format!("element vertex {n}\n"));
                    continue;
                }
                Some("element") => dropped = true,
                Some("end_header") => dropped = false,
                _ => {}
            }
            if !dropped {
                out.push_str(line);
            }
        }
        out.into_bytes()
    }

    /// The file of the records `i` with `keep(i)`, in input order, each followed by its
    /// [`COLUMNS`] (little-endian `int32`) when `cols` is given.
    pub fn subset(&self, cols: Option<&Columns>, keep: impl Fn(usize) -> bool) -> Vec<u8> {
        let n = (0..self.count).filter(|&i| keep(i)).count();
        let width = self.stride + if cols.is_some() { 4 * COLUMNS.len() } else { 0 };
        let mut out = self.head(n, cols.is_some());
        out.reserve(n * width);
        for (i, rec) in self.records.chunks_exact(self.stride).enumerate() {
            if keep(i) {
                out.extend_from_slice(rec);
                if let Some(c) = cols {
                    for v in &c.values {
                        out.extend_from_slice(&v[i].to_le_bytes());
                    }
                }
            }
        }
        out
    }
}

/// The byte-level split of the module docs, without the semantic columns: `Some([extract,
/// remove])` file contents, or `None` when the file's layout needs the typed path.
pub fn split_bytes(
    path: &Path,
    bytes: &[u8],
    keep: &[bool],
) -> Result<Option<[Vec<u8>; 2]>, super::QueryError> {
    let Some(raw) = RawVertices::parse(path, bytes)? else {
        return Ok(None);
    };
    if raw.len() != keep.len() {
        return Err(count_mismatch(path, raw.len(), keep.len()));
    }
    Ok(Some([
        raw.subset(None, |i| keep[i]),
        raw.subset(None, |i| !keep[i]),
    ]))
}

/// The Gaussians `i` with `keep[i] == want`, in input order, every field copied.
pub fn subset(g: &Gaussians, keep: &[bool], want: bool) -> Gaussians {
    subset_where(g, |i| keep[i] == want)
}

fn subset_where(g: &Gaussians, keep: impl Fn(usize) -> bool) -> Gaussians {
    let idx: Vec<usize> = (0..g.len()).filter(|&i| keep(i)).collect();
    g.select(&idx)
}

/// The input's Gaussians, either as raw records or decoded and prepared (columns set, colour
/// and frame applied).
enum Source<'a> {
    Raw(RawVertices<'a>),
    Typed(Gaussians),
}

impl Source<'_> {
    fn write(
        &self,
        path: &Path,
        cols: &Columns,
        keep: impl Fn(usize) -> bool,
    ) -> Result<usize, super::QueryError> {
        match self {
            Source::Raw(raw) => {
                let n = (0..raw.len()).filter(|&i| keep(i)).count();
                fsutil::write_bytes(path, &raw.subset(Some(cols), keep))?;
                Ok(n)
            }
            Source::Typed(g) => {
                let s = subset_where(g, keep);
                splat::write_ply(path, &s, PlyEncoding::BinaryLittleEndian)?;
                Ok(s.len())
            }
        }
    }
}

/// Keeps only the characters of a file name that every file system accepts.
fn file_safe(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Reads `ply`, checks it has one Gaussian per entry of `selected` and of `cols`, and writes
/// `out/extract.ply` and `out/remove.ply` (module docs), and with `opts.split_by` the files
/// `out/split/…` and `out/split/split.json`. `frame`: the motion of `opts.up` (from
/// [`frame_motion`]); required when `opts.up` is set.
pub fn export(
    ply: &Path,
    cols: &Columns,
    selected: &[bool],
    opts: &ExportOptions,
    frame: Option<&Motion>,
    out: &Path,
) -> Result<(ExportCounts, Vec<SplitFile>), super::QueryError> {
    let bytes = ply::read_file(ply).map_err(splat::PlyError::from)?;
    if cols.values.iter().any(|v| v.len() != selected.len())
        || cols.building.len() != selected.len()
    {
        return Err(super::QueryError::Inputs(format!(
            "{} labels but {} selection entries: the run's label files disagree",
            cols.values[0].len(),
            selected.len()
        )));
    }
    let plain = opts.color_by == ColorBy::Rgb && opts.up.is_none();
    let raw = if plain {
        RawVertices::parse(ply, &bytes)?
    } else {
        None
    };
    let src = match raw {
        Some(raw) => {
            if raw.len() != selected.len() {
                return Err(count_mismatch(ply, raw.len(), selected.len()));
            }
            Source::Raw(raw)
        }
        None => {
            let (mut g, _) = splat::ply::read_ply_bytes(ply, &bytes, &splat::ReadOptions::KEEP)?;
            if g.len() != selected.len() {
                return Err(count_mismatch(ply, g.len(), selected.len()));
            }
            prepare(&mut g, cols, opts, frame)?;
            Source::Typed(g)
        }
    };
    let (ra, rb) = rayon::join(
        || src.write(&out.join("extract.ply"), cols, |i| selected[i]),
        || src.write(&out.join("remove.ply"), cols, |i| !selected[i]),
    );
    let counts = ExportCounts {
        extracted: ra?,
        removed: rb?,
    };
    let mut files = Vec::new();
    if let Some(by) = opts.split_by {
        let dir = out.join("split");
        let _ = std::fs::remove_dir_all(&dir);
        fsutil::create_dir(&dir)?;
        let key = |i: usize| match by {
            SplitBy::Class => cols.values[1][i],
            SplitBy::Building => cols.building[i],
        };
        let groups: std::collections::BTreeSet<i32> = (0..selected.len())
            .filter(|&i| selected[i])
            .map(key)
            .collect();
        for k in groups {
            let (file, group) = match by {
                SplitBy::Class => {
                    let name = crate::classes::name(k);
                    (format!("class_{name}.ply"), name.to_string())
                }
                SplitBy::Building if k < 0 => ("building_none.ply".to_string(), "none".to_string()),
                SplitBy::Building => {
                    let gml = cols.gml_ids.get(k as usize).cloned().unwrap_or_default();
                    (format!("building_{k}_{}.ply", file_safe(&gml)), gml)
                }
            };
            let n = src.write(&dir.join(&file), cols, |i| selected[i] && key(i) == k)?;
            files.push(SplitFile {
                file,
                group,
                gaussians: n,
            });
        }
        fsutil::write_json(&dir.join("split.json"), &files)?;
    }
    Ok((counts, files))
}

/// Sets the semantic columns of `g` and applies the colour and frame options.
fn prepare(
    g: &mut Gaussians,
    cols: &Columns,
    opts: &ExportOptions,
    frame: Option<&Motion>,
) -> Result<(), super::QueryError> {
    g.extras.retain(|e| !COLUMNS.contains(&e.name.as_str()));
    for (name, v) in COLUMNS.iter().zip(&cols.values) {
        g.extras.push(ExtraProperty {
            name: (*name).to_string(),
            kind: ScalarKind::I32,
            values: v.iter().map(|&x| f64::from(x)).collect(),
        });
    }
    match opts.color_by {
        ColorBy::Rgb => {}
        ColorBy::Class => {
            for i in 0..g.len() {
                transform::paint(g, i, crate::classes::color(cols.values[1][i]));
            }
        }
        ColorBy::Building => {
            for i in 0..g.len() {
                transform::paint(g, i, crate::classes::building_color(cols.building[i]));
            }
        }
    }
    if opts.up.is_some() {
        let Some(m) = frame else {
            return Err(super::QueryError::Inputs(
                "an export with an up axis needs the run's alignment".into(),
            ));
        };
        transform::apply(g, m);
    }
    Ok(())
}
