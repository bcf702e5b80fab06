//! The work knobs of `gs4city run` (docs/quality.md) on a SIMULATED scene (the small preset:
//! 2 real buildings): the full work, the default preset, training views at a lower resolution
//! and the view cover give the same outputs at 1 and 2 threads, and every per-view stage works at the resolution the cache
//! holds its view (sizes worked out by hand from the cameras).
use std::path::Path;

use crate::common::{self, wall};
use gs4city::cache::ViewSelection;
use gs4city::run::{Quality, RunOptions, Work, run};

/// Every output file of a run folder, by relative name, except what records times, paths or
/// run ids (`summary.json` files, `run.json`, `report.html`).
fn outputs(dir: &Path) -> Vec<(String, Vec<u8>)> {
    common::files(dir)
        .into_iter()
        // Summaries hold times; `.lock` names the process that held the folder.
        .filter(|(n, _)| {
            !(n.ends_with("summary.json")
                || n == "run.json"
                || n == "report.html"
                || n.ends_with(".lock"))
        })
        .collect()
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

/// Runs `scene` into `out` with `opts` on a pool of `threads` threads.
fn run_at(scene: &Path, out: &Path, opts: &RunOptions, threads: usize) {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(|| run(scene, out, opts))
        .unwrap();
}

/// The deterministic part of the render's view choice (`selection` less its time).
fn selection(out: &Path) -> serde_json::Value {
    let mut s = json(&out.join("render/summary.json"))["selection"].clone();
    if let Some(o) = s.as_object_mut() {
        o.remove("seconds");
    }
    s
}

#[test]
fn a_run_is_the_same_at_one_and_two_threads_with_and_without_the_work_knobs() {
    let dir = wall::tmp("work-knobs");
    let scene = dir.join("scene");
    let mut cfg = gs4city::synth::SynthConfig::preset(gs4city::synth::Preset::Small);
    cfg.cameras.orbit_views = 12;
    cfg.cameras.street_views = 6;
    gs4city::synth::run(&cfg, &scene).unwrap();
    let base = RunOptions {
        test_every: Some(6),
        ..Default::default()
    };
    let knobs = Work {
        train_scale: 3,
        views: ViewSelection::Cover { k: 2, share: 0.95 },
        ..Quality::Full.work()
    };
    let mut per_setting = Vec::new();
    for (label, opts) in [
        ("full", base.clone().with_work(Quality::Full.work())),
        ("default", base.clone().with_work(Quality::Default.work())),
        ("knobs", base.clone().with_work(knobs)),
    ] {
        let one = dir.join(format!("{label}-1"));
        let two = dir.join(format!("{label}-2"));
        run_at(&scene, &one, &opts, 1);
        run_at(&scene, &two, &opts, 2);
        let (a, b) = (outputs(&one), outputs(&two));
        assert!(a.len() > 20, "{label}: {}", a.len());
        let names = |v: &[(String, Vec<u8>)]| v.iter().map(|x| x.0.clone()).collect::<Vec<_>>();
        assert_eq!(names(&a), names(&b), "{label}");
        for ((n, x), (_, y)) in a.iter().zip(&b) {
            assert!(x == y, "{label}: {n} differs between 1 and 2 threads");
        }
        assert_eq!(selection(&one), selection(&two), "{label}");
        per_setting.push(one);
    }
    // Without the knobs every view is cached at its full size and nothing is selected.
    let full = json(&per_setting[0].join("render/summary.json"));
    assert!(full["selection"].is_null(), "{}", full["selection"]);
    assert_eq!(full["views"].as_array().unwrap().len(), 18);
    // The default preset stops each pixel's blend at transmittance 0.2 (full: 0.02) and
    // leaves out contributions with α < 1/32 (full: 1/255), so its lists hold fewer entries,
    // view by view, and never more.
    let default = json(&per_setting[1].join("render/summary.json"));
    let opt = |s: &serde_json::Value, k: &str| s["options"][k].as_f64().unwrap();
    assert!((opt(&default, "t_stop") - 0.2).abs() < 1e-6);
    assert!((opt(&full, "t_stop") - 0.02).abs() < 1e-6);
    assert!((opt(&default, "alpha_min") - 1.0 / 32.0).abs() < 1e-9);
    assert!((opt(&full, "alpha_min") - 1.0 / 255.0).abs() < 1e-6);
    let entries = |s: &serde_json::Value| -> Vec<u64> {
        s["views"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v["entries"].as_u64().unwrap())
            .collect()
    };
    let (e_full, e_default) = (entries(&full), entries(&default));
    assert!(e_full.iter().zip(&e_default).all(|(f, d)| d <= f));
    assert!(e_default.iter().sum::<u64>() < e_full.iter().sum::<u64>());

    // The render stage's choice: a subset of the 15 training views (18 views, every 6th by
    // name a test view); test views at the cameras' W × H, training views at ⌈W/3⌉ × ⌈H/3⌉.
    let out = &per_setting[2];
    let r = json(&out.join("render/summary.json"));
    let cams = gs4city::colmap::read_model(&scene.join("sparse/0")).unwrap();
    let (w, h) = (
        cams[0].camera.intrinsics.width as u64,
        cams[0].camera.intrinsics.height as u64,
    );
    let mut names: Vec<String> = cams.iter().map(|v| v.name.clone()).collect();
    names.sort();
    let test: Vec<&String> = names.iter().step_by(6).collect();
    let sel = &r["selection"];
    assert_eq!(sel["offered"], 15);
    let chosen = sel["chosen"].as_array().unwrap().len();
    assert!((1..=15).contains(&chosen), "{sel}");
    let cached = r["views"].as_array().unwrap();
    assert_eq!(cached.len(), chosen + test.len());
    let rc = json(&out.join("raycast/summary.json"));
    for (v, t) in cached.iter().zip(rc["per_view"].as_array().unwrap()) {
        let name = v["name"].as_str().unwrap().to_string();
        let size = (v["width"].as_u64().unwrap(), v["height"].as_u64().unwrap());
        let want = if test.contains(&&name) {
            (w, h)
        } else {
            (w.div_ceil(3), h.div_ceil(3))
        };
        assert_eq!(size, want, "{name}");
        // The raycast traced the cache's views at the cache's size.
        assert_eq!(t["name"].as_str().unwrap(), name);
        assert_eq!(
            (t["width"].as_u64().unwrap(), t["height"].as_u64().unwrap()),
            want
        );
        let stem = name.trim_end_matches(".png");
        if !test.contains(&&name) {
            // Kept masks, group maps and fused maps of a training view: the same size.
            let kept =
                gs4city::maskfile::read_kept(&out.join(format!("masks/{stem}.json"))).unwrap();
            for k in &kept {
                assert_eq!(k.sam.segmentation.size, [want.1 as usize, want.0 as usize]);
            }
            for d in ["associate", "fuse"] {
                let (shape, _) =
                    gs4city::npy::read::<i32>(&out.join(format!("{d}/{stem}.ids.npy"))).unwrap();
                assert_eq!(shape, [want.1 as usize, want.0 as usize], "{d}/{stem}");
            }
        }
    }
    // The test views are scored at their full size.
    let m = json(&out.join("eval/metrics.json"));
    assert_eq!(m["images"], test.len());
    std::fs::remove_dir_all(&dir).unwrap();
}
