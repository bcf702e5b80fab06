//! The COLMAP binary reader against files written by an independent writer
//! (`scripts/colmap_bin_writer.py`: Python's struct module following COLMAP's documented
//! layout, every supported camera model, unsorted and sparse ids, image names with folders,
//! spaces and non-ASCII letters, 2D points and tracks, unnormalised quaternions): every value
//! read equals the value written, and each pose's rotation equals the one NumPy computed from the
//! quaternion.
use std::path::Path;
use std::process::Command;

use crate::common::python_can_import;
use gs4city::camera::Distortion;
use gs4city::colmap;

#[test]
fn binary_models_from_an_independent_writer_read_back_exactly() {
    if !python_can_import(
        "colmap::binary_models_from_an_independent_writer_read_back_exactly",
        &["numpy"],
    ) {
        return;
    }
    let dir = crate::common::temp_dir().join(format!("gs4city-colmap-bin-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/colmap_bin_writer.py"))
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let want: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("expected.json")).unwrap()).unwrap();
    let sparse = dir.join("sparse");
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    // The values travel as float64 both ways; serde_json's float parsing may be one ulp off
    // (it is not always correctly rounded), so "equal" is within 2 ulp.
    let same = |a: f64, b: f64| (a - b).abs() <= 2.0 * f64::EPSILON * b.abs();
    let all_same =
        |a: &[f64], b: &[f64]| a.len() == b.len() && a.iter().zip(b).all(|(x, y)| same(*x, *y));

    // Cameras, in file order.
    let cams = colmap::read_cameras(&sparse).unwrap();
    let wc = want["cameras"].as_array().unwrap();
    assert_eq!(cams.len(), wc.len());
    assert_eq!(cams.len(), 6, "every model gs4city reads");
    for (c, w) in cams.iter().zip(wc) {
        let p: Vec<f64> = w["params"].as_array().unwrap().iter().map(f).collect();
        let names: Vec<&str> = w["param_names"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        let param = |n: &str| p[names.iter().position(|&m| m == n).unwrap()];
        assert_eq!(u64::from(c.camera_id), w["camera_id"].as_u64().unwrap());
        assert_eq!(c.model.name(), w["model"].as_str().unwrap());
        assert_eq!(i64::from(c.model.id()), w["model_id"].as_i64().unwrap());
        let i = &c.intrinsics;
        assert_eq!(u64::from(i.width), w["width"].as_u64().unwrap());
        assert_eq!(u64::from(i.height), w["height"].as_u64().unwrap());
        let (fx, fy) = if names[0] == "f" {
            (param("f"), param("f"))
        } else {
            (param("fx"), param("fy"))
        };
        assert!(
            all_same(
                &[i.fx, i.fy, i.cx, i.cy],
                &[fx, fy, param("cx"), param("cy")]
            ),
            "{}: {i:?} vs {p:?}",
            c.model.name()
        );
        let d = match w["model"].as_str().unwrap() {
            "SIMPLE_PINHOLE" | "PINHOLE" => Distortion::None,
            "SIMPLE_RADIAL" => Distortion::Radial {
                k1: param("k"),
                k2: 0.0,
            },
            "RADIAL" => Distortion::Radial {
                k1: param("k1"),
                k2: param("k2"),
            },
            "OPENCV" => Distortion::OpenCv {
                k1: param("k1"),
                k2: param("k2"),
                p1: param("p1"),
                p2: param("p2"),
            },
            "FULL_OPENCV" => Distortion::FullOpenCv {
                k: ["k1", "k2", "k3", "k4", "k5", "k6"].map(param),
                p1: param("p1"),
                p2: param("p2"),
            },
            m => panic!("unexpected model {m}"),
        };
        let coefficients = |d: &Distortion| match *d {
            Distortion::None => vec![],
            Distortion::Radial { k1, k2 } => vec![k1, k2],
            Distortion::OpenCv { k1, k2, p1, p2 } => vec![k1, k2, p1, p2],
            Distortion::FullOpenCv { k, p1, p2 } => [k.to_vec(), vec![p1, p2]].concat(),
        };
        assert_eq!(
            std::mem::discriminant(&i.distortion),
            std::mem::discriminant(&d),
            "{}",
            c.model.name()
        );
        assert!(
            all_same(&coefficients(&i.distortion), &coefficients(&d)),
            "{}: {:?} vs {d:?}",
            c.model.name(),
            i.distortion
        );
    }

    // Images: sorted by name; camera resolved; pose from the quaternion.
    let views = colmap::read_model(&sparse).unwrap();
    let mut wi: Vec<&serde_json::Value> = want["images"].as_array().unwrap().iter().collect();
    wi.sort_by_key(|w| w["name"].as_str().unwrap().to_string());
    assert_eq!(views.len(), wi.len());
    for (v, w) in views.iter().zip(wi) {
        assert_eq!(v.name, w["name"].as_str().unwrap());
        assert_eq!(u64::from(v.image_id), w["image_id"].as_u64().unwrap());
        assert_eq!(u64::from(v.camera_id), w["camera_id"].as_u64().unwrap());
        let cam = cams.iter().find(|c| c.camera_id == v.camera_id).unwrap();
        assert_eq!(v.camera.intrinsics, cam.intrinsics);
        let t: Vec<f64> = w["tvec"].as_array().unwrap().iter().map(f).collect();
        assert!(
            all_same(&v.camera.pose.translation.to_array(), &t),
            "{}",
            v.name
        );
        let r = &v.camera.pose.rotation;
        for (row, wr) in w["rotation"].as_array().unwrap().iter().enumerate() {
            for (col, x) in wr.as_array().unwrap().iter().enumerate() {
                let got = r.col(col)[row];
                assert!(
                    (got - f(x)).abs() < 1e-12,
                    "{}: R[{row}][{col}] {got} vs NumPy {}",
                    v.name,
                    f(x)
                );
            }
        }
    }

    // Points, in file order, tracks skipped.
    let pts = colmap::read_points3d(&sparse).unwrap();
    let wp = want["points"].as_array().unwrap();
    assert_eq!(pts.len(), wp.len());
    for (p, w) in pts.iter().zip(wp) {
        assert_eq!(p.id, w["id"].as_u64().unwrap());
        let xyz: Vec<f64> = w["xyz"].as_array().unwrap().iter().map(f).collect();
        assert!(all_same(&p.xyz, &xyz), "point {}", p.id);
        let rgb: Vec<u8> = w["rgb"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c.as_u64().unwrap() as u8)
            .collect();
        assert_eq!(p.rgb.to_vec(), rgb);
        assert!(same(p.error, f(&w["error"])), "point {}", p.id);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
