//! Viewer-ready PLY exports of `gs4city query --export` on a hand-built run whose answers are
//! known: two buildings (B1: wall W1 with window Win1, roof R1; B2: wall W2), six Gaussians with
//! hand-assigned labels, an alignment with scale 2, a quarter turn about z and a translation.
//! The expected positions, orientations, colours and columns are worked out by hand here; the
//! files are read back by `@playcanvas/splat-transform` (npm, installed by scripts/setup.sh into
//! tools/js) and by the crate's own reader, and the view-dependent colour of the moved
//! Gaussians is checked with the renderer's SH evaluation (`render::project::sh_color`).
use std::path::{Path, PathBuf};
use std::process::Command;

use glam::{DMat3, DVec3};
use gs4city::citygml::Level;
use gs4city::semantics::Entity;
use gs4city::splat::{self, Gaussians, PlyEncoding};
use gs4city::{fsutil, npy};
use serde_json::{Value, json};

const N: usize = 6;
const C0: f64 = 0.282_094_791_773_878_14;

fn entity(id: i32, oid: &str, class: &str, level: Level, parent: Option<i32>, b: i32) -> Entity {
    Entity {
        id,
        object_id: oid.into(),
        class: gs4city::semantics::Class::from_local_name(class).unwrap(),
        level,
        parent,
        building: b,
        source: "hand.gml".into(),
        lod: Some(3),
        attributes: Default::default(),
    }
}

fn entities() -> Vec<Entity> {
    use Level::*;
    vec![
        entity(0, "B1", "Building", Feature, None, 0),
        entity(1, "W1", "WallSurface", Surface, Some(0), 0),
        entity(2, "Win1", "Window", Part, Some(1), 0),
        entity(3, "R1", "RoofSurface", Surface, Some(0), 0),
        entity(4, "B/2", "Building", Feature, None, 4),
        entity(5, "W2", "WallSurface", Surface, Some(4), 4),
    ]
}

/// Per Gaussian: label (= entity id; −1 none) and, by hand, class, feature, surface, part and
/// building. g0, g5: Win1; g1: W1; g2: R1; g3: W2; g4: unlabelled.
const LABEL: [i32; N] = [2, 1, 3, 5, -1, 2];
const CLASS: [i32; N] = [2, 0, 1, 0, -1, 2];
const FEATURE: [i32; N] = [0, 0, 0, 4, -1, 0];
const SURFACE: [i32; N] = [1, 1, 3, 5, -1, 1];
const PART: [i32; N] = [2, -1, -1, -1, -1, 2];

/// The class palette by hand (docs/design.md): wall, roof, window; unlabelled black.
fn palette(class: i32) -> [u8; 3] {
    match class {
        0 => [200, 180, 140],
        1 => [180, 60, 50],
        2 => [60, 140, 230],
        _ => [0, 0, 0],
    }
}

/// The alignment: `p_scene = 2·R·(p_geo − origin) + t`, R a quarter turn about z.
const ORIGIN: [f64; 3] = [500_000.0, 5_400_000.0, 100.0];
const T: [f64; 3] = [10.0, 20.0, 30.0];
fn r() -> DMat3 {
    DMat3::from_cols(DVec3::Y, -DVec3::X, DVec3::Z)
}

/// The georeferenced position (minus the origin) of Gaussian `i`.
fn geo(i: usize) -> DVec3 {
    DVec3::new(i as f64 + 0.5, 2.0 * i as f64 - 3.0, 4.0 - i as f64)
}

/// The input Gaussians, SH degree 3, in the scene frame: centres `2·R·geo + t`, axis-aligned
/// (identity quaternion), log-scales (−1, −2, −3), opacity 0.
fn gaussians() -> Gaussians {
    Gaussians {
        positions: (0..N)
            .map(|i| {
                (2.0 * (r() * geo(i)) + DVec3::from_array(T))
                    .to_array()
                    .map(|x| x as f32)
            })
            .collect(),
        normals: None,
        sh_degree: 3,
        f_dc: (0..N).map(|i| [0.1 * i as f32, 0.2, -0.3]).collect(),
        f_rest: (0..N * 45)
            .map(|k| ((k * 37 % 101) as f32 / 101.0 - 0.5) * 0.6)
            .collect(),
        opacity: vec![0.0; N],
        scale: vec![[-1.0, -2.0, -3.0]; N],
        rotation: vec![[1.0, 0.0, 0.0, 0.0]; N],
        extras: vec![],
    }
}

