//! The run store: one folder per stage under the run folder `R`, and `R/run.json` recording, per
//! completed stage, its fingerprint (program version, options, the identities of the scene files
//! it read, the outputs of the upstream stages it read) and the size and digest of every file it
//! wrote.
//!
//! * A stage runs in `R/.<stage>.partial/`; only when it has finished is that folder renamed to
//!   `R/<stage>/` (an older `R/<stage>/` is first moved aside to `R/.<stage>.old/` and removed
//!   after), and only then is `run.json` rewritten (atomically). A crash therefore leaves either
//!   the old complete folder with its old record, or no folder: never half old, half new.
//!   Leftover `.partial`/`.old` folders are removed when the store is opened.
//! * A stage is resumed only when its record's fingerprint equals the new one **and** every
//!   recorded output still exists with the recorded size and content ([`check_outputs`]): a
//!   file is read back and its digest recomputed unless both its modification time and its
//!   inode change time are the recorded ones. The kernel moves the inode change time on every
//!   write and on every change of the modification time, and no system call sets it back, so a
//!   file changed in place with its size and modification time restored is read back and found.
//!   An output that is not what the stage wrote is one warning naming it, and the stage reruns,
//!   with a new run id; downstream fingerprints include the run ids of their upstream stages,
//!   so everything that depends on a rerun stage reruns too.
//! * The caller holds the run folder's exclusive lock (`crate::lock`) while the store is open:
//!   two processes never write one run folder.
//! * Scene inputs are identified by path, size and an xxh3-64 content digest (recomputed only
//!   when size, modification time or inode change time differ from the last record), so
//!   touching a file does not force work but changing it does.
use std::path::{Path, PathBuf};
use std::time::{Instant, UNIX_EPOCH};

use rayon::prelude::*;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::fsutil::{self, FsError, mtime_ns};
use crate::layout::Stage;
pub use crate::layout::{FileId, RunRecord, StageRecord, check_outputs, digest_file};

fn digest(path: &Path) -> Result<String, StoreError> {
    digest_file(path).map_err(|err| StoreError::Io {
        path: path.to_path_buf(),
        err,
    })
}

/// Errors of the run store.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{path}: {err}")]
    Io { path: PathBuf, err: std::io::Error },
    #[error(transparent)]
    Fs(#[from] FsError),
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |err| StoreError::Io {
        path: path.to_path_buf(),
        err,
    }
}

/// What happened to one stage in this invocation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageReport {
    pub stage: Stage,
    /// `true`: its complete output was reused.
    pub resumed: bool,
    /// Time spent now (near zero when resumed).
    pub seconds: f64,
    /// Time of the run that made the output.
    pub compute_seconds: f64,
    pub out: PathBuf,
}

/// The identity of `path` (`shown` is the path recorded); the digest of `previous` is reused
/// when size, modification time and inode change time are unchanged ([`FileId::unchanged`]).
fn file_id(path: &Path, shown: String, previous: Option<&FileId>) -> Result<FileId, StoreError> {
    let m = std::fs::metadata(path).map_err(io(path))?;
    let digest = match previous {
        Some(p) if p.unchanged(&m) => p.digest.clone(),
        _ => digest(path)?,
    };
    Ok(FileId {
        path: shown,
        size: m.len(),
        mtime_ns: mtime_ns(&m),
        ctime_ns: fsutil::ctime_ns(&m),
        digest,
    })
}

