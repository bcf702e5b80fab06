//! Output files that never survive half-written: everything is written to a temporary
//! sibling and renamed into place once complete. The xxh3-64 digest of what
//! [`atomic_write`] wrote is computed on the way ([`written`]), so the run store need not read
//! a stage's outputs back to record them.
use std::fs::{self, File};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::Serialize;

/// Errors of atomic output writing.
#[derive(Debug, thiserror::Error)]
pub enum FsError {
    #[error("cannot write {path}: {err}")]
    Write { path: PathBuf, err: io::Error },
    #[error("cannot create directory {path}: {err}")]
    CreateDir { path: PathBuf, err: io::Error },
    #[error("cannot read {path}: {err}")]
    Read { path: PathBuf, err: io::Error },
    #[error("{path}: {err}")]
    Parse {
        path: PathBuf,
        err: serde_json::Error,
    },
    #[error("cannot serialise JSON for {path}: {err}")]
    Json {
        path: PathBuf,
        err: serde_json::Error,
    },
}

fn tmp_path(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp{}", std::process::id()))
}

/// The file [`atomic_write`] fills: every byte also goes into the xxh3-64 digest.
pub struct Digesting {
    file: File,
    hash: xxhash_rust::xxh3::Xxh3,
    bytes: u64,
}

impl Write for Digesting {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.file.write(buf)?;
        self.hash.update(&buf[..n]);
        self.bytes += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.file.flush()
    }
}

/// What [`atomic_write`] wrote to a path: size, modification and inode change times (ns since
/// the epoch) and the xxh3-64 digest of the content (hex).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Written {
    pub size: u64,
    pub mtime_ns: u64,
    pub ctime_ns: u64,
    pub digest: String,
}

/// The files this process has written with [`atomic_write`], by path, until [`written`] takes
/// them.
static WRITTEN: std::sync::LazyLock<Mutex<std::collections::HashMap<PathBuf, Written>>> =
    std::sync::LazyLock::new(Default::default);

/// How a content digest is written: the xxh3-64 value as 16 hex digits.
pub fn digest_hex(h: u64) -> String {
    format!("{h:016x}")
}

/// The modification time of `m` in ns since the epoch (0 where unknown).
pub fn mtime_ns(m: &fs::Metadata) -> u64 {
    m.modified()
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos() as u64)
}

/// The inode change time of `m` in ns since the epoch: set by the kernel to the current time on
/// every write, rename, link or attribute change of the file — including a change of its
/// modification time — and settable by no system call (only by setting the clock back).
pub fn ctime_ns(m: &fs::Metadata) -> u64 {
    use std::os::unix::fs::MetadataExt;
    u64::try_from(m.ctime())
        .ok()
        .and_then(|s| s.checked_mul(1_000_000_000))
        .and_then(|ns| ns.checked_add(u64::try_from(m.ctime_nsec()).ok()?))
        .unwrap_or(0)
}

/// Takes what this process wrote to `path` with [`atomic_write`], when the file still has that
/// size, modification time and inode change time (so it was not changed since); `None`
/// otherwise.
pub fn written(path: &Path) -> Option<Written> {
    let w = WRITTEN
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .remove(path)?;
    let m = fs::metadata(path).ok()?;
    (m.is_file() && m.len() == w.size && mtime_ns(&m) == w.mtime_ns && ctime_ns(&m) == w.ctime_ns)
        .then_some(w)
}

/// Writes `path` through `fill`, into a temporary file that is renamed over `path` only
/// when `fill` succeeded and the data was flushed. On failure the temporary file is removed.
/// The content's digest is kept for [`written`].
pub fn atomic_write<E, F>(path: &Path, fill: F) -> Result<(), E>
where
    E: From<FsError>,
    F: FnOnce(&mut BufWriter<Digesting>) -> Result<(), E>,
{
    let tmp = tmp_path(path);
    let wrap = |err| FsError::Write {
        path: path.to_path_buf(),
        err,
    };
    let file = File::create(&tmp).map_err(wrap)?;
    let mut writer = BufWriter::with_capacity(
        1 << 20,
        Digesting {
            file,
            hash: xxhash_rust::xxh3::Xxh3::new(),
            bytes: 0,
        },
    );
    let result = fill(&mut writer).and_then(|()| {
        writer.flush().map_err(wrap)?;
        fs::rename(&tmp, path).map_err(|err| {
            FsError::Write {
                path: path.to_path_buf(),
                err,
            }
            .into()
        })
    });
    match &result {
        Err(_) => {
            let _ = fs::remove_file(&tmp);
        }
        Ok(()) => {
            let d = writer.get_ref();
            if let Ok(m) = fs::metadata(path) {
                let w = Written {
                    size: d.bytes,
                    mtime_ns: mtime_ns(&m),
                    ctime_ns: ctime_ns(&m),
                    digest: digest_hex(d.hash.digest()),
                };
                WRITTEN
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .insert(path.to_path_buf(), w);
            }
        }
    }
    result
}

