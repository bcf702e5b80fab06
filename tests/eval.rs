//! `gs4city eval`: hand-made label maps with answers computed by hand, file-level errors
//! and warnings, and a cross-check against the independent NumPy reference
//! `scripts/eval_reference.py` on seeded random maps (agreement ≤ 1e-9 on every number).
use std::path::{Path, PathBuf};
use std::process::Command;

use gs4city::eval::{self, EvalError};
use gs4city::npy;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;

// Class ids (DESIGN.md).
const N: i32 = -1;
const WALL: i32 = 0;
const ROOF: i32 = 1;
const WINDOW: i32 = 2;
const DOOR: i32 = 3;
const TREE: i32 = 6;
const CAR: i32 = 8;
const ROAD: i32 = 9;

struct TmpDir(PathBuf);

impl TmpDir {
    fn new(tag: &str) -> TmpDir {
        let d =
            crate::common::temp_dir().join(format!("gs4city-eval-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(d.join("gt")).unwrap();
        std::fs::create_dir_all(d.join("pred")).unwrap();
        TmpDir(d)
    }
    fn gt(&self) -> PathBuf {
        self.0.join("gt")
    }
    fn pred(&self) -> PathBuf {
        self.0.join("pred")
    }
    fn out(&self) -> PathBuf {
        self.0.join("out")
    }
}

impl Drop for TmpDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn put(dir: &Path, stem: &str, shape: [usize; 2], data: &[i32]) {
    npy::write(&dir.join(format!("{stem}.class.npy")), &shape, data).unwrap();
}

fn num(v: &Value, path: &[&str]) -> Option<f64> {
    let mut cur = v;
    for p in path {
        cur = match p.parse::<usize>() {
            Ok(i) if cur.is_array() => &cur[i],
            _ => &cur[*p],
        };
    }
    assert!(
        cur.is_number() || cur.is_null(),
        "{path:?} is not a number or null: {cur}"
    );
    cur.as_f64()
}

fn approx(v: &Value, path: &[&str], want: Option<f64>) {
    let got = num(v, path);
    match (got, want) {
        (Some(g), Some(w)) => assert!((g - w).abs() < 1e-12, "{path:?}: {g} ≠ {w}"),
        (g, w) => assert_eq!(g, w, "{path:?}"),
    }
}

fn run_eval(t: &TmpDir) -> Value {
    eval::run(&t.pred(), &t.gt(), &t.out()).unwrap();
    let text = std::fs::read_to_string(t.out().join("metrics.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// Two views, both evaluated, answers by hand.
///
/// View `a` (2×4), GT / prediction:
/// ```text
///   GT:   wall wall roof window      pred: wall wall wall  −1
///         tree tree road  −1               tree  car  wall roof
/// ```
/// Valid: 7 (one −1). Coarse: GT building = wall wall roof window (4), non-building = tree
/// tree road (3). Pred building: wall wall wall | . . wall roof(on −1, ignored).
///   tp = wall,wall,roof→wall = 3; fn = window→−1 = 1; fp = road→wall = 1; tn = tree→tree,
///   tree→car = 2. IoU 3/5, acc 5/7, prec 3/4, rec 3/4, F1 6/8.
/// Fine (GT wall roof window tree tree; road/−1 not evaluated):
///   wall: tp 2, fp 1 (roof→wall), fn 0 → IoU 2/3, prec 2/3
///   roof: tp 0, fp 0, fn 1 → IoU 0, prec 0 (present, never predicted)
///   window: tp 0, fn 1 → IoU 0, prec 0
///   tree: tp 1, fn 1 (→car), fp 0 → IoU 1/2, prec 1
///   image mIoU = (2/3 + 0 + 0 + 1/2) / 4 = 7/24.
///
/// View `b` (1×4): GT all −1 → skipped at both levels; its prediction is irrelevant.
///
/// View `c` (1×4): GT door door car car, prediction −1 everywhere.
///   Coarse: tp 0, fn 2, fp 0, tn 2 → IoU 0, acc 1/2, prec 0 (missed), rec 0, F1 0.
///   Fine: door IoU 0 prec 0; car: tp 0, fn 2 → IoU 0 prec 0; mIoU 0.
///
/// Paper protocol (images a, c): coarse IoU (3/5 + 0)/2 = 3/10, acc (5/7 + 1/2)/2 = 17/28,
/// prec (3/4 + 0)/2 = 3/8, rec 3/8; mIoU (7/24 + 0)/2 = 7/48; wall IoU 2/3 (one image);
/// car 0 (one image); door 0; person absent → null with 0 images.
/// Dataset: coarse tp 3, fn 3, fp 1, tn 4 → IoU 3/7, acc 7/11, prec 3/4, rec 1/2.
/// Fine summed: wall 2/3, roof 0, window 0, door 0, tree 1/2, car 0, person null →
/// dataset mIoU = (2/3 + 1/2) / 6 = 7/36.
#[test]
fn hand_computed_two_levels_two_protocols() {
    let t = TmpDir::new("hand");
    put(
        &t.gt(),
        "a",
        [2, 4],
        &[WALL, WALL, ROOF, WINDOW, TREE, TREE, ROAD, N],
    );
    put(
        &t.pred(),
        "a",
        [2, 4],
        &[WALL, WALL, WALL, N, TREE, CAR, WALL, ROOF],
    );
    put(&t.gt(), "b", [1, 4], &[N; 4]);
    put(&t.pred(), "b", [1, 4], &[WALL, ROOF, TREE, N]);
    put(&t.gt(), "c", [1, 4], &[DOOR, DOOR, CAR, CAR]);
    put(&t.pred(), "c", [1, 4], &[N; 4]);
    let m = run_eval(&t);

    // Per image a.
    let a = &m["per_image"][0];
    assert_eq!(a["stem"], "a");
    approx(a, &["valid_pixels"], Some(7.0));
    for (k, v) in [
        ("tp", 3.0),
        ("fn", 1.0),
        ("fp", 1.0),
        ("tn", 2.0),
        ("iou", 0.6),
        ("accuracy", 5.0 / 7.0),
        ("precision", 0.75),
        ("recall", 0.75),
        ("f1", 0.75),
    ] {
        approx(a, &["coarse", k], Some(v));
    }
    approx(a, &["fine", "iou", "wall"], Some(2.0 / 3.0));
    approx(a, &["fine", "precision", "wall"], Some(2.0 / 3.0));
    approx(a, &["fine", "iou", "roof"], Some(0.0));
    approx(a, &["fine", "precision", "roof"], Some(0.0));
    approx(a, &["fine", "iou", "window"], Some(0.0));
    approx(a, &["fine", "iou", "tree"], Some(0.5));
    approx(a, &["fine", "precision", "tree"], Some(1.0));
    approx(a, &["fine", "iou", "car"], None);
    approx(a, &["fine", "miou"], Some(7.0 / 24.0));
    // Per image b: skipped at both levels.
    let b = &m["per_image"][1];
    assert!(b["coarse"].is_null() && b["fine"].is_null());
    approx(b, &["ignored_pixels"], Some(4.0));
    // Per image c.
    let c = &m["per_image"][2];
    approx(c, &["coarse", "iou"], Some(0.0));
    approx(c, &["coarse", "accuracy"], Some(0.5));
    approx(c, &["coarse", "precision"], Some(0.0));
    approx(c, &["fine", "miou"], Some(0.0));
    approx(c, &["fine", "precision", "car"], Some(0.0));

    // Paper protocol.
    let p = &m["paper"];
    approx(p, &["coarse_skipped_no_valid_gt"], Some(1.0));
    approx(p, &["fine_skipped_no_fine_gt"], Some(1.0));
    approx(p, &["coarse", "iou", "mean"], Some(0.3));
    approx(p, &["coarse", "iou", "images"], Some(2.0));
    approx(p, &["coarse", "accuracy", "mean"], Some(17.0 / 28.0));
    approx(p, &["coarse", "precision", "mean"], Some(3.0 / 8.0));
    approx(p, &["coarse", "recall", "mean"], Some(3.0 / 8.0));
    approx(p, &["miou", "mean"], Some(7.0 / 48.0));
    approx(p, &["iou", "wall", "mean"], Some(2.0 / 3.0));
    approx(p, &["iou", "wall", "images"], Some(1.0));
    approx(p, &["iou", "car", "mean"], Some(0.0));
    approx(p, &["iou", "door", "mean"], Some(0.0));
    approx(p, &["iou", "person", "mean"], None);
    approx(p, &["iou", "person", "images"], Some(0.0));

    // Dataset level.
    let d = &m["dataset"];
    approx(d, &["coarse", "iou"], Some(3.0 / 7.0));
    approx(d, &["coarse", "accuracy"], Some(7.0 / 11.0));
    approx(d, &["coarse", "precision"], Some(0.75));
    approx(d, &["coarse", "recall"], Some(0.5));
    approx(d, &["fine", "miou"], Some(7.0 / 36.0));
    approx(d, &["fine", "iou", "person"], None);
    approx(d, &["fine", "iou", "car"], Some(0.0));
    assert_eq!(
        d["fine"]["classes_present"],
        serde_json::json!(["wall", "roof", "window", "door", "tree", "car"])
    );
    // No NaN anywhere: serde_json would have refused to parse it; and the file holds a
    // definitions field.
    assert!(m["definitions"]["paper"].is_string());
}

/// Perfect prediction: every number is 1 (or, for absent classes, null).
#[test]
fn perfect_prediction_is_all_ones() {
    let t = TmpDir::new("perfect");
    let g = [WALL, ROOF, WINDOW, DOOR, TREE, CAR, ROAD, N, WALL];
    put(&t.gt(), "v", [3, 3], &g);
    put(&t.pred(), "v", [3, 3], &g);
    let m = run_eval(&t);
    for k in ["iou", "accuracy", "precision", "recall", "f1"] {
        approx(&m, &["paper", "coarse", k, "mean"], Some(1.0));
        approx(&m, &["dataset", "coarse", k], Some(1.0));
    }
    approx(&m, &["paper", "miou", "mean"], Some(1.0));
    approx(&m, &["dataset", "fine", "miou"], Some(1.0));
    approx(&m, &["dataset", "fine", "iou", "person"], None);
}

/// All wrong: building ↔ non-building swapped, fine classes permuted.
/// GT wall roof tree car; pred tree car wall roof → coarse tp 0, fp 2, fn 2, tn 0:
/// IoU 0, acc 0, prec 0, rec 0; every fine class IoU 0, precision 0; mIoU 0.
#[test]
fn all_wrong_is_all_zeros() {
    let t = TmpDir::new("wrong");
    put(&t.gt(), "v", [2, 2], &[WALL, ROOF, TREE, CAR]);
    put(&t.pred(), "v", [2, 2], &[TREE, CAR, WALL, ROOF]);
    let m = run_eval(&t);
    for k in ["iou", "accuracy", "precision", "recall", "f1"] {
        approx(&m, &["dataset", "coarse", k], Some(0.0));
    }
    for c in ["wall", "roof", "tree", "car"] {
        approx(&m, &["paper", "iou", c, "mean"], Some(0.0));
        approx(&m, &["paper", "precision", c, "mean"], Some(0.0));
    }
    approx(&m, &["paper", "miou", "mean"], Some(0.0));
}

/// A prediction of another aspect ratio is another image: an error naming it, not a stretch.
#[test]
fn a_prediction_of_another_shape_is_refused() {
    let t = TmpDir::new("shape");
    put(&t.gt(), "v", [40, 60], &[WALL; 2400]);
    put(&t.pred(), "v", [20, 60], &[WALL; 1200]);
    let e = eval::evaluate_dirs(&t.pred(), &t.gt())
        .unwrap_err()
        .to_string();
    // Both files are named.
    let (pred, gt) = (t.pred().join("v.class.npy"), t.gt().join("v.class.npy"));
    assert!(
        e.contains(&format!("{}: a 20×60 prediction", pred.display()))
            && e.contains(&format!("the 40×60 ground truth {}", gt.display())),
        "{e}"
    );
    // Half the resolution, the same shape: resized.
    put(&t.pred(), "v", [20, 30], &[WALL; 600]);
    assert!(eval::evaluate_dirs(&t.pred(), &t.gt()).unwrap().images[0].resized());
}

/// Size mismatch: GT 2×4, prediction 1×2 (wall, tree) → resized to
/// `wall wall tree tree` on both rows. GT: wall wall wall tree / window window tree tree.
/// Coarse: GT building = 3 walls + 2 windows; predicted building = columns 0,1.
///   tp = (0,0),(0,1),(1,0),(1,1) = 4; fn = (0,2) wall→tree = 1; fp 0; tn 3.
///   IoU 4/5, acc 7/8. Fine: wall tp 2, fp 2 (windows→wall), fn 1 → IoU 2/5;
///   window tp 0 fn 2 → 0; tree tp 3, fp 1 → IoU 3/4. mIoU = (2/5 + 0 + 3/4)/3 = 23/60.
#[test]
fn size_mismatch_is_resized_with_warning() {
    let t = TmpDir::new("resize");
    put(
        &t.gt(),
        "v",
        [2, 4],
        &[WALL, WALL, WALL, TREE, WINDOW, WINDOW, TREE, TREE],
    );
    put(&t.pred(), "v", [1, 2], &[WALL, TREE]);
    let ev = eval::evaluate_dirs(&t.pred(), &t.gt()).unwrap();
    assert!(ev.images[0].resized());
    assert!(
        ev.warnings
            .iter()
            .any(|w| w.contains("resized") && w.contains("1×2 → 2×4")),
        "{:?}",
        ev.warnings
    );
    let m = run_eval(&t);
    approx(&m, &["resized_predictions"], Some(1.0));
    approx(&m, &["dataset", "coarse", "iou"], Some(0.8));
    approx(&m, &["dataset", "coarse", "accuracy"], Some(7.0 / 8.0));
    approx(&m, &["dataset", "fine", "iou", "wall"], Some(0.4));
    approx(&m, &["dataset", "fine", "iou", "tree"], Some(0.75));
    approx(&m, &["paper", "miou", "mean"], Some(23.0 / 60.0));
}

#[test]
fn missing_prediction_is_an_error_naming_the_stem() {
    let t = TmpDir::new("missing");
    put(&t.gt(), "view_007", [1, 1], &[WALL]);
    put(&t.gt(), "view_008", [1, 1], &[WALL]);
    put(&t.pred(), "view_008", [1, 1], &[WALL]);
    let err = eval::evaluate_dirs(&t.pred(), &t.gt()).unwrap_err();
    assert!(matches!(&err, EvalError::MissingPrediction { stem, .. } if stem == "view_007"));
    assert!(err.to_string().contains("view_007"));
}

#[test]
fn prediction_without_gt_is_a_warning() {
    let t = TmpDir::new("extra");
    put(&t.gt(), "a", [1, 1], &[WALL]);
    put(&t.pred(), "a", [1, 1], &[WALL]);
    put(&t.pred(), "zz_extra", [1, 1], &[WALL]);
    let ev = eval::evaluate_dirs(&t.pred(), &t.gt()).unwrap();
    assert_eq!(ev.predictions_without_gt, vec!["zz_extra".to_string()]);
    assert!(ev.warnings.iter().any(|w| w.contains("zz_extra")));
    assert_eq!(ev.images.len(), 1);
}

#[test]
fn bad_dtype_shape_and_values_name_the_file() {
    let t = TmpDir::new("bad");
    put(&t.gt(), "a", [1, 2], &[WALL, ROOF]);
    // float32 prediction
    npy::write(&t.pred().join("a.class.npy"), &[1, 2], &[0.0f32, 1.0]).unwrap();
    let err = eval::evaluate_dirs(&t.pred(), &t.gt()).unwrap_err();
    assert!(err.to_string().contains("a.class.npy"), "{err}");
    // 3-D prediction
    npy::write(&t.pred().join("a.class.npy"), &[1, 1, 2], &[0i32, 1]).unwrap();
    let err = eval::evaluate_dirs(&t.pred(), &t.gt()).unwrap_err();
    assert!(matches!(&err, EvalError::IdMap(_)), "{err}");
    assert!(err.to_string().contains("2-D H×W class map"), "{err}");
    assert!(err.to_string().contains("a.class.npy"), "{err}");
    // GT value 42 is not a class id
    put(&t.pred(), "a", [1, 2], &[WALL, ROOF]);
    put(&t.gt(), "a", [1, 2], &[WALL, 42]);
    let err = eval::evaluate_dirs(&t.pred(), &t.gt()).unwrap_err();
    assert!(
        matches!(&err, EvalError::GtValue { value: 42, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("a.class.npy"), "{err}");
    // no GT at all
    let empty = TmpDir::new("empty");
    let err = eval::evaluate_dirs(&empty.pred(), &empty.gt()).unwrap_err();
    assert!(matches!(err, EvalError::NoGroundTruth { .. }));
}

/// The command line end to end: files written, table printed, error exit on a missing
/// prediction.
#[test]
fn cli_writes_metrics_summary_and_table() {
    let t = TmpDir::new("cli");
    put(&t.gt(), "a", [1, 3], &[WALL, ROOF, TREE]);
    put(&t.pred(), "a", [1, 3], &[WALL, N, TREE]);
    let bin = env!("CARGO_BIN_EXE_gs4city");
    let args = |t: &TmpDir| {
        [
            "eval".to_string(),
            "--pred".into(),
            t.pred().display().to_string(),
            "--gt".into(),
            t.gt().display().to_string(),
            "--out".into(),
            t.out().display().to_string(),
        ]
    };
    let out = Command::new(bin).args(args(&t)).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("Table 1") && stdout.contains("Table 2"),
        "{stdout}"
    );
    assert!(stdout.contains("paper (per image)") && stdout.contains("mIoU"));
    assert!(t.out().join("metrics.json").is_file() && t.out().join("summary.json").is_file());
    let s: Value =
        serde_json::from_str(&std::fs::read_to_string(t.out().join("summary.json")).unwrap())
            .unwrap();
    // Coarse: tp 1, fn 1, tn 1 → IoU 1/2.
    approx(&s, &["paper", "coarse_iou"], Some(0.5));
    put(&t.gt(), "b", [1, 1], &[WALL]);
    let out = Command::new(bin).args(args(&t)).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("'b'"));
}

// ---------------------------------------------------------------------------------------
// Cross-check against scripts/eval_reference.py

/// A structured random label map: rectangles of classes over a background, plus noise.
fn random_map(rng: &mut ChaCha8Rng, h: usize, w: usize, palette: &[i32], noise: f64) -> Vec<i32> {
    let mut m = vec![palette[0]; h * w];
    for _ in 0..rng.random_range(3..9) {
        let c = palette[rng.random_range(0..palette.len())];
        let (r0, c0) = (rng.random_range(0..h), rng.random_range(0..w));
        let (r1, c1) = (
            (r0 + rng.random_range(1..=h / 2 + 1)).min(h),
            (c0 + rng.random_range(1..=w / 2 + 1)).min(w),
        );
        for r in r0..r1 {
            m[r * w + c0..r * w + c1].fill(c);
        }
    }
    for v in m.iter_mut() {
        if rng.random_bool(noise) {
            *v = palette[rng.random_range(0..palette.len())];
        }
    }
    m
}

/// A prediction derived from a GT map: mostly right, some blocks and pixels relabelled.
fn perturb(rng: &mut ChaCha8Rng, gt: &[i32], h: usize, w: usize) -> Vec<i32> {
    const PRED: [i32; 15] = [-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 0, 6];
    let mut p: Vec<i32> = gt.iter().map(|&g| if g < 0 { 9 } else { g }).collect();
    let wrong = random_map(rng, h, w, &PRED, 0.1);
    let keep = random_map(rng, h, w, &[1, 1, 0], 0.05);
    for i in 0..p.len() {
        if keep[i] == 0 {
            p[i] = wrong[i];
        }
    }
    p
}

/// Every key, number (≤ 1e-9), null, string and bool of gs4city's metrics.json agrees with
/// the reference's; `definitions` is gs4city's only extra key.
fn compare(a: &Value, b: &Value, path: &str, n: &mut usize) {
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let kx: Vec<&String> = x.keys().filter(|k| *k != "definitions").collect();
            let ky: Vec<&String> = y.keys().collect();
            assert_eq!(kx, ky, "keys differ at {path}");
            for k in kx {
                compare(&x[k], &y[k], &format!("{path}.{k}"), n);
            }
        }
        (Value::Array(x), Value::Array(y)) => {
            assert_eq!(x.len(), y.len(), "lengths differ at {path}");
            for (i, (u, v)) in x.iter().zip(y).enumerate() {
                compare(u, v, &format!("{path}[{i}]"), n);
            }
        }
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!(
                (x - y).abs() <= 1e-9,
                "{path}: gs4city {x} vs reference {y}"
            );
            *n += 1;
        }
        _ => assert_eq!(a, b, "values differ at {path}"),
    }
}

#[test]
fn agrees_with_numpy_reference() {
    if !crate::common::python_can_import("eval::agrees_with_numpy_reference", &["numpy"]) {
        return;
    }
    let t = TmpDir::new("xcheck");
    let mut rng = ChaCha8Rng::seed_from_u64(20240611);
    // GT palette: −1 (ignore) and every class id; one view without fine classes, one all −1.
    let full: Vec<i32> = (-1..=11).chain([0, 0, 1, 2, 6]).collect();
    let views: [(&str, usize, usize, &[i32]); 7] = [
        ("v0", 48, 64, &full),
        ("v1", 37, 53, &full),
        ("v2", 60, 40, &full),
        ("v3_nofine", 30, 30, &[4, 5, 9, 10, 11, -1]),
        ("v4_ignored", 20, 25, &[-1]),
        ("v5_resized", 50, 70, &full),
        ("v6_two", 33, 47, &[0, 8, -1]),
    ];
    for (stem, h, w, palette) in views {
        let g = random_map(&mut rng, h, w, palette, 0.05);
        put(&t.gt(), stem, [h, w], &g);
        if stem == "v5_resized" {
            // A prediction at another resolution (not an integer factor).
            let (ph, pw) = (31, 43);
            let p = random_map(&mut rng, ph, pw, &[0, 1, 2, 3, 6, 7, 8, -1], 0.05);
            put(&t.pred(), stem, [ph, pw], &p);
        } else {
            let mut p = perturb(&mut rng, &g, h, w);
            if stem == "v1" {
                p[3] = 77; // an unknown prediction value
            }
            put(&t.pred(), stem, [h, w], &p);
        }
    }
    put(&t.pred(), "v9_no_gt", [2, 2], &[0, 0, 0, 0]);

    let m = run_eval(&t);
    let ref_path = t.0.join("reference.json");
    let out = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/eval_reference.py"))
        .arg("--pred")
        .arg(t.pred())
        .arg("--gt")
        .arg(t.gt())
        .arg("--out")
        .arg(&ref_path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "eval_reference.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: Value = serde_json::from_str(&std::fs::read_to_string(&ref_path).unwrap()).unwrap();
    let mut n = 0;
    compare(&m, &r, "", &mut n);
    eprintln!("{n} numbers agree");
    assert!(n > 700, "only {n} numbers compared");
    eprintln!(
        "{}",
        eval::tables(&eval::metrics_json(
            &eval::evaluate_dirs(&t.pred(), &t.gt()).unwrap()
        ))
    );
    // Not degenerate: the maps give intermediate scores.
    let miou = num(&m, &["paper", "miou", "mean"]).unwrap();
    assert!(miou > 0.2 && miou < 0.95, "paper mIoU {miou}");
    // The set exercises what it should.
    approx(&m, &["resized_predictions"], Some(1.0));
    approx(&m, &["paper", "coarse_skipped_no_valid_gt"], Some(1.0));
    approx(&m, &["paper", "fine_skipped_no_fine_gt"], Some(2.0));
    assert_eq!(m["predictions_without_gt"], serde_json::json!(["v9_no_gt"]));
    assert!(m["per_image"][1]["unknown_pred_values"].as_u64() == Some(1));
}
