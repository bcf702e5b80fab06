//! Real inputs (`../shared/data/real/`): render time per view of the two real captured splat
//! scenes next to SIMULATED scenes of the same size, and `segment --semantic` (ESPNet, the
//! repository's `models/espnet/`) seconds per real Lund photo. `cargo bench --bench
//! real_inputs`; prints Markdown. Needs ONNX Runtime for the second part (skipped without).
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::DVec3;
use gs4city::camera::{Camera, Distortion, Intrinsics, Pose};
use gs4city::render::{PreparedScene, RenderOptions, render_view};
use gs4city::splat::{Gaussians, ReadOptions, read_ply};
use rand::{Rng, SeedableRng};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The robust centre and box (10–90 % per axis) of the Gaussians' centres.
fn extent(g: &Gaussians) -> (DVec3, DVec3, DVec3) {
    let q = |k: usize| {
        let mut v: Vec<f64> = g.positions.iter().map(|p| f64::from(p[k])).collect();
        v.sort_by(f64::total_cmp);
        (v[v.len() / 2], v[v.len() / 10], v[v.len() * 9 / 10])
    };
    let (a, b, c) = (q(0), q(1), q(2));
    (
        DVec3::new(a.0, b.0, c.0),
        DVec3::new(a.1, b.1, c.1),
        DVec3::new(a.2, b.2, c.2),
    )
}

/// SIMULATED: as many Gaussians as `g`, centres uniform in `g`'s robust box, log scales
/// N(median of `g`'s, 0.6), opacity logits N(1, 2) (as the render bench's city), SH degree 0.
fn simulated_like(g: &Gaussians) -> Gaussians {
    let (_, lo, hi) = extent(g);
    let mut ls: Vec<f32> = g.scale.iter().flatten().copied().collect();
    ls.sort_by(f32::total_cmp);
    let med = ls[ls.len() / 2];
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(59);
    let mut n = |m: f32, s: f32| {
        let u1: f32 = rng.random_range(f32::EPSILON..1.0);
        let u2: f32 = rng.random();
        m + s * (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    };
    let mut uniform = rand_chacha::ChaCha8Rng::seed_from_u64(60);
    let mut out = Gaussians::default();
    for _ in 0..g.len() {
        let p = [0, 1, 2].map(|k| {
            let t: f64 = uniform.random();
            (lo[k] + t * (hi[k] - lo[k])) as f32
        });
        out.positions.push(p);
        out.f_dc.push([n(0.0, 1.0), n(0.0, 1.0), n(0.0, 1.0)]);
        out.opacity.push(n(1.0, 2.0));
        out.scale.push([n(med, 0.6), n(med, 0.6), n(med, 0.6)]);
        out.rotation
            .push([n(0.0, 1.0), n(0.0, 1.0), n(0.0, 1.0), n(0.0, 1.0)]);
    }
    out
}

fn cameras(g: &Gaussians, w: u32, h: u32) -> Vec<Camera> {
    let (c, lo, hi) = extent(g);
    let r = (hi - lo).length() * 0.5;
    (0..4)
        .map(|k| {
            let a = k as f64 * std::f64::consts::FRAC_PI_2 + 0.3;
            let eye = c + DVec3::new(a.cos(), -0.35, a.sin()).normalize() * 1.5 * r;
            let f = 0.8 * f64::from(w);
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
                pose: Pose::look_at(eye, c, DVec3::new(0.0, -1.0, 0.0)).unwrap(),
            }
        })
        .collect()
}

/// Best of 3 per view, averaged over the views; and the mean alpha.
fn time_views(g: &Gaussians, cams: &[Camera]) -> (f64, f64) {
    let scene = PreparedScene::new(g).unwrap();
    let (mut total, mut alpha) = (0.0, 0.0);
    for c in cams {
        let mut best = f64::INFINITY;
        for _ in 0..3 {
            let t = Instant::now();
            let out = render_view(&scene, c, &RenderOptions::default()).unwrap();
            best = best.min(t.elapsed().as_secs_f64());
            alpha = out.alpha.iter().map(|&a| f64::from(a)).sum::<f64>() / out.alpha.len() as f64;
        }
        total += best;
    }
    (total / cams.len() as f64, alpha)
}

