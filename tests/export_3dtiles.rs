//! `gs4city export --format 3dtiles` (and `--spz`) on a SIMULATED scene run (`synth --preset
//! small`: two real Ingolstadt LoD3 buildings in EPSG:32632, `run --mode vote`), checked by
//! tools that are not the code under test:
//! - the Khronos glTF validator (npm `gltf-validator`, tools/js/validate_gltf.mjs) on every tile;
//! - `3d-tiles-tools` (npm; tools/js/read_tileset.mjs) traversing the tileset and typing every
//!   content;
//! - PROJ's `cs2cs` (Debian proj-bin) for the root's ECEF position and its east-north-up axes;
//! - scripts/tiles3d_reference.py (NumPy, scipy): every splat decoded from the tiles and placed
//!   on the globe by the tile transforms, matched to the run's Gaussians placed by the
//!   alignment formula and `cs2cs`, its building / surface / part gml:ids and class compared
//!   with semantic.ply and semantics.json, its colour with the class palette;
//! - scripts/spz_reference.py (NumPy): the `--spz` tiles' SPZ blobs decoded and compared with the
//!   uncompressed export; CesiumJS (tools/js/cesium_shot.mjs) drawing them as Gaussian splats;
//! - `gs4city query`'s count for `--where`; bad inputs → one error line and no output folder.
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use serde_json::Value;

use crate::common;

const BIN: &str = env!("CARGO_BIN_EXE_gs4city");
const MAX_SPLATS: usize = 40_000;

fn tools_js() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/js")
}

