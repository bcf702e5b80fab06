//! Two-pass raycasting on hand-built scenes with exactly predictable pixels.
//!
//! The camera sits at the origin looking along +z (x right, y down), 100×100 px, f = 50,
//! principal point (50, 50). Pixel index `i` casts through `i + 0.5`, so a plane at depth
//! `z` covers `|x| < X` exactly for `|i + 0.5 − 50| < 50·X/z`.

use crate::common::*;
use gs4city::mesh::TriMesh;
use gs4city::raycast::{Overlays, RaycastOptions, TwoPassScene, ViewIds, raycast_view};

const WALL: (i32, i32, i32) = (0, 1, -1);

fn opts(tau: f64, single_pass: bool) -> RaycastOptions {
    RaycastOptions { tau, single_pass }
}

fn cast(m: &TriMesh, o: RaycastOptions) -> ViewIds {
    let scene = TwoPassScene::build(m).unwrap();
    raycast_view(&scene, &axis_camera(100, 100, 50.0), &o)
}

fn at(v: &ViewIds, i: usize, j: usize) -> (i32, i32, i32, i32, f32) {
    let p = j * v.width + i;
    (v.feature[p], v.surface[p], v.part[p], v.city[p], v.depth[p])
}

/// Wall at z = 10 over [−5,5]² (pixels 25..=74) with label WALL.
fn wall(m: &mut TriMesh) {
    zquad(
        m,
        [-5.0, 5.0],
        [-5.0, 5.0],
        10.0,
        label(WALL.0, WALL.1, WALL.2),
    );
}

fn in_r(i: usize, r: std::ops::RangeInclusive<usize>) -> bool {
    r.contains(&i)
}

fn assert_invariants(v: &ViewIds) {
    for p in 0..v.width * v.height {
        assert_eq!(v.face[p] >= 0, v.depth[p].is_finite(), "pixel {p}");
        if v.face[p] < 0 {
            assert_eq!(
                (v.feature[p], v.surface[p], v.part[p], v.city[p]),
                (-1, -1, -1, -1)
            );
        } else {
            assert!(v.depth[p] > 0.0);
        }
    }
}

#[test]
fn coplanar_window_in_unholed_wall_is_recovered_by_the_part_pass() {
    let mut m = TriMesh::default();
    wall(&mut m);
    // Window exactly in the wall plane over [−1,1]²: pixels 45..=54.
    zquad(&mut m, [-1.0, 1.0], [-1.0, 1.0], 10.0, label(0, 1, 2));
    let two = cast(&m, opts(0.5, false));
    let one = cast(&m, opts(0.5, true));
    assert_invariants(&two);
    assert_invariants(&one);
    for j in 0..100 {
        for i in 0..100 {
            let (f, s, p, c, d) = at(&two, i, j);
            let on_wall = in_r(i, 25..=74) && in_r(j, 25..=74);
            let on_win = in_r(i, 45..=54) && in_r(j, 45..=54);
            if !on_wall {
                assert_eq!((f, s, p, c), (-1, -1, -1, -1), "({i},{j})");
                assert!(d.is_nan());
                continue;
            }
            assert_eq!((f, s), (0, 1), "({i},{j})");
            assert!((d - 10.0).abs() < 1e-4, "({i},{j}) depth {d}");
            let expect = if on_win { (2, 2) } else { (-1, 1) };
            assert_eq!((p, c), expect, "({i},{j})");
            // Single pass: same surface, part only where the z-fight went to the window.
            let (_, s1, p1, _, _) = at(&one, i, j);
            assert_eq!(s1, 1);
            assert!(p1 == -1 || (on_win && p1 == 2));
        }
    }
    assert_eq!(two.part_pixels(), 100);
    let single_parts = one.part_pixels();
    assert_eq!(two.recovered_pixels(), 100 - single_parts);
}

