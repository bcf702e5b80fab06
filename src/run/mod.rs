//! The `run` orchestrator: a scene folder through every stage into a run folder `R` (`docs/design.md`,
//! "Stage contract"): (`R/align`) → `R/citymodel` → `R/render` (the training views the run needs
//! and the contributions cache) → `R/raycast` → `R/masks` → `R/associate` → `R/fuse` → `R/lift`
//! (the vote) → (`R/train`) → `R/eval`
//! (when the scene has `gt/`), `R/report.html` and `R/run.json`. With `--supervision city` the
//! mask stages are skipped and the vote reads `M_city` alone (paper §3.1).
//!
//! Each stage is a library function from typed inputs to a typed summary; this module only wires
//! them: it passes paths and typed summaries, never reads a stage's JSON by key. The run store
//! ([`store`]) decides what is resumed and makes every stage folder appear atomically.
pub mod report;
pub mod store;

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::alignment::Alignment;
use crate::associate::{self, AssociateOptions, AssociateSummary};
pub use crate::cache::ViewSelection;
use crate::cache::{self, Cache, CacheOptions, CacheSummary};
use crate::camera::View;
use crate::citymodel::{self, CitymodelSummary};
use crate::eval::EvalSummary;
use crate::fuse::{self, FuseOptions, FuseSummary};
use crate::idmap::LabelMaps;
use crate::labels::LabelTable;
pub use crate::layout::Mode;
use crate::layout::Stage;
use crate::lift::{self, LiftOptions, LiftSummary};
use crate::masks::{self, MasksOptions, MasksSummary};
use crate::openings::{self, OpeningsOptions, OpeningsSummary};
use crate::raycast::{self, RaycastSummary};
use crate::render;
use crate::scene::{Scene, SceneError, Split};
use crate::semantics;
use crate::train::{self, TrainOptions, TrainSummary};
use crate::vote::VoteInputs;
use crate::{classes, colmap, fsutil};
pub use store::StageReport;
use store::{Store, StoreError};

/// What the per-Gaussian labels are learned from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Supervision {
    /// `M_city` alone (paper §3.1): buildings, surfaces and openings only.
    City,
    /// `M_city` fused with the scene's filtered and associated masks (paper §3.2): also trees,
    /// cars, people and other objects. A scene without `masks/` uses the mask-free source.
    #[default]
    Fused,
}

impl std::str::FromStr for Supervision {
    type Err = String;
    fn from_str(s: &str) -> Result<Supervision, String> {
        match s {
            "fused" => Ok(Supervision::Fused),
            "city" => Ok(Supervision::City),
            _ => Err(format!("{s:?} is not one of fused, city")),
        }
    }
}

