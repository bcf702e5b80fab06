//! The weighted vote on a hand-built scene whose truth is known per Gaussian and per pixel
//! (tests/common/wall.rs): CityGML → citymodel → raycast → contributions cache → lift.

use crate::common::wall;
use gs4city::cache::{Cache, CacheOptions};
use gs4city::idmap::LabelMaps;
use gs4city::labels::LabelTable;
use gs4city::lift::{self, LiftOptions};
use gs4city::render::PreparedScene;
use gs4city::scene::Split;
use gs4city::{citymodel, classes, npy, raycast};

struct Lifted {
    /// Per Gaussian: predicted class, −2 where no training view voted (not judged).
    pred: Vec<i32>,
    summary: lift::LiftSummary,
    dir: std::path::PathBuf,
}

fn lift_wall(name: &str, gamma: f32, top_k: usize) -> (Lifted, wall::Splats) {
    lift_wall_with(name, gamma, top_k, 0.0, None, None).unwrap()
}

/// A change to the cache folder before the lift (its path, the views, the Gaussians).
type Tamper<'a> = &'a dyn Fn(&std::path::Path, &[gs4city::camera::View], &PreparedScene);

/// [`lift_wall`] with the city-model prior's weight and, when the prior is on, the mesh it
/// reads (`None`: the citymodel stage's own `mesh.ply`).
fn lift_wall_with(
    name: &str,
    gamma: f32,
    top_k: usize,
    prior: f32,
    mesh: Option<&std::path::Path>,
    tamper: Option<Tamper<'_>>,
) -> Result<(Lifted, wall::Splats), lift::LiftError> {
    let dir = wall::tmp(name);
    let (scene, s) = wall::write_scene(&dir.join("scene"), 5);
    let gml = scene.join("citymodel/wall.gml");
    let cm = citymodel::run(&[gml], &Default::default()).unwrap();
    citymodel::write(&cm, &dir.join("citymodel")).unwrap();
    let views = wall::views();
    raycast::run(
        &cm.mesh,
        &views,
        &raycast::RaycastOptions {
            tau: 0.5,
            single_pass: false,
        },
        raycast::Overlays::Off,
        &dir.join("raycast"),
    )
    .unwrap();
    let prepared = PreparedScene::new(&s.gaussians).unwrap();
    gs4city::render::cache::build(
        &prepared,
        &views,
        &CacheOptions {
            top_k,
            epsilon: 0.0,
            t_stop: 0.0,
            alpha_min: gs4city::cache::INRIA_ALPHA_MIN,
        },
        &dir.join("cache"),
    )
    .unwrap();
    if let Some(f) = tamper {
        f(&dir.join("cache"), &views, &prepared);
    }
    let cache = Cache::open(&dir.join("cache")).unwrap();
    let split = Split::new(views, 4);
    let labels = LabelTable::city(&cm.entities, &classes::table(&cm.entities)).unwrap();
    let own_mesh = dir.join("citymodel/mesh.ply");
    let summary = lift::run(
        &lift::LiftInputs {
            ply: &scene.join("point_cloud.ply"),
            cache: &cache,
            train: &split.train,
            test: &split.test,
            maps: &LabelMaps::City(dir.join("raycast")),
            labels: &labels,
            entities: &cm.entities,
            city_depth: None,
            city_mesh: (prior > 0.0).then(|| (mesh.unwrap_or(&own_mesh), 1.0)),
        },
        &LiftOptions {
            gamma: Some(gamma),
            model_prior: prior,
            ..Default::default()
        },
        &dir.join("lift"),
    )?;
    let (shape, table) = npy::read::<i32>(&dir.join("lift/gaussians.npy")).unwrap();
    assert_eq!(shape, vec![s.real.len(), 2]);
    // Gaussians no training view saw have no vote (confidence 0): −2, not judged.
    let (g, _) =
        gs4city::splat::read_ply(&dir.join("lift/semantic.ply"), &Default::default()).unwrap();
    let conf = &g.extra("label_confidence").unwrap().values;
    let pred = table
        .chunks(2)
        .zip(conf)
        .map(|(r, &c)| if c > 0.0 { r[1] } else { -2 })
        .collect();
    Ok((Lifted { pred, summary, dir }, s))
}

