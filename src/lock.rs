//! Advisory locks on the folders commands write: a run folder (`gs4city run`), a tile's folder
//! (`gs4city run-plan P --tile I`) and a merged run (`gs4city merge`). The lock is `flock(2)` on
//! the file [`LOCK_FILE`] inside the folder, held by an open file for the command's life: the
//! kernel releases it when the process ends, however it ends, so a killed command never leaves a
//! stale lock behind.
//!
//! * A command that writes takes the lock **exclusively** ([`FolderLock::exclusive`]) and writes
//!   who it is into the lock file (pid, command line, start time: [`Holder`]).
//! * A command that only reads a finished run (query, view, export, eval --by-query) takes it
//!   **shared** ([`FolderLock::shared`]): readers run side by side, and never beside a writer, so
//!   none of them sees a run between two stages.
//! * Neither waits: a folder that is locked the other way is refused at once with
//!   [`LockError::Busy`], one line naming the holder (the writer from the lock file; readers from
//!   `/proc/locks`). `gs4city` exits with [`EXIT_BUSY`] then.
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, Write};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use rustix::fs::{FlockOperation, flock};
use serde::{Deserialize, Serialize};

/// The lock file inside a locked folder.
pub const LOCK_FILE: &str = ".lock";

/// The exit status of a command refused because a folder it needs is locked (`EX_TEMPFAIL` of
/// BSD's `sysexits.h`: try again later). `run-plan` waits and retries a tile whose job exits so.
pub const EXIT_BUSY: u8 = 75;

/// Errors of taking a folder's lock.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    #[error("{folder} is in use by {holder}; wait for it to end (or stop it) and try again")]
    Busy { folder: PathBuf, holder: String },
    #[error("cannot lock {path}: {err}")]
    Io { path: PathBuf, err: std::io::Error },
}

impl LockError {
    /// Whether the folder is locked by another process (rather than the lock being impossible).
    pub fn is_busy(&self) -> bool {
        matches!(self, LockError::Busy { .. })
    }
}

/// What the holder of an exclusive lock writes into the lock file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Holder {
    pub pid: u32,
    /// This process's command line.
    pub command: String,
    /// When the lock was taken (seconds since the Unix epoch).
    pub started_unix: u64,
}

impl Holder {
    fn me() -> Holder {
        Holder {
            pid: std::process::id(),
            command: std::env::args_os()
                .map(|a| a.to_string_lossy().into_owned())
                .collect::<Vec<_>>()
                .join(" "),
            started_unix: now_unix(),
        }
    }

    /// `` `gs4city run …` (pid 1234, started 12 s ago) ``.
    pub fn describe(&self) -> String {
        let ago = now_unix().saturating_sub(self.started_unix);
        format!(
            "`{}` (pid {}, started {} ago)",
            self.command,
            self.pid,
            duration_words(ago)
        )
    }
}

fn now_unix() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// `12 s`, `5 min`, `3 h`, `2 days`.
fn duration_words(s: u64) -> String {
    match s {
        0..120 => format!("{s} s"),
        120..7200 => format!("{} min", s / 60),
        7200..172_800 => format!("{} h", s / 3600),
        _ => format!("{} days", s / 86_400),
    }
}

/// A held lock on a folder; released when dropped (or when the process ends). A folder that
/// [`FolderLock::exclusive`] created and that holds nothing but the lock file when the lock is
/// dropped is removed (a command refused before it wrote anything leaves no folder behind).
#[derive(Debug)]
pub struct FolderLock {
    file: File,
    path: PathBuf,
    created: Option<PathBuf>,
}

impl Drop for FolderLock {
    fn drop(&mut self) {
        let Some(folder) = &self.created else { return };
        let only_lock = std::fs::read_dir(folder).is_ok_and(|rd| {
            rd.flatten()
                .all(|e| e.file_name().to_str() == Some(LOCK_FILE))
        });
        if only_lock && self.path == folder.join(LOCK_FILE) {
            let _ = std::fs::remove_file(&self.path);
            let _ = std::fs::remove_dir(folder);
        }
    }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> LockError + '_ {
    move |err| LockError::Io {
        path: path.to_path_buf(),
        err,
    }
}