#[test]
fn recessed_window_accepted_within_tau_rejected_beyond() {
    let mut m = TriMesh::default();
    wall(&mut m);
    // 0.3 behind the wall: |i + 0.5 − 50| < 50/10.3 = 4.85 → pixels 45..=54.
    zquad(&mut m, [-1.0, 1.0], [-1.0, 1.0], 10.3, label(0, 1, 2));
    let ok = cast(&m, opts(0.5, false));
    let no = cast(&m, opts(0.2, false));
    for j in 25..=74 {
        for i in 25..=74 {
            let on_win = in_r(i, 45..=54) && in_r(j, 45..=54);
            let (_, s, p, c, d) = at(&ok, i, j);
            assert_eq!(s, 1);
            assert!((d - 10.0).abs() < 1e-4, "depth is the global (wall) depth");
            assert_eq!((p, c), if on_win { (2, 2) } else { (-1, 1) }, "({i},{j})");
            assert_eq!(at(&no, i, j).2, -1, "τ = 0.2 < gap 0.3 rejects ({i},{j})");
        }
    }
    assert_eq!((ok.recovered_pixels(), ok.recovered_parts()), (100, 1));
    assert_eq!((no.recovered_pixels(), no.part_pixels()), (0, 0));
}

#[test]
fn window_of_another_wall_is_rejected_by_the_parent_check() {
    let mut m = TriMesh::default();
    // Wall A (surface 1) covers the left half at z = 10; wall B (surface 3) spans the whole
    // width at z = 10.2 with a coplanar window (part 4) over [−2,2]²: at z = 10.2 that is
    // |i + 0.5 − 50| < 9.8 → pixels 40..=59. Left of centre (i ≤ 49) wall A hides it with a
    // depth gap of only 0.2 < τ, but the parent surfaces differ.
    zquad(&mut m, [-5.0, 0.0], [-5.0, 5.0], 10.0, label(0, 1, -1));
    zquad(&mut m, [-5.0, 5.0], [-5.0, 5.0], 10.2, label(0, 3, -1));
    zquad(&mut m, [-2.0, 2.0], [-2.0, 2.0], 10.2, label(0, 3, 4));
    let v = cast(&m, opts(0.5, false));
    assert_invariants(&v);
    for j in 40..=59 {
        for i in 40..=59 {
            let (_, s, p, c, _) = at(&v, i, j);
            if i <= 49 {
                assert_eq!((s, p, c), (1, -1, 1), "({i},{j}) behind wall A");
            } else {
                assert_eq!((s, p, c), (3, 4, 4), "({i},{j}) through the gap");
            }
        }
    }
    assert_eq!(v.part_pixels(), 10 * 20);
}

#[test]
fn occluding_box_in_front_of_the_facade_wins() {
    let mut m = TriMesh::default();
    wall(&mut m);
    zquad(&mut m, [-1.0, 1.0], [-1.0, 1.0], 10.0, label(0, 1, 2));
    // Box (feature 9, no surface) at z ∈ [5, 6], |x|,|y| < 0.3: front face covers
    // |i + 0.5 − 50| < 3 → pixels 47..=52.
    aabox(&mut m, [-0.3, -0.3, 5.0], [0.3, 0.3, 6.0], label(9, -1, -1));
    let v = cast(&m, opts(0.5, false));
    assert_invariants(&v);
    for j in 45..=54 {
        for i in 45..=54 {
            let (f, s, p, c, d) = at(&v, i, j);
            if in_r(i, 47..=52) && in_r(j, 47..=52) {
                assert_eq!((f, s, p, c), (9, -1, -1, 9), "({i},{j}) box");
                assert!((d - 5.0).abs() < 1e-4);
            } else {
                assert_eq!((f, s, p, c), (0, 1, 2, 2), "({i},{j}) window");
            }
        }
    }
    assert_eq!(v.part_pixels(), 100 - 36);
}

#[test]
fn grazing_rays_along_a_wall_give_ids_or_clean_misses() {
    let mut m = TriMesh::default();
    // A wall through the camera centre containing the optical axis (x = 0): every ray
    // meets its plane only at the camera centre, outside the wall (z ≥ 0.5).
    quad(
        &mut m,
        [
            [0.0, -50.0, 0.5],
            [0.0, -50.0, 100.0],
            [0.0, 50.0, 100.0],
            [0.0, 50.0, 0.5],
        ],
        label(5, 6, -1),
    );
    // A parallel wall 1 cm to the right: column i = 50 (x/z = 0.01) meets it at z = 1;
    // column 51 (x/z = 0.03) would at z = 0.33 < 0.5. Only column 50 hits.
    quad(
        &mut m,
        [
            [0.01, -50.0, 0.5],
            [0.01, -50.0, 100.0],
            [0.01, 50.0, 100.0],
            [0.01, 50.0, 0.5],
        ],
        label(0, 1, 7),
    );
    let v = cast(&m, opts(0.5, false));
    assert_invariants(&v);
    for j in 0..100 {
        for i in 0..100 {
            let (f, s, p, c, d) = at(&v, i, j);
            if i == 50 {
                assert_eq!((f, s, p, c), (0, 1, 7, 7), "({i},{j})");
                assert!((d - 1.0).abs() < 1e-4, "({i},{j}) depth {d}");
            } else {
                assert_eq!(c, -1, "({i},{j})");
            }
        }
    }
}