#[test]
fn the_city_model_prior_reaches_every_gaussian_on_the_model_no_floater_and_turns_none_wrong() {
    let (off, s) = lift_wall("prior_off", 0.0, 16);
    let (on, _) = lift_wall_with("prior_on", 0.0, 16, 0.3, None, None).unwrap();
    // Every wall and window Gaussian lies on the model (the window 0.15 m behind the wall's
    // plane, within the 0.2 m reach); the floaters stand 8–12 m in front of it.
    let on_model = s.real.iter().filter(|&&c| c >= 0).count();
    assert_eq!(on.summary.stats.model_prior_gaussians, on_model);
    assert!(on.summary.stats.model_prior_weight > 0.0);
    // Judged wall and window Gaussians (away from the outlines): every one whose class the
    // prior changes is then right, and none that was right turns wrong.
    let judged: Vec<usize> = (0..s.judged.len()).filter(|&i| s.judged[i] >= 0).collect();
    let changed: Vec<usize> = judged
        .iter()
        .copied()
        .filter(|&i| on.pred[i] != off.pred[i])
        .collect();
    let wrong = changed
        .iter()
        .filter(|&&i| on.pred[i] != s.judged[i])
        .count();
    assert_eq!(
        wrong,
        0,
        "{wrong} of {} changed Gaussians turned wrong",
        changed.len()
    );
    let right = |p: &[i32]| judged.iter().filter(|&&i| p[i] == s.judged[i]).count();
    assert!(right(&on.pred) >= right(&off.pred));
    // No floater is within reach: their labels do not change.
    for i in (0..s.real.len()).filter(|&i| s.real[i] == -1) {
        assert_eq!(on.pred[i], off.pred[i], "floater {i}");
    }
}

#[test]
fn a_missing_city_mesh_is_an_error_naming_it() {
    let missing = std::env::temp_dir().join("gs4city-no-such-dir/mesh.ply");
    let e = lift_wall_with("prior_missing", 0.0, 16, 0.3, Some(&missing), None)
        .err()
        .expect("a missing mesh fails the stage")
        .to_string();
    assert!(e.contains("gs4city-no-such-dir/mesh.ply"), "{e}");
}

#[test]
fn weighted_vote_recovers_wall_window_and_background() {
    let (l, s) = lift_wall("vote", 0.0, 16);
    let (mut right, mut total) = ([0usize; 3], [0usize; 3]);
    let unseen = l.pred.iter().filter(|&&p| p == -2).count();
    assert!(
        unseen < s.judged.len() / 10,
        "{unseen} Gaussians without votes"
    );
    for (p, t) in l
        .pred
        .iter()
        .zip(&s.judged)
        .filter(|(p, t)| **p != -2 && **t != -3)
    {
        let k = match *t {
            classes::WALL => 0,
            classes::WINDOW => 1,
            _ => 2,
        };
        total[k] += 1;
        right[k] += usize::from(p == t);
    }
    let frac = |k: usize| right[k] as f64 / total[k] as f64;
    assert!(frac(0) > 0.97, "wall {right:?}/{total:?}");
    assert!(frac(1) > 0.9, "window {right:?}/{total:?}");
    // Floaters between a camera and the wall receive the wall's label on the pixels they
    // cover: the city-model vote alone cannot tell occluders (mask fusion, paper §3.2, does).
    assert!(
        frac(2) > 0.85,
        "most floaters stay unlabelled {right:?}/{total:?}"
    );
    // Test views (every 4th: v00, v04): predicted maps against the analytic truth.
    assert_eq!(l.summary.test_views, ["v00", "v04"]);
    let (shape, class) = npy::read::<i32>(&l.dir.join("lift/v04.class.npy")).unwrap();
    assert_eq!(shape, vec![120, 160]);
    let truth = wall::truth(&wall::views()[4], &s.floaters);
    let iou = |c: i32| {
        let inter = class
            .iter()
            .zip(&truth)
            .filter(|(p, t)| **p == c && **t == c)
            .count();
        let union = class
            .iter()
            .zip(&truth)
            .filter(|(p, t)| (**p == c || **t == c) && **t != -1)
            .count();
        inter as f64 / union as f64
    };
    assert!(iou(classes::WALL) > 0.9, "wall IoU {}", iou(classes::WALL));
    assert!(
        iou(classes::WINDOW) > 0.6,
        "window IoU {}",
        iou(classes::WINDOW)
    );
    // The semantic PLY keeps the input and adds the label properties (DESIGN: label, class).
    let (g, _) =
        gs4city::splat::read_ply(&l.dir.join("lift/semantic.ply"), &Default::default()).unwrap();
    let names: Vec<&str> = g.extras.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "label",
            "class",
            "feature_id",
            "surface_id",
            "part_id",
            "label_confidence"
        ]
    );
    // Window Gaussians carry the hierarchy chain building → wall → window (entities 0, 1, 2).
    let k = l.pred.iter().position(|&p| p == classes::WINDOW).unwrap();
    let chain: Vec<f64> = ["feature_id", "surface_id", "part_id"]
        .iter()
        .map(|n| g.extra(n).unwrap().values[k])
        .collect();
    assert_eq!(chain, [0.0, 1.0, 2.0]);
    std::fs::remove_dir_all(&l.dir).unwrap();
}

