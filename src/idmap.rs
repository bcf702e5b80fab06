//! The per-view maps of a run folder, one reader and writer for all of them (`docs/design.md`,
//! "Run folder"): int32 id maps `<stem>.ids.npy` — the raycast's four channels `4×H×W`
//! (feature, surface, part, `M_city`), the associate stage's group map and the fuse stage's
//! label map (`H×W` each) — the raycast's city-model depth `<stem>.depth.npy` (float32 `H×W`,
//! NaN where no surface is hit) and the class / instance maps of predictions and ground truth
//! (`<stem>.class.npy`, `<stem>.instance.npy`, int32 `H×W`, −1 = none). Every read checks the
//! shape against the view's camera. A format: it imports no stage.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::npy::{self, NpyElement, NpyError};

/// Errors of reading or writing a map.
#[derive(Debug, thiserror::Error)]
pub enum IdMapError {
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error("{path}: {why}")]
    Shape { path: PathBuf, why: String },
    #[error("cannot list {path}: {err}")]
    ReadDir { path: PathBuf, err: std::io::Error },
}

/// Suffix of a class map (prediction or ground truth).
pub const CLASS_SUFFIX: &str = ".class.npy";

/// Path of view `stem`'s id map in `dir` (raycast, associate or fuse folder).
pub fn ids_file(dir: &Path, stem: &str) -> PathBuf {
    dir.join(format!("{stem}.ids.npy"))
}

/// Path of view `stem`'s city-model depth map in a raycast folder.
pub fn depth_file(dir: &Path, stem: &str) -> PathBuf {
    dir.join(format!("{stem}.depth.npy"))
}

/// Path of view `stem`'s class map in `dir`.
pub fn class_file(dir: &Path, stem: &str) -> PathBuf {
    dir.join(format!("{stem}{CLASS_SUFFIX}"))
}

/// Path of view `stem`'s instance (label) map in `dir`.
pub fn instance_file(dir: &Path, stem: &str) -> PathBuf {
    dir.join(format!("{stem}.instance.npy"))
}

/// Reads `path` and checks its shape is `shape`; `what` describes the expected shape in the
/// error (e.g. "for this camera").
pub fn read_checked<T: NpyElement>(
    path: &Path,
    shape: &[usize],
    what: &str,
) -> Result<Vec<T>, IdMapError> {
    let (s, data) = npy::read::<T>(path)?;
    if s != shape {
        return Err(IdMapError::Shape {
            path: path.to_path_buf(),
            why: format!("shape {s:?}, expected {shape:?} {what}"),
        });
    }
    Ok(data)
}

/// A raycast view's four channels (feature, surface, part, city), each row-major `H×W`.
pub fn read_raycast(
    dir: &Path,
    stem: &str,
    width: usize,
    height: usize,
) -> Result<Vec<i32>, IdMapError> {
    read_checked(
        &ids_file(dir, stem),
        &[4, height, width],
        "(feature, surface, part, city) for this camera",
    )
}

/// Writes a raycast view's four channels as `4×H×W`.
pub fn write_raycast(
    dir: &Path,
    stem: &str,
    width: usize,
    height: usize,
    channels: [&[i32]; 4],
) -> Result<(), IdMapError> {
    let mut stacked = Vec::with_capacity(4 * width * height);
    for ch in channels {
        stacked.extend_from_slice(ch);
    }
    npy::write(&ids_file(dir, stem), &[4, height, width], &stacked)?;
    Ok(())
}

/// A raycast view's city-model depth (`H×W`).
pub fn read_depth(
    dir: &Path,
    stem: &str,
    width: usize,
    height: usize,
) -> Result<Vec<f32>, IdMapError> {
    read_checked(&depth_file(dir, stem), &[height, width], "for this camera")
}

/// Writes a raycast view's depth.
pub fn write_depth(
    dir: &Path,
    stem: &str,
    width: usize,
    height: usize,
    depth: &[f32],
) -> Result<(), IdMapError> {
    npy::write(&depth_file(dir, stem), &[height, width], depth)?;
    Ok(())
}

/// A one-channel id map (`H×W`: associate groups or fused labels).
pub fn read_ids(
    dir: &Path,
    stem: &str,
    width: usize,
    height: usize,
) -> Result<Vec<i32>, IdMapError> {
    read_checked(&ids_file(dir, stem), &[height, width], "for this camera")
}

