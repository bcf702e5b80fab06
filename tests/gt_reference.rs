//! The simulated ground truth against independent re-derivations.
//!
//! * The per-view maps: `scripts/gt_reference.py` reads only the files of a `gs4city synth` scene
//!   (the PLY, the per-Gaussian truth table, the COLMAP text cameras, `min_alpha`) and splats the
//!   sampled pixels with NumPy (float64, INRIA forward rules) to find each pixel's top-1
//!   Gaussian; its class and instance must agree with `gt/<stem>.class.npy` / `.instance.npy`.
//!   Every simulated metric of the README rests on these maps. On the `small` preset (every view)
//!   and on four views of the `street` preset (two orbit, two street-level).
//! * The per-Gaussian truth table itself: `scripts/truth_geometry.py` reads the scene's CityGML
//!   with ElementTree, triangulates every patch with CGAL (the functions of
//!   `scripts/cgal_reference.py`) and checks on the `street` preset that every city row's class
//!   and hierarchy follow from its entity, that sampled city Gaussians lie on their entity's
//!   surface (windows and doors: within the recess behind it), and that every tree, car and
//!   person Gaussian lies in the solids its object was drawn in (`summary.json`); and that the
//!   check fails on a truth table whose labels were moved.
//!
//! The rule at occlusion boundaries: a sampled pixel whose 3×3 neighbourhood in the GT map is
//! not uniform (or that lies on the image border) is counted apart — there the top-1 Gaussian
//! is decided by weights that can differ in the last f32 bits between the two implementations.
//! Away from boundaries at least 99.9 % must agree, and at boundaries at least 97 % (measured:
//! 100 % and 100 % on both presets; the re-derivation with its pixel centres half a pixel off
//! leaves the interior at 100 % and the boundaries at 87–88 %, which the street test checks).
//! No class is excluded: sky, buildings, ground, trees, cars, persons and floaters are all
//! Gaussians with a truth row.
use std::path::Path;
use std::process::Command;

use crate::common::python_can_import;

