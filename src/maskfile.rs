//! The masks stage's files (`docs/design.md`, "Run folder"): per view the kept masks
//! `<stem>.json` (SAM format plus the [`Rule`] that kept each mask and its prompt class) and the
//! decisions on every input mask `<stem>.decisions.json`. A format: it imports no stage.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::fsutil::{self, FsError};
use crate::sam::{self, SamError, SamMask};

/// Errors of reading or writing the masks files.
#[derive(Debug, thiserror::Error)]
pub enum MaskFileError {
    #[error(transparent)]
    Sam(#[from] SamError),
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
}

/// Path of view `stem`'s kept masks in a masks folder.
pub fn kept_file(dir: &Path, stem: &str) -> PathBuf {
    dir.join(format!("{stem}.json"))
}

/// Path of view `stem`'s decisions in a masks folder.
pub fn decisions_file(dir: &Path, stem: &str) -> PathBuf {
    dir.join(format!("{stem}.decisions.json"))
}

/// Why a mask was kept or dropped (the `rule` of a kept mask or a decision; serialised by
/// its snake_case name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Rule {
    /// Dropped: `predicted_iou < τ_q`.
    Quality,
    /// Dropped, support-only: `support_floor ≤ predicted_iou < τ_q`, every other rule would keep it.
    LowQualitySupport,
    /// Dropped: area below `τ_a`.
    Area,
    /// Kept: `R_ov < ρ` (a non-building candidate, the paper's rule).
    LowOverlap,
    /// Dropped: `R_ov < ρ`, but the low-overlap check found it is building.
    LowOverlapBuilding,
    /// Kept: `S_fore > S_city + δ`.
    FeaturesForeground,
    /// Dropped: `S_fore ≤ S_city + δ`.
    FeaturesBuilding,
    /// Kept: enough of the mask is in front of the city surface.
    Occluder,
    /// Kept by the combined test: both the features and the depth say foreground.
    OccluderAndFeatures,
    /// Dropped: the 3DGS lies on (or behind) the city surface.
    OnSurface,
    /// Dropped: too few pixels with depth evidence to call it an occluder.
    NoDepth,
    /// Dropped: high overlap and no evidence to disambiguate (test `overlap`).
    HighOverlap,
    /// Kept: a component of the mask-free source.
    DepthComponent,
}

impl Rule {
    /// The name written in the files.
    pub fn name(self) -> &'static str {
        match self {
            Rule::Quality => "quality",
            Rule::LowQualitySupport => "low_quality_support",
            Rule::Area => "area",
            Rule::LowOverlap => "low_overlap",
            Rule::LowOverlapBuilding => "low_overlap_building",
            Rule::FeaturesForeground => "features_foreground",
            Rule::FeaturesBuilding => "features_building",
            Rule::Occluder => "occluder",
            Rule::OccluderAndFeatures => "occluder_and_features",
            Rule::OnSurface => "on_surface",
            Rule::NoDepth => "no_depth",
            Rule::HighOverlap => "high_overlap",
            Rule::DepthComponent => "depth_component",
        }
    }

    /// Whether a mask with this rule is kept.
    pub fn keeps(self) -> bool {
        matches!(
            self,
            Rule::LowOverlap
                | Rule::FeaturesForeground
                | Rule::Occluder
                | Rule::OccluderAndFeatures
                | Rule::DepthComponent
        )
    }
}

impl std::fmt::Display for Rule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
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
    pub rule: Rule,
    /// Best prompt class id, −1 without features/prompts.
    pub class: i32,
}

/// The decision on one input mask.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Decision {
    pub source_index: i64,
    pub kept: bool,
    pub rule: Rule,
    pub r_ov: f64,
    /// Scores the rule used (e.g. `s_city`, `s_fore`, `occluder_share`), by name.
    pub scores: std::collections::BTreeMap<String, f64>,
}

/// Reads a view's kept masks (`<stem>.json` of a masks folder), validating every mask's RLE,
/// size and area as [`sam::read_sam_json`] does.
pub fn read_kept(path: &Path) -> Result<Vec<KeptMask>, MaskFileError> {
    let bytes = std::fs::read(path).map_err(|err| SamError::Read {
        path: path.to_path_buf(),
        err,
    })?;
    sam::parse_sam_json(path, &bytes, None)?;
    let masks: Vec<KeptMask> = serde_json::from_slice(&bytes).map_err(|err| FsError::Parse {
        path: path.to_path_buf(),
        err,
    })?;
    Ok(masks)
}

/// Writes a view's kept masks (compact JSON), atomically.
pub fn write_kept(path: &Path, masks: &[KeptMask]) -> Result<(), MaskFileError> {
    let mut text = serde_json::to_vec(masks).map_err(|e| MaskFileError::Invalid {
        path: path.to_path_buf(),
        why: format!("cannot serialise: {e}"),
    })?;
    text.push(b'\n');
    fsutil::write_bytes(path, &text)?;
    Ok(())
}

/// Reads a view's decisions (`<stem>.decisions.json`).
pub fn read_decisions(path: &Path) -> Result<Vec<Decision>, MaskFileError> {
    Ok(fsutil::read_json(path)?)
}
