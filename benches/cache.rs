//! The contributions cache: speed, size and error of the list rules (top-k, mass rule)
//! against complete lists.
//!
//! Run: `GS4CITY_RUN=R cargo bench --bench cache`, where `R` is a finished `gs4city run` folder
//! (its `run.json` names the scene; its `raycast/` holds `M_city`). Optional `GS4CITY_VIEWS=N`
//! (default 24): the first N training views by name.
//!
//! For each rule (top-k for k = 4, 8, 16, 32, all; the mass rule for ε = 0.02, 0.05, 0.1 with no
//! bound and with at most 32 entries; ε 0.05 ≤ 32 with the blend stopped early at T < 0.001,
//! 0.005, 0.01, 0.02, 0.05), every chosen view is rendered with its lists (nothing
//! written: the bytes of the version 4 file are counted, ids coded; since version 4 they include
//! the median-depth plane, 4 bytes per pixel, and their time includes computing it), and the
//! city-model vote of `lift` runs over them. `GS4CITY_RULES=a,b` keeps the rows whose label is listed.
//! Errors are measured against the complete lists with unrounded f32 weights ("all, f32": what
//! the rasterizer computes; the cache stores weights as IEEE half): the share of Gaussians whose
//! voted label differs, and the share of pixels whose predicted label differs when the same
//! per-Gaussian labels (those of the reference) are read back through the stored lists.
//!
//! `GS4CITY_READ=1` instead times the *readers'* side: every view of the run's `render/` cache is
//! read and decoded (`ViewContrib::read_into`, buffers reused; one thread, best of 3 passes),
//! reported as ms per view and million entries per second. A checksum of the decoded ids and
//! weights is printed so that two builds can be compared for identical output.
use std::path::PathBuf;
use std::time::Instant;

use gs4city::cache::{CacheOptions, ViewContrib};
use gs4city::idmap::LabelMaps;
use gs4city::render::PreparedScene;
use gs4city::scene::{Scene, Split};
use gs4city::vote::Votes;

fn main() {
    let Some(run) = std::env::var_os("GS4CITY_RUN").map(PathBuf::from) else {
        eprintln!("set GS4CITY_RUN to a finished `gs4city run` folder (see the file's docs)");
        return;
    };
    let n_views: usize = std::env::var("GS4CITY_VIEWS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(24);
    if std::env::var_os("GS4CITY_READ").is_some() {
        read_speed(&run);
        return;
    }
    let rec: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("run.json")).expect("run.json")).unwrap();
    let scene = Scene::open(&PathBuf::from(rec["scene"].as_str().unwrap())).unwrap();
    let views = gs4city::colmap::read_model(&scene.sparse).unwrap();
    let split = Split::new(views, 8);
    let chosen: Vec<_> = split.train.iter().take(n_views).cloned().collect();
    let (g, _) = gs4city::splat::read_ply(&scene.ply, &Default::default()).unwrap();
    let prepared = PreparedScene::new(&g).unwrap();
    let maps = LabelMaps::City(run.join("raycast"));
    let n = prepared.len();
    println!(
        "{} Gaussians, {} views of {}×{}, rayon threads {}",
        n,
        chosen.len(),
        chosen[0].camera.intrinsics.width,
        chosen[0].camera.intrinsics.height,
        rayon::current_num_threads()
    );
    // (options, weights rounded to half as stored); the first row is the reference.
    let opt = |top_k, epsilon| CacheOptions {
        top_k,
        epsilon,
        t_stop: 0.0,
        alpha_min: gs4city::cache::INRIA_ALPHA_MIN,
    };
    let stop = |t_stop| CacheOptions {
        t_stop,
        ..opt(32, 0.05)
    };
    let only: Option<Vec<String>> = std::env::var("GS4CITY_RULES")
        .ok()
        .map(|v| v.split(',').map(str::to_string).collect());
    let ks: Vec<(CacheOptions, bool)> = [
        (opt(0, 0.0), false),
        (opt(0, 0.0), true),
        (opt(32, 0.0), true),
        (opt(16, 0.0), true),
        (opt(8, 0.0), true),
        (opt(4, 0.0), true),
        (opt(0, 0.02), true),
        (opt(0, 0.05), true),
        (opt(0, 0.1), true),
        (opt(32, 0.02), true),
        (opt(32, 0.05), true),
        (opt(32, 0.1), true),
        (stop(0.001), true),
        (stop(0.005), true),
        (stop(0.01), true),
        (stop(0.02), true),
        (stop(0.05), true),
    ]
    .into_iter()
    .enumerate()
    .filter(|(i, (o, r))| *i == 0 || only.as_ref().is_none_or(|l| l.contains(&label(o, *r))))
    .map(|(_, x)| x)
    .collect();
    let mut reference: Option<(Vec<i32>, Vec<ViewContrib>)> = None;
    println!(
        "\n| rule | s/view (render + lists) | MB/view | entries/px | dropped α·T share | Gaussians voted otherwise than with all lists | pixels read otherwise |"
    );
    println!("|---|---|---|---|---|---|---|");
    for &(o, rounded) in &ks {
        let mut votes = Votes::new(n);
        let (mut secs, mut bytes, mut entries, mut dropped, mut covered) =
            (0.0, 0usize, 0usize, 0.0, 0usize);
        let mut kept = Vec::new();
        for v in &chosen {
            let t = Instant::now();
            let c = if rounded {
                gs4city::render::cache::contrib(&prepared, v, &o).unwrap()
            } else {
                gs4city::render::cache::contrib_unrounded(&prepared, v, &o).unwrap()
            };
            secs += t.elapsed().as_secs_f64();
            // The reference is costed as version 1 (u32 ids, f32 weights), 8 bytes per entry.
            bytes += if rounded {
                c.file_bytes()
            } else {
                64 + 14 * c.pixels() + 8 * c.entries()
            };
            entries += c.entries();
            for p in 0..c.pixels() {
                if c.alpha[p] >= 1e-3 {
                    covered += 1;
                    dropped += f64::from(c.lists.residual[p] / c.alpha[p]);
                }
            }
            let labels = maps.read(&v.stem(), c.width, c.height).unwrap();
            votes.accumulate(&c, &labels);
            // Keep a few views' lists to read labels back through them.
            if kept.len() < 4 {
                kept.push(c);
            }
        }
        let assigned: Vec<i32> = gs4city::vote::assign(&votes, n, 0.0)
            .iter()
            .map(|a| a.label)
            .collect();
        let npx = (chosen[0].camera.intrinsics.width * chosen[0].camera.intrinsics.height) as usize;
        let (voted_diff, px_diff) = match &reference {
            None => ("0 (reference)".to_string(), "0 (reference)".to_string()),
            Some((all_labels, all_lists)) => {
                let voted = (0..n).filter(|&i| all_labels[i] >= 0 || assigned[i] >= 0);
                let (mut d, mut t) = (0usize, 0usize);
                for i in voted {
                    t += 1;
                    d += usize::from(all_labels[i] != assigned[i]);
                }
                let class: Vec<i32> = all_labels.clone();
                let (mut pd, mut pt) = (0usize, 0usize);
                for (full, trunc) in all_lists.iter().zip(&kept) {
                    let (_, a) = gs4city::cache::predict(full, all_labels, &class);
                    let (_, b) = gs4city::cache::predict(trunc, all_labels, &class);
                    pt += a.len();
                    pd += a.iter().zip(&b).filter(|(x, y)| x != y).count();
                }
                (
                    format!("{:.3} %", 100.0 * d as f64 / t.max(1) as f64),
                    format!("{:.3} %", 100.0 * pd as f64 / pt.max(1) as f64),
                )
            }
        };
        println!(
            "| {} | {:.3} | {:.1} | {:.2} | {:.4} | {} | {} |",
            label(&o, rounded),
            secs / chosen.len() as f64,
            bytes as f64 / chosen.len() as f64 / 1e6,
            entries as f64 / (chosen.len() * npx) as f64,
            dropped / covered.max(1) as f64,
            voted_diff,
            px_diff
        );
        if !rounded {
            reference = Some((assigned, kept));
        }
    }
}

