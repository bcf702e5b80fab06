//! The run-folder layout (`docs/design.md`, "Run folder"): the stage folders ([`Stage`]), the
//! per-Gaussian label modes ([`Mode`]), the one `summary.json` reader and writer of every
//! stage ([`Summary`]), and the run's record `run.json` ([`RunRecord`]: per stage the size and
//! xxh3-64 digest of every file it wrote, checked by [`check_outputs`]; written by the run
//! store, `run::store`). A format: it imports no stage. Which stage runs after which is known to
//! the orchestrator (`run`) alone.
use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::fsutil::{self, FsError};

/// The file name of every stage's summary, written last as the completion marker.
pub const SUMMARY: &str = "summary.json";

/// Identity of one file: size, modification and inode change times and content digest.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileId {
    /// Absolute for scene inputs; relative to the stage folder for outputs.
    pub path: String,
    pub size: u64,
    pub mtime_ns: u64,
    /// The inode change time (`fsutil::ctime_ns`); 0 where unknown (a record written before it
    /// was kept: the content is then always read back).
    #[serde(default)]
    pub ctime_ns: u64,
    /// xxh3-64 of the content, hex.
    pub digest: String,
}

impl FileId {
    /// Whether `m` has this identity's size and both its times: then the file has not been
    /// written since the digest was taken (the kernel moves the inode change time on every
    /// write, and on every change of the modification time).
    pub fn unchanged(&self, m: &std::fs::Metadata) -> bool {
        self.ctime_ns != 0
            && m.len() == self.size
            && fsutil::mtime_ns(m) == self.mtime_ns
            && fsutil::ctime_ns(m) == self.ctime_ns
    }
}

/// What `run.json` keeps of one completed stage.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StageRecord {
    pub fingerprint: String,
    /// Unique per execution: downstream fingerprints include it, so a stage that reruns makes
    /// every stage that reads it rerun too.
    pub run_id: String,
    pub options: serde_json::Value,
    pub inputs: Vec<FileId>,
    pub upstream: Vec<String>,
    pub outputs: Vec<FileId>,
    pub seconds: f64,
}

/// `run.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunRecord {
    pub program: String,
    pub version: String,
    pub scene: PathBuf,
    /// Every option of the run.
    pub options: serde_json::Value,
    pub stages: BTreeMap<String, StageRecord>,
}

/// xxh3-64 of a file's content, hex.
pub fn digest_file(path: &Path) -> std::io::Result<String> {
    let mut f = std::fs::File::open(path)?;
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(fsutil::digest_hex(h.digest()))
}

/// Whether the recorded outputs of the stage folder `dir` are what the stage wrote: every file
/// present, of the recorded size, and of the recorded content — read back and digested (in
/// parallel) unless its modification and inode change times are both still the recorded ones
/// ([`FileId::unchanged`]: then it has not been written since its digest was taken). `Ok`
/// gives the identities refreshed by a digest that matched (index into `outputs`, new times),
/// for the record; `Err` is one line naming the first file that is not what was written (in the
/// record's order) and how many others are not either.
pub fn check_outputs(dir: &Path, outputs: &[FileId]) -> Result<Vec<(usize, FileId)>, String> {
    let shown = |rel: &str| {
        let d = dir
            .file_name()
            .map_or(String::new(), |n| format!("{}/", n.to_string_lossy()));
        format!("{d}{rel}")
    };
    if !dir.is_dir() {
        return Err(format!("{} is missing", dir.display()));
    }
    let checked: Vec<Result<Option<(usize, FileId)>, String>> = outputs
        .par_iter()
        .enumerate()
        .map(|(i, o)| {
            let p = dir.join(&o.path);
            let why = match std::fs::metadata(&p) {
                Ok(m) if !m.is_file() => "is not a file".to_string(),
                Ok(m) if m.len() != o.size => {
                    format!("has {} bytes, {} when it was written", m.len(), o.size)
                }
                Ok(m) if o.unchanged(&m) => return Ok(None),
                Ok(m) => match digest_file(&p) {
                    Ok(d) if d == o.digest => {
                        return Ok(Some((
                            i,
                            FileId {
                                mtime_ns: fsutil::mtime_ns(&m),
                                ctime_ns: fsutil::ctime_ns(&m),
                                ..o.clone()
                            },
                        )));
                    }
                    Ok(d) => format!(
                        "has changed since it was written (xxh3 {d}, recorded {})",
                        o.digest
                    ),
                    Err(e) => format!("cannot be read: {e}"),
                },
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => "is missing".to_string(),
                Err(e) => format!("cannot be read: {e}"),
            };
            Err(format!("{} {why}", shown(&o.path)))
        })
        .collect();
    let problems: Vec<&String> = checked.iter().filter_map(|c| c.as_ref().err()).collect();
    match problems.split_first() {
        None => Ok(checked
            .into_iter()
            .filter_map(|c| c.ok().flatten())
            .collect()),
        Some((first, [])) => Err((*first).clone()),
        Some((first, rest)) => Err(format!(
            "{first} (and {} more of its {} files)",
            rest.len(),
            outputs.len()
        )),
    }
}

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
        f.pad(self.dir())
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