#[test]
fn utm_coordinates_after_alignment_lose_no_precision() {
    // The coplanar-window scene placed at UTM coordinates, then aligned (origin subtracted
    // in f64 before the f32 conversion) must give exactly the near-origin result.
    let origin = [691_234.37_f64, 5_336_789.91, 512.27];
    let local = {
        let mut m = TriMesh::default();
        wall(&mut m);
        zquad(&mut m, [-1.0, 1.0], [-1.0, 1.0], 10.0, label(0, 1, 2));
        m
    };
    let geo: Vec<[f64; 3]> = local
        .vertices
        .iter()
        .map(|v| std::array::from_fn(|k| f64::from(v[k]) + origin[k]))
        .collect();
    let aligned = TriMesh {
        vertices: geo
            .iter()
            .map(|g| std::array::from_fn(|k| (g[k] - origin[k]) as f32))
            .collect(),
        ..local.clone()
    };
    // Control: storing the UTM coordinates directly in f32 would move vertices by > 1 cm.
    let naive_err = geo
        .iter()
        .flat_map(|g| (0..3).map(move |k| ((g[k] as f32) as f64 - g[k]).abs()))
        .fold(0.0, f64::max);
    assert!(naive_err > 0.01, "naive f32 error {naive_err}");
    let a = cast(&aligned, opts(0.5, false));
    let b = cast(&local, opts(0.5, false));
    assert_eq!(
        (&a.feature, &a.surface, &a.part, &a.city),
        (&b.feature, &b.surface, &b.part, &b.city)
    );
    assert_eq!(a.part_pixels(), 100);
    let bits = |v: &ViewIds| v.depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a), bits(&b));
}

#[test]
fn same_output_for_one_and_two_threads_and_distorted_cameras_work() {
    let m = city_block(12, 4, 7);
    let scene = TwoPassScene::build(&m).unwrap();
    let mut cam = orbit_camera(123, 77, 90.0, 0.7, 120.0, 20.0);
    cam.intrinsics.distortion = gs4city::camera::Distortion::OpenCv {
        k1: -0.1,
        k2: 0.01,
        p1: 1e-3,
        p2: 0.0,
    };
    let o = opts(0.5, false);
    let run = |threads| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| raycast_view(&scene, &cam, &o))
    };
    let (a, b) = (run(1), run(2));
    assert_eq!((&a.face, &a.city, &a.part), (&b.face, &b.city, &b.part));
    let bits = |v: &ViewIds| v.depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a), bits(&b));
    assert_invariants(&a);
    assert_eq!(a.undistort_failures, 0);
    assert!(a.face.iter().filter(|&&f| f >= 0).count() > 123 * 77 / 2);
    // Packets agree with single rays (global pass) on every pixel's surface (the faces
    // themselves may differ where coplanar window and wall faces tie).
    let surf = |f: i32| {
        if f < 0 {
            -2
        } else {
            m.labels[f as usize].surface
        }
    };
    let mut differ = 0;
    for j in 0..77 {
        for i in 0..123 {
            let (o, d, _) = gs4city::raycast::pixel_ray(&cam, i, j).unwrap();
            let single = scene.trace_global(o, d).map_or(-1, |(f, _)| f as i32);
            differ += usize::from(surf(single) != surf(a.face[j * 123 + i]));
        }
    }
    assert!(
        differ <= 2,
        "{differ} pixels differ between packets and single rays"
    );
}

