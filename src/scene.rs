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
//!   scene.json               optional: the scene's own description ([`SceneMeta`]: the
//!                            declared test views, whether it is SIMULATED, what wrote it)
//! ```
//! Pipeline stages take the paths they need from [`Scene`]; only evaluation uses [`Scene::gt`].
//! Nothing else of the folder is listed here: a simulator's own files are not inputs
//! (`docs/design.md`, "Inputs the algorithms may read"). `scene.json` is an input (the split
//! a dataset declares, like its image list), never simulation truth.
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use crate::camera::View;

/// Errors of opening a scene folder.
#[derive(Debug, thiserror::Error)]
#[error("scene {scene}: {why}")]
pub struct SceneError {
    pub scene: PathBuf,
    pub why: String,
}

/// `scene.json`: what a scene folder declares about itself. Written by `gs4city synth` (a
/// SIMULATED scene with its test views) and `gs4city scene import` (the parts it linked, no test
/// views); a user may write one by hand (e.g. to declare a capture's test views).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneMeta {
    /// The scene is SIMULATED (`gs4city synth`): its images, Gaussians and masks are synthetic;
    /// reports say so in a banner.
    #[serde(default)]
    pub simulated: bool,
    /// What wrote the folder (e.g. `gs4city synth --preset small --seed 1`).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub generator: String,
    /// The declared test views (image names as in COLMAP, or their stems): held back from
    /// labelling, predicted as novel views, evaluated where `gt/` has them. Absent: every view
    /// trains (`gs4city run --test-every N` makes a split of its own).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test_views: Option<Vec<String>>,
    /// `scene import`: each part it linked or copied (`point_cloud.ply`, `sparse/0`, …) and its
    /// source, so that a second import into the folder replaces what the first one made.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub imported: BTreeMap<String, PathBuf>,
}

impl SceneMeta {
    /// The file name inside the scene folder (`docs/design.md`, "scene.json").
    pub const FILE: &'static str = "scene.json";

    /// Reads `root/scene.json`; `Ok(None)` when the folder has none. A file that is not such a
    /// JSON object is an error naming it.
    pub fn read(root: &Path) -> Result<Option<SceneMeta>, SceneError> {
        let p = root.join(Self::FILE);
        if !p.is_file() {
            return Ok(None);
        }
        crate::fsutil::read_json(&p)
            .map(Some)
            .map_err(|e| SceneError {
                scene: root.to_path_buf(),
                why: e.to_string(),
            })
    }

    /// The split of `views` this file declares for the scene folder `root`: its test views,
    /// without them every view trains. A declared name that is not a view is an error naming it.
    pub fn split(&self, root: &Path, views: Vec<View>) -> Result<Split, SceneError> {
        match &self.test_views {
            None => Ok(Split::new(views, 0)),
            Some(names) => Split::declared(views, names).map_err(|why| SceneError {
                scene: root.to_path_buf(),
                why: format!("{}: {why}", Self::FILE),
            }),
        }
    }

    /// Writes `root/scene.json` (atomically).
    pub fn write(&self, root: &Path) -> Result<(), SceneError> {
        crate::fsutil::write_json(&root.join(Self::FILE), self).map_err(|e| SceneError {
            scene: root.to_path_buf(),
            why: e.to_string(),
        })
    }
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
    /// `scene.json`: the scene's own description (a scene without it is a real capture with
    /// no declared test views, as far as anything here can tell).
    pub meta: SceneMeta,
}

/// A file left out of a listing, and the file listed before it that it reaches.
pub type Twin = (PathBuf, PathBuf);

