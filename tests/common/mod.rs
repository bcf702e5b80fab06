//! Shared fixtures of the raycast tests and bench: labelled quads/boxes, simple cameras,
//! and a seeded synthetic city block.
#![allow(dead_code)]
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};
use gs4city::camera::{Camera, Distortion, Intrinsics, Pose};
use gs4city::mesh::{FaceLabel, TriMesh};
use rand::{Rng, SeedableRng};

/// The folder every test writes under ([`gs4city::fsutil::test_temp_dir`]).
pub fn temp_dir() -> PathBuf {
    gs4city::fsutil::test_temp_dir()
}

pub fn label(feature: i32, surface: i32, part: i32) -> FaceLabel {
    FaceLabel {
        feature,
        surface,
        part,
    }
}

/// Adds the quad `a b c d` (two triangles) with `l`.
pub fn quad(m: &mut TriMesh, q: [[f64; 3]; 4], l: FaceLabel) {
    let base = m.vertices.len() as u32;
    m.vertices
        .extend(q.iter().map(|p| [p[0] as f32, p[1] as f32, p[2] as f32]));
    m.faces.push([base, base + 1, base + 2]);
    m.faces.push([base, base + 2, base + 3]);
    m.labels.extend([l, l]);
}

/// A quad in the plane `z = const` covering `[x0,x1]×[y0,y1]`.
pub fn zquad(m: &mut TriMesh, x: [f64; 2], y: [f64; 2], z: f64, l: FaceLabel) {
    quad(
        m,
        [
            [x[0], y[0], z],
            [x[1], y[0], z],
            [x[1], y[1], z],
            [x[0], y[1], z],
        ],
        l,
    );
}

/// An axis-aligned box with all faces labelled `l`.
pub fn aabox(m: &mut TriMesh, lo: [f64; 3], hi: [f64; 3], l: FaceLabel) {
    let c = |i: usize| {
        [
            if i & 1 == 0 { lo[0] } else { hi[0] },
            if i & 2 == 0 { lo[1] } else { hi[1] },
            if i & 4 == 0 { lo[2] } else { hi[2] },
        ]
    };
    for f in [
        [0, 1, 3, 2],
        [4, 6, 7, 5],
        [0, 4, 5, 1],
        [2, 3, 7, 6],
        [0, 2, 6, 4],
        [1, 5, 7, 3],
    ] {
        quad(m, f.map(c), l);
    }
}

/// A pinhole camera at the origin looking along world +z (x right, y down),
/// `w×h` pixels, focal `f`, principal point at the image centre.
pub fn axis_camera(w: u32, h: u32, f: f64) -> Camera {
    Camera {
        intrinsics: Intrinsics {
            width: w,
            height: h,
            fx: f,
            fy: f,
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
            distortion: Distortion::None,
        },
        pose: Pose {
            rotation: DMat3::IDENTITY,
            translation: DVec3::ZERO,
        },
    }
}

/// A seeded synthetic city block: ground plane and `n` buildings (boxes, feature `b`,
/// one surface per side) whose façades are split into `grid×grid` wall quads, with
/// coplanar window quads (part ids) on every other cell. Returns the mesh.
pub fn city_block(n: usize, grid: usize, seed: u64) -> TriMesh {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut m = TriMesh::default();
    zquad_ground(&mut m, 200.0);
    let mut next_id = 1_000_000;
    for b in 0..n {
        let cx: f64 = rng.random_range(-80.0..80.0);
        let cy: f64 = rng.random_range(-80.0..80.0);
        let sx: f64 = rng.random_range(4.0..12.0);
        let sy: f64 = rng.random_range(4.0..12.0);
        let h: f64 = rng.random_range(6.0..30.0);
        let (x0, x1, y0, y1) = (cx - sx / 2.0, cx + sx / 2.0, cy - sy / 2.0, cy + sy / 2.0);
        // Four façades: (start, end) along the ground.
        let sides = [
            ([x0, y0], [x1, y0]),
            ([x1, y0], [x1, y1]),
            ([x1, y1], [x0, y1]),
            ([x0, y1], [x0, y0]),
        ];
        for (s, (a, e)) in sides.iter().enumerate() {
            let surface = (b * 10 + s) as i32;
            for gi in 0..grid {
                for gj in 0..grid {
                    let (t0, t1) = (gi as f64 / grid as f64, (gi + 1) as f64 / grid as f64);
                    let (z0, z1) = (
                        h * gj as f64 / grid as f64,
                        h * (gj + 1) as f64 / grid as f64,
                    );
                    let p =
                        |t: f64, z: f64| [a[0] + (e[0] - a[0]) * t, a[1] + (e[1] - a[1]) * t, z];
                    quad(
                        &mut m,
                        [p(t0, z0), p(t1, z0), p(t1, z1), p(t0, z1)],
                        label(b as i32, surface, -1),
                    );
                    if (gi + gj) % 2 == 0 {
                        let (u0, u1) = (t0 + 0.25 * (t1 - t0), t1 - 0.25 * (t1 - t0));
                        let (w0, w1) = (z0 + 0.25 * (z1 - z0), z1 - 0.25 * (z1 - z0));
                        next_id += 1;
                        quad(
                            &mut m,
                            [p(u0, w0), p(u1, w0), p(u1, w1), p(u0, w1)],
                            label(b as i32, surface, next_id),
                        );
                    }
                }
            }
        }
        zquad(
            &mut m,
            [x0, x1],
            [y0, y1],
            h,
            label(b as i32, (b * 10 + 4) as i32, -1),
        );
    }
    m
}

