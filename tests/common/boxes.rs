//! A hand-built scene with known answers for the association and fusion tests: a ground square
//! (20×20 m, "road"), two car-sized boxes A and B and a person-sized box C, covered by flat
//! Gaussians whose object is known; 8 cameras on a circle around them. The masks of each view
//! are computed analytically (ray–box and ray–plane intersections per pixel centre), not by any
//! code under test, and written in the masks stage's kept-mask format with per-mask features.
#![allow(dead_code)]
use std::path::{Path, PathBuf};

use glam::DVec3;
use gs4city::cache::{Cache, CacheOptions};
use gs4city::camera::{Camera, Distortion, Intrinsics, Pose, View};
use gs4city::maskfile::{KeptMask, write_kept};
use gs4city::render::PreparedScene;
use gs4city::sam::SamMask;
use gs4city::splat::{Gaussians, PlyEncoding, write_ply};
use ndarray::Array2;

pub const W: u32 = 160;
pub const H: u32 = 120;
/// Objects: 0 = box A (car), 1 = box B (car), 2 = box C (person), 3 = ground (road).
pub const OBJECTS: usize = 4;
pub const CLASS: [i32; OBJECTS] = [8, 8, 7, 9];
/// Feature dimension of the simulated per-mask features.
pub const DIM: usize = 4;

/// `(lo, hi)` of the three boxes.
pub fn boxes() -> [([f64; 3], [f64; 3]); 3] {
    [
        ([-4.0, -0.5, 0.0], [-2.0, 0.5, 1.0]),
        ([2.0, -0.5, 0.0], [4.0, 0.5, 1.0]),
        ([-0.25, 2.75, 0.0], [0.25, 3.25, 1.8]),
    ]
}

