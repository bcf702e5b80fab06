//! Benchmark of `align --refine` on a SIMULATED street scene (default out/results/street/scene, or
//! `REFINE_BENCH_SCENE`): the basin of convergence (a sweep of initial alignment errors →
//! final error vs the truth and success rate), the same with noisy Gaussian centres, and
//! speed against error for the `max_points` knob. The truth (`summary.json` →
//! `alignment_true`) is read here, for scoring only; the stage never sees it.
//!
//! Perturbations are made in-process (the Gaussians are the same, only the alignment handed
//! over changes): `gs4city::synth::perturb` about the Gaussians' bounding-box centre, exactly
//! as `gs4city synth` makes `alignment.json`, with `REFINE_BENCH_SEEDS` seeds (default 5)
//! per row. Run: `cargo bench --bench refine` (`REFINE_BENCH_QUICK=1`: 2 seeds, fewer rows;
//! `REFINE_BENCH_CASE=t_m,rot_deg,scale,seed`: one case with its whole summary;
//! `REFINE_BENCH_SCORE=alignment.json`: that alignment's error against the scene's truth;
//! `REFINE_BENCH_ONLY=basin|noisy|knob`: one part).
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::DVec3;
use gs4city::alignment::Alignment;
use gs4city::citymodel;
use gs4city::mesh::TriMesh;
use gs4city::refine::{self, RefineInput, RefineOptions};
use gs4city::splat::{self, Gaussians, ReadOptions};
use gs4city::synth::{self, config::Noise};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Success: the error targets (3 cm RMS, 0.05°, 0.2 % scale).
const OK_CM: f64 = 3.0;
const OK_DEG: f64 = 0.05;
const OK_PCT: f64 = 0.2;

struct Scene {
    truth: Alignment,
    /// The mesh aligned by the truth (f32, as the citymodel stage writes it).
    mesh: TriMesh,
    entities: Vec<gs4city::semantics::Entity>,
    gaussians: Gaussians,
    centre: DVec3,
}

fn load(dir: &Path) -> Scene {
    let summary: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("summary.json")).expect("scene summary.json"),
    )
    .expect("json");
    let truth = Alignment::from_json_str(
        &dir.join("summary.json"),
        &summary["alignment_true"].to_string(),
    )
    .expect("alignment_true");
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir.join("citymodel"))
        .expect("citymodel/")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "gml"))
        .collect();
    files.sort();
    let city = citymodel::run(
        &files,
        &citymodel::Options {
            alignment: Some(truth),
        },
    )
    .expect("citymodel");
    let (gaussians, _) =
        splat::read_ply(&dir.join("point_cloud.ply"), &ReadOptions::default()).expect("ply");
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for p in &gaussians.positions {
        let q = DVec3::from_array(p.map(f64::from));
        lo = lo.min(q);
        hi = hi.max(q);
    }
    Scene {
        truth,
        mesh: city.mesh,
        entities: city.entities,
        gaussians,
        centre: (lo + hi) * 0.5,
    }
}

/// The mesh as the citymodel stage would write it for `given` (vertices moved in f64 by the
/// relative similarity truth → given, stored f32).
fn mesh_for(s: &Scene, given: &Alignment) -> TriMesh {
    let rel = s.truth.relative(given);
    let mut m = s.mesh.clone();
    for v in &mut m.vertices {
        let p = rel.apply(DVec3::from_array(v.map(f64::from)));
        *v = [p.x as f32, p.y as f32, p.z as f32];
    }
    m
}

/// One trial: Ok((rms cm, rotation °, scale %, seconds, iterations)) or Err(refusal).
fn trial(
    s: &Scene,
    g: &Gaussians,
    given: &Alignment,
    opts: &RefineOptions,
) -> Result<(f64, f64, f64, f64, usize), String> {
    let mesh = mesh_for(s, given);
    let input = RefineInput {
        mesh: &mesh,
        entities: &s.entities,
        initial: given,
        gaussians: g,
        camera_centres: None,
    };
    let t = Instant::now();
    let out = refine::refine(&input, opts).map_err(|e| e.to_string())?;
    let secs = t.elapsed().as_secs_f64();
    let err = refine::compare(&s.truth, &out.alignment, &s.mesh.vertices, &s.truth);
    Ok((
        err.rms_m * 100.0,
        err.rotation_deg,
        err.scale_pct,
        secs,
        out.iterations,
    ))
}

