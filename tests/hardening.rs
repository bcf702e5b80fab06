//! Bad input: every bad input gets one clear error (or a warning where the output stays
//! right). One test per class of bad input; each builds its inputs here (or reads them from
//! `tests/data/bad/`) and checks the reader's answer against what the input is known to be.
//! `replayed_fuzz_inputs_give_clean_answers` replays every committed fuzz finding through the
//! same checks the fuzz targets run (`fuzz/src/checks.rs`).
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};
use gs4city::alignment::{self as align, Alignment};
use gs4city::camera::{Camera, Distortion, Intrinsics, Pose, SCENE_COORD_LIMIT};
use gs4city::mesh::{FaceLabel, TriMesh};
use gs4city::raycast::{RaycastError, TwoPassScene};
use gs4city::splat::{self, InvalidPolicy, PlyError, ReadOptions};
use gs4city::{citygml, colmap, npy, ply, sam};
use gs4city::{citymodel, semantics};

#[path = "../fuzz/src/checks.rs"]
#[allow(dead_code)]
mod checks;

fn tmp(tag: &str) -> PathBuf {
    let d =
        crate::common::temp_dir().join(format!("gs4city-hardening-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// An error message as `main` prints it (`{:#}` of the chain): the message, then each
/// source. Checks the rules of bad-input messages: one line, names `file`, no Rust debug dump, and no
/// part of the chain repeated.
fn check_message(e: &dyn std::error::Error, file: &str) -> String {
    let mut parts = vec![e.to_string()];
    let mut src = e.source();
    while let Some(s) = src {
        parts.push(s.to_string());
        src = s.source();
    }
    let msg = parts.join(": ");
    assert!(!msg.contains('\n'), "not one line: {msg}");
    assert!(msg.contains(file), "does not name {file}: {msg}");
    // A number printed in full (10³⁰⁰ as 301 digits) instead of `1e300`.
    let digits = msg
        .split(|c: char| !c.is_ascii_digit())
        .map(str::len)
        .max()
        .unwrap_or(0);
    assert!(digits < 25, "a number of {digits} digits: {msg}");
    for dump in ["{ ", " }", "Some(", "Err(", "Error {", "\\\""] {
        assert!(!msg.contains(dump), "debug dump ({dump}): {msg}");
    }
    for (i, p) in parts.iter().enumerate().skip(1) {
        assert!(
            !parts[0..i].iter().any(|q| q.contains(p.as_str())),
            "repeated cause {p:?}: {msg}"
        );
    }
    msg
}

// ------------------------------------------------------------------ sizes from headers

#[test]
fn ply_header_sizes_are_checked_before_anything_is_allocated() {
    let core = "property float x\nproperty float y\nproperty float z\n";
    for (count, enc) in [
        ("1000000000000", "binary_little_endian"),
        ("18446744073709551615", "binary_big_endian"),
        ("100000000000000", "ascii"),
    ] {
        let text = format!("ply\nformat {enc} 1.0\nelement vertex {count}\n{core}end_header\n");
        let e = TriMesh::from_ply_bytes(Path::new("huge.ply"), text.as_bytes()).unwrap_err();
        let msg = check_message(&e, "huge.ply");
        assert!(msg.contains(count) || msg.contains("vertex 0 of"), "{msg}");
    }
    // A count beyond usize is a header error on its line.
    let text =
        format!("ply\nformat ascii 1.0\nelement vertex 99999999999999999999\n{core}end_header\n");
    let e = ply::Reader::new(Path::new("h.ply"), text.as_bytes())
        .err()
        .unwrap();
    assert!(matches!(e, ply::PlyError::Header { line: 3, .. }), "{e}");
    // A list whose count runs past the end of the file.
    let mut mesh = sample_mesh().to_ply_bytes();
    let n = mesh.len();
    mesh[n - 25] = 250; // the first face's uchar count (2 faces × 25 bytes)
    let e = TriMesh::from_ply_bytes(Path::new("list.ply"), &mesh).unwrap_err();
    assert!(check_message(&e, "list.ply").contains("face 1 of 2"), "{e}");
}

#[test]
fn npy_shape_products_that_overflow_are_errors() {
    let header = |shape: &str| {
        let mut h = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((h.len() as u16).to_le_bytes());
        b.extend(h.as_bytes());
        b
    };
    for shape in [
        "(4294967296, 4294967296, 2)",
        "(4611686018427387904, 4)", // fits usize, but ×4 bytes does not
        "(18446744073709551615,)",
    ] {
        let e = npy::decode::<f32>(Path::new("big.npy"), &header(shape)).unwrap_err();
        let msg = check_message(&e, "big.npy");
        assert!(
            matches!(e, npy::NpyError::Overflow { .. }),
            "{shape}: {msg}"
        );
    }
    let e = npy::decode::<f32>(Path::new("b.npy"), &header("(3, x)")).unwrap_err();
    assert!(check_message(&e, "b.npy").contains("not a tuple of whole numbers"));
    // The committed fixture (the class as a file).
    let p = data_bad("npy/shape_overflow.npy");
    let e = npy::read::<f32>(&p).unwrap_err();
    check_message(&e, "shape_overflow.npy");
}

/// A 64-byte `cameras.bin` declaring a 60000×60000 image (an allocation bomb): the COLMAP
/// reader refuses it with `Camera::validate`'s reason, so no stage ever allocates for it.
#[test]
fn a_camera_declaring_a_huge_image_is_refused_by_the_reader() {
    let dir = tmp("huge-camera");
    std::fs::copy(
        data_bad("colmap/cameras_60000.bin"),
        dir.join("cameras.bin"),
    )
    .unwrap();
    assert_eq!(
        std::fs::metadata(dir.join("cameras.bin")).unwrap().len(),
        64
    );
    let mut images = 1u64.to_le_bytes().to_vec();
    images.extend(1u32.to_le_bytes());
    for v in [1.0f64, 0.0, 0.0, 0.0, 0.0, 0.0, 5.0] {
        images.extend(v.to_le_bytes());
    }
    images.extend(1u32.to_le_bytes());
    images.extend(b"a.png\0");
    images.extend(0u64.to_le_bytes());
    std::fs::write(dir.join("images.bin"), &images).unwrap();
    let e = colmap::read_model(&dir).unwrap_err();
    let msg = check_message(&e, "cameras.bin");
    assert!(
        msg.contains("camera 1") && msg.contains("60000×60000") && msg.contains("megapixels"),
        "{msg}"
    );
    // The same camera in text form names the line.
    std::fs::write(
        dir.join("cameras.txt"),
        "# c\n1 PINHOLE 60000 60000 500 500 30000 30000\n",
    )
    .unwrap();
    std::fs::write(dir.join("images.txt"), "1 1 0 0 0 0 0 5 1 a.png\n\n").unwrap();
    std::fs::remove_file(dir.join("cameras.bin")).unwrap();
    std::fs::remove_file(dir.join("images.bin")).unwrap();
    let e = colmap::read_model(&dir).unwrap_err();
    let msg = check_message(&e, "cameras.txt");
    assert!(
        msg.contains("cameras.txt:2: camera 1: image size 60000×60000"),
        "{msg}"
    );
}

// ------------------------------------------------------------------ values the math cannot take

fn good_camera() -> Camera {
    Camera {
        intrinsics: Intrinsics {
            width: 640,
            height: 480,
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            distortion: Distortion::Radial { k1: -0.1, k2: 0.0 },
        },
        pose: Pose::look_at(DVec3::new(10.0, 0.0, 2.0), DVec3::ZERO, DVec3::Z).unwrap(),
    }
}

#[test]
fn camera_validate_refuses_what_render_and_raycast_cannot_take() {
    good_camera().validate().unwrap();
    type Change = Box<dyn Fn(&mut Camera)>;
    let cases: Vec<(&str, Change, &str)> = vec![
        (
            "huge image",
            Box::new(|c| c.intrinsics.width = 60000),
            "megapixels",
        ),
        (
            "empty image",
            Box::new(|c| c.intrinsics.height = 0),
            "empty",
        ),
        (
            "tiny focal",
            Box::new(|c| c.intrinsics.fx = 1e-300),
            "focal length fx = 1e-300 px",
        ),
        (
            "NaN focal",
            Box::new(|c| c.intrinsics.fy = f64::NAN),
            "focal length fy",
        ),
        (
            "huge focal",
            Box::new(|c| c.intrinsics.fx = 1e12),
            "focal length fx = 1e12 px",
        ),
        (
            "principal point",
            Box::new(|c| c.intrinsics.cx = 1e30),
            "principal point cx = 1e30 px",
        ),
        (
            "distortion",
            Box::new(|c| c.intrinsics.distortion = Distortion::Radial { k1: 1e300, k2: 0.0 }),
            "distortion coefficient 1e300 is",
        ),
        (
            "NaN pose",
            Box::new(|c| c.pose.translation.y = f64::NAN),
            "finite",
        ),
        (
            "not a rotation",
            Box::new(|c| c.pose.rotation = DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0))),
            "not a rotation",
        ),
        (
            "centre at 1e20",
            Box::new(|c| {
                c.pose = Pose::look_at(DVec3::splat(1e20), DVec3::ZERO, DVec3::Z).unwrap()
            }),
            "camera centre",
        ),
    ];
    for (what, change, expect) in cases {
        let mut c = good_camera();
        change(&mut c);
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains(expect), "{what}: {e}");
        assert!(!e.contains('\n'));
    }
    // The scene-frame limit itself: a centre just inside passes, just outside fails.
    let mut c = good_camera();
    c.pose = Pose::look_at(DVec3::new(0.9e6, 0.0, 0.0), DVec3::ZERO, DVec3::Z).unwrap();
    c.validate().unwrap();
    c.pose = Pose::look_at(DVec3::new(1.1e6, 0.0, 0.0), DVec3::ZERO, DVec3::Z).unwrap();
    assert!(c.validate().is_err());
}