fn faint_share(g: &Gaussians) -> f64 {
    (0..g.len())
        .filter(|&i| g.activated_opacity(i) < 0.1)
        .count() as f64
        / g.len() as f64
}

fn render_part(real: &Path) {
    println!("### Render time per view: real captures and SIMULATED scenes of the same size\n");
    println!(
        "Four orbit views at 1.5× the robust radius, 960×720, best of 3 per view; SIMULATED: the same count in the capture's robust box, log scales N(capture median, 0.6), opacity logits N(1, 2).\n"
    );
    println!(
        "| scene | Gaussians | opacity < 0.1 | median scale / box diagonal | ms per view | mean alpha |"
    );
    println!("|---|---:|---:|---:|---:|---:|");
    for cap in ["plant", "tarot_cards"] {
        let (g, _) = read_ply(
            &real.join(format!("splats/{cap}.splat")),
            &ReadOptions::KEEP,
        )
        .unwrap();
        let sim = simulated_like(&g);
        let cams = cameras(&g, 960, 720);
        let (_, lo, hi) = extent(&g);
        let diag = (hi - lo).length();
        for (name, s) in [
            (format!("{cap} (real)"), &g),
            (format!("{cap}-sized SIMULATED"), &sim),
        ] {
            let mut sc: Vec<f32> = (0..s.len())
                .map(|i| s.activated_scale(i).into_iter().fold(0f32, f32::max))
                .collect();
            sc.sort_by(f32::total_cmp);
            let (ms, alpha) = time_views(s, &cams);
            println!(
                "| {name} | {} | {:.1} % | {:.4} | {:.1} | {alpha:.3} |",
                s.len(),
                100.0 * faint_share(s),
                f64::from(sc[sc.len() / 2]) / diag,
                1000.0 * ms
            );
        }
    }
    println!();
}

fn semantic_part(real: &Path) {
    let model = repo().join("models/espnet/espnet_p2_q8_cityscapes.onnx");
    let mut m = match gs4city::segment::semantic::SemanticModel::open(&model, 0) {
        Ok(m) => m,
        Err(e) => {
            println!("(segment --semantic skipped: {e})\n");
            return;
        }
    };
    let images = gs4city::segment::list_images(&real.join("lund/images")).unwrap();
    let (mut net, mut post, mut masks) = (0.0, 0.0, 0usize);
    for img in &images {
        let rgb = gs4city::imageio::read_rgb(img).unwrap();
        let t = Instant::now();
        let p = m.probabilities(&rgb).unwrap();
        net += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (ms, _) = gs4city::segment::semantic::masks(&p, &m.mapped, 394).unwrap();
        post += t.elapsed().as_secs_f64();
        masks += ms.len();
    }
    let n = images.len() as f64;
    println!("### `segment --semantic` (ESPNet, Cityscapes) on the real Lund photos\n");
    println!(
        "{} photos, 1024×768 (two 1024×512 tiles each), ONNX Runtime's default threads: network {:.2} s per photo, masks and features {:.3} s per photo, {:.1} masks per photo.\n",
        images.len(),
        net / n,
        post / n,
        masks as f64 / n
    );
}

fn main() {
    let real = repo().join("../shared/data/real");
    if !real.join("SOURCES.md").is_file() {
        println!("{} is missing: nothing to measure", real.display());
        return;
    }
    println!("## Real inputs\n");
    println!(
        "Command: `cargo bench --bench real_inputs` (release profile). rayon threads: {}.\n",
        rayon::current_num_threads()
    );
    render_part(&real);
    semantic_part(&real);
}
