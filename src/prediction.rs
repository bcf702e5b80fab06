//! The per-Gaussian result files of `lift` and `train` (`docs/design.md`, "Run folder"):
//! `gaussians.npy` (int32 N×2: label, class), `semantic.ply` (the input PLY plus the label, the
//! class, the city hierarchy and extra float properties) and the test-view prediction maps
//! (`<stem>.class.npy`, `<stem>.instance.npy`, `<stem>.class.png`). A format: it imports no
//! stage.
use std::path::{Path, PathBuf};

use crate::labels::LabelTable;
use crate::semantics::Entity;
use crate::{classes, idmap, npy};

/// Errors of writing the result files.
#[derive(Debug, thiserror::Error)]
pub enum PredictionError {
    #[error(transparent)]
    Npy(#[from] npy::NpyError),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Image(#[from] crate::imageio::ImageError),
    #[error("{path}: {why}")]
    Labels { path: PathBuf, why: String },
}

/// Writes the test-view predictions `<stem>.class.npy`, `<stem>.instance.npy` (int32 H×W: class
/// and label per pixel) and `<stem>.class.png` into `out` from per-pixel maps made by [`crate::cache::predict`].
pub fn write_prediction(
    out: &Path,
    stem: &str,
    width: usize,
    height: usize,
    class_map: &[i32],
    label_map: &[i32],
) -> Result<(), PredictionError> {
    npy::write(&idmap::class_file(out, stem), &[height, width], class_map)?;
    npy::write(
        &idmap::instance_file(out, stem),
        &[height, width],
        label_map,
    )?;
    let img = ndarray::Array3::from_shape_fn((height, width, 3), |(y, x, c)| {
        classes::color(class_map[y * width + x])[c]
    });
    crate::imageio::write_png(&out.join(format!("{stem}.class.png")), &img)?;
    Ok(())
}

/// Per-Gaussian results written by `lift` and `train`.
pub struct GaussianLabels<'a> {
    /// Fused label id per Gaussian (−1 none).
    pub label: &'a [i32],
    /// Class id per Gaussian (−1 none).
    pub class: &'a [i32],
    /// Extra per-Gaussian float properties for `semantic.ply` (e.g. `label_confidence`,
    /// `obj_dc_0..15`).
    pub extra: Vec<(String, Vec<f32>)>,
}

/// Writes `gaussians.npy` (int32 N×2: label, class) and `semantic.ply` (the input PLY plus
/// `label`, `class`, the city hierarchy `feature_id surface_id part_id` of city labels, and the
/// extra float properties). Every Gaussian of the input PLY is kept, in input order; an invalid
/// one ([`crate::splat::ply::is_valid`], kept by [`crate::splat::InvalidPolicy::Keep`] and
/// never drawn) is labelled −1. Returns the number of invalid Gaussians.
pub fn write_gaussians(
    ply: &Path,
    out: &Path,
    g: &GaussianLabels<'_>,
    labels: &LabelTable,
    entities: &[Entity],
) -> Result<usize, PredictionError> {
    let (mut gaussians, report) = crate::splat::read_ply(ply, &crate::splat::ReadOptions::KEEP)?;
    let n = gaussians.len();
    if g.label.len() != n || g.class.len() != n {
        return Err(PredictionError::Labels {
            path: ply.to_path_buf(),
            why: format!(
                "{n} Gaussians in the PLY, {} labels: the PLY changed since the cache was built",
                g.label.len()
            ),
        });
    }
    let (mut label, mut class) = (g.label.to_vec(), g.class.to_vec());
    if report.kept_invalid > 0 {
        for i in (0..n).filter(|&i| !crate::splat::ply::is_valid(&gaussians, i)) {
            (label[i], class[i]) = (-1, -1);
        }
    }
    let chain = crate::semantics::chains(entities);
    let hier = |l: i32| -> crate::mesh::FaceLabel {
        labels
            .get(l)
            .and_then(|x| x.entity)
            .and_then(|e| chain.get(e as usize).copied())
            .unwrap_or(crate::mesh::FaceLabel::NONE)
    };
    let int_prop = |name: &str, f: &dyn Fn(usize) -> i32| crate::splat::ExtraProperty {
        name: name.to_string(),
        kind: crate::splat::ScalarKind::I32,
        values: (0..n).map(|i| f64::from(f(i))).collect(),
    };
    let mut props = vec![
        int_prop("label", &|i| label[i]),
        int_prop("class", &|i| class[i]),
        int_prop("feature_id", &|i| hier(label[i]).feature),
        int_prop("surface_id", &|i| hier(label[i]).surface),
        int_prop("part_id", &|i| hier(label[i]).part),
    ];
    for (name, values) in &g.extra {
        props.push(crate::splat::ExtraProperty {
            name: name.clone(),
            kind: crate::splat::ScalarKind::F32,
            values: values.iter().map(|&v| f64::from(v)).collect(),
        });
    }
    gaussians
        .extras
        .retain(|e| !props.iter().any(|p| p.name == e.name));
    gaussians.extras.extend(props);
    crate::splat::write_ply(
        &out.join("semantic.ply"),
        &gaussians,
        crate::splat::PlyEncoding::BinaryLittleEndian,
    )?;
    let table: Vec<i32> = (0..n).flat_map(|i| [label[i], class[i]]).collect();
    crate::npy::write(&out.join("gaussians.npy"), &[n, 2], &table)?;
    Ok(report.kept_invalid)
}