fn sample_mesh() -> TriMesh {
    TriMesh {
        vertices: vec![
            [0.0, 0.0, 5.0],
            [1.0, 0.0, 5.0],
            [1.0, 1.0, 5.0],
            [0.0, 1.0, 5.0],
        ],
        faces: vec![[0, 1, 2], [0, 2, 3]],
        labels: vec![
            FaceLabel {
                feature: 0,
                surface: 1,
                part: -1,
            },
            FaceLabel {
                feature: 0,
                surface: 1,
                part: 2,
            },
        ],
    }
}

/// A mesh coordinate of 1e20 used to trip an Embree assertion (process abort, no file
/// named); it is now refused before Embree sees it, in memory and on reading.
#[test]
fn mesh_coordinates_beyond_the_scene_frame_are_refused_before_embree() {
    for bad in [1e20f32, -2.0e6, f32::INFINITY, f32::NAN] {
        let mut m = sample_mesh();
        m.vertices[2][1] = bad;
        let e = TwoPassScene::build(&m).err().expect("refused");
        assert!(matches!(e, RaycastError::Mesh(_)), "{e}");
        assert!(e.to_string().contains("vertex 2"), "{e}");
        let e = TriMesh::from_ply_bytes(Path::new("far.ply"), &m.to_ply_bytes()).unwrap_err();
        assert!(check_message(&e, "far.ply").contains("vertex 2"));
    }
    let mut m = sample_mesh();
    m.vertices[0][0] = (SCENE_COORD_LIMIT * 0.99) as f32;
    assert!(TwoPassScene::build(&m).is_ok());
}

/// Face ids beyond the semantic table: refused with the face named, before raycasting,
/// and never turned into a huge per-surface table.
#[test]
fn mesh_face_ids_beyond_the_semantic_table_are_refused() {
    let entities: Vec<semantics::Entity> = serde_json::from_str(
        r#"[{"id":0,"object_id":"B","class":"Building","level":"feature","parent":null,"building":0,"source":"a","lod":3,"attributes":{}},
            {"id":1,"object_id":"W","class":"WallSurface","level":"surface","parent":0,"building":0,"source":"a","lod":3,"attributes":{}},
            {"id":2,"object_id":"O","class":"Window","level":"part","parent":1,"building":0,"source":"a","lod":3,"attributes":{}}]"#,
    )
    .unwrap();
    let p = Path::new("mesh.ply");
    semantics::check_mesh_labels(p, &sample_mesh(), &entities).unwrap();
    let mut m = sample_mesh();
    m.labels[1].part = 3;
    let e = semantics::check_mesh_labels(p, &m, &entities).unwrap_err();
    let msg = check_message(&e, "mesh.ply");
    assert!(
        msg.contains("face 1 has part id 3") && msg.contains("3 entities"),
        "{msg}"
    );
    let mut m = sample_mesh();
    m.labels[0].surface = 2; // a part used as a surface
    let e = semantics::check_mesh_labels(p, &m, &entities).unwrap_err();
    assert!(
        e.to_string()
            .contains("face 0: its surface id 2 is entity O, a part"),
        "{e}"
    );
    // Without the table: ids below −1 are invalid, and ids too large for the dense
    // per-surface table are refused instead of allocated.
    let mut m = sample_mesh();
    m.labels[0].feature = -7;
    assert!(m.validate().unwrap_err().contains("face 0"));
    let mut m = sample_mesh();
    m.labels[1].surface = i32::MAX;
    let e = TwoPassScene::build(&m).err().expect("refused");
    assert!(e.to_string().contains("face 1"), "{e}");
}