#[test]
fn gamma_one_sends_everything_to_background_and_all_equals_topk_here() {
    let (one, _) = lift_wall("gamma1", 1.0, 16);
    assert!(one.pred.iter().all(|&p| p < 0), "γ = 1 must win every vote");
    let (all, _) = lift_wall("all", 0.0, 0);
    let (top, _) = lift_wall("top16", 0.0, 16);
    let same = all
        .pred
        .iter()
        .zip(&top.pred)
        .filter(|(x, y)| x == y)
        .count();
    assert!(
        same as f64 > 0.99 * all.pred.len() as f64,
        "top-16 vs all: {same}/{}",
        all.pred.len()
    );
    for l in [one, all, top] {
        std::fs::remove_dir_all(&l.dir).unwrap();
    }
}

/// A training view's cache file rendered for a camera of half the size (a stale or foreign
/// file): the lift refuses it naming that file and both sizes, not the label map it would
/// then read at the wrong size.
#[test]
fn a_cache_file_of_another_size_than_its_camera_is_named() {
    let stem = std::cell::RefCell::new(String::new());
    let half = |dir: &std::path::Path, views: &[gs4city::camera::View], g: &PreparedScene| {
        let mut v = views[1].clone();
        let k = &mut v.camera.intrinsics;
        (k.width, k.height) = (k.width / 2, k.height / 2);
        (k.fx, k.fy, k.cx, k.cy) = (k.fx / 2.0, k.fy / 2.0, k.cx / 2.0, k.cy / 2.0);
        let opts = CacheOptions {
            top_k: 16,
            epsilon: 0.0,
            t_stop: 0.0,
            alpha_min: gs4city::cache::INRIA_ALPHA_MIN,
        };
        let c = gs4city::render::cache::contrib(g, &v, &opts).unwrap();
        c.write(&gs4city::cache::cache_file(dir, &v.stem()))
            .unwrap();
        *stem.borrow_mut() = v.stem();
    };
    let e = lift_wall_with("half_size", 0.0, 16, 0.0, None, Some(&half))
        .err()
        .expect("refused")
        .to_string();
    let views = wall::views();
    let k = &views[1].camera.intrinsics;
    let want = format!(
        "{}.contrib: {}×{} pixels (width × height), its view's camera is {}×{}",
        stem.borrow(),
        k.width / 2,
        k.height / 2,
        k.width,
        k.height
    );
    assert!(e.contains(&want), "{e}\nwanted: {want}");
}