#[test]
fn synthetic_ground_truth_agrees_with_a_numpy_re_derivation() {
    if !python_can_import(
        "gt_reference::synthetic_ground_truth_agrees_with_a_numpy_re_derivation",
        &["numpy"],
    ) {
        return;
    }
    let dir = crate::common::temp_dir().join(format!("gs4city-gtref-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let scene = dir.join("small");
    let st = Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(["synth", "--preset", "small", "-q", "--out"])
        .arg(&scene)
        .status()
        .unwrap();
    assert!(st.success());
    let t = gt_reference(&scene, 14, "small");
    let n = |k: &str| t[k].as_u64().unwrap();
    let background = n("background_interior");
    assert!(background > 1000, "too few sky pixels: {t}");
    assert!(
        n("class_interior") - background > 10_000,
        "too few scene pixels: {t}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Least agreement of interior and of boundary pixels.
const MIN_INTERIOR: f64 = 0.999;
const MIN_BOUNDARY: f64 = 0.97;

/// Runs `scripts/gt_reference.py` on every view of `scene` (4 000 pixels each, seed 7), checks
/// the agreement bounds and returns its totals.
fn gt_reference(scene: &Path, views: u64, what: &str) -> serde_json::Value {
    let t = gt_reference_totals(scene, None);
    let n = |k: &str| t[k].as_u64().unwrap();
    assert_eq!(n("sampled"), views * 4000, "{t}");
    eprintln!(
        "GT re-derivation, {what}: class {}/{} interior pixels agree ({} of {} at boundaries), instance {}/{} ({} of {})",
        n("class_agree"),
        n("class_interior"),
        n("class_boundary_agree"),
        n("class_boundary"),
        n("instance_agree"),
        n("instance_interior"),
        n("instance_boundary_agree"),
        n("instance_boundary")
    );
    for map in ["class", "instance"] {
        let interior = n(&format!("{map}_interior"));
        let agree = n(&format!("{map}_agree"));
        // Most samples are away from boundaries, and both sky and scene are sampled.
        assert!(interior * 10 >= n("sampled") * 8, "{map}: {t}");
        assert!(
            agree as f64 >= MIN_INTERIOR * interior as f64,
            "{map}: {agree} of {interior} interior pixels agree: {t}"
        );
        let boundary = n(&format!("{map}_boundary"));
        let agree = n(&format!("{map}_boundary_agree"));
        assert!(
            agree as f64 >= MIN_BOUNDARY * boundary as f64,
            "{map}: {agree} of {boundary} boundary pixels agree: {t}"
        );
    }
    t
}

/// The totals of `scripts/gt_reference.py` on every view of `scene` (4 000 pixels each, seed
/// 7), with the deliberate `defect`, if any.
fn gt_reference_totals(scene: &Path, defect: Option<&str>) -> serde_json::Value {
    let mut c = Command::new("python3");
    c.arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/gt_reference.py"))
        .arg(scene)
        .args(["--samples", "4000", "--seed", "7"]);
    if let Some(d) = defect {
        c.args(["--defect", d]);
    }
    let out = c.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    r["total"].clone()
}

const STREET: &str = "gt_reference::street_truth_lies_on_its_city_model_and_in_its_objects";

/// The `street` preset with four views (two orbit, two street-level) instead of 128: the views
/// are drawn from their own random stream after every Gaussian is made, so `point_cloud.ply` and
/// `gt/gaussians.npy` are byte for byte those of the whole preset (compared when this was
/// written), at 180 MB instead of 1.1 GB.
fn street_scene(dir: &Path) -> std::path::PathBuf {
    let shared = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/citygml");
    assert!(shared.is_dir(), "{} missing", shared.display());
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir).unwrap();
    let config = dir.join("four-views.toml");
    std::fs::write(&config, "[cameras]\norbit_views = 2\nstreet_views = 2\n").unwrap();
    let scene = dir.join("street");
    let out = Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(["-q", "synth", "--preset", "street", "--config"])
        .arg(&config)
        .arg("--out")
        .arg(&scene)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    scene
}

/// `scripts/truth_geometry.py` on `scene` (100 000 sampled city Gaussians, seed 7), the truth
/// table `truth` in place of `gt/gaussians.npy` when given.
fn truth_geometry(scene: &Path, truth: Option<&Path>) -> serde_json::Value {
    let mut c = Command::new("python3");
    c.arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/truth_geometry.py"))
        .arg(scene)
        .args(["--samples", "100000", "--seed", "7", "--tol", "0.001"]);
    if let Some(t) = truth {
        c.arg("--truth").arg(t);
    }
    let out = c.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// The per-Gaussian truth of the SIMULATED `street` preset against its geometry, read
/// independently (`scripts/truth_geometry.py`: ElementTree + CGAL + NumPy, f64): the entity
/// table matches the CityGML; every city row's class and feature/surface/part follow from its
/// entity; 100 000 sampled city Gaussians lie within 1 mm of their entity's surface (windows
/// and doors within the 0.15 m recess + 1 mm; measured when this was written: 0.50 mm and
/// 0.15004 m at most); every tree, car and person Gaussian lies within 1 mm of the solids its
/// object was drawn in, with its object's class and count. Then the same check on a copy of
/// the truth with one wall Gaussian in 50 relabelled as another wall (whole rows copied, so
/// class and hierarchy stay consistent) and two cars' labels swapped must fail; and
/// `gt_reference.py` re-derives the maps of the four views.
#[test]
fn street_truth_lies_on_its_city_model_and_in_its_objects() {
    if !python_can_import(STREET, &["numpy", "CGAL"]) {
        return;
    }
    let dir = crate::common::temp_dir().join(format!("gs4city-gtgeom-{}", std::process::id()));
    let scene = street_scene(&dir);
    let r = truth_geometry(&scene, None);
    let n = |k: &str| r[k].as_u64().unwrap_or_else(|| panic!("{k}: {r}"));
    eprintln!(
        "street truth against geometry: {} city rows, {} sampled, max distance {} m (openings {} m), {} object Gaussians of {} objects",
        n("city_rows"),
        n("sampled"),
        r["max_distance"],
        r["max_distance_openings"],
        n("object_gaussians"),
        n("objects")
    );
    assert_eq!(r["entity_table"]["mismatch"], serde_json::json!([]), "{r}");
    assert!(r["entity_table"]["checked"].as_u64().unwrap() > 2000, "{r}");
    assert!(n("city_rows") * 2 > n("gaussians"), "{r}");
    for k in [
        "city_rows_bad_class",
        "city_rows_bad_chain",
        "city_rows_not_finest",
        "unmeasured",
        "off_surface",
        "object_outside",
        "object_bad_class",
        "object_unknown",
        "simulated_rows_bad_class",
        "rows_unaccounted",
    ] {
        assert_eq!(n(k), 0, "{k}: {r}");
    }
    assert_eq!(n("sampled"), 100_000);
    assert_eq!(r["object_count_mismatch"], serde_json::json!([]), "{r}");
    // Every class of the city model is sampled, and every kind of object is there.
    for c in [
        "wall",
        "roof",
        "window",
        "door",
        "ground_surface",
        "installation",
    ] {
        assert!(
            r["by_class"][c]["sampled"].as_u64().unwrap_or(0) >= 100,
            "{c}: {r}"
        );
    }
    for c in ["tree", "car", "person"] {
        assert!(r["objects_by_class"][c].as_u64().unwrap() >= 10, "{c}: {r}");
    }
    assert!(n("object_gaussians") > 50_000, "{r}");

    // Moved labels must fail it.
    let truth = scene.join("gt/gaussians.npy");
    let (shape, mut t) = gs4city::npy::read::<i32>(&truth).unwrap();
    assert_eq!(shape[1], 5);
    let row = |t: &[i32], i: usize| -> [i32; 5] { t[5 * i..5 * i + 5].try_into().unwrap() };
    let walls: Vec<usize> = (0..shape[0])
        .filter(|&i| row(&t, i)[0] == 0 && (0..1_000_000).contains(&row(&t, i)[1]))
        .collect();
    let mut moved = 0;
    for (k, &i) in walls.iter().enumerate().step_by(50) {
        let j = walls[(k + walls.len() / 2) % walls.len()];
        if row(&t, j)[1] != row(&t, i)[1] {
            let other = row(&t, j);
            t[5 * i..5 * i + 5].copy_from_slice(&other);
            moved += 1;
        }
    }
    let objects: serde_json::Value =
        serde_json::from_slice(&std::fs::read(scene.join("summary.json")).unwrap()).unwrap();
    let car: Vec<(i64, u64)> = objects["objects"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|o| o["class"] == "car")
        .map(|o| {
            (
                o["instance"].as_i64().unwrap(),
                o["gaussians"].as_u64().unwrap(),
            )
        })
        .take(2)
        .collect();
    let (a, b) = (car[0].0 as i32, car[1].0 as i32);
    for i in 0..shape[0] {
        if t[5 * i + 1] == a {
            t[5 * i + 1] = b;
        } else if t[5 * i + 1] == b {
            t[5 * i + 1] = a;
        }
    }
    let bad = dir.join("moved.npy");
    gs4city::npy::write(&bad, &shape, &t).unwrap();
    let p = truth_geometry(&scene, Some(&bad));
    let m = |k: &str| p[k].as_u64().unwrap_or_else(|| panic!("{k}: {p}"));
    eprintln!(
        "moved labels: {moved} wall rows relabelled ({} of the sampled Gaussians off their surface), cars {a} and {b} swapped ({} of their {} Gaussians outside)",
        m("off_surface"),
        m("object_outside"),
        car[0].1 + car[1].1
    );
    // Rows copied whole: class and hierarchy stay consistent, only the geometry tells.
    assert_eq!(m("city_rows_bad_class"), 0, "{p}");
    assert_eq!(m("city_rows_bad_chain"), 0, "{p}");
    assert!(moved > 5000, "{moved}");
    // ~1 in 50 of the ~52 000 sampled walls was moved; nearly all of them land off-surface.
    assert!(m("off_surface") >= 500, "{p}");
    assert!(m("object_outside") * 10 >= (car[0].1 + car[1].1) * 9, "{p}");

    gt_reference(&scene, 4, "street preset, 2 orbit + 2 street views");
    // The bounds notice a small defect: pixel centres half a pixel off pass the interior (the
    // maps are the same away from edges) but not the boundaries.
    let t = gt_reference_totals(&scene, Some("half-pixel"));
    for map in ["class", "instance"] {
        let n = |k: &str| t[format!("{map}_{k}")].as_u64().unwrap() as f64;
        let share = n("boundary_agree") / n("boundary");
        eprintln!(
            "GT re-derivation with pixel centres half a pixel off: {map} boundaries {share:.3}"
        );
        assert!(share < MIN_BOUNDARY, "{map}: {t}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
