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
//! - `--where`: as many splats as scripts/selection_reference.py (docs/query.md's rules over
//!   semantic.ply read by plyfile) selects; bad inputs → one error line and no output folder.
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
            gs4city_ok(&args);
        }
        (scene, run)
    })
}

/// PROJ's `cs2cs` and the Python modules `python`; a missing one skips the test (said once).
fn have_cs2cs_and(test: &str, python: &[&str]) -> bool {
    have(
        test,
        "cs2cs",
        "cs2cs is missing (scripts/setup.sh installs proj-bin)",
    ) && (python.is_empty() || common::python_can_import(test, python))
}

/// Runs gs4city with `args`; panics with its stderr when it fails.
fn gs4city_ok(args: &[&str]) {
    let o = Command::new(BIN).args(args).output().unwrap();
    assert!(
        o.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

fn export(run: &Path, out: &Path, extra: &[&str]) -> Output {
    Command::new(BIN)
        .args(["-q", "export", "--run"])
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

/// The run's colours (no `--color-by`), uncompressed or `--spz`: what the reference decoder
/// compares with semantic.ply.
fn rgb_export(spz: bool) -> &'static PathBuf {
    static PLAIN: OnceLock<PathBuf> = OnceLock::new();
    static SPZ: OnceLock<PathBuf> = OnceLock::new();
    (if spz { &SPZ } else { &PLAIN }).get_or_init(|| {
        let (_, run) = small_run();
        let out = run
            .parent()
            .unwrap()
            .join(if spz { "tiles-rgb-spz" } else { "tiles-rgb" });
        let _ = std::fs::remove_dir_all(&out);
        let max = MAX_SPLATS.to_string();
        let mut args = vec!["--max-splats", max.as_str()];
        if spz {
            args.push("--spz");
        }
        ok(&export(run, &out, &args));
        out
    })
}

/// scripts/khr_gs_reference.py (a reader written from the extension's text) on `tileset`.
fn khr_reference(tileset: &Path, extra: &[&str]) -> Value {
    let (_, run) = small_run();
    let o = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/khr_gs_reference.py"))
        .arg(tileset)
        .arg(run)
        .args(["lift", "EPSG:32632"])
        .args(extra)
        .output()
        .unwrap();
    ok(&o);
    serde_json::from_slice(&o.stdout).unwrap()
}

/// A copy of `src` whose tile `uri` (none when empty) has its `KHR_gaussian_splatting:SCALE`
/// values replaced by their natural logarithm (the log-space convention the extension's text
/// does not use).
fn log_scale_copy(src: &Path, dst: &Path, uri: &str) {
    let _ = std::fs::remove_dir_all(dst);
    std::fs::create_dir_all(dst.join("tiles")).unwrap();
    for e in std::fs::read_dir(src.join("tiles")).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), dst.join("tiles").join(e.file_name())).unwrap();
    }
    std::fs::copy(src.join("tileset.json"), dst.join("tileset.json")).unwrap();
    if !uri.is_empty() {
        log_scale_tile(&dst.join(uri));
    }
}