struct Fixture {
    root: PathBuf,
    scene: PathBuf,
    run: PathBuf,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.root);
    }
}

fn fixture(name: &str, alignment: bool) -> Fixture {
    let root =
        crate::common::temp_dir().join(format!("gs4city-export-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let (scene, run) = (root.join("scene"), root.join("run"));
    for d in ["citymodel", "sparse/0", "images"] {
        std::fs::create_dir_all(scene.join(d)).unwrap();
    }
    std::fs::write(scene.join("citymodel/hand.gml"), "<CityModel/>").unwrap();
    std::fs::write(scene.join("sparse/0/images.txt"), "").unwrap();
    splat::write_ply(
        &scene.join("point_cloud.ply"),
        &gaussians(),
        PlyEncoding::BinaryLittleEndian,
    )
    .unwrap();
    for d in ["citymodel", "lift"] {
        std::fs::create_dir_all(run.join(d)).unwrap();
    }
    fsutil::write_json(
        &run.join("citymodel/semantics.json"),
        &json!({"entities": entities()}),
    )
    .unwrap();
    if alignment {
        // Rows of R: a quarter turn about z.
        fsutil::write_json(
            &run.join("citymodel/alignment.json"),
            &json!({"origin": ORIGIN, "rotation": [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
                    "scale": 2.0, "translation": T}),
        )
        .unwrap();
    }
    let table: Vec<i32> = (0..N).flat_map(|i| [LABEL[i], CLASS[i]]).collect();
    npy::write(&run.join("lift/gaussians.npy"), &[N, 2], &table).unwrap();
    Fixture { root, scene, run }
}

fn gs4city(f: &Fixture, out: &Path, extra: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(["query", "--run"])
        .arg(&f.run)
        .arg("--scene")
        .arg(&f.scene)
        .args(["--views", "none", "--no-sqlite", "--out"])
        .arg(out)
        .args(extra)
        .output()
        .unwrap()
}

/// The project-local splat-transform (scripts/setup.sh), or `None` after [`common::skip`].
fn splat_transform(test: &str) -> Option<PathBuf> {
    let p =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/js/node_modules/.bin/splat-transform");
    if p.is_file() {
        return Some(p);
    }
    crate::common::skip(
        test,
        "tools/js/node_modules/.bin/splat-transform is missing (scripts/setup.sh runs npm ci in tools/js)",
    );
    None
}

/// `ply` as read by splat-transform, written out as CSV: the header and one map per row.
fn read_with_splat_transform(st: &Path, ply: &Path) -> Vec<std::collections::HashMap<String, f64>> {
    let csv = ply.with_extension("csv");
    let o = Command::new(st)
        .args(["-q", "-w"])
        .arg(ply)
        .arg(&csv)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "splat-transform {}: {}",
        ply.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let head: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    lines
        .map(|l| {
            head.iter()
                .cloned()
                .zip(l.split(',').map(|v| v.parse::<f64>().unwrap()))
                .collect()
        })
        .collect()
}

/// The rotation matrix of a unit quaternion (w, x, y, z).
fn quat_matrix(w: f64, x: f64, y: f64, z: f64) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y + w * z),
            2.0 * (x * z - w * y),
        ),
        DVec3::new(
            2.0 * (x * y - w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z + w * x),
        ),
        DVec3::new(
            2.0 * (x * z + w * y),
            2.0 * (y * z - w * x),
            1.0 - 2.0 * (x * x + y * y),
        ),
    )
}