pub fn tmp(name: &str) -> PathBuf {
    let d = crate::common::temp_dir().join(format!("gs4city-assoc-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Flat Gaussians on the box faces (not the bottoms) and on the ground outside the boxes; per
/// Gaussian its object.
pub fn splats() -> (Gaussians, Vec<usize>) {
    let mut g = Gaussians {
        sh_degree: 0,
        ..Default::default()
    };
    let mut obj = Vec::new();
    let mut push =
        |g: &mut Gaussians, p: [f64; 3], normal: usize, s: f64, o: usize, rgb: [f32; 3]| {
            g.positions.push([p[0] as f32, p[1] as f32, p[2] as f32]);
            g.f_dc.push(rgb.map(|c| (c - 0.5) / 0.282_094_8));
            g.opacity.push(3.0);
            let mut sc = [(s as f32).ln(); 3];
            sc[normal] = (0.005f32).ln();
            g.scale.push(sc);
            g.rotation.push([1.0, 0.0, 0.0, 0.0]);
            obj.push(o);
        };
    let colors = [[0.8, 0.1, 0.1], [0.1, 0.1, 0.8], [0.9, 0.8, 0.2]];
    for (o, (lo, hi)) in boxes().iter().enumerate() {
        let step = 0.08;
        for axis in 0..3 {
            for side in [lo[axis], hi[axis]] {
                if axis == 2 && side == lo[2] {
                    continue; // bottom
                }
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                let nu = ((hi[u] - lo[u]) / step).round() as usize;
                let nv = ((hi[v] - lo[v]) / step).round() as usize;
                for i in 0..nu {
                    for j in 0..nv {
                        let mut p = [0.0; 3];
                        p[axis] = side;
                        p[u] = lo[u] + (i as f64 + 0.5) * step;
                        p[v] = lo[v] + (j as f64 + 0.5) * step;
                        push(&mut g, p, axis, step * 0.7, o, colors[o]);
                    }
                }
            }
        }
    }
    let step = 0.2;
    let n = (20.0 / step) as usize;
    for i in 0..n {
        for j in 0..n {
            let p = [
                -10.0 + (i as f64 + 0.5) * step,
                -10.0 + (j as f64 + 0.5) * step,
                0.0,
            ];
            let inside = boxes()
                .iter()
                .any(|(lo, hi)| (lo[0]..=hi[0]).contains(&p[0]) && (lo[1]..=hi[1]).contains(&p[1]));
            if !inside {
                push(&mut g, p, 2, step * 0.7, 3, [0.4, 0.4, 0.4]);
            }
        }
    }
    (g, obj)
}

/// 12 views on a circle of radius 12 m, 5 m high, looking at the scene centre; `v00` … `v11`.
pub fn views() -> Vec<View> {
    (0..12)
        .map(|i| {
            let a = std::f64::consts::TAU * (i as f64 + 0.3) / 12.0;
            let eye = DVec3::new(12.0 * a.cos(), 12.0 * a.sin(), 5.0);
            View {
                image_id: i + 1,
                camera_id: i + 1,
                name: format!("v{i:02}.png"),
                camera: Camera {
                    intrinsics: Intrinsics {
                        width: W,
                        height: H,
                        fx: 120.0,
                        fy: 120.0,
                        cx: 80.0,
                        cy: 60.0,
                        distortion: Distortion::None,
                    },
                    pose: Pose::look_at(eye, DVec3::new(0.0, 1.0, 0.5), DVec3::Z).unwrap(),
                },
            }
        })
        .collect()
}

/// Ray–box slab test: the entry distance, if the ray hits.
fn hit_box(o: DVec3, d: DVec3, lo: [f64; 3], hi: [f64; 3]) -> Option<f64> {
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for k in 0..3 {
        if d[k].abs() < 1e-12 {
            if o[k] < lo[k] || o[k] > hi[k] {
                return None;
            }
            continue;
        }
        let (a, b) = ((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    (t0 <= t1).then_some(t0)
}

/// The object each pixel shows (−1 sky), from the geometry alone.
pub fn truth(view: &View) -> Vec<i32> {
    let cam = &view.camera;
    let o = cam.pose.center();
    let rt = cam.pose.rotation.transpose();
    let mut out = vec![-1; (W * H) as usize];
    for j in 0..H as usize {
        for i in 0..W as usize {
            let d = rt * cam.pixel_ray(i as f64 + 0.5, j as f64 + 0.5);
            let mut best = (f64::INFINITY, -1);
            for (k, (lo, hi)) in boxes().iter().enumerate() {
                if let Some(t) = hit_box(o, d, *lo, *hi)
                    && t < best.0
                {
                    best = (t, k as i32);
                }
            }
            if d.z < 0.0 {
                let t = -o.z / d.z;
                let p = o + d * t;
                if t < best.0 && p.x.abs() <= 10.0 && p.y.abs() <= 10.0 {
                    best = (t, 3);
                }
            }
            out[j * W as usize + i] = best.1;
        }
    }
    out
}

/// A unit feature for object `o`: its class prototype (the two cars share one).
pub fn feature(o: usize) -> Vec<f32> {
    let mut f = [0.05f32; DIM];
    f[match CLASS[o] {
        8 => 0,
        7 => 1,
        _ => 2,
    }] = 1.0;
    let n = f.iter().map(|x| x * x).sum::<f32>().sqrt();
    f.iter().map(|x| x / n).collect()
}

/// The mask of object `o` in a truth map (None under `min_px` pixels).
pub fn object_mask(truth: &[i32], o: usize, min_px: usize) -> Option<SamMask> {
    let a = Array2::from_shape_fn((H as usize, W as usize), |(y, x)| {
        truth[y * W as usize + x] == o as i32
    });
    (a.iter().filter(|&&b| b).count() >= min_px).then(|| SamMask::from_mask(&a, 0.95, 0.97, vec![]))
}

/// A built scene: folders and per-view truth.
pub struct Built {
    pub dir: PathBuf,
    pub views: Vec<View>,
    pub ply: PathBuf,
    pub cache: PathBuf,
    pub masks: PathBuf,
    /// The scene's SAM lists (`masks/`) and features (`features/`): the same masks.
    pub sam: PathBuf,
    pub features: PathBuf,
    pub truth: Vec<Vec<i32>>,
    pub objects: Vec<usize>,
}

/// Writes the scene: PLY, contributions cache, kept masks (every object with ≥ 20 pixels, in
/// object order, except those `skip(view, object)` drops), SAM lists and features.
pub fn build(name: &str, skip: impl Fn(usize, usize) -> bool) -> Built {
    let dir = tmp(name);
    let (g, objects) = splats();
    let ply = dir.join("point_cloud.ply");
    write_ply(&ply, &g, PlyEncoding::BinaryLittleEndian).unwrap();
    let views = views();
    let prepared = PreparedScene::new(&g).unwrap();
    gs4city::render::cache::build(
        &prepared,
        &views,
        &CacheOptions {
            top_k: 16,
            epsilon: 0.0,
            t_stop: 0.0,
            alpha_min: gs4city::cache::INRIA_ALPHA_MIN,
        },
        &dir.join("cache"),
    )
    .unwrap();
    let (masks, sam, features) = (dir.join("kept"), dir.join("masks"), dir.join("features"));
    for d in [&masks, &sam, &features] {
        std::fs::create_dir_all(d).unwrap();
    }
    let mut truth = Vec::new();
    for (v, view) in views.iter().enumerate() {
        let t = truth_of(view);
        let mut kept = Vec::new();
        let mut list = Vec::new();
        let mut feats = Vec::new();
        for (o, &class) in CLASS.iter().enumerate() {
            let Some(m) = object_mask(&t, o, 20) else {
                continue;
            };
            let index = list.len() as i64;
            list.push(m.clone());
            feats.push(feature(o));
            if !skip(v, o) {
                kept.push(KeptMask {
                    sam: m,
                    source_index: index,
                    r_ov: 0.0,
                    rule: gs4city::maskfile::Rule::LowOverlap,
                    class,
                });
            }
        }
        let stem = view.stem();
        write_kept(&masks.join(format!("{stem}.json")), &kept).unwrap();
        gs4city::sam::write_sam_json(&sam.join(format!("{stem}.json")), &list).unwrap();
        gs4city::sam::write_features_npy(&features.join(format!("{stem}.npy")), DIM, &feats)
            .unwrap();
        truth.push(t);
    }
    Built {
        cache: dir.join("cache"),
        dir,
        views,
        ply,
        masks,
        sam,
        features,
        truth,
        objects,
    }
}

fn truth_of(view: &View) -> Vec<i32> {
    truth(view)
}

impl Built {
    pub fn open_cache(&self) -> Cache {
        Cache::open(&self.cache).unwrap()
    }
}

/// Reads a per-view int32 map.
pub fn read_map(path: &Path) -> Vec<i32> {
    gs4city::npy::read::<i32>(path).unwrap().1
}
