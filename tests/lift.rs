//! End to end on a hand-made scene whose truth is known per Gaussian:
//! CityGML → citymodel → COLMAP views → raycast → lift (weighted vote) → test-view maps.
use std::path::{Path, PathBuf};

use glam::DVec3;
use gs4city::camera::{Camera, Distortion, Intrinsics, Pose, View};
use gs4city::lift::{self, LiftConfig, LiftOptions};
use gs4city::render::ContributionMode;
use gs4city::splat::{Gaussians, PlyEncoding, write_ply};
use gs4city::{citymodel, classes, colmap, npy, raycast};
use rand::{Rng, SeedableRng};

/// A 10×6 m wall in the plane y = 0 (x 0..10, z 0..6) with a 2×2 m window hole at x 4..6, z 2..4,
/// and the window polygon filling the hole; georeferenced at UTM-like coordinates.
fn citygml() -> String {
    let (e, n) = (678_000.0, 5_403_000.0);
    let p = |x: f64, z: f64| format!("{} {} {}", e + x, n, 400.0 + z);
    let ring = |pts: &[(f64, f64)]| {
        let mut v: Vec<String> = pts.iter().map(|&(x, z)| p(x, z)).collect();
        v.push(v[0].clone());
        v.join(" ")
    };
    let wall = ring(&[(0.0, 0.0), (10.0, 0.0), (10.0, 6.0), (0.0, 6.0)]);
    let hole = ring(&[(4.0, 2.0), (4.0, 4.0), (6.0, 4.0), (6.0, 2.0)]);
    let win = ring(&[(4.0, 2.0), (6.0, 2.0), (6.0, 4.0), (4.0, 4.0)]);
    format!(
        r#"<?xml version="1.0"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:gml="http://www.opengis.net/gml">
<core:cityObjectMember><bldg:Building gml:id="B"><bldg:boundedBy><bldg:WallSurface gml:id="W">
<bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>{wall}</gml:posList></gml:LinearRing></gml:exterior>
<gml:interior><gml:LinearRing><gml:posList>{hole}</gml:posList></gml:LinearRing></gml:interior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface>
<bldg:opening><bldg:Window gml:id="Win"><bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>{win}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface></bldg:Window></bldg:opening>
</bldg:WallSurface></bldg:boundedBy></bldg:Building></core:cityObjectMember></core:CityModel>
"#
    )
}

/// Flat Gaussians on the wall plane (scene frame = geo − floor(origin)), a recessed window, and floaters.
/// Returns the Gaussians and their true class (wall, window, or −1 for floaters).
fn splats(seed: u64) -> (Gaussians, Vec<i32>) {
    let (g, judged, _) = splats_with_truth(seed);
    (g, judged)
}

