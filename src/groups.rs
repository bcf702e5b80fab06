//! The associate stage's files (`docs/design.md`, "Run folder"): `groups.json` ([`GroupsFile`]:
//! one record per cross-view group) and `features.npy` (float32 G×D, the unit mean feature of
//! each group); the per-view group maps `<stem>.ids.npy` are id maps ([`crate::idmap`]). A
//! format: it imports no stage.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::fsutil::{self, FsError};
use crate::npy::{self, NpyError};

/// Errors of reading the associate files.
#[derive(Debug, thiserror::Error)]
pub enum GroupsError {
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
}

/// One group in `groups.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroupRecord {
    pub id: i32,
    /// Stems of the views it was seen in (kept masks).
    pub views: Vec<String>,
    /// Stems of further views where a mask dropped for quality or area only matches it (the
    /// view support, `AssociateOptions::support`).
    #[serde(default)]
    pub support_views: Vec<String>,
    /// Masks assigned to it.
    pub masks: usize,
    /// Pixels it covers, over all views.
    pub pixels: u64,
    /// Gaussians it owns.
    pub gaussians: usize,
    /// Prompt class (pixel-weighted vote of its masks' classes), −1 unknown.
    pub class: i32,
    /// Centroid of its candidate Gaussians, weighted by their mass in the masks (scene frame).
    pub centroid: [f64; 3],
    /// Distance from the centroid to the nearest camera centre (scene units).
    pub nearest_camera_distance: f64,
}

/// `groups.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroupsFile {
    /// Feature dimension of `features.npy`, none without features.
    pub feature_dim: Option<usize>,
    pub groups: Vec<GroupRecord>,
}

impl GroupsFile {
    /// Reads `dir/groups.json`.
    pub fn read(dir: &Path) -> Result<GroupsFile, GroupsError> {
        Ok(fsutil::read_json(&dir.join("groups.json"))?)
    }

    /// The group features (`features.npy`, G×D, row i ↔ group i), when the file says they exist.
    pub fn features(&self, dir: &Path) -> Result<Option<Vec<f32>>, GroupsError> {
        let Some(d) = self.feature_dim else {
            return Ok(None);
        };
        let path = dir.join("features.npy");
        let (shape, data) = npy::read::<f32>(&path)?;
        if shape != [self.groups.len(), d] {
            return Err(GroupsError::Invalid {
                path,
                why: format!(
                    "shape {shape:?}, groups.json lists {} groups of dimension {d}",
                    self.groups.len()
                ),
            });
        }
        Ok(Some(data))
    }
}
