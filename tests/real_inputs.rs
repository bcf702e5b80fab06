//! Real inputs, not simulated (`../shared/data/real/`, SOURCES.md there): a real COLMAP 3.8
//! model of 29 real photos of a street in Lund with GPS in their EXIF, a real trained
//! semantic segmentation network (ESPNet, Cityscapes; the repository's `models/espnet/`), and
//! two real captured splat scenes (`.splat`, CC-BY-4.0, Marcel Padilla). Each is checked
//! against an independent reader or reference: pycolmap, onnxruntime + NumPy
//! (`scripts/semantic_reference.py`), splat-transform, the NumPy rasterizer
//! (`scripts/ref_raster.py`).
use std::path::{Path, PathBuf};
use std::process::Command;

use glam::{DMat3, DQuat, DVec3};
use gs4city::camera::{Camera, Distortion, Intrinsics, Pose};
use gs4city::splat::{Gaussians, ReadOptions, SplatFormat, read_ply};

use crate::common::{python_can_import, skip};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The real data, or `None` after [`skip`].
fn real(test: &str) -> Option<PathBuf> {
    let p = repo().join("../shared/data/real");
    if p.join("SOURCES.md").is_file() {
        return Some(p);
    }
    skip(test, &format!("{} is missing", p.display()));
    None
}

