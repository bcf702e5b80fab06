//! The scene folder (`docs/design.md`): which of its parts exist, and the train/test split of its views.
//!
//! ```text
//! scene/
//!   images/                  RGB images, names as in COLMAP
//!   sparse/0/                COLMAP model (.bin or .txt)
//!   point_cloud.ply          pre-trained 3DGS (INRIA layout)
//!   citymodel/*.gml          LoD3 CityGML or CityJSON (*.city.json, *.city.jsonl) (+ alignment.json)
//!   masks/<stem>.json        optional: SAM automatic masks per view
//!   features/<stem>.npy      optional: one feature row per SAM mask; features/prompts.json
//!   gt/                      optional: ground truth, read only by evaluation
//!   scene.json               optional: the scene's own description ([`SceneMeta`]: whether it is
//!                            SIMULATED); written by `gs4city synth`
//! ```
//! Pipeline stages take the paths they need from [`Scene`]; only evaluation uses [`Scene::gt`].
//! Nothing else of the folder is listed here: a simulator's own files are not inputs
//! (`docs/design.md`, "Inputs the algorithms may read").
use std::collections::BTreeSet;
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
    /// `citymodel/*.gml` (and `*.xml`, CityJSON: `crate::cityjson::is_model_file`), sorted by
    /// name: the order fixes the entity ids.
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
    /// `scene.json`: the scene's own description (a scene without it is a real capture as far
    /// as anything here can tell).
    pub meta: SceneMeta,
}

/// The scene's own description, `S/scene.json`. It is metadata, not truth: what it says is
/// shown (`report.html` says SIMULATED at the top), never used to compute anything.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneMeta {
    /// True for a scene that `gs4city synth` simulated.
    #[serde(default)]
    pub simulated: bool,
}

impl SceneMeta {
    /// The file name inside the scene folder.
    pub const FILE: &'static str = "scene.json";

    /// Reads `root/scene.json`; a scene without one gets the default (not simulated). A file
    /// that is not such a JSON object is an error naming it.
    pub fn read(root: &Path) -> Result<SceneMeta, SceneError> {
        let path = root.join(Self::FILE);
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(SceneMeta::default()),
            Err(e) => {
                return Err(SceneError {
                    scene: root.to_path_buf(),
                    why: format!("{}: {e}", Self::FILE),
                });
            }
        };
        serde_json::from_slice(&bytes).map_err(|e| SceneError {
            scene: root.to_path_buf(),
            why: format!("{}: {e}", Self::FILE),
        })
    }
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
            .filter(|p| p.is_file() && crate::cityjson::is_model_file(p))
            .collect();
        gml.sort();
        if gml.is_empty() {
            return Err(bad(
                "citymodel/ holds no city model (.gml, .xml, .city.json, .city.jsonl)".into(),
            ));
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
            meta: SceneMeta::read(root)?,
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

/// Where the parts of a scene folder come from ([`import`]).
#[derive(Debug, Clone, Default)]
pub struct ImportSpec {
    /// A 3DGS training output (INRIA `-m` folder: `point_cloud/iteration_N/point_cloud.ply`,
    /// `cameras.json`, `cfg_args`), or `None` with [`ImportSpec::ply`].
    pub model: Option<PathBuf>,
    /// The iteration to take (default: the highest `point_cloud/iteration_N`).
    pub iteration: Option<u32>,
    /// A PLY in the INRIA layout (nerfstudio `ns-export gaussian-splat`, gsplat's export), or
    /// a `.splat`, `.spz` or SuperSplat compressed PLY (converted to an INRIA PLY on import);
    /// overrides the training output's.
    pub ply: Option<PathBuf>,
    /// The COLMAP folder the scene was trained from (`sparse/0/`, `images/`); default: the
    /// `source_path` recorded in the training output's `cfg_args`.
    pub source: Option<PathBuf>,
    /// The CityGML files, or folders holding them (`*.gml`, `*.xml`).
    pub citygml: Vec<PathBuf>,
    /// `alignment.json` (copied: it is the file a user edits or refines).
    pub alignment: Option<PathBuf>,
    /// SAM lists (`masks/`) and per-mask features (`features/`), optional.
    pub masks: Option<PathBuf>,
    pub features: Option<PathBuf>,
    /// Copy the files instead of linking them.
    pub copy: bool,
}

/// What [`import`] made: every part of the scene folder and where it points.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ImportReport {
    pub scene: PathBuf,
    /// `(part, source)`: `point_cloud.ply`, `sparse/0`, `images`, `citymodel/<file>`, …
    pub parts: Vec<(String, PathBuf)>,
    /// The parts that could not be found (the scene check names what they are for).
    pub missing: Vec<String>,
}

