//! A hand-built scene with known answers: one georeferenced 10×6 m wall with a 2×2 m window,
//! flat Gaussians sampled on it (the window recessed 0.15 m), floaters in front, 8 cameras, and
//! ground truth computed analytically from the geometry (ray–plane intersections), not by any
//! code under test.
use std::path::{Path, PathBuf};

use glam::DVec3;
use gs4city::camera::{Camera, Distortion, Intrinsics, Pose, View};
use gs4city::classes;
use gs4city::splat::{Gaussians, PlyEncoding, write_ply};
use rand::{Rng, SeedableRng};

/// The georeferenced origin of the wall's corner (UTM-like, f64).
pub const ORIGIN: [f64; 3] = [678_000.0, 5_403_000.0, 400.0];
pub const WIDTH: u32 = 160;
pub const HEIGHT: u32 = 120;

/// The CityGML 2.0 file: Building B, WallSurface W (with a hole), Window Win in the hole.
pub fn citygml() -> String {
    let [e, n, h] = ORIGIN;
    let p = |x: f64, z: f64| format!("{} {} {}", e + x, n, h + z);
    let ring = |pts: &[(f64, f64)]| {
        let mut v: Vec<String> = pts.iter().map(|&(x, z)| p(x, z)).collect();
        v.push(v[0].clone());
        v.join(" ")
    };
    let wall = ring(&[(0.0, 0.0), (10.0, 0.0), (10.0, 6.0), (0.0, 6.0)]);
    let hole = ring(&[(4.0, 2.0), (4.0, 4.0), (6.0, 4.0), (6.0, 2.0)]);
    let win = ring(&[(4.0, 2.0), (6.0, 2.0), (6.0, 4.0), (4.0, 4.0)]);
    format!(
        r#"<?xml version="1.0"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:gml="http://www.opengis.net/gml">
<core:cityObjectMember><bldg:Building gml:id="B"><bldg:measuredHeight uom="m">6.0</bldg:measuredHeight><bldg:boundedBy><bldg:WallSurface gml:id="W">
<bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>{wall}</gml:posList></gml:LinearRing></gml:exterior>
<gml:interior><gml:LinearRing><gml:posList>{hole}</gml:posList></gml:LinearRing></gml:interior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface>
<bldg:opening><bldg:Window gml:id="Win"><bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>{win}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface></bldg:Window></bldg:opening>
</bldg:WallSurface></bldg:boundedBy></bldg:Building></core:cityObjectMember></core:CityModel>
"#
    )
}

/// `alignment.json` of the wall: the origin subtracted, nothing else (scene = metres).
pub fn alignment_json() -> String {
    let [e, n, h] = ORIGIN;
    format!(
        r#"{{"origin": [{e}, {n}, {h}], "scale": 1.0, "rotation": [[1,0,0],[0,1,0],[0,0,1]], "translation": [0,0,0]}}"#
    )
}

/// Floater centres (in front of the wall, y ∈ [−12, −8]).
pub struct Splats {
    pub gaussians: Gaussians,
    /// Per Gaussian: WALL, WINDOW or −1 (floater); −3 for wall/window Gaussians within 0.25 m
    /// of an outline (their footprint straddles two labels: not judged).
    pub judged: Vec<i32>,
    /// Per Gaussian: its real class (WALL, WINDOW, −1 floater), edge band included.
    pub real: Vec<i32>,
    pub floaters: Vec<[f32; 3]>,
}

/// Flat Gaussians on the wall plane y = 0 (scene frame = geo − ORIGIN), a window recessed to
/// y = 0.15 (inside the building), and 100 round floaters (σ = 0.1 m) in front.
pub fn splats(seed: u64) -> Splats {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut g = Gaussians {
        sh_degree: 0,
        ..Default::default()
    };
    let (mut judged, mut real, mut floaters) = (Vec::new(), Vec::new(), Vec::new());
    let push = |g: &mut Gaussians, p: [f32; 3], rgb: [f32; 3], flat: bool| {
        g.positions.push(p);
        g.f_dc.push(rgb.map(|c| (c - 0.5) / 0.282_094_8));
        g.opacity.push(3.0);
        g.scale.push(if flat {
            [(0.12f32).ln(), (0.002f32).ln(), (0.12f32).ln()]
        } else {
            [(0.1f32).ln(); 3]
        });
        g.rotation.push([1.0, 0.0, 0.0, 0.0]);
    };
    for _ in 0..6000 {
        let (x, z) = (
            rng.random_range(0.0..10.0f32),
            rng.random_range(0.0..6.0f32),
        );
        let in_hole = (4.0..6.0).contains(&x) && (2.0..4.0).contains(&z);
        let edge = x.min(10.0 - x).min(z).min(6.0 - z) < 0.25
            || ((3.75..6.25).contains(&x)
                && (1.75..4.25).contains(&z)
                && !((4.25..5.75).contains(&x) && (2.25..3.75).contains(&z)));
        let class = if in_hole {
            classes::WINDOW
        } else {
            classes::WALL
        };
        let (y, rgb) = if in_hole {
            (0.15, [0.2, 0.4, 0.8])
        } else {
            (0.0, [0.8, 0.7, 0.5])
        };
        push(&mut g, [x, y, z], rgb, true);
        real.push(class);
        judged.push(if edge { -3 } else { class });
    }
    for _ in 0..100 {
        let p = [
            rng.random_range(-5.0..15.0),
            rng.random_range(-12.0..-8.0),
            rng.random_range(0.0..8.0),
        ];
        push(&mut g, p, [0.3, 0.6, 0.2], false);
        real.push(-1);
        judged.push(-1);
        floaters.push(p);
    }
    Splats {
        gaussians: g,
        judged,
        real,
        floaters,
    }
}

