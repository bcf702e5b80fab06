//! The masks stage on a hand-built scene whose answers are known by construction: a wall at
//! 10 m with a window recessed 0.15 m, a person 3 m in front of the wall, a semi-transparent
//! veil in front of part of the wall, a road beside the building (no city hit), plus masks that
//! fail the quality and area filters. Every expected rule below is derived from that geometry,
//! not from the code. Also: byte-identical outputs without the simulation truth, bad inputs
//! (one clear error naming the file), and the command line.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};
use gs4city::cache::Contributions;
use gs4city::cache::{Cache, CacheOptions, CacheSummary, CachedView, ViewContrib};
use gs4city::camera::{Camera, Distortion, Intrinsics, Pose, View};
use gs4city::layout::Summary;
use gs4city::maskfile::KeptMask;
use gs4city::masks::{self, GsDepth, MasksInputs, MasksOptions, MasksSummary, Source, Test};
use gs4city::sam::{self, Prompts, SamMask};
use gs4city::scene::Scene;
use gs4city::splat::{Gaussians, PlyEncoding};
use gs4city::{npy, sam::write_sam_json};
use ndarray::Array2;

const H: usize = 20;
const W: usize = 30;
const STEM: &str = "v0";

/// Gaussian ids: wall (z 10), window (z 10.15, recessed), person (z 7), veil (z 1), road (z 8).
const WALL: u32 = 0;
const WINDOW: u32 = 1;
const PERSON: u32 = 2;
const VEIL: u32 = 3;
const ROAD: u32 = 4;
const Z: [f32; 5] = [10.0, 10.15, 7.0, 1.0, 8.0];

fn in_rect(y: usize, x: usize, r: [usize; 4]) -> bool {
    (r[0]..r[1]).contains(&y) && (r[2]..r[3]).contains(&x)
}

/// Rectangles `[y0, y1, x0, x1]` (end exclusive).
const BUILDING: [usize; 4] = [0, H, 0, 20];
const WINDOW_R: [usize; 4] = [2, 7, 11, 18];
const PERSON_R: [usize; 4] = [5, 16, 4, 9];
const VEIL_R: [usize; 4] = [10, 18, 11, 18];
const ROAD_R: [usize; 4] = [8, H, 21, 29];

fn mask_of(r: [usize; 4]) -> Array2<bool> {
    Array2::from_shape_fn((H, W), |(y, x)| in_rect(y, x, r))
}

/// The per-pixel contribution list of the hand-built 3DGS (in depth order).
fn pixel_list(y: usize, x: usize) -> Vec<(u32, f32)> {
    if in_rect(y, x, PERSON_R) {
        return vec![(PERSON, 0.98)];
    }
    if in_rect(y, x, BUILDING) {
        let surface = if in_rect(y, x, WINDOW_R) {
            WINDOW
        } else {
            WALL
        };
        if in_rect(y, x, VEIL_R) {
            // 30 % of the light stopped by a veil at 1 m: expected depth 0.3·1 + 0.68·10 /
            // 0.98 ≈ 7.25 m, median depth 10 m (the wall).
            return vec![(VEIL, 0.3), (surface, 0.68)];
        }
        return vec![(surface, 0.98)];
    }
    if in_rect(y, x, ROAD_R) {
        return vec![(ROAD, 0.98)];
    }
    vec![]
}

fn view() -> View {
    View {
        image_id: 1,
        camera_id: 1,
        name: format!("{STEM}.png"),
        camera: Camera {
            intrinsics: Intrinsics {
                width: W as u32,
                height: H as u32,
                fx: 30.0,
                fy: 30.0,
                cx: 15.0,
                cy: 10.0,
                distortion: Distortion::None,
            },
            pose: Pose {
                rotation: DMat3::IDENTITY,
                translation: DVec3::ZERO,
            },
        },
    }
}