/// The SIMULATED small scene and its vote run, made once per test binary under cargo's target
/// tmp dir (replaced by the next test run).
fn small_run() -> &'static (PathBuf, PathBuf) {
    static RUN: OnceLock<(PathBuf, PathBuf)> = OnceLock::new();
    RUN.get_or_init(|| {
        let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("export-3dtiles");
        let _ = std::fs::remove_dir_all(&dir);
        let (scene, run) = (dir.join("scene"), dir.join("run"));
        for args in [
            vec![
                "-q",
                "synth",
                "--preset",
                "small",
                "--out",
                scene.to_str().unwrap(),
            ],
            vec![
                "-q",
                "run",
                "--scene",
                scene.to_str().unwrap(),
                "--out",
                run.to_str().unwrap(),
                "--mode",
                "vote",
            ],
        ] {
            let o = Command::new(BIN).args(&args).output().unwrap();
            assert!(
                o.status.success(),
                "{args:?}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
        (scene, run)
    })
}

fn export(run: &Path, out: &Path, extra: &[&str]) -> Output {
    Command::new(BIN)
        .args(["-q", "export", "--format", "3dtiles", "--run"])
        .arg(run)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap()
}

fn ok(o: &Output) {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

fn read_json(p: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

/// Whether a program runs (`cs2cs`, `node`), else a counted skip.
fn have(test: &str, program: &str, why: &str) -> bool {
    if Command::new(program).arg("--version").output().is_ok()
        || Command::new("which")
            .arg(program)
            .output()
            .is_ok_and(|o| o.status.success())
    {
        return true;
    }
    common::skip(test, why);
    false
}

/// Whether tools/js has its packages (scripts/setup.sh), else a counted skip.
fn have_js(test: &str, package: &str) -> bool {
    if tools_js().join("node_modules").join(package).is_dir() {
        return true;
    }
    common::skip(
        test,
        &format!(
            "tools/js/node_modules/{package} is missing (scripts/setup.sh runs npm ci in tools/js)"
        ),
    );
    false
}

/// `cs2cs from to` on one point, as three numbers.
fn cs2cs(from: &str, to: &str, p: [f64; 3]) -> [f64; 3] {
    use std::io::Write;
    let mut child = Command::new("cs2cs")
        .args(["-f", "%.9f", from, to])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    writeln!(child.stdin.take().unwrap(), "{} {} {}", p[0], p[1], p[2]).unwrap();
    let out = child.wait_with_output().unwrap();
    let text = String::from_utf8(out.stdout).unwrap();
    let v: Vec<f64> = text
        .split_whitespace()
        .take(3)
        .map(|w| w.parse().unwrap())
        .collect();
    [v[0], v[1], v[2]]
}

/// Every tile of a tileset.json subtree: (tile, depth).
fn walk<'a>(t: &'a Value, depth: usize, out: &mut Vec<(&'a Value, usize)>) {
    out.push((t, depth));
    for c in t["children"].as_array().into_iter().flatten() {
        walk(c, depth + 1, out);
    }
}

/// The full export of the small run, class-coloured, with several tiles.
fn full_export() -> &'static PathBuf {
    static T: OnceLock<PathBuf> = OnceLock::new();
    T.get_or_init(|| {
        let (_, run) = small_run();
        let out = run.parent().unwrap().join("tiles-class");
        let _ = std::fs::remove_dir_all(&out);
        ok(&export(
            run,
            &out,
            &[
                "--color-by",
                "class",
                "--max-splats",
                &MAX_SPLATS.to_string(),
            ],
        ));
        out
    })
}

/// The same export as [`full_export`] with `--spz` (the splats SPZ-compressed).
fn spz_export() -> &'static PathBuf {
    static T: OnceLock<PathBuf> = OnceLock::new();
    T.get_or_init(|| {
        let (_, run) = small_run();
        let out = run.parent().unwrap().join("tiles-class-spz");
        let _ = std::fs::remove_dir_all(&out);
        ok(&export(
            run,
            &out,
            &[
                "--color-by",
                "class",
                "--max-splats",
                &MAX_SPLATS.to_string(),
                "--spz",
            ],
        ));
        out
    })
}

/// `--spz`: every tile's SPZ blob decoded by scripts/spz_reference.py (an SPZ v2 decoder
/// written from the format's description) holds the uncompressed export's splats within half
/// a quantisation step (positions 1/4096 m, alphas 1/255, DC colours 1/(0.15·255), log scales
/// 1/16, quaternion x y z 1/127.5, SH 8/128 and 16/128 buckets); the attributes are declared
/// by accessors without buffer views, counts equal to the SPZ count, while the feature ids,
/// `EXT_mesh_features` and the property tables are those of the uncompressed export; the
/// tileset declares the extensions CesiumJS needs; and SPZ is the smaller.
#[test]
fn spz_tiles_decode_to_the_uncompressed_splats() {
    let test = "export_3dtiles::spz_tiles_decode_to_the_uncompressed_splats";
    if !common::python_can_import(test, &["numpy", "scipy"]) {
        return;
    }
    let (plain, spz) = (full_export(), spz_export());
    let o = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/spz_reference.py"))
        .arg(plain)
        .arg(spz)
        .output()
        .unwrap();
    ok(&o);
    let r: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["structure_errors"], serde_json::json!([]), "{r}");
    let s: Value = read_json(&plain.join("summary.json"));
    assert_eq!(r["splats"], s["splats"], "{r}");
    assert_eq!(r["tiles"], s["leaves"], "{r}");
    assert_eq!(r["sh_degree"], 1, "{r}");
    for (k, e) in r["max_error"].as_object().unwrap() {
        let bound = r["half_step"][k].as_f64().unwrap();
        assert!(e.as_f64().unwrap() <= bound, "{k}: {e} > {bound}: {r}");
    }
    let ts = read_json(&spz.join("tileset.json"));
    let required = &ts["extensions"]["3DTILES_content_gltf"]["extensionsRequired"];
    assert_eq!(
        required,
        &serde_json::json!([
            "KHR_gaussian_splatting",
            "KHR_gaussian_splatting_compression_spz_2"
        ])
    );
    let spz_summary = read_json(&spz.join("summary.json"));
    assert!(
        spz_summary["bytes"].as_u64() < s["bytes"].as_u64(),
        "{spz_summary}"
    );
}

