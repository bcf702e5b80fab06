//! `extract.ply` (the selected Gaussians) and `remove.ply` (the rest): the input 3DGS PLY split
//! in two, so any 3DGS viewer opens both and together they hold every input Gaussian exactly once.
//!
//! A binary little-endian input whose `vertex` element comes first and holds scalars only (every
//! INRIA file) is split **byte for byte**: both outputs keep the input's header (vertex count
//! changed, elements after `vertex` dropped) and copy the selected vertex records unchanged, in
//! input order. Any other input (ASCII, big endian) goes through the typed reader and writer
//! ([`crate::splat`]): INRIA property order, binary little endian, every property kept.
use std::path::Path;

use ply_rs::parser::Parser;
use ply_rs::ply::{DefaultElement, Encoding, PropertyType, ScalarType};

use crate::fsutil;
use crate::splat::{self, ExtraProperty, Gaussians, PlyEncoding, PlyError};

/// The Gaussians `i` with `keep[i] == want`, in input order, every field copied.
pub fn subset(g: &Gaussians, keep: &[bool], want: bool) -> Gaussians {
    let idx: Vec<usize> = (0..g.len()).filter(|&i| keep[i] == want).collect();
    let rest = g.rest_per_gaussian();
    let pick = |v: &Vec<[f32; 3]>| idx.iter().map(|&i| v[i]).collect::<Vec<_>>();
    Gaussians {
        positions: pick(&g.positions),
        normals: g.normals.as_ref().map(pick),
        sh_degree: g.sh_degree,
        f_dc: pick(&g.f_dc),
        f_rest: idx
            .iter()
            .flat_map(|&i| g.f_rest[i * rest..(i + 1) * rest].iter().copied())
            .collect(),
        opacity: idx.iter().map(|&i| g.opacity[i]).collect(),
        scale: pick(&g.scale),
        rotation: idx.iter().map(|&i| g.rotation[i]).collect(),
        extras: g
            .extras
            .iter()
            .map(|e| ExtraProperty {
                name: e.name.clone(),
                kind: e.kind,
                values: idx.iter().map(|&i| e.values[i]).collect(),
            })
            .collect(),
    }
}

/// Counts of an export.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ExportCounts {
    pub extracted: usize,
    pub removed: usize,
}

fn scalar_size(t: &ScalarType) -> usize {
    match t {
        ScalarType::Char | ScalarType::UChar => 1,
        ScalarType::Short | ScalarType::UShort => 2,
        ScalarType::Int | ScalarType::UInt | ScalarType::Float => 4,
        ScalarType::Double => 8,
    }
}

fn count_mismatch(ply: &Path, found: usize, expected: usize) -> super::QueryError {
    super::QueryError::Inputs(format!(
        "{} holds {found} Gaussians, the run's labels have {expected}: the PLY is not the one the run was made from",
        ply.display()
    ))
}

/// The byte-level split of the module docs: `Some([extract, remove])` file contents, or `None`
/// when the file's layout needs the typed path.
pub fn split_bytes(
    path: &Path,
    bytes: &[u8],
    keep: &[bool],
) -> Result<Option<[Vec<u8>; 2]>, super::QueryError> {
    let mut cursor: &[u8] = bytes;
    let header = Parser::<DefaultElement>::new()
        .read_header(&mut cursor)
        .map_err(|e| PlyError::Header {
            path: path.into(),
            why: e.to_string(),
        })?;
    let header_len = bytes.len() - cursor.len();
    let Some((first, def)) = header.elements.iter().next() else {
        return Err(PlyError::NoVertex { path: path.into() }.into());
    };
    if header.encoding != Encoding::BinaryLittleEndian || first != "vertex" {
        return Ok(None);
    }
    let mut stride = 0;
    for p in def.properties.values() {
        match &p.data_type {
            PropertyType::Scalar(t) => stride += scalar_size(t),
            PropertyType::List(..) => return Ok(None),
        }
    }
    if def.count != keep.len() {
        return Err(count_mismatch(path, def.count, keep.len()));
    }
    if stride == 0 || cursor.len() < def.count * stride {
        return Err(PlyError::Truncated {
            path: path.into(),
            vertex: cursor.len() / stride.max(1),
            count: def.count,
        }
        .into());
    }
    // The header text with the vertex count replaced and later elements dropped.
    let text = String::from_utf8_lossy(&bytes[..header_len]);
    let head = |n: usize| -> Vec<u8> {
        let mut out = String::new();
        let mut dropped = false;
        for line in text.split_inclusive('\n') {
            let words: Vec<&str> = line.split_whitespace().collect();
            match words.first().copied() {
                Some("element") if words.get(1) == Some(&"vertex") => {
                    dropped = false;
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
    };
    let n_keep = keep.iter().filter(|&&k| k).count();
    let mut files = [head(n_keep), head(keep.len() - n_keep)];
    files[0].reserve(n_keep * stride);
    files[1].reserve((keep.len() - n_keep) * stride);
    for (i, rec) in cursor[..def.count * stride]
        .chunks_exact(stride)
        .enumerate()
    {
        files[usize::from(!keep[i])].extend_from_slice(rec);
    }
    Ok(Some(files))
}

/// Reads `ply`, checks it has one Gaussian per entry of `selected`, and writes
/// `out/extract.ply` and `out/remove.ply` (module docs).
pub fn export(
    ply: &Path,
    selected: &[bool],
    out: &Path,
) -> Result<ExportCounts, super::QueryError> {
    let bytes = std::fs::read(ply).map_err(|source| PlyError::Io {
        path: ply.into(),
        source,
    })?;
    if let Some([a, b]) = split_bytes(ply, &bytes, selected)? {
        let (ra, rb) = rayon::join(
            || fsutil::write_bytes(&out.join("extract.ply"), &a),
            || fsutil::write_bytes(&out.join("remove.ply"), &b),
        );
        ra?;
        rb?;
        let extracted = selected.iter().filter(|&&s| s).count();
        return Ok(ExportCounts {
            extracted,
            removed: selected.len() - extracted,
        });
    }
    let (g, _) = splat::ply::read_ply_bytes(ply, &bytes, &Default::default())?;
    if g.len() != selected.len() {
        return Err(count_mismatch(ply, g.len(), selected.len()));
    }
    let (a, b) = (subset(&g, selected, true), subset(&g, selected, false));
    let (ra, rb) = rayon::join(
        || {
            splat::write_ply(
                &out.join("extract.ply"),
                &a,
                PlyEncoding::BinaryLittleEndian,
            )
        },
        || splat::write_ply(&out.join("remove.ply"), &b, PlyEncoding::BinaryLittleEndian),
    );
    ra?;
    rb?;
    Ok(ExportCounts {
        extracted: a.len(),
        removed: b.len(),
    })
}
