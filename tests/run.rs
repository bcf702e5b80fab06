//! `gs4city run` on a hand-built scene with analytic ground truth (tests/common/wall.rs): the
//! metrics, and the run store's promises — resume, reruns of exactly what depends on a changed,
//! deleted or truncated file, no stale predictions, refusal of a run folder inside the scene.

use crate::common::wall;
use gs4city::run::{RunOptions, RunSummary, run};

fn reruns(s: &RunSummary) -> Vec<&str> {
    s.stages
        .iter()
        .filter(|r| !r.resumed)
        .map(|r| r.stage.dir())
        .collect()
}

/// The default options with 3DGS's split (every 8th view a test view): the hand-built scenes
/// declare no test views (no scene.json), so by default every view would train.
fn eighth() -> RunOptions {
    RunOptions {
        test_every: Some(8),
        ..Default::default()
    }
}

fn miou(s: &RunSummary) -> (Option<f64>, Option<f64>) {
    let e = s.eval.as_ref().expect("gt/ exists: metrics");
    (e.paper["miou"], e.dataset["coarse_iou"])
}

#[test]
fn metrics_against_the_analytic_truth_and_every_stage_in_order() {
    let dir = wall::tmp("run-metrics");
    let (scene, _) = wall::write_scene(&dir.join("scene"), 5);
    let o = RunOptions {
        test_every: Some(4),
        ..Default::default()
    };
    let s = run(&scene, &dir.join("out"), &o).unwrap();
    let names: Vec<&str> = s.stages.iter().map(|r| r.stage.dir()).collect();
    assert_eq!(
        names,
        [
            "citymodel",
            "render",
            "raycast",
            "masks",
            "openings",
            "associate",
            "fuse",
            "lift",
            "eval"
        ]
    );
    assert_eq!(s.test_views, ["v00", "v04"]);
    let e = s.eval.as_ref().unwrap();
    assert_eq!(e.mode.as_deref(), Some("vote"));
    // Coarse building/non-building against the analytic truth, and the fine classes present
    // (wall in both views; the window only in v04: a floater hides it in v00).
    assert!(e.dataset["coarse_iou"].unwrap() > 0.85, "{e:?}");
    assert!(e.paper_iou["wall"].unwrap() > 0.85, "{:?}", e.paper_iou);
    assert!(e.paper_iou["window"].unwrap() > 0.4, "{:?}", e.paper_iou);
    assert!(e.paper_iou["tree"].is_none(), "absent classes are null");
    // The query-driven evaluation (a "building" selection and one per class) agrees with the
    // class maps on this scene to within 2 points.
    assert!(
        e.by_query_tables
            .as_deref()
            .is_some_and(|t| t.contains("Table 1"))
    );
    let bq: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("out/eval/metrics_by_query.json")).unwrap())
            .unwrap();
    let q_iou = bq["metrics"]["dataset"]["coarse"]["iou"].as_f64().unwrap();
    assert!(
        (q_iou - e.dataset["coarse_iou"].unwrap()).abs() < 0.02,
        "{q_iou}"
    );
    // report.html shows the metrics tables and a panel per test view.
    let html = std::fs::read_to_string(&s.report).unwrap();
    assert!(html.contains("Table 1") && html.contains("report/v04.png"));
    // … and the masks stage's overlays (kept masks coloured by rule).
    let overlay = html
        .split("src=\"masks/")
        .nth(1)
        .and_then(|t| t.split('"').next())
        .expect("a masks overlay in the report");
    assert!(dir.join("out/masks").join(overlay).is_file(), "{overlay}");
    assert!(dir.join("out/report/v00.png").is_file());
    crate::report::check_report(&dir.join("out"), "v04");
    // run.json records the version, every option, inputs and outputs with digests.
    let rec: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("out/run.json")).unwrap()).unwrap();
    assert_eq!(rec["version"], env!("CARGO_PKG_VERSION"));
    assert_eq!(rec["options"]["top_k"], gs4city::cache::TOP_K);
    // The default preset's lists (docs/quality.md).
    let opt = |k: &str| rec["options"][k].as_f64().unwrap() as f32;
    assert_eq!(opt("epsilon"), 0.1);
    assert_eq!(opt("t_stop"), 0.2);
    assert_eq!(opt("alpha_min"), 1.0 / 32.0);
    let lift_outputs = rec["stages"]["lift"]["outputs"].as_array().unwrap();
    assert!(
        lift_outputs
            .iter()
            .any(|o| o["path"] == "gaussians.npy" && o["digest"].as_str().unwrap().len() == 16)
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn resume_and_exact_reruns_after_deleting_or_truncating_any_output() {
    let dir = wall::tmp("run-resume");
    let (scene, _) = wall::write_scene(&dir.join("scene"), 5);
    let out = dir.join("out");
    let o = eighth();
    let clean = run(&scene, &out, &o).unwrap();
    let clean_metrics = miou(&clean);
    let again = run(&scene, &out, &o).unwrap();
    assert!(reruns(&again).is_empty(), "{:?}", again.stages);
    // For one output of each stage: delete it, then truncate it; the next run redoes that
    // stage and exactly the stages that read it, and the metrics equal the clean run's.
    // (The wall scene has no masks/: the masks stage uses the mask-free depth source.)
    let cases: [(&str, &str, &[&str]); 8] = [
        (
            "citymodel",
            "mesh.ply",
            &[
                "citymodel",
                "raycast",
                "masks",
                "openings",
                "associate",
                "fuse",
                "lift",
                "eval",
            ],
        ),
        (
            "raycast",
            "v03.ids.npy",
            &[
                "raycast",
                "masks",
                "openings",
                "associate",
                "fuse",
                "lift",
                "eval",
            ],
        ),
        (
            "render",
            "v05.contrib",
            &[
                "render",
                "masks",
                "openings",
                "associate",
                "fuse",
                "lift",
                "eval",
            ],
        ),
        (
            "masks",
            "summary.json",
            &["masks", "openings", "associate", "fuse", "lift", "eval"],
        ),
        (
            "associate",
            "groups.json",
            &["associate", "fuse", "lift", "eval"],
        ),
        ("fuse", "labels.json", &["fuse", "lift", "eval"]),
        ("lift", "v00.class.npy", &["lift", "eval"]),
        ("eval", "metrics.json", &["eval"]),
    ];
    for (stage, file, expected) in cases {
        let path = out.join(stage).join(file);
        std::fs::remove_file(&path).unwrap();
        let s = run(&scene, &out, &o).unwrap();
        assert_eq!(reruns(&s), expected, "deleted {stage}/{file}");
        assert_eq!(miou(&s), clean_metrics);
        let f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
        let len = f.metadata().unwrap().len();
        f.set_len(len / 2).unwrap();
        drop(f);
        let s = run(&scene, &out, &o).unwrap();
        assert_eq!(reruns(&s), expected, "truncated {stage}/{file}");
        assert_eq!(miou(&s), clean_metrics);
    }
    // A run that fails part-way (a damaged PLY) leaves no run summary or report behind that
    // could pass for its own; the next good run restores them.
    let ply = scene.join("point_cloud.ply");
    let good = std::fs::read(&ply).unwrap();
    std::fs::write(&ply, &good[..good.len() / 2]).unwrap();
    assert!(run(&scene, &out, &o).is_err());
    assert!(!out.join("summary.json").exists() && !out.join("report.html").exists());
    std::fs::write(&ply, &good).unwrap();
    let s = run(&scene, &out, &o).unwrap();
    assert!(reruns(&s).is_empty(), "the same PLY again: {:?}", s.stages);
    assert!(out.join("summary.json").is_file() && out.join("report.html").is_file());
    // A changed PLY reruns the cache and everything after it; another τ the raycast onwards.
    let mut bytes = std::fs::read(&ply).unwrap();
    let n = bytes.len();
    bytes[n - 1] ^= 1; // the last byte of the last Gaussian's last rotation value
    std::fs::write(&ply, &bytes).unwrap();
    let s = run(&scene, &out, &o).unwrap();
    assert_eq!(
        reruns(&s),
        [
            "render",
            "masks",
            "openings",
            "associate",
            "fuse",
            "lift",
            "eval"
        ]
    );
    let s = run(
        &scene,
        &out,
        &RunOptions {
            tau_m: 0.3,
            ..o.clone()
        },
    )
    .unwrap();
    assert_eq!(
        reruns(&s),
        [
            "raycast",
            "masks",
            "openings",
            "associate",
            "fuse",
            "lift",
            "eval"
        ]
    );
    // Touching an input without changing it reruns nothing (identity = content digest).
    std::fs::write(&ply, &bytes).unwrap();
    let s = run(
        &scene,
        &out,
        &RunOptions {
            tau_m: 0.3,
            ..o.clone()
        },
    )
    .unwrap();
    assert!(reruns(&s).is_empty(), "{:?}", s.stages);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--supervision city` is the paper's §3.1 pipeline (no mask stages); `--mode learned` adds the
/// train stage after the vote, and eval and queries read its labels; going back to the vote
/// reruns only eval (the vote's folder was kept) and removes the learned labels, so that a query
/// cannot read them as this run's.
#[test]
fn city_supervision_and_learned_mode() {
    use gs4city::run::{Mode, Supervision};
    let dir = wall::tmp("run-modes");
    let (scene, _) = wall::write_scene(&dir.join("scene"), 5);
    let out = dir.join("out");
    let mut o = RunOptions {
        test_every: Some(4),
        supervision: Supervision::City,
        mode: Mode::Learned,
        ..Default::default()
    };
    o.train.iterations = 60;
    let s = run(&scene, &out, &o).unwrap();
    let names: Vec<&str> = s.stages.iter().map(|r| r.stage.dir()).collect();
    assert_eq!(
        names,
        ["citymodel", "render", "raycast", "lift", "train", "eval"]
    );
    let e = s.eval.as_ref().unwrap();
    assert_eq!(e.mode.as_deref(), Some("learned"));
    assert!(e.paper_iou["wall"].unwrap() > 0.85, "{:?}", e.paper_iou);
    assert!(out.join("train/gaussians.npy").is_file());
    assert!(out.join("train/v04.class.npy").is_file());
    assert!(!out.join("masks").exists() && !out.join("fuse").exists());
    let v = run(
        &scene,
        &out,
        &RunOptions {
            mode: Mode::Vote,
            ..o.clone()
        },
    )
    .unwrap();
    assert_eq!(reruns(&v), ["eval"]);
    assert_eq!(v.eval.as_ref().unwrap().mode.as_deref(), Some("vote"));
    assert!(!out.join("train").exists());
    // And a fused run after a city one, then a city one again: no stale mask stage is left.
    let f = run(
        &scene,
        &out,
        &RunOptions {
            supervision: Supervision::Fused,
            mode: Mode::Vote,
            ..o.clone()
        },
    )
    .unwrap();
    assert!(
        f.stages
            .iter()
            .any(|r| r.stage.dir() == "fuse" && !r.resumed)
    );
    run(
        &scene,
        &out,
        &RunOptions {
            mode: Mode::Vote,
            ..o.clone()
        },
    )
    .unwrap();
    assert!(!out.join("fuse").exists() && !out.join("masks").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn another_test_split_leaves_no_stale_prediction() {
    let dir = wall::tmp("run-split");
    let (scene, _) = wall::write_scene(&dir.join("scene"), 5);
    let out = dir.join("out");
    let a = run(&scene, &out, &eighth()).unwrap();
    assert_eq!(a.test_views, ["v00"]);
    let b = run(
        &scene,
        &out,
        &RunOptions {
            test_every: Some(3),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(b.test_views, ["v00", "v03", "v06"]);
    assert_eq!(b.eval.as_ref().unwrap().images, 3);
    let c = run(&scene, &out, &eighth()).unwrap();
    assert_eq!(c.eval.as_ref().unwrap().images, 1);
    let preds: Vec<String> = std::fs::read_dir(out.join("lift"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".class.npy"))
        .collect();
    assert_eq!(
        preds,
        ["v00.class.npy"],
        "no prediction of the old split is left"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_image_that_cannot_be_decoded_is_a_grey_report_panel_not_a_failed_run() {
    let dir = wall::tmp("run-badimage");
    let (scene, _) = wall::write_scene(&dir.join("scene"), 5);
    // The test view's image cut short after its PNG header (`gs4city check` warns that the
    // report shows a grey panel for it); the other views' images are whole (black).
    std::fs::create_dir_all(scene.join("images")).unwrap();
    for v in wall::views() {
        let k = &v.camera.intrinsics;
        let black = ndarray::Array3::<u8>::zeros((k.height as usize, k.width as usize, 3));
        gs4city::imageio::write_png(&scene.join("images").join(&v.name), &black).unwrap();
    }
    std::fs::write(
        scene.join("images/v00.png"),
        b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR\0\0\0\x10",
    )
    .unwrap();
    let out = dir.join("out");
    let s = run(&scene, &out, &eighth()).unwrap();
    assert_eq!(s.test_views, ["v00"]);
    assert!(out.join("report.html").is_file());
    // The first of the panel's four images (image | classes | truth | prediction, 4-pixel
    // gaps) is grey.
    let panel = gs4city::imageio::read_rgb(&out.join("report/v00.png")).unwrap();
    let (h, total, _) = panel.dim();
    for y in 0..h {
        for x in 0..(total - 12) / 4 {
            assert_eq!(panel[[y, x, 1]], 128, "pixel ({x}, {y})");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn refuses_a_run_folder_in_the_scene_and_a_scene_without_alignment() {
    let dir = wall::tmp("run-refuse");
    let (scene, _) = wall::write_scene(&dir.join("scene"), 5);
    let before = crate::common::files(&scene);
    for out in [scene.clone(), scene.join("run"), scene.join("gt/../x")] {
        let e = run(&scene, &out, &eighth()).unwrap_err().to_string();
        assert!(e.contains("scene folder"), "{e}");
        assert_eq!(
            crate::common::files(&scene),
            before,
            "the scene must stay unchanged"
        );
    }
    std::fs::remove_file(scene.join("citymodel/alignment.json")).unwrap();
    let e = run(&scene, &dir.join("out"), &eighth())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("alignment.json") && e.contains("--local-origin"),
        "{e}"
    );
    assert!(
        !dir.join("out").exists(),
        "nothing written before the refusal"
    );
    // With --local-origin it runs (the wall's local origin equals its alignment here).
    let s = run(
        &scene,
        &dir.join("out"),
        &RunOptions {
            local_origin: true,
            ..eighth()
        },
    )
    .unwrap();
    assert!(s.eval.unwrap().dataset["coarse_iou"].unwrap() > 0.85);
    // A scene without point_cloud.ply is one clear error.
    std::fs::remove_file(scene.join("point_cloud.ply")).unwrap();
    let e = run(&scene, &dir.join("out2"), &eighth())
        .unwrap_err()
        .to_string();
    assert!(e.contains("point_cloud.ply"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The synth `small` preset (2 real buildings, SIMULATED) with `orbit_views` orbit views of
/// 330×247 and no street views: a scene of a few seconds.
fn small_config(orbit_views: usize) -> gs4city::synth::SynthConfig {
    use gs4city::synth::{Preset, SynthConfig};
    let mut cfg = SynthConfig::preset(Preset::Small);
    cfg.cameras.orbit_views = orbit_views;
    cfg.cameras.street_views = 0;
    cfg.cameras.width = 330;
    cfg.cameras.height = 247;
    cfg
}

/// `run --refine-alignment` on a SIMULATED scene (synth small preset, 2 real buildings) with a
/// 0.3 m / 0.5° alignment error: the align stage runs first and the citymodel stage — so every
/// later stage — uses its refined alignment, which is close to the truth (read from the scene's
/// summary.json here only, to score).
#[test]
fn refine_alignment_feeds_the_whole_run() {
    use gs4city::alignment::Alignment;
    use gs4city::synth;
    let dir = wall::tmp("run-refine");
    let mut cfg = small_config(6);
    cfg.noise.translation_m = 0.3;
    cfg.noise.rotation_deg = 0.5;
    let scene = dir.join("scene");
    let truth = synth::run(&cfg, &scene).unwrap();
    let out = dir.join("out");
    let s = run(
        &scene,
        &out,
        &RunOptions {
            refine_alignment: true,
            test_every: Some(3),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(s.stages[0].stage.dir(), "align");
    let refined = Alignment::read(&out.join("align/alignment.json")).unwrap();
    let used = Alignment::read(&out.join("citymodel/alignment.json")).unwrap();
    let read = |v: &serde_json::Value| {
        Alignment::from_json_str(std::path::Path::new("summary.json"), &v.to_string()).unwrap()
    };
    let (t, given) = (read(&truth.alignment_true), read(&truth.alignment_given));
    // Scored at the corners of a 60 × 60 × 20 m box over the buildings (local metres).
    let mut worst: (f64, f64, f64) = (0.0, 0.0, 0.0);
    for c in 0..8 {
        let geo = t.origin
            + glam::DVec3::new(
                60.0 * f64::from(c & 1),
                60.0 * f64::from((c >> 1) & 1),
                20.0 * f64::from(c >> 2),
            );
        worst.0 = worst.0.max((refined.apply(geo) - t.apply(geo)).length());
        worst.1 = worst.1.max((given.apply(geo) - t.apply(geo)).length());
        worst.2 = worst.2.max((used.apply(geo) - refined.apply(geo)).length());
    }
    assert!(worst.1 > 0.3, "the given alignment is off: {worst:?}");
    assert!(
        worst.0 < 0.03,
        "refined within 3 cm of the truth: {worst:?}"
    );
    assert!(
        worst.2 < 1e-6,
        "the citymodel stage used the refined alignment: {worst:?}"
    );
    let rec: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("run.json")).unwrap()).unwrap();
    assert!(rec["stages"]["align"]["outputs"].is_array());
    assert_eq!(rec["options"]["refine_alignment"], true);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The whole default pipeline (masks → associate → fuse → lift) on a SIMULATED scene with SAM
/// masks and features never reads the simulation truth: a second run on a copy of the scene
/// without `masks/*.sim.json`, `masks/README.json` and the scene's `summary.json` writes the same
/// bytes in every stage folder (`gt/` stays: eval reads it, and only eval).
#[test]
fn the_pipeline_never_reads_the_simulation_truth() {
    use gs4city::synth;
    let dir = wall::tmp("run-notruth");
    let cfg = small_config(8);
    let a = dir.join("a");
    synth::run(&cfg, &a).unwrap();
    let b = dir.join("b");
    synth::run(&cfg, &b).unwrap();
    let mut removed = 0;
    for e in std::fs::read_dir(b.join("masks")).unwrap() {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        if name.ends_with(".sim.json") || name == "README.json" {
            std::fs::remove_file(&p).unwrap();
            removed += 1;
        }
    }
    std::fs::remove_file(b.join("summary.json")).unwrap();
    assert!(removed > 1, "the simulation wrote its truth files");
    let o = RunOptions {
        test_every: Some(4),
        ..Default::default()
    };
    let sa = run(&a, &dir.join("ra"), &o).unwrap();
    let sb = run(&b, &dir.join("rb"), &o).unwrap();
    let paper = |s: &gs4city::run::RunSummary| {
        serde_json::to_string(&s.eval.as_ref().unwrap().paper).unwrap()
    };
    assert_eq!(paper(&sa), paper(&sb));
    // Every output byte of the label stages (summaries hold timings: skipped).
    for stage in ["masks", "associate", "fuse", "lift"] {
        let strip = |m: std::collections::BTreeMap<String, Vec<u8>>| {
            m.into_iter()
                .filter(|(k, _)| k != "summary.json")
                .collect::<std::collections::BTreeMap<_, _>>()
        };
        let fa = strip(crate::common::files(&dir.join("ra").join(stage)));
        let fb = strip(crate::common::files(&dir.join("rb").join(stage)));
        assert!(!fa.is_empty(), "{stage}");
        assert!(
            fa == fb,
            "{stage}: outputs differ without the simulation truth"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