#[test]
fn class_coloured_y_up_export_and_batches_read_by_splat_transform() {
    let f = fixture("class", true);
    let out = f.root.join("q");
    let o = gs4city(
        &f,
        &out,
        &[
            "--where",
            "class=Building",
            "--export",
            "--color-by",
            "class",
            "--up",
            "y",
            "--split-by",
            "building",
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Every city label is in B1 or B2: g0 g1 g2 g3 g5 extracted, g4 removed; the batches are
    // B1 (g0 g1 g2 g5) and B2 (g3), the file named by entity id and the gml:id made file-safe.
    let split: Value = fsutil::read_json(&out.join("split/split.json")).unwrap();
    assert_eq!(
        split,
        json!([
            {"file": "building_0_B1.ply", "group": "B1", "gaussians": 4},
            {"file": "building_4_B_2.ply", "group": "B/2", "gaussians": 1}
        ])
    );
    let Some(st) = splat_transform("export_ply::class_coloured") else {
        return;
    };
    let files: [(&str, Vec<usize>); 4] = [
        ("extract.ply", vec![0, 1, 2, 3, 5]),
        ("remove.ply", vec![4]),
        ("split/building_0_B1.ply", vec![0, 1, 2, 5]),
        ("split/building_4_B_2.ply", vec![3]),
    ];
    // Scene → output: Rᵀ (rows (0 1 0), (−1 0 0), (0 0 1)), then Z-up → Y-up
    // (x, y, z) ↦ (x, z, −y): by hand the product has rows (0 1 0), (0 0 1), (1 0 0).
    let m = DMat3::from_cols(DVec3::Z, DVec3::X, DVec3::Y);
    for (file, ids) in files {
        let rows = read_with_splat_transform(&st, &out.join(file));
        assert_eq!(rows.len(), ids.len(), "{file}");
        for (row, &i) in rows.iter().zip(&ids) {
            let g = geo(i);
            let want = [g.x, g.z, -g.y];
            for (k, c) in ["x", "y", "z"].iter().enumerate() {
                assert!(
                    (row[*c] - want[k]).abs() < 1e-4,
                    "{file} g{i} {c}: {} vs {}",
                    row[*c],
                    want[k]
                );
            }
            let rgb = palette(CLASS[i]);
            for c in 0..3 {
                let dc = (f64::from(rgb[c]) / 255.0 - 0.5) / C0;
                assert!(
                    (row[&format!("f_dc_{c}")] - dc).abs() < 1e-5,
                    "{file} g{i} f_dc_{c}"
                );
            }
            for k in 0..45 {
                assert_eq!(row[&format!("f_rest_{k}")], 0.0, "{file} g{i} f_rest_{k}");
            }
            // Scales shrink by the alignment's 2: log-scale − ln 2.
            for (c, s) in [-1.0, -2.0, -3.0].iter().enumerate() {
                let got = row[&format!("scale_{c}")];
                assert!(
                    (got - (s - 2f64.ln())).abs() < 1e-5,
                    "{file} g{i} scale_{c}"
                );
            }
            let q = quat_matrix(row["rot_0"], row["rot_1"], row["rot_2"], row["rot_3"]);
            assert!(q.abs_diff_eq(m, 1e-5), "{file} g{i}: {q} vs {m}");
            let cols = [
                ("label", LABEL[i]),
                ("class", CLASS[i]),
                ("feature_id", FEATURE[i]),
                ("surface_id", SURFACE[i]),
                ("part_id", PART[i]),
            ];
            for (c, v) in cols {
                assert_eq!(row[c], f64::from(v), "{file} g{i} {c}");
            }
        }
    }
}

#[test]
fn building_colours_and_rgb_byte_export_read_by_splat_transform() {
    let f = fixture("building", false);
    // Building colours: one per building, grey outside; no frame change needs no alignment.
    let out = f.root.join("b");
    let o = gs4city(
        &f,
        &out,
        &[
            "--where",
            "class=Building",
            "--export",
            "--color-by",
            "building",
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (g, _) = splat::read_ply(&out.join("extract.ply"), &Default::default()).unwrap();
    let (rest, _) = splat::read_ply(&out.join("remove.ply"), &Default::default()).unwrap();
    // Every labelled Gaussian: g0 g1 g2 g5 (B1) and g3 (B2).
    assert_eq!(g.len(), 5);
    let shown = |g: &Gaussians, k: usize| g.f_dc[k].map(|v| (C0 * f64::from(v) + 0.5) * 255.0);
    let (b1, b2) = (shown(&g, 0), shown(&g, 3));
    for k in [1, 2, 4] {
        for (got, want) in shown(&g, k).iter().zip(&b1) {
            assert!((got - want).abs() < 1e-3, "same building, same colour");
        }
    }
    assert!(
        (0..3).map(|c| (b1[c] - b2[c]).abs()).sum::<f64>() > 60.0,
        "B1 {b1:?} and B2 {b2:?} differ clearly"
    );
    // Outside every building: grey 128.
    for c in 0..3 {
        assert!((shown(&rest, 0)[c] - 128.0).abs() < 1e-3);
    }
    assert!(g.f_rest.iter().all(|&v| v == 0.0));

    // RGB: the byte path, input records unchanged plus the columns, positions in the scene frame.
    let out = f.root.join("rgb");
    let o = gs4city(&f, &out, &["--where", "within(B1)", "--export"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let Some(st) = splat_transform("export_ply::rgb_byte_export") else {
        return;
    };
    let input = gaussians();
    let rows = read_with_splat_transform(&st, &out.join("extract.ply"));
    assert_eq!(rows.len(), 4);
    for (row, i) in rows.iter().zip([0, 1, 2, 5]) {
        assert_eq!(row["x"], f64::from(input.positions[i][0]));
        assert_eq!(row["f_dc_0"], f64::from(input.f_dc[i][0]));
        assert_eq!(row["f_rest_44"], f64::from(input.f_rest[i * 45 + 44]));
        assert_eq!(
            (row["label"], row["class"]),
            (f64::from(LABEL[i]), f64::from(CLASS[i]))
        );
        assert_eq!(row["part_id"], f64::from(PART[i]));
    }
}

#[test]
fn up_axis_turns_the_view_dependent_colour_with_the_gaussians() {
    let f = fixture("sh", true);
    let out = f.root.join("z");
    let o = gs4city(
        &f,
        &out,
        &["--where", "within(B1)", "--export", "--up", "z"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (g, _) = splat::read_ply(&out.join("extract.ply"), &Default::default()).unwrap();
    let input = gaussians();
    // Z up: the geo frame itself, Rᵀ (scale aside); a colour seen along d in the scene is seen
    // along Rᵀd after the export.
    let m = r().transpose();
    let coeffs = |g: &Gaussians, k: usize| -> Vec<[f32; 3]> {
        let mut c = vec![g.f_dc[k]];
        for j in 0..15 {
            c.push([0, 1, 2].map(|ch| g.f_rest[k * 45 + ch * 15 + j]));
        }
        c
    };
    for (k, i) in [0, 1, 2, 5].into_iter().enumerate() {
        let p = geo(i);
        assert!((DVec3::from_array(g.positions[k].map(f64::from)) - p).length() < 1e-4);
        for d in [
            DVec3::new(0.3, -0.5, 0.81),
            DVec3::new(-0.9, 0.1, 0.2),
            DVec3::new(0.2, 0.7, -0.6),
        ] {
            let d = d.normalize();
            let before = gs4city::render::project::sh_color(&coeffs(&input, i), 3, d);
            let after = gs4city::render::project::sh_color(&coeffs(&g, k), 3, m * d);
            for c in 0..3 {
                assert!(
                    (before[c] - after[c]).abs() < 1e-4,
                    "g{i} along {d}: {before:?} vs {after:?}"
                );
            }
        }
    }
}

#[test]
fn export_options_fail_clearly() {
    let f = fixture("errors", false);
    let out = f.root.join("e");
    // An up axis needs the run's alignment.
    let o = gs4city(
        &f,
        &out,
        &["--where", "within(B1)", "--export", "--up", "y"],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("alignment.json"), "{err}");
    assert!(!out.join("extract.ply").exists());
    // The viewer options belong to --export; unknown values are refused by name.
    let o = gs4city(&f, &out, &["--where", "within(B1)", "--color-by", "class"]);
    assert!(!o.status.success());
    let o = gs4city(
        &f,
        &out,
        &["--where", "within(B1)", "--export", "--color-by", "red"],
    );
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("rgb, class, building"));
}