/// Every regular file under `dir`, relative and sorted (symbolic links are not followed).
fn list_files(dir: &Path) -> Result<Vec<PathBuf>, StoreError> {
    let mut out = Vec::new();
    let mut stack = vec![PathBuf::new()];
    while let Some(rel) = stack.pop() {
        let here = dir.join(&rel);
        for e in std::fs::read_dir(&here).map_err(io(&here))? {
            let e = e.map_err(io(&here))?;
            let t = e.file_type().map_err(io(&here))?;
            let r = rel.join(e.file_name());
            if t.is_dir() {
                stack.push(r);
            } else if t.is_file() {
                out.push(r);
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The run folder and its record.
pub struct Store {
    root: PathBuf,
    record: RunRecord,
    force: bool,
    pub reports: Vec<StageReport>,
}

impl Store {
    /// Opens (or starts) the run folder `root`: reads `run.json` where it exists and removes
    /// what an interrupted stage left (`.<stage>.partial`, `.<stage>.old`).
    pub fn open(
        root: &Path,
        scene: &Path,
        options: serde_json::Value,
        force: bool,
    ) -> Result<Store, StoreError> {
        fsutil::create_dir(root)?;
        for e in std::fs::read_dir(root).map_err(io(root))? {
            let e = e.map_err(io(root))?;
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') && (name.ends_with(".partial") || name.ends_with(".old")) {
                let p = e.path();
                log::debug!("removing what an interrupted stage left: {}", p.display());
                std::fs::remove_dir_all(&p).map_err(io(&p))?;
            }
        }
        let previous: Option<RunRecord> = fsutil::read_json(&root.join("run.json")).ok();
        let stages = previous.map(|r| r.stages).unwrap_or_default();
        Ok(Store {
            root: root.to_path_buf(),
            record: RunRecord {
                program: "gs4city".into(),
                version: env!("CARGO_PKG_VERSION").into(),
                scene: scene.to_path_buf(),
                options,
                stages,
            },
            force,
            reports: Vec::new(),
        })
    }

    /// The folder of `stage`.
    pub fn dir(&self, stage: Stage) -> PathBuf {
        stage.path(&self.root)
    }

    /// The record of a stage that ran or was resumed in this run.
    pub fn record(&self, stage: Stage) -> Option<&StageRecord> {
        self.record.stages.get(stage.dir())
    }

    /// The fingerprint of a stage: program version, stage name, options, input identities and
    /// the run ids of the upstream stages.
    fn fingerprint(
        &self,
        stage: Stage,
        options: &serde_json::Value,
        inputs: &[FileId],
        upstream: &[Stage],
    ) -> String {
        let mut s = format!(
            "{} {}\n{stage}\n{options}\n",
            self.record.program, self.record.version
        );
        for f in inputs {
            s.push_str(&format!("in {} {} {}\n", f.path, f.size, f.digest));
        }
        for u in upstream {
            let id = self
                .record
                .stages
                .get(u.dir())
                .map_or("missing", |r| r.run_id.as_str());
            s.push_str(&format!("upstream {u} {id}\n"));
        }
        fsutil::digest_hex(xxhash_rust::xxh3::xxh3_64(s.as_bytes()))
    }

    /// Runs `stage` (or resumes it, see the module docs). `inputs` are the scene files it reads,
    /// `upstream` the stages whose folders it reads; `body` writes into the folder it is given
    /// and returns the stage's typed summary, which is also its `summary.json` (read back when
    /// resuming).
    pub fn stage<T, E, F>(
        &mut self,
        stage: Stage,
        options: &impl Serialize,
        inputs: &[PathBuf],
        upstream: &[Stage],
        body: F,
    ) -> Result<T, E>
    where
        T: Serialize + DeserializeOwned,
        E: From<StoreError>,
        F: FnOnce(&Path) -> Result<T, E>,
    {
        let t0 = Instant::now();
        let options = serde_json::to_value(options).unwrap_or(serde_json::Value::Null);
        let old = self.record.stages.get(stage.dir()).cloned();
        let ids = inputs
            .par_iter()
            .map(|p| {
                let shown = p.display().to_string();
                let prev = old
                    .as_ref()
                    .and_then(|r| r.inputs.iter().find(|f| f.path == shown));
                file_id(p, shown, prev)
            })
            .collect::<Result<Vec<_>, _>>()?;
        let fp = self.fingerprint(stage, &options, &ids, upstream);
        let dir = self.dir(stage);
        if !self.force
            && let Some(r) = &old
            && r.fingerprint == fp
        {
            // Same inputs and options: resumed when its outputs are what it wrote.
            let checked = check_outputs(&dir, &r.outputs).and_then(|refreshed| {
                let summary =
                    fsutil::read_json::<T>(&dir.join("summary.json")).map_err(|e| e.to_string())?;
                Ok((summary, refreshed))
            });
            match checked {
                Ok((summary, refreshed)) => {
                    // Files read back whose content matched (copied, linked, their mode
                    // changed): their new times go into the record, so that the next resume
                    // need not read them again.
                    if !refreshed.is_empty()
                        && let Some(rec) = self.record.stages.get_mut(stage.dir())
                    {
                        for (i, id) in refreshed {
                            rec.outputs[i] = id;
                        }
                        self.save().map_err(E::from)?;
                    }
                    log::info!(
                        "{stage}: complete and unchanged, resumed ({})",
                        dir.display()
                    );
                    self.reports.push(StageReport {
                        stage,
                        resumed: true,
                        seconds: t0.elapsed().as_secs_f64(),
                        compute_seconds: r.seconds,
                        out: dir,
                    });
                    return Ok(summary);
                }
                Err(why) => log::warn!("{stage}: {why}; the stage runs again"),
            }
        }
        // Run into a fresh partial folder.
        let partial = self.root.join(format!(".{stage}.partial"));
        if partial.exists() {
            std::fs::remove_dir_all(&partial).map_err(|e| E::from(io(&partial)(e)))?;
        }
        fsutil::create_dir(&partial).map_err(StoreError::from)?;
        let summary = body(&partial)?;
        let summary_path = partial.join("summary.json");
        if !summary_path.is_file() {
            fsutil::write_json(&summary_path, &summary).map_err(StoreError::from)?;
        }
        // The digests computed while the files were written (`fsutil::written`: unchanged
        // since); the others are read back, in parallel (a render cache is gigabytes). The
        // order stays the listing's.
        let outputs = list_files(&partial)?
            .par_iter()
            .map(|rel| {
                let path = partial.join(rel);
                let shown = rel.display().to_string();
                match fsutil::written(&path) {
                    Some(w) => Ok(FileId {
                        path: shown,
                        size: w.size,
                        mtime_ns: w.mtime_ns,
                        ctime_ns: w.ctime_ns,
                        digest: w.digest,
                    }),
                    None => file_id(&path, shown, None),
                }
            })
            .collect::<Result<Vec<_>, _>>()?;
        // Swap it into place.
        let aside = self.root.join(format!(".{stage}.old"));
        if dir.exists() {
            std::fs::rename(&dir, &aside).map_err(|e| E::from(io(&dir)(e)))?;
        }
        std::fs::rename(&partial, &dir).map_err(|e| E::from(io(&dir)(e)))?;
        if aside.exists() {
            std::fs::remove_dir_all(&aside).map_err(|e| E::from(io(&aside)(e)))?;
        }
        // Outputs moved with the folder: their mtimes are unchanged by a rename.
        let seconds = t0.elapsed().as_secs_f64();
        self.record.stages.insert(
            stage.to_string(),
            StageRecord {
                fingerprint: fp,
                run_id: format!(
                    "{:x}-{:x}",
                    std::time::SystemTime::now()
                        .duration_since(UNIX_EPOCH)
                        .map_or(0, |d| d.as_nanos()),
                    std::process::id()
                ),
                options,
                inputs: ids,
                upstream: upstream.iter().map(|s| s.dir().to_string()).collect(),
                outputs,
                seconds,
            },
        );
        self.save().map_err(E::from)?;
        self.reports.push(StageReport {
            stage,
            resumed: false,
            seconds,
            compute_seconds: seconds,
            out: dir,
        });
        Ok(summary)
    }

    /// Removes a stage this run does not use (its folder and its record), so that nothing
    /// downstream — `gs4city query`, a later resume — mistakes it for part of the run.
    pub fn discard(&mut self, stage: Stage) -> Result<(), StoreError> {
        let dir = self.dir(stage);
        if dir.exists() {
            std::fs::remove_dir_all(&dir).map_err(io(&dir))?;
        }
        if self.record.stages.remove(stage.dir()).is_some() {
            self.save()?;
        }
        Ok(())
    }

    /// Writes `run.json` atomically.
    pub fn save(&self) -> Result<(), StoreError> {
        fsutil::write_json(&self.root.join("run.json"), &self.record)?;
        Ok(())
    }
}

/// Refuses a run folder equal to or inside the scene folder (checked before anything is
/// written; `out` need not exist), or one that would put a stage folder onto the scene.
pub fn check_out_dir(scene: &Path, out: &Path, stages: &[Stage]) -> Result<(), String> {
    let scene_c = scene
        .canonicalize()
        .map_err(|e| format!("scene {}: {e}", scene.display()))?;
    // Canonicalise the deepest existing ancestor of `out`, then append the rest.
    let abs = if out.is_absolute() {
        out.to_path_buf()
    } else {
        std::env::current_dir()
            .map_err(|e| format!("current directory: {e}"))?
            .join(out)
    };
    let mut existing = abs.clone();
    let mut rest = Vec::new();
    while !existing.exists() {
        match (existing.file_name(), existing.parent()) {
            (Some(n), Some(p)) => {
                rest.push(n.to_os_string());
                existing = p.to_path_buf();
            }
            _ => break,
        }
    }
    let mut out_c = existing.canonicalize().unwrap_or(existing);
    for n in rest.iter().rev() {
        if n == ".." {
            out_c.pop();
        } else if n != "." {
            out_c.push(n);
        }
    }
    if out_c.starts_with(&scene_c) {
        return Err(format!(
            "--out {} is {} the scene folder {}: a run never writes into its scene; choose a folder outside it",
            out.display(),
            if out_c == scene_c {
                "equal to"
            } else {
                "inside"
            },
            scene.display()
        ));
    }
    if let Ok(rel) = scene_c.strip_prefix(&out_c)
        && let Some(first) = rel.components().next()
        && stages.iter().any(|s| first.as_os_str() == s.dir())
    {
        return Err(format!(
            "--out {}: the scene {} sits where the run's `{}` stage folder would go",
            out.display(),
            scene.display(),
            first.as_os_str().to_string_lossy()
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        let d = crate::fsutil::test_temp_dir()
            .join(format!("gs4city-store-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[derive(Debug, thiserror::Error)]
    enum E {
        #[error(transparent)]
        S(#[from] StoreError),
        #[error("boom")]
        Boom,
    }

    #[derive(Serialize, Deserialize, PartialEq, Debug)]
    struct Sum {
        n: u32,
    }

    /// A stage that writes `a.txt` = the input's content + options; counts its executions.
    fn stage_a(store: &mut Store, input: &Path, opt: u32, runs: &mut u32) -> Sum {
        store
            .stage::<Sum, E, _>(Stage::Citymodel, &opt, &[input.to_path_buf()], &[], |dir| {
                *runs += 1;
                let text = std::fs::read_to_string(input).unwrap();
                std::fs::write(dir.join("a.txt"), format!("{text}{opt}")).unwrap();
                Ok(Sum { n: opt })
            })
            .unwrap()
    }

    fn stage_b(store: &mut Store, runs: &mut u32) -> Sum {
        let a = store.dir(Stage::Citymodel);
        store
            .stage::<Sum, E, _>(Stage::Raycast, &0, &[], &[Stage::Citymodel], |dir| {
                *runs += 1;
                let t = std::fs::read_to_string(a.join("a.txt")).unwrap();
                std::fs::write(dir.join("b.txt"), t.to_uppercase()).unwrap();
                Ok(Sum { n: t.len() as u32 })
            })
            .unwrap()
    }

    #[test]
    fn resume_rerun_on_change_deletion_and_truncation() {
        let d = tmp("resume");
        let input = d.join("in.txt");
        std::fs::write(&input, "hello").unwrap();
        let root = d.join("run");
        let (mut ra, mut rb) = (0, 0);
        let go = |opt: u32, ra: &mut u32, rb: &mut u32| {
            let mut s = Store::open(&root, &d, serde_json::json!({}), false).unwrap();
            let a = stage_a(&mut s, &input, opt, ra);
            let b = stage_b(&mut s, rb);
            (a, b)
        };
        assert_eq!(go(1, &mut ra, &mut rb), (Sum { n: 1 }, Sum { n: 6 }));
        assert_eq!((ra, rb), (1, 1));
        go(1, &mut ra, &mut rb);
        assert_eq!((ra, rb), (1, 1), "nothing changed: both resumed");
        go(2, &mut ra, &mut rb);
        assert_eq!((ra, rb), (2, 2), "an option of a: a and b rerun");
        std::fs::remove_file(root.join("raycast/b.txt")).unwrap();
        go(2, &mut ra, &mut rb);
        assert_eq!((ra, rb), (2, 3), "an output of b deleted: only b reruns");
        let f = std::fs::OpenOptions::new()
            .write(true)
            .open(root.join("citymodel/a.txt"))
            .unwrap();
        f.set_len(2).unwrap();
        drop(f);
        go(2, &mut ra, &mut rb);
        assert_eq!((ra, rb), (3, 4), "an output of a truncated: a and b rerun");
        assert_eq!(
            std::fs::read_to_string(root.join("raycast/b.txt")).unwrap(),
            "HELLO2"
        );
        std::fs::write(&input, "HELLO").unwrap();
        go(2, &mut ra, &mut rb);
        assert_eq!((ra, rb), (4, 5), "input content changed");
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn a_change_with_size_and_mtime_restored_is_found_and_a_chmod_is_not_a_change() {
        let d = tmp("content");
        let input = d.join("in.txt");
        std::fs::write(&input, "hello").unwrap();
        let root = d.join("run");
        let (mut ra, mut rb) = (0, 0);
        let go = |ra: &mut u32, rb: &mut u32| {
            let mut s = Store::open(&root, &d, serde_json::json!({}), false).unwrap();
            stage_a(&mut s, &input, 1, ra);
            stage_b(&mut s, rb);
        };
        go(&mut ra, &mut rb);
        // One byte of a's output changed, its size and modification time put back (a moment
        // later: the kernel's clock for file times advances in steps of a few ms).
        std::thread::sleep(std::time::Duration::from_millis(20));
        let a = root.join("citymodel/a.txt");
        let m = std::fs::metadata(&a).unwrap();
        std::fs::write(&a, "jello1").unwrap();
        std::fs::File::options()
            .write(true)
            .open(&a)
            .unwrap()
            .set_modified(m.modified().unwrap())
            .unwrap();
        let m2 = std::fs::metadata(&a).unwrap();
        assert_eq!(
            (m2.len(), m2.modified().unwrap()),
            (m.len(), m.modified().unwrap())
        );
        go(&mut ra, &mut rb);
        assert_eq!((ra, rb), (2, 2), "a reran, and b after it");
        assert_eq!(std::fs::read_to_string(&a).unwrap(), "hello1");
        // The mode set again (the inode change time moves, the content does not): resumed, and
        // the record takes the new times, so the next resume reads nothing back.
        use std::os::unix::fs::PermissionsExt;
        std::thread::sleep(std::time::Duration::from_millis(20));
        std::fs::set_permissions(&a, std::fs::Permissions::from_mode(0o644)).unwrap();
        let ctime = crate::fsutil::ctime_ns(&std::fs::metadata(&a).unwrap());
        go(&mut ra, &mut rb);
        assert_eq!((ra, rb), (2, 2), "nothing reran");
        let rec: RunRecord = crate::fsutil::read_json(&root.join("run.json")).unwrap();
        let id = &rec.stages["citymodel"].outputs[0];
        assert_eq!((id.path.as_str(), id.ctime_ns), ("a.txt", ctime));
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn recorded_digests_match_the_files_however_they_were_written() {
        let d = tmp("digests");
        let root = d.join("run");
        let mut s = Store::open(&root, &d, serde_json::json!({}), false).unwrap();
        s.stage::<Sum, E, _>(Stage::Render, &0, &[], &[], |dir| {
            // Digested while written (fsutil), written plainly, and written through fsutil
            // then changed in place (its digest must be read back, not the one from writing).
            crate::fsutil::write_bytes(&dir.join("a.bin"), &[7u8; 3000]).unwrap();
            std::fs::write(dir.join("b.bin"), b"plain").unwrap();
            crate::fsutil::write_bytes(&dir.join("c.bin"), b"before").unwrap();
            std::fs::write(dir.join("c.bin"), b"after, longer").unwrap();
            Ok(Sum { n: 0 })
        })
        .unwrap();
        let rec = s.record(Stage::Render).unwrap();
        let names: Vec<&str> = rec.outputs.iter().map(|o| o.path.as_str()).collect();
        assert_eq!(names, ["a.bin", "b.bin", "c.bin", "summary.json"]);
        for o in &rec.outputs {
            let bytes = std::fs::read(root.join("render").join(&o.path)).unwrap();
            let want = format!("{:016x}", xxhash_rust::xxh3::xxh3_64(&bytes));
            assert_eq!(o.digest, want, "{}", o.path);
            assert_eq!(o.size, bytes.len() as u64, "{}", o.path);
        }
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn a_failed_stage_leaves_the_old_output_and_no_partial_folder() {
        let d = tmp("fail");
        let input = d.join("in.txt");
        std::fs::write(&input, "x").unwrap();
        let root = d.join("run");
        let mut runs = 0;
        {
            let mut s = Store::open(&root, &d, serde_json::json!({}), false).unwrap();
            stage_a(&mut s, &input, 1, &mut runs);
        }
        let mut s = Store::open(&root, &d, serde_json::json!({}), true).unwrap();
        let r: Result<Sum, E> = s.stage(
            Stage::Citymodel,
            &1,
            std::slice::from_ref(&input),
            &[],
            |dir| {
                std::fs::write(dir.join("a.txt"), "half").unwrap();
                Err(E::Boom)
            },
        );
        assert!(r.is_err());
        assert_eq!(
            std::fs::read_to_string(root.join("citymodel/a.txt")).unwrap(),
            "x1"
        );
        // The partial folder of the failed attempt is removed when the store is next opened.
        assert!(root.join(".citymodel.partial").exists());
        Store::open(&root, &d, serde_json::json!({}), false).unwrap();
        assert!(!root.join(".citymodel.partial").exists());
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn out_dir_inside_or_equal_to_the_scene_is_refused() {
        let d = tmp("outdir");
        let scene = d.join("scene");
        std::fs::create_dir_all(&scene).unwrap();
        let stages = [Stage::Citymodel, Stage::Raycast];
        assert!(check_out_dir(&scene, &scene, &stages).is_err());
        assert!(check_out_dir(&scene, &scene.join("run/x"), &stages).is_err());
        assert!(check_out_dir(&scene, &scene.join("../scene/./r"), &stages).is_err());
        assert!(check_out_dir(&scene, &d.join("run"), &stages).is_ok());
        let nested = d.join("citymodel");
        std::fs::create_dir_all(&nested).unwrap();
        assert!(check_out_dir(&nested, &d, &stages).is_err());
        let _ = std::fs::remove_dir_all(&d);
    }
}
