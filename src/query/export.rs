//! `extract.ply` (the selected Gaussians) and `remove.ply` (the rest): the input 3DGS PLY split
//! in two, in the INRIA layout (every property of the input kept, extras included, in input
//! order), so any 3DGS viewer opens both and together they hold every input Gaussian exactly once.
use std::path::Path;

use crate::splat::{self, ExtraProperty, Gaussians, PlyEncoding};

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

/// Reads `ply`, checks it has one Gaussian per entry of `selected`, and writes
/// `out/extract.ply` and `out/remove.ply` (binary little endian).
pub fn export(
    ply: &Path,
    selected: &[bool],
    out: &Path,
) -> Result<ExportCounts, super::QueryError> {
    let (g, _) = splat::read_ply(ply, &Default::default())?;
    if g.len() != selected.len() {
        return Err(super::QueryError::Inputs(format!(
            "{} holds {} Gaussians, the run's labels have {}: the PLY is not the one the run was made from",
            ply.display(),
            g.len(),
            selected.len()
        )));
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