struct Row {
    label: String,
    n: usize,
    ok: usize,
    refused: usize,
    errs_cm: Vec<f64>,
    rot: Vec<f64>,
    scale: Vec<f64>,
    secs: Vec<f64>,
    iters: Vec<usize>,
    initial_cm: Vec<f64>,
    refusals: Vec<String>,
}

fn median(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut w = v.to_vec();
    w.sort_by(f64::total_cmp);
    w[w.len() / 2]
}

fn max(v: &[f64]) -> f64 {
    v.iter().copied().fold(f64::NAN, f64::max)
}

fn sweep_row(s: &Scene, g: &Gaussians, noise: &Noise, seeds: u64, opts: &RefineOptions) -> Row {
    let mut row = Row {
        label: format!(
            "{:.1} m, {:.1}°, ±{:.1} %",
            noise.translation_m,
            noise.rotation_deg,
            noise.scale * 100.0
        ),
        n: 0,
        ok: 0,
        refused: 0,
        errs_cm: vec![],
        rot: vec![],
        scale: vec![],
        secs: vec![],
        iters: vec![],
        initial_cm: vec![],
        refusals: vec![],
    };
    for seed in 0..seeds {
        let mut rng = ChaCha8Rng::seed_from_u64(1000 + seed);
        let given = synth::perturb(&s.truth, noise, s.centre, &mut rng);
        let init = refine::compare(&s.truth, &given, &s.mesh.vertices, &s.truth);
        row.initial_cm.push(init.rms_m * 100.0);
        row.n += 1;
        match trial(s, g, &given, opts) {
            Ok((cm, deg, pct, secs, it)) => {
                if cm <= OK_CM && deg <= OK_DEG && pct.abs() <= OK_PCT {
                    row.ok += 1;
                }
                row.errs_cm.push(cm);
                row.rot.push(deg);
                row.scale.push(pct.abs());
                row.secs.push(secs);
                row.iters.push(it);
            }
            Err(e) => {
                row.refused += 1;
                row.refusals.push(e);
            }
        }
    }
    row
}

fn print_table(title: &str, rows: &[Row]) {
    println!("\n### {title}\n");
    println!(
        "| initial error (t, rot, scale) | initial rms | runs | success | refused | final rms cm (median / max) | rot ° (max) | scale % (max) | iterations (median) | s per run (median) |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        let it: Vec<f64> = r.iters.iter().map(|&i| i as f64).collect();
        println!(
            "| {} | {:.2} m | {} | {} / {} | {} | {:.3} / {:.3} | {:.4} | {:.4} | {:.0} | {:.2} |",
            r.label,
            median(&r.initial_cm) / 100.0,
            r.n,
            r.ok,
            r.n,
            r.refused,
            median(&r.errs_cm),
            max(&r.errs_cm),
            max(&r.rot),
            max(&r.scale),
            median(&it),
            median(&r.secs),
        );
    }
    for r in rows {
        for e in &r.refusals {
            println!("refused ({}): {e}", r.label);
        }
    }
}

/// The Gaussians with every centre jittered by an isotropic normal offset of σ `sigma_m`
/// (scene units = metres × scale), seeded: closer to what a trained 3DGS scene looks like.
fn jittered(g: &Gaussians, sigma: f64, seed: u64) -> Gaussians {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = g.clone();
    let mut n = || {
        let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    };
    for p in &mut out.positions {
        for c in p.iter_mut() {
            *c += (n() * sigma) as f32;
        }
    }
    out
}