/// As [`splats`], plus the real class of every Gaussian (edge band included).
fn splats_with_truth(seed: u64) -> (Gaussians, Vec<i32>, Vec<i32>) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut g = Gaussians {
        sh_degree: 0,
        ..Default::default()
    };
    let mut truth = Vec::new();
    let mut real = Vec::new();
    let mut push = |g: &mut Gaussians, p: [f32; 3], rgb: [f32; 3], flat: bool, t: i32| {
        real.push(if !flat {
            -1
        } else if p[1] > 0.1 {
            classes::WINDOW
        } else {
            classes::WALL
        });
        g.positions.push(p);
        g.f_dc.push(rgb.map(|c| (c - 0.5) / 0.282_094_8));
        g.opacity.push(3.0);
        g.scale.push(if flat {
            [(0.12f32).ln(), (0.002f32).ln(), (0.12f32).ln()]
        } else {
            [(0.1f32).ln(); 3]
        });
        g.rotation.push([1.0, 0.0, 0.0, 0.0]);
        truth.push(t);
    };
    for _ in 0..6000 {
        let (x, z) = (
            rng.random_range(0.0..10.0f32),
            rng.random_range(0.0..6.0f32),
        );
        let in_hole = (4.0..6.0).contains(&x) && (2.0..4.0).contains(&z);
        // Within 0.25 m of an outline the footprint (3σ = 0.36 m) straddles two labels: not judged.
        let edge = x.min(10.0 - x).min(z).min(6.0 - z) < 0.25
            || ((3.75..6.25).contains(&x)
                && (1.75..4.25).contains(&z)
                && !((4.25..5.75).contains(&x) && (2.25..3.75).contains(&z)));
        if edge {
            push(
                &mut g,
                [x, if in_hole { 0.15 } else { 0.0 }, z],
                [0.8, 0.7, 0.5],
                true,
                -3,
            );
        } else if in_hole {
            // Truth: windows sit 0.15 m behind the wall plane (inside the building, +y).
            push(&mut g, [x, 0.15, z], [0.2, 0.4, 0.8], true, classes::WINDOW);
        } else {
            push(&mut g, [x, 0.0, z], [0.8, 0.7, 0.5], true, classes::WALL);
        }
    }
    for _ in 0..300 {
        push(
            &mut g,
            [
                rng.random_range(-5.0..15.0),
                rng.random_range(-12.0..-8.0),
                rng.random_range(0.0..8.0),
            ],
            [0.3, 0.6, 0.2],
            false,
            -1,
        );
    }
    (g, truth, real)
}