/// The highest `point_cloud/iteration_N/point_cloud.ply` of a training output (or `N` itself).
fn trained_ply(model: &Path, iteration: Option<u32>) -> Option<PathBuf> {
    let dir = model.join("point_cloud");
    let n = match iteration {
        Some(n) => n,
        None => std::fs::read_dir(&dir)
            .ok()?
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                e.file_name()
                    .to_str()?
                    .strip_prefix("iteration_")?
                    .parse::<u32>()
                    .ok()
            })
            .filter(|n| dir.join(format!("iteration_{n}/point_cloud.ply")).is_file())
            .max()?,
    };
    Some(dir.join(format!("iteration_{n}/point_cloud.ply"))).filter(|p| p.is_file())
}

/// A string field `name='…'` of the training output's `cfg_args` (a Python `Namespace`).
fn cfg_field(model: &Path, name: &str) -> Option<String> {
    let text = std::fs::read_to_string(model.join("cfg_args")).ok()?;
    let at = text.find(&format!("{name}="))? + name.len() + 1;
    let rest = &text[at..];
    let q = rest.chars().next().filter(|c| *c == '\'' || *c == '"')?;
    let end = rest[1..].find(q)?;
    Some(rest[1..1 + end].to_string())
}

/// Builds the scene folder `out` (`docs/design.md`) from a 3DGS training output, the COLMAP
/// folder it was trained from and the CityGML model, by symbolic links (or copies with
/// [`ImportSpec::copy`]); nothing is renamed by hand. `out` must not exist or be empty. A part
/// that cannot be found is listed in [`ImportReport::missing`], not an error: `gs4city check`
/// then says what it is for.
pub fn import(spec: &ImportSpec, out: &Path) -> Result<ImportReport, SceneError> {
    let bad = |why: String| SceneError {
        scene: out.to_path_buf(),
        why,
    };
    if out.exists()
        && std::fs::read_dir(out)
            .map(|mut d| d.next().is_some())
            .unwrap_or(true)
    {
        return Err(bad(
            "exists and is not empty: scene import writes a new folder".into(),
        ));
    }
    let abs = |p: &Path| {
        p.canonicalize()
            .map_err(|e| bad(format!("{}: {e}", p.display())))
    };
    let mut parts: Vec<(String, PathBuf)> = Vec::new();
    let mut missing = Vec::new();
    // The Gaussians.
    let ply = match (&spec.ply, &spec.model) {
        (Some(p), _) => Some(abs(p)?),
        (None, Some(m)) => Some(abs(&trained_ply(m, spec.iteration).ok_or_else(|| {
            bad(format!(
                "{}: no point_cloud/iteration_{}/point_cloud.ply (a 3DGS training output, `train.py -m`)",
                m.display(),
                spec.iteration.map_or("N".to_string(), |n| n.to_string())
            ))
        })?)?),
        (None, None) => None,
    };
    match ply {
        Some(p) => parts.push(("point_cloud.ply".into(), p)),
        None => missing.push("point_cloud.ply".into()),
    }
    // The COLMAP folder, and why it is missing when it is.
    let mut no_source = String::new();
    let source = match (&spec.source, &spec.model) {
        (Some(s), _) => Some(abs(s)?),
        (None, Some(m)) => match cfg_field(m, "source_path") {
            None => {
                no_source = format!(
                    "{} holds no readable source_path='…': give --source",
                    m.join("cfg_args").display()
                );
                None
            }
            // A relative source_path is relative to where training ran: tried from here,
            // then from the training output and its parent folder.
            Some(p) => match [PathBuf::from(&p), m.join(&p), m.join("..").join(&p)]
                .into_iter()
                .find(|c| c.is_dir())
            {
                Some(dir) => Some(abs(&dir)?),
                None => {
                    no_source = format!(
                        "the source_path of {}, {p}, is not a folder here: give --source",
                        m.join("cfg_args").display()
                    );
                    None
                }
            },
        },
        (None, None) => {
            no_source = "give --source (the COLMAP folder) or --model".into();
            None
        }
    };
    if let Some(src) = &source {
        let sparse = [src.join("sparse/0"), src.join("sparse")]
            .into_iter()
            .find(|p| p.join("images.bin").is_file() || p.join("images.txt").is_file());
        match sparse {
            Some(p) => parts.push(("sparse/0".into(), p)),
            None => missing.push(format!(
                "sparse/0 (no images.bin or images.txt in {0}/sparse/0 or {0}/sparse)",
                src.display()
            )),
        }
        let images = spec
            .model
            .as_deref()
            .and_then(|m| cfg_field(m, "images"))
            .unwrap_or_else(|| "images".into());
        match Some(src.join(&images)).filter(|p| p.is_dir()) {
            Some(p) => parts.push(("images".into(), p)),
            None => missing.push(format!(
                "images (no folder {})",
                src.join(&images).display()
            )),
        }
    } else {
        missing.extend([
            format!("sparse/0 ({no_source})"),
            format!("images ({no_source})"),
        ]);
    }
    // The city model.
    let mut gml = Vec::new();
    for p in &spec.citygml {
        let p = abs(p)?;
        if p.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(&p)
                .map_err(|e| bad(format!("{}: {e}", p.display())))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|q| q.is_file() && crate::cityjson::is_model_file(q))
                .collect();
            found.sort();
            gml.extend(found);
        } else {
            gml.push(p);
        }
    }
    if gml.is_empty() {
        missing.push("citymodel/*.gml".into());
    }
    let mut names = BTreeSet::new();
    for g in &gml {
        let name = g
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        if !names.insert(name.clone()) {
            return Err(bad(format!(
                "two CityGML files are called {name}: citymodel/ holds one folder level"
            )));
        }
        parts.push((format!("citymodel/{name}"), g.clone()));
    }
    match &spec.alignment {
        Some(a) => parts.push(("citymodel/alignment.json".into(), abs(a)?)),
        None => missing.push("citymodel/alignment.json".into()),
    }
    for (name, p) in [("masks", &spec.masks), ("features", &spec.features)] {
        if let Some(p) = p {
            parts.push((name.into(), abs(p)?));
        }
    }
    // Write: the folder, then one link (or copy) per part.
    crate::fsutil::create_dir(&out.join("citymodel")).map_err(|e| bad(e.to_string()))?;
    for (part, src) in &parts {
        let dst = out.join(part);
        if let Some(parent) = dst.parent() {
            crate::fsutil::create_dir(parent).map_err(|e| bad(e.to_string()))?;
        }
        // alignment.json is always copied: it is edited and refined in place.
        let copy = spec.copy || part == "citymodel/alignment.json";
        if part == "point_cloud.ply" && !is_inria_ply(src) {
            // .splat, .spz, compressed PLY: converted once into the INRIA layout, which every
            // stage (and `gs4city tile`'s streaming cut) reads
            let (g, _) = crate::splat::read_ply(src, &crate::splat::ReadOptions::KEEP)
                .map_err(|e| bad(e.to_string()))?;
            crate::splat::write_ply(&dst, &g, crate::splat::PlyEncoding::BinaryLittleEndian)
                .map_err(|e| bad(e.to_string()))?;
            continue;
        }
        let r = if copy {
            copy_tree(src, &dst)
        } else {
            link(src, &dst)
        };
        r.map_err(|e| bad(format!("{part} ← {}: {e}", src.display())))?;
    }
    Ok(ImportReport {
        scene: out.to_path_buf(),
        parts,
        missing,
    })
}

