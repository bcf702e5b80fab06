//! The `run` stage: a scene folder through every stage into a run folder `R` (DESIGN.md,
//! "Wave 2 contract"): [`R/align`] → `R/citymodel` → `R/raycast` → `R/render` (the contributions
//! cache) → `R/masks` → `R/associate` → `R/fuse` → `R/lift` (the vote) → [`R/train`] → `R/eval`
//! (when the scene has `gt/`), `R/report.html` and `R/run.json`. With `--supervision city` the
//! mask stages are skipped and the vote reads `M_city` alone (paper §3.1).
//!
//! Each stage is a library function from typed inputs to a typed summary; this module only wires
//! them: it passes paths and typed summaries, never reads a stage's JSON by key. The run store
//! ([`store`]) decides what is resumed and makes every stage folder appear atomically.
pub mod store;
pub mod report;

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::semantics;
use crate::associate::{self, AssociateOptions, AssociateSummary};
use crate::camera::View;
use crate::alignment::Alignment;
use crate::citymodel::{self, CitymodelSummary};
use crate::eval::EvalSummary;
use crate::fuse::{self, FuseOptions, FuseSummary};
use crate::labels::LabelTable;
use crate::idmap::LabelMaps;
use crate::lift::{self, LiftOptions, LiftSummary};
use crate::masks::{self, MasksOptions, MasksSummary};
pub use crate::layout::Mode;
use crate::raycast::{self, RaycastSummary};
use crate::cache::{self, Cache, CacheOptions, CacheSummary};
use crate::scene::{Scene, SceneError, Split};
use crate::train::{self, TrainOptions, TrainSummary};
use crate::render;
use crate::{classes, colmap, fsutil};
pub use store::StageReport;
use store::{Store, StoreError};

