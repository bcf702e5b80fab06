//! `demo`, `associate`, `fuse` and `train` through the binary, each checked on a value against
//! an expectation computed outside the stage: the demo's metrics against the NumPy evaluation
//! (`scripts/eval_reference.py`) of its own predictions, and the three stages (run by hand on the
//! demo's scene and run folders) against the simulator's ground truth (`gt/`, itself checked
//! against a NumPy re-derivation in `gt_reference`).
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common::python_can_import;
use gs4city::npy;

fn gs4city(args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(args)
        .arg("-q")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "gs4city {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn stems(dir: &Path, suffix: &str) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| {
            let n = e.unwrap().file_name().to_string_lossy().into_owned();
            n.strip_suffix(suffix).map(str::to_string)
        })
        .collect();
    v.sort();
    v
}

/// `scripts/eval_reference.py` on the `<stem>.class.npy` of `pred` against the same stems of
/// `scene/gt` (copied to `work`): its metrics JSON.
fn reference_eval(pred: &Path, scene: &Path, work: &Path) -> serde_json::Value {
    let gt = work.join("gt");
    std::fs::create_dir_all(&gt).unwrap();
    for s in stems(pred, ".class.npy") {
        let f = format!("{s}.class.npy");
        std::fs::copy(scene.join("gt").join(&f), gt.join(&f)).unwrap();
    }
    let json = work.join("reference.json");
    let out = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/eval_reference.py"))
        .arg("--pred")
        .arg(pred)
        .arg("--gt")
        .arg(&gt)
        .arg("--out")
        .arg(&json)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap()
}

fn get(v: &serde_json::Value, path: &[&str]) -> f64 {
    path.iter()
        .fold(v, |v, k| &v[*k])
        .as_f64()
        .unwrap_or_else(|| panic!("{path:?} in {v}"))
}