/// Writes raw bytes atomically.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<(), FsError> {
    atomic_write(path, |w| {
        w.write_all(bytes).map_err(|err| FsError::Write {
            path: path.to_path_buf(),
            err,
        })
    })
}

/// Writes pretty JSON atomically.
pub fn write_json<T: Serialize + ?Sized>(path: &Path, value: &T) -> Result<(), FsError> {
    let mut text = serde_json::to_vec_pretty(value).map_err(|err| FsError::Json {
        path: path.to_path_buf(),
        err,
    })?;
    text.push(b'\n');
    write_bytes(path, &text)
}

/// `bytes` without a leading UTF-8 byte-order mark (editors on Windows write one; JSON
/// readers must not trip over it).
pub fn strip_bom(bytes: &[u8]) -> &[u8] {
    bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes)
}

/// Reads a JSON file into `T` (an error names the file, and serde's message the line and column).
pub fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, FsError> {
    let bytes = fs::read(path).map_err(|err| FsError::Read {
        path: path.to_path_buf(),
        err,
    })?;
    serde_json::from_slice(strip_bom(&bytes)).map_err(|err| FsError::Parse {
        path: path.to_path_buf(),
        err,
    })
}

/// Creates `dir` and its parents.
pub fn create_dir(dir: &Path) -> Result<(), FsError> {
    fs::create_dir_all(dir).map_err(|err| FsError::CreateDir {
        path: dir.to_path_buf(),
        err,
    })
}

/// The folder the test suites write under: `<temp>/gs4city-tests-<pid>`, created on first use.
/// That first use also removes the folders of earlier test processes that have ended, so a
/// failed test keeps its files while its process lives and nothing piles up across runs.
/// (For the crate's own tests and `tests/`; no stage uses it.)
#[doc(hidden)]
pub fn test_temp_dir() -> PathBuf {
    static ROOT: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    ROOT.get_or_init(|| {
        let tmp = std::env::temp_dir();
        // Whether a process still runs is read from /proc; without it nothing is removed.
        let entries = Path::new("/proc/self").exists().then(|| fs::read_dir(&tmp));
        for e in entries.into_iter().flatten().flatten().flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if let Some(pid) = name.strip_prefix("gs4city-tests-")
                && pid.parse::<u32>().is_ok()
                && !Path::new("/proc").join(pid).exists()
            {
                let _ = fs::remove_dir_all(e.path());
            }
        }
        let root = tmp.join(format!("gs4city-tests-{}", std::process::id()));
        let _ = fs::create_dir_all(&root);
        root
    })
    .clone()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failed_fill_leaves_nothing_behind() {
        let dir =
            crate::fsutil::test_temp_dir().join(format!("gs4city-fsutil-{}", std::process::id()));
        create_dir(&dir).unwrap();
        let target = dir.join("out.bin");
        let r: Result<(), FsError> = atomic_write(&target, |w| {
            w.write_all(b"partial").unwrap();
            Err(FsError::Write {
                path: target.clone(),
                err: io::Error::other("boom"),
            })
        });
        assert!(r.is_err());
        assert!(!target.exists());
        assert_eq!(
            fs::read_dir(&dir).unwrap().count(),
            0,
            "temporary file must be removed"
        );
        write_bytes(&target, b"ok").unwrap();
        assert_eq!(fs::read(&target).unwrap(), b"ok");
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn written_gives_the_digest_of_what_was_written_once_and_only_while_unchanged() {
        let d = test_temp_dir().join(format!("fsutil-written-{}", std::process::id()));
        create_dir(&d).unwrap();
        let p = d.join("x.bin");
        let content: Vec<u8> = (0..5000u32).map(|i| (i * 7 % 251) as u8).collect();
        write_bytes(&p, &content).unwrap();
        let w = written(&p).expect("just written");
        assert_eq!(w.size, 5000);
        assert_eq!(
            w.digest,
            format!("{:016x}", xxhash_rust::xxh3::xxh3_64(&content))
        );
        assert_eq!(written(&p), None, "taken once");
        // Rewritten, then grown in place: the file no longer matches what was written.
        write_bytes(&p, b"abc").unwrap();
        fs::OpenOptions::new()
            .append(true)
            .open(&p)
            .unwrap()
            .write_all(b"d")
            .unwrap();
        assert_eq!(written(&p), None);
        // A failed fill records nothing.
        let q = d.join("y.bin");
        let r: Result<(), FsError> = atomic_write(&q, |_| {
            Err(FsError::Write {
                path: q.clone(),
                err: io::Error::other("boom"),
            })
        });
        assert!(r.is_err() && !q.exists() && written(&q).is_none());
        let _ = fs::remove_dir_all(&d);
    }
}
