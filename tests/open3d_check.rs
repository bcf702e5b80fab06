//! Cross-check of the global pass against Open3D's `RaycastingScene`
//! (`scripts/open3d_check.py`): primitive → feature ids must agree on ≥ 99.99 % of rays.
//! Skipped, with a message, where python3 cannot import open3d.

use std::path::Path;
use std::process::Command;

use crate::common::*;
use gs4city::mesh::TriMesh;
use gs4city::raycast::{RaycastOptions, TwoPassScene, pixel_ray, raycast_view};

/// Writes mesh + rays + gs4city's global-pass faces for `cams` into `dir`.
pub fn export(m: &TriMesh, cams: &[gs4city::camera::Camera], dir: &Path) -> usize {
    std::fs::create_dir_all(dir).unwrap();
    let scene = TwoPassScene::build(m).unwrap();
    let (mut rays, mut faces): (Vec<f32>, Vec<i32>) = (Vec::new(), Vec::new());
    for cam in cams {
        let v = raycast_view(&scene, cam, &RaycastOptions::default());
        for j in 0..v.height {
            for i in 0..v.width {
                let (o, d, _) = pixel_ray(cam, i, j).unwrap();
                rays.extend(o.iter().chain(&d));
                faces.push(v.face[j * v.width + i]);
            }
        }
    }
    let flat_v: Vec<f32> = m.vertices.iter().flatten().copied().collect();
    let flat_f: Vec<i32> = m.faces.iter().flatten().map(|&i| i as i32).collect();
    let feat: Vec<i32> = m.labels.iter().map(|l| l.feature).collect();
    gs4city::npy::write(&dir.join("vertices.npy"), &[m.vertices.len(), 3], &flat_v).unwrap();
    gs4city::npy::write(&dir.join("faces.npy"), &[m.faces.len(), 3], &flat_f).unwrap();
    gs4city::npy::write(&dir.join("feature.npy"), &[m.faces.len()], &feat).unwrap();
    gs4city::npy::write(&dir.join("rays.npy"), &[faces.len(), 6], &rays).unwrap();
    gs4city::npy::write(&dir.join("rust_face.npy"), &[faces.len()], &faces).unwrap();
    faces.len()
}

#[test]
fn global_pass_agrees_with_open3d() {
    if !python_can_import(
        "open3d_check::global_pass_agrees_with_open3d",
        &["open3d", "numpy"],
    ) {
        return;
    }
    let m = city_block(40, 4, 11);
    let cams: Vec<_> = (0..4)
        .map(|k| orbit_camera(160, 120, 130.0, k as f64 * 1.57 + 0.3, 130.0, 25.0))
        .collect();
    let dir = crate::common::temp_dir().join(format!("gs4city-o3d-{}", std::process::id()));
    let n = export(&m, &cams, &dir);
    let out = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/open3d_check.py"))
        .arg(&dir)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    eprintln!("{text}{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "open3d_check.py failed: {text}");
    let agreement: f64 = text
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .expect("agreement printed");
    assert!(agreement >= 0.9999, "agreement {agreement}");
    assert!(text.contains(&format!("of {n} rays")));
    let _ = std::fs::remove_dir_all(&dir);
}