fn zquad_ground(m: &mut TriMesh, r: f64) {
    zquad(m, [-r, r], [-r, r], 0.0, label(-1, -1, -1));
    // Ground is feature-less terrain: relabel as feature 9999 so hits are distinguishable.
    let n = m.labels.len();
    for l in &mut m.labels[n - 2..] {
        l.feature = 9999;
    }
}

/// A camera orbiting the block at `radius`, height `z`, looking at the centre.
pub fn orbit_camera(w: u32, h: u32, f: f64, angle: f64, radius: f64, z: f64) -> Camera {
    let eye = DVec3::new(radius * angle.cos(), radius * angle.sin(), z);
    let mut c = axis_camera(w, h, f);
    c.pose = Pose::look_at(eye, DVec3::new(0.0, 0.0, 5.0), DVec3::Z).expect("valid orbit pose");
    c
}

/// Every file below `dir` (relative path) → its bytes.
pub fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(dir).unwrap().display().to_string();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

/// Runs `python SCRIPT args --out out` (SCRIPT relative to the crate root), which must
/// succeed: the model generators and exporters of the segment and features tests.
pub fn python_script(python: &str, script: &str, args: &[&str], out: &Path) {
    let result = std::process::Command::new(python)
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join(script))
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(
        result.status.success(),
        "{script}: {}",
        String::from_utf8_lossy(&result.stderr)
    );
}

/// Whether `python3` can import every module of `modules` (the packages of a Python
/// cross-check named `test`). When it cannot, the cross-check must not pass silently: with `CI`
/// or `GS4CITY_REQUIRE_PY` set (`scripts/test.sh` sets the latter once `scripts/setup.sh` has
/// installed the packages) this panics; otherwise it prints `SKIPPED: <test>: <why>` and
/// appends that line to the file `$GS4CITY_SKIP_LOG`, which `scripts/test.sh` counts into its
/// totals line, and returns false (the caller returns).
pub fn python_can_import(test: &str, modules: &[&str]) -> bool {
    let code = if modules.is_empty() {
        "import sys".to_string()
    } else {
        format!("import {}", modules.join(", "))
    };
    let ok = std::process::Command::new("python3")
        .args(["-c", &code])
        .output()
        .is_ok_and(|o| o.status.success());
    if ok {
        return true;
    }
    skip(
        test,
        &format!(
            "python3 cannot `{code}` (scripts/setup.sh installs {})",
            if modules.is_empty() { "python3" } else { "it" }
        ),
    );
    false
}

/// Skips the cross-check `test` because of `why` (a package or model it needs is missing):
/// with `CI` or `GS4CITY_REQUIRE_PY` set this panics; otherwise it prints
/// `SKIPPED: <test>: <why>` and appends that line to `$GS4CITY_SKIP_LOG` (see
/// [`python_can_import`]). The caller then returns. `test` is the test's name as cargo prints
/// it (`module::function`): `scripts/test.sh` counts each skipped test once by that name.
pub fn skip(test: &str, why: &str) {
    assert!(
        std::env::var_os("CI").is_none() && std::env::var_os("GS4CITY_REQUIRE_PY").is_none(),
        "{test}: {why}; with CI or GS4CITY_REQUIRE_PY set this cross-check must run"
    );
    log_skip(test, why);
}

/// Skips `test` because of `why`, a property of the machine that no installation changes (the
/// user is not root): panics under `CI` (which must run it) but not under `GS4CITY_REQUIRE_PY`;
/// otherwise as [`skip`].
pub fn skip_unless_ci(test: &str, why: &str) {
    assert!(
        std::env::var_os("CI").is_none(),
        "{test}: {why}; with CI set this test must run"
    );
    log_skip(test, why);
}

/// The real user id of this process (`Uid:` of `/proc/self/status`; `None` where it cannot
/// be read).
pub fn uid() -> Option<u32> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines()
        .find_map(|l| l.strip_prefix("Uid:"))?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

fn log_skip(test: &str, why: &str) {
    let line = format!("SKIPPED: {test}: {why}");
    eprintln!("{line}");
    if let Some(log) = std::env::var_os("GS4CITY_SKIP_LOG") {
        use std::io::Write;
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log)
            .expect("GS4CITY_SKIP_LOG cannot be opened");
        writeln!(f, "{line}").expect("GS4CITY_SKIP_LOG cannot be written");
    }
}

pub mod wall;

/// A CityGML 2.0 document of one building `building` with one LoD3 wall surface whose one
/// polygon `polygon` has the exterior ring `ring` (points `x y z`, the closing one included).
pub fn one_wall_citygml(building: &str, polygon: &str, ring: &[[f64; 3]]) -> String {
    let pos: Vec<String> = ring
        .iter()
        .map(|[x, y, z]| format!("{x} {y} {z}"))
        .collect();
    format!(
        r#"<?xml version="1.0" encoding="utf-8"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:gml="http://www.opengis.net/gml">
<core:cityObjectMember><bldg:Building gml:id="{building}"><bldg:boundedBy><bldg:WallSurface gml:id="{building}_WALL"><bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon gml:id="{polygon}"><gml:exterior><gml:LinearRing><gml:posList srsDimension="3">{}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface></bldg:WallSurface></bldg:boundedBy></bldg:Building></core:cityObjectMember>
</core:CityModel>
"#,
        pos.join(" ")
    )
}