/// The SAM list: (mask, predicted_iou, feature class index into PROMPTS).
fn sam_list() -> Vec<(Array2<bool>, f64, usize)> {
    let wall = Array2::from_shape_fn((H, W), |(y, x)| {
        in_rect(y, x, BUILDING)
            && !in_rect(y, x, WINDOW_R)
            && !in_rect(y, x, PERSON_R)
            && !in_rect(y, x, VEIL_R)
    });
    let mut speck = Array2::from_elem((H, W), false);
    speck[[0, 25]] = true;
    vec![
        (wall, 0.95, 0),                   // 0: wall → building
        (mask_of(WINDOW_R), 0.9, 1),       // 1: recessed window → building
        (mask_of(PERSON_R), 0.92, 2),      // 2: person in front → occluder
        (mask_of(VEIL_R), 0.88, 3),        // 3: the veil region, looks like a tree
        (mask_of(ROAD_R), 0.97, 4),        // 4: road, no city hit → low overlap
        (mask_of([0, 4, 0, 4]), 0.5, 0),   // 5: low quality
        (speck, 0.99, 4),                  // 6: one pixel → area
        (mask_of([14, 17, 1, 3]), 0.9, 0), // 7: a small wall blob → building
    ]
}

/// Prompts (dimension 5): one axis each; "a tree" is resolved by keyword, the others from
/// the file's `classes`.
const PROMPTS: [(&str, i32); 5] = [
    ("a wall", 0),
    ("a window", 2),
    ("a person", 7),
    ("a tree", 6),
    ("a road", 9),
];

fn unit(i: usize, dim: usize) -> Vec<f32> {
    let mut v = vec![0.0f32; dim];
    v[i] = 1.0;
    v
}

struct Fixture {
    _tmp: TempDir,
    scene: PathBuf,
    raycast: PathBuf,
    cache: PathBuf,
    root: PathBuf,
}

