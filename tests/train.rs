//! Identity training (paper §3.3) on the hand-built wall scene (tests/common/wall.rs), whose
//! truth is known per Gaussian and per pixel: gradients against finite differences, the 3D
//! term on a hidden Gaussian, determinism over thread counts, the outputs (a standard PLY read
//! by Python's `plyfile`), and bad label maps.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common::wall;
use gs4city::cache::{Cache, CacheOptions};
use gs4city::camera::View;
use gs4city::idmap::LabelMaps;
use gs4city::labels::{Label, LabelTable, Source};
use gs4city::lift::LiftInputs;
use gs4city::render::PreparedScene;
use gs4city::scene::Split;
use gs4city::semantics::Entity;
use gs4city::splat::{PlyEncoding, write_ply};
use gs4city::train::model::{self, Active, Grads, Model, PixelBatch};
use gs4city::train::{self, TrainOptions, knn, pool};
use gs4city::{citymodel, classes, npy, raycast};
use ndarray::Array2;
use rand::{Rng, SeedableRng};

/// The wall scene, optionally with one extra Gaussian, through citymodel → raycast → cache.
struct Fixture {
    dir: PathBuf,
    ply: PathBuf,
    cache: Cache,
    split: Split,
    entities: Vec<Entity>,
    table: LabelTable,
    splats: wall::Splats,
}

impl Fixture {
    fn new(name: &str, extra: Option<[f32; 3]>) -> Fixture {
        let dir = wall::tmp(name);
        let (scene, mut s) = wall::write_scene(&dir.join("scene"), 5);
        let ply = scene.join("point_cloud.ply");
        if let Some(p) = extra {
            let g = &mut s.gaussians;
            g.positions.push(p);
            g.f_dc.push([0.0; 3]);
            g.opacity.push(-2.0);
            g.scale.push([(0.02f32).ln(); 3]);
            g.rotation.push([1.0, 0.0, 0.0, 0.0]);
            s.real.push(classes::WALL);
            s.judged.push(-3);
            write_ply(&ply, g, PlyEncoding::BinaryLittleEndian).unwrap();
        }
        let cm = citymodel::run(&[scene.join("citymodel/wall.gml")], &Default::default()).unwrap();
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
                top_k: 16,
                epsilon: 0.0,
                t_stop: 0.0,
                alpha_min: gs4city::cache::INRIA_ALPHA_MIN,
            },
            &dir.join("cache"),
        )
        .unwrap();
        let table = LabelTable::city(&cm.entities, &classes::table(&cm.entities)).unwrap();
        Fixture {
            cache: Cache::open(&dir.join("cache")).unwrap(),
            split: Split::new(views, 4),
            entities: cm.entities,
            table,
            ply,
            dir,
            splats: s,
        }
    }

    fn maps(&self) -> LabelMaps {
        LabelMaps::City(self.dir.join("raycast"))
    }

    fn train(&self, out: &str, opts: &TrainOptions) -> train::TrainSummary {
        self.train_with(out, opts, &self.maps(), &self.table)
    }

    fn train_with(
        &self,
        out: &str,
        opts: &TrainOptions,
        maps: &LabelMaps,
        table: &LabelTable,
    ) -> train::TrainSummary {
        self.try_train(out, opts, maps, table).unwrap()
    }

    fn try_train(
        &self,
        out: &str,
        opts: &TrainOptions,
        maps: &LabelMaps,
        table: &LabelTable,
    ) -> Result<train::TrainSummary, train::TrainError> {
        train::run(
            &LiftInputs {
                ply: &self.ply,
                cache: &self.cache,
                train: &self.split.train,
                test: &self.split.test,
                maps,
                labels: table,
                entities: &self.entities,
                city_depth: None,
                city_mesh: None,
            },
            opts,
            &self.dir.join(out),
        )
    }

    /// `gaussians.npy` of an output folder: (label, class) per Gaussian.
    fn gaussians(&self, out: &str) -> Vec<(i32, i32)> {
        let (shape, t) = npy::read::<i32>(&self.dir.join(out).join("gaussians.npy")).unwrap();
        assert_eq!(shape, vec![self.splats.real.len(), 2]);
        t.chunks(2).map(|r| (r[0], r[1])).collect()
    }
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn quick() -> TrainOptions {
    TrainOptions {
        iterations: 150,
        pixels: 2048,
        stride: 1,
        window: 50,
        ..TrainOptions::default()
    }
}