/// Tile `path` with its `KHR_gaussian_splatting:SCALE` values replaced by their logarithms.
fn log_scale_tile(path: &Path) {
    let mut bytes = std::fs::read(path).unwrap();
    let (json, _) = gs4city::glb::read("tile", &bytes).unwrap();
    let jlen = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    let prim = &json["meshes"][0]["primitives"][0];
    let acc = &json["accessors"][prim["attributes"]["KHR_gaussian_splatting:SCALE"]
        .as_u64()
        .unwrap() as usize];
    let view = &json["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
    let at = 28 + jlen + view["byteOffset"].as_u64().unwrap_or(0) as usize;
    for k in 0..acc["count"].as_u64().unwrap() as usize * 3 {
        let o = at + 4 * k;
        let v = f32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        bytes[o..o + 4].copy_from_slice(&v.ln().to_le_bytes());
    }
    std::fs::write(path, bytes).unwrap();
}

/// The reference decoder of the extension's text (scripts/khr_gs_reference.py, NumPy, written
/// from the text alone) reads every tile, finds each conformant (POINTS, `kernel`,
/// `colorSpace`, the attributes' types, linear non-negative SCALE, OPACITY in [0, 1], unit
/// quaternions, complete SH degrees, splats inside their boxes, leaves' geometric error 0,
/// inner ones positive and no larger than their parent's) and matches every leaf splat to its
/// Gaussian of semantic.ply: ECEF position (alignment formula + cs2cs) within 1 mm, covariance
/// `M C Cᵀ Mᵀ` within 2·10⁻³ (relative) of the Gaussian's carried by the alignment and cs2cs's
/// Jacobian, world axes within 10⁻³, opacity within 10⁻⁶, DC colour within 10⁻⁵; the SPZ
/// tiles within their quantisation (the bounds in the script). A tile whose SCALE holds log
/// scales fails it, and so do the SPZ tiles read with the draft's `LUF` axes (docs/export.md).
#[test]
fn reference_decoder_of_the_text_matches_semantic_ply() {
    let test = "export_3dtiles::reference_decoder_of_the_text_matches_semantic_ply";
    if !have_cs2cs_and(test, &["numpy", "scipy"]) {
        return;
    }
    for spz in [false, true] {
        let t = rgb_export(spz);
        let r = khr_reference(t, &[]);
        assert_eq!(r["ok"], true, "{r}");
        let s = read_json(&t.join("summary.json"));
        assert_eq!(r["splats"], s["splats"], "{r}");
        assert_eq!(r["tiles"], s["tiles"], "{r}");
        assert_eq!(r["root_splats"], s["root_splats"], "{r}");
        assert!(r["inner"].as_u64().unwrap() > 0, "{r}");
        assert_eq!(r["spz"], spz, "{r}");
    }
    // A log-scale tile: refused (negative SCALE) and its covariances far off.
    let plain = rgb_export(false);
    let bad = plain.parent().unwrap().join("tiles-rgb-log");
    let ts = read_json(&plain.join("tileset.json"));
    let mut tiles = Vec::new();
    walk(&ts["root"], 0, &mut tiles);
    let leaf = tiles
        .iter()
        .find(|(t, _)| t.get("children").is_none())
        .unwrap()
        .0["content"]["uri"]
        .as_str()
        .unwrap()
        .to_string();
    log_scale_copy(plain, &bad, &leaf);
    let r = khr_reference(&bad, &[]);
    assert_eq!(r["ok"], false, "{r}");
    assert!(r["fails"]["covariance_rel"].as_u64().unwrap() > 0, "{r}");
    assert!(
        r["conformance"][0]
            .as_str()
            .unwrap()
            .contains("SCALE negative"),
        "{r}"
    );
    // The draft's LUF axes: positions mirrored, the match fails.
    let r = khr_reference(rgb_export(true), &["--spz-axes", "luf"]);
    assert_eq!(r["ok"], false, "{r}");
    assert!(r["fails"]["position_m"].as_u64().unwrap() > 0, "{r}");
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
    // Every tile: the leaves' Gaussians and the inner tiles' coarse splats.
    assert_eq!(
        r["splats"].as_u64().unwrap(),
        s["splats"].as_u64().unwrap() + s["coarse_splats"].as_u64().unwrap(),
        "{r}"
    );
    assert_eq!(r["tiles"], s["tiles"], "{r}");
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
/// Gaussians and together every Gaussian of the run once, whose inner tiles each hold a coarse
/// set of at most `--max-splats` splats and fewer than their children together, with a positive
/// geometric error no smaller than their children's (refine REPLACE: coarse to fine); tiles
/// read back by 3d-tiles-tools.
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
    assert_eq!(ts["root"]["refine"], "REPLACE");
    let count = |tile: &Value| -> usize {
        let bytes = std::fs::read(t.join(tile["content"]["uri"].as_str().unwrap())).unwrap();
        let (json, _) = gs4city::glb::read("tile", &bytes).unwrap();
        let prim = &json["meshes"][0]["primitives"][0];
        json["accessors"][prim["attributes"]["POSITION"].as_u64().unwrap() as usize]["count"]
            .as_u64()
            .unwrap() as usize
    };
    // Splats a subtree's leaves hold.
    fn below(t: &Value, count: &dyn Fn(&Value) -> usize) -> usize {
        match t.get("children") {
            None => count(t),
            Some(c) => c.as_array().unwrap().iter().map(|c| below(c, count)).sum(),
        }
    }
    for (tile, _) in &tiles {
        assert_eq!(tile["transform"].as_array().unwrap().len(), 16);
        assert_eq!(tile["boundingVolume"]["box"].as_array().unwrap().len(), 12);
        assert!(tile["content"]["uri"].is_string(), "every tile has content");
        if let Some(children) = tile.get("children") {
            let e = tile["geometricError"].as_f64().unwrap();
            assert!(e > 0.0);
            let n = count(tile);
            assert!(n > 0 && n <= MAX_SPLATS, "an inner tile holds {n}");
            let under: usize = children
                .as_array()
                .unwrap()
                .iter()
                .map(|c| below(c, &count))
                .sum();
            assert!(n < under, "{n} coarse splats for {under} Gaussians");
            for c in children.as_array().unwrap() {
                assert!(c["geometricError"].as_f64().unwrap() <= e);
            }
        }
    }
    assert_eq!(summary["root_splats"], count(&ts["root"]));
    assert!(summary["coarse_splats"].as_u64().unwrap() > 0);
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
    assert_eq!(read["contents"].as_array().unwrap().len(), tiles.len());
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
    if !have_cs2cs_and(test, &["numpy", "scipy"]) {
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

/// `--where` exports exactly as many Gaussians as an independent reading of the expression over
/// `semantic.ply` (plyfile) and `semantics.json` selects (`scripts/selection_reference.py`).
#[test]
fn where_exports_what_semantic_ply_selects() {
    const TEST: &str = "export_3dtiles::where_exports_what_semantic_ply_selects";
    let (_, run) = small_run();
    let q = "category=window or class=RoofSurface";
    let Some(want) = crate::view::reference_selections(TEST, run, &[q]) else {
        return;
    };
    let want = want[0].len() as u64;
    assert!(want > 1000, "{want}");
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
    if !have_browser(test, "cesium", &[]) {
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
    // Every tile has content (the inner ones their coarse sets): Cesium loads them on its way
    // down (refine REPLACE) and draws the leaves' splats (`splatsReady`: all of them).
    let tiles = read_json(&t.join("summary.json"))["tiles"].clone();
    assert_eq!(r["contents"], tiles, "{r}");
    assert_eq!(r["splatContents"], tiles, "{r}");
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

/// The two probes of [`probes`]: per probe its standard deviations along its two ground axes
/// (metres) and the angle of the first from east towards north (degrees, in the CRS grid).
const PROBES: [([f64; 3], f64, f64); 2] = [
    ([1.5, 1.5, 1.5], 0.0, -15.0),
    ([3.0, 0.75, 0.75], 30.0, 15.0),
];
/// How high above a probe the camera looks straight down (metres).
const PROBE_HEIGHT: f64 = 25.0;

/// A probe scene: the small scene whose PLY has every Gaussian made transparent (opacity logit
/// −30) but two white probes of known size, 25 m above the scene's centre (`PROBES`), and its
/// exports (the run's labels: the same count of Gaussians), uncompressed and `--spz`; with the
/// camera views that look straight down at each probe from `PROBE_HEIGHT` (root frame, north
/// up in the picture).
struct Probes {
    plain: PathBuf,
    spz: PathBuf,
    views: Value,
}

fn probes() -> &'static Probes {
    static P: OnceLock<Probes> = OnceLock::new();
    P.get_or_init(|| {
        let (scene, run) = small_run();
        let dir = run.parent().unwrap().join("probe");
        let _ = std::fs::remove_dir_all(&dir);
        let s2 = dir.join("scene");
        std::fs::create_dir_all(&s2).unwrap();
        for e in std::fs::read_dir(scene).unwrap() {
            let e = e.unwrap();
            if e.file_name() != "point_cloud.ply" {
                std::os::unix::fs::symlink(e.path(), s2.join(e.file_name())).unwrap();
            }
        }
        let (mut g, _) = gs4city::splat::read_ply(
            &scene.join("point_cloud.ply"),
            &gs4city::splat::ReadOptions::KEEP,
        )
        .unwrap();
        let al =
            gs4city::alignment::Alignment::read(&run.join("citymodel/alignment.json")).unwrap();
        let mean = g
            .positions
            .iter()
            .map(|p| al.unapply(glam::DVec3::from_array(p.map(f64::from))))
            .sum::<glam::DVec3>()
            / g.len() as f64;
        for o in &mut g.opacity {
            *o = -30.0;
        }
        let rest = g.rest_per_gaussian();
        let mut geo = Vec::new();
        for (k, (sigma, angle, dx)) in PROBES.iter().enumerate() {
            let p = mean + glam::DVec3::new(*dx, 0.0, PROBE_HEIGHT);
            geo.push(p);
            let q = glam::DQuat::from_mat3(
                &(al.rotation * glam::DMat3::from_rotation_z(angle.to_radians())),
            );
            g.positions[k] = al.apply(p).to_array().map(|v| v as f32);
            g.scale[k] = sigma.map(|s| (s * al.scale).ln() as f32);
            g.rotation[k] = [q.w, q.x, q.y, q.z].map(|v| v as f32);
            g.opacity[k] = 8.0;
            g.f_dc[k] = [(0.5 / gs4city::splat::transform::SH_C0) as f32; 3];
            g.f_rest[k * rest..(k + 1) * rest].fill(0.0);
        }
        gs4city::splat::write_ply(
            &s2.join("point_cloud.ply"),
            &g,
            gs4city::splat::PlyEncoding::BinaryLittleEndian,
        )
        .unwrap();
        let mut outs = Vec::new();
        for spz in [false, true] {
            let out = dir.join(if spz { "tiles-spz" } else { "tiles" });
            let max = MAX_SPLATS.to_string();
            let mut args = vec![
                "--scene",
                s2.to_str().unwrap(),
                "--max-splats",
                max.as_str(),
            ];
            if spz {
                args.push("--spz");
            }
            ok(&export(run, &out, &args));
            outs.push(out);
        }
        // The probes in the root frame: the root's ENU axes and origin, the probes' ECEF by cs2cs.
        let ts = read_json(&outs[0].join("tileset.json"));
        let m: Vec<f64> = ts["root"]["transform"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let views: Vec<Value> = geo
            .iter()
            .enumerate()
            .map(|(k, p)| {
                let e = cs2cs("EPSG:32632", "EPSG:4978", p.to_array());
                let d = [e[0] - m[12], e[1] - m[13], e[2] - m[14]];
                let enu: Vec<f64> = (0..3)
                    .map(|c| (0..3).map(|r| m[4 * c + r] * d[r]).sum())
                    .collect();
                serde_json::json!({
                    "name": format!("probe{k}"),
                    "eye": [enu[0], enu[1], enu[2] + PROBE_HEIGHT],
                    "target": enu,
                    "up": [0.0, 1.0, 0.0],
                })
            })
            .collect();
        Probes {
            plain: outs[0].clone(),
            spz: outs[1].clone(),
            views: Value::Array(views),
        }
    })
}

/// Whether each probe's picture shows the footprint its size gives (a view straight down,
/// focal length `f` pixels): the pixels at or above half the peak form an ellipse of semi-axes
/// `√(2 ln 2) σ f / d` (σ the probe's standard deviations, d = `PROBE_HEIGHT`), measured by
/// their second moments (a uniform ellipse's variance along an axis is a²/4) within 10 %, and
/// turned by the probe's angle within 4° (the grid north of the CRS is 1.8° off true north
/// there); its centroid within 3 px of the centre. Returns the problems found.
fn footprint_problems(views: &Value, f: f64) -> Vec<String> {
    let mut bad = Vec::new();
    for (k, (sigma, angle, _)) in PROBES.iter().enumerate() {
        let v = &views[format!("probe{k}")];
        let g = |x: &Value| x.as_f64().unwrap();
        let size = v["size"].as_array().unwrap();
        let Some(c) = v["centroid"].as_array() else {
            bad.push(format!("probe{k}: nothing drawn: {v}"));
            continue;
        };
        let (cx, cy) = (g(&size[0]) / 2.0 - 0.5, g(&size[1]) / 2.0 - 0.5);
        if (g(&c[0]) - cx).hypot(g(&c[1]) - cy) > 3.0 {
            bad.push(format!("probe{k}: centroid {c:?}, not at ({cx}, {cy})"));
        }
        let m = v["moments"].as_array().unwrap();
        let (sxx, syy, sxy) = (g(&m[0]), g(&m[1]), g(&m[2]));
        let mid = (sxx + syy) / 2.0;
        let r = ((sxx - syy) / 2.0).hypot(sxy);
        let (major, minor) = (2.0 * (mid + r).sqrt(), 2.0 * (mid - r).max(0.0).sqrt());
        let half = (2.0 * 2f64.ln()).sqrt();
        let want = [
            half * sigma[0] * f / PROBE_HEIGHT,
            half * sigma[1] * f / PROBE_HEIGHT,
        ];
        for (got, want, what) in [(major, want[0], "major"), (minor, want[1], "minor")] {
            if (got / want - 1.0).abs() > 0.10 {
                bad.push(format!(
                    "probe{k}: {what} semi-axis {got:.1} px, want {want:.1} px"
                ));
            }
        }
        if sigma[0] != sigma[1] {
            // Image y points south: the angle from east towards north is minus the picture's.
            let got = -0.5 * (2.0 * sxy).atan2(sxx - syy).to_degrees();
            if (got - angle).abs() > 4.0 {
                bad.push(format!("probe{k}: major axis at {got:.1}°, want {angle}°"));
            }
        }
    }
    bad
}

/// What a browser test needs: node, the npm `package` and playwright-core in tools/js, Debian's
/// Chromium, `cs2cs` and the Python modules `python`; a missing one skips the test (said once).
fn have_browser(test: &str, package: &str, python: &[&str]) -> bool {
    have(test, "node", "node is missing (scripts/setup.sh)")
        && have_js(test, package)
        && have_js(test, "playwright-core")
        && have_cs2cs_and(test, python)
        && if Path::new("/usr/bin/chromium").is_file() {
            true
        } else {
            common::skip(
                test,
                "/usr/bin/chromium is missing (scripts/setup.sh installs chromium)",
            );
            false
        }
}

/// The PlayCanvas engine (npm `playcanvas` 2.23.3, whose glTF loader reads
/// `KHR_gaussian_splatting` with linear scales) in headless Chromium draws the probe tileset
/// (tools/js/playcanvas_shot.mjs: every leaf placed by its tile transforms) and each probe
/// covers the footprint its size gives ([`footprint_problems`]); the same tileset with its
/// SCALE values replaced by their logarithms (a log-space convention) does not. A second picture, of the demo export in the run's colours, is docs/img/playcanvas_3dtiles.png.
#[test]
fn playcanvas_draws_splats_of_the_size_the_tiles_say() {
    let test = "export_3dtiles::playcanvas_draws_splats_of_the_size_the_tiles_say";
    if !have_browser(test, "playcanvas", &[]) {
        return;
    }
    let p = probes();
    let (w, h, fov) = (640.0, 480.0, 40.0f64);
    let f = h / 2.0 / (fov / 2.0).to_radians().tan();
    let shoot = |t: &Path, prefix: &Path, views: &Value| -> Value {
        let spec = serde_json::json!({"width": w, "height": h, "fov": fov, "views": views});
        let o = Command::new("node")
            .arg(tools_js().join("playcanvas_shot.mjs"))
            .arg(t)
            .arg(prefix)
            .arg(spec.to_string())
            .current_dir(tools_js())
            .output()
            .unwrap();
        ok(&o);
        let r: Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(r["ok"], true, "{r}");
        r
    };
    let r = shoot(&p.plain, &p.plain.with_extension("pc"), &p.views);
    let s = read_json(&p.plain.join("summary.json"));
    assert_eq!(r["loaded"]["tiles"], s["leaves"], "{r}");
    assert_eq!(r["loaded"]["gsplatAssets"], s["leaves"], "{r}");
    let bad = footprint_problems(&r["views"], f);
    assert!(bad.is_empty(), "{bad:?}: {r}");
    // Log scales in every leaf: the probes shrink (or vanish) and the check fails.
    let ts = read_json(&p.plain.join("tileset.json"));
    let mut tiles = Vec::new();
    walk(&ts["root"], 0, &mut tiles);
    let log = p.plain.with_extension("log");
    log_scale_copy(&p.plain, &log, "");
    for (t, _) in tiles.iter().filter(|(t, _)| t.get("children").is_none()) {
        log_scale_tile(&log.join(t["content"]["uri"].as_str().unwrap()));
    }
    let r = shoot(&log, &log.with_extension("pc"), &p.views);
    let bad = footprint_problems(&r["views"], f);
    assert!(
        !bad.is_empty(),
        "log scales passed the footprint check: {r}"
    );
    // The demo export, for the picture.
    let demo = rgb_export(false);
    let png = demo.with_extension("pc");
    let view = serde_json::json!([{"name": "overview", "eye": [0.0, -70.0, 55.0],
        "target": [0.0, 0.0, 5.0], "up": [0.0, 0.0, 1.0]}]);
    let r = shoot(demo, &png, &view);
    assert!(
        r["views"]["overview"]["lit"].as_u64().unwrap() > 20_000,
        "{r}"
    );
    if let Ok(dst) = std::env::var("GS4CITY_PLAYCANVAS_PNG") {
        std::fs::copy(
            png.with_file_name(format!(
                "{}-overview.png",
                png.file_name().unwrap().to_string_lossy()
            )),
            dst,
        )
        .unwrap();
    }
}

/// CesiumJS 1.145 draws the `--spz` probe tileset as Gaussian splats and each probe covers the
/// footprint its size gives ([`footprint_problems`]; tools/js/cesium_shot.mjs with views).
#[test]
fn cesium_draws_splats_of_the_size_the_tiles_say() {
    let test = "export_3dtiles::cesium_draws_splats_of_the_size_the_tiles_say";
    if !have_browser(test, "cesium", &[]) {
        return;
    }
    let p = probes();
    // Cesium's field of view is that of the wider side (800 of the 800 × 600 canvas).
    let f = 400.0 / (1.0907f64 / 2.0).tan();
    let spec = serde_json::json!({"fov": 1.0907, "views": p.views});
    let png = p.spz.with_extension("png");
    let o = Command::new("node")
        .arg(tools_js().join("cesium_shot.mjs"))
        .arg(&p.spz)
        .arg(&png)
        .arg("{}")
        .arg(spec.to_string())
        .current_dir(tools_js())
        .output()
        .unwrap();
    ok(&o);
    let r: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["ok"], true, "{r}");
    for v in r["views"].as_object().unwrap().values() {
        assert!(v["splatContents"].as_u64().unwrap() > 0, "{r}");
    }
    let bad = footprint_problems(&r["views"], f);
    assert!(bad.is_empty(), "{bad:?}: {r}");
}

/// The SIMULATED small scene replicated 2 × 2 (scripts/replicate_scene.py: four copies, 524 616
/// Gaussians), cut into a plan of 60 m tiles, every tile run (`run-plan --jobs 2`, vote mode,
/// no test views) and merged; the merged run exported with `--spz --max-splats 20000`.
fn merged_replicated_export() -> &'static PathBuf {
    static T: OnceLock<PathBuf> = OnceLock::new();
    T.get_or_init(|| {
        let (scene, _) = small_run();
        let dir = scene.parent().unwrap().join("replicated");
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let (rep, plan) = (dir.join("scene"), dir.join("P"));
        let o = Command::new("python3")
            .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/replicate_scene.py"))
            .arg(scene)
            .arg(&rep)
            .arg("4")
            .output()
            .unwrap();
        ok(&o);
        for args in [
            vec![
                "-q",
                "tile",
                "--scene",
                rep.to_str().unwrap(),
                "--size",
                "60",
                "--margin",
                "10",
                "--test-every",
                "0",
                "--run-args",
                "--mode vote",
                "--out",
                plan.to_str().unwrap(),
            ],
            vec![
                "-q",
                "run-plan",
                plan.to_str().unwrap(),
                "--jobs",
                "2",
                "--no-test-views",
            ],
        ] {
            gs4city_ok(&args);
        }
        let out = dir.join("tiles");
        ok(&export(
            &plan.join("merged"),
            &out,
            &["--spz", "--max-splats", "20000"],
        ));
        out
    })
}

/// The depth of a tile from its content name (`tiles/r.glb` 0, `tiles/r0.glb` 1, …).
fn depth_of(uri: &str) -> usize {
    uri.trim_start_matches("tiles/r")
        .trim_end_matches(".glb")
        .len()
}

/// Level of detail on a merged tile plan: every inner tile has content (a coarse set), and
/// CesiumJS 1.145 (headless, tools/js/cesium_shot.mjs counting the tiles it requests) asks, for
/// a camera 3 km above the city, for the top levels alone (depth ≤ 1), and for a camera at
/// street level for leaves, fetching more bytes.
#[test]
fn cesium_refines_coarse_to_fine_on_a_merged_plan() {
    let test = "export_3dtiles::cesium_refines_coarse_to_fine_on_a_merged_plan";
    if !have_browser(test, "cesium", &["numpy"]) {
        return;
    }
    let t = merged_replicated_export();
    let s = read_json(&t.join("summary.json"));
    assert_eq!(s["splats"], 4 * 131_154, "{s}");
    assert!(s["root_splats"].as_u64().unwrap() <= 20_000, "{s}");
    let ts = read_json(&t.join("tileset.json"));
    let mut tiles = Vec::new();
    walk(&ts["root"], 0, &mut tiles);
    let depth = tiles.iter().map(|(_, d)| *d).max().unwrap();
    assert!(depth >= 2, "{depth}");
    assert!(
        tiles.iter().all(|(t, _)| t["content"]["uri"].is_string()),
        "every tile has content"
    );
    // The root box (its own frame: east, north, up): the cameras.
    let b: Vec<f64> = ts["root"]["boundingVolume"]["box"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let (c, hz) = ([b[0], b[1], b[2]], b[11]);
    let street = c[2] - hz + 0.25 * 2.0 * hz;
    let shoot = |name: &str, eye: [f64; 3], target: [f64; 3]| -> Value {
        let spec = serde_json::json!({"fov": 1.0, "wait": "tiles", "views": [
            {"name": name, "eye": eye, "target": target, "up": [0.0, 0.0, 1.0]}]});
        let o = Command::new("node")
            .arg(tools_js().join("cesium_shot.mjs"))
            .arg(t)
            .arg(t.with_extension("png"))
            .arg("{}")
            .arg(spec.to_string())
            .current_dir(tools_js())
            .output()
            .unwrap();
        ok(&o);
        let r: Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(r["ok"], true, "{r}");
        r["views"][name].clone()
    };
    let far = shoot("far", [c[0], c[1] - 10.0, c[2] + 3000.0], c);
    let near = shoot(
        "near",
        [c[0], c[1] - 20.0, street],
        [c[0], c[1] + 40.0, street - 4.0],
    );
    let stats = |v: &Value| -> (usize, u64, usize) {
        let r = v["requests"].as_array().unwrap();
        let bytes = r.iter().map(|x| x["bytes"].as_u64().unwrap()).sum();
        let deepest = r
            .iter()
            .map(|x| depth_of(x["uri"].as_str().unwrap()))
            .max()
            .unwrap_or(0);
        (r.len(), bytes, deepest)
    };
    let (nf, bf, df) = stats(&far);
    let (nn, bn, dn) = stats(&near);
    eprintln!(
        "LOD: far {nf} tiles {bf} bytes (deepest {df}); near {nn} tiles {bn} bytes (deepest {dn}); tileset {} bytes, {} tiles, depth {depth}",
        s["bytes"], s["tiles"]
    );
    assert!(nf >= 1 && df <= 1, "far: {far}");
    assert!(dn == depth && nn > nf && bn > bf, "near: {near}");
    assert!(far["numSplats"].as_u64().unwrap() > 0, "{far}");
}
