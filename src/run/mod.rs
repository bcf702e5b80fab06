//! The `run` stage: a scene folder through every stage into a run folder `R` (DESIGN.md,
//! "Wave 2 contract"): `R/citymodel` → `R/raycast` → `R/render` (the contributions cache) →
//! `R/lift` → `R/eval` (when the scene has `gt/`), `R/report.html` and `R/run.json`.
//!
//! Each stage is a library function from typed inputs to a typed summary; this module only wires
//! them: it passes paths and typed summaries, never reads a stage's JSON by key. The run store
//! ([`store`]) decides what is resumed and makes every stage folder appear atomically.
pub mod store;

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::camera::View;
use crate::citymodel::{self, Alignment, CitymodelSummary};
use crate::eval::EvalSummary;
use crate::labels::LabelTable;
use crate::lift::{self, LabelMaps, LiftOptions, LiftSummary};
use crate::raycast::{self, RaycastSummary};
use crate::render::cache::{self, Cache, CacheOptions, CacheSummary};
use crate::scene::{Scene, SceneError, Split};
use crate::{classes, colmap, fsutil};
pub use store::StageReport;
use store::{Store, StoreError};

/// The stage folders of a run, in order.
pub const STAGES: [&str; 9] = [
    "align",
    "citymodel",
    "raycast",
    "render",
    "masks",
    "associate",
    "fuse",
    "lift",
    "eval",
];

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
    Align(#[from] citymodel::AlignError),
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
    Report(#[from] crate::report::ReportError),
    #[error(transparent)]
    Refine(#[from] crate::refine::RefineError),
    #[error(transparent)]
    Query(#[from] crate::query::QueryError),
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
    let sparse_files = files_in(&scene.sparse);

    // 0. align --refine (optional): the alignment every later stage uses
    let alignment_file = if opts.refine_alignment {
        let mut ins = scene.gml.clone();
        ins.extend(scene.alignment.clone());
        ins.push(scene.ply.clone());
        ins.extend(sparse_files.iter().cloned());
        let _r: crate::refine::RefineOutput =
            st.stage("align", &opts.refine, &ins, &[], |dir| {
                let initial = scene
                    .alignment
                    .as_deref()
                    .map(Alignment::read)
                    .transpose()?;
                let city = citymodel::run(&scene.gml, &citymodel::Options { alignment: initial })?;
                let (g, _) = crate::splat::read_ply(&scene.ply, &Default::default())?;
                let centres: Vec<glam::DVec3> =
                    views.iter().map(|v| v.camera.pose.center()).collect();
                let out = crate::refine::refine(
                    &crate::refine::RefineInput {
                        mesh: &city.mesh,
                        entities: &city.entities,
                        initial: &city.alignment,
                        gaussians: &g,
                        camera_centres: Some(&centres),
                    },
                    &opts.refine,
                )?;
                fsutil::write_json(&dir.join("alignment.json"), &out.alignment.to_json())?;
                Ok::<_, RunError>(out)
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
        let mesh = crate::mesh::TriMesh::read_ply(&cm_dir.join("mesh.ply"))?;
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
        Ok::<_, RunError>(cache::build(&prepared, &views, &co, dir)?)
    })?;
    let cache = Cache::open(&st.dir("render"))?;

    // 4. lift: the vote of M_city over the training views
    let lift_opts = (opts.lift, opts.test_every);
    let lift_s: LiftSummary = st.stage(
        "lift",
        &lift_opts,
        std::slice::from_ref(&scene.ply),
        &["citymodel", "raycast", "render"],
        |dir| {
            let entities = citymodel::read_semantics(&cm_dir.join("semantics.json"))?;
            let labels = LabelTable::city(&entities, &classes::table(&entities))?;
            Ok::<_, RunError>(lift::run(
                &lift::LiftInputs {
                    ply: &scene.ply,
                    cache: &cache,
                    train: &split.train,
                    test: &split.test,
                    maps: &LabelMaps::City(rc_dir.clone()),
                    labels: &labels,
                    entities: &entities,
                },
                &opts.lift,
                dir,
            )?)
        },
    )?;
    let pred_dir = st.dir("lift");

    // 5. eval on the test views, when the scene has ground truth
    let mut eval_summary = None;
    if let Some(gt) = &scene.gt {
        let stems = split.test_stems();
        let inputs: Vec<PathBuf> = stems
            .iter()
            .map(|s| gt.join(format!("{s}.class.npy")))
            .filter(|p| p.is_file())
            .collect();
        let mode = "vote";
        let e: EvalSummary = st.stage("eval", &(mode, &stems), &inputs, &["lift"], |dir| {
            let (mut e, _) = crate::eval::run_for(&pred_dir, gt, dir, Some(&stems), Some(mode))?;
            // The paper's query-driven evaluation, next to the class maps'.
            let sr =
                crate::query::SemanticRun::open(out, &scene.root, Some(crate::query::Mode::Vote))?;
            let bq = crate::query::evaluate::evaluate(
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
        })?;
        eval_summary = Some(e);
    }
    let _ = lift_s;

    // Report (rewritten every time: it lists what this invocation resumed).
    let report = crate::report::write(&crate::report::ReportInputs {
        scene: &scene,
        out,
        views: &split.test,
        predictions: &pred_dir,
        stages: &st.reports,
        eval: eval_summary.as_ref(),
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

/// The views of `names` in `views` (for callers that hold stems).
pub fn views_named<'a>(views: &'a [View], stems: &[String]) -> Vec<&'a View> {
    views.iter().filter(|v| stems.contains(&v.stem())).collect()
}