/// A checked parameter: its name, how to reach it in a model, and its analytic derivative.
type Param = (String, Box<dyn Fn(&mut Model<f64>) -> &mut f64>, f64);

/// Central finite differences of `f` at the parameters selected by `get`/`set` against the
/// analytic gradient `want`; every entry must agree to a relative error ≤ 1e-4.
fn check_gradient(what: &str, m: &Model<f64>, params: &[Param], f: &dyn Fn(&Model<f64>) -> f64) {
    let h = 1e-5;
    let mut worst: f64 = 0.0;
    for (name, sel, want) in params {
        let mut mp = m.clone();
        *sel(&mut mp) += h;
        let mut mm = m.clone();
        *sel(&mut mm) -= h;
        let fd = (f(&mp) - f(&mm)) / (2.0 * h);
        let rel = (want - fd).abs() / want.abs().max(fd.abs()).max(1e-8);
        worst = worst.max(rel);
        assert!(
            rel <= 1e-4,
            "{what}: ∂/∂{name}: analytic {want:.9e}, finite differences {fd:.9e} (relative error {rel:.2e})"
        );
    }
    eprintln!(
        "{what}: {} partial derivatives, worst relative error {worst:.2e}",
        params.len()
    );
}

/// The parameters a gradient check looks at: codes of touched Gaussians, classifier rows and
/// biases of touched classes.
#[allow(clippy::type_complexity)]
fn selected(
    g: &Grads<f64>,
    d: usize,
) -> Vec<(String, Box<dyn Fn(&mut Model<f64>) -> &mut f64>, f64)> {
    let mut out: Vec<(String, Box<dyn Fn(&mut Model<f64>) -> &mut f64>, f64)> = Vec::new();
    for &gid in g.touched_codes.iter().step_by(7).take(12) {
        for j in [0, d / 2, d - 1] {
            let gi = gid as usize;
            out.push((
                format!("e[{gi}][{j}]"),
                Box::new(move |m: &mut Model<f64>| &mut m.codes[gi * d + j]),
                g.codes[gi * d + j],
            ));
        }
    }
    for &c in g.touched_classes.iter().take(8) {
        let c = c as usize;
        for j in [0, d - 1] {
            out.push((
                format!("W[{c}][{j}]"),
                Box::new(move |m: &mut Model<f64>| &mut m.weights[[c, j]]),
                g.weights[[c, j]],
            ));
        }
        out.push((
            format!("b[{c}]"),
            Box::new(move |m: &mut Model<f64>| &mut m.bias[c]),
            g.bias[c],
        ));
    }
    out
}