/// The issue's 1e308 scale: refused when read, and an alignment that puts the mesh beyond
/// the scene frame is refused with the polygon named.
#[test]
fn alignments_that_leave_the_scene_frame_are_refused() {
    let p = Path::new("alignment.json");
    let json = |scale: &str, t: &str| {
        format!(
            r#"{{"origin":[0,0,0],"scale":{scale},"rotation":[[1,0,0],[0,1,0],[0,0,1]],"translation":[{t},0,0]}}"#
        )
    };
    for scale in ["1e308", "0", "-1", "1e-12"] {
        let e = Alignment::from_json_str(p, &json(scale, "0")).unwrap_err();
        let m = check_message(&e, "alignment.json");
        assert!(m.contains(&format!("scale {scale} is outside")), "{m}");
    }
    let e = Alignment::from_json_str(p, &json("1", "1e400")).unwrap_err();
    assert!(e.to_string().contains("alignment.json"), "{e}");
    // Within range, but it carries the building 5e6 units away.
    let a = Alignment::from_json_str(p, &json("1", "5e6")).unwrap();
    let dir = tmp("frame");
    let gml = dir.join("b.gml");
    std::fs::write(&gml, building_gml("", "")).unwrap();
    let e = citymodel::run(
        std::slice::from_ref(&gml),
        &citymodel::Options { alignment: Some(a) },
    )
    .err()
    .expect("refused");
    let msg = check_message(&e, "b.gml");
    assert!(
        msg.contains("polygon P1") && msg.contains("scene frame"),
        "{msg}"
    );
    // Without an alignment the stage says where the mesh is.
    let out = citymodel::run(&[gml], &citymodel::Options::default()).unwrap();
    let w = out.summary.warnings.items.join("\n");
    assert!(w.contains("no alignment given"), "{w}");
}

/// A round window whose ring has a few mistyped exponents (`…e9`, found by a mutation sweep of
/// the FZK house) made the triangulator panic inside spade, before the frame check on its
/// output ran. Every vertex is now checked before triangulation: one line naming the polygon.
#[test]
fn a_ring_with_mistyped_exponents_is_refused_before_triangulation() {
    let gml = data_bad("fuzz/citymodel/mistyped_exponents_circle.gml");
    let e = citymodel::run(std::slice::from_ref(&gml), &citymodel::Options::default())
        .err()
        .expect("refused");
    let msg = check_message(&e, "mistyped_exponents_circle.gml");
    assert!(
        msg.contains("mistyped_exponents_circle.gml:4: polygon P1")
            && msg.contains("in the scene frame, beyond"),
        "{msg}"
    );
}

/// A self-crossing ring 10 km wide, 100 km tall and 12 cm deep (a mutation of the FZK house,
/// with a small pinned triangle so that the local origin is the mutant's) made spade fail an
/// internal assertion ("Failed to locate position"): the polygon is now skipped with spade's
/// words, the rest of the model is written, and nothing is printed as a panic.
#[test]
fn a_ring_the_triangulator_fails_on_is_skipped_not_a_crash() {
    let gml = data_bad("fuzz/citymodel/spade_locate_failure.gml");
    let out = citymodel::run(std::slice::from_ref(&gml), &citymodel::Options::default())
        .expect("the pinned triangle is still written");
    let skipped = &out.summary.skipped.polygons;
    assert_eq!(skipped.len(), 1, "{skipped:?}");
    assert_eq!(skipped[0].polygon.as_deref(), Some("P1"));
    assert!(skipped[0].reason.contains("spade"), "{:?}", skipped[0]);
    assert_eq!(out.mesh.faces.len(), 1, "the pinned triangle");
}

/// Mirrored and degenerate point pairs used to give an RMS of 31 m without a word.
#[test]
fn mirrored_degenerate_and_poor_point_pairs_are_refused_or_warned() {
    let p = Path::new("pairs.csv");
    let geo: Vec<DVec3> = [
        [0.0, 0.0, 0.0],
        [30.0, 0.0, 0.0],
        [0.0, 20.0, 0.0],
        [0.0, 0.0, 10.0],
        [30.0, 20.0, 5.0],
        [12.0, 7.0, 9.0],
    ]
    .iter()
    .map(|a| DVec3::from_array(*a) + DVec3::new(678_000.0, 5_403_000.0, 400.0))
    .collect();
    let truth = Alignment {
        origin: DVec3::new(678_000.0, 5_403_000.0, 400.0),
        scale: 0.5,
        rotation: DMat3::from_rotation_z(0.3),
        translation: DVec3::new(1.0, 2.0, 3.0),
    };
    let pairs: Vec<(DVec3, DVec3)> = geo.iter().map(|g| (*g, truth.apply(*g))).collect();
    let est = align::estimate(p, &pairs).unwrap();
    assert!(est.rms < 1e-9 && est.warnings.is_empty());
    // Mirror: the scene x axis flipped.
    let mirrored: Vec<_> = pairs
        .iter()
        .map(|(g, s)| (*g, DVec3::new(-s.x, s.y, s.z)))
        .collect();
    let e = align::estimate(p, &mirrored).unwrap_err();
    let msg = check_message(&e, "pairs.csv");
    assert!(msg.contains("mirror"), "{msg}");
    // Degenerate scene side: all scene points on a line.
    let line: Vec<_> = pairs
        .iter()
        .enumerate()
        .map(|(i, (g, _))| (*g, DVec3::X * i as f64))
        .collect();
    let e = align::estimate(p, &line).unwrap_err();
    assert!(
        e.to_string()
            .contains("scene points are (nearly) collinear"),
        "{e}"
    );
    // Pairs that do not correspond: accepted, with a warning naming the worst pair.
    let mut shuffled = pairs.clone();
    shuffled[4].1 = pairs[1].1;
    shuffled[1].1 = pairs[4].1;
    let est = align::estimate(p, &shuffled).unwrap();
    assert_eq!(est.warnings.len(), 1, "{:?}", est.warnings);
    assert!(
        est.warnings[0].contains("fits poorly"),
        "{}",
        est.warnings[0]
    );
    // CSV messages say what is wrong.
    let e = align::parse_pairs(p, "1,2,3,4,5,6\n1,2,3,4,5\n").unwrap_err();
    assert!(
        e.to_string().contains("pairs.csv:2: expected 6 numbers"),
        "{e}"
    );
    assert!(e.to_string().contains("found 5"), "{e}");
    let e = align::parse_pairs(p, "1,2,3,4,5,6\n1,2,inf,4,5,6\n").unwrap_err();
    assert!(
        e.to_string().contains("geo_z is inf, not a finite number"),
        "{e}"
    );
    let e = align::parse_pairs(p, "1,2,3,4,5,6\n1,2,x,4,5,6\n").unwrap_err();
    assert!(e.to_string().contains("\"x\" is not a number"), "{e}");
    // A finite but absurd coordinate is named on its row (it was "collinear or coincident").
    let e = align::parse_pairs(p, "1,2,3,4,5,6\n1,2,3,4,1e300,6\n").unwrap_err();
    assert!(
        e.to_string()
            .contains("pairs.csv:2: scene_y is 1e300: beyond 1e12"),
        "{e}"
    );
    let ok = align::parse_pairs(p, "6e6,5e6,400,1e11,-1e11,3\n").unwrap();
    assert_eq!(ok[0].1, glam::DVec3::new(1e11, -1e11, 3.0));
}