/// The city-model files of a scene's `citymodel/` folder (`*.gml`, `*.xml`, CityJSON:
/// `crate::cityjson::is_model_file`), sorted by name, each file once: a name that reaches a
/// file listed before it (a link) is left out and returned with that file, so its objects are
/// not read twice.
pub fn citymodel_files(cm: &Path) -> std::io::Result<(Vec<PathBuf>, Vec<Twin>)> {
    let mut all: Vec<PathBuf> = std::fs::read_dir(cm)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && crate::cityjson::is_model_file(p))
        .collect();
    all.sort();
    let mut seen: std::collections::HashMap<PathBuf, usize> = Default::default();
    let mut files: Vec<PathBuf> = Vec::with_capacity(all.len());
    let mut twins = Vec::new();
    for p in all {
        let canon = std::fs::canonicalize(&p).unwrap_or_else(|_| p.clone());
        match seen.get(&canon) {
            Some(&i) => twins.push((p, files[i].clone())),
            None => {
                seen.insert(canon, files.len());
                files.push(p);
            }
        }
    }
    Ok((files, twins))
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
        let (gml, _) = citymodel_files(&cm).map_err(|e| bad(format!("citymodel/: {e}")))?;
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
        let meta = SceneMeta::read(root)?.unwrap_or_default();
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
            meta,
        })
    }

    /// Whether the scene declares itself SIMULATED (`scene.json`).
    pub fn simulated(&self) -> bool {
        self.meta.simulated
    }

    /// The split of `views` the scene declares ([`SceneMeta::split`]).
    pub fn declared_split(&self, views: Vec<View>) -> Result<Split, SceneError> {
        self.meta.split(&self.root, views)
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

    /// Splits views sorted by name into the test views named in `names` (image names or
    /// stems) and the training views; a name that matches no view is an error naming it.
    pub fn declared(mut views: Vec<View>, names: &[String]) -> Result<Split, String> {
        views.sort_by(|a, b| a.name.cmp(&b.name));
        for n in names {
            if !views.iter().any(|v| &v.name == n || &v.stem() == n) {
                return Err(format!(
                    "test view `{n}` is not an image of the COLMAP model"
                ));
            }
        }
        let mut s = Split::default();
        for v in views {
            if names.iter().any(|n| *n == v.name || *n == v.stem()) {
                s.test.push(v)
            } else {
                s.train.push(v)
            }
        }
        Ok(s)
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
    /// Import into a folder that holds other files (not an earlier import's): the parts it
    /// makes are replaced, the rest stays.
    pub force: bool,
}

/// What [`import`] made: every part of the scene folder and where it points.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ImportReport {
    pub scene: PathBuf,
    /// `(part, source)`: `point_cloud.ply`, `sparse/0`, `images`, `citymodel/<file>`, …
    pub parts: Vec<(String, PathBuf)>,
    /// The parts that could not be found (the scene check names what they are for).
    pub missing: Vec<String>,
    /// The folder held an earlier import, whose parts this one replaced.
    pub reimported: bool,
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
/// [`ImportSpec::copy`]); nothing is renamed by hand, and `out/scene.json` records what was
/// linked (no test views: an imported capture trains on every view). `out` is a new or empty
/// folder, or one an earlier import wrote (its parts are replaced and parts it no longer has are
/// removed; `citymodel/alignment.json`, written by `gs4city align` after an import, stays unless
/// this import brings one), or any folder with [`ImportSpec::force`]. A part that cannot be found
/// is listed in [`ImportReport::missing`], not an error: `gs4city check` then says what it is for.
pub fn import(spec: &ImportSpec, out: &Path) -> Result<ImportReport, SceneError> {
    let bad = |why: String| SceneError {
        scene: out.to_path_buf(),
        why,
    };
    let nonempty = out.exists()
        && std::fs::read_dir(out)
            .map(|mut d| d.next().is_some())
            .unwrap_or(true);
    // An earlier import's record (a scene.json that is not an import's, or none, is not one).
    let earlier = match SceneMeta::read(out) {
        Ok(m) => m.filter(|m| !m.imported.is_empty()),
        Err(e) if spec.force => {
            log::warn!("{e}: replaced (--force)");
            None
        }
        Err(e) => return Err(e),
    };
    if nonempty && earlier.is_none() && !spec.force {
        return Err(bad(
            "exists and holds files that `scene import` did not write (no scene.json of an \
             import): give a new --out folder, or --force to import into this one (the parts it \
             links are replaced, other files stay)"
                .into(),
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
    // Write: the folder, then one link (or copy) per part; an earlier import's parts that
    // this one does not make are removed first (never the alignment: `gs4city align` writes
    // it into the folder after an import).
    crate::fsutil::create_dir(&out.join("citymodel")).map_err(|e| bad(e.to_string()))?;
    if let Some(old) = &earlier {
        for part in old.imported.keys() {
            if part != "citymodel/alignment.json" && !parts.iter().any(|(p, _)| p == part) {
                remove_part(&out.join(part)).map_err(|e| bad(format!("{part}: {e}")))?;
            }
        }
    }
    // scene.json first: an interrupted import is imported again into the same folder.
    let meta = SceneMeta {
        simulated: false,
        generator: "gs4city scene import".into(),
        // A split the user declared by hand survives a second import.
        test_views: earlier.as_ref().and_then(|m| m.test_views.clone()),
        imported: parts.iter().cloned().collect(),
    };
    meta.write(out)?;
    for (part, src) in &parts {
        let dst = out.join(part);
        if let Some(parent) = dst.parent() {
            crate::fsutil::create_dir(parent).map_err(|e| bad(e.to_string()))?;
        }
        remove_part(&dst).map_err(|e| bad(format!("{part}: {e}")))?;
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
        reimported: earlier.is_some(),
    })
}

/// Removes what lies at a part's place (a link, a file or a folder); nothing there is fine.
fn remove_part(p: &Path) -> std::io::Result<()> {
    match std::fs::symlink_metadata(p) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(e),
        Ok(m) if m.is_dir() => std::fs::remove_dir_all(p),
        Ok(_) => std::fs::remove_file(p),
    }
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