#[test]
fn gradients_agree_with_finite_differences_in_f64() {
    let fx = Fixture::new("train-grad", None);
    let pool = pool::build(
        &fx.cache,
        &fx.split.train,
        &fx.maps(),
        &fx.table,
        None,
        1,
        0,
        0.0,
    )
    .unwrap();
    let positions = gs4city::splat::read_ply(&fx.ply, &Default::default())
        .unwrap()
        .0
        .positions;
    let graph = knn::build(&positions, 5);
    // A model with 40 classes (the wall's few labels and 36 unused ones), away from the
    // initialisation: random codes and classifier.
    let n = positions.len();
    let (d, c) = (16, 40);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
    let m = Model::<f64> {
        dim: d,
        codes: (0..n * d).map(|_| rng.random_range(-1.0..1.0)).collect(),
        weights: Array2::from_shape_fn((c, d), |_| rng.random_range(-1.5..1.5)),
        bias: (0..c).map(|_| rng.random_range(-1.0..1.0)).collect(),
    };
    // 300 pixels of the first training view.
    let v = &pool.views[0];
    let mut batch = PixelBatch::default();
    for r in (0..v.len()).step_by(v.len() / 300) {
        let (ids, ws) = v.pixel(r);
        batch.push(ids, ws, v.targets[r]);
    }
    let members: Vec<u32> = [0].into_iter().chain(v.classes.iter().copied()).collect();
    let sampled = Active::sampled(c, members, 6, &mut rng);
    assert!(
        sampled.log_omega > 0.0,
        "negatives stand for several classes"
    );
    for (what, active) in [
        ("CE, exact softmax", Active::full(c)),
        ("CE, sampled softmax", sampled.clone()),
    ] {
        let mut g = Grads::new(&m);
        model::cross_entropy(&m, &batch, &active, 1.0, &mut g);
        let f =
            |mm: &Model<f64>| model::cross_entropy(mm, &batch, &active, 1.0, &mut Grads::new(mm));
        check_gradient(what, &m, &selected(&g, d), &f);
    }
    // The class-level term mixed in (μ = 0.4; four groups, the background alone in its own).
    let group: Vec<u32> = (0..c as u32)
        .map(|k| if k == 0 { 0 } else { 1 + k % 4 })
        .collect();
    for (what, active) in [
        ("CE + class term, exact softmax", Active::full(c)),
        ("CE + class term, sampled softmax", sampled.clone()),
    ] {
        let mut g = Grads::new(&m);
        model::cross_entropy_mixed(&m, &batch, &active, &group, 0.4, 1.0, &mut g);
        let f = |mm: &Model<f64>| {
            model::cross_entropy_mixed(mm, &batch, &active, &group, 0.4, 1.0, &mut Grads::new(mm))
        };
        check_gradient(what, &m, &selected(&g, d), &f);
    }
    // The 3D term: 40 anchors and their 5 neighbours.
    let anchors: Vec<u32> = (0..40).map(|i| (i * 151 % n) as u32).collect();
    let neighbours: Vec<u32> = anchors
        .iter()
        .flat_map(|&a| graph.of(a as usize).to_vec())
        .collect();
    let sample: Vec<u32> = vec![3, 9, 14, 22, 30, 37];
    let per_anchor: Vec<Active> = anchors
        .iter()
        .enumerate()
        .map(|(j, _)| Active::from_sample(c, vec![0, (j % 5) as u32 + 1, 7], &sample))
        .collect();
    for (what, actives) in [
        ("KNN-KL, exact softmax", vec![Active::full(c)]),
        ("KNN-KL, sampled softmax", per_anchor),
    ] {
        let mut g = Grads::new(&m);
        model::knn_kl(&m, &anchors, &neighbours, 5, &actives, 1.0, &mut g);
        let f = |mm: &Model<f64>| {
            model::knn_kl(
                mm,
                &anchors,
                &neighbours,
                5,
                &actives,
                1.0,
                &mut Grads::new(mm),
            )
            .0
        };
        check_gradient(what, &m, &selected(&g, d), &f);
    }
}

#[test]
fn the_3d_term_pulls_a_hidden_gaussian_to_its_neighbours_label() {
    // A Gaussian just behind the wall (y = +0.05): no view sees it, the vote leaves it
    // unlabelled, and its nearest neighbours are wall Gaussians.
    let fx = Fixture::new("train-kl", Some([2.0, 0.05, 3.0]));
    let h = fx.splats.real.len() - 1;
    let pool = pool::build(
        &fx.cache,
        &fx.split.train,
        &fx.maps(),
        &fx.table,
        None,
        1,
        0,
        0.0,
    )
    .unwrap();
    assert_eq!(
        pool.vote[h].weight, 0.0,
        "the hidden Gaussian must not be seen"
    );
    assert_eq!(pool.vote[h].label, -1);
    let positions = gs4city::splat::read_ply(&fx.ply, &Default::default())
        .unwrap()
        .0
        .positions;
    let graph = knn::build(&positions, 5);
    let wall_label = pool.vote[graph.of(h)[0] as usize].label;
    for &nb in graph.of(h) {
        assert_eq!(
            pool.vote[nb as usize].label, wall_label,
            "neighbours share the wall label"
        );
        assert_eq!(fx.splats.real[nb as usize], classes::WALL);
    }
    let opts = TrainOptions {
        iterations: 200,
        kl_every: 1,
        kl_samples: positions.len(),
        ..quick()
    };
    fx.train("kl", &opts);
    assert_eq!(
        fx.gaussians("kl")[h],
        (wall_label, classes::WALL),
        "pulled to the wall"
    );
    // Control: without the 3D term the hidden Gaussian keeps the background.
    fx.train(
        "nokl",
        &TrainOptions {
            kl_lambda: 0.0,
            ..opts
        },
    );
    assert_eq!(fx.gaussians("nokl")[h], (-1, -1));
}

