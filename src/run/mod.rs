//! The `run` stage: a whole scene folder through citymodel → raycast → lift (→ eval when the
//! scene has `gt/`), one output folder per stage. A stage whose folder holds a `stage.json`
//! with the same fingerprint (its options and the size/mtime of its inputs, chained through
//! the upstream stages' fingerprints) is complete and valid, and is resumed rather than rerun.
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use crate::citymodel::{self, Alignment};
use crate::lift::{self, LiftConfig, LiftOptions};
use crate::{colmap, fsutil, raycast};

/// Errors of the run stage.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error("scene {scene}: {why}")]
    Scene { scene: PathBuf, why: String },
    #[error(transparent)]
    CityModel(#[from] citymodel::CityModelError),
    #[error(transparent)]
    Align(#[from] citymodel::AlignError),
    #[error(transparent)]
    Colmap(#[from] colmap::ColmapError),
    #[error(transparent)]
    Raycast(#[from] raycast::RaycastError),
    #[error(transparent)]
    Lift(#[from] lift::LiftError),
    #[error(transparent)]
    Eval(#[from] crate::eval::EvalError),
    #[error(transparent)]
    Fs(#[from] fsutil::FsError),
    #[error(transparent)]
    Mesh(#[from] crate::mesh::MeshError),
}

/// Options of a run.
#[derive(Debug, Clone, Serialize)]
pub struct RunOptions {
    /// Part-pass depth tolerance in metres.
    pub tau_m: f64,
    pub single_pass: bool,
    pub lift: LiftOptions,
    pub test_every: usize,
    /// Rerun every stage even when its output is complete.
    pub force: bool,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            tau_m: 0.5,
            single_pass: false,
            lift: LiftOptions::default(),
            test_every: 8,
            force: false,
        }
    }
}

/// What happened to one stage.
#[derive(Debug, Clone, Serialize)]
pub struct StageReport {
    pub stage: String,
    pub resumed: bool,
    pub seconds: f64,
    pub out: PathBuf,
}

/// The scene folder's parts (DESIGN.md).
#[derive(Debug, Clone)]
pub struct Scene {
    pub root: PathBuf,
    pub gml: Vec<PathBuf>,
    pub alignment: Option<PathBuf>,
    pub sparse: PathBuf,
    pub images: Option<PathBuf>,
    pub ply: PathBuf,
    pub gt: Option<PathBuf>,
}

impl Scene {
    /// Finds and checks the parts of a scene folder.
    pub fn open(root: &Path) -> Result<Scene, RunError> {
        let bad = |why: String| RunError::Scene {
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
                p.extension()
                    .is_some_and(|x| x.eq_ignore_ascii_case("gml") || x.eq_ignore_ascii_case("xml"))
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
        let images = Some(root.join("images")).filter(|p| p.is_dir());
        let gt = Some(root.join("gt")).filter(|p| p.is_dir());
        Ok(Scene {
            root: root.to_path_buf(),
            gml,
            alignment,
            sparse,
            images,
            ply,
            gt,
        })
    }
}

/// FNV-1a 64 of a string.
fn fnv(s: &str) -> String {
    let mut h: u64 = 0xcbf29ce484222325;
    for b in s.bytes() {
        h ^= b as u64;
        h = h.wrapping_mul(0x100000001b3);
    }
    format!("{h:016x}")
}

/// Fingerprint of a stage: its name, options and the size/mtime of each input path (files,
/// or every file directly in an input directory), plus upstream fingerprints.
fn fingerprint(
    stage: &str,
    options: &serde_json::Value,
    inputs: &[&Path],
    upstream: &[&str],
) -> String {
    let mut s = format!("{stage}\n{options}\n");
    for p in inputs {
        let mut files = vec![p.to_path_buf()];
        if p.is_dir() {
            files = std::fs::read_dir(p)
                .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
                .unwrap_or_default();
            files.sort();
        }
        for f in files {
            let m = std::fs::metadata(&f).ok();
            let (len, mtime) = m.map_or((0, 0), |m| {
                (
                    m.len(),
                    m.modified()
                        .ok()
                        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                        .map_or(0, |d| d.as_nanos()),
                )
            });
            s.push_str(&format!("{}\t{len}\t{mtime}\n", f.display()));
        }
    }
    for u in upstream {
        s.push_str(u);
        s.push('\n');
    }
    fnv(&s)
}

fn is_done(dir: &Path, fp: &str) -> bool {
    std::fs::read(dir.join("stage.json"))
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .is_some_and(|v| v["fingerprint"] == fp && dir.join("summary.json").is_file())
}

fn mark_done(dir: &Path, stage: &str, fp: &str) -> Result<(), RunError> {
    fsutil::write_json(
        &dir.join("stage.json"),
        &serde_json::json!({ "stage": stage, "fingerprint": fp }),
    )?;
    Ok(())
}

/// Runs (or resumes) every stage of a scene into `out`; returns the per-stage reports and,
/// when the scene has ground truth, the metrics.
pub fn run(
    scene_dir: &Path,
    out: &Path,
    opts: &RunOptions,
) -> Result<(Vec<StageReport>, Option<serde_json::Value>), RunError> {
    let scene = Scene::open(scene_dir)?;
    fsutil::create_dir(out)?;
    let mut reports = Vec::new();
    let mut stage = |name: &str,
                     fp: &str,
                     body: &mut dyn FnMut(&Path) -> Result<(), RunError>|
     -> Result<(), RunError> {
        let dir = out.join(name);
        let t = Instant::now();
        let resumed = !opts.force && is_done(&dir, fp);
        if !resumed {
            fsutil::create_dir(&dir)?;
            let _ = std::fs::remove_file(dir.join("stage.json"));
            body(&dir)?;
            mark_done(&dir, name, fp)?;
        }
        reports.push(StageReport {
            stage: name.into(),
            resumed,
            seconds: t.elapsed().as_secs_f64(),
            out: dir,
        });
        Ok(())
    };

    // 1. citymodel
    let mut inputs: Vec<&Path> = scene.gml.iter().map(|p| p.as_path()).collect();
    if let Some(a) = &scene.alignment {
        inputs.push(a);
    }
    let fp_cm = fingerprint("citymodel", &serde_json::json!({}), &inputs, &[]);
    stage("citymodel", &fp_cm, &mut |dir| {
        let alignment = scene
            .alignment
            .as_deref()
            .map(Alignment::read)
            .transpose()?;
        let o = citymodel::run(&scene.gml, &citymodel::Options { alignment })?;
        citymodel::write(&o, dir)?;
        Ok(())
    })?;
    let cm_dir = out.join("citymodel");

    // 2. raycast (all views)
    let rc_opts = serde_json::json!({ "tau_m": opts.tau_m, "single_pass": opts.single_pass });
    let fp_rc = fingerprint("raycast", &rc_opts, &[&scene.sparse], &[&fp_cm]);
    stage("raycast", &fp_rc, &mut |dir| {
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(cm_dir.join("summary.json")).map_err(|e| {
                RunError::Scene {
                    scene: scene.root.clone(),
                    why: format!("{}: {e}", cm_dir.join("summary.json").display()),
                }
            })?)
            .map_err(|e| RunError::Scene {
                scene: scene.root.clone(),
                why: format!("citymodel summary.json: {e}"),
            })?;
        let scale = summary["alignment"]["scale"].as_f64().unwrap_or(1.0);
        let mesh = crate::mesh::TriMesh::read_ply(&cm_dir.join("mesh.ply"))?;
        let views = colmap::read_model(&scene.sparse)?;
        let ro = raycast::RaycastOptions {
            tau: opts.tau_m * scale,
            single_pass: opts.single_pass,
        };
        let s = raycast::run(&mesh, &views, &ro, scene.images.as_deref(), dir)?;
        fsutil::write_json(&dir.join("summary.json"), &s)?;
        Ok(())
    })?;

    // 3. lift
    let lift_opts = serde_json::json!({ "lift": opts.lift, "test_every": opts.test_every });
    let fp_lift = fingerprint("lift", &lift_opts, &[&scene.ply, &scene.sparse], &[&fp_rc]);
    stage("lift", &fp_lift, &mut |dir| {
        lift::run(&LiftConfig {
            ply: scene.ply.clone(),
            colmap: scene.sparse.clone(),
            raycast: out.join("raycast"),
            citymodel: cm_dir.clone(),
            out: dir.to_path_buf(),
            options: opts.lift,
            test_every: opts.test_every,
            predict_k: 16,
        })?;
        Ok(())
    })?;

    // 4. eval on the test views, when the scene has ground truth
    let mut metrics: Option<serde_json::Value> = None;
    if let Some(gt) = &scene.gt {
        let fp_eval = fingerprint("eval", &serde_json::json!({}), &[gt], &[&fp_lift]);
        let stems = lift::test_views(&out.join("lift"));
        if stems.is_empty() {
            return Err(RunError::Scene {
                scene: scene.root.clone(),
                why: "gt/ exists but there are no test views to evaluate (--test-every 0?)".into(),
            });
        }
        stage("eval", &fp_eval, &mut |dir| {
            let (summary, _) = crate::eval::run_for(&out.join("lift"), gt, dir, Some(&stems))?;
            fsutil::write_json(&dir.join("summary.json"), &summary)?;
            Ok(())
        })?;
        metrics = serde_json::from_slice(
            &std::fs::read(out.join("eval/metrics.json")).unwrap_or_default(),
        )
        .ok();
    }
    fsutil::write_json(
        &out.join("summary.json"),
        &serde_json::json!({ "scene": scene.root, "options": opts, "stages": reports, "metrics": metrics.as_ref().map(|m| serde_json::json!({"paper": m["paper"], "dataset": m["dataset"]})) }),
    )?;
    Ok((reports, metrics))
}