fn would_block(e: &rustix::io::Errno) -> bool {
    *e == rustix::io::Errno::WOULDBLOCK
}

impl FolderLock {
    /// Takes `folder`'s lock exclusively (creating the folder and its lock file where missing)
    /// and records this process as its holder; [`LockError::Busy`] when another process holds
    /// it either way.
    pub fn exclusive(folder: &Path) -> Result<FolderLock, LockError> {
        let created = (!folder.exists()).then(|| folder.to_path_buf());
        std::fs::create_dir_all(folder).map_err(io_err(folder))?;
        let path = folder.join(LOCK_FILE);
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(io_err(&path))?;
        match flock(&file, FlockOperation::NonBlockingLockExclusive) {
            Ok(()) => {}
            Err(e) if would_block(&e) => {
                return Err(LockError::Busy {
                    folder: folder.to_path_buf(),
                    holder: describe_holders(&mut file, &path),
                });
            }
            Err(e) => return Err(io_err(&path)(e.into())),
        }
        // From here on the lock is held: dropping it (an error below) removes a new folder.
        let mut held = FolderLock {
            file,
            path,
            created,
        };
        let mut line = serde_json::to_string(&Holder::me()).unwrap_or_default();
        line.push('\n');
        held.file
            .set_len(0)
            .and_then(|()| held.file.rewind())
            .and_then(|()| held.file.write_all(line.as_bytes()))
            .map_err(|err| LockError::Io {
                path: held.path.clone(),
                err,
            })?;
        Ok(held)
    }