fn views() -> Vec<View> {
    (0..8)
        .map(|i| {
            let x = 1.0 + i as f64 * 1.1;
            let eye = DVec3::new(x, -14.0, 3.0 + (i % 3) as f64 * 0.5);
            let camera = Camera {
                intrinsics: Intrinsics {
                    width: 160,
                    height: 120,
                    fx: 120.0,
                    fy: 120.0,
                    cx: 80.0,
                    cy: 60.0,
                    distortion: Distortion::None,
                },
                pose: Pose::look_at(eye, DVec3::new(5.0, 0.0, 3.0), DVec3::Z).unwrap(),
            };
            View {
                image_id: i + 1,
                camera_id: i + 1,
                name: format!("v{i:02}.png"),
                camera,
            }
        })
        .collect()
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("gs4city-lift-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn pipeline(
    dir: &Path,
    gamma: f32,
    contributions: ContributionMode,
) -> (serde_json::Value, Vec<i32>, Vec<i32>) {
    let gml = dir.join("wall.gml");
    std::fs::write(&gml, citygml()).unwrap();
    let cm = citymodel::run(&[gml], &Default::default()).unwrap();
    citymodel::write(&cm, &dir.join("citymodel")).unwrap();
    let vs = views();
    colmap::write_model(&dir.join("sparse"), &vs, true).unwrap();
    let (g, truth) = splats(5);
    write_ply(&dir.join("scene.ply"), &g, PlyEncoding::BinaryLittleEndian).unwrap();
    raycast::run(
        &cm.mesh,
        &vs,
        &raycast::RaycastOptions {
            tau: 0.5,
            single_pass: false,
        },
        None,
        &dir.join("raycast"),
    )
    .unwrap();
    let cfg = LiftConfig {
        ply: dir.join("scene.ply"),
        colmap: dir.join("sparse"),
        raycast: dir.join("raycast"),
        citymodel: dir.join("citymodel"),
        out: dir.join("lift"),
        options: LiftOptions {
            contributions,
            gamma,
        },
        test_every: 4,
        predict_k: 16,
    };
    let s = lift::run(&cfg).unwrap();
    let (shape, table) = npy::read::<i32>(&dir.join("lift/gaussians.npy")).unwrap();
    assert_eq!(shape, vec![truth.len(), 5]);
    let pred: Vec<i32> = table.chunks(5).map(|r| r[0]).collect();
    // Gaussians no training view saw have no vote (confidence 0): mark them −2 (not judged).
    let (g, _) = gs4city::splat::read_ply(
        &dir.join("lift/point_cloud_semantic.ply"),
        &Default::default(),
    )
    .unwrap();
    let conf = &g
        .extras
        .iter()
        .find(|e| e.name == "label_confidence")
        .unwrap()
        .values;
    let pred = pred
        .iter()
        .zip(conf)
        .map(|(&p, &c)| if c > 0.0 { p } else { -2 })
        .collect();
    (s, pred, truth)
}

#[test]
fn weighted_vote_recovers_wall_window_and_background() {
    let dir = tmp("e2e");
    let (s, pred, truth) = pipeline(&dir, 0.0, ContributionMode::TopK(16));
    // Gaussians that received votes: compare with the truth.
    let mut right = [0usize; 3];
    let mut total = [0usize; 3];
    let unseen = pred.iter().filter(|&&p| p == -2).count();
    assert!(
        unseen < truth.len() / 10,
        "{unseen} Gaussians without votes"
    );
    for (p, t) in pred
        .iter()
        .zip(&truth)
        .filter(|(p, t)| **p != -2 && **t != -3)
    {
        let k = match *t {
            classes::WALL => 0,
            classes::WINDOW => 1,
            _ => 2,
        };
        total[k] += 1;
        if p == t {
            right[k] += 1;
        }
    }
    let wall_as: std::collections::BTreeMap<i32, usize> = pred
        .iter()
        .zip(&truth)
        .filter(|(p, t)| **t == classes::WALL && **p != classes::WALL)
        .fold(Default::default(), |mut m, (p, _)| {
            *m.entry(*p).or_default() += 1;
            m
        });
    println!("wall Gaussians predicted otherwise: {wall_as:?}");
    let frac = |k: usize| right[k] as f64 / total[k] as f64;
    assert!(frac(0) > 0.97, "wall {right:?}/{total:?}");
    assert!(frac(1) > 0.9, "window {right:?}/{total:?}");
    // Floaters between a camera and the wall receive the wall's city label on the pixels they
    // cover: the vote alone cannot tell occluders (that is what mask fusion, paper §3.2, is for).
    assert!(
        frac(2) > 0.85,
        "most floaters stay unlabelled {right:?}/{total:?}"
    );
    // Test views (every 4th: v00, v04) have predicted class maps with wall and window pixels.
    assert_eq!(s["test_views"], serde_json::json!(["v00", "v04"]));
    let (shape, class) = npy::read::<i32>(&dir.join("lift/v04.class.npy")).unwrap();
    assert_eq!(shape, vec![120, 160]);
    // The 2×2 m window at ≈ 14 m with fx = 120 covers ≈ 17×17 = 290 px.
    let win_px = class.iter().filter(|&&c| c == classes::WINDOW).count();
    assert!((200..400).contains(&win_px), "{win_px} window pixels");
    assert!(class.iter().filter(|&&c| c == classes::WALL).count() > 3000);
    // The semantic PLY keeps the input and adds the label properties.
    let (g, _) = gs4city::splat::read_ply(
        &dir.join("lift/point_cloud_semantic.ply"),
        &Default::default(),
    )
    .unwrap();
    let names: Vec<&str> = g.extras.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "instance_id",
            "feature_id",
            "surface_id",
            "part_id",
            "class_id",
            "label_confidence"
        ]
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn gamma_one_sends_everything_to_background_and_all_equals_topk_here() {
    let dir = tmp("gamma");
    let (_, pred, _) = pipeline(&dir, 1.0, ContributionMode::TopK(16));
    assert!(pred.iter().all(|&p| p < 0), "γ = 1 must win every vote");
    let dir2 = tmp("all");
    let (_, a, _) = pipeline(&dir2, 0.0, ContributionMode::All);
    let (_, b, _) = pipeline(&dir, 0.0, ContributionMode::TopK(16));
    let same = a.iter().zip(&b).filter(|(x, y)| x == y).count();
    assert!(
        same as f64 > 0.99 * a.len() as f64,
        "top-16 vs all: {same}/{}",
        a.len()
    );
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::remove_dir_all(&dir2).unwrap();
}

#[test]
fn run_all_stages_resume_and_rerun_downstream_of_a_changed_input() {
    use gs4city::lift::GaussianLabel;
    use gs4city::run::{RunOptions, run};
    let dir = tmp("run");
    let scene = dir.join("scene");
    std::fs::create_dir_all(scene.join("citymodel")).unwrap();
    std::fs::write(scene.join("citymodel/wall.gml"), citygml()).unwrap();
    let vs = views();
    colmap::write_model(&scene.join("sparse/0"), &vs, true).unwrap();
    let (g, _, real) = splats_with_truth(5);
    write_ply(
        &scene.join("point_cloud.ply"),
        &g,
        PlyEncoding::BinaryLittleEndian,
    )
    .unwrap();
    // Ground truth: the class of the Gaussians carrying the weight at each pixel.
    let prepared = gs4city::render::PreparedScene::new(&g).unwrap();
    let labels: Vec<GaussianLabel> = real
        .iter()
        .map(|&c| GaussianLabel {
            instance: c,
            class: c,
            ..GaussianLabel::NONE
        })
        .collect();
    std::fs::create_dir_all(scene.join("gt")).unwrap();
    for v in &vs {
        let (class, _) = lift::predict_view(&prepared, &v.camera, &labels, 16).unwrap();
        npy::write(
            &scene.join(format!("gt/{}.class.npy", v.stem())),
            &[120, 160],
            &class,
        )
        .unwrap();
    }
    let out = dir.join("out");
    let (first, metrics) = run(&scene, &out, &RunOptions::default()).unwrap();
    let names: Vec<&str> = first.iter().map(|r| r.stage.as_str()).collect();
    assert_eq!(names, ["citymodel", "raycast", "lift", "eval"]);
    assert!(first.iter().all(|r| !r.resumed));
    let m = metrics.expect("gt/ exists: metrics");
    // Test view v00 (every 8th of 8 views) sees the left end of the wall, which the training
    // views barely see: those Gaussians have no vote and stay unlabelled (recall ≈ 0.9).
    let c = &m["dataset"]["coarse"];
    assert!(c["iou"].as_f64().unwrap() > 0.85, "{c}");
    assert!(c["precision"].as_f64().unwrap() > 0.99, "{c}");
    // v00 looks obliquely at a 2×2 m window recessed behind its hole: the rim Gaussians'
    // footprints straddle wall and window, so the window IoU is modest (measured 0.52).
    let fine = &m["dataset"]["fine"]["iou"];
    assert!(
        fine["wall"].as_f64().unwrap() > 0.8 && fine["window"].as_f64().unwrap() > 0.4,
        "{fine}"
    );
    assert!(
        fine["tree"].is_null(),
        "classes absent from the GT are null: {fine}"
    );
    // Second run: every stage resumed.
    let (second, _) = run(&scene, &out, &RunOptions::default()).unwrap();
    assert!(second.iter().all(|r| r.resumed), "{second:?}");
    // A new PLY invalidates lift and eval only.
    std::thread::sleep(std::time::Duration::from_millis(20));
    write_ply(
        &scene.join("point_cloud.ply"),
        &g,
        PlyEncoding::BinaryLittleEndian,
    )
    .unwrap();
    let (third, _) = run(&scene, &out, &RunOptions::default()).unwrap();
    let resumed: Vec<bool> = third.iter().map(|r| r.resumed).collect();
    assert_eq!(resumed, [true, true, false, false]);
    // Another τ invalidates raycast and everything after it.
    let (fourth, _) = run(
        &scene,
        &out,
        &RunOptions {
            tau_m: 0.3,
            ..Default::default()
        },
    )
    .unwrap();
    let resumed: Vec<bool> = fourth.iter().map(|r| r.resumed).collect();
    assert_eq!(resumed, [true, false, false, false]);
    // A scene without point_cloud.ply is one clear error.
    std::fs::remove_file(scene.join("point_cloud.ply")).unwrap();
    let e = run(&scene, &out, &RunOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("point_cloud.ply"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}