// ------------------------------------------------------------------ 3DGS values at load

fn splat_ascii(rows: &[[&str; 14]]) -> Vec<u8> {
    let mut t = format!("ply\nformat ascii 1.0\nelement vertex {}\n", rows.len());
    for p in [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ] {
        t.push_str(&format!("property float {p}\n"));
    }
    t.push_str("end_header\n");
    for r in rows {
        t.push_str(&r.join(" "));
        t.push('\n');
    }
    t.into_bytes()
}

const GOOD: [&str; 14] = [
    "0", "0", "1", "0.1", "0.2", "0.3", "0", "-3", "-3", "-3", "1", "0", "0", "0",
];

#[test]
fn gaussian_values_are_checked_once_at_load() {
    let p = Path::new("scene.ply");
    // (column, value, expected fragment); the header has 18 lines, row 1 is line 20.
    let cases = [
        (8, "95", "`scale_1` is 95.0, outside the log-scale range"),
        (9, "-60", "`scale_2` is -60.0"),
        (4, "1e30", "`f_dc_1` is 1e30, outside ±1e6"),
        (0, "1e20", "`x` is 1e20, outside ±1e6"),
        (5, "nan", "`f_dc_2` is NaN, not a finite number"),
        (6, "inf", "`opacity` is inf, not a finite number"),
    ];
    for (col, value, expect) in cases {
        let mut bad = GOOD;
        bad[col] = value;
        let bytes = splat_ascii(&[GOOD, bad, GOOD]);
        let e = splat::read_ply_bytes(p, &bytes, &ReadOptions::default()).unwrap_err();
        let msg = check_message(&e, "scene.ply");
        assert!(
            msg.contains("vertex 1 (line 20)") && msg.contains(expect),
            "{msg}"
        );
        let drop = ReadOptions {
            invalid: InvalidPolicy::Drop,
            ..Default::default()
        };
        let (g, report) = splat::read_ply_bytes(p, &bytes, &drop).unwrap();
        assert_eq!(g.len(), 2);
        assert_eq!(
            report.dropped_non_finite + report.dropped_out_of_range,
            1,
            "{value}"
        );
    }
    // A saturated opacity logit is fine (sigmoid cannot overflow); so are the range ends.
    let mut edge = GOOD;
    edge[6] = "-1e30";
    edge[7] = "-40";
    edge[8] = "20";
    edge[3] = "-1e6";
    let (g, _) = splat::read_ply_bytes(p, &splat_ascii(&[edge]), &ReadOptions::default()).unwrap();
    assert_eq!(g.activated_opacity(0), 0.0);
}

// ------------------------------------------------------------------ PLY content

/// A PLY whose payload holds more rows than its header declares is refused (it used to be
/// read silently, dropping the rest).
#[test]
fn ply_with_more_data_than_declared_is_refused() {
    let p = Path::new("extra.ply");
    let mut bytes = splat_ascii(&[GOOD, GOOD]);
    bytes.extend(b"0 0 1 0 0 0 0 -3 -3 -3 1 0 0 0\n");
    // Declares 2 rows, holds 3.
    assert!(String::from_utf8_lossy(&bytes).contains("element vertex 2\n"));
    let e = splat::read_ply_bytes(p, &bytes, &ReadOptions::default()).unwrap_err();
    let msg = check_message(&e, "extra.ply");
    assert!(
        msg.contains("line 21") && msg.contains("more rows than its header declares"),
        "{msg}"
    );
    // Binary: the committed fixture (a 3DGS file with one vertex more than declared).
    let path = data_bad("ply/splat_extra_vertex.ply");
    let e = splat::read_ply(&path, &ReadOptions::default()).unwrap_err();
    let msg = check_message(&e, "splat_extra_vertex.ply");
    assert!(
        msg.contains("bytes after the last row of `vertex`"),
        "{msg}"
    );
    // mesh.ply with one face more than declared.
    let m = sample_mesh();
    let mut bytes = m.to_ply_bytes();
    let last = bytes[bytes.len() - 25..].to_vec();
    bytes.extend(last);
    let e = TriMesh::from_ply_bytes(Path::new("mesh.ply"), &bytes).unwrap_err();
    assert!(check_message(&e, "mesh.ply").contains("25 bytes after the last row of `face`"));
}

#[test]
fn ply_errors_are_one_line_sentences() {
    let cases: [(&[u8], &str); 6] = [
        (b"PLY\n", "line 1: not a PLY file"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "ends before end_header"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty flt x\nend_header\n1\n", "line 4: unknown property type `flt`"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty uchar x\nend_header\n300\n", "vertex 0 (line 6): `300` is not a uchar"),
        (b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n-1\n", "face 0 (line 6): `-1` is not a uchar"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty double x\nend_header\n12345678", "the file ends in vertex 1 of 2"),
    ];
    // Every element read, as a consumer of the format would.
    let read_all = |bytes: &[u8]| -> Result<(), ply::PlyError> {
        let mut r = ply::Reader::new(Path::new("m.ply"), bytes)?;
        let names: Vec<String> = r.header().elements.iter().map(|e| e.name.clone()).collect();
        for n in names {
            r.read_element(&n, |_| Ok::<(), ply::PlyError>(()))?;
        }
        r.finish()
    };
    for (bytes, expect) in cases {
        let e = read_all(bytes).unwrap_err();
        let msg = check_message(&e, "m.ply");
        assert!(msg.contains(expect), "{msg}");
    }
    // The OS reason of a missing file appears once.
    let e = splat::read_ply(Path::new("/nonexistent/x.ply"), &ReadOptions::default()).unwrap_err();
    assert!(matches!(e, PlyError::Format(ply::PlyError::Io { .. })));
    let msg = check_message(&e, "x.ply");
    assert_eq!(msg.matches("os error 2").count(), 1, "{msg}");
}