/// Reading speed of the run's cache (see the file's docs).
fn read_speed(run: &std::path::Path) {
    let cache = gs4city::cache::Cache::open(&run.join("render")).unwrap();
    let stems: Vec<String> = cache.summary.views.iter().map(|v| v.stem.clone()).collect();
    let (mut view, mut buf) = (ViewContrib::empty(), Vec::new());
    let (mut best, mut entries, mut sum) = (f64::INFINITY, 0usize, 0u64);
    for _ in 0..3 {
        let t = Instant::now();
        let (mut e, mut s) = (0usize, 0u64);
        for stem in &stems {
            cache.load_into(stem, &mut view, &mut buf).unwrap();
            e += view.entries();
            // Order-dependent checksum of the decoded lists.
            for (&id, &w) in view.lists.ids.iter().zip(&view.lists.weights) {
                s = s.rotate_left(5) ^ u64::from(id) ^ (u64::from(w.to_bits()) << 32);
            }
        }
        best = best.min(t.elapsed().as_secs_f64());
        (entries, sum) = (e, s);
    }
    println!(
        "{} views, {:.2} M entries per view: {:.2} ms per view (best of 3, checksum included), {:.1} M entries/s; checksum {sum:016x}",
        stems.len(),
        entries as f64 / stems.len() as f64 / 1e6,
        1e3 * best / stems.len() as f64,
        entries as f64 / best / 1e6
    );
}

/// A rule's row label: `all, f32`, `all`, `16`, `ε 0.05`, `ε 0.05 ≤ 32`.
fn label(o: &CacheOptions, rounded: bool) -> String {
    if o.t_stop > 0.0 {
        return format!(
            "{} / T < {}",
            label(&CacheOptions { t_stop: 0.0, ..*o }, rounded),
            o.t_stop
        );
    }
    match (rounded, o.epsilon > 0.0, o.top_k) {
        (false, ..) => "all, f32".into(),
        (true, false, 0) => "all".into(),
        (true, false, k) => k.to_string(),
        (true, true, 0) => format!("ε {}", o.epsilon),
        (true, true, k) => format!("ε {} ≤ {k}", o.epsilon),
    }
}