/// 8 views from y = −14 looking at the wall centre; `v00` … `v07`.
pub fn views() -> Vec<View> {
    (0..8)
        .map(|i| {
            let x = 1.0 + i as f64 * 1.1;
            let eye = DVec3::new(x, -14.0, 3.0 + (i % 3) as f64 * 0.5);
            let camera = Camera {
                intrinsics: Intrinsics {
                    width: WIDTH,
                    height: HEIGHT,
                    fx: 120.0,
                    fy: 120.0,
                    cx: 80.0,
                    cy: 60.0,
                    distortion: Distortion::None,
                },
                pose: Pose::look_at(eye, DVec3::new(5.0, 0.0, 3.0), DVec3::Z).unwrap(),
            };
            View {
                image_id: i + 1,
                camera_id: i + 1,
                name: format!("v{i:02}.png"),
                camera,
            }
        })
        .collect()
}

/// Ground truth of a view from the geometry alone: per pixel centre, the ray is intersected with
/// the wall plane y = 0 (wall where it lands on the wall outside the hole) and, through the hole,
/// with the window plane y = 0.15 (window). Pixels whose ray passes within 0.11 m of a floater
/// centre show the floater (class 11, other), within 0.11–0.35 m a mix (−1, ignored); pixels
/// within 0.3 m of an outline are −1; rays that miss the wall are class 11 (non-building).
pub fn truth(view: &View, floaters: &[[f32; 3]]) -> Vec<i32> {
    let cam = &view.camera;
    let (w, h) = (
        cam.intrinsics.width as usize,
        cam.intrinsics.height as usize,
    );
    let o = cam.pose.center();
    let rt = cam.pose.rotation.transpose();
    let mut out = vec![-1; w * h];
    for j in 0..h {
        for i in 0..w {
            let d = rt * cam.pixel_ray(i as f64 + 0.5, j as f64 + 0.5);
            // A floater's α = 0.95·e^(−r²/2σ²) is ≥ 0.5 within r < 0.11 m (it is what the
            // pixel shows: class 11) and ≥ 1/255 up to r ≈ 0.33 m (mixed: ignored).
            let floater = floaters
                .iter()
                .filter_map(|f| {
                    let c = DVec3::new(f[0] as f64, f[1] as f64, f[2] as f64) - o;
                    let t = c.dot(d);
                    (t > 0.0).then(|| (c - d * t).length())
                })
                .fold(f64::INFINITY, f64::min);
            if floater < 0.11 {
                out[j * w + i] = classes::OTHER;
                continue;
            }
            if floater < 0.35 {
                continue;
            }
            let at = |y: f64| -> Option<(f64, f64)> {
                (d.y.abs() > 1e-9).then(|| {
                    let t = (y - o.y) / d.y;
                    let p = o + d * t;
                    (p.x, p.z)
                })
            };
            let Some((x, z)) = at(0.0) else { continue };
            let on_wall = (0.0..=10.0).contains(&x) && (0.0..=6.0).contains(&z);
            let in_hole = (4.0..6.0).contains(&x) && (2.0..4.0).contains(&z);
            let wall_edge = x.min(10.0 - x).min(z).min(6.0 - z).abs() < 0.3
                || ((3.7..6.3).contains(&x)
                    && (1.7..4.3).contains(&z)
                    && !((4.3..5.7).contains(&x) && (2.3..3.7).contains(&z)));
            out[j * w + i] = if wall_edge {
                -1
            } else if !on_wall {
                classes::OTHER
            } else if in_hole {
                match at(0.15) {
                    Some((x1, z1)) if (4.3..5.7).contains(&x1) && (2.3..3.7).contains(&z1) => {
                        classes::WINDOW
                    }
                    _ => -1,
                }
            } else {
                classes::WALL
            };
        }
    }
    out
}

/// Writes a complete scene folder into `dir`: `citymodel/wall.gml` + `alignment.json`,
/// `sparse/0` (binary COLMAP), `point_cloud.ply`, `gt/<stem>.class.npy` (analytic truth).
pub fn write_scene(dir: &Path, seed: u64) -> (PathBuf, Splats) {
    std::fs::create_dir_all(dir.join("citymodel")).unwrap();
    std::fs::write(dir.join("citymodel/wall.gml"), citygml()).unwrap();
    std::fs::write(dir.join("citymodel/alignment.json"), alignment_json()).unwrap();
    let vs = views();
    gs4city::colmap::write_model(&dir.join("sparse/0"), &vs, true).unwrap();
    let s = splats(seed);
    write_ply(
        &dir.join("point_cloud.ply"),
        &s.gaussians,
        PlyEncoding::BinaryLittleEndian,
    )
    .unwrap();
    std::fs::create_dir_all(dir.join("gt")).unwrap();
    for v in &vs {
        gs4city::npy::write(
            &dir.join(format!("gt/{}.class.npy", v.stem())),
            &[HEIGHT as usize, WIDTH as usize],
            &truth(v, &s.floaters),
        )
        .unwrap();
    }
    (dir.to_path_buf(), s)
}

/// A fresh temporary folder.
pub fn tmp(name: &str) -> PathBuf {
    let d = crate::common::temp_dir().join(format!("gs4city-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}