fn main() {
    let dir =
        std::env::var("REFINE_BENCH_SCENE").unwrap_or_else(|_| "out/results/street/scene".into());
    let dir = PathBuf::from(dir);
    if !dir.join("summary.json").is_file() {
        println!(
            "refine bench: no SIMULATED scene at {} (set REFINE_BENCH_SCENE); skipped",
            dir.display()
        );
        return;
    }
    let quick = std::env::var_os("REFINE_BENCH_QUICK").is_some();
    let seeds: u64 = std::env::var("REFINE_BENCH_SEEDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(if quick { 2 } else { 5 });
    let t = Instant::now();
    let s = load(&dir);
    println!(
        "scene {} (SIMULATED): {} Gaussians, {} triangles, loaded in {:.1} s; rayon threads {}; {} seeds per row",
        dir.display(),
        s.gaussians.len(),
        s.mesh.faces.len(),
        t.elapsed().as_secs_f64(),
        rayon::current_num_threads(),
        seeds
    );
    let opts = RefineOptions::default();
    let noise = |t: f64, r: f64, sc: f64| Noise {
        translation_m: t,
        rotation_deg: r,
        scale: sc,
    };
    // Score an alignment.json (e.g. written by `gs4city align --refine`) against the truth:
    // REFINE_BENCH_SCORE=path/alignment.json.
    if let Ok(path) = std::env::var("REFINE_BENCH_SCORE") {
        let a = Alignment::read(Path::new(&path)).expect("alignment.json");
        let given_path = dir.join("citymodel/alignment.json");
        let given = Alignment::read(&given_path).expect("the scene's citymodel/alignment.json");
        for (name, x) in [("given", &given), ("scored", &a)] {
            let e = refine::compare(&s.truth, x, &s.mesh.vertices, &s.truth);
            println!(
                "{name:<7} vs truth: vertex displacement rms {:.4} cm, max {:.4} cm, centroid {:.4} cm; rotation {:.6}°; scale {:+.6} %",
                e.rms_m * 100.0,
                e.max_m * 100.0,
                e.centroid_m * 100.0,
                e.rotation_deg,
                e.scale_pct
            );
        }
        let moved = refine::compare(&given, &a, &s.mesh.vertices, &s.truth);
        println!(
            "given → scored: vertices moved rms {:.4} cm, max {:.4} cm",
            moved.rms_m * 100.0,
            moved.max_m * 100.0
        );
        return;
    }
    // One case in detail: REFINE_BENCH_CASE="t_m,rot_deg,scale,seed" prints the summary.
    if let Ok(case) = std::env::var("REFINE_BENCH_CASE") {
        let v: Vec<f64> = case
            .split(',')
            .map(|x| x.trim().parse().expect("number"))
            .collect();
        assert!(v.len() == 4, "REFINE_BENCH_CASE=t_m,rot_deg,scale,seed");
        let mut rng = ChaCha8Rng::seed_from_u64(1000 + v[3] as u64);
        let given = synth::perturb(&s.truth, &noise(v[0], v[1], v[2]), s.centre, &mut rng);
        let mesh = mesh_for(&s, &given);
        let input = RefineInput {
            mesh: &mesh,
            entities: &s.entities,
            initial: &given,
            gaussians: &s.gaussians,
            camera_centres: None,
        };
        match refine::refine(&input, &opts) {
            Ok(out) => {
                let err = refine::compare(&s.truth, &out.alignment, &s.mesh.vertices, &s.truth);
                println!("{}", serde_json::to_string_pretty(&out).expect("json"));
                println!("error vs truth: {err:?}");
            }
            Err(e) => println!("refused: {e}"),
        }
        return;
    }
    let mut cases = vec![];
    for t in [0.1, 0.3, 0.5, 1.0, 1.5, 2.0] {
        cases.push(noise(t, 0.0, 0.0));
    }
    for r in [0.2, 0.5, 1.0, 2.0, 3.0, 5.0] {
        cases.push(noise(0.0, r, 0.0));
    }
    for sc in [0.005, 0.01, 0.02] {
        cases.push(noise(0.0, 0.0, sc));
    }
    cases.extend([
        noise(0.3, 0.5, 0.0),
        noise(0.3, 0.5, 0.005),
        noise(1.0, 1.0, 0.01),
        noise(2.0, 2.0, 0.02),
        noise(2.0, 5.0, 0.02),
        // Beyond the range: where the basin ends.
        noise(3.0, 0.0, 0.0),
        noise(5.0, 0.0, 0.0),
        noise(0.0, 8.0, 0.0),
        noise(0.0, 12.0, 0.0),
        noise(0.0, 0.0, 0.05),
        noise(3.0, 8.0, 0.05),
    ]);
    if quick {
        cases = vec![
            noise(0.3, 0.5, 0.0),
            noise(2.0, 2.0, 0.02),
            noise(0.0, 5.0, 0.0),
        ];
    }
    let only = std::env::var("REFINE_BENCH_ONLY").unwrap_or_default();
    let part = |name: &str| only.is_empty() || only == name;
    if !part("basin") {
        cases.clear();
    }
    let rows: Vec<Row> = cases
        .iter()
        .map(|c| sweep_row(&s, &s.gaussians, c, seeds, &opts))
        .collect();
    print_table(
        "Basin: SIMULATED Gaussians exactly on the true surfaces (scale sign and axes random per seed)",
        &rows,
    );

    let sigma = 0.02 * s.truth.scale;
    let noisy = jittered(&s.gaussians, sigma, 99);
    let noisy_cases: Vec<Noise> = if !part("noisy") {
        vec![]
    } else if quick {
        vec![noise(0.3, 0.5, 0.0)]
    } else {
        vec![
            noise(0.0, 0.0, 0.0),
            noise(0.3, 0.5, 0.0),
            noise(1.0, 1.0, 0.01),
            noise(2.0, 2.0, 0.02),
        ]
    };
    let rows: Vec<Row> = noisy_cases
        .iter()
        .map(|c| sweep_row(&s, &noisy, c, seeds, &opts))
        .collect();
    print_table(
        "Basin with every Gaussian centre jittered (isotropic σ = 2 cm)",
        &rows,
    );

    // Speed against error: the number of sampled Gaussians (0.3 m / 0.5° error, noisy centres).
    if !part("knob") {
        return;
    }
    println!(
        "\n### Speed against error: `max_points` (voxel 0.1 m; 0.3 m, 0.5°; centres jittered σ = 2 cm; best of 3 runs)\n"
    );
    println!("| max_points | sampled | s per run (best of 3) | final rms cm | rot ° | scale % |");
    println!("|---:|---:|---:|---:|---:|---:|");
    let mut rng = ChaCha8Rng::seed_from_u64(1000);
    let given = synth::perturb(&s.truth, &noise(0.3, 0.5, 0.0), s.centre, &mut rng);
    let knobs: &[usize] = if quick {
        &[20_000, 200_000]
    } else {
        &[10_000, 25_000, 50_000, 100_000, 200_000, 400_000]
    };
    for &mp in knobs {
        let o = RefineOptions {
            max_points: mp,
            voxel_m: 0.1,
            ..opts.clone()
        };
        let mut best = f64::INFINITY;
        let mut res = None;
        for _ in 0..3 {
            let r = trial(&s, &noisy, &given, &o);
            if let Ok(v) = &r {
                best = best.min(v.3);
            }
            res = Some(r);
        }
        match res.expect("3 runs") {
            Ok((cm, deg, pct, _, _)) => {
                let sampled = {
                    let mesh = mesh_for(&s, &given);
                    let input = RefineInput {
                        mesh: &mesh,
                        entities: &s.entities,
                        initial: &given,
                        gaussians: &noisy,
                        camera_centres: None,
                    };
                    refine::refine(&input, &o)
                        .map(|x| x.selection.sampled)
                        .unwrap_or(0)
                };
                println!(
                    "| {mp} | {sampled} | {best:.2} | {cm:.3} | {deg:.4} | {:.4} |",
                    pct.abs()
                );
            }
            Err(e) => println!("| {mp} | – | – | refused: {e} | | |"),
        }
    }
}