fn scratch(name: &str) -> PathBuf {
    let d = gs4city::fsutil::test_temp_dir()
        .join(format!("gs4city-real-{}", std::process::id()))
        .join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn gs4city(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(args)
        .output()
        .unwrap()
}

fn python(code: &str, args: &[&str]) -> String {
    let o = Command::new("python3")
        .arg("-c")
        .arg(code)
        .args(args)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8(o.stdout).unwrap()
}

// ---------------------------------------------------------------- COLMAP

/// gs4city's COLMAP reader on the real Lund model gives what pycolmap reads: the camera's
/// model and parameters, every image's name, camera and pose, every point's position, colour
/// and error.
#[test]
fn colmap_reader_on_lund_matches_pycolmap() {
    // pycolmap's numbers travel as Python's shortest round-trip strings, parsed exactly here
    let num = |v: &serde_json::Value| -> f64 { v.as_str().unwrap().parse().unwrap() };
    const TEST: &str = "real_inputs::colmap_reader_on_lund_matches_pycolmap";
    let Some(real) = real(TEST) else { return };
    if !python_can_import(TEST, &["pycolmap"]) {
        return;
    }
    let sparse = real.join("lund/sparse/0");
    let code = r#"
import json, sys, pycolmap
r = pycolmap.Reconstruction(sys.argv[1])
f = lambda v: repr(float(v))
cams = [{"id": i, "model": c.model.name, "w": c.width, "h": c.height, "params": [f(v) for v in c.params]}
        for i, c in r.cameras.items()]
ims = []
for i, im in r.images.items():
    p = im.cam_from_world()
    x, y, z, w = p.rotation.quat
    ims.append({"id": i, "camera": im.camera_id, "name": im.name, "q": [f(w), f(x), f(y), f(z)],
                "t": [f(v) for v in p.translation]})
pts = [{"id": i, "xyz": [f(v) for v in p.xyz], "rgb": list(map(int, p.color)), "error": f(p.error)}
       for i, p in r.points3D.items()]
print(json.dumps({"cameras": cams, "images": ims, "points": pts}))
"#;
    let py: serde_json::Value =
        serde_json::from_str(&python(code, &[sparse.to_str().unwrap()])).unwrap();
    let cams = gs4city::colmap::read_cameras(&sparse).unwrap();
    let pc = py["cameras"].as_array().unwrap();
    assert_eq!(cams.len(), pc.len());
    for c in &cams {
        let p = pc
            .iter()
            .find(|p| p["id"].as_u64() == Some(u64::from(c.camera_id)))
            .unwrap();
        assert_eq!(c.model.name(), p["model"].as_str().unwrap());
        let k = &c.intrinsics;
        assert_eq!((k.width, k.height), (1024, 768));
        let params: Vec<f64> = p["params"].as_array().unwrap().iter().map(num).collect();
        // SIMPLE_RADIAL: f, cx, cy, k
        assert_eq!(params.len(), 4);
        assert_eq!(
            (k.fx, k.fy, k.cx, k.cy),
            (params[0], params[0], params[1], params[2])
        );
        assert_eq!(
            k.distortion,
            Distortion::Radial {
                k1: params[3],
                k2: 0.0
            }
        );
    }
    let views = gs4city::colmap::read_model(&sparse).unwrap();
    let pi = py["images"].as_array().unwrap();
    assert_eq!((views.len(), pi.len()), (29, 29));
    for v in &views {
        let p = pi
            .iter()
            .find(|p| p["id"].as_u64() == Some(u64::from(v.image_id)))
            .unwrap();
        assert_eq!(v.name, p["name"].as_str().unwrap());
        assert_eq!(u64::from(v.camera_id), p["camera"].as_u64().unwrap());
        let q: Vec<f64> = p["q"].as_array().unwrap().iter().map(num).collect();
        let r = DMat3::from_quat(DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize());
        assert!(
            (v.camera.pose.rotation - r).abs_diff_eq(DMat3::ZERO, 1e-12),
            "{}",
            v.name
        );
        let t = &p["t"];
        let t = DVec3::new(num(&t[0]), num(&t[1]), num(&t[2]));
        assert_eq!(v.camera.pose.translation, t, "{}", v.name);
    }
    let points = gs4city::colmap::read_points3d(&sparse).unwrap();
    let pp = py["points"].as_array().unwrap();
    assert_eq!((points.len(), pp.len()), (1715, 1715));
    let by_id: std::collections::HashMap<u64, &serde_json::Value> =
        pp.iter().map(|p| (p["id"].as_u64().unwrap(), p)).collect();
    for p in &points {
        let q = by_id[&p.id];
        for k in 0..3 {
            assert_eq!(p.xyz[k], num(&q["xyz"][k]));
            assert_eq!(u64::from(p.rgb[k]), q["rgb"][k].as_u64().unwrap());
        }
        assert_eq!(p.error, num(&q["error"]));
    }
}

// ---------------------------------------------------------------- splat formats

/// The project-local splat-transform, or `None` after [`skip`].
fn splat_transform(test: &str) -> Option<PathBuf> {
    let p = repo().join("tools/js/node_modules/.bin/splat-transform");
    if p.is_file() {
        return Some(p);
    }
    skip(
        test,
        "tools/js/node_modules/.bin/splat-transform is missing (scripts/setup.sh runs npm ci in tools/js)",
    );
    None
}

fn run_ok(cmd: &mut Command) {
    let o = cmd.output().unwrap();
    assert!(
        o.status.success(),
        "{cmd:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

fn convert(st: &Path, from: &Path, to: &Path, extra: &[&str]) {
    run_ok(
        Command::new(st)
            .args(["-q", "-w"])
            .args(extra)
            .arg(from)
            .arg(to),
    );
}

/// Any splat file, every Gaussian kept in place (splat-transform writes the logit of a byte
/// opacity 0 or 255 as ∓∞, which the pipeline's policy keeps and hides).
fn read(p: &Path) -> Gaussians {
    read_ply(p, &ReadOptions::KEEP)
        .unwrap_or_else(|e| panic!("{e}"))
        .0
}

fn unit(q: [f32; 4]) -> [f64; 4] {
    let n = q.iter().map(|v| f64::from(*v).powi(2)).sum::<f64>().sqrt();
    q.map(|v| f64::from(v) / n)
}

/// The largest difference of each field between two readings of the same Gaussians (rotation:
/// the angle between the unit quaternions, degrees; opacity: after the sigmoid).
#[derive(Debug, Default)]
struct Diff {
    position: f64,
    log_scale: f64,
    dc: f64,
    opacity: f64,
    rotation_deg: f64,
    rest: f64,
}

fn diff(a: &Gaussians, b: &Gaussians) -> Diff {
    assert_eq!(a.len(), b.len());
    assert_eq!(a.sh_degree, b.sh_degree);
    let mut d = Diff::default();
    let m = |x: &mut f64, y: f64| *x = x.max(y);
    for i in 0..a.len() {
        for k in 0..3 {
            m(
                &mut d.position,
                f64::from((a.positions[i][k] - b.positions[i][k]).abs()),
            );
            m(
                &mut d.log_scale,
                f64::from((a.scale[i][k] - b.scale[i][k]).abs()),
            );
            m(&mut d.dc, f64::from((a.f_dc[i][k] - b.f_dc[i][k]).abs()));
        }
        m(
            &mut d.opacity,
            f64::from((a.activated_opacity(i) - b.activated_opacity(i)).abs()),
        );
        let (p, q) = (unit(a.rotation[i]), unit(b.rotation[i]));
        let dot = p
            .iter()
            .zip(&q)
            .map(|(x, y)| x * y)
            .sum::<f64>()
            .abs()
            .min(1.0);
        m(&mut d.rotation_deg, 2.0 * dot.acos().to_degrees());
    }
    for (x, y) in a.f_rest.iter().zip(&b.f_rest) {
        m(&mut d.rest, f64::from((x - y).abs()));
    }
    d
}

/// Both real captures (`.splat`) read into the Gaussians splat-transform reads from them (its
/// PLY conversion), and the compressed PLY, SPZ version 3 and SPZ version 2 files made from
/// them by splat-transform (and its SPZ library) read into the Gaussians splat-transform
/// decodes from those files, and into the original ones within each format's quantisation.
#[test]
fn real_captures_read_alike_in_every_format() {
    const TEST: &str = "real_inputs::real_captures_read_alike_in_every_format";
    let Some(real) = real(TEST) else { return };
    let Some(st) = splat_transform(TEST) else {
        return;
    };
    let dir = scratch("formats");
    for cap in ["plant", "tarot_cards"] {
        let src = real.join(format!("splats/{cap}.splat"));
        let (ours, report) = read_ply(&src, &ReadOptions::default()).unwrap();
        assert_eq!(report.format, SplatFormat::Splat);
        let n = std::fs::metadata(&src).unwrap().len() as usize / 32;
        assert_eq!(ours.len(), n);
        assert_eq!(gs4city::splat::read_count(&src).unwrap(), n);
        let f = |ext: &str| dir.join(format!("{cap}.{ext}"));
        convert(&st, &src, &f("ply"), &[]);
        convert(&st, &src, &f("compressed.ply"), &[]);
        convert(&st, &src, &f("v3.spz"), &["--spz-version", "3"]);
        run_ok(
            Command::new("node")
                .arg(repo().join("tools/js/spz_version.mjs"))
                .arg(f("v3.spz"))
                .arg(f("v2.spz"))
                .arg("2"),
        );
        for (from, to) in [
            ("compressed.ply", "cdec.ply"),
            ("v3.spz", "v3dec.ply"),
            ("v2.spz", "v2dec.ply"),
        ] {
            convert(&st, &f(from), &f(to), &[]);
        }
        // .splat: the same arithmetic as splat-transform's reader, but for the rotation bytes
        // (antimatter15's (b − 128)/128 here, b/127.5 − 1 there: ≤ 0.9° between the two)
        let d = diff(&ours, &read(&f("ply")));
        eprintln!("{cap} .splat vs splat-transform's PLY: {d:?}");
        assert_eq!(d.position, 0.0);
        assert!(
            d.log_scale <= 1e-6 && d.dc <= 1e-5 && d.opacity <= 1e-6,
            "{d:?}"
        );
        assert!(d.rotation_deg <= 1.0, "{d:?}");
        for (file, dec, format) in [
            ("compressed.ply", "cdec.ply", SplatFormat::CompressedPly),
            ("v3.spz", "v3dec.ply", SplatFormat::Spz),
            ("v2.spz", "v2dec.ply", SplatFormat::Spz),
        ] {
            let (g, r) = read_ply(&f(file), &ReadOptions::default()).unwrap();
            assert_eq!((r.format, g.len()), (format, n), "{file}");
            assert_eq!(gs4city::splat::read_count(&f(file)).unwrap(), n);
            // splat-transform's own decoding of the same file
            let d = diff(&g, &read(&f(dec)));
            eprintln!("{cap} {file} vs splat-transform's decoding: {d:?}");
            assert!(d.position <= 1e-5 * 50.0, "{file}: {d:?}");
            assert!(
                d.log_scale <= 1e-5 && d.dc <= 1e-4 && d.opacity <= 1e-5,
                "{file}: {d:?}"
            );
            assert!(d.rotation_deg <= 0.05, "{file}: {d:?}");
        }
        // SPZ keeps the order: within its quantisation of the Gaussians it was made from,
        // splat-transform's reading of the .splat (positions 12 fractional bits; log scales
        // 1/16; colours 1/255 of 1/0.15; byte opacities; version 3 rotations 9 bits, version 2
        // 8 bits per component of x, y, z with w derived: when w is near 0 the derived w
        // carries the error of |xyz| ≈ 1, up to ≈ 12° on these captures, the reason version 3
        // stores the smallest three)
        let source = read(&f("ply"));
        for (file, rot) in [("v3.spz", 0.3), ("v2.spz", 15.0)] {
            let d = diff(&read(&f(file)), &source);
            eprintln!("{cap} {file} vs the Gaussians it was made from: {d:?}");
            assert!(d.position <= 0.5 / 4096.0 + 1e-5, "{file}: {d:?}");
            assert!(d.log_scale <= 0.5 / 16.0 + 1e-4, "{file}: {d:?}");
            assert!(d.dc <= 0.5 / 255.0 / 0.15 + 1e-4, "{file}: {d:?}");
            assert!(d.opacity <= 0.5 / 255.0 + 1e-4, "{file}: {d:?}");
            assert!(d.rotation_deg <= rot, "{file}: {d:?}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// SH bands through SPZ and the compressed PLY: an INRIA PLY of degree 3 (seeded random
/// values) made into both by splat-transform reads back within the quantisation (SPZ: 5 bits
/// for band 1, 4 for bands 2–3; compressed PLY: 8 bits over ±4), in the PLY's axes (the SPZ
/// reader's turn from right-up-back negates the odd SH terms: a wrong sign is an error of
/// twice the value).
#[test]
fn sh_bands_survive_spz_and_compressed_ply() {
    const TEST: &str = "real_inputs::sh_bands_survive_spz_and_compressed_ply";
    let Some(st) = splat_transform(TEST) else {
        return;
    };
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(59);
    let n = 300;
    let mut g = Gaussians {
        sh_degree: 3,
        ..Default::default()
    };
    for _ in 0..n {
        g.positions
            .push([0, 1, 2].map(|_| rng.random_range(-3.0f32..3.0)));
        g.f_dc
            .push([0, 1, 2].map(|_| rng.random_range(-1.5f32..1.5)));
        g.f_rest
            .extend((0..45).map(|_| rng.random_range(-0.9f32..0.9)));
        g.opacity.push(rng.random_range(-4.0f32..4.0));
        g.scale
            .push([0, 1, 2].map(|_| rng.random_range(-5.0f32..0.0)));
        g.rotation
            .push([0, 1, 2, 3].map(|_| rng.random_range(-1.0f32..1.0)));
    }
    let dir = scratch("sh");
    let src = dir.join("sh3.ply");
    gs4city::splat::write_ply(&src, &g, gs4city::splat::PlyEncoding::BinaryLittleEndian).unwrap();
    let f = |s: &str| dir.join(s);
    convert(&st, &src, &f("sh3.spz"), &["--spz-version", "3"]);
    convert(&st, &src, &f("sh3.compressed.ply"), &[]);
    convert(&st, &f("sh3.compressed.ply"), &f("cdec.ply"), &[]);
    let spz = read(&f("sh3.spz"));
    let d = diff(&spz, &g);
    eprintln!("degree-3 SPZ vs the original: {d:?}");
    // band 1: buckets of 8/128; bands 2–3: 16/128 (half a bucket and the rounding to 1/128)
    let k = 15;
    for i in 0..n {
        for c in 0..3 {
            for j in 0..k {
                let (a, b) = (spz.f_rest[i * 45 + c * k + j], g.f_rest[i * 45 + c * k + j]);
                let tol = if j < 3 { 4.5 / 128.0 } else { 8.5 / 128.0 };
                assert!(
                    (a - b).abs() <= tol,
                    "Gaussian {i} channel {c} coefficient {j}: {a} vs {b}"
                );
            }
        }
    }
    assert!(
        d.position <= 0.5 / 4096.0 + 1e-6 && d.rotation_deg <= 0.3,
        "{d:?}"
    );
    // the compressed PLY: splat-transform reorders into chunks; its own decoding is the
    // reference, and every band is read (8 bits over ±4: 1/32 per step)
    let c = read(&f("sh3.compressed.ply"));
    let d = diff(&c, &read(&f("cdec.ply")));
    eprintln!("degree-3 compressed PLY vs splat-transform's decoding: {d:?}");
    assert_eq!(c.sh_degree, 3);
    assert!(
        d.rest <= 1e-6 && d.dc <= 1e-4 && d.rotation_deg <= 0.05,
        "{d:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A bad file of each format is refused in one line naming the file and the record or part.
#[test]
fn damaged_splat_files_are_named() {
    let dir = scratch("bad");
    let one = |name: &str, bytes: &[u8]| -> String {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        let e = read_ply(&p, &ReadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains(name), "{e}");
        assert!(!e.contains('\n'), "{e}");
        e
    };
    // a .splat file cut inside its third record
    let mut rec = Vec::new();
    for v in [1.0f32, 2.0, 3.0, 0.1, 0.1, 0.1] {
        rec.extend_from_slice(&v.to_le_bytes());
    }
    rec.extend_from_slice(&[10, 20, 30, 255, 255, 128, 128, 128]);
    let mut cut = rec.repeat(2);
    cut.extend_from_slice(&rec[..20]);
    assert!(one("cut.splat", &cut).contains("record 2"));
    // a NaN position in record 1
    let mut nan = rec.repeat(3);
    nan[32..36].copy_from_slice(&f32::NAN.to_le_bytes());
    let e = one("nan.splat", &nan);
    assert!(e.contains("vertex 1") && e.contains("`x`"), "{e}");
    // not gzip, not a PLY
    assert!(one("junk.spz", b"\x1f\x8bjunk").contains("SPZ"));
    // a compressed PLY whose chunk count does not fit its splats
    let mut head = String::from("ply\nformat binary_little_endian 1.0\nelement chunk 2\n");
    for p in [
        "min_x",
        "min_y",
        "min_z",
        "max_x",
        "max_y",
        "max_z",
        "min_scale_x",
        "min_scale_y",
        "min_scale_z",
        "max_scale_x",
        "max_scale_y",
        "max_scale_z",
    ] {
        head.push_str(&format!("property float {p}\n"));
    }
    head.push_str("element vertex 3\n");
    for p in [
        "packed_position",
        "packed_rotation",
        "packed_scale",
        "packed_color",
    ] {
        head.push_str(&format!("property uint {p}\n"));
    }
    head.push_str("end_header\n");
    let mut bytes = head.into_bytes();
    bytes.extend(vec![0u8; 2 * 12 * 4 + 3 * 16]);
    assert!(one("bad.compressed.ply", &bytes).contains("2 chunks for 3 splats"));
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------- renders

/// A camera at `eye` looking at `target` (world up −y, as COLMAP captures often are).
fn look_at(eye: DVec3, target: DVec3, w: u32, h: u32, f: f64) -> Camera {
    let z = (target - eye).normalize();
    let x = DVec3::Y.cross(z).normalize();
    let y = z.cross(x);
    let r = DMat3::from_cols(x, y, z).transpose();
    Camera {
        intrinsics: Intrinsics {
            width: w,
            height: h,
            fx: f,
            fy: f,
            cx: f64::from(w) / 2.0,
            cy: f64::from(h) / 2.0,
            distortion: Distortion::None,
        },
        pose: Pose {
            rotation: r,
            translation: -(r * eye),
        },
    }
}

/// Virtual cameras around a capture: at 1.2 and 1.6 times the Gaussians' robust radius from
/// their median centre, from two sides.
fn orbit(g: &Gaussians, w: u32, h: u32) -> Vec<(String, Camera)> {
    let med = |k: usize| {
        let mut v: Vec<f64> = g.positions.iter().map(|p| f64::from(p[k])).collect();
        v.sort_by(f64::total_cmp);
        (v[v.len() / 2], v[v.len() / 10], v[v.len() * 9 / 10])
    };
    let (cx, x0, x1) = med(0);
    let (cy, y0, y1) = med(1);
    let (cz, z0, z1) = med(2);
    let c = DVec3::new(cx, cy, cz);
    let r = DVec3::new(x1 - x0, y1 - y0, z1 - z0).length() * 0.5;
    vec![
        (
            "front".into(),
            look_at(
                c + DVec3::new(0.3, -0.4, -1.0).normalize() * 1.6 * r,
                c,
                w,
                h,
                0.9 * f64::from(w),
            ),
        ),
        (
            "side".into(),
            look_at(
                c + DVec3::new(1.0, -0.2, 0.4).normalize() * 1.2 * r,
                c,
                w,
                h,
                0.7 * f64::from(w),
            ),
        ),
    ]
}

/// CPU renders of both real captures from virtual cameras agree with the independent NumPy
/// rasterizer (`scripts/ref_raster.py`, the INRIA rule in float64) on the same Gaussians
/// (written as an INRIA PLY): alpha within 2·10⁻⁴ at every pixel, colour within 10⁻³ (mean
/// within 10⁻⁵).
#[test]
fn real_captures_render_as_the_numpy_reference() {
    const TEST: &str = "real_inputs::real_captures_render_as_the_numpy_reference";
    let Some(real) = real(TEST) else { return };
    if !python_can_import(TEST, &["numpy"]) {
        return;
    }
    use gs4city::render::{PreparedScene, RenderOptions, render_view};
    let dir = scratch("render");
    let (w, h) = (40u32, 30u32);
    for cap in ["plant", "tarot_cards"] {
        let g = read(&real.join(format!("splats/{cap}.splat")));
        let ply = dir.join(format!("{cap}.ply"));
        gs4city::splat::write_ply(&ply, &g, gs4city::splat::PlyEncoding::BinaryLittleEndian)
            .unwrap();
        let cams = orbit(&g, w, h);
        let json: Vec<serde_json::Value> = cams
            .iter()
            .map(|(name, c)| {
                let k = &c.intrinsics;
                let r = c.pose.rotation.transpose().to_cols_array_2d();
                serde_json::json!({
                    "name": format!("{cap}_{name}"), "width": k.width, "height": k.height,
                    "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
                    "rotation": r, "translation": c.pose.translation.to_array(),
                })
            })
            .collect();
        let cj = dir.join(format!("{cap}.cameras.json"));
        std::fs::write(&cj, serde_json::to_string(&json).unwrap()).unwrap();
        let o = Command::new("python3")
            .arg(repo().join("scripts/ref_raster.py"))
            .args([
                "--ply",
                ply.to_str().unwrap(),
                "--cameras",
                cj.to_str().unwrap(),
            ])
            .args(["--out", dir.to_str().unwrap()])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let scene = PreparedScene::new(&g).unwrap();
        for (name, c) in &cams {
            let out = render_view(&scene, c, &RenderOptions::default()).unwrap();
            let load = |ch: &str| -> Vec<f32> {
                let (_, v) =
                    gs4city::npy::read::<f32>(&dir.join(format!("{cap}_{name}.{ch}.npy"))).unwrap();
                v
            };
            let (rgb, alpha) = (load("rgb"), load("alpha"));
            let worst =
                |a: &[f32], b: &[f32]| a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
            let (dr, da) = (worst(&out.rgb, &rgb), worst(&out.alpha, &alpha));
            let mean = out
                .rgb
                .iter()
                .zip(&rgb)
                .map(|(x, y)| f64::from((x - y).abs()))
                .sum::<f64>()
                / rgb.len() as f64;
            let cover = alpha.iter().filter(|&&a| a > 0.5).count();
            eprintln!(
                "{cap} {name}: max |Δrgb| {dr:.2e} (mean {mean:.1e}), |Δalpha| {da:.2e}; {cover} of {} pixels over alpha 0.5",
                alpha.len()
            );
            assert!(
                cover > alpha.len() / 10,
                "{cap} {name}: the capture is not in view"
            );
            // f32 against f64 over thousands of faint Gaussians per pixel, and a Gaussian whose
            // α sits at the 1/255 cut can fall on either side of it: the colour's worst pixel
            // within 10⁻³, its mean within 10⁻⁵
            assert!(
                dr <= 1e-3 && mean <= 1e-5 && da <= 2e-4,
                "{cap} {name}: {dr} {mean} {da}"
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

// ---------------------------------------------------------------- semantic segmentation

fn espnet() -> PathBuf {
    repo().join("models/espnet/espnet_p2_q8_cityscapes.onnx")
}

/// `segment --semantic`'s per-pixel classes on the 29 real Lund photos equal those of the
/// independent onnxruntime + NumPy reference (`scripts/semantic_reference.py`: Pillow's JPEG
/// decoding, the card's preprocessing, the same tiling) on at least 99.9 % of the pixels; and
/// the network sees the street: building, vegetation and road each cover a real share.
#[test]
fn semantic_segmentation_of_lund_matches_the_numpy_reference() {
    const TEST: &str = "real_inputs::semantic_segmentation_of_lund_matches_the_numpy_reference";
    let Some(real) = real(TEST) else { return };
    if !python_can_import(TEST, &["numpy", "onnxruntime", "PIL"]) {
        return;
    }
    let dir = scratch("semantic-ref");
    let images = real.join("lund/images");
    let o = Command::new("python3")
        .arg(repo().join("scripts/semantic_reference.py"))
        .args(["--model", espnet().to_str().unwrap()])
        .args([
            "--images",
            images.to_str().unwrap(),
            "--out",
            dir.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut m = gs4city::segment::semantic::SemanticModel::open(&espnet(), 0).unwrap();
    let (mut same, mut all) = (0usize, 0usize);
    let mut hist = vec![0usize; 20];
    let t = std::time::Instant::now();
    let list = gs4city::segment::list_images(&images).unwrap();
    assert_eq!(list.len(), 29);
    for img in &list {
        let rgb = gs4city::imageio::read_rgb(img).unwrap();
        let labels = m.probabilities(&rgb).unwrap().argmax();
        let stem = img.file_stem().unwrap().to_str().unwrap();
        let (shape, reference) =
            gs4city::npy::read::<u16>(&dir.join(format!("{stem}.npy"))).unwrap();
        assert_eq!(shape, vec![768, 1024]);
        let eq = labels
            .iter()
            .zip(&reference)
            .filter(|(a, b)| a == b)
            .count();
        for &l in labels.iter() {
            hist[usize::from(l)] += 1;
        }
        eprintln!(
            "{stem}: {:.4} % of pixels equal",
            100.0 * eq as f64 / reference.len() as f64
        );
        assert!(eq as f64 >= 0.995 * reference.len() as f64, "{stem}");
        same += eq;
        all += reference.len();
    }
    eprintln!(
        "29 photos: {:.4} % of {all} pixels equal; {:.2} s per photo (network, tiles, softmax); classes {hist:?}",
        100.0 * same as f64 / all as f64,
        t.elapsed().as_secs_f64() / 29.0
    );
    assert!(same as f64 >= 0.999 * all as f64);
    // Cityscapes ids: 0 road, 2 building, 8 vegetation
    for (k, name) in [(0, "road"), (2, "building"), (8, "vegetation")] {
        assert!(hist[k] as f64 > 0.03 * all as f64, "{name}: {hist:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A scene folder of the first `n` real Lund photos (copies) and its COLMAP model (a link).
fn lund_scene(real: &Path, name: &str, n: usize) -> PathBuf {
    let s = scratch(name);
    std::fs::create_dir_all(s.join("images")).unwrap();
    std::fs::create_dir_all(s.join("sparse")).unwrap();
    for k in 1..=n {
        let f = format!("{k:02}.jpg");
        std::fs::copy(real.join("lund/images").join(&f), s.join("images").join(&f)).unwrap();
    }
    std::os::unix::fs::symlink(real.join("lund/sparse/0"), s.join("sparse/0")).unwrap();
    s
}

/// `segment --semantic` writes masks and features that load as the masks stage and the
/// association load them (SAM lists of the image size, one feature row per mask of the
/// prompts' dimension, one-hot prompts with both prompt sets); the features are the masks'
/// mean class probabilities; a second run skips every image; a corrupt model, a model
/// without its card and a card whose class count is not the network's each stop the command
/// with one line naming the file.
#[test]
fn segment_semantic_writes_masks_and_features_the_stages_load() {
    const TEST: &str = "real_inputs::segment_semantic_writes_masks_and_features_the_stages_load";
    let Some(real) = real(TEST) else { return };
    if !python_can_import(TEST, &["onnxruntime"]) {
        return;
    }
    let s = lund_scene(&real, "semantic-cli", 4);
    let args = |net: &Path| -> Vec<String> {
        vec![
            "segment".into(),
            "--scene".into(),
            s.to_str().unwrap().into(),
            "--semantic".into(),
            net.to_str().unwrap().into(),
        ]
    };
    let run = |net: &Path| {
        let a = args(net);
        let refs: Vec<&str> = a.iter().map(String::as_str).collect();
        gs4city(&refs)
    };
    let o = run(&espnet());
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "{err}");
    let pp = s.join("features/prompts.json");
    let prompts = gs4city::sam::read_prompts_json(&pp).unwrap();
    assert_eq!(prompts.dim, 20);
    assert_eq!(prompts.prompts.len(), 19, "every class but void");
    assert_eq!(prompts.classes["building"], gs4city::classes::WALL);
    assert_eq!(prompts.classes["vegetation"], gs4city::classes::TREE);
    assert_eq!(prompts.classes["rider"], gs4city::classes::PERSON);
    let table = gs4city::masks::prompts::PromptTable::new(&pp, &prompts).unwrap();
    let mut classes_seen = std::collections::BTreeSet::new();
    let mut agree = (0, 0);
    for img in gs4city::segment::list_images(&s.join("images")).unwrap() {
        let mp = gs4city::segment::mask_path(&s.join("masks"), &img);
        let masks = gs4city::sam::read_sam_json_sized(&mp, Some([768, 1024])).unwrap();
        assert!(!masks.is_empty());
        let fp = gs4city::segment::features::features_path(&s.join("features"), &img);
        let f = gs4city::sam::read_view_features(&fp, masks.len(), prompts.dim, &pp).unwrap();
        for (m, row) in masks.iter().zip(f.chunks(prompts.dim)) {
            let sum: f32 = row.iter().sum();
            assert!(
                (sum - 1.0).abs() < 1e-3,
                "a feature is a probability vector: {sum}"
            );
            assert!(m.predicted_iou > 0.0 && m.predicted_iou <= 1.0);
            assert!(m.area >= (768 * 1024usize).div_ceil(2000) as u64);
            let scores = table.score(row);
            classes_seen.insert(scores.class);
            // the class the masks stage reads from the feature is the mask's own class
            let top = row
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1))
                .unwrap()
                .0;
            agree.1 += 1;
            if prompts.classes.get(
                [
                    "road",
                    "sidewalk",
                    "building",
                    "wall",
                    "fence",
                    "pole",
                    "traffic light",
                    "traffic sign",
                    "vegetation",
                    "terrain",
                    "sky",
                    "person",
                    "rider",
                    "car",
                    "truck",
                    "bus",
                    "train",
                    "motorcycle",
                    "bicycle",
                    "void",
                ][top],
            ) == Some(&scores.class)
            {
                agree.0 += 1;
            }
        }
    }
    assert_eq!(agree.0, agree.1, "{agree:?}");
    assert!(
        classes_seen.contains(&gs4city::classes::WALL)
            && classes_seen.contains(&gs4city::classes::TREE)
    );
    // a second run skips every image
    let o = run(&espnet());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("4 skipped"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // the three bad models
    let bad = scratch("semantic-bad");
    let one_line = |o: std::process::Output, file: &Path| {
        assert!(!o.status.success());
        let e = String::from_utf8_lossy(&o.stderr).trim().to_string();
        assert_eq!(e.lines().count(), 1, "{e}");
        assert!(e.contains(file.to_str().unwrap()), "{e}");
        assert!(!e.contains("panicked"), "{e}");
        e
    };
    let card = std::fs::read_to_string(espnet().with_extension("json")).unwrap();
    let corrupt = bad.join("corrupt.onnx");
    std::fs::write(&corrupt, &std::fs::read(espnet()).unwrap()[..4000]).unwrap();
    std::fs::write(corrupt.with_extension("json"), &card).unwrap();
    let s2 = lund_scene(&real, "semantic-cli2", 1);
    let run2 = |net: &Path| {
        gs4city(&[
            "segment",
            "--scene",
            s2.to_str().unwrap(),
            "--semantic",
            net.to_str().unwrap(),
        ])
    };
    one_line(run2(&corrupt), &corrupt);
    let nocard = bad.join("nocard.onnx");
    std::fs::copy(espnet(), &nocard).unwrap();
    let e = one_line(run2(&nocard), &nocard);
    assert!(e.contains("model card"), "{e}");
    let fewer = bad.join("fewer.onnx");
    std::fs::copy(espnet(), &fewer).unwrap();
    let mut c: serde_json::Value = serde_json::from_str(&card).unwrap();
    c["classes"].as_array_mut().unwrap().pop();
    std::fs::write(fewer.with_extension("json"), c.to_string()).unwrap();
    let e = one_line(run2(&fewer), &fewer);
    assert!(
        e.contains("gives 20 classes") && e.contains("names 19"),
        "{e}"
    );
    assert!(
        !s2.join("masks").exists()
            || std::fs::read_dir(s2.join("masks"))
                .unwrap()
                .next()
                .is_none()
    );
    let _ = std::fs::remove_dir_all(&s);
    let _ = std::fs::remove_dir_all(&s2);
    let _ = std::fs::remove_dir_all(&bad);
}

// ---------------------------------------------------------------- GPS

/// `align --exif` on the real Lund photos: every photo's GPS fix is used, the CRS is the UTM
/// zone (no city model), the vertical comes from the cameras, each camera's residual and the
/// RMS are printed, and `alignment.json` is written (the residuals are what phone GPS gives:
/// metres).
#[test]
fn align_exif_on_lund() {
    const TEST: &str = "real_inputs::align_exif_on_lund";
    let Some(real) = real(TEST) else { return };
    let s = scratch("exif-lund");
    std::os::unix::fs::symlink(real.join("lund/images"), s.join("images")).unwrap();
    std::fs::create_dir_all(s.join("sparse")).unwrap();
    std::os::unix::fs::symlink(real.join("lund/sparse/0"), s.join("sparse/0")).unwrap();
    let out = s.join("alignment.json");
    let o = gs4city(&[
        "align",
        "--exif",
        s.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    eprintln!("{text}");
    assert!(text.contains("GPS of 29 photos in EPSG:32633"), "{text}");
    assert!(text.contains("vertical: the cameras' up"), "{text}");
    let rows = text
        .lines()
        .filter(|l| {
            l.split_whitespace()
                .next()
                .is_some_and(|w| w.ends_with(".jpg"))
        })
        .count();
    assert_eq!(rows, 29, "{text}");
    let a = gs4city::alignment::Alignment::read(&out).unwrap();
    assert!(a.scale > 0.0);
    let rms: f64 = text
        .lines()
        .find(|l| l.starts_with("RMS"))
        .and_then(|l| l.split("horizontal ").nth(1))
        .and_then(|t| t.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap();
    assert!(rms < 10.0, "horizontal RMS {rms} m");
    let _ = std::fs::remove_dir_all(&s);
}

/// SIMULATED GPS: level cameras along a curved street (a COLMAP model written here), their
/// photos tagged (Pillow) with GPS positions made from a known similarity, 2 m horizontal and
/// 5 m vertical noise, and two fixes 60–80 m off. `align --exif` recovers the similarity
/// (scale within 2 %, rotation within 1.5°), names the two as outliers, and the noisy
/// altitudes do not tilt it.
#[test]
fn align_exif_recovers_a_known_similarity_from_noisy_gps() {
    const TEST: &str = "real_inputs::align_exif_recovers_a_known_similarity_from_noisy_gps";
    if !python_can_import(TEST, &["PIL"]) {
        return;
    }
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5959);
    let mut gauss = |s: f64| -> f64 {
        let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
        s * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    };
    let crs = "EPSG:32633";
    let georef = gs4city::crs::Georef::new(crs).unwrap();
    let origin = DVec3::new(374_150.0, 6_177_600.0, 30.0);
    let truth = gs4city::alignment::Alignment {
        origin,
        scale: 0.21,
        rotation: DMat3::from_euler(glam::EulerRot::XYZ, -1.7, 0.4, 2.9),
        translation: DVec3::new(1.0, 2.0, -0.5),
    };
    let s = scratch("exif-sim");
    std::fs::create_dir_all(s.join("images")).unwrap();
    let mut views = Vec::new();
    let mut tags = Vec::new();
    for k in 0..24 {
        let t = k as f64 / 23.0;
        // a street, heading changing along it; cameras 1.6 m above it, level, looking sideways
        // or along the street
        let g = origin + DVec3::new(160.0 * t - 80.0, 30.0 * (2.0 * t).sin(), 1.6);
        let heading = (2.0 * t).cos().atan2(1.0)
            + if k % 3 == 0 {
                0.0
            } else {
                std::f64::consts::FRAC_PI_2 * if k % 2 == 0 { 1.0 } else { -1.0 }
            };
        let fwd = DVec3::new(heading.cos(), heading.sin(), 0.0);
        let right = DVec3::new(fwd.y, -fwd.x, 0.0);
        let down = DVec3::NEG_Z;
        // camera axes in the geo frame → in the scene frame by the similarity's rotation
        let rot = truth.rotation;
        let (x, y, z) = (rot * right, rot * down, rot * fwd);
        let r_wc = DMat3::from_cols(x, y, z).transpose();
        let centre = truth.apply(g);
        let name = format!("{k:02}.jpg");
        views.push(gs4city::camera::View {
            image_id: k + 1,
            camera_id: 1,
            name: name.clone(),
            camera: Camera {
                intrinsics: Intrinsics {
                    width: 64,
                    height: 48,
                    fx: 50.0,
                    fy: 50.0,
                    cx: 32.0,
                    cy: 24.0,
                    distortion: Distortion::None,
                },
                pose: Pose {
                    rotation: r_wc,
                    translation: -(r_wc * centre),
                },
            },
        });
        let mut noisy = g + DVec3::new(gauss(2.0), gauss(2.0), gauss(5.0));
        if k == 5 {
            noisy += DVec3::new(80.0, 10.0, 0.0);
        }
        if k == 17 {
            noisy += DVec3::new(-20.0, 60.0, 12.0);
        }
        let (lon, lat) = georef.lon_lat(noisy.x, noisy.y).unwrap();
        tags.push(serde_json::json!({"name": name, "lat": lat, "lon": lon, "alt": noisy.z}));
    }
    gs4city::colmap::write_model(&s.join("sparse/0"), &views, true).unwrap();
    let tj = s.join("tags.json");
    std::fs::write(&tj, serde_json::to_string(&tags).unwrap()).unwrap();
    let code = r#"
import json, sys
from PIL import Image
from fractions import Fraction
tags = json.load(open(sys.argv[1]))
def dms(v):
    v = abs(v); d = int(v); m = int((v - d) * 60); s = (v - d - m / 60) * 3600
    return (Fraction(d), Fraction(m), Fraction(round(s * 10000), 10000))
for t in tags:
    im = Image.new("RGB", (64, 48), (120, 130, 140))
    ex = Image.Exif()
    ex[0x0112] = 1
    gps = {1: "N" if t["lat"] >= 0 else "S", 2: dms(t["lat"]), 3: "E" if t["lon"] >= 0 else "W",
           4: dms(t["lon"]), 5: 0 if t["alt"] >= 0 else 1, 6: Fraction(round(abs(t["alt"]) * 100), 100)}
    ex[0x8825] = gps
    im.save(sys.argv[2] + "/" + t["name"], exif=ex.tobytes())
"#;
    python(
        code,
        &[tj.to_str().unwrap(), s.join("images").to_str().unwrap()],
    );
    let out = s.join("alignment.json");
    let o = gs4city(&[
        "align",
        "--exif",
        s.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    eprintln!("{text}");
    let outliers: Vec<&str> = text
        .lines()
        .filter(|l| l.ends_with("outlier"))
        .map(|l| l.split_whitespace().next().unwrap())
        .collect();
    assert_eq!(outliers, vec!["05.jpg", "17.jpg"], "{text}");
    assert!(text.contains("vertical: the cameras' up"), "{text}");
    let a = gs4city::alignment::Alignment::read(&out).unwrap();
    assert!(
        (a.scale / truth.scale - 1.0).abs() < 0.02,
        "scale {}",
        a.scale
    );
    let angle = gs4city::alignment::rotation_angle_deg(&(a.rotation.transpose() * truth.rotation));
    assert!(angle < 1.5, "rotation off by {angle}°");
    // the altitudes (5 m noise) do not tilt it: up maps onto up within 0.01°
    let tilt = (a.rotation * DVec3::Z)
        .angle_between(truth.rotation * DVec3::Z)
        .to_degrees();
    assert!(tilt < 0.01, "tilt {tilt}°");
    for v in &views {
        let c = v.camera.pose.center();
        let err = (a.unapply(c) - truth.unapply(c)).truncate().length();
        assert!(err < 2.5, "{}: {err} m", v.name);
    }
    let _ = std::fs::remove_dir_all(&s);
}

/// The masks and features of `segment --semantic` feed the pipeline unchanged: on a
/// SIMULATED scene (synth small preset, its SIMULATED masks and features removed) segmented by
/// the real ESPNet, `run` takes them — the masks stage runs its features test on the one-hot
/// prompts, and the association calibrates `τ_sim` from them (the network knows nothing of
/// simulated oblique views: this checks the plumbing, not the labels).
#[test]
fn semantic_masks_feed_the_masks_and_associate_stages() {
    const TEST: &str = "real_inputs::semantic_masks_feed_the_masks_and_associate_stages";
    if !python_can_import(TEST, &["onnxruntime"]) {
        return;
    }
    let dir = scratch("semantic-run");
    let mut cfg = gs4city::synth::SynthConfig::preset(gs4city::synth::Preset::Small);
    cfg.cameras.orbit_views = 3;
    cfg.cameras.street_views = 0;
    cfg.cameras.width = 330;
    cfg.cameras.height = 247;
    let s = dir.join("scene");
    gs4city::synth::run(&cfg, &s).unwrap();
    std::fs::remove_dir_all(s.join("masks")).unwrap();
    let _ = std::fs::remove_dir_all(s.join("features"));
    let o = gs4city(&[
        "segment",
        "--scene",
        s.to_str().unwrap(),
        "--semantic",
        espnet().to_str().unwrap(),
        "--min-area",
        "20",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = dir.join("out");
    let o = gs4city(&[
        "run",
        "--scene",
        s.to_str().unwrap(),
        "--out",
        r.to_str().unwrap(),
        "--test-every",
        "3",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let read = |p: &str| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(r.join(p)).unwrap()).unwrap()
    };
    let masks = read("masks/summary.json");
    assert_eq!(masks["features"], serde_json::Value::Bool(true), "{masks}");
    let assoc = read("associate/summary.json");
    eprintln!(
        "masks: {masks}\nassociate calibration: {}",
        assoc["calibration"]
    );
    assert!(assoc["calibration"]["mode"].is_string(), "{assoc}");
    let _ = std::fs::remove_dir_all(&dir);
}