#[test]
fn os_errors_are_printed_once_by_every_reader() {
    let missing = Path::new("/nonexistent/gs4city/input");
    let errors: Vec<Box<dyn std::error::Error>> = vec![
        Box::new(citygml::read(missing).unwrap_err()),
        Box::new(npy::read::<f32>(missing).unwrap_err()),
        Box::new(TriMesh::read_ply(missing).unwrap_err()),
        Box::new(Alignment::read(missing).unwrap_err()),
        Box::new(align::read_pairs(missing).unwrap_err()),
        Box::new(sam::read_sam_json(missing).unwrap_err()),
        Box::new(sam::read_prompts_json(missing).unwrap_err()),
    ];
    for e in errors {
        let msg = check_message(e.as_ref(), "/nonexistent/gs4city/input");
        assert_eq!(msg.matches("os error 2").count(), 1, "{msg}");
    }
}

// ------------------------------------------------------------------ CityGML content

const NS: &str = r#"xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:gml="http://www.opengis.net/gml""#;

/// One building with one wall polygon `P1` (10 × 6 m), an optional extra interior ring and
/// optional extra content before the building.
fn building_gml(interior: &str, before: &str) -> String {
    format!(
        r#"<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel {NS}>{before}
<core:cityObjectMember><bldg:Building gml:id="B1"><bldg:boundedBy><bldg:WallSurface gml:id="W1">
<bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon gml:id="P1">
<gml:exterior><gml:LinearRing><gml:posList srsDimension="3">0 0 0 10 0 0 10 0 6 0 0 6 0 0 0</gml:posList></gml:LinearRing></gml:exterior>{interior}
</gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface>
</bldg:WallSurface></bldg:boundedBy></bldg:Building></core:cityObjectMember>
</core:CityModel>
"#
    )
}

fn interior(pts: &[[f64; 3]]) -> String {
    let mut s: Vec<String> = pts
        .iter()
        .map(|p| format!("{} {} {}", p[0], p[1], p[2]))
        .collect();
    s.push(s[0].clone());
    format!(
        "<gml:interior><gml:LinearRing><gml:posList>{}</gml:posList></gml:LinearRing></gml:interior>",
        s.join(" ")
    )
}

fn mesh_area(m: &TriMesh) -> f64 {
    m.faces
        .iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| DVec3::from_array(m.vertices[i as usize].map(f64::from)));
            0.5 * (b - a).cross(c - a).length()
        })
        .sum()
}

/// An interior ring outside its exterior used to be filled (an extra island); it is now
/// dropped with a sentence naming the polygon. A proper hole still cuts.
#[test]
fn interior_rings_outside_their_exterior_are_dropped_with_a_warning() {
    let dir = tmp("holes");
    let run = |hole: &str| {
        let f = dir.join("h.gml");
        std::fs::write(&f, building_gml(hole, "")).unwrap();
        citymodel::run(&[f], &citymodel::Options::default()).unwrap()
    };
    let inside = run(&interior(&[
        [2.0, 0.0, 1.0],
        [4.0, 0.0, 1.0],
        [4.0, 0.0, 3.0],
        [2.0, 0.0, 3.0],
    ]));
    assert!((mesh_area(&inside.mesh) - (60.0 - 4.0)).abs() < 1e-9);
    for (hole, how) in [
        // Entirely outside (beyond x = 10).
        (
            [
                [12.0, 0.0, 1.0],
                [14.0, 0.0, 1.0],
                [14.0, 0.0, 3.0],
                [12.0, 0.0, 3.0],
            ],
            "lies outside",
        ),
        // Straddling the edge x = 10.
        (
            [
                [9.0, 0.0, 1.0],
                [11.0, 0.0, 1.0],
                [11.0, 0.0, 3.0],
                [9.0, 0.0, 3.0],
            ],
            "crosses",
        ),
    ] {
        let out = run(&interior(&hole));
        assert!(
            (mesh_area(&out.mesh) - 60.0).abs() < 1e-9,
            "{how}: area {}",
            mesh_area(&out.mesh)
        );
        let w = out.summary.warnings.items.join("\n");
        assert!(
            w.contains("polygon P1: interior ring 1") && w.contains(how),
            "{w}"
        );
        assert_eq!(out.summary.repairs["holes_not_inside_dropped"], 1);
    }
}

#[test]
fn duplicate_gml_ids_are_warned_and_kept_apart() {
    let dup = r#"<core:cityObjectMember><bldg:Building gml:id="B1"><gml:name>twin</gml:name></bldg:Building></core:cityObjectMember>"#;
    let m = citygml::read_bytes(Path::new("d.gml"), building_gml("", dup).as_bytes()).unwrap();
    let ids: Vec<&str> = m.objects.iter().map(|o| o.object_id.as_str()).collect();
    assert_eq!(ids, ["B1", "B1~2", "W1"]);
    let w: Vec<String> = m.warnings.iter().map(|w| w.to_string()).collect();
    assert!(
        w.iter()
            .any(|w| w.contains("d.gml:3: B1: gml:id \"B1\" is already used at line 2")),
        "{w:?}"
    );
}