/// The test's own reading of the documented pixel rule (docs/train.md, the vote's rule) from a
/// cached view's contribution lists, in f64 and without `gs4city::cache::predict`: per pixel,
/// the value of `of` whose Gaussians carry the largest summed weight, ties to the smaller value;
/// −1 where `1 − α`, the truncated mass and the Gaussians valued −1 weigh at least as much.
/// Returns the map and, per pixel, whether the two heaviest candidates are closer than 1e-4
/// (f32 sums in another order may pick either: not compared).
fn vote_by_hand(c: &gs4city::cache::ViewContrib, of: &[i32]) -> (Vec<i32>, Vec<bool>) {
    let mut map = Vec::with_capacity(c.pixels());
    let mut near = Vec::with_capacity(c.pixels());
    for p in 0..c.pixels() {
        let (ids, ws) = c.pixel(p);
        let mut sums = std::collections::BTreeMap::<i32, f64>::new();
        let mut background = 1.0 - f64::from(c.alpha[p]) + f64::from(c.lists.residual[p]);
        for (&g, &w) in ids.iter().zip(ws) {
            match of[g as usize] {
                -1 => background += f64::from(w),
                v => *sums.entry(v).or_default() += f64::from(w),
            }
        }
        // Candidates by weight, then by value (BTreeMap order: smaller values first).
        let mut cands: Vec<(i32, f64)> = sums.into_iter().collect();
        cands.sort_by(|a, b| b.1.total_cmp(&a.1));
        let (best, w) = cands.first().copied().unwrap_or((-1, f64::NEG_INFINITY));
        let (value, top, second) = if w > background {
            let second = cands.get(1).map_or(background, |c| c.1.max(background));
            (best, w, second)
        } else {
            (-1, background, w)
        };
        map.push(value);
        near.push(top - second < 1e-4);
    }
    (map, near)
}

/// IoU of class `c` on a view's predicted class map against the analytic truth.
fn iou(pred: &[i32], truth: &[i32], c: i32) -> f64 {
    let inter = pred
        .iter()
        .zip(truth)
        .filter(|(p, t)| **p == c && **t == c)
        .count();
    let union = pred
        .iter()
        .zip(truth)
        .filter(|(p, t)| (**p == c || **t == c) && **t != -1)
        .count();
    inter as f64 / union as f64
}

