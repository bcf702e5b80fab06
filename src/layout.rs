//! The run-folder layout (`docs/design.md`, "Run folder"): the stage folders ([`Stage`]), the
//! per-Gaussian label modes ([`Mode`]) and the one `summary.json` reader and writer of every
//! stage ([`Summary`]). A format: it imports no stage. Which stage runs after which is known to
//! the orchestrator (`run`) alone.
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::fsutil::{self, FsError};

/// The file name of every stage's summary, written last as the completion marker.
pub const SUMMARY: &str = "summary.json";

/// A stage folder of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    Align,
    Citymodel,
    Raycast,
    Render,
    Masks,
    Openings,
    Associate,
    Fuse,
    Lift,
    Train,
    Eval,
}

impl Stage {
    /// Every stage folder a run can hold.
    pub const ALL: [Stage; 11] = [
        Stage::Align,
        Stage::Citymodel,
        Stage::Render,
        Stage::Raycast,
        Stage::Masks,
        Stage::Openings,
        Stage::Associate,
        Stage::Fuse,
        Stage::Lift,
        Stage::Train,
        Stage::Eval,
    ];

    /// The folder name (and the stage's name in `run.json` and in log lines).
    pub fn dir(self) -> &'static str {
        match self {
            Stage::Align => "align",
            Stage::Citymodel => "citymodel",
            Stage::Raycast => "raycast",
            Stage::Render => "render",
            Stage::Masks => "masks",
            Stage::Openings => "openings",
            Stage::Associate => "associate",
            Stage::Fuse => "fuse",
            Stage::Lift => "lift",
            Stage::Train => "train",
            Stage::Eval => "eval",
        }
    }

    /// The stage's folder in run folder `run`.
    pub fn path(self, run: &Path) -> PathBuf {
        run.join(self.dir())
    }
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.dir())
    }
}

/// The semantic table of run folder `run`: the openings stage's completed table when it added
/// openings (`openings/semantics.json`, docs/completeness.md), else the citymodel stage's.
pub fn semantics_file(run: &Path) -> PathBuf {
    let completed = Stage::Openings.path(run).join("semantics.json");
    if completed.is_file() {
        completed
    } else {
        Stage::Citymodel.path(run).join("semantics.json")
    }
}

/// Which per-Gaussian labels a run's queries and evaluation read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// The closed-form vote (`R/lift/gaussians.npy`).
    Vote,
    /// Identity learning (`R/train/gaussians.npy`).
    Learned,
}

impl std::str::FromStr for Mode {
    type Err = String;
    fn from_str(s: &str) -> Result<Mode, String> {
        match s {
            "vote" => Ok(Mode::Vote),
            "learned" => Ok(Mode::Learned),
            _ => Err(format!("{s:?} is not one of vote, learned")),
        }
    }
}

impl Mode {
    /// The mode's name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Mode::Vote => "vote",
            Mode::Learned => "learned",
        }
    }

    /// The stage whose folder holds this mode's `gaussians.npy` and test-view predictions.
    pub fn stage(self) -> Stage {
        match self {
            Mode::Vote => Stage::Lift,
            Mode::Learned => Stage::Train,
        }
    }

    /// The run subfolder that holds this mode's `gaussians.npy` and test-view predictions.
    pub fn dir(self) -> &'static str {
        self.stage().dir()
    }

    /// `learned` when the run has `train/gaussians.npy`, else `vote`.
    pub fn default_for(run: &Path) -> Mode {
        if run.join("train/gaussians.npy").is_file() {
            Mode::Learned
        } else {
            Mode::Vote
        }
    }
}

/// A stage's `summary.json`: one reader and one writer for all of them.
pub trait Summary: Serialize + DeserializeOwned {
    /// Reads `dir/summary.json`.
    fn read(dir: &Path) -> Result<Self, FsError> {
        fsutil::read_json(&dir.join(SUMMARY))
    }

    /// Writes `dir/summary.json` (atomically; call it last).
    fn write(&self, dir: &Path) -> Result<(), FsError> {
        fsutil::write_json(&dir.join(SUMMARY), self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stage_names_are_their_folders_and_modes_name_their_folders() {
        let dirs: std::collections::BTreeSet<&str> = Stage::ALL.iter().map(|s| s.dir()).collect();
        assert_eq!(dirs.len(), Stage::ALL.len(), "two stages share a folder");
        for s in Stage::ALL {
            // run.json names a stage by its folder.
            assert_eq!(
                serde_json::to_string(&s).unwrap(),
                format!("\"{}\"", s.dir())
            );
        }
        assert_eq!(Mode::Vote.dir(), "lift");
        assert_eq!(Mode::Learned.dir(), "train");
        assert_eq!("learned".parse::<Mode>(), Ok(Mode::Learned));
        assert!("votes".parse::<Mode>().is_err());
    }
}