/// The stage folders of a run, in order.
pub const STAGES: [&str; 10] = [
    "align",
    "citymodel",
    "raycast",
    "render",
    "masks",
    "associate",
    "fuse",
    "lift",
    "train",
    "eval",
];

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
    #[error("{0}")]
    Refused(String),
    #[error(transparent)]
    Store(#[from] StoreError),
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
    /// Contribution-list length of the cache (0 = complete lists).
    pub top_k: usize,
    pub lift: LiftOptions,
    /// Where the labels come from (city model alone, or fused with the masks).
    pub supervision: Supervision,
    pub masks: MasksOptions,
    pub associate: AssociateOptions,
    pub fuse: FuseOptions,
    /// The per-Gaussian labels that are evaluated and queried: the vote, or identity learning
    /// (the `train` stage, which starts from the vote).
    pub mode: Mode,
    pub train: TrainOptions,
    /// Every `test_every`-th view (by name) is a test view; 0 = none.
    pub test_every: usize,
    /// Run without `citymodel/alignment.json` (the CityGML coordinates minus a local origin).
    pub local_origin: bool,
    /// Refine the alignment from the 3DGS scene first (`R/align/`, `align --refine`); every
    /// later stage uses the refined transform.
    pub refine_alignment: bool,
    pub refine: crate::refine::RefineOptions,
    /// Rerun every stage even when its output is complete.
    pub force: bool,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            tau_m: 0.5,
            single_pass: false,
            top_k: 16,
            lift: LiftOptions::default(),
            supervision: Supervision::Fused,
            masks: MasksOptions::default(),
            associate: AssociateOptions::default(),
            fuse: FuseOptions::default(),
            mode: Mode::Vote,
            train: TrainOptions::default(),
            test_every: 8,
            local_origin: false,
            refine_alignment: false,
            refine: crate::refine::RefineOptions::default(),
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

/// Runs (or resumes) every stage of the scene folder `scene_dir` into `out`.
pub fn run(scene_dir: &Path, out: &Path, opts: &RunOptions) -> Result<RunSummary, RunError> {
    // Validate before anything is written.
    store::check_out_dir(scene_dir, out, &STAGES).map_err(RunError::Refused)?;
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
            opts.tau_m
        )));
    }
    let views = colmap::read_model(&scene.sparse)?;
    let split = Split::new(views.clone(), opts.test_every);
    if split.train.is_empty() {
        return Err(RunError::Refused(
            "no training views: every view is a test view (--test-every 1?)".into(),
        ));
    }
    if scene.gt.is_some() && split.test.is_empty() {
        return Err(RunError::Refused(
            "the scene has gt/ but there are no test views to evaluate (--test-every 0?)".into(),
        ));
    }
    let mut st = Store::open(
        out,
        &scene.root,
        serde_json::to_value(opts).unwrap_or_default(),
        opts.force,
    )?;
    // The run's own completion markers are written last; a run that fails part-way must not
    // leave the previous run's summary and report looking like this one's.
    for f in ["summary.json", "report.html"] {
        let p = out.join(f);
        if p.exists() {
            std::fs::remove_file(&p).map_err(|e| {
                RunError::Refused(format!("cannot remove the old {}: {e}", p.display()))
            })?;
        }
    }
    let sparse_files = files_in(&scene.sparse);

    // 0. align --refine (optional): the alignment every later stage uses
    let alignment_file = if opts.refine_alignment {
        let mut ins = scene.gml.clone();
        ins.extend(scene.alignment.clone());
        ins.push(scene.ply.clone());
        ins.extend(sparse_files.iter().cloned());
        let _r: crate::refine::RefineSummary =
            st.stage("align", &opts.refine, &ins, &[], |dir| {
                let t = std::time::Instant::now();
                let initial = scene
                    .alignment
                    .as_deref()
                    .map(Alignment::read)
                    .transpose()?;
                let city = citymodel::run(&scene.gml, &citymodel::Options { alignment: initial })?;
                let centres: Vec<glam::DVec3> =
                    views.iter().map(|v| v.camera.pose.center()).collect();
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
        Some(st.dir("align").join("alignment.json"))
    } else {
        scene.alignment.clone()
    };
    let upstream_cm: &[&str] = if opts.refine_alignment {
        &["align"]
    } else {
        &[]
    };

    // 1. citymodel
    let mut inputs = scene.gml.clone();
    inputs.extend(alignment_file.clone());
    let cm: CitymodelSummary = st.stage(
        "citymodel",
        &opts.local_origin,
        &inputs,
        upstream_cm,
        |dir| {
            let alignment = alignment_file.as_deref().map(Alignment::read).transpose()?;
            let o = citymodel::run(&scene.gml, &citymodel::Options { alignment })?;
            citymodel::write(&o, dir)?;
            Ok::<_, RunError>(o.summary)
        },
    )?;
    let cm_dir = st.dir("citymodel");

    // 2. raycast (every view)
    let ro = raycast::RaycastOptions {
        tau: opts.tau_m * cm.alignment.scale,
        single_pass: opts.single_pass,
    };
    let mut inputs = sparse_files.clone();
    if let Some(d) = &scene.images {
        inputs.extend(files_in(d));
    }
    let _rc: RaycastSummary = st.stage("raycast", &ro, &inputs, &["citymodel"], |dir| {
        let mesh_path = cm_dir.join("mesh.ply");
        let mesh = crate::mesh::TriMesh::read_ply(&mesh_path)?;
        let entities = semantics::read(&cm_dir.join("semantics.json"))?;
        semantics::check_mesh_labels(&mesh_path, &mesh, &entities)?;
        Ok::<_, RunError>(raycast::run(
            &mesh,
            &views,
            &ro,
            scene.images.as_deref(),
            dir,
        )?)
    })?;
    let rc_dir = st.dir("raycast");

    // 3. render: the contributions cache of every view
    let co = CacheOptions { top_k: opts.top_k };
    let mut inputs = vec![scene.ply.clone()];
    inputs.extend(sparse_files.iter().cloned());
    let _cs: CacheSummary = st.stage("render", &co, &inputs, &[], |dir| {
        let (g, _) = crate::splat::read_ply(&scene.ply, &Default::default())?;
        let prepared = crate::render::PreparedScene::new(&g)?;
        Ok::<_, RunError>(render::cache::build(&prepared, &views, &co, dir)?)
    })?;
    let cache = Cache::open(&st.dir("render"))?;

    let entities = semantics::read(&cm_dir.join("semantics.json"))?;

    // 4–6. masks → associate → fuse: the fused supervision (paper §3.2), training views only
    let mut masks_summary = None;
    let (maps, labels, label_stages): (LabelMaps, LabelTable, Vec<&str>) = match opts.supervision {
        Supervision::City => {
            for stage in ["masks", "associate", "fuse"] {
                st.discard(stage)?;
            }
            (
                LabelMaps::City(rc_dir.clone()),
                LabelTable::city(&entities, &classes::table(&entities))?,
                vec!["citymodel", "raycast"],
            )
        }
        Supervision::Fused => {
            let scale = cm.alignment.scale;
            // The scene's SAM lists and features of the training views (their digests decide
            // whether the mask stages rerun).
            let mut inputs: Vec<PathBuf> = Vec::new();
            for v in &split.train {
                let stem = v.stem();
                inputs.extend(scene.sam_file(&stem));
                inputs.extend(scene.feature_file(&stem));
            }
            inputs.extend(scene.prompts_file());
            let features = scene.features.clone();
            let ms: MasksSummary = st.stage(
                "masks",
                &opts.masks,
                &inputs,
                &["citymodel", "raycast", "render"],
                |dir| {
                    Ok::<_, RunError>(masks::run(
                        &masks::MasksInputs {
                            scene: &scene,
                            views: &split.train,
                            raycast: &rc_dir,
                            cache: Some(&cache),
                            alignment_scale: scale,
                        },
                        &opts.masks,
                        dir,
                    )?)
                },
            )?;
            let masks_dir = st.dir("masks");
            // The scene's SAM lists, when the masks stage filtered them (not for the mask-free
            // source): view support of small groups and snapping read them.
            let sam = scene
                .masks
                .as_deref()
                .filter(|_| ms.source == masks::Source::Sam);
            let _as: AssociateSummary = st.stage(
                "associate",
                &opts.associate,
                &inputs,
                &["masks", "render"],
                |dir| {
                    Ok::<_, RunError>(associate::run(
                        &associate::AssociateInputs {
                            views: &split.train,
                            masks: &masks_dir,
                            features: features.as_deref(),
                            sam,
                            cache: &cache,
                            ply: &scene.ply,
                            scale,
                        },
                        &opts.associate,
                        dir,
                    )?)
                },
            )?;
            let as_dir = st.dir("associate");
            let mut fo = opts.fuse;
            fo.snap &= sam.is_some();
            let _fs: FuseSummary = st.stage(
                "fuse",
                &fo,
                &inputs,
                &["citymodel", "raycast", "masks", "associate"],
                |dir| {
                    Ok::<_, RunError>(fuse::run(
                        &fuse::FuseInputs {
                            views: &split.train,
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
            let fuse_dir = st.dir("fuse");
            masks_summary = Some(ms);
            (
                LabelMaps::Fused(fuse_dir.clone()),
                LabelTable::read(&fuse_dir.join("labels.json"))?,
                vec!["citymodel", "fuse"],
            )
        }
    };

    // 7. lift: the vote of the labels over the training views
    let lift_opts = (opts.lift, opts.test_every);
    let mut upstream = label_stages.clone();
    upstream.push("render");
    let inputs = VoteInputs {
        ply: &scene.ply,
        cache: &cache,
        split: &split,
        maps: &maps,
        labels: &labels,
        entities: &entities,
    };
    let _lift: LiftSummary = st.stage(
        "lift",
        &lift_opts,
        std::slice::from_ref(&scene.ply),
        &upstream,
        |dir| Ok::<_, RunError>(lift::run(&inputs.get(), &opts.lift, dir)?),
    )?;

    // 8. train (mode learned): identity codes + classifier, starting from the vote
    if opts.mode == Mode::Learned {
        let train_opts = (opts.train, opts.test_every);
        let _t: TrainSummary = st.stage(
            "train",
            &train_opts,
            std::slice::from_ref(&scene.ply),
            &upstream,
            |dir| Ok::<_, RunError>(train::run(&inputs.get(), &opts.train, dir)?),
        )?;
    }
    if opts.mode == Mode::Vote {
        st.discard("train")?;
    }
    let pred_dir = st.dir(opts.mode.dir());

    // 9. eval on the test views, when the scene has ground truth
    let mut eval_summary = None;
    if let Some(gt) = &scene.gt {
        let stems = split.test_stems();
        let inputs: Vec<PathBuf> = stems
            .iter()
            .map(|s| gt.join(format!("{s}.class.npy")))
            .filter(|p| p.is_file())
            .collect();
        let mode = match opts.mode {
            Mode::Vote => "vote",
            Mode::Learned => "learned",
        };
        let e: EvalSummary = st.stage(
            "eval",
            &(mode, &stems),
            &inputs,
            &[opts.mode.dir()],
            |dir| {
                let (mut e, _) =
                    crate::eval::run_for(&pred_dir, gt, dir, Some(&stems), Some(mode))?;
                // The paper's query-driven evaluation, next to the class maps'.
                let sr = crate::selection::SemanticRun::open(out, &scene.root, Some(opts.mode))?;
                let bq = crate::eval::by_query::evaluate(
                    &sr,
                    &cache,
                    gt,
                    &stems,
                    Default::default(),
                    Default::default(),
                )?;
                fsutil::write_json(&dir.join("metrics_by_query.json"), &bq)?;
                e.by_query_tables = Some(bq.tables);
                fsutil::write_json(&dir.join("summary.json"), &e)?;
                Ok::<_, RunError>(e)
            },
        )?;
        eval_summary = Some(e);
    }

    // Report (rewritten every time: it lists what this invocation resumed).
    let report = report::write(&report::ReportInputs {
        scene: &scene,
        out,
        views: &split.test,
        predictions: &pred_dir,
        stages: &st.reports,
        eval: eval_summary.as_ref(),
        masks: masks_summary.as_ref(),
    })?;
    let summary = RunSummary {
        scene: scene.root.clone(),
        options: opts.clone(),
        stages: st.reports.clone(),
        test_views: split.test_stems(),
        eval: eval_summary,
        report,
    };
    fsutil::write_json(&out.join("summary.json"), &summary)?;
    Ok(summary)
}

/// The inputs the vote and the training share (both take [`lift::LiftInputs`]).
struct VoteInputs<'a> {
    ply: &'a Path,
    cache: &'a Cache,
    split: &'a Split,
    maps: &'a LabelMaps,
    labels: &'a LabelTable,
    entities: &'a [semantics::Entity],
}

impl VoteInputs<'_> {
    fn get(&self) -> lift::LiftInputs<'_> {
        lift::LiftInputs {
            ply: self.ply,
            cache: self.cache,
            train: &self.split.train,
            test: &self.split.test,
            maps: self.maps,
            labels: self.labels,
            entities: self.entities,
        }
    }
}

/// The views of `names` in `views` (for callers that hold stems).
pub fn views_named<'a>(views: &'a [View], stems: &[String]) -> Vec<&'a View> {
    views.iter().filter(|v| stems.contains(&v.stem())).collect()
}