#[test]
fn bad_inputs_are_errors() {
    let mut m = TriMesh::default();
    wall(&mut m);
    let mut bad = m.clone();
    bad.faces[0][1] = 99;
    assert!(TwoPassScene::build(&bad).is_err());
    let mut bad = m.clone();
    bad.labels.pop();
    assert!(TwoPassScene::build(&bad).is_err());
    let mut bad = m.clone();
    bad.vertices[0][2] = f32::INFINITY;
    assert!(TwoPassScene::build(&bad).is_err());
    // An empty mesh builds and hits nothing: every pixel unlabelled, NaN depth, nothing
    // recovered; a single ray misses too.
    let empty = TwoPassScene::build(&TriMesh::default()).unwrap();
    let v = raycast_view(&empty, &axis_camera(12, 8, 10.0), &opts(0.5, false));
    assert_eq!((v.width, v.height), (12, 8));
    for ids in [&v.feature, &v.surface, &v.part, &v.city, &v.face] {
        assert_eq!(ids, &vec![-1; 96]);
    }
    assert!(v.depth.iter().all(|d| d.is_nan()));
    assert!(v.recovered.iter().all(|r| !r) && v.undistort_failures == 0);
    assert_eq!(empty.trace_global([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]), None);

    let out = crate::common::temp_dir().join(format!("gs4city-rc-bad-{}", std::process::id()));
    let view = |w| gs4city::camera::View {
        image_id: 1,
        camera_id: 1,
        name: "a.png".into(),
        camera: axis_camera(w, 10, 5.0),
    };
    for tau in [f64::NAN, -1.0, f64::INFINITY] {
        assert!(
            gs4city::raycast::run(&m, &[view(10)], &opts(tau, false), Overlays::Off, &out).is_err()
        );
    }
    let e =
        gs4city::raycast::run(&m, &[view(0)], &opts(0.5, false), Overlays::Off, &out).unwrap_err();
    assert!(e.to_string().contains("a.png"), "{e}");
    let e = gs4city::raycast::run(
        &m,
        &[view(10), view(10)],
        &opts(0.5, false),
        Overlays::Off,
        &out,
    )
    .unwrap_err();
    assert!(e.to_string().contains("stem"), "{e}");
}

#[test]
fn run_writes_ids_depth_overlay_and_summary() {
    let mut m = TriMesh::default();
    wall(&mut m);
    zquad(&mut m, [-1.0, 1.0], [-1.0, 1.0], 10.3, label(0, 1, 2));
    let out = crate::common::temp_dir().join(format!("gs4city-rc-run-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let views = vec![gs4city::camera::View {
        image_id: 3,
        camera_id: 1,
        name: "sub/DJI_0001.JPG".into(),
        camera: axis_camera(100, 100, 50.0),
    }];
    let s = gs4city::raycast::run(&m, &views, &opts(0.5, false), Overlays::On(None), &out).unwrap();
    assert_eq!((s.views, s.rays, s.faces, s.part_faces), (1, 10_000, 4, 2));
    assert_eq!(s.per_view[0].recovered_pixels, 100);
    assert_eq!(s.per_view[0].recovered_parts, 1);
    assert_eq!(s.per_view[0].hit_pixels, 2500);
    let (shape, ids) = gs4city::npy::read::<i32>(&out.join("DJI_0001.ids.npy")).unwrap();
    assert_eq!(shape, [4, 100, 100]);
    let px = |ch: usize, i: usize, j: usize| ids[ch * 10_000 + j * 100 + i];
    assert_eq!(
        [px(0, 50, 50), px(1, 50, 50), px(2, 50, 50), px(3, 50, 50)],
        [0, 1, 2, 2]
    );
    assert_eq!([px(2, 30, 30), px(3, 30, 30)], [-1, 1]);
    assert_eq!(px(3, 0, 0), -1);
    let (shape, depth) = gs4city::npy::read::<f32>(&out.join("DJI_0001.depth.npy")).unwrap();
    assert_eq!(shape, [100, 100]);
    assert!(depth[0].is_nan() && (depth[50 * 100 + 50] - 10.0).abs() < 1e-4);
    let png = gs4city::imageio::read_rgb(&out.join("DJI_0001.overlay.png")).unwrap();
    assert_eq!(png.dim(), (100, 100, 3));
    assert_eq!(png[[0, 0, 0]], 0);
    assert!(png.slice(ndarray::s![50, 50, ..]).iter().any(|&c| c > 0));
    // Without overlays (what `gs4city run` asks for): the same maps, no picture.
    let off = out.with_extension("off");
    let _ = std::fs::remove_dir_all(&off);
    gs4city::raycast::run(&m, &views, &opts(0.5, false), Overlays::Off, &off).unwrap();
    for f in ["DJI_0001.ids.npy", "DJI_0001.depth.npy"] {
        assert_eq!(
            std::fs::read(off.join(f)).unwrap(),
            std::fs::read(out.join(f)).unwrap()
        );
    }
    assert!(!off.join("DJI_0001.overlay.png").exists());
}
