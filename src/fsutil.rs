//! Output files that never survive half-written: everything is written to a temporary
//! sibling and renamed into place once complete.
use std::fs::{self, File};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

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

/// Writes `path` through `fill`, into a temporary file that is renamed over `path` only
/// when `fill` succeeded and the data was flushed. On failure the temporary file is removed.
pub fn atomic_write<E, F>(path: &Path, fill: F) -> Result<(), E>
where
    E: From<FsError>,
    F: FnOnce(&mut BufWriter<File>) -> Result<(), E>,
{
    let tmp = tmp_path(path);
    let wrap = |err| FsError::Write {
        path: path.to_path_buf(),
        err,
    };
    let file = File::create(&tmp).map_err(wrap)?;
    let mut writer = BufWriter::with_capacity(1 << 20, file);
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
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
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
}
