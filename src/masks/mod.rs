//! The `masks` stage (paper §3.2, foundation-mask filtering): per view, the scene's SAM masks are
//! cleaned against the city model so that what remains is what the city model does not know
//! (trees, cars, people, foreground objects in front of façades).
//!
//! Output files (DESIGN.md, "Wave 2 contract"): per view `<stem>.json` = the kept masks in SAM
//! format, each with the extra keys `source_index`, `r_ov`, `rule`, `class` ([`KeptMask`]);
//! `<stem>.decisions.json` = one [`Decision`] per input mask; `summary.json`.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::fsutil::{self, FsError};
use crate::sam::SamMask;

/// Errors of the masks stage.
#[derive(Debug, thiserror::Error)]
pub enum MasksError {
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error(transparent)]
    Sam(#[from] crate::sam::SamError),
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// One kept mask: a SAM mask plus why it was kept.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeptMask {
    #[serde(flatten)]
    pub sam: SamMask,
    /// Index in the scene's SAM list of the view; −1 for a mask derived without a foundation
    /// model (the model-free source).
    pub source_index: i64,
    /// Building-support overlap `|s ∩ Ω_feat| / |s|`.
    pub r_ov: f64,
    /// Why it was kept (the rule's name).
    pub rule: String,
    /// Best prompt class id, −1 without features/prompts.
    pub class: i32,
}

/// The decision on one input mask.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Decision {
    pub source_index: i64,
    pub kept: bool,
    pub rule: String,
    pub r_ov: f64,
    /// Scores the rule used (e.g. `s_city`, `s_fore`, `occluder_share`), by name.
    pub scores: std::collections::BTreeMap<String, f64>,
}

/// Reads a view's kept masks (`<stem>.json` of a masks folder).
pub fn read_kept(path: &Path) -> Result<Vec<KeptMask>, MasksError> {
    let masks: Vec<KeptMask> = fsutil::read_json(path)?;
    Ok(masks)
}

/// Writes a view's kept masks (compact JSON), atomically.
pub fn write_kept(path: &Path, masks: &[KeptMask]) -> Result<(), MasksError> {
    let mut text = serde_json::to_vec(masks).map_err(|e| MasksError::Invalid {
        path: path.to_path_buf(),
        why: format!("cannot serialise: {e}"),
    })?;
    text.push(b'\n');
    fsutil::write_bytes(path, &text)?;
    Ok(())
}
