//! Raycasting benchmark (plain `Instant`): scene build, two-pass and single-pass rays/s at
//! 1 MP, time per 20 MP view, and Open3D `RaycastingScene` on the same mesh and rays
//! (via `python3 scripts/open3d_check.py DIR --bench`, same run); each packet width (8, 16
//! lanes) and Embree's high-quality BVH build, for comparison.
//! Run: `cargo bench --bench raycast`.
//!
//! `GS4CITY_RAYCAST_PROFILE=N cargo bench --bench raycast` traces only the 1 MP view, single
//! pass, N times after the scene build and stops (`N:two`: both passes): a steady window for
//! `perf record` (how much of a pass is Embree's traversal, how much is gs4city's ray setup
//! and id lookup).
#[path = "../tests/common/mod.rs"]
mod common;

use std::process::Command;
use std::time::Instant;

use gs4city::embree::PacketWidth;
use gs4city::raycast::{RaycastOptions, TwoPassScene, pixel_ray, raycast_view, raycast_view_with};

fn best_of<T>(n: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut last = None;
    for _ in 0..n {
        let t = Instant::now();
        let r = f();
        best = best.min(t.elapsed().as_secs_f64());
        last = Some(r);
    }
    (best, last.expect("n > 0"))
}

fn main() {
    let mesh = common::city_block(400, 8, 1);
    let parts = mesh.labels.iter().filter(|l| l.part != -1).count();
    println!(
        "mesh: {} triangles ({} part-level), {} vertices; threads: {}",
        mesh.faces.len(),
        parts,
        mesh.vertices.len(),
        rayon::current_num_threads()
    );
    let (build, scene) = best_of(3, || TwoPassScene::build(&mesh).expect("scene"));
    println!(
        "scene build (global + part, best of 3): {:.1} ms",
        build * 1e3
    );

    let two = RaycastOptions::default();
    let one = RaycastOptions {
        single_pass: true,
        ..two
    };
    let cam1 = common::orbit_camera(1280, 800, 1000.0, 0.4, 110.0, 30.0);
    let n1 = 1280.0 * 800.0;
    if let Ok(v) = std::env::var("GS4CITY_RAYCAST_PROFILE") {
        let (count, both) = match v.strip_suffix(":two") {
            Some(c) => (c, true),
            None => (v.as_str(), false),
        };
        let n: usize = count.parse().expect("GS4CITY_RAYCAST_PROFILE=N or N:two");
        let opts = if both { &two } else { &one };
        let t = Instant::now();
        let mut hits = 0usize;
        for _ in 0..n {
            let v = raycast_view(&scene, &cam1, opts);
            hits += v.face.iter().filter(|&&f| f >= 0).count();
        }
        let s = t.elapsed().as_secs_f64();
        println!(
            "profile: {n} {} 1 MP views in {s:.2} s = {:.2} Mrays/s ({hits} hits)",
            if both { "two-pass" } else { "single-pass" },
            n as f64 * n1 / s / 1e6
        );
        return;
    }
    let (t_two, v) = best_of(5, || raycast_view(&scene, &cam1, &two));
    let (t_one, _) = best_of(5, || raycast_view(&scene, &cam1, &one));
    let hits = v.face.iter().filter(|&&f| f >= 0).count();
    println!("native packet width: {:?}", scene.packet_width());
    for width in [PacketWidth::W8, PacketWidth::W16] {
        let (a, _) = best_of(5, || raycast_view_with(&scene, &cam1, &two, width));
        let (b, _) = best_of(5, || raycast_view_with(&scene, &cam1, &one, width));
        println!(
            "1 MP, {} lanes: two-pass {:.1} ms = {:.2} Mrays/s, single-pass {:.1} ms = {:.2} Mrays/s",
            width.lanes(),
            a * 1e3,
            n1 / a / 1e6,
            b * 1e3,
            n1 / b / 1e6
        );
    }
    let (build_hq, scene_hq) = best_of(3, || TwoPassScene::build_with(&mesh, true).expect("scene"));
    let (a, _) = best_of(5, || raycast_view(&scene_hq, &cam1, &two));
    let (b, _) = best_of(5, || raycast_view(&scene_hq, &cam1, &one));
    println!(
        "high-quality BVH: build {:.1} ms; 1 MP two-pass {:.1} ms = {:.2} Mrays/s, single-pass {:.1} ms = {:.2} Mrays/s",
        build_hq * 1e3,
        a * 1e3,
        n1 / a / 1e6,
        b * 1e3,
        n1 / b / 1e6
    );
    drop(scene_hq);
    println!(
        "1 MP (1280x800, {:.1} % hit): two-pass {:.1} ms = {:.2} Mrays/s (pixels), single-pass {:.1} ms = {:.2} Mrays/s; recovered parts {}",
        100.0 * hits as f64 / n1,
        t_two * 1e3,
        n1 / t_two / 1e6,
        t_one * 1e3,
        n1 / t_one / 1e6,
        v.recovered_parts()
    );

    let cam20 = common::orbit_camera(5280, 3956, 4000.0, 0.4, 110.0, 30.0);
    let (t20, v20) = best_of(1, || raycast_view(&scene, &cam20, &two));
    println!(
        "20 MP (5280x3956): two-pass {:.2} s per view = {:.2} Mrays/s (pixels); recovered pixels {}",
        t20,
        5280.0 * 3956.0 / t20 / 1e6,
        v20.recovered_pixels()
    );
    drop(v20);

    // Open3D on the same mesh and the same 1 MP rays.
    let dir = std::env::temp_dir().join(format!("gs4city-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp dir");
    let mut rays: Vec<f32> = Vec::with_capacity(6 * 1280 * 800);
    for j in 0..800 {
        for i in 0..1280 {
            let (o, d, _) = pixel_ray(&cam1, i, j).expect("pinhole");
            rays.extend(o.iter().chain(&d));
        }
    }
    let w = |name: &str, shape: &[usize], data: &[i32]| {
        gs4city::npy::write(&dir.join(name), shape, data).expect("npy")
    };
    let flat_v: Vec<f32> = mesh.vertices.iter().flatten().copied().collect();
    gs4city::npy::write(
        &dir.join("vertices.npy"),
        &[mesh.vertices.len(), 3],
        &flat_v,
    )
    .expect("npy");
    let flat_f: Vec<i32> = mesh.faces.iter().flatten().map(|&i| i as i32).collect();
    w("faces.npy", &[mesh.faces.len(), 3], &flat_f);
    let feat: Vec<i32> = mesh.labels.iter().map(|l| l.feature).collect();
    w("feature.npy", &[mesh.faces.len()], &feat);
    gs4city::npy::write(&dir.join("rays.npy"), &[1280 * 800, 6], &rays).expect("npy");
    w("rust_face.npy", &[1280 * 800], &v.face);
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/open3d_check.py");
    match Command::new("python3")
        .arg(script)
        .arg(&dir)
        .arg("--bench")
        .output()
    {
        Ok(out) if out.status.success() => {
            let text = String::from_utf8_lossy(&out.stdout);
            print!("open3d: {text}");
            let get = |key: &str| {
                text.lines()
                    .find_map(|l| l.strip_prefix(key))
                    .and_then(|s| s.trim().parse::<f64>().ok())
            };
            if let Some(t) = get("open3d_seconds") {
                println!(
                    "Open3D cast_rays 1 MP (best of 3): {:.1} ms = {:.2} Mrays/s; gs4city two-pass / Open3D = {:.2}x, single-pass / Open3D = {:.2}x",
                    t * 1e3,
                    n1 / t / 1e6,
                    t / t_two,
                    t / t_one
                );
            }
        }
        Ok(out) => println!(
            "open3d check failed: {}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
        Err(e) => println!("python3 not runnable: {e}"),
    }
    let _ = std::fs::remove_dir_all(&dir);
}