/// Layout: a 3D Tiles 1.1 tileset, a quadtree whose leaves hold at most `--max-splats`
/// Gaussians and together every Gaussian of the run once, tiles read back by 3d-tiles-tools.
#[test]
fn tileset_layout_is_read_by_3d_tiles_tools() {
    let t = full_export();
    let ts = read_json(&t.join("tileset.json"));
    let summary = read_json(&t.join("summary.json"));
    assert_eq!(ts["asset"]["version"], "1.1");
    let mut tiles = Vec::new();
    walk(&ts["root"], 0, &mut tiles);
    let leaves: Vec<&Value> = tiles
        .iter()
        .filter(|(t, _)| t.get("children").is_none())
        .map(|(t, _)| *t)
        .collect();
    assert!(
        leaves.len() > 1,
        "the small scene is split: {} leaves",
        leaves.len()
    );
    assert!(leaves.iter().all(|l| l["content"]["uri"].is_string()));
    assert!(leaves.iter().all(|l| l["geometricError"] == 0.0));
    for (tile, _) in &tiles {
        assert_eq!(tile["transform"].as_array().unwrap().len(), 16);
        assert_eq!(tile["boundingVolume"]["box"].as_array().unwrap().len(), 12);
        if tile.get("children").is_some() {
            assert!(tile["geometricError"].as_f64().unwrap() > 0.0);
        }
    }
    // Every leaf's POSITION count from its own glb header; together every Gaussian once.
    let mut total = 0;
    for l in &leaves {
        let bytes = std::fs::read(t.join(l["content"]["uri"].as_str().unwrap())).unwrap();
        let (json, _) = gs4city::glb::read("tile", &bytes).unwrap();
        let prim = &json["meshes"][0]["primitives"][0];
        assert_eq!(prim["mode"], 0, "POINTS");
        let n =
            json["accessors"][prim["attributes"]["POSITION"].as_u64().unwrap() as usize]["count"]
                .as_u64()
                .unwrap() as usize;
        assert!(n <= MAX_SPLATS, "a leaf holds {n} > {MAX_SPLATS}");
        total += n;
    }
    let gaussians = gs4city::splat::read_ply(
        &small_run().0.join("point_cloud.ply"),
        &gs4city::splat::ReadOptions::KEEP,
    )
    .unwrap()
    .0
    .len();
    assert_eq!(total, gaussians);
    assert_eq!(summary["splats"], total);

    let test = "export_3dtiles::tileset_layout_is_read_by_3d_tiles_tools";
    if !have(test, "node", "node is missing (scripts/setup.sh)") || !have_js(test, "3d-tiles-tools")
    {
        return;
    }
    let o = Command::new("node")
        .arg(tools_js().join("read_tileset.mjs"))
        .arg(t)
        .current_dir(tools_js())
        .output()
        .unwrap();
    ok(&o);
    let read: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(read["version"], "1.1");
    assert_eq!(read["tiles"], tiles.len());
    assert_eq!(read["contents"].as_array().unwrap().len(), leaves.len());
    for c in read["contents"].as_array().unwrap() {
        assert_eq!(c["type"], "CONTENT_TYPE_GLB", "{c}");
    }
}

