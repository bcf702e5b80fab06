//! The command line end to end, through the real `gs4city` binary: citymodel (with an
//! alignment that scales metres), raycast (τ scaled by it), render, lift; and bad arguments.
use std::path::{Path, PathBuf};
use std::process::Command;

use glam::DVec3;
use gs4city::camera::{Camera, Distortion, Intrinsics, Pose, View};
use gs4city::splat::{Gaussians, PlyEncoding, write_ply};
use gs4city::{colmap, npy};

fn gs4city(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(args)
        .output()
        .expect("run gs4city");
    (
        out.status.success(),
        format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
    )
}

fn tmp() -> PathBuf {
    let d = crate::common::temp_dir().join(format!("gs4city-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A wall (x 0..10 m, z 0..6 m at y = 0) with a window whose surface lies 0.3 m *behind* the
/// wall plane (recessed), georeferenced near UTM coordinates; the wall has no hole, so only the
/// part pass can see the window.
fn gml(dir: &Path) -> PathBuf {
    let (e, n) = (678_000.0, 5_403_000.0);
    let ring = |pts: &[(f64, f64, f64)]| {
        let mut v: Vec<String> = pts
            .iter()
            .map(|&(x, y, z)| format!("{} {} {}", e + x, n + y, 400.0 + z))
            .collect();
        v.push(v[0].clone());
        v.join(" ")
    };
    let wall = ring(&[
        (0.0, 0.0, 0.0),
        (10.0, 0.0, 0.0),
        (10.0, 0.0, 6.0),
        (0.0, 0.0, 6.0),
    ]);
    let win = ring(&[
        (4.0, 0.3, 2.0),
        (6.0, 0.3, 2.0),
        (6.0, 0.3, 4.0),
        (4.0, 0.3, 4.0),
    ]);
    let text = format!(
        r#"<?xml version="1.0"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:gml="http://www.opengis.net/gml">
<core:cityObjectMember><bldg:Building gml:id="B"><bldg:boundedBy><bldg:WallSurface gml:id="W">
<bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>{wall}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface>
<bldg:opening><bldg:Window gml:id="Win"><bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>{win}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface></bldg:Window></bldg:opening>
</bldg:WallSurface></bldg:boundedBy></bldg:Building></core:cityObjectMember></core:CityModel>
"#
    );
    let p = dir.join("wall.gml");
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn citymodel_raycast_render_lift_through_the_binary() {
    let dir = tmp();
    let d = |s: &str| dir.join(s).to_string_lossy().into_owned();
    let gml = gml(&dir);
    // Scene frame in half-metres: s = 2, origin at the wall corner.
    std::fs::write(
        dir.join("alignment.json"),
        r#"{"origin":[678000,5403000,400],"scale":2,"rotation":[[1,0,0],[0,1,0],[0,0,1]],"translation":[0,0,0]}"#,
    )
    .unwrap();
    let (ok, log) = gs4city(&[
        "citymodel",
        gml.to_str().unwrap(),
        "--align",
        &d("alignment.json"),
        "--out",
        &d("cm"),
    ]);
    assert!(ok, "{log}");
    // Cameras (scene units) looking at the window centre (10, 0, 6) from the front.
    let views: Vec<View> = (0..3)
        .map(|i| View {
            image_id: i + 1,
            camera_id: 1,
            name: format!("img{i}.png"),
            camera: Camera {
                intrinsics: Intrinsics {
                    width: 96,
                    height: 64,
                    fx: 80.0,
                    fy: 80.0,
                    cx: 48.0,
                    cy: 32.0,
                    distortion: Distortion::None,
                },
                pose: Pose::look_at(
                    DVec3::new(8.0 + 2.0 * i as f64, -30.0, 6.0),
                    DVec3::new(10.0, 0.0, 6.0),
                    DVec3::Z,
                )
                .unwrap(),
            },
        })
        .collect();
    colmap::write_model(&dir.join("sparse"), &views, false).unwrap();
    // τ = 0.5 m = 1.0 scene unit ≥ the 0.6-unit recess: the window is recovered.
    let (ok, log) = gs4city(&[
        "raycast",
        "--citymodel",
        &d("cm"),
        "--colmap",
        &d("sparse"),
        "--overlays",
        "--out",
        &d("rc"),
    ]);
    assert!(ok, "{log}");
    let (shape, ids) = npy::read::<i32>(&dir.join("rc/img1.ids.npy")).unwrap();
    assert_eq!(shape, vec![4, 64, 96]);
    let city = &ids[3 * 64 * 96..];
    let centre = city[32 * 96 + 48];
    let sem: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("cm/semantics.json")).unwrap()).unwrap();
    assert_eq!(
        sem["entities"][centre as usize]["class"], "Window",
        "centre pixel label {centre}"
    );
    assert!(dir.join("rc/img1.overlay.png").is_file() && dir.join("rc/summary.json").is_file());
    // τ = 0.2 m = 0.4 units < 0.6: rejected, the wall keeps the pixel.
    let (ok, log) = gs4city(&[
        "raycast",
        "--citymodel",
        &d("cm"),
        "--colmap",
        &d("sparse"),
        "--tau",
        "0.2",
        "--out",
        &d("rc2"),
    ]);
    assert!(ok, "{log}");
    let (_, ids2) = npy::read::<i32>(&dir.join("rc2/img1.ids.npy")).unwrap();
    assert_eq!(
        sem["entities"][ids2[3 * 64 * 96 + 32 * 96 + 48] as usize]["class"],
        "WallSurface"
    );

    // A semantic table that does not match the mesh (ids beyond its rows): refused before
    // raycasting, naming the mesh and the face.
    std::fs::create_dir_all(dir.join("cm_bad")).unwrap();
    for f in ["mesh.ply", "alignment.json", "summary.json"] {
        std::fs::copy(dir.join("cm").join(f), dir.join("cm_bad").join(f)).unwrap();
    }
    let mut short = sem.clone();
    short["entities"].as_array_mut().unwrap().truncate(1);
    std::fs::write(
        dir.join("cm_bad/semantics.json"),
        serde_json::to_vec(&short).unwrap(),
    )
    .unwrap();
    let (ok, log) = gs4city(&[
        "raycast",
        "--citymodel",
        &d("cm_bad"),
        "--colmap",
        &d("sparse"),
        "--out",
        &d("rc_bad"),
    ]);
    assert!(!ok && log.contains("mesh.ply"), "{log}");
    assert!(!dir.join("rc_bad/summary.json").exists());

    // A few Gaussians on the wall; render and lift through the binary.
    let mut g = Gaussians {
        sh_degree: 0,
        ..Default::default()
    };
    for i in 0..400 {
        let (x, z) = ((i % 20) as f32 + 0.5, (i / 20) as f32 * 0.6 + 0.3);
        g.positions.push([x, 0.0, z]);
        g.f_dc.push([0.5, 0.2, 0.1]);
        g.opacity.push(4.0);
        g.scale.push([(0.5f32).ln(), (0.01f32).ln(), (0.4f32).ln()]);
        g.rotation.push([1.0, 0.0, 0.0, 0.0]);
    }
    write_ply(&dir.join("scene.ply"), &g, PlyEncoding::BinaryLittleEndian).unwrap();
    let (ok, log) = gs4city(&[
        "render",
        "--ply",
        &d("scene.ply"),
        "--colmap",
        &d("sparse"),
        "--views",
        "img0,img2.png",
        "--out",
        &d("rd"),
    ]);
    assert!(ok, "{log}");
    assert!(
        !dir.join("rd/img1.png").exists(),
        "only the views asked for"
    );
    // img2 looks from (12, −30, 6) at (10, 0, 6): the centre ray meets the opaque wall plane
    // y = 0 at depth 30·cos(atan(2/30)) ≈ 29.93 along the axis … the expected depth there.
    let (shape, depth) = npy::read::<f32>(&dir.join("rd/img2.depth.npy")).unwrap();
    assert_eq!(shape, vec![64, 96]);
    let axis = (DVec3::new(10.0, 0.0, 6.0) - DVec3::new(12.0, -30.0, 6.0)).length();
    let z = depth[32 * 96 + 48] as f64;
    assert!(
        (z - axis).abs() < 0.05,
        "centre depth {z}, expected ≈ {axis}"
    );
    // Colour: f_dc (0.5, 0.2, 0.1) → 0.5 + C0·f_dc = (0.641, 0.556, 0.528) on an opaque wall.
    let img = gs4city::imageio::read_rgb(&dir.join("rd/img0.png")).unwrap();
    let px = img.slice(ndarray::s![32, 48, ..]).to_vec();
    for (c, want) in px.iter().zip([0.641f32, 0.556, 0.528]) {
        assert!((*c as f32 / 255.0 - want).abs() < 0.02, "{px:?}");
    }
    let (ok, log) = gs4city(&[
        "render",
        "--ply",
        &d("scene.ply"),
        "--colmap",
        &d("sparse"),
        "--cache",
        "--top-k",
        "8",
        "--out",
        &d("cache"),
    ]);
    assert!(ok, "{log}");
    let (ok, log) = gs4city(&[
        "lift",
        "--ply",
        &d("scene.ply"),
        "--colmap",
        &d("sparse"),
        "--cache",
        &d("cache"),
        "--raycast",
        &d("rc"),
        "--citymodel",
        &d("cm"),
        "--test-every",
        "3",
        "--out",
        &d("lift"),
    ]);
    assert!(ok, "{log}");
    // Test view img0 (every 3rd by name): Gaussians on the wall plane in front of the recessed
    // window took the window's label from the training views; the rest of the wall is wall.
    let (_, class) = npy::read::<i32>(&dir.join("lift/img0.class.npy")).unwrap();
    let cam = &views[0].camera;
    let pixel = |p: DVec3| {
        let uv = cam.project(cam.pose.world_to_camera(p)).unwrap();
        class[uv.y as usize * 96 + uv.x as usize]
    };
    assert_eq!(pixel(DVec3::new(10.0, 0.0, 6.0)), gs4city::classes::WINDOW);
    assert_eq!(pixel(DVec3::new(3.0, 0.0, 2.0)), gs4city::classes::WALL);
    assert_eq!(
        pixel(DVec3::new(10.0, 0.0, 14.0)),
        -1,
        "above the wall: nothing"
    );

    // Bad arguments: one clear error each, naming what is wrong.
    let (ok, log) = gs4city(&[
        "render",
        "--ply",
        &d("scene.ply"),
        "--colmap",
        &d("sparse"),
        "--views",
        "nope",
        "--out",
        &d("x"),
    ]);
    assert!(!ok && log.contains("nope"), "{log}");
    for (flag, name, bad) in [
        ("--t-stop", "t_stop", "1.5"),
        ("--t-stop", "t_stop", "NaN"),
        ("--epsilon", "epsilon", "1"),
        ("--top-k", "top_k", "3000"),
        ("--alpha-min", "alpha_min", "0.001"),
        ("--alpha-min", "alpha_min", "0.99"),
    ] {
        let (ok, log) = gs4city(&[
            "render",
            "--ply",
            &d("scene.ply"),
            "--colmap",
            &d("sparse"),
            "--cache",
            flag,
            bad,
            "--out",
            &d("x"),
        ]);
        assert!(
            !ok && log.contains(&format!("{name} "))
                && log.contains(bad)
                && log.lines().count() == 1,
            "{log}"
        );
        assert!(!dir.join("x").exists(), "nothing written for {flag} {bad}");
    }
    let (ok, log) = gs4city(&[
        "raycast",
        "--citymodel",
        &d("missing"),
        "--colmap",
        &d("sparse"),
        "--out",
        &d("x"),
    ]);
    assert!(!ok && log.contains("missing"), "{log}");
    let (ok, log) = gs4city(&["citymodel", &d("alignment.json"), "--out", &d("x")]);
    assert!(!ok && log.contains("alignment.json"), "{log}");
    std::fs::remove_dir_all(&dir).unwrap();
}
