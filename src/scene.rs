//! The scene folder (`docs/design.md`): which of its parts exist, and the train/test split of its views.
//!
//! ```text
//! scene/
//!   images/                  RGB images, names as in COLMAP
//!   sparse/0/                COLMAP model (.bin or .txt)
//!   point_cloud.ply          pre-trained 3DGS (INRIA layout)
//!   citymodel/*.gml          LoD3 CityGML (+ alignment.json)
//!   masks/<stem>.json        optional: SAM automatic masks per view
//!   features/<stem>.npy      optional: one feature row per SAM mask; features/prompts.json
//!   gt/                      optional: ground truth, read only by evaluation
//! ```
//! Pipeline stages take the paths they need from [`Scene`]; only evaluation uses [`Scene::gt`].
//! Nothing else of the folder is listed here: a simulator's own files are not inputs
//! (`docs/design.md`, "Inputs the algorithms may read").
use std::path::{Path, PathBuf};

use crate::camera::View;

/// Errors of opening a scene folder.
#[derive(Debug, thiserror::Error)]
#[error("scene {scene}: {why}")]
pub struct SceneError {
    pub scene: PathBuf,
    pub why: String,
}

/// The parts of a scene folder.
#[derive(Debug, Clone)]
pub struct Scene {
    pub root: PathBuf,
    /// `citymodel/*.gml` (and `*.xml`), sorted by name: the order fixes the entity ids.
    pub gml: Vec<PathBuf>,
    /// `citymodel/alignment.json` where it exists.
    pub alignment: Option<PathBuf>,
    /// The COLMAP model folder (`sparse/0`, or `sparse` itself).
    pub sparse: PathBuf,
    pub images: Option<PathBuf>,
    pub ply: PathBuf,
    /// `masks/` where it exists (SAM lists `<stem>.json`).
    pub masks: Option<PathBuf>,
    /// `features/` where it exists (`<stem>.npy`, `prompts.json`).
    pub features: Option<PathBuf>,
    /// `gt/` where it exists: for evaluation only.
    pub gt: Option<PathBuf>,
}

impl Scene {
    /// Finds and checks the parts of a scene folder.
    pub fn open(root: &Path) -> Result<Scene, SceneError> {
        let bad = |why: String| SceneError {
            scene: root.to_path_buf(),
            why,
        };
        if !root.is_dir() {
            return Err(bad("not a directory".into()));
        }
        let cm = root.join("citymodel");
        let mut gml: Vec<PathBuf> = std::fs::read_dir(&cm)
            .map_err(|e| bad(format!("citymodel/: {e}")))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.is_file()
                    && p.extension().is_some_and(|x| {
                        x.eq_ignore_ascii_case("gml") || x.eq_ignore_ascii_case("xml")
                    })
            })
            .collect();
        gml.sort();
        if gml.is_empty() {
            return Err(bad("citymodel/ holds no .gml files".into()));
        }
        let alignment = Some(cm.join("alignment.json")).filter(|p| p.is_file());
        let sparse = [root.join("sparse/0"), root.join("sparse")]
            .into_iter()
            .find(|p| p.join("images.bin").is_file() || p.join("images.txt").is_file())
            .ok_or_else(|| bad("no COLMAP model in sparse/0 (images.bin or images.txt)".into()))?;
        let ply = root.join("point_cloud.ply");
        if !ply.is_file() {
            return Err(bad("no point_cloud.ply (the pre-trained 3DGS scene)".into()));
        }
        let dir = |name: &str| Some(root.join(name)).filter(|p| p.is_dir());
        Ok(Scene {
            root: root.to_path_buf(),
            gml,
            alignment,
            sparse,
            images: dir("images"),
            ply,
            masks: dir("masks"),
            features: dir("features"),
            gt: dir("gt"),
        })
    }

    /// The SAM list of view `stem` (`masks/<stem>.json`), where it exists.
    pub fn sam_file(&self, stem: &str) -> Option<PathBuf> {
        self.masks
            .as_ref()
            .map(|d| d.join(format!("{stem}.json")))
            .filter(|p| p.is_file())
    }

    /// The per-mask features of view `stem` (`features/<stem>.npy`), where they exist.
    pub fn feature_file(&self, stem: &str) -> Option<PathBuf> {
        self.features
            .as_ref()
            .map(|d| d.join(format!("{stem}.npy")))
            .filter(|p| p.is_file())
    }

    /// `features/prompts.json`, where it exists.
    pub fn prompts_file(&self) -> Option<PathBuf> {
        self.features
            .as_ref()
            .map(|d| d.join("prompts.json"))
            .filter(|p| p.is_file())
    }
}

/// Training and test views.
#[derive(Debug, Clone, Default)]
pub struct Split {
    pub train: Vec<View>,
    pub test: Vec<View>,
}

impl Split {
    /// Splits views sorted by name: index `i` with `i % every == 0` is a test view (the 3DGS
    /// `--eval` convention, `every` = 8); `every` = 0 makes every view a training view.
    pub fn new(mut views: Vec<View>, every: usize) -> Split {
        views.sort_by(|a, b| a.name.cmp(&b.name));
        let mut s = Split::default();
        for (i, v) in views.into_iter().enumerate() {
            if every != 0 && i % every == 0 {
                s.test.push(v)
            } else {
                s.train.push(v)
            }
        }
        s
    }

    /// Every view, training views first.
    pub fn all(&self) -> impl Iterator<Item = &View> {
        self.train.iter().chain(&self.test)
    }

    /// The test views' stems.
    pub fn test_stems(&self) -> Vec<String> {
        self.test.iter().map(|v| v.stem()).collect()
    }
}