/// The Khronos validator on every tile (uncompressed and `--spz`): its only errors are the `KHR_gaussian_splatting:*`
/// attribute semantics it predates (one per such attribute), and with those renamed to
/// application-specific names it reports no error and no warning.
#[test]
fn every_tile_passes_the_gltf_validator() {
    let test = "export_3dtiles::every_tile_passes_the_gltf_validator";
    if !have(test, "node", "node is missing (scripts/setup.sh)") || !have_js(test, "gltf-validator")
    {
        return;
    }
    let mut files: Vec<PathBuf> = [full_export(), spz_export()]
        .iter()
        .flat_map(|t| std::fs::read_dir(t.join("tiles")).unwrap())
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    let o = Command::new("node")
        .arg(tools_js().join("validate_gltf.mjs"))
        .args(&files)
        .current_dir(tools_js())
        .output()
        .unwrap();
    ok(&o);
    let reports: Vec<Value> = String::from_utf8(o.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(reports.len(), files.len());
    for (r, f) in reports.iter().zip(&files) {
        let (json, _) = gs4city::glb::read("tile", &std::fs::read(f).unwrap()).unwrap();
        let khr = json["meshes"][0]["primitives"][0]["attributes"]
            .as_object()
            .unwrap()
            .keys()
            .filter(|k| k.starts_with("KHR_gaussian_splatting:"))
            .count();
        // Uncompressed: ROTATION, SCALE, OPACITY, SH degree 0 and 1; SPZ: ROTATION, SCALE and
        // SH degree 1 (the opacity and the DC colour are COLOR_0's).
        assert!(khr >= 5, "{khr} KHR_gaussian_splatting attributes");
        assert_eq!(r["errors"], khr, "{r}");
        for m in r["messages"].as_array().unwrap() {
            assert_eq!(m["code"], "MESH_PRIMITIVE_INVALID_ATTRIBUTE", "{m}");
            assert!(
                m["pointer"]
                    .as_str()
                    .unwrap()
                    .contains("/attributes/KHR_gaussian_splatting:"),
                "{m}"
            );
        }
        assert_eq!(r["warnings"], 0, "{r}");
        assert_eq!(r["renamed"]["errors"], 0, "{r}");
        assert_eq!(r["renamed"]["warnings"], 0, "{r}");
    }
}

/// The root lands where PROJ's `cs2cs` puts the root's CRS centre (ECEF within 1 mm), with the
/// east-north-up axes of the cs2cs latitude and longitude there.
#[test]
fn root_transform_matches_cs2cs() {
    let test = "export_3dtiles::root_transform_matches_cs2cs";
    if !have(
        test,
        "cs2cs",
        "cs2cs is missing (scripts/setup.sh installs proj-bin)",
    ) {
        return;
    }
    let t = full_export();
    let ts = read_json(&t.join("tileset.json"));
    let s = read_json(&t.join("summary.json"));
    assert_eq!(
        s["crs"], "EPSG:32632",
        "the srsName of the small scene's CityGML"
    );
    let c: Vec<f64> = s["root"]["crs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let m: Vec<f64> = ts["root"]["transform"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let ecef = cs2cs("EPSG:32632", "EPSG:4978", [c[0], c[1], c[2]]);
    for k in 0..3 {
        assert!(
            (m[12 + k] - ecef[k]).abs() < 1e-3,
            "{k}: {} vs {}",
            m[12 + k],
            ecef[k]
        );
    }
    // cs2cs to geographic 3D: latitude, longitude (EPSG axis order), height.
    let g = cs2cs("EPSG:32632", "EPSG:4979", [c[0], c[1], c[2]]);
    let (lat, lon) = (g[0].to_radians(), g[1].to_radians());
    assert!(
        (g[2] - c[2]).abs() < 1e-6,
        "the height is ellipsoidal: {g:?}"
    );
    let east = [-lon.sin(), lon.cos(), 0.0];
    let north = [-lat.sin() * lon.cos(), -lat.sin() * lon.sin(), lat.cos()];
    let up = [lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin()];
    for (col, axis) in [east, north, up].iter().enumerate() {
        for k in 0..3 {
            assert!((m[4 * col + k] - axis[k]).abs() < 1e-9, "column {col}");
        }
    }
    assert!((s["root"]["lat"].as_f64().unwrap() - g[0]).abs() < 1e-9);
    assert!((s["root"]["lon"].as_f64().unwrap() - g[1]).abs() < 1e-9);
}

/// Every splat decoded from the tiles (scripts/tiles3d_reference.py) lies within 1 cm of its
/// Gaussian placed by the alignment formula and cs2cs, and carries that Gaussian's building,
/// surface and part gml:ids and class (semantic.ply + semantics.json) and class colour.
#[test]
fn splats_carry_their_place_ids_and_class() {
    let test = "export_3dtiles::splats_carry_their_place_ids_and_class";
    if !have(
        test,
        "cs2cs",
        "cs2cs is missing (scripts/setup.sh installs proj-bin)",
    ) || !common::python_can_import(test, &["numpy", "scipy"])
    {
        return;
    }
    let t = full_export();
    let (_, run) = small_run();
    let o = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/tiles3d_reference.py"))
        .arg(t)
        .arg(run)
        .args(["lift", "EPSG:32632", "--class-colors"])
        .output()
        .unwrap();
    ok(&o);
    let r: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["splats"], r["expected"], "{r}");
    assert_eq!(r["mismatch_count"], 0, "{r}");
    assert_eq!(r["unmatched_expected"], 0, "{r}");
    assert!(r["max_distance_m"].as_f64().unwrap() < 0.01, "{r}");
    // The simulated scene has walls, roofs and windows, and unlabelled Gaussians.
    for c in ["wall", "roof", "window"] {
        assert!(r["categories"][c].as_u64().unwrap() > 0, "{r}");
    }
}

/// `--where` exports exactly the Gaussians `gs4city query --where` selects.
#[test]
fn where_exports_what_query_selects() {
    let (_, run) = small_run();
    let q = "category=window or class=RoofSurface";
    let qdir = run.parent().unwrap().join("query-where");
    let o = Command::new(BIN)
        .args(["-q", "query", "--run"])
        .arg(run)
        .args(["--where", q, "--views", "none", "--no-sqlite", "--out"])
        .arg(&qdir)
        .output()
        .unwrap();
    ok(&o);
    let want = read_json(&qdir.join("selection.json"))["gaussians"]
        .as_u64()
        .unwrap();
    assert!(want > 0);
    let out = run.parent().unwrap().join("tiles-where");
    let _ = std::fs::remove_dir_all(&out);
    ok(&export(run, &out, &["--where", q]));
    let s = read_json(&out.join("summary.json"));
    assert_eq!(
        s["splats"].as_u64().unwrap() + s["invalid"].as_u64().unwrap(),
        want
    );
    assert_eq!(s["query"], "(category=window or class=RoofSurface)");
}

/// The stderr lines of a failed export, and that nothing that looks done is left.
fn fails(o: &Output, out: &Path) -> Vec<String> {
    assert!(!o.status.success());
    assert!(
        !out.join("tileset.json").exists(),
        "a failed export left a tileset"
    );
    let parent = out.parent().unwrap();
    let leftovers: Vec<String> = std::fs::read_dir(parent)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".partial-"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
    String::from_utf8_lossy(&o.stderr)
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(String::from)
        .collect()
}

/// Bad inputs: a run whose city model names no CRS, an unknown EPSG code, an empty selection,
/// an output folder that is not an export → one error line naming the problem, no tileset.
#[test]
fn bad_inputs_fail_with_one_line_and_leave_nothing() {
    let (_, run) = small_run();
    let root = run.parent().unwrap().join("bad");
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).unwrap();

    // A run without srsName: the same run, its citymodel summary without CRS names.
    let norun = root.join("run-no-crs");
    std::fs::create_dir_all(norun.join("citymodel")).unwrap();
    for e in std::fs::read_dir(run).unwrap() {
        let e = e.unwrap();
        if e.file_name() != "citymodel" {
            std::os::unix::fs::symlink(e.path(), norun.join(e.file_name())).unwrap();
        }
    }
    for e in std::fs::read_dir(run.join("citymodel")).unwrap() {
        let e = e.unwrap();
        if e.file_name() != "summary.json" {
            std::os::unix::fs::symlink(e.path(), norun.join("citymodel").join(e.file_name()))
                .unwrap();
        }
    }
    let mut s = read_json(&run.join("citymodel/summary.json"));
    for f in s["files"].as_array_mut().unwrap() {
        f["srs_name"] = Value::Null;
    }
    std::fs::write(
        norun.join("citymodel/summary.json"),
        serde_json::to_vec(&s).unwrap(),
    )
    .unwrap();
    let out = root.join("t-no-crs");
    let lines = fails(&export(&norun, &out, &[]), &out);
    assert_eq!(lines.len(), 1, "{lines:?}");
    assert!(
        lines[0].contains("srsName") && lines[0].contains("--crs"),
        "{lines:?}"
    );
    assert!(!out.exists());
    // … and with --crs it exports.
    ok(&export(&norun, &out, &["--crs", "EPSG:32632"]));
    assert!(out.join("tileset.json").is_file());

    // An unknown EPSG code: one line (checked against PROJ's database first, so PROJ does not
    // log a line of its own), in every spelling.
    for crs in ["EPSG:999999", "urn:ogc:def:crs:EPSG::999999"] {
        let out = root.join("t-bad-epsg");
        let lines = fails(&export(run, &out, &["--crs", crs]), &out);
        assert_eq!(lines.len(), 1, "{lines:?}");
        assert!(
            lines[0].starts_with("error:")
                && lines[0].contains("EPSG:999999")
                && lines[0].contains("PROJ"),
            "{lines:?}"
        );
        assert!(!out.exists());
    }

    // An empty selection.
    let out = root.join("t-empty");
    let lines = fails(
        &export(run, &out, &["--where", "category=window and category=roof"]),
        &out,
    );
    assert_eq!(lines.len(), 1, "{lines:?}");
    assert!(lines[0].contains("holds no Gaussian"), "{lines:?}");
    assert!(!out.exists());

    // An output folder that holds something else is left alone.
    let out = root.join("t-other");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let lines = fails(&export(run, &out, &[]), &out);
    assert_eq!(lines.len(), 1, "{lines:?}");
    assert!(lines[0].contains("no tileset.json"), "{lines:?}");
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).unwrap(),
        "mine"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// The georeferencing itself against cs2cs, heights included, and the srsName spellings that