#[test]
fn demo_associate_fuse_and_train_through_the_binary_give_measured_values() {
    if !python_can_import(
        "cli_stages::demo_associate_fuse_and_train_through_the_binary_give_measured_values",
        &["numpy"],
    ) {
        return;
    }
    let dir = crate::common::temp_dir().join(format!("gs4city-cli-stages-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let d = |s: &str| -> PathBuf { dir.join(s) };
    let p = |s: &str| d(s).to_string_lossy().into_owned();

    // demo: its eval equals the NumPy evaluation of its predictions (lift/, the test views).
    gs4city(&["demo", "--out", &p("demo")]);
    let (scene, run) = (d("demo/scene"), d("demo/run"));
    assert!(run.join("report.html").is_file());
    let reported: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("eval/metrics.json")).unwrap()).unwrap();
    let reference = reference_eval(&run.join("lift"), &scene, &d("ref_lift"));
    for key in [
        &["paper", "miou", "mean"][..],
        &["paper", "coarse", "iou", "mean"],
        &["dataset", "fine", "miou"],
        &["dataset", "coarse", "iou"],
    ] {
        let (a, b) = (get(&reported, key), get(&reference, key));
        assert!((a - b).abs() <= 1e-9, "{key:?}: demo {a} vs reference {b}");
    }
    assert!(get(&reference, &["paper", "coarse", "iou", "mean"]) > 0.9);
    assert!(get(&reference, &["paper", "miou", "mean"]) > 0.5);

    let s = |x: &str| scene.join(x).to_string_lossy().into_owned();
    let r = |x: &str| run.join(x).to_string_lossy().into_owned();
    // associate: every group's pixels are (pixel-weighted) ≥ 90 % one simulated instance.
    gs4city(&[
        "associate",
        "--masks",
        &r("masks"),
        "--cache",
        &r("render"),
        "--ply",
        &s("point_cloud.ply"),
        "--colmap",
        &s("sparse/0"),
        "--citymodel",
        &r("citymodel"),
        "--features",
        &s("features"),
        "--sam",
        &s("masks"),
        "--split",
        &s("scene.json"),
        "--out",
        &p("assoc"),
    ]);
    let groups: serde_json::Value =
        serde_json::from_slice(&std::fs::read(d("assoc/groups.json")).unwrap()).unwrap();
    let n_groups = groups["groups"].as_array().unwrap().len();
    let (mut total, mut majority) = (0usize, 0usize);
    let mut seen = std::collections::BTreeSet::new();
    let views = stems(&d("assoc"), ".ids.npy");
    assert!(views.len() >= 10, "{views:?}");
    for v in &views {
        let (_, ids) = npy::read::<i32>(&d("assoc").join(format!("{v}.ids.npy"))).unwrap();
        let (_, inst) = npy::read::<i32>(&scene.join(format!("gt/{v}.instance.npy"))).unwrap();
        let mut by_group: BTreeMap<i32, BTreeMap<i32, usize>> = BTreeMap::new();
        for (&g, &t) in ids.iter().zip(&inst) {
            if g >= 0 {
                *by_group.entry(g).or_default().entry(t).or_default() += 1;
            }
        }
        for (g, counts) in by_group {
            seen.insert(g);
            total += counts.values().sum::<usize>();
            majority += counts.values().max().unwrap();
        }
    }
    assert!(
        seen.len() == n_groups && n_groups >= 5,
        "{} groups in the maps, {n_groups} in groups.json",
        seen.len()
    );
    assert!(
        majority as f64 >= 0.9 * total as f64,
        "group purity {majority}/{total}"
    );

    // fuse: the fused labels' classes agree with the simulated class on ≥ 90 % of the pixels
    // both label.
    gs4city(&[
        "fuse",
        "--associate",
        &p("assoc"),
        "--raycast",
        &r("raycast"),
        "--citymodel",
        &r("citymodel"),
        "--colmap",
        &s("sparse/0"),
        "--sam",
        &s("masks"),
        "--masks",
        &r("masks"),
        "--split",
        &s("scene.json"),
        "--out",
        &p("fuse"),
    ]);
    let labels: serde_json::Value =
        serde_json::from_slice(&std::fs::read(d("fuse/labels.json")).unwrap()).unwrap();
    let class_of: BTreeMap<i64, i64> = labels["labels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| (l["id"].as_i64().unwrap(), l["class"].as_i64().unwrap()))
        .collect();
    let (mut both, mut right) = (0usize, 0usize);
    for v in &views {
        let (_, ids) = npy::read::<i32>(&d("fuse").join(format!("{v}.ids.npy"))).unwrap();
        let (_, cls) = npy::read::<i32>(&scene.join(format!("gt/{v}.class.npy"))).unwrap();
        for (&l, &c) in ids.iter().zip(&cls) {
            if l >= 0 && c >= 0 {
                both += 1;
                right += usize::from(class_of[&i64::from(l)] == i64::from(c));
            }
        }
    }
    assert!(both > 1_000_000, "{both} labelled pixels");
    assert!(
        right as f64 >= 0.9 * both as f64,
        "fused class accuracy {right}/{both}"
    );

    // train (on the fused labels): its test-view maps, scored by the NumPy evaluation against
    // the simulated GT.
    gs4city(&[
        "train",
        "--ply",
        &s("point_cloud.ply"),
        "--colmap",
        &s("sparse/0"),
        "--cache",
        &r("render"),
        "--citymodel",
        &r("citymodel"),
        "--fuse",
        &p("fuse"),
        "--iterations",
        "300",
        "--split",
        &s("scene.json"),
        "--out",
        &p("train"),
    ]);
    assert_eq!(stems(&d("train"), ".class.npy"), ["orbit_000", "orbit_008"]);
    let scored = reference_eval(&d("train"), &scene, &d("ref_train"));
    let (coarse, miou) = (
        get(&scored, &["paper", "coarse", "iou", "mean"]),
        get(&scored, &["paper", "miou", "mean"]),
    );
    assert!(
        coarse > 0.9 && miou > 0.5,
        "train: coarse IoU {coarse}, fine mIoU {miou}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