/// Errors of the run stage.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error(transparent)]
    Check(#[from] crate::inspect::InspectError),
    #[error("{0}")]
    Refused(String),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Lock(#[from] crate::lock::LockError),
    #[error(transparent)]
    CityModel(#[from] citymodel::CityModelError),
    #[error(transparent)]
    Semantics(#[from] semantics::SemanticsError),
    #[error(transparent)]
    Align(#[from] crate::alignment::AlignError),
    #[error(transparent)]
    Colmap(#[from] colmap::ColmapError),
    #[error(transparent)]
    Raycast(#[from] raycast::RaycastError),
    #[error(transparent)]
    Render(#[from] crate::render::RenderError),
    #[error(transparent)]
    Cache(#[from] cache::CacheError),
    #[error(transparent)]
    Labels(#[from] crate::labels::LabelsError),
    #[error(transparent)]
    Lift(#[from] lift::LiftError),
    #[error(transparent)]
    Eval(#[from] crate::eval::EvalError),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Fs(#[from] fsutil::FsError),
    #[error(transparent)]
    Mesh(#[from] crate::mesh::MeshError),
    #[error(transparent)]
    Report(#[from] report::ReportError),
    #[error(transparent)]
    Refine(#[from] crate::refine::RefineError),
    #[error(transparent)]
    Selection(#[from] crate::selection::SelectionError),
    #[error(transparent)]
    Masks(#[from] masks::MasksError),
    #[error(transparent)]
    Openings(#[from] crate::openings::OpeningsError),
    #[error(transparent)]
    Associate(#[from] associate::AssociateError),
    #[error(transparent)]
    Fuse(#[from] fuse::FuseError),
    #[error(transparent)]
    Train(#[from] train::TrainError),
}

/// Every option of a run (recorded in `run.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunOptions {
    /// Part-pass depth tolerance τ in metres (× the alignment scale in the scene frame).
    pub tau_m: f64,
    pub single_pass: bool,
    /// Longest contribution list of the cache (0 = no bound; with `epsilon` 0 the top-k).
    pub top_k: usize,
    /// The cache's mass rule (`cache::CacheOptions::epsilon`); 0 (and in run.json files
    /// before it existed) = plain top-k lists.
    #[serde(default)]
    pub epsilon: f32,
    /// The cache's early stop (`cache::CacheOptions::t_stop`); 0 (and in run.json files
    /// before it existed) = the rasterizer's own stop only.
    #[serde(default)]
    pub t_stop: f32,
    /// The cache's smallest contributing α (`cache::CacheOptions::alpha_min`); 1/255 in
    /// run.json files before it existed.
    #[serde(default = "inria_alpha_min")]
    pub alpha_min: f32,
    /// Training views are worked at `1/train_scale` of their resolution, from the render and
    /// the raycast to the vote (masks, openings, association, fusion, vote); test views always
    /// at their full resolution. 1 (and in run.json files before it existed) = full.
    #[serde(default = "full_scale")]
    pub train_scale: u32,
    /// Which training views the run works on (`render::select`); every one in run.json files
    /// before it existed.
    #[serde(default)]
    pub views: ViewSelection,
    pub lift: LiftOptions,
    /// Where the labels come from (city model alone, or fused with the masks).
    pub supervision: Supervision,
    pub masks: MasksOptions,
    /// Windows and doors from the images where the model lacks them, and the completeness
    /// report (`R/openings/`, docs/completeness.md).
    #[serde(default)]
    pub openings: OpeningsOptions,
    pub associate: AssociateOptions,
    pub fuse: FuseOptions,
    /// The per-Gaussian labels that are evaluated and queried: the vote, or identity learning
    /// (the `train` stage, which starts from the vote).
    pub mode: Mode,
    pub train: TrainOptions,
    /// Every `test_every`-th view (by name) is a test view; 0 = none. `None`: the split the
    /// scene declares (`scene.json`'s test views; without them every view trains). Whether
    /// the scene has `gt/` never changes the split.
    pub test_every: Option<usize>,
    /// Run without `citymodel/alignment.json` (the CityGML coordinates minus a local origin).
    pub local_origin: bool,
    /// Refine the alignment from the 3DGS scene first (`R/align/`, `align --refine`); every
    /// later stage uses the refined transform.
    pub refine_alignment: bool,
    pub refine: crate::refine::RefineOptions,
    /// The scene check that runs first ([`crate::inspect`]; `local_origin` is this run's).
    #[serde(default)]
    pub check: crate::inspect::CheckOptions,
    /// Rerun every stage even when its output is complete.
    pub force: bool,
}

fn full_scale() -> u32 {
    1
}

fn inria_alpha_min() -> f32 {
    cache::INRIA_ALPHA_MIN
}

/// How much work a run does for its answer: the presets of `gs4city run --quality`, points of
/// the speed–error curve in BENCHMARKS.md ("Work knobs") and docs/quality.md.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Quality {
    /// Every training view at full resolution, the longest contribution lists.
    Full,
    /// The default: the cheapest setting within 0.5 points of fine mIoU of `full` on every
    /// scene measured: `full`'s views and resolution, the cache's blend stopped once a pixel's
    /// transmittance falls below [`DEFAULT_T_STOP`], contributions from α ≥
    /// [`DEFAULT_ALPHA_MIN`], lists to 1 − [`DEFAULT_EPSILON`] of a pixel's mass.
    #[default]
    Default,
    /// Less work, for a first look: training views at half resolution and the 3-cover of
    /// the views (it costs fine mIoU points: docs/quality.md).
    Fast,
}

/// The early stop of the default preset's cache (`cache::CacheOptions::t_stop`): the Gaussians
/// behind the last 20 % of a pixel's transmittance are not listed (BENCHMARKS.md, "Work knobs").
pub const DEFAULT_T_STOP: f32 = 0.2;

/// The mass share the default preset's lists leave out (`cache::CacheOptions::epsilon`): a
/// pixel keeps its largest weights up to 90 % of its mass (BENCHMARKS.md, "Work knobs").
pub const DEFAULT_EPSILON: f32 = 0.1;

/// The smallest contributing α of the default preset's cache (`cache::CacheOptions::alpha_min`):
/// the faint tails of Gaussians are left out of the lists and the blend (BENCHMARKS.md, "Work
/// knobs").
pub const DEFAULT_ALPHA_MIN: f32 = 1.0 / 32.0;

impl std::str::FromStr for Quality {
    type Err = String;
    fn from_str(s: &str) -> Result<Quality, String> {
        match s {
            "full" => Ok(Quality::Full),
            "default" => Ok(Quality::Default),
            "fast" => Ok(Quality::Fast),
            _ => Err(format!("{s:?} is not one of full, default, fast")),
        }
    }
}

/// The work knobs a [`Quality`] sets.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Work {
    pub train_scale: u32,
    pub views: ViewSelection,
    pub top_k: usize,
    pub epsilon: f32,
    pub t_stop: f32,
    pub alpha_min: f32,
}

impl Quality {
    /// The preset's knobs.
    pub fn work(self) -> Work {
        let full = Work {
            train_scale: 1,
            views: ViewSelection::All,
            top_k: cache::TOP_K,
            epsilon: cache::EPSILON,
            t_stop: cache::T_STOP,
            alpha_min: cache::INRIA_ALPHA_MIN,
        };
        let default = Work {
            epsilon: DEFAULT_EPSILON,
            t_stop: DEFAULT_T_STOP,
            alpha_min: DEFAULT_ALPHA_MIN,
            ..full
        };
        match self {
            Quality::Full => full,
            Quality::Default => default,
            // The early stop costs more at half resolution (street: 78.69 against 79.59), so
            // `fast` keeps full's lists.
            Quality::Fast => Work {
                train_scale: 2,
                views: ViewSelection::Cover { k: 3, share: 1.0 },
                ..full
            },
        }
    }
}

impl RunOptions {
    /// These options with the work knobs of `w`.
    pub fn with_work(self, w: Work) -> RunOptions {
        RunOptions {
            train_scale: w.train_scale,
            views: w.views,
            top_k: w.top_k,
            epsilon: w.epsilon,
            t_stop: w.t_stop,
            alpha_min: w.alpha_min,
            ..self
        }
    }
}

impl Default for RunOptions {
    fn default() -> Self {
        let work = Quality::Default.work();
        RunOptions {
            tau_m: raycast::TAU_M,
            single_pass: false,
            top_k: work.top_k,
            epsilon: work.epsilon,
            t_stop: work.t_stop,
            alpha_min: work.alpha_min,
            train_scale: work.train_scale,
            views: work.views,
            lift: LiftOptions::default(),
            supervision: Supervision::Fused,
            masks: MasksOptions::default(),
            openings: OpeningsOptions::default(),
            associate: AssociateOptions::default(),
            fuse: FuseOptions::default(),
            mode: Mode::Vote,
            train: TrainOptions::default(),
            test_every: None,
            local_origin: false,
            refine_alignment: false,
            refine: crate::refine::RefineOptions::default(),
            check: crate::inspect::CheckOptions::default(),
            force: false,
        }
    }
}

/// What a run did.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunSummary {
    pub scene: PathBuf,
    pub options: RunOptions,
    pub stages: Vec<StageReport>,
    pub test_views: Vec<String>,
    /// The evaluation, when the scene has ground truth.
    pub eval: Option<EvalSummary>,
    pub report: PathBuf,
    /// The stages' loud lines: a stage that contributed (almost) nothing, with the likely cause.
    #[serde(default)]
    pub warnings: Vec<String>,
}

/// Every file directly in `dir` (sorted; none when it does not exist).
fn files_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_file())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// Runs (or resumes) every stage of the scene folder `scene_dir` into `out`, in this order
/// (the only place that knows it): align (optional) → citymodel → render → raycast → masks →
/// openings (windows/doors the model lacks; the completed model is raycast again) →
/// associate → fuse (fused supervision) → lift → train (mode learned) → eval (with `gt/`) →
/// report.
///
/// The scene folder is used by its canonical path (`S`, `./S/` and `/abs/S` are one scene
/// to the run store, and `run.json` names it absolutely, so `query --run R` works from any
/// working directory). The scene is checked first ([`crate::inspect`]): every problem is
/// reported at once and nothing runs while one is an error.
pub fn run(scene_dir: &Path, out: &Path, opts: &RunOptions) -> Result<RunSummary, RunError> {
    let scene_dir = &canonical(scene_dir)?;
    let mut r = open(scene_dir, out, opts)?;
    let alignment_file = align_step(&mut r, opts)?;
    let cm = citymodel_step(&mut r, alignment_file.as_deref(), opts)?;
    let cache = render_step(&mut r, opts)?;
    raycast_step(&mut r, cm.alignment.scale, opts)?;
    let entities = semantics::read(&r.st.dir(Stage::Citymodel).join("semantics.json"))?;
    let srs = cm.files.iter().find_map(|f| f.srs_name.clone());
    let sup = match opts.supervision {
        Supervision::City => city_supervision(&mut r, entities)?,
        Supervision::Fused => {
            fused_supervision(&mut r, &cache, entities, cm.alignment.scale, srs, opts)?
        }
    };
    let pred_dir = vote_steps(&mut r, &cache, &sup, cm.alignment.scale, opts)?;
    let eval = eval_step(&mut r, &cache, &pred_dir, out, opts)?;
    finish(r, out, opts, &pred_dir, eval, sup, &cache)
}

/// The command line of this process, each word quoted for a POSIX shell where needed.
fn command_line() -> String {
    std::env::args_os()
        .map(|a| report::shell_word(&a.to_string_lossy()))
        .collect::<Vec<_>>()
        .join(" ")
}

/// The canonical path of the scene folder (one clear line when it does not exist).
fn canonical(scene_dir: &Path) -> Result<PathBuf, RunError> {
    scene_dir.canonicalize().map_err(|e| {
        RunError::Scene(SceneError {
            scene: scene_dir.to_path_buf(),
            why: format!("cannot open the scene folder: {e}"),
        })
    })
}

/// What every step of a run shares.
struct Running {
    scene: Scene,
    /// Every view the run works on, by name: the training views of the selection at the work
    /// resolution and the test views (set by [`render_step`]; before it, every view at its
    /// full resolution).
    views: Vec<View>,
    /// The training and test views, as `views`.
    split: Split,
    st: Store,
    /// The scene check's warnings (CityGML warnings stay in `R/citymodel/summary.json`).
    check_warnings: Vec<String>,
    sparse_files: Vec<PathBuf>,
    /// The run folder's exclusive lock, held for the whole run.
    _lock: crate::lock::FolderLock,
}

/// Validates everything before anything is written, then opens the run store.
fn open(scene_dir: &Path, out: &Path, opts: &RunOptions) -> Result<Running, RunError> {
    store::check_out_dir(scene_dir, out, &Stage::ALL).map_err(RunError::Refused)?;
    // Before anything in the folder is touched: one run at a time, and none beside a reader.
    let lock = crate::lock::FolderLock::exclusive(out)?;
    // The run's own completion markers are written last; a run that fails part-way (or at
    // the scene check) must not leave the previous run's summary and report looking like
    // this one's.
    for f in ["summary.json", "report.html"] {
        let p = out.join(f);
        if p.exists() {
            std::fs::remove_file(&p).map_err(|e| {
                RunError::Refused(format!("cannot remove the old {}: {e}", p.display()))
            })?;
        }
    }
    let check = crate::inspect::check(
        scene_dir,
        &crate::inspect::CheckOptions {
            local_origin: opts.local_origin,
            refine_next: opts.refine_alignment,
            ..opts.check
        },
    );
    let mut shown = 0;
    let mut check_warnings = Vec::new();
    for f in check.of(crate::inspect::Severity::Warning) {
        shown += 1;
        if shown <= 5 || crate::progress::verbose() {
            log::warn!("{f}");
        }
        let citygml = crate::cityjson::is_model_file(&f.file);
        if !citygml {
            check_warnings.push(f.to_string());
        }
    }
    if shown > 5 && !crate::progress::verbose() {
        log::warn!(
            "{} more warnings of the scene check (-v shows them all; `gs4city check --scene {}`)",
            shown - 5,
            scene_dir.display()
        );
    }
    let check = check.into_result()?;
    if let Some(a) = &check.alignment {
        log::info!(
            "check: the city model projects into {} of {} views; opaque Gaussians lie {:.2} m from it (lower quartile; median {:.2} m)",
            a.views_seeing_model,
            a.views,
            a.quartile_distance_m,
            a.median_distance_m
        );
    }
    let scene = Scene::open(scene_dir)?;
    if scene.alignment.is_none() && !opts.local_origin {
        return Err(RunError::Refused(format!(
            "{}: no citymodel/alignment.json, so the transform from the CityGML coordinates to the \
             3DGS scene frame is unknown; write one (`gs4city align`) or pass --local-origin to use \
             the CityGML coordinates minus a local origin",
            scene.root.display()
        )));
    }
    if let Some(a) = &scene.alignment {
        Alignment::read(a)?;
    }
    if !(opts.tau_m.is_finite() && opts.tau_m >= 0.0) {
        return Err(RunError::Refused(format!(
            "tau must be a finite number ≥ 0 (metres), got {}",
            crate::numfmt::Num(opts.tau_m)
        )));
    }
    let views = colmap::read_model(&scene.sparse)?;
    // Never from `gt/`: a run must give the same outputs with the simulation truth deleted.
    let split = match opts.test_every {
        Some(every) => Split::new(views.clone(), every),
        None => scene.declared_split(views.clone())?,
    };
    if split.train.is_empty() {
        return Err(RunError::Refused(format!(
            "no training views: every view is a test view ({})",
            match opts.test_every {
                Some(n) => format!("--test-every {n}"),
                None => format!(
                    "the test views of {}",
                    scene.root.join(crate::scene::SceneMeta::FILE).display()
                ),
            }
        )));
    }
    if scene.gt.is_some() && split.test.is_empty() {
        log::warn!(
            "the scene has gt/ but --test-every 0 leaves no test view: every view trains and \
             eval is skipped"
        );
    }
    let st = Store::open(
        out,
        &scene.root,
        serde_json::to_value(opts).unwrap_or_default(),
        opts.force,
    )?;
    let sparse_files = files_in(&scene.sparse);
    Ok(Running {
        scene,
        views,
        split,
        st,
        check_warnings,
        sparse_files,
        _lock: lock,
    })
}

/// Step 0: align --refine (optional): the alignment file every later stage uses.
fn align_step(r: &mut Running, opts: &RunOptions) -> Result<Option<PathBuf>, RunError> {
    if !opts.refine_alignment {
        return Ok(r.scene.alignment.clone());
    }
    let (scene, views) = (&r.scene, &r.views);
    let mut ins = scene.gml.clone();
    ins.extend(scene.alignment.clone());
    ins.push(scene.ply.clone());
    ins.extend(r.sparse_files.iter().cloned());
    let _r: crate::refine::RefineSummary =
        r.st.stage(Stage::Align, &opts.refine, &ins, &[], |dir| {
            let t = std::time::Instant::now();
            let initial = scene
                .alignment
                .as_deref()
                .map(Alignment::read)
                .transpose()?;
            let city = citymodel::run(&scene.gml, &citymodel::Options { alignment: initial })?;
            let centres: Vec<glam::DVec3> = views.iter().map(|v| v.camera.pose.center()).collect();
            Ok::<_, RunError>(crate::refine::run(
                &crate::refine::CityFrame {
                    mesh: &city.mesh,
                    entities: &city.entities,
                    initial: &city.alignment,
                    load_s: t.elapsed().as_secs_f64(),
                },
                crate::refine::RefineSources {
                    citymodel: scene.root.join("citymodel"),
                    city_source: "CityGML".into(),
                    initial_alignment: scene.alignment.clone(),
                    ply: scene.ply.clone(),
                    ply_report: None,
                    colmap: Some(scene.sparse.clone()),
                    cameras: None,
                },
                Some(&centres),
                &opts.refine,
                &dir.join("alignment.json"),
                dir,
            )?)
        })?;
    Ok(Some(r.st.dir(Stage::Align).join("alignment.json")))
}

/// Step 1: citymodel: the hierarchy table and the aligned mesh.
fn citymodel_step(
    r: &mut Running,
    alignment_file: Option<&Path>,
    opts: &RunOptions,
) -> Result<CitymodelSummary, RunError> {
    let upstream: &[Stage] = if opts.refine_alignment {
        &[Stage::Align]
    } else {
        &[]
    };
    let gml = &r.scene.gml;
    let mut inputs = gml.clone();
    inputs.extend(alignment_file.map(Path::to_path_buf));
    r.st.stage(
        Stage::Citymodel,
        &opts.local_origin,
        &inputs,
        upstream,
        |dir| {
            let alignment = alignment_file.map(Alignment::read).transpose()?;
            let o = citymodel::run(gml, &citymodel::Options { alignment })?;
            citymodel::write(&o, dir)?;
            Ok::<_, RunError>(o.summary)
        },
    )
}

/// Step 3: raycast (the views of the render): `M_city` and the city-model depth.
fn raycast_step(r: &mut Running, scale: f64, opts: &RunOptions) -> Result<(), RunError> {
    let ro = raycast::RaycastOptions {
        tau: opts.tau_m * scale,
        single_pass: opts.single_pass,
    };
    // No overlays (pictures no stage reads; `gs4city raycast --overlays`), so the images are
    // not read either.
    let inputs = r.sparse_files.clone();
    let cm_dir = r.st.dir(Stage::Citymodel);
    let views = &r.views;
    // Which views are traced at which size: part of the options when the render chose fewer
    // or smaller training views than the cameras', so that another choice reruns the raycast
    // and a new PLY with the same choice does not.
    let traced: Vec<(String, u32, u32)> =
        if opts.train_scale > 1 || opts.views != ViewSelection::All {
            views
                .iter()
                .map(|v| {
                    let k = &v.camera.intrinsics;
                    (v.name.clone(), k.width, k.height)
                })
                .collect()
        } else {
            Vec::new()
        };
    let key = TracedViews {
        options: &ro,
        views: traced,
    };
    let _rc: RaycastSummary =
        r.st.stage(Stage::Raycast, &key, &inputs, &[Stage::Citymodel], |dir| {
            let mesh_path = cm_dir.join("mesh.ply");
            let mesh = crate::mesh::TriMesh::read_ply(&mesh_path)?;
            let entities = semantics::read(&cm_dir.join("semantics.json"))?;
            semantics::check_mesh_labels(&mesh_path, &mesh, &entities)?;
            Ok::<_, RunError>(raycast::run(
                &mesh,
                views,
                &ro,
                raycast::Overlays::Off,
                dir,
            )?)
        })?;
    Ok(())
}

/// The raycast step's options as the run store records them (`views`: empty for every view
/// at its camera's size).
#[derive(Serialize)]
struct TracedViews<'a> {
    #[serde(flatten)]
    options: &'a raycast::RaycastOptions,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    views: Vec<(String, u32, u32)>,
}

/// Step 2: render: the training views the run works on ([`RunOptions::views`]) and their
/// contributions cache at the work resolution ([`RunOptions::train_scale`]), and the test
/// views' at their full resolution. From here on the run works on the views the cache holds.
fn render_step(r: &mut Running, opts: &RunOptions) -> Result<Cache, RunError> {
    let co = CacheOptions {
        top_k: opts.top_k,
        epsilon: opts.epsilon,
        t_stop: opts.t_stop,
        alpha_min: opts.alpha_min,
    };
    opts.views.validate().map_err(RunError::Refused)?;
    if !(1..=crate::camera::MAX_DOWNSCALE as u32).contains(&opts.train_scale) {
        return Err(RunError::Refused(format!(
            "the training views' resolution divisor must be 1 to {}, got {}",
            crate::camera::MAX_DOWNSCALE,
            opts.train_scale
        )));
    }
    let mut inputs = vec![r.scene.ply.clone()];
    inputs.extend(r.sparse_files.iter().cloned());
    let (ply, split) = (&r.scene.ply, &r.split);
    let work = (co, opts.train_scale, opts.views);
    let _cs: CacheSummary = r.st.stage(Stage::Render, &work, &inputs, &[], |dir| {
        let (mut g, _) = crate::splat::read_ply(ply, &crate::splat::ReadOptions::KEEP)?;
        crate::splat::ply::hide_invalid(&mut g);
        let prepared = crate::render::PreparedScene::new(&g)?;
        let cover = match opts.views {
            ViewSelection::All => None,
            ViewSelection::Cover { k, share } => {
                let c = render::select::cover(&prepared, &split.train, k, share);
                log::info!(
                    "views: {} of {} training views meet {:.1} % of the demand of each Gaussian seen by {k} ({:.1} of {:.1} views per Gaussian) in {:.2} s",
                    c.chosen.len(),
                    c.offered,
                    100.0 * share,
                    c.mean_views_chosen,
                    c.mean_views_offered,
                    c.seconds
                );
                Some(c)
            }
        };
        let train: Vec<&View> = match &cover {
            None => split.train.iter().collect(),
            Some(c) => c.chosen.iter().map(|&i| &split.train[i]).collect(),
        };
        let mut views: Vec<View> = train
            .into_iter()
            .map(|v| v.downscaled(opts.train_scale))
            .chain(split.test.iter().cloned())
            .collect();
        views.sort_by(|a, b| a.name.cmp(&b.name));
        let mut s = render::cache::build(&prepared, &views, &co, dir)?;
        if cover.is_some() {
            s.selection = cover;
            crate::layout::Summary::write(&s, dir)?;
        }
        Ok::<_, RunError>(s)
    })?;
    let cache = Cache::open(&r.st.dir(Stage::Render))?;
    let test = cache.views_as_cached(&r.split.test)?;
    if test.len() != r.split.test.len() {
        return Err(RunError::Refused(format!(
            "{}: the cache lacks test views; rerun with --force",
            cache.dir.display()
        )));
    }
    r.split = Split {
        train: cache.views_as_cached(&r.split.train)?,
        test,
    };
    r.views = r.split.all().cloned().collect();
    r.views.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(cache)
}

/// The per-view label maps the vote reads, their label table, the stages they come from, and
/// the masks stage's summary (fused supervision only).
struct Supervised {
    /// The semantic table of the labels: the model's, or the one the openings stage completed.
    entities: Vec<semantics::Entity>,
    /// The raycast folder of that table's mesh (the city votes' depth gate).
    raycast: PathBuf,
    /// That table's `mesh.ply` (the vote's city-model prior).
    mesh: PathBuf,
    maps: LabelMaps,
    labels: LabelTable,
    upstream: Vec<Stage>,
    masks: Option<MasksSummary>,
    /// The mask stages' loud lines and the thresholds they chose (for the report).
    warnings: Vec<String>,
    choices: Vec<String>,
}

/// Steps 4–6 skipped: `M_city` alone (paper §3.1); the mask stages' folders are removed.
fn city_supervision(
    r: &mut Running,
    entities: Vec<semantics::Entity>,
) -> Result<Supervised, RunError> {
    for stage in [Stage::Masks, Stage::Openings, Stage::Associate, Stage::Fuse] {
        r.st.discard(stage)?;
    }
    Ok(Supervised {
        raycast: r.st.dir(Stage::Raycast),
        mesh: r.st.dir(Stage::Citymodel).join("mesh.ply"),
        maps: LabelMaps::City(r.st.dir(Stage::Raycast)),
        labels: LabelTable::city(&entities, &classes::table(&entities))?,
        entities,
        upstream: vec![Stage::Citymodel, Stage::Raycast],
        masks: None,
        warnings: Vec::new(),
        choices: Vec::new(),
    })
}

/// The options of the masks, openings and associate stages with their pixel units at the
/// training views' resolution (`1/s`, [`RunOptions::train_scale`]), so that a threshold means
/// the same piece of the scene at any work resolution: areas in pixels divide by `s²` (masks'
/// `bias_min_px`, openings' `min_px`, the association's `min_mass` in pixels' worth of α·T),
/// lengths by `s` (masks' `surface_radius_px` and `open_px`, openings' `guard_px`), rounded up
/// and never below 1 where the full-resolution value is ≥ 1; at `s = 1` they are unchanged.
fn in_work_pixels(opts: &RunOptions) -> (MasksOptions, OpeningsOptions, AssociateOptions) {
    let s = opts.train_scale.max(1) as usize;
    let length = |v: usize| if v == 0 { 0 } else { v.div_ceil(s) };
    let area = |v: usize| if v == 0 { 0 } else { v.div_ceil(s * s) };
    let mut masks = opts.masks.clone();
    masks.surface_radius_px = length(masks.surface_radius_px);
    masks.bias_min_px = area(masks.bias_min_px);
    masks.open_px = length(masks.open_px);
    let mut openings = opts.openings;
    openings.guard_px = length(openings.guard_px);
    openings.min_px = area(openings.min_px);
    let mut associate = opts.associate;
    associate.weighted.min_mass /= (s * s) as f32;
    (masks, openings, associate)
}

/// Steps 4–6: masks → associate → fuse: the fused supervision (paper §3.2), training views only.
fn fused_supervision(
    r: &mut Running,
    cache: &Cache,
    entities: Vec<semantics::Entity>,
    scale: f64,
    srs_name: Option<String>,
    opts: &RunOptions,
) -> Result<Supervised, RunError> {
    let (scene, train) = (&r.scene, &r.split.train);
    let rc_dir = r.st.dir(Stage::Raycast);
    let (masks_opts, openings_opts, associate_opts) = in_work_pixels(opts);
    // The scene's SAM lists and features of the training views (their digests decide
    // whether the mask stages rerun).
    let mut inputs: Vec<PathBuf> = Vec::new();
    for v in train {
        let stem = v.stem();
        inputs.extend(scene.sam_file(&stem));
        inputs.extend(scene.feature_file(&stem));
    }
    inputs.extend(scene.prompts_file());
    let features = scene.features.clone();
    let ms: MasksSummary = r.st.stage(
        Stage::Masks,
        &masks_opts,
        &inputs,
        &[Stage::Citymodel, Stage::Raycast, Stage::Render],
        |dir| {
            Ok::<_, RunError>(masks::run(
                &masks::MasksInputs {
                    scene,
                    views: train,
                    raycast: &rc_dir,
                    cache: Some(cache),
                    alignment_scale: scale,
                },
                &masks_opts,
                dir,
            )?)
        },
    )?;
    let masks_dir = r.st.dir(Stage::Masks);
    // The scene's SAM lists, when the masks stage filtered them (not for the mask-free
    // source): view support of small groups and snapping read them.
    let sam = scene
        .masks
        .as_deref()
        .filter(|_| ms.source == masks::Source::Sam);
    // Openings the images show but the model lacks (docs/completeness.md); with any added,
    // the completed model is raycast again and everything downstream uses it.
    let cm_dir = r.st.dir(Stage::Citymodel);
    let ro = raycast::RaycastOptions {
        tau: opts.tau_m * scale,
        single_pass: opts.single_pass,
    };
    let all_views = &r.views;
    let os: OpeningsSummary = r.st.stage(
        Stage::Openings,
        &(openings_opts, ro),
        &inputs,
        &[
            Stage::Citymodel,
            Stage::Raycast,
            Stage::Render,
            Stage::Masks,
        ],
        |dir| {
            let mesh = crate::mesh::TriMesh::read_ply(&cm_dir.join("mesh.ply"))?;
            let alignment = Alignment::read(&cm_dir.join("alignment.json"))?;
            // The geometric cue's Gaussian centres (the cache was built for this PLY), read
            // only for a cache without the median-depth plane.
            let positions = if openings_opts.cues.geometry() && !cache.summary.median_depth {
                let (g, _) = crate::splat::read_ply(&scene.ply, &crate::splat::ReadOptions::KEEP)?;
                if g.len() != cache.summary.gaussians {
                    return Err(RunError::Refused(format!(
                        "{}: {} Gaussians, but the cache {} was built for {}",
                        scene.ply.display(),
                        g.len(),
                        cache.dir.display(),
                        cache.summary.gaussians
                    )));
                }
                Some(g.positions)
            } else {
                None
            };
            let out = openings::run(
                &openings::OpeningsInputs {
                    views: train,
                    raycast: &rc_dir,
                    masks: &masks_dir,
                    sam,
                    entities: &entities,
                    mesh: &mesh,
                    alignment: &alignment,
                    srs_name,
                    geometry: openings_opts.cues.geometry().then_some(openings::Geometry {
                        cache,
                        positions: positions.as_deref(),
                    }),
                },
                &openings_opts,
            )?;
            openings::write(&out, dir)?;
            if let Some((e, m)) = &out.completed {
                let rdir = dir.join("raycast");
                fsutil::create_dir(&rdir)?;
                semantics::check_mesh_labels(&dir.join("mesh.ply"), m, e)?;
                let _rc: RaycastSummary =
                    raycast::run(m, all_views, &ro, raycast::Overlays::Off, &rdir)?;
            }
            Ok::<_, RunError>(out.summary)
        },
    )?;
    let od = r.st.dir(Stage::Openings);
    let (entities, rc_dir, mesh) = if os.added > 0 {
        (
            semantics::read(&od.join("semantics.json"))?,
            od.join("raycast"),
            od.join("mesh.ply"),
        )
    } else {
        (
            entities,
            rc_dir,
            r.st.dir(Stage::Citymodel).join("mesh.ply"),
        )
    };
    let asum: AssociateSummary = r.st.stage(
        Stage::Associate,
        &associate_opts,
        &inputs,
        &[Stage::Masks, Stage::Render],
        |dir| {
            Ok::<_, RunError>(associate::run(
                &associate::AssociateInputs {
                    views: train,
                    masks: &masks_dir,
                    features: features.as_deref(),
                    sam,
                    cache,
                    ply: &scene.ply,
                    scale,
                },
                &associate_opts,
                dir,
            )?)
        },
    )?;
    let as_dir = r.st.dir(Stage::Associate);
    let mut fo = opts.fuse;
    fo.snap &= sam.is_some();
    let _fs: FuseSummary = r.st.stage(
        Stage::Fuse,
        &fo,
        &inputs,
        &[
            Stage::Citymodel,
            Stage::Raycast,
            Stage::Masks,
            Stage::Openings,
            Stage::Associate,
        ],
        |dir| {
            Ok::<_, RunError>(fuse::run(
                &fuse::FuseInputs {
                    views: train,
                    associate: &as_dir,
                    raycast: &rc_dir,
                    entities: &entities,
                    sam,
                    features: features.as_deref(),
                    kept: Some(&masks_dir),
                },
                &fo,
                dir,
            )?)
        },
    )?;
    let fuse_dir = r.st.dir(Stage::Fuse);
    let mut warnings = ms.warnings.clone();
    warnings.extend(os.warnings.iter().cloned());
    warnings.extend(asum.warnings.iter().cloned());
    let choices = asum
        .calibration
        .iter()
        .map(|c| format!("associate: τ_sim = {} ({}): {}", c.tau_sim, c.mode, c.why))
        .collect();
    Ok(Supervised {
        entities,
        raycast: rc_dir,
        mesh,
        labels: LabelTable::read(&fuse_dir.join("labels.json"))?,
        maps: LabelMaps::Fused(fuse_dir),
        upstream: vec![Stage::Citymodel, Stage::Openings, Stage::Fuse],
        masks: Some(ms),
        warnings,
        choices,
    })
}

/// Steps 7–8: lift (the vote over the training views) and, in mode learned, train (identity codes
/// + classifier, starting from the vote); returns the folder of the mode's predictions.
fn vote_steps(
    r: &mut Running,
    cache: &Cache,
    sup: &Supervised,
    scale: f64,
    opts: &RunOptions,
) -> Result<PathBuf, RunError> {
    let mut upstream = sup.upstream.clone();
    upstream.push(Stage::Render);
    // The depth gate of city votes reads the raycast's depth maps.
    if !upstream.contains(&Stage::Raycast) {
        upstream.push(Stage::Raycast);
    }
    let ply = r.scene.ply.clone();
    let raycast = sup.raycast.clone();
    let entities = &sup.entities;
    let inputs = VoteInputs {
        city_depth: Some((&raycast, scale)),
        city_mesh: Some((&sup.mesh, scale)),
        ply: &ply,
        cache,
        train: &r.split.train,
        test: &r.split.test,
        maps: &sup.maps,
        labels: &sup.labels,
        entities,
    };
    // The split is part of each labelling stage's fingerprint: the test views' names.
    let test_views = r.split.test_stems();
    let lift_opts = (opts.lift, &test_views);
    let _lift: LiftSummary = r.st.stage(
        Stage::Lift,
        &lift_opts,
        std::slice::from_ref(&ply),
        &upstream,
        |dir| Ok::<_, RunError>(lift::run(&inputs, &opts.lift, dir)?),
    )?;
    match opts.mode {
        Mode::Learned => {
            let train_opts = (opts.train, &test_views);
            let _t: TrainSummary = r.st.stage(
                Stage::Train,
                &train_opts,
                std::slice::from_ref(&ply),
                &upstream,
                |dir| Ok::<_, RunError>(train::run(&inputs, &opts.train, dir)?),
            )?;
        }
        Mode::Vote => r.st.discard(Stage::Train)?,
    }
    Ok(r.st.dir(opts.mode.stage()))
}

/// Step 9: eval on the test views, when the scene has ground truth: the class maps and the paper's
/// query-driven evaluation next to them.
fn eval_step(
    r: &mut Running,
    cache: &Cache,
    pred_dir: &Path,
    out: &Path,
    opts: &RunOptions,
) -> Result<Option<EvalSummary>, RunError> {
    let Some(gt) = &r.scene.gt else {
        return Ok(None);
    };
    let stems = r.split.test_stems();
    if stems.is_empty() {
        // --test-every 0: nothing held out to evaluate (warned before the stages).
        return Ok(None);
    }
    let inputs: Vec<PathBuf> = stems
        .iter()
        .map(|s| crate::idmap::class_file(gt, s))
        .filter(|p| p.is_file())
        .collect();
    let mode = opts.mode.name();
    let scene_root = &r.scene.root;
    let e: EvalSummary = r.st.stage(
        Stage::Eval,
        &(mode, &stems),
        &inputs,
        &[opts.mode.stage()],
        |dir| {
            let (mut e, _) = crate::eval::run_for(pred_dir, gt, dir, Some(&stems), Some(mode))?;
            let sr = crate::selection::SemanticRun::open(out, scene_root, Some(opts.mode))?;
            let bq = crate::eval::by_query::evaluate(
                &sr,
                cache,
                gt,
                &stems,
                Default::default(),
                Default::default(),
            )?;
            fsutil::write_json(&dir.join("metrics_by_query.json"), &bq)?;
            e.by_query_tables = Some(bq.tables);
            crate::layout::Summary::write(&e, dir)?;
            Ok::<_, RunError>(e)
        },
    )?;
    Ok(Some(e))
}

/// The report (rewritten every time: it lists what this invocation resumed), then the run's
/// `summary.json` (last).
fn finish(
    r: Running,
    out: &Path,
    opts: &RunOptions,
    pred_dir: &Path,
    eval: Option<EvalSummary>,
    sup: Supervised,
    cache: &Cache,
) -> Result<RunSummary, RunError> {
    let mut warnings = r.check_warnings.clone();
    warnings.extend(sup.warnings);
    let semantics = crate::selection::SemanticRun::open(out, &r.scene.root, Some(opts.mode))?;
    let ply = pred_dir.join("semantic.ply");
    let command = command_line();
    // The views the report shows: the test views, or without any a few training views (their
    // class colours).
    let shown: Vec<View> = if r.split.test.is_empty() {
        let n = r.split.train.len();
        let k = n.min(4);
        (0..k).map(|i| r.split.train[i * n / k].clone()).collect()
    } else {
        r.split.test.clone()
    };
    let report = report::write(&report::ReportInputs {
        scene: &r.scene,
        out,
        views: &shown,
        predicted: !r.split.test.is_empty(),
        predictions: pred_dir,
        stages: &r.st.reports,
        eval: eval.as_ref(),
        command: &command,
        semantic_ply: ply.is_file().then_some(ply.as_path()),
        semantics: Some(&semantics),
        masks: sup.masks.as_ref(),
        warnings: &warnings,
        choices: &sup.choices,
        cache,
    })?;
    let summary = RunSummary {
        scene: r.scene.root.clone(),
        options: opts.clone(),
        stages: r.st.reports.clone(),
        test_views: r.split.test_stems(),
        eval,
        report,
        warnings,
    };
    fsutil::write_json(&out.join("summary.json"), &summary)?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixel_thresholds_follow_the_work_resolution() {
        let mut opts = RunOptions::default();
        opts.masks.surface_radius_px = 5;
        opts.masks.bias_min_px = 64;
        opts.masks.open_px = 0;
        opts.openings.guard_px = 2;
        opts.openings.min_px = 12;
        opts.associate.weighted.min_mass = 0.9;
        let at = |s: u32| {
            let (m, o, a) = in_work_pixels(&RunOptions {
                train_scale: s,
                ..opts.clone()
            });
            (
                m.surface_radius_px,
                m.bias_min_px,
                m.open_px,
                o.guard_px,
                o.min_px,
                a.weighted.min_mass,
            )
        };
        // By hand: lengths ⌈v/s⌉, areas ⌈v/s²⌉, a zero stays zero, the mass divided by s².
        assert_eq!(at(1), (5, 64, 0, 2, 12, 0.9));
        assert_eq!(at(2), (3, 16, 0, 1, 3, 0.225));
        assert_eq!(at(3), (2, 8, 0, 1, 2, 0.9 / 9.0));
        assert_eq!(at(8), (1, 1, 0, 1, 1, 0.9 / 64.0));
    }
}