/// name the same CRS.
#[test]
fn crs_to_ecef_matches_cs2cs() {
    let test = "export_3dtiles::crs_to_ecef_matches_cs2cs";
    if !have(
        test,
        "cs2cs",
        "cs2cs is missing (scripts/setup.sh installs proj-bin)",
    ) {
        return;
    }
    for (crs, p) in [
        ("EPSG:32632", [678_039.0, 5_403_766.0, 412.0]),
        ("EPSG:32632", [500_000.0, 0.0, -30.0]),
        ("EPSG:25832", [691_000.5, 5_336_000.25, 1_500.0]),
        ("EPSG:3857", [1_000_000.0, 6_000_000.0, 50.0]),
        ("EPSG:4326", [48.7, 11.4, 420.0]),
    ] {
        let want = cs2cs(crs, "EPSG:4978", p);
        for spelling in [
            crs.to_string(),
            format!("urn:ogc:def:crs:EPSG::{}", &crs[5..]),
            format!("http://www.opengis.net/def/crs/EPSG/0/{}", &crs[5..]),
        ] {
            let g = gs4city::crs::Georef::new(&spelling).unwrap();
            // EPSG:4326 in EPSG axis order (lat, lon) for cs2cs; our CRS points are (x, y) =
            // (lon, lat) as PROJ's normalised order.
            let q = if crs == "EPSG:4326" {
                [p[1], p[0], p[2]]
            } else {
                p
            };
            let got = g.ecef(glam::DVec3::from_array(q)).unwrap();
            for k in 0..3 {
                assert!(
                    (got[k] - want[k]).abs() < 1e-4,
                    "{spelling} {p:?}: {got:?} vs cs2cs {want:?}"
                );
            }
        }
    }
    let e = gs4city::crs::Georef::new("EPSG:999999")
        .unwrap_err()
        .to_string();
    assert!(e.contains("EPSG:999999") && e.contains("--crs"), "{e}");
}