#[test]
fn outputs_are_standard_start_from_the_vote_and_predict_the_test_views() {
    let fx = Fixture::new("train-out", None);
    // Zero iterations: the initialisation reproduces the vote Gaussian by Gaussian.
    let s0 = fx.train(
        "init",
        &TrainOptions {
            iterations: 0,
            ..quick()
        },
    );
    assert_eq!(s0.changed_from_vote, 0);
    let pool = pool::build(
        &fx.cache,
        &fx.split.train,
        &fx.maps(),
        &fx.table,
        None,
        1,
        0,
        gs4city::vote::gamma_for(quick().gamma, &fx.maps()),
    )
    .unwrap();
    let init = fx.gaussians("init");
    for (g, a) in init.iter().zip(&pool.vote) {
        assert_eq!(g.0, a.label);
    }
    let s = fx.train("out", &quick());
    assert_eq!(s.iterations, 150);
    assert_eq!(s.history.len(), 3);
    assert!(
        s.history[2].ce < s.history[0].ce,
        "the loss falls: {:?}",
        s.history
    );
    assert_eq!(s.test_views, ["v00", "v04"]);
    let out = fx.dir.join("out");
    // classifier.json: background row first, one row per label of the training maps.
    let clf = train::predict::Classifier::read(&out.join("classifier.json")).unwrap();
    assert_eq!(clf.labels[0], -1);
    assert_eq!(clf.labels.len(), s.classes);
    assert!(clf.weights.iter().all(|r| r.len() == 16));
    // Per Gaussian: judged wall/window Gaussians keep their class.
    let g = fx.gaussians("out");
    let (mut right, mut total) = (0, 0);
    for ((_, c), t) in g.iter().zip(&fx.splats.judged) {
        if *t == classes::WALL || *t == classes::WINDOW {
            total += 1;
            right += usize::from(c == t);
        }
    }
    assert!(right as f64 > 0.95 * total as f64, "{right}/{total}");
    // Test view v04 against the analytic truth.
    let (shape, class) = npy::read::<i32>(&out.join("v04.class.npy")).unwrap();
    assert_eq!(shape, vec![120, 160]);
    let (_, inst) = npy::read::<i32>(&out.join("v04.instance.npy")).unwrap();
    // The default rule: the written per-Gaussian labels through the vote's pixel rule, read
    // by the test from the contribution lists.
    let (gl, gc): (Vec<i32>, Vec<i32>) = g.iter().copied().unzip();
    let view = fx.cache.load("v04").unwrap();
    for (name, of, written) in [("class", &gc, &class), ("label", &gl, &inst)] {
        let (want, near) = vote_by_hand(&view, of);
        let ties = near.iter().filter(|&&n| n).count();
        assert!(ties * 100 <= want.len(), "{name}: {ties} near ties");
        let wrong = (0..want.len())
            .filter(|&p| !near[p] && want[p] != written[p])
            .count();
        assert_eq!(wrong, 0, "{name} map: pixels against the rule");
        assert!(
            want.iter().any(|&v| v != -1),
            "{name} map is all background"
        );
    }
    // The paper's rule (rendered code → label of the largest logit): class map = class of the
    // label map.
    fx.train(
        "paper-rule",
        &TrainOptions {
            iterations: 0,
            rule: train::predict::Rule::Label,
            ..quick()
        },
    );
    let (_, pc) = npy::read::<i32>(&fx.dir.join("paper-rule/v04.class.npy")).unwrap();
    let (_, pl) = npy::read::<i32>(&fx.dir.join("paper-rule/v04.instance.npy")).unwrap();
    for (&c, &l) in pc.iter().zip(&pl) {
        assert_eq!(
            c,
            fx.table.class_of(l),
            "class map = class of the label map"
        );
    }
    let truth = wall::truth(&wall::views()[4], &fx.splats.floaters);
    assert!(iou(&class, &truth, classes::WALL) > 0.9);
    assert!(iou(&class, &truth, classes::WINDOW) > 0.6);
    // semantic.ply: read back by gs4city and by Python's plyfile.
    let (ply, _) =
        gs4city::splat::read_ply(&out.join("semantic.ply"), &Default::default()).unwrap();
    let codes: Vec<&[f64]> = (0..16)
        .map(|j| ply.extra(&format!("obj_dc_{j}")).unwrap().values.as_slice())
        .collect();
    assert!(codes[0].iter().any(|&x| x != 0.0));
    let label = &ply.extra("label").unwrap().values;
    assert!(label.iter().zip(&g).all(|(&a, b)| a == f64::from(b.0)));
    if !crate::common::python_can_import(
        "train::outputs_are_standard_start_from_the_vote_and_predict_the_test_views",
        &["plyfile"],
    ) {
        return;
    }
    let script = r#"
import sys
from plyfile import PlyData
v = PlyData.read(sys.argv[1])['vertex']
names = [p.name for p in v.properties]
need = ['x', 'y', 'z', 'opacity', 'label', 'class'] + ['obj_dc_%d' % j for j in range(16)]
missing = [n for n in need if n not in names]
assert not missing, missing
print(len(v.data), int(sum(v['label'] >= 0)), float(v['obj_dc_0'].sum()), int(v['class'][0]))
"#;
    let o = Command::new("python3")
        .args(["-c", script, out.join("semantic.ply").to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "plyfile: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let text = String::from_utf8_lossy(&o.stdout);
    let f: Vec<&str> = text.split_whitespace().collect();
    assert_eq!(f[0].parse::<usize>().unwrap(), g.len());
    assert_eq!(f[1].parse::<usize>().unwrap(), s.labelled);
    let sum0: f64 = codes[0].iter().sum();
    assert!((f[2].parse::<f64>().unwrap() - sum0).abs() < 1e-3 * sum0.abs().max(1.0));
    assert_eq!(f[3].parse::<i32>().unwrap(), g[0].1);
}

/// Bytes of every output file of a folder, by name.
fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap() != "summary.json")
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect();
    v.sort();
    v
}