struct TempDir(PathBuf);
impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn tmpdir(name: &str) -> TempDir {
    let d = crate::common::temp_dir().join(format!("gs4city_masks_{name}_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    TempDir(d)
}

/// Writes the scene folder, a raycast folder and a cache folder.
fn fixture(name: &str, with_features: bool) -> Fixture {
    let tmp = tmpdir(name);
    let root = tmp.0.clone();
    let scene = root.join("scene");
    for d in ["citymodel", "masks", "images"] {
        std::fs::create_dir_all(scene.join(d)).unwrap();
    }
    std::fs::write(scene.join("citymodel/a.gml"), "<CityModel/>").unwrap();
    gs4city::colmap::write_model(&scene.join("sparse/0"), &[view()], false).unwrap();
    // The Gaussians: only the centres matter here (z in the identity camera frame).
    let n = Z.len();
    let g = Gaussians {
        positions: Z.iter().map(|&z| [0.0, 0.0, z]).collect(),
        normals: None,
        sh_degree: 0,
        f_dc: vec![[0.5; 3]; n],
        f_rest: vec![],
        opacity: vec![2.0; n],
        scale: vec![[-2.0; 3]; n],
        rotation: vec![[1.0, 0.0, 0.0, 0.0]; n],
        extras: vec![],
    };
    gs4city::splat::write_ply(
        &scene.join("point_cloud.ply"),
        &g,
        PlyEncoding::BinaryLittleEndian,
    )
    .unwrap();
    let img = ndarray::Array3::from_shape_fn((H, W, 3), |(y, x, c)| {
        ((y * 7 + x * 3 + c * 50) % 256) as u8
    });
    gs4city::imageio::write_png(&scene.join(format!("images/{STEM}.png")), &img).unwrap();
    // SAM list and features.
    let list = sam_list();
    let masks: Vec<SamMask> = list
        .iter()
        .map(|(m, q, _)| SamMask::from_mask(m, *q, 0.97, vec![]))
        .collect();
    write_sam_json(&scene.join(format!("masks/{STEM}.json")), &masks).unwrap();
    if with_features {
        std::fs::create_dir_all(scene.join("features")).unwrap();
        let dim = PROMPTS.len();
        let feats: Vec<Vec<f32>> = list
            .iter()
            .map(|(_, _, k)| {
                // Mostly its own prompt, a little of the wall's.
                let mut v = unit(*k, dim);
                v[0] += 0.2;
                v
            })
            .collect();
        sam::write_features_npy(&scene.join(format!("features/{STEM}.npy")), dim, &feats).unwrap();
        let prompts = Prompts {
            simulated: false,
            dim,
            prompts: PROMPTS
                .iter()
                .enumerate()
                .map(|(i, (t, _))| (t.to_string(), unit(i, dim)))
                .collect(),
            classes: PROMPTS
                .iter()
                .filter(|(t, _)| *t != "a tree")
                .map(|(t, c)| (t.to_string(), *c))
                .collect(),
        };
        sam::write_prompts_json(&scene.join("features/prompts.json"), &prompts).unwrap();
    }
    // Raycast: feature/surface/part/city ids and the city z-depth (wall 10, window 10).
    let raycast = root.join("raycast");
    std::fs::create_dir_all(&raycast).unwrap();
    let mut ids = vec![-1i32; 4 * H * W];
    let mut depth = vec![f32::NAN; H * W];
    for y in 0..H {
        for x in 0..W {
            if in_rect(y, x, BUILDING) {
                let p = y * W + x;
                let part = if in_rect(y, x, WINDOW_R) { 2 } else { -1 };
                ids[p] = 0;
                ids[H * W + p] = 1;
                ids[2 * H * W + p] = part;
                ids[3 * H * W + p] = if part >= 0 { part } else { 1 };
                depth[p] = 10.0;
            }
        }
    }
    npy::write(&raycast.join(format!("{STEM}.ids.npy")), &[4, H, W], &ids).unwrap();
    npy::write(&raycast.join(format!("{STEM}.depth.npy")), &[H, W], &depth).unwrap();
    // The contributions cache.
    let cache = root.join("cache");
    std::fs::create_dir_all(&cache).unwrap();
    let mut offsets = vec![0u64];
    let (mut lids, mut lw, mut alpha, mut edepth) = (vec![], vec![], vec![], vec![]);
    for y in 0..H {
        for x in 0..W {
            let l = pixel_list(y, x);
            let a: f32 = l.iter().map(|e| e.1).sum();
            let zs: f32 = l.iter().map(|e| e.1 * Z[e.0 as usize]).sum();
            alpha.push(a);
            edepth.push(if a >= 1e-3 { zs / a } else { f32::NAN });
            for (i, w) in l {
                lids.push(i);
                lw.push(w);
            }
            offsets.push(lids.len() as u64);
        }
    }
    let vc = ViewContrib {
        width: W,
        height: H,
        k: 16,
        gaussians: n,
        lists: Contributions {
            offsets,
            ids: lids,
            weights: lw,
            residual: vec![0.0; H * W],
        },
        alpha,
        depth: edepth,
        median: Vec::new(),
    };
    vc.write(&gs4city::cache::cache_file(&cache, STEM)).unwrap();
    let summary = CacheSummary {
        gaussians: n,
        skipped_gaussians: 0,
        options: CacheOptions {
            top_k: 16,
            epsilon: 0.0,
            t_stop: 0.0,
            alpha_min: gs4city::cache::INRIA_ALPHA_MIN,
        },
        median_depth: false,
        views: vec![CachedView {
            name: format!("{STEM}.png"),
            stem: STEM.into(),
            width: W,
            height: H,
            entries: vc.entries() as u64,
            mean_list: 1.0,
            mean_dropped_share: 0.0,
            coverage: 1.0,
            bytes: vc.file_bytes() as u64,
            render_s: 0.0,
        }],
        selection: None,
        bytes: vc.file_bytes() as u64,
        render_s: 0.0,
        write_s: 0.0,
        total_s: 0.0,
    };
    gs4city::fsutil::write_json(&cache.join("summary.json"), &summary).unwrap();
    Fixture {
        _tmp: tmp,
        scene,
        raycast,
        cache,
        root,
    }
}

fn opts(test: Test) -> MasksOptions {
    MasksOptions {
        test,
        // τ_a = ⌈0.004·600⌉ = 3 pixels: the one-pixel speck fails it, the 6-pixel blob passes.
        area_frac: 0.004,
        overlays: 1,
        ..Default::default()
    }
}

fn run(
    f: &Fixture,
    o: &MasksOptions,
    out: &str,
    cache: bool,
) -> Result<MasksSummary, masks::MasksError> {
    let scene = Scene::open(&f.scene).unwrap();
    let c = Cache::open(&f.cache).unwrap();
    masks::run(
        &MasksInputs {
            scene: &scene,
            views: &[view()],
            raycast: &f.raycast,
            cache: cache.then_some(&c),
            alignment_scale: 1.0,
        },
        o,
        &f.root.join(out),
    )
}

/// `(source_index → rule)` and the kept set.
fn rules(f: &Fixture, out: &str) -> (BTreeMap<i64, String>, Vec<KeptMask>) {
    let d = gs4city::maskfile::read_decisions(&gs4city::maskfile::decisions_file(
        &f.root.join(out),
        STEM,
    ))
    .unwrap();
    let kept = gs4city::maskfile::read_kept(&gs4city::maskfile::kept_file(&f.root.join(out), STEM))
        .unwrap();
    (
        d.into_iter()
            .map(|d| (d.source_index, d.rule.name().to_string()))
            .collect(),
        kept,
    )
}

fn expect(f: &Fixture, out: &str, want: &[&str]) -> Vec<KeptMask> {
    let (r, kept) = rules(f, out);
    let got: Vec<&str> = r.values().map(String::as_str).collect();
    assert_eq!(got, want, "{out}");
    kept
}

#[test]
fn geometry_test_keeps_the_person_and_road_and_drops_wall_window_and_veil() {
    let f = fixture("geometry", false);
    let s = run(&f, &opts(Test::Geometry), "geo", true).unwrap();
    assert_eq!(
        (s.source, s.test, s.features),
        (Source::Sam, Test::Geometry, false)
    );
    let kept = expect(
        &f,
        "geo",
        &[
            "on_surface",  // wall
            "on_surface",  // window: 3DGS 0.15 m behind its polygon
            "occluder",    // person: 3 m in front
            "on_surface",  // veil: median depth is the wall's
            "low_overlap", // road
            "quality",
            "area",
            "on_surface", // wall blob
        ],
    );
    assert_eq!(
        kept.iter()
            .map(|k| (k.source_index, k.class))
            .collect::<Vec<_>>(),
        vec![(2, -1), (4, -1)]
    );
    // R_ov by construction: person 1, road 0.
    assert_eq!(kept[0].r_ov, 1.0);
    assert_eq!(kept[1].r_ov, 0.0);
    assert_eq!(s.rules["on_surface"], 4);
    assert_eq!(s.overlays, vec![format!("overlay_{STEM}.png")]);
    assert!(f.root.join("geo").join(&s.overlays[0]).is_file());
}

#[test]
fn expected_depth_is_fooled_by_the_veil_and_the_median_is_not() {
    let f = fixture("expected", false);
    let o = MasksOptions {
        gs_depth: GsDepth::Expected,
        ..opts(Test::Geometry)
    };
    run(&f, &o, "exp", true).unwrap();
    let (r, _) = rules(&f, "exp");
    // Expected depth ≈ 7.25 m, 2.75 m in front of the wall.
    assert_eq!(r[&3], "occluder");
    assert_eq!(r[&2], "occluder");
    assert_eq!(r[&1], "on_surface");
}

#[test]
fn a_larger_tolerance_makes_the_person_part_of_the_surface() {
    let f = fixture("tau", false);
    let o = MasksOptions {
        tau_occ_m: 3.5,
        ..opts(Test::Geometry)
    };
    run(&f, &o, "tau", true).unwrap();
    assert_eq!(rules(&f, "tau").0[&2], "on_surface");
    // The alignment scale multiplies τ_occ: 1.0 m × 4 = 4 m > 3 m.
    let scene = Scene::open(&f.scene).unwrap();
    let c = Cache::open(&f.cache).unwrap();
    let o = MasksOptions {
        tau_occ_m: 1.0,
        ..opts(Test::Geometry)
    };
    let s = masks::run(
        &MasksInputs {
            scene: &scene,
            views: &[view()],
            raycast: &f.raycast,
            cache: Some(&c),
            alignment_scale: 4.0,
        },
        &o,
        &f.root.join("scaled"),
    )
    .unwrap();
    assert_eq!(s.tau_occ, 4.0);
    assert_eq!(rules(&f, "scaled").0[&2], "on_surface");
}

#[test]
fn features_test_is_the_papers_rule_with_classes_from_the_prompts() {
    let f = fixture("features", true);
    let s = run(&f, &opts(Test::Features), "feat", false).unwrap();
    assert!(s.features);
    let tree = s.prompts.iter().find(|p| p.text == "a tree").unwrap();
    assert_eq!((tree.class, tree.from.as_str()), (6, "keyword"));
    let kept = expect(
        &f,
        "feat",
        &[
            "features_building",
            "features_building",
            "features_foreground",
            "features_foreground", // the veil region looks like a tree
            "low_overlap",
            "quality",
            "area",
            "features_building",
        ],
    );
    assert_eq!(
        kept.iter()
            .map(|k| (k.source_index, k.class))
            .collect::<Vec<_>>(),
        vec![(2, 7), (3, 6), (4, 9)]
    );
    // Scores: feature (0.2, 0, 1, 0, 0)/|·| of the person: S_fore = 1/√1.04, S_city = 0.2/√1.04.
    let d = gs4city::maskfile::read_decisions(&gs4city::maskfile::decisions_file(
        &f.root.join("feat"),
        STEM,
    ))
    .unwrap();
    let n = 1.04f64.sqrt();
    assert!((d[2].scores["s_fore"] - 1.0 / n).abs() < 1e-6);
    assert!((d[2].scores["s_city"] - 0.2 / n).abs() < 1e-6);
    assert!((d[2].scores["class_margin"] - 0.8 / n).abs() < 1e-6);
}

#[test]
fn both_keeps_what_the_depth_and_the_features_agree_on() {
    let f = fixture("both", true);
    let mut o = opts(Test::Auto);
    o.low_overlap_check = true;
    let s = run(&f, &o, "both", true).unwrap();
    assert_eq!(s.test, Test::Both);
    expect(
        &f,
        "both",
        &[
            "on_surface",
            "on_surface",
            "occluder_and_features",
            "on_surface", // features say tree, the depth says wall: dropped
            "low_overlap",
            "quality",
            "area",
            "on_surface",
        ],
    );
    // Auto without a cache falls back to the features alone.
    let s = run(&f, &opts(Test::Auto), "auto_nocache", false).unwrap();
    assert_eq!(s.test, Test::Features);
}

#[test]
fn low_overlap_check_drops_a_low_overlap_building_mask() {
    // A mask half on the wall (R_ov 0.5 < ρ) and half on the empty right side.
    let f = fixture("lowcheck", true);
    let m = Array2::from_shape_fn((H, W), |(y, x)| y < 4 && (16..24).contains(&x));
    let mut list = sam::read_sam_json(&f.scene.join(format!("masks/{STEM}.json"))).unwrap();
    list[7] = SamMask::from_mask(&m, 0.9, 0.97, vec![]);
    write_sam_json(&f.scene.join(format!("masks/{STEM}.json")), &list).unwrap();
    let mut o = opts(Test::Geometry);
    o.low_overlap_check = false; // the paper's rule
    run(&f, &o, "nocheck", true).unwrap();
    assert_eq!(rules(&f, "nocheck").0[&7], "low_overlap");
    o.low_overlap_check = true;
    run(&f, &o, "check", true).unwrap();
    let (r, _) = rules(&f, "check");
    assert_eq!(r[&7], "low_overlap_building");
    assert_eq!(r[&4], "low_overlap", "the road has no depth evidence: kept");
}

#[test]
fn mask_free_source_finds_the_person_as_one_component() {
    let f = fixture("maskfree", false);
    std::fs::remove_dir_all(f.scene.join("masks")).unwrap();
    let o = MasksOptions {
        open_px: 0,
        ..opts(Test::Auto)
    };
    let s = run(&f, &o, "free", true).unwrap();
    assert_eq!(s.source, Source::Depth);
    let (_, kept) = rules(&f, "free");
    assert_eq!(kept.len(), 1, "{kept:?}");
    let k = &kept[0];
    assert_eq!(
        (k.source_index, k.rule.name(), k.class),
        (-1, "depth_component", -1)
    );
    assert_eq!(k.sam.segmentation.decode().unwrap(), mask_of(PERSON_R));
    // The default opening (radius 3, a 7×7 ellipse) removes anything thinner than 7 pixels:
    // the 5-pixel-wide person too.
    let s = run(&f, &opts(Test::Auto), "free_open", true).unwrap();
    assert_eq!(s.kept, 0);
    // Without a cache the mask-free source refuses clearly.
    let e = run(&f, &opts(Test::Auto), "free2", false)
        .unwrap_err()
        .to_string();
    assert!(e.contains("--cache"), "{e}");
}

fn strip_timing(v: &mut serde_json::Value) {
    if let Some(o) = v.as_object_mut() {
        o.remove("timing");
        o.remove("seconds");
        for (_, x) in o.iter_mut() {
            strip_timing(x);
        }
    } else if let Some(a) = v.as_array_mut() {
        a.iter_mut().for_each(strip_timing);
    }
}

fn folder_bytes(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        let mut b = std::fs::read(&p).unwrap();
        if name == "summary.json" {
            let mut v: serde_json::Value = serde_json::from_slice(&b).unwrap();
            strip_timing(&mut v);
            b = serde_json::to_vec(&v).unwrap();
        }
        out.insert(name, b);
    }
    out
}

#[test]
fn outputs_are_identical_without_the_simulation_truth() {
    let f = fixture("truth", true);
    // Simulation truth and evaluation files the stage must never read.
    std::fs::create_dir_all(f.scene.join("gt")).unwrap();
    std::fs::write(f.scene.join("gt/v0.class.npy"), b"garbage").unwrap();
    std::fs::write(f.scene.join("masks/v0.sim.json"), b"[{\"index\": 0}]").unwrap();
    std::fs::write(f.scene.join("masks/README.json"), b"{\"simulated\": true}").unwrap();
    std::fs::write(f.scene.join("summary.json"), b"{}").unwrap();
    let mut o = opts(Test::Both);
    o.low_overlap_check = true;
    run(&f, &o, "with", true).unwrap();
    for p in [
        "gt",
        "masks/v0.sim.json",
        "masks/README.json",
        "summary.json",
    ] {
        let p = f.scene.join(p);
        if p.is_dir() {
            std::fs::remove_dir_all(p).unwrap();
        } else {
            std::fs::remove_file(p).unwrap();
        }
    }
    run(&f, &o, "without", true).unwrap();
    let (a, b) = (
        folder_bytes(&f.root.join("with")),
        folder_bytes(&f.root.join("without")),
    );
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    assert!(a.len() >= 4, "{:?}", a.keys());
    for (k, v) in &a {
        assert!(v == &b[k], "{k} differs");
    }
}

fn err(f: &Fixture, test: Test, cache: bool) -> String {
    run(f, &opts(test), "err", cache).unwrap_err().to_string()
}

#[test]
fn a_sam_list_of_another_size_is_an_error_naming_the_file() {
    let f = fixture("badsize", false);
    let m = Array2::from_elem((H + 1, W), true);
    write_sam_json(
        &f.scene.join(format!("masks/{STEM}.json")),
        &[SamMask::from_mask(&m, 0.9, 0.9, vec![])],
    )
    .unwrap();
    let e = err(&f, Test::Geometry, true);
    assert!(
        e.contains("masks/v0.json") && e.contains("image size"),
        "{e}"
    );
}

#[test]
fn features_with_the_wrong_rows_or_dimension_are_errors_naming_the_file() {
    let f = fixture("badfeat", true);
    let path = f.scene.join(format!("features/{STEM}.npy"));
    sam::write_features_npy(&path, PROMPTS.len(), &vec![vec![1.0; PROMPTS.len()]; 3]).unwrap();
    let e = err(&f, Test::Features, false);
    assert!(
        e.contains("features/v0.npy") && e.contains("3 feature rows") && e.contains("8 masks"),
        "{e}"
    );
    sam::write_features_npy(&path, 4, &vec![vec![1.0; 4]; 8]).unwrap();
    let e = err(&f, Test::Features, false);
    assert!(
        e.contains("features/v0.npy") && e.contains("dimension 4") && e.contains("prompts.json"),
        "{e}"
    );
    npy::write(&path, &[8], &[0.0f32; 8]).unwrap();
    let e = err(&f, Test::Features, false);
    assert!(
        e.contains("features/v0.npy") && e.contains("not 2-D"),
        "{e}"
    );
    let mut bad = vec![vec![0.0; PROMPTS.len()]; 8];
    bad[5][1] = f32::NAN;
    sam::write_features_npy(&path, PROMPTS.len(), &bad).unwrap();
    let e = err(&f, Test::Features, false);
    assert!(e.contains("features/v0.npy") && e.contains("row 5"), "{e}");
}

#[test]
fn prompts_of_another_dimension_are_an_error_naming_the_file() {
    let f = fixture("badprompts", true);
    let path = f.scene.join("features/prompts.json");
    let mut p = sam::read_prompts_json(&path).unwrap();
    p.prompts.insert("a car".into(), vec![1.0, 0.0, 0.0]);
    sam::write_prompts_json(&path, &p).unwrap();
    let e = err(&f, Test::Features, false);
    assert!(
        e.contains("prompts.json") && e.contains("\"a car\"") && e.contains("has 3 values"),
        "{e}"
    );
    // A consistent file of another dimension than the features.
    p.prompts = p
        .prompts
        .into_iter()
        .map(|(t, mut v)| {
            v.resize(7, 0.0);
            (t, v)
        })
        .collect();
    p.dim = 7;
    sam::write_prompts_json(&path, &p).unwrap();
    let e = err(&f, Test::Features, false);
    assert!(
        e.contains("features/v0.npy") && e.contains("dimension 5") && e.contains("dimension 7"),
        "{e}"
    );
}

#[test]
fn other_bad_inputs_are_refused_clearly() {
    let f = fixture("badother", true);
    // The depth test without a cache.
    let e = err(&f, Test::Geometry, false);
    assert!(e.contains("--cache"), "{e}");
    // Raycast ids of another size.
    let ids = f.raycast.join(format!("{STEM}.ids.npy"));
    let good = std::fs::read(&ids).unwrap();
    npy::write(&ids, &[4, H, W + 1], &vec![-1i32; 4 * H * (W + 1)]).unwrap();
    let e = err(&f, Test::Features, false);
    assert!(e.contains("v0.ids.npy") && e.contains("[4, 20, 31]"), "{e}");
    std::fs::write(&ids, good).unwrap();
    // A missing SAM list while masks/ exists.
    std::fs::rename(
        f.scene.join(format!("masks/{STEM}.json")),
        f.scene.join("masks/other.json"),
    )
    .unwrap();
    let e = err(&f, Test::Features, false);
    assert!(e.contains("masks/v0.json") && e.contains("missing"), "{e}");
    // Options out of range.
    let o = MasksOptions {
        rho: 1.5,
        ..Default::default()
    };
    let e = run(&f, &o, "err", false).unwrap_err().to_string();
    assert!(e.contains("rho"), "{e}");
}

#[test]
fn kept_files_are_validated_on_reading() {
    let f = fixture("readkept", false);
    run(&f, &opts(Test::Geometry), "geo", true).unwrap();
    let path = gs4city::maskfile::kept_file(&f.root.join("geo"), STEM);
    let text = std::fs::read_to_string(&path).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v[0]["area"] = serde_json::json!(1);
    std::fs::write(&path, serde_json::to_vec(&v).unwrap()).unwrap();
    let e = gs4city::maskfile::read_kept(&path).unwrap_err().to_string();
    assert!(e.contains("v0.json") && e.contains("area"), "{e}");
}

#[test]
fn command_line_runs_and_refuses_the_depth_test_without_a_cache() {
    let f = fixture("cli", true);
    let bin = env!("CARGO_BIN_EXE_gs4city");
    let out = f.root.join("cli_out");
    let o = std::process::Command::new(bin)
        .args(["-q", "masks", "--scene"])
        .arg(&f.scene)
        .arg("--raycast")
        .arg(&f.raycast)
        .arg("--cache")
        .arg(&f.cache)
        .args(["--area-frac", "0.004", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let s = MasksSummary::read(&out).unwrap();
    assert_eq!((s.source, s.test), (Source::Sam, Test::Both));
    assert_eq!(
        s.kept,
        gs4city::maskfile::read_kept(&gs4city::maskfile::kept_file(&out, STEM))
            .unwrap()
            .len()
    );
    let o = std::process::Command::new(bin)
        .args(["-q", "masks", "--test", "geometry", "--scene"])
        .arg(&f.scene)
        .arg("--raycast")
        .arg(&f.raycast)
        .arg("--out")
        .arg(f.root.join("cli_err"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("--cache"), "{e}");
    assert!(!f.root.join("cli_err/summary.json").exists());
}

#[test]
fn a_low_quality_mask_that_passes_every_other_rule_is_support_only() {
    // τ_q = 0.93 fails the person (0.92), the veil (0.88), the window (0.9) and the wall blob
    // (0.9). Only the person would be kept by the rest (an occluder): it alone becomes
    // `low_quality_support`, and is still not kept. The others, and mask 5 (0.5, below the
    // floor 0.6), stay `quality`.
    let f = fixture("support-only", false);
    let o = MasksOptions {
        tau_q: 0.93,
        support_floor: Some(0.6),
        ..opts(Test::Geometry)
    };
    let s = run(&f, &o, "on", true).unwrap();
    let kept = expect(
        &f,
        "on",
        &[
            "on_surface",
            "quality",
            "low_quality_support",
            "quality",
            "low_overlap",
            "quality",
            "area",
            "quality",
        ],
    );
    assert_eq!(
        kept.iter().map(|k| k.source_index).collect::<Vec<_>>(),
        vec![4]
    );
    assert_eq!(s.rules["low_quality_support"], 1);
    // A floor above the person's quality, or none: `quality`, as in the paper.
    for (tag, floor) in [("high", Some(0.95)), ("none", None)] {
        let o = MasksOptions {
            support_floor: floor,
            ..o.clone()
        };
        run(&f, &o, tag, true).unwrap();
        let (r, _) = rules(&f, tag);
        assert_eq!(r[&2], "quality", "{tag}");
        assert!(!r.values().any(|v| v == "low_quality_support"), "{tag}");
    }
    // A floor outside [0, 1] is refused.
    let bad = MasksOptions {
        support_floor: Some(1.5),
        ..o
    };
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("support_floor")
    );
}

/// The version 4 cache: with the render stage's median-depth plane the stage reads only the
/// cache's planes and no Gaussian centres, and gives exactly the masks it gives from the lists
/// and the PLY's centres (a cache from before version 4); the PLY's header still tells a stale
/// cache.
#[test]
fn the_stored_median_plane_gives_the_masks_of_the_lists_and_the_centres() {
    let f = fixture("plane", true);
    let mut o = opts(Test::Both);
    o.low_overlap_check = true;
    run(&f, &o, "lists", true).unwrap();
    // The same view with its median plane, and a summary that says the cache has them.
    let file = gs4city::cache::cache_file(&f.cache, STEM);
    let mut c = ViewContrib::read(&file, None).unwrap();
    assert!(c.median.is_empty());
    let centres: Vec<[f32; 3]> = Z.iter().map(|&z| [0.0, 0.0, z]).collect();
    c.median = gs4city::cache::median_depth(&c, &centres, &view().camera.pose);
    assert!(c.median.iter().any(|m| m.is_finite()));
    c.write(&file).unwrap();
    let mut summary = Cache::open(&f.cache).unwrap().summary;
    summary.median_depth = true;
    summary.write(&f.cache).unwrap();
    // The PLY's centres moved 1 km away (same count): a stage that still read them for the
    // median would see every Gaussian far behind the city surface, and keep other masks.
    let ply = f.scene.join("point_cloud.ply");
    let (mut far, _) = gs4city::splat::read_ply(&ply, &gs4city::splat::ReadOptions::KEEP).unwrap();
    far.positions.iter_mut().for_each(|p| p[2] += 1000.0);
    gs4city::splat::write_ply(&ply, &far, PlyEncoding::BinaryLittleEndian).unwrap();
    run(&f, &o, "plane", true).unwrap();
    let (a, b) = (
        folder_bytes(&f.root.join("lists")),
        folder_bytes(&f.root.join("plane")),
    );
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (k, v) in &a {
        assert!(v == &b[k], "{k} differs");
    }
    // A PLY with another number of Gaussians: the cache is stale, named with the PLY.
    let one = Gaussians {
        positions: vec![[0.0, 0.0, 5.0]],
        normals: None,
        sh_degree: 0,
        f_dc: vec![[0.5; 3]],
        f_rest: vec![],
        opacity: vec![2.0],
        scale: vec![[-2.0; 3]],
        rotation: vec![[1.0, 0.0, 0.0, 0.0]],
        extras: vec![],
    };
    gs4city::splat::write_ply(&ply, &one, PlyEncoding::BinaryLittleEndian).unwrap();
    let e = run(&f, &o, "stale", true).unwrap_err().to_string();
    assert!(e.contains("point_cloud.ply") && e.contains("stale"), "{e}");
    // So does the expected depth of a cache from before version 4, which reads no centres.
    summary.median_depth = false;
    summary.write(&f.cache).unwrap();
    o.gs_depth = GsDepth::Expected;
    let e = run(&f, &o, "stale_expected", true).unwrap_err().to_string();
    assert!(e.contains("point_cloud.ply") && e.contains("stale"), "{e}");
}