/// Whether `path` is an INRIA PLY (not a `.splat`, SPZ or compressed PLY, which [`import`]
/// converts).
fn is_inria_ply(path: &Path) -> bool {
    use crate::splat::SplatFormat;
    let mut head = [0u8; 4];
    let n = std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read(&mut f, &mut head))
        .unwrap_or(0);
    match crate::splat::formats::detect(path, &head[..n]) {
        SplatFormat::Ply | SplatFormat::CompressedPly => crate::ply::read_header(path)
            .map_or(true, |(h, _)| !crate::splat::compressed::is_compressed(&h)),
        SplatFormat::Splat | SplatFormat::Spz => false,
    }
}

#[cfg(unix)]
fn link(src: &Path, dst: &Path) -> std::io::Result<()> {
    std::os::unix::fs::symlink(src, dst)
}

#[cfg(not(unix))]
fn link(src: &Path, dst: &Path) -> std::io::Result<()> {
    copy_tree(src, dst)
}

/// Copies a file, or a folder recursively.
fn copy_tree(src: &Path, dst: &Path) -> std::io::Result<()> {
    if src.is_dir() {
        std::fs::create_dir_all(dst)?;
        for e in std::fs::read_dir(src)? {
            let e = e?;
            copy_tree(&e.path(), &dst.join(e.file_name()))?;
        }
        Ok(())
    } else {
        std::fs::copy(src, dst).map(|_| ())
    }
}