/// CesiumJS 1.145 in headless Chromium (SwiftShader WebGL; tools/js/cesium_shot.mjs, served on
/// 127.0.0.1, no ion, no imagery, no terrain) loads the class-coloured tileset, flies to it and
/// draws the class colours where the tileset projects, on the globe where cs2cs puts the root.
/// The tileset is the `--spz` export, served as written (no renaming): Cesium loads every tile
/// through its Gaussian splat path (`GaussianSplat3DTileContent`) and draws splats
/// (docs/export.md). The screenshot is docs/img/cesium_3dtiles.png.
#[test]
fn cesium_draws_the_class_colours_at_the_right_place() {
    let test = "export_3dtiles::cesium_draws_the_class_colours_at_the_right_place";
    if !have(test, "node", "node is missing (scripts/setup.sh)")
        || !have_js(test, "cesium")
        || !have_js(test, "playwright-core")
        || !have(
            test,
            "cs2cs",
            "cs2cs is missing (scripts/setup.sh installs proj-bin)",
        )
    {
        return;
    }
    if !Path::new("/usr/bin/chromium").is_file() {
        common::skip(
            test,
            "/usr/bin/chromium is missing (scripts/setup.sh installs chromium)",
        );
        return;
    }
    let t = spz_export();
    let png = t.parent().unwrap().join("cesium.png");
    // The class palette of docs/design.md, by hand.
    let palette = r#"{"wall":[200,180,140],"roof":[180,60,50],"window":[60,140,230],"tree":[40,160,60],"car":[230,230,30]}"#;
    let o = Command::new("node")
        .arg(tools_js().join("cesium_shot.mjs"))
        .arg(t)
        .arg(&png)
        .arg(palette)
        .current_dir(tools_js())
        .output()
        .unwrap();
    ok(&o);
    let r: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["ok"], true, "{r}");
    assert_eq!(r["tilesLoaded"], true, "{r}");
    // Every tile drawn as Gaussian splats, all of them gathered and sorted before the shot.
    assert_eq!(r["splatsReady"], true, "{r}");
    let leaves = read_json(&t.join("summary.json"))["leaves"].clone();
    assert_eq!(r["contents"], leaves, "{r}");
    assert_eq!(r["splatContents"], leaves, "{r}");
    assert!(png.is_file());
    // Where Cesium puts the tileset: the root translation through cs2cs to latitude/longitude.
    let ts = read_json(&t.join("tileset.json"));
    let m: Vec<f64> = ts["root"]["transform"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let g = cs2cs("EPSG:4978", "EPSG:4979", [m[12], m[13], m[14]]);
    let (lat, lon) = (g[0], g[1]);
    let f = |v: &Value| v.as_f64().unwrap();
    // The bounding sphere's centre is the root box's centre, within a metre of the root origin.
    assert!(
        (f(&r["centre"]["lon"]) - lon).abs() < 2e-5,
        "{r} vs lon {lon}"
    );
    assert!(
        (f(&r["centre"]["lat"]) - lat).abs() < 2e-5,
        "{r} vs lat {lat}"
    );
    assert!((f(&r["camera"]["lon"]) - lon).abs() < 5e-3, "{r}");
    assert!((f(&r["camera"]["lat"]) - lat).abs() < 5e-3, "{r}");
    // Class colours drawn, around the tileset's projection.
    let c = r["centreWindow"].as_array().unwrap();
    let (cx, cy, radius) = (f(&c[0]), f(&c[1]), f(&r["radiusPixels"]));
    for class in ["wall", "roof", "window", "tree", "car"] {
        let p = &r["pixels"]["byColor"][class];
        assert!(p["count"].as_u64().unwrap() >= 50, "{class}: {r}");
        let q = p["centroid"].as_array().unwrap();
        let d = (f(&q[0]) - cx).hypot(f(&q[1]) - cy);
        assert!(
            d < radius,
            "{class} drawn {d} px from the tileset centre (radius {radius}): {r}"
        );
    }
}