#[test]
fn invalid_srs_dimension_entities_and_encodings_are_errors_with_lines() {
    let p = Path::new("e.gml");
    let gml = building_gml("", "").replace(r#"srsDimension="3""#, r#"srsDimension="three""#);
    let e = citygml::read_bytes(p, gml.as_bytes()).unwrap_err();
    assert!(
        check_message(&e, "e.gml").contains("e.gml:5: srsDimension=\"three\""),
        "{e}"
    );
    let gml = building_gml("", "").replace(r#"srsDimension="3""#, r#"srsDimension="7""#);
    assert!(citygml::read_bytes(p, gml.as_bytes()).is_err());
    let gml = building_gml("", "<gml:name>A &nbsp; B</gml:name>");
    let e = citygml::read_bytes(p, gml.as_bytes()).unwrap_err();
    assert!(
        check_message(&e, "e.gml").contains("e.gml:2: undefined XML entity &nbsp;"),
        "{e}"
    );
    let gml = building_gml("", "").replacen(
        "<core:CityModel",
        "<!DOCTYPE x [<!ENTITY co \"Company\">]>\n<core:CityModel",
        1,
    );
    let gml = gml.replace(
        "<bldg:boundedBy>",
        "<gml:name>&co;</gml:name><bldg:boundedBy>",
    );
    let e = citygml::read_bytes(p, gml.as_bytes()).unwrap_err();
    assert!(
        e.to_string().contains("declared in the document type"),
        "{e}"
    );
    let gml = building_gml("", "").replace(r#"gml:id="B1""#, r#"gml:id="B&bogus;1""#);
    let e = citygml::read_bytes(p, gml.as_bytes()).unwrap_err();
    assert!(e.to_string().contains("e.gml:3:"), "{e}");
    // Latin-1 with its declaration: read, and an error on line 8 is reported on line 8.
    let e = citygml::read(&data_bad("citygml/latin1_bad_number.gml")).unwrap_err();
    let msg = check_message(&e, "latin1_bad_number.gml");
    assert!(
        msg.contains("latin1_bad_number.gml:8: polygon P1: 'x' is not a number"),
        "{msg}"
    );
    let bad = std::fs::read(data_bad("citygml/latin1_bad_number.gml")).unwrap();
    let good = replace_bytes(&bad, b" x</gml:posList>", b" 0</gml:posList>");
    let m = citygml::read_bytes(Path::new("l.gml"), &good).unwrap();
    assert_eq!(m.objects[0].attributes["name"], "H\u{e4}user");
    // Latin-1 bytes without a declaration: the error names the line of the first bad byte
    // (the `ü` of line 3, line 2 once the declaration is gone).
    let start = good.iter().position(|&b| b == b'\n').unwrap() + 1;
    let e = citygml::read_bytes(Path::new("u.gml"), &good[start..]).unwrap_err();
    let msg = check_message(&e, "u.gml");
    assert!(
        msg.contains("u.gml:2: the file is not valid UTF-8 (byte 0xfc)"),
        "{msg}"
    );
}

/// UTF-16 (with a byte-order mark) and windows-1252 files read as their text says.
#[test]
fn citygml_in_utf16_and_windows_1252_reads_the_same_model() {
    let text = building_gml("", "<gml:name>Caf\u{e9} \u{20ac}5</gml:name>");
    let utf8 = citygml::read_bytes(Path::new("a.gml"), text.as_bytes()).unwrap();
    for big in [false, true] {
        let mut bytes = if big {
            vec![0xFE, 0xFF]
        } else {
            vec![0xFF, 0xFE]
        };
        for u in text.encode_utf16() {
            bytes.extend(if big {
                u.to_be_bytes()
            } else {
                u.to_le_bytes()
            });
        }
        let m = citygml::read_bytes(Path::new("a16.gml"), &bytes).unwrap();
        assert_eq!(m.polygons, utf8.polygons);
        assert_eq!(m.objects, utf8.objects);
        // A lone surrogate is an error naming its line.
        let at = bytes.len() - 8;
        bytes[at..at + 2].copy_from_slice(if big { &[0xDC, 0x00] } else { &[0x00, 0xDC] });
        let e = citygml::read_bytes(Path::new("a16.gml"), &bytes).unwrap_err();
        let msg = check_message(&e, "a16.gml");
        assert!(
            msg.contains("a16.gml:8: the file is not valid UTF-16"),
            "{msg}"
        );
    }
    // windows-1252: é is 0xE9, € is 0x80.
    let cp = text
        .replace("encoding=\"UTF-8\"", "encoding=\"windows-1252\"")
        .replace('\u{20ac}', "\u{80}");
    let bytes: Vec<u8> = cp.chars().map(|c| c as u32 as u8).collect();
    let m = citygml::read_bytes(Path::new("cp.gml"), &bytes).unwrap();
    assert_eq!(m.polygons, utf8.polygons);
    let e = citygml::read_bytes(
        Path::new("x.gml"),
        text.replace("UTF-8", "EBCDIC").as_bytes(),
    )
    .unwrap_err();
    assert!(
        e.to_string()
            .contains("x.gml:1: the XML declaration names encoding \"EBCDIC\"")
    );
}

fn replace_bytes(hay: &[u8], from: &[u8], to: &[u8]) -> Vec<u8> {
    let at = hay
        .windows(from.len())
        .position(|w| w == from)
        .expect("pattern present");
    [&hay[..at], to, &hay[at + from.len()..]].concat()
}

// ------------------------------------------------------------------ file-system shapes

#[cfg(unix)]
#[test]
fn symlink_loops_links_to_dot_and_repeated_files_are_read_once() {
    use std::os::unix::fs::symlink;
    let dir = tmp("links");
    let city = dir.join("city");
    std::fs::create_dir_all(city.join("sub")).unwrap();
    std::fs::write(city.join("a.gml"), building_gml("", "")).unwrap();
    std::fs::write(city.join("sub/b.GML"), building_gml("", "")).unwrap();
    symlink(&city, city.join("sub/loop")).unwrap(); // a loop back to the top
    symlink(".", city.join("here")).unwrap(); // a link to `.`
    symlink(city.join("a.gml"), city.join("sub/a_again.xml")).unwrap();
    symlink(city.join("missing.gml"), city.join("dangling.gml")).unwrap();
    let inputs = [city.clone(), city.join("a.gml"), city.join("sub")];
    let found = citymodel::collect_files(&inputs).unwrap();
    let names: Vec<String> = found
        .files
        .iter()
        .map(|f| f.strip_prefix(&dir).unwrap().display().to_string())
        .collect();
    assert_eq!(names, ["city/a.gml", "city/sub/b.GML"]);
    let w = found.warnings.join("\n");
    assert!(
        w.contains("city/here leads to") && w.contains("already searched"),
        "{w}"
    );
    assert!(w.contains("city/sub/loop leads to"), "{w}");
    assert!(w.contains("a_again.xml is the same file as"), "{w}");
    assert!(w.contains("dangling.gml cannot be read"), "{w}");
    assert!(w.contains("city/a.gml is the same file as"), "{w}");
    // The same file given twice doubles nothing.
    let twice = [city.join("a.gml"), city.join("a.gml")];
    assert_eq!(citymodel::collect_files(&twice).unwrap().files.len(), 1);
    // Missing inputs and folders without CityGML are errors naming the path.
    let e = citymodel::collect_files(&[dir.join("nope")]).unwrap_err();
    check_message(&e, "nope");
    std::fs::create_dir_all(dir.join("empty")).unwrap();
    let e = citymodel::collect_files(&[dir.join("empty")]).unwrap_err();
    assert!(e.to_string().contains("no city-model files"), "{e}");
}

/// semantics.json whose parents form a cycle would hang an ancestor walk: refused.
#[test]
fn hierarchy_tables_with_cycles_are_refused() {
    let row = |id: i32, parent: &str, building: i32| {
        format!(
            r#"{{"id":{id},"object_id":"E{id}","class":"Building","level":"feature","parent":{parent},"building":{building},"source":"a","lod":3,"attributes":{{}}}}"#
        )
    };
    let p = Path::new("semantics.json");
    let ok = format!(
        r#"{{"entities":[{},{}]}}"#,
        row(0, "null", 0),
        row(1, "0", 0)
    );
    assert_eq!(semantics::parse(p, &ok).unwrap().len(), 2);
    let cycle = format!(r#"{{"entities":[{},{}]}}"#, row(0, "1", 0), row(1, "0", 0));
    let e = semantics::parse(p, &cycle).unwrap_err();
    assert!(
        check_message(&e, "semantics.json").contains("E0 (id 0) names parent 1"),
        "{e}"
    );
    let self_loop = format!(r#"{{"entities":[{}]}}"#, row(0, "0", 0));
    assert!(semantics::parse(p, &self_loop).is_err());
    let wrong_root = format!(
        r#"{{"entities":[{},{}]}}"#,
        row(0, "null", 0),
        row(1, "0", 1)
    );
    assert!(semantics::parse(p, &wrong_root).is_err());
}

/// An image whose header declares a huge size is refused before OpenCV decodes it.
#[test]
fn images_declaring_huge_sizes_are_refused_before_decoding() {
    let dir = tmp("images");
    let small = dir.join("small.png");
    gs4city::imageio::write_png(&small, &ndarray::Array3::zeros((3, 5, 3))).unwrap();
    let bytes = std::fs::read(&small).unwrap();
    assert_eq!(gs4city::imageio::declared_size(&bytes), Some((5, 3)));
    assert_eq!(gs4city::imageio::read_rgb(&small).unwrap().dim(), (3, 5, 3));
    // PNG: signature + an IHDR chunk declaring 60000×60000 (no pixel data at all).
    let mut png = bytes[..16].to_vec();
    png.extend(60000u32.to_be_bytes());
    png.extend(60000u32.to_be_bytes());
    png.extend([8, 2, 0, 0, 0, 0, 0, 0, 0]);
    // JPEG: SOI, an APP0 segment, then SOF0 declaring 65535×65535.
    let mut jpg = vec![0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x04, 0x4A, 0x46];
    jpg.extend([0xFF, 0xC0, 0x00, 0x11, 0x08, 0xFF, 0xFF, 0xFF, 0xFF, 0x03]);
    for (name, data, size) in [
        ("huge.png", png, "60000×60000"),
        ("huge.jpg", jpg, "65535×65535"),
    ] {
        let p = dir.join(name);
        std::fs::write(&p, &data).unwrap();
        let e = gs4city::imageio::read_rgb(&p).unwrap_err();
        let msg = check_message(&e, name);
        assert!(msg.contains(size) && msg.contains("megapixels"), "{msg}");
    }
}

// ------------------------------------------------------------------ SAM

#[test]
fn sam_masks_with_impossible_sizes_are_refused_without_allocating() {
    let p = Path::new("m.json");
    for size in ["[1000000000, 1000000000]", "[18446744073709551615, 2]"] {
        let json = format!(
            r#"[{{"segmentation":{{"size":{size},"counts":[0]}},"area":0,"bbox":[0,0,0,0],"predicted_iou":1,"stability_score":1}}]"#
        );
        let e = sam::parse_sam_json(p, json.as_bytes(), None).unwrap_err();
        assert!(check_message(&e, "m.json").contains("mask 0: size"), "{e}");
    }
    let e = sam::parse_prompts_json(p, br#"{"dim":3,"prompts":{"door":[1,2]}}"#).unwrap_err();
    assert!(e.to_string().contains("\"door\": has 2 values"), "{e}");
}

// ------------------------------------------------------------------ fuzz findings

fn data_bad(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/bad")
        .join(rel)
}

/// Every input under `tests/data/bad/fuzz/<reader>/` (crashes, hangs and huge allocations
/// the fuzzers found, each fixed) goes through the fuzz target's own check: no panic, and a
/// refusal is one line. `pre-hardening-*` are inputs the same fuzz targets found in 3 minutes on
/// the readers before this branch (docs/robustness.md). Every folder there must be a reader of
/// the fuzz targets, and every file in it must have been replayed (a missing or misnamed folder
/// fails instead of replaying nothing). How long a replay takes is measured by the fuzz
/// targets' own time limit (`scripts/fuzz.sh`), not here.
#[test]
fn replayed_fuzz_inputs_give_clean_answers() {
    let root = data_bad("fuzz");
    // The expectation, from a plain walk of the folder: (reader, file) pairs.
    let mut on_disk = Vec::new();
    for e in std::fs::read_dir(&root).unwrap() {
        let dir = e.unwrap().path();
        let reader = dir.file_name().unwrap().to_string_lossy().into_owned();
        assert!(
            checks::READERS.contains(&reader.as_str()),
            "{}: no fuzz target reads `{reader}`",
            dir.display()
        );
        for f in std::fs::read_dir(&dir).unwrap() {
            on_disk.push((reader.clone(), f.unwrap().path()));
        }
    }
    on_disk.sort();
    assert!(!on_disk.is_empty(), "{}: no fuzz findings", root.display());
    let mut replayed = Vec::new();
    for reader in checks::READERS {
        let Ok(dir) = std::fs::read_dir(root.join(reader)) else {
            continue;
        };
        for f in dir.map(|e| e.unwrap().path()) {
            let data = std::fs::read(&f).unwrap();
            let answer = std::panic::catch_unwind(|| checks::run(reader, &data))
                .unwrap_or_else(|_| panic!("{reader}: {} panics", f.display()));
            if let Some(msg) = &answer {
                assert!(!msg.contains('\n'), "{}: {msg}", f.display());
            }
            // Inputs that crashed the readers before this branch are garbage: refused.
            let name = f.file_name().unwrap().to_string_lossy().into_owned();
            if name.starts_with("pre-hardening") {
                assert!(answer.is_some(), "{reader}: {name} was accepted");
            }
            replayed.push((reader.to_string(), f));
        }
    }
    replayed.sort();
    assert_eq!(replayed, on_disk, "findings not replayed");
}

/// The seeds the fuzzers start from are valid inputs of their readers.
#[test]
fn fuzz_seeds_are_accepted() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds");
    for reader in checks::READERS {
        for e in std::fs::read_dir(root.join(reader)).unwrap() {
            let f = e.unwrap().path();
            let name = f.file_name().unwrap().to_string_lossy().into_owned();
            let data = std::fs::read(&f).unwrap();
            let answer = checks::run(reader, &data);
            // Seeds that feed a second reader of the same target (points3D, prompts, pairs,
            // semantics, RLE strings) are refused by the first one.
            let secondary = ["points", "prompts", "pairs", "semantics", "counts"]
                .iter()
                .any(|s| name.starts_with(s));
            assert!(secondary || answer.is_none(), "{reader}/{name}: {answer:?}");
        }
    }
}

// ------------------------------------------------------------------ found by a bad-input sweep

/// A COLMAP binary model with bytes after its last record, an image name without a file stem,
/// or an image id used twice: one line naming the file and what is wrong.
#[test]
fn colmap_trailing_bytes_empty_names_and_repeated_ids_are_named() {
    let dir = tmp("colmap-sweep");
    let view = |id: u32, name: &str| gs4city::camera::View {
        image_id: id,
        camera_id: 1,
        name: name.into(),
        camera: Camera {
            intrinsics: Intrinsics {
                distortion: Distortion::None,
                ..good_camera().intrinsics
            },
            ..good_camera()
        },
    };
    let write = |views: &[gs4city::camera::View]| {
        let d = dir.join("m");
        let _ = std::fs::remove_dir_all(&d);
        colmap::write_model(&d, views, true).unwrap();
        d
    };
    let d = write(&[view(1, "a.png"), view(2, "b.png")]);
    assert_eq!(colmap::read_model(&d).unwrap().len(), 2);
    for file in ["cameras.bin", "images.bin"] {
        let d = write(&[view(1, "a.png")]);
        let p = d.join(file);
        let mut b = std::fs::read(&p).unwrap();
        b.extend([0u8; 24]);
        std::fs::write(&p, b).unwrap();
        let e = colmap::read_model(&d).unwrap_err();
        let msg = check_message(&e, file);
        assert!(msg.contains("24 bytes after the last"), "{msg}");
    }
    let d = write(&[view(1, "frames/")]);
    let msg = check_message(&colmap::read_model(&d).unwrap_err(), "images.bin");
    assert!(
        msg.contains("image 1") && msg.contains("no file stem"),
        "{msg}"
    );
    let d = write(&[view(1, "a.png"), view(1, "a.png")]);
    let msg = check_message(&colmap::read_model(&d).unwrap_err(), "images.bin");
    assert!(msg.contains("duplicate image id 1"), "{msg}");
}

/// SAM lists: scores out of range, polygon segmentations and a byte-order mark.
#[test]
fn sam_scores_polygons_and_a_bom_are_handled() {
    let dir = tmp("sam-sweep");
    let p = dir.join("v.json");
    let m = ndarray::Array2::from_elem((4, 5), true);
    // (predicted_iou, stability_score, what the error says; "" = read)
    for (iou, stab, why) in [
        (0.9, 0.95, ""),
        (1.02, 1.0, ""),
        (1e308, 0.9, "\"predicted_iou\" is 1e308, outside"),
        (0.9, 1.5, "\"stability_score\" is 1.5e0, outside"),
        // JSON has no NaN: it is written as null, which is not a number.
        (f64::NAN, 0.9, "expected f64"),
    ] {
        sam::write_sam_json(&p, &[sam::SamMask::from_mask(&m, iou, stab, vec![])]).unwrap();
        match sam::read_sam_json(&p) {
            Ok(_) => assert!(why.is_empty(), "{iou} {stab} was read"),
            Err(e) => {
                let msg = check_message(&e, "v.json");
                assert!(
                    !why.is_empty() && msg.contains("mask 0") && msg.contains(why),
                    "{msg}"
                );
            }
        }
    }
    sam::write_sam_json(&p, &[sam::SamMask::from_mask(&m, 0.9, 0.9, vec![])]).unwrap();
    let mut b = b"\xEF\xBB\xBF".to_vec();
    b.extend(std::fs::read(&p).unwrap());
    assert_eq!(sam::parse_sam_json(&p, &b, Some([4, 5])).unwrap().len(), 1);
    let poly = br#"[{"segmentation": [[0, 0, 4, 0, 4, 3]], "area": 6, "bbox": [0, 0, 4, 3],
        "predicted_iou": 0.9, "stability_score": 0.9, "point_coords": [[1, 1]], "crop_box": [0, 0, 5, 4]}]"#;
    let e = sam::parse_sam_json(&p, poly, None).unwrap_err();
    let msg = check_message(&e, "v.json");
    assert!(
        msg.contains("polygon list") && msg.contains("coco_rle"),
        "{msg}"
    );
}

/// Nothing to render — no views, no Gaussians, or none that can be drawn — is an error
/// before any file is written.
#[test]
fn a_render_with_nothing_to_draw_is_refused() {
    use gs4city::render::{self, PreparedScene};
    let views = vec![gs4city::camera::View {
        image_id: 1,
        camera_id: 1,
        name: "a.png".into(),
        camera: good_camera(),
    }];
    let g = |scale: f32, n: usize| splat::Gaussians {
        positions: vec![[0.0; 3]; n],
        normals: None,
        sh_degree: 0,
        f_dc: vec![[0.0; 3]; n],
        f_rest: Vec::new(),
        opacity: vec![2.0; n],
        scale: vec![[scale; 3]; n],
        rotation: vec![[1.0, 0.0, 0.0, 0.0]; n],
        extras: Vec::new(),
    };
    let ok = PreparedScene::new(&g(-2.0, 3)).unwrap();
    render::check_inputs(&ok, &views).unwrap();
    let e = render::check_inputs(&ok, &[]).unwrap_err().to_string();
    assert!(e.contains("no views to render"), "{e}");
    let empty = PreparedScene::new(&g(-2.0, 0)).unwrap();
    let e = render::check_inputs(&empty, &views)
        .unwrap_err()
        .to_string();
    assert!(e.contains("no Gaussians"), "{e}");
    let mut bad = g(-2.0, 3);
    bad.rotation = vec![[0.0; 4]; 3];
    let none = PreparedScene::new(&bad).unwrap();
    let e = render::check_inputs(&none, &views).unwrap_err().to_string();
    assert!(e.contains("none of the 3 Gaussians can be drawn"), "{e}");
    let dir = tmp("render-nothing");
    let out = dir.join("r");
    assert!(render::render_to_dir(&none, &views, &out, &Default::default()).is_err());
    assert!(!out.exists(), "a refused render leaves no folder");
}