    /// Takes `folder`'s lock shared, beside other readers; [`LockError::Busy`] while a writer
    /// holds it. `None` (nothing to hold) when the folder has no lock file and none can be made
    /// (read-only media: no command can write there either) or the folder does not exist (the
    /// caller's own check names it).
    pub fn shared(folder: &Path) -> Result<Option<FolderLock>, LockError> {
        if !folder.is_dir() {
            return Ok(None);
        }
        let path = folder.join(LOCK_FILE);
        let opened = OpenOptions::new().read(true).open(&path).or_else(|e| {
            if e.kind() == std::io::ErrorKind::NotFound {
                OpenOptions::new()
                    .read(true)
                    .write(true)
                    .create(true)
                    .truncate(false)
                    .open(&path)
            } else {
                Err(e)
            }
        });
        let mut file = match opened {
            Ok(f) => f,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::PermissionDenied | std::io::ErrorKind::ReadOnlyFilesystem
                ) =>
            {
                return Ok(None);
            }
            Err(e) => return Err(io_err(&path)(e)),
        };
        match flock(&file, FlockOperation::NonBlockingLockShared) {
            Ok(()) => Ok(Some(FolderLock {
                file,
                path,
                created: None,
            })),
            Err(e) if would_block(&e) => Err(LockError::Busy {
                folder: folder.to_path_buf(),
                holder: describe_holders(&mut file, &path),
            }),
            Err(e) => Err(io_err(&path)(e.into())),
        }
    }

    /// Whether another process holds `folder`'s lock, and who: `None` when it is free (or the
    /// folder has no lock file). Takes nothing.
    pub fn holder(folder: &Path) -> Option<String> {
        let path = folder.join(LOCK_FILE);
        let mut file = File::open(&path).ok()?;
        match flock(&file, FlockOperation::NonBlockingLockExclusive) {
            Ok(()) => None,
            Err(e) if would_block(&e) => Some(describe_holders(&mut file, &path)),
            Err(_) => None,
        }
    }

    /// Replaces the locked `folder` by `partial` (a complete new version built beside it) while
    /// keeping the lock: the lock file moves into `partial` first (the lock belongs to the open
    /// file, not to its name), then the old folder is removed and `partial` renamed into place.
    pub fn replace_folder(&mut self, folder: &Path, partial: &Path) -> Result<(), LockError> {
        let moved = partial.join(LOCK_FILE);
        std::fs::rename(&self.path, &moved).map_err(io_err(&self.path))?;
        self.path = moved;
        if folder.exists() {
            std::fs::remove_dir_all(folder).map_err(io_err(folder))?;
        }
        std::fs::rename(partial, folder).map_err(io_err(folder))?;
        self.path = folder.join(LOCK_FILE);
        self.created = None;
        Ok(())
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Who holds the lock on `file` (which this process failed to lock): the writer recorded in
/// it, or, when only readers hold it, the processes `/proc/locks` names.
fn describe_holders(file: &mut File, path: &Path) -> String {
    // Shared while only readers hold it: then the file's record is an old writer's.
    if flock(&*file, FlockOperation::NonBlockingLockShared).is_ok() {
        let _ = flock(&*file, FlockOperation::Unlock);
        let readers = lock_holders(path)
            .into_iter()
            .filter(|&p| p != std::process::id())
            .map(|p| format!("`{}` (pid {p})", command_of(p)))
            .collect::<Vec<_>>();
        return if readers.is_empty() {
            "another command reading it".into()
        } else {
            format!("{} reading it", readers.join(", "))
        };
    }
    // A writer: its record (it writes it right after taking the lock; give it a moment).
    for _ in 0..20 {
        let mut text = String::new();
        if file.rewind().is_ok() && file.read_to_string(&mut text).is_ok() {
            if let Ok(h) = serde_json::from_str::<Holder>(text.trim()) {
                return h.describe();
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    match lock_holders(path).first() {
        Some(&p) => format!("`{}` (pid {p})", command_of(p)),
        None => "another process".into(),
    }
}

/// The processes holding an `flock` on `path`, from `/proc/locks` (empty where it is missing).
fn lock_holders(path: &Path) -> Vec<u32> {
    let Ok(meta) = std::fs::metadata(path) else {
        return Vec::new();
    };
    let Ok(text) = std::fs::read_to_string("/proc/locks") else {
        return Vec::new();
    };
    let (major, minor) = (rustix::fs::major(meta.dev()), rustix::fs::minor(meta.dev()));
    parse_proc_locks(&text, major, minor, meta.ino())
}

/// The pids of the `FLOCK` lines of `/proc/locks` on device `major:minor`, inode `ino` (granted
/// locks only, not waiters), in order. A line reads `1: FLOCK  ADVISORY  WRITE 1234 fd:01:5678
/// 0 EOF` (device numbers in hexadecimal).
pub fn parse_proc_locks(text: &str, major: u32, minor: u32, ino: u64) -> Vec<u32> {
    let mut out = Vec::new();
    for line in text.lines() {
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 6 || f[1] == "->" || f[1] != "FLOCK" {
            continue;
        }
        let (Ok(pid), Some(id)) = (f[4].parse::<u32>(), f.get(5)) else {
            continue;
        };
        let parts: Vec<&str> = id.split(':').collect();
        if let [ma, mi, i] = parts[..]
            && u32::from_str_radix(ma, 16) == Ok(major)
            && u32::from_str_radix(mi, 16) == Ok(minor)
            && i.parse::<u64>() == Ok(ino)
            && !out.contains(&pid)
        {
            out.push(pid);
        }
    }
    out
}

/// The command line of process `pid` (`?` where it cannot be read).
fn command_of(pid: u32) -> String {
    match std::fs::read(format!("/proc/{pid}/cmdline")) {
        Ok(b) if !b.is_empty() => b
            .split(|&c| c == 0)
            .filter(|a| !a.is_empty())
            .map(|a| String::from_utf8_lossy(a).into_owned())
            .collect::<Vec<_>>()
            .join(" "),
        _ => "?".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn proc_locks_lines_are_matched_by_device_and_inode() {
        let text = "1: FLOCK  ADVISORY  WRITE 1234 fd:01:5678 0 EOF\n\
                    1: -> FLOCK  ADVISORY  WRITE 999 fd:01:5678 0 EOF\n\
                    2: FLOCK  ADVISORY  READ 42 fd:01:5678 0 EOF\n\
                    3: POSIX  ADVISORY  WRITE 7 fd:01:5678 0 EOF\n\
                    4: FLOCK  ADVISORY  READ 8 fd:02:5678 0 EOF\n\
                    5: FLOCK  ADVISORY  READ 9 fd:01:56780 0 EOF\n";
        assert_eq!(parse_proc_locks(text, 0xfd, 1, 5678), vec![1234, 42]);
        assert!(parse_proc_locks(text, 0xfd, 3, 5678).is_empty());
    }

    fn tmp(name: &str) -> PathBuf {
        let d = crate::fsutil::test_temp_dir().join(format!("lock-{name}"));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    /// Locks taken twice in one process conflict as between processes (`flock` locks belong to
    /// the open file, and each take opens the lock file anew).
    #[test]
    fn a_writer_excludes_everyone_and_readers_exclude_writers() {
        let d = tmp("kinds");
        let w = FolderLock::exclusive(&d).unwrap();
        // (Something written, so that the folder stays when the writer lets go.)
        std::fs::write(d.join("x"), "x").unwrap();
        let rec: Holder =
            serde_json::from_str(std::fs::read_to_string(d.join(LOCK_FILE)).unwrap().trim())
                .unwrap();
        assert_eq!(rec.pid, std::process::id());
        for e in [
            FolderLock::exclusive(&d).unwrap_err(),
            FolderLock::shared(&d).unwrap_err(),
        ] {
            assert!(e.is_busy());
            let m = e.to_string();
            assert!(
                m.contains(&format!("pid {}, started", std::process::id())),
                "{m}"
            );
        }
        assert!(FolderLock::holder(&d).is_some());
        drop(w);
        assert!(FolderLock::holder(&d).is_none());
        let r1 = FolderLock::shared(&d).unwrap().unwrap();
        let _r2 = FolderLock::shared(&d).unwrap().unwrap();
        let e = FolderLock::exclusive(&d).unwrap_err();
        assert!(e.is_busy() && e.to_string().contains("reading it"), "{e}");
        drop(r1);
        assert!(
            FolderLock::exclusive(&d).unwrap_err().is_busy(),
            "one reader left"
        );
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn a_folder_the_lock_made_and_left_empty_goes_with_it_and_a_replace_keeps_the_lock() {
        let d = tmp("made");
        drop(FolderLock::exclusive(&d).unwrap());
        assert!(!d.exists(), "a refused command leaves no folder");
        let mut l = FolderLock::exclusive(&d).unwrap();
        std::fs::write(d.join("old.txt"), "old").unwrap();
        let partial = d.with_file_name("made.partial");
        std::fs::create_dir_all(&partial).unwrap();
        std::fs::write(partial.join("new.txt"), "new").unwrap();
        l.replace_folder(&d, &partial).unwrap();
        assert!(!partial.exists() && !d.join("old.txt").exists());
        assert_eq!(std::fs::read_to_string(d.join("new.txt")).unwrap(), "new");
        assert!(
            FolderLock::exclusive(&d).unwrap_err().is_busy(),
            "still held"
        );
        drop(l);
        assert!(d.join("new.txt").exists(), "a folder with content stays");
        assert!(FolderLock::holder(&d).is_none());
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn durations_in_words() {
        assert_eq!(duration_words(0), "0 s");
        assert_eq!(duration_words(119), "119 s");
        assert_eq!(duration_words(120), "2 min");
        assert_eq!(duration_words(7199), "119 min");
        assert_eq!(duration_words(7200), "2 h");
        assert_eq!(duration_words(3 * 86_400), "3 days");
    }
}