#[test]
fn same_seed_same_outputs_with_one_or_two_threads() {
    let fx = Fixture::new("train-det", None);
    let opts = TrainOptions {
        iterations: 60,
        kl_samples: 300,
        ..quick()
    };
    for (threads, out) in [(1, "t1"), (2, "t2")] {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| fx.train(out, &opts));
    }
    let (a, b) = (files(&fx.dir.join("t1")), files(&fx.dir.join("t2")));
    assert!(a.len() >= 8, "{} files", a.len());
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.0, y.0);
        assert!(x.1 == y.1, "{} differs between 1 and 2 threads", x.0);
    }
    // Another seed trains differently (the check above can fail).
    fx.train("seed1", &TrainOptions { seed: 1, ..opts });
    let c = files(&fx.dir.join("seed1"));
    let clf = |v: &[(String, Vec<u8>)]| {
        v.iter()
            .find(|x| x.0 == "classifier.json")
            .unwrap()
            .1
            .clone()
    };
    assert_ne!(clf(&a), clf(&c));
}

#[test]
fn fused_label_maps_train_and_unknown_labels_are_refused() {
    let fx = Fixture::new("train-fused", None);
    // A fused folder: M_city with the window relabelled as image group 3 (id Δ + 3).
    let fuse = fx.dir.join("fuse");
    std::fs::create_dir_all(&fuse).unwrap();
    let delta = fx.table.delta;
    let window = fx
        .table
        .labels
        .iter()
        .find(|l| l.class == classes::WINDOW)
        .unwrap()
        .id;
    let views: Vec<View> = wall::views();
    for v in &views {
        let (shape, ids) =
            npy::read::<i32>(&fx.dir.join(format!("raycast/{}.ids.npy", v.stem()))).unwrap();
        let npx = shape[1] * shape[2];
        let m: Vec<i32> = ids[3 * npx..]
            .iter()
            .map(|&l| if l == window { delta + 3 } else { l })
            .collect();
        npy::write(&fuse.join(format!("{}.ids.npy", v.stem())), &shape[1..], &m).unwrap();
    }
    let mut labels = fx.table.labels.clone();
    labels.push(Label {
        id: delta + 3,
        source: Source::Image,
        entity: None,
        group: Some(3),
        class: classes::WINDOW,
        level: None,
    });
    let table = LabelTable::new(delta, labels).unwrap();
    let s = fx.train_with("fused", &quick(), &LabelMaps::Fused(fuse.clone()), &table);
    assert!(s.labelled > 0);
    let g = fx.gaussians("fused");
    let image = g.iter().filter(|x| x.0 == delta + 3).count();
    assert!(image > 100, "{image} Gaussians carry the image label");
    assert!(
        g.iter()
            .filter(|x| x.0 == delta + 3)
            .all(|x| x.1 == classes::WINDOW)
    );
    // The same maps with the city-only table: the image label is unknown → a clear error.
    let e = fx
        .try_train("bad", &quick(), &LabelMaps::Fused(fuse), &fx.table)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("ids.npy") && e.contains(&format!("label {}", delta + 3)),
        "{e}"
    );
    assert!(!fx.dir.join("bad/summary.json").exists());
}