/// Writes a one-channel id map.
pub fn write_ids(
    dir: &Path,
    stem: &str,
    width: usize,
    height: usize,
    ids: &[i32],
) -> Result<(), IdMapError> {
    npy::write(&ids_file(dir, stem), &[height, width], ids)?;
    Ok(())
}

/// An int32 `H×W` map of any size (class maps); returns `([H, W], data)`.
pub fn read_any_map(path: &Path) -> Result<([usize; 2], Vec<i32>), IdMapError> {
    let (shape, data) = npy::read::<i32>(path)?;
    match shape[..] {
        [h, w] if h > 0 && w > 0 => Ok(([h, w], data)),
        _ => Err(IdMapError::Shape {
            path: path.to_path_buf(),
            why: format!("expected a non-empty 2-D H×W class map, found shape {shape:?}"),
        }),
    }
}

/// The `<stem>` → path map of the `*.class.npy` files of a folder.
pub fn list_class_maps(dir: &Path) -> Result<BTreeMap<String, PathBuf>, IdMapError> {
    let rd = |err| IdMapError::ReadDir {
        path: dir.to_path_buf(),
        err,
    };
    let mut out = BTreeMap::new();
    for entry in std::fs::read_dir(dir).map_err(rd)? {
        let entry = entry.map_err(rd)?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if let Some(stem) = name.strip_suffix(CLASS_SUFFIX)
            && !stem.is_empty()
            && entry.path().is_file()
        {
            out.insert(stem.to_string(), entry.path());
        }
    }
    Ok(out)
}

/// Where the per-view label maps of the vote come from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum LabelMaps {
    /// `M_city`: channel 3 of a raycast folder's `<stem>.ids.npy` (4×H×W).
    City(PathBuf),
    /// A fuse folder's `<stem>.ids.npy` (H×W).
    Fused(PathBuf),
}

impl LabelMaps {
    /// The folder the maps are read from.
    pub fn dir(&self) -> &Path {
        match self {
            LabelMaps::City(d) | LabelMaps::Fused(d) => d,
        }
    }

    /// The file of view `stem`.
    pub fn file(&self, stem: &str) -> PathBuf {
        ids_file(self.dir(), stem)
    }

    /// The label map of view `stem` (`width × height`, row-major).
    pub fn read(&self, stem: &str, width: usize, height: usize) -> Result<Vec<i32>, IdMapError> {
        match self {
            LabelMaps::City(d) => {
                let mut all = read_raycast(d, stem, width, height)?;
                Ok(all.split_off(3 * width * height))
            }
            LabelMaps::Fused(d) => read_ids(d, stem, width, height),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn maps_round_trip_and_wrong_shapes_are_named() {
        let dir = std::env::temp_dir().join(format!("gs4city-idmap-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (w, h) = (3, 2);
        let ch: Vec<Vec<i32>> = (0..4)
            .map(|c| (0..6).map(|p| c * 10 + p).collect())
            .collect();
        write_raycast(&dir, "v", w, h, [&ch[0], &ch[1], &ch[2], &ch[3]]).unwrap();
        let all = read_raycast(&dir, "v", w, h).unwrap();
        assert_eq!(all[..6], ch[0][..]);
        assert_eq!(all[18..], ch[3][..]);
        // The city channel is the last one.
        let city = LabelMaps::City(dir.clone()).read("v", w, h).unwrap();
        assert_eq!(city, vec![30, 31, 32, 33, 34, 35]);
        // A raycast map read as a one-channel map: refused with both shapes named.
        let e = read_ids(&dir, "v", w, h).unwrap_err().to_string();
        assert!(e.contains("[4, 2, 3]") && e.contains("[2, 3]"), "{e}");
        let e = read_raycast(&dir, "v", 2, 3).unwrap_err().to_string();
        assert!(e.contains("v.ids.npy") && e.contains("[4, 3, 2]"), "{e}");
        write_depth(&dir, "v", w, h, &[1.0, f32::NAN, 2.0, 3.0, 4.0, 5.0]).unwrap();
        let d = read_depth(&dir, "v", w, h).unwrap();
        assert!(d[1].is_nan() && d[5] == 5.0);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
