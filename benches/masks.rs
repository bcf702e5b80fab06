//! Benchmark and evaluation of the masks stage on a SIMULATED scene (`gs4city synth`): the time
//! per view on one thread, and the quality of the kept set against the simulation truth
//! (`masks/<stem>.sim.json`, `gt/<stem>.class.npy`) — which only this benchmark reads, never the
//! stage.
//!
//! ```text
//! cargo bench --bench masks -- [--scene out/results/street/scene] [--run out/results/street/run]
//!     [--out DIR] [--repeat 2] [--no-sweep]
//! ```
//! `--run` is a `gs4city run` folder with `raycast/`, `render/` (the contributions cache) and
//! `citymodel/`. Metrics (masks passing the quality filter `q ≥ τ_q, area ≥ τ_a` are "QC"):
//! * precision = kept masks whose simulated class is not a building class (0–5) / kept;
//! * non-building recall = kept QC non-building masks / QC non-building masks;
//! * occluder recall = the same over QC non-building masks with `R_ov ≥ 0.8` (`R_ov` recomputed
//!   here by decoding every mask).
//!
//! For the mask-free source (no SAM masks are used) a kept component counts as correct when the
//! majority ground-truth class of its pixels is not a building class, and a simulated
//! non-building mask counts as found when kept components cover at least half of it.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use gs4city::alignment::Alignment;
use gs4city::cache::Cache;
use gs4city::camera::View;
use gs4city::masks::{self, MasksInputs, MasksOptions, Source, Test};
use gs4city::scene::Scene;
use gs4city::{colmap, npy, sam};

struct Args {
    scene: PathBuf,
    run: PathBuf,
    out: PathBuf,
    repeat: usize,
    sweep: bool,
}

fn args() -> Args {
    let mut a = Args {
        scene: "out/results/street/scene".into(),
        run: "out/results/street/run".into(),
        out: std::env::temp_dir().join("gs4city_masks_bench"),
        repeat: 2,
        sweep: true,
    };
    let v: Vec<String> = std::env::args().skip(1).collect();
    let mut i = 0;
    while i < v.len() {
        let next = |i: usize| v.get(i + 1).cloned().unwrap_or_default();
        match v[i].as_str() {
            "--scene" => a.scene = next(i).into(),
            "--run" => a.run = next(i).into(),
            "--out" => a.out = next(i).into(),
            "--repeat" => a.repeat = next(i).parse().unwrap_or(2).max(1),
            "--no-sweep" => {
                a.sweep = false;
                i += 1;
                continue;
            }
            _ => {
                i += 1;
                continue;
            }
        }
        i += 2;
    }
    a
}

/// What the simulation knows of one SAM mask, and its `R_ov` recomputed here.
struct TruthMask {
    class: i32,
    q: f64,
    area: u64,
    r_ov: f64,
    mask: ndarray::Array2<bool>,
}

fn is_building(c: i32) -> bool {
    (0..=5).contains(&c)
}

fn truth(scene: &Path, raycast: &Path, stem: &str) -> Vec<TruthMask> {
    let list = sam::read_sam_json(&scene.join(format!("masks/{stem}.json"))).unwrap();
    let sim: Vec<serde_json::Value> = serde_json::from_slice(
        &std::fs::read(scene.join(format!("masks/{stem}.sim.json"))).unwrap(),
    )
    .unwrap();
    assert_eq!(
        sim.len(),
        list.len(),
        "{stem}: sim.json and the SAM list differ in length"
    );
    let (shape, ids) = npy::read::<i32>(&raycast.join(format!("{stem}.ids.npy"))).unwrap();
    let w = shape[2];
    list.iter()
        .zip(&sim)
        .map(|(m, s)| {
            let mask = m.segmentation.decode().unwrap();
            let on = mask.iter().filter(|&&v| v).count() as f64;
            let feat = mask
                .indexed_iter()
                .filter(|((y, x), v)| **v && ids[y * w + x] >= 0)
                .count() as f64;
            TruthMask {
                class: s["class"].as_i64().unwrap() as i32,
                q: m.predicted_iou,
                area: m.area,
                r_ov: if on > 0.0 { feat / on } else { 0.0 },
                mask,
            }
        })
        .collect()
}

#[derive(Default, Debug, Clone, serde::Serialize)]
struct Score {
    kept: usize,
    correct: usize,
    nb: usize,
    nb_found: usize,
    occ: usize,
    occ_found: usize,
}

impl Score {
    fn precision(&self) -> f64 {
        self.correct as f64 / self.kept.max(1) as f64
    }
    fn nb_recall(&self) -> f64 {
        self.nb_found as f64 / self.nb.max(1) as f64
    }
    fn occ_recall(&self) -> f64 {
        self.occ_found as f64 / self.occ.max(1) as f64
    }
}

const RHO_EVAL: f64 = 0.8;

/// Scores a SAM-based output folder.
fn score_sam(out: &Path, truths: &BTreeMap<String, Vec<TruthMask>>, o: &MasksOptions) -> Score {
    let mut s = Score::default();
    for (stem, t) in truths {
        let kept = gs4city::maskfile::read_kept(&gs4city::maskfile::kept_file(out, stem)).unwrap();
        let set: std::collections::BTreeSet<usize> =
            kept.iter().map(|k| k.source_index as usize).collect();
        s.kept += kept.len();
        s.correct += kept
            .iter()
            .filter(|k| !is_building(t[k.source_index as usize].class))
            .count();
        for (i, m) in t.iter().enumerate() {
            let (h, w) = m.mask.dim();
            let qc = m.q >= o.tau_q && m.area >= o.min_area_px(h, w);
            if !qc || is_building(m.class) {
                continue;
            }
            s.nb += 1;
            s.nb_found += usize::from(set.contains(&i));
            if m.r_ov >= RHO_EVAL {
                s.occ += 1;
                s.occ_found += usize::from(set.contains(&i));
            }
        }
    }
    s
}

/// Scores a mask-free output folder against the ground-truth class maps.
fn score_free(
    out: &Path,
    scene: &Path,
    truths: &BTreeMap<String, Vec<TruthMask>>,
    o: &MasksOptions,
) -> Score {
    let mut s = Score::default();
    for (stem, t) in truths {
        let kept = gs4city::maskfile::read_kept(&gs4city::maskfile::kept_file(out, stem)).unwrap();
        let (shape, gt) = npy::read::<i32>(&scene.join(format!("gt/{stem}.class.npy"))).unwrap();
        let (h, w) = (shape[0], shape[1]);
        let mut union = vec![false; h * w];
        for k in &kept {
            let m = k.sam.segmentation.decode().unwrap();
            let mut votes: BTreeMap<i32, usize> = BTreeMap::new();
            for ((y, x), &on) in m.indexed_iter() {
                if on {
                    union[y * w + x] = true;
                    if gt[y * w + x] >= 0 {
                        *votes.entry(gt[y * w + x]).or_default() += 1;
                    }
                }
            }
            let major = votes
                .iter()
                .max_by_key(|(c, n)| (**n, -**c))
                .map(|(c, _)| *c);
            s.kept += 1;
            s.correct += usize::from(major.is_some_and(|c| !is_building(c)));
        }
        for m in t {
            let qc = m.q >= o.tau_q && m.area >= o.min_area_px(h, w);
            if !qc || is_building(m.class) {
                continue;
            }
            let on = m.mask.iter().filter(|&&v| v).count();
            let cov = m
                .mask
                .indexed_iter()
                .filter(|((y, x), v)| **v && union[y * w + x])
                .count();
            let found = 2 * cov >= on;
            s.nb += 1;
            s.nb_found += usize::from(found);
            if m.r_ov >= RHO_EVAL {
                s.occ += 1;
                s.occ_found += usize::from(found);
            }
        }
    }
    s
}

struct Ctx {
    scene: Scene,
    views: Vec<View>,
    cache: Cache,
    raycast: PathBuf,
    scale: f64,
}

/// Runs the stage on `threads` threads, `repeat` times; returns the best wall time.
fn timed(
    c: &Ctx,
    o: &MasksOptions,
    out: &Path,
    threads: usize,
    repeat: usize,
) -> (f64, masks::MasksSummary) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let mut best = f64::INFINITY;
    let mut last = None;
    for _ in 0..repeat {
        let t = Instant::now();
        let s = pool
            .install(|| {
                masks::run(
                    &MasksInputs {
                        scene: &c.scene,
                        views: &c.views,
                        raycast: &c.raycast,
                        cache: Some(&c.cache),
                        alignment_scale: c.scale,
                    },
                    o,
                    out,
                )
            })
            .unwrap();
        best = best.min(t.elapsed().as_secs_f64());
        last = Some(s);
    }
    (best, last.unwrap())
}

fn main() {
    let a = args();
    if !a.scene.join("masks").is_dir() || !a.run.join("render/summary.json").is_file() {
        println!(
            "masks bench: needs a simulated scene with masks/ ({}) and a run folder with raycast/ and render/ ({}); skipped",
            a.scene.display(),
            a.run.display()
        );
        return;
    }
    let scene = Scene::open(&a.scene).unwrap();
    let views = colmap::read_model(&scene.sparse).unwrap();
    let cache = Cache::open(&a.run.join("render")).unwrap();
    let scale = Alignment::read(&a.run.join("citymodel/alignment.json"))
        .map(|x| x.scale)
        .unwrap_or(1.0);
    let raycast = a.run.join("raycast");
    let t = Instant::now();
    let truths: BTreeMap<String, Vec<TruthMask>> = views
        .iter()
        .map(|v| (v.stem(), truth(&a.scene, &raycast, &v.stem())))
        .collect();
    println!(
        "masks bench: {} ({} views, {} SAM masks; truth read in {:.1} s), run {}",
        a.scene.display(),
        views.len(),
        truths.values().map(Vec::len).sum::<usize>(),
        t.elapsed().as_secs_f64(),
        a.run.display()
    );
    let c = Ctx {
        scene,
        views,
        cache,
        raycast,
        scale,
    };
    let base = MasksOptions {
        overlays: 0,
        ..Default::default()
    };
    let modes: Vec<(&str, MasksOptions)> = vec![
        (
            "paper (features, low overlap kept unchecked)",
            MasksOptions {
                test: Test::Features,
                low_overlap_check: false,
                ..base.clone()
            },
        ),
        (
            "features",
            MasksOptions {
                test: Test::Features,
                ..base.clone()
            },
        ),
        (
            "geometry",
            MasksOptions {
                test: Test::Geometry,
                ..base.clone()
            },
        ),
        (
            "geometry, expected depth",
            MasksOptions {
                test: Test::Geometry,
                gs_depth: masks::GsDepth::Expected,
                ..base.clone()
            },
        ),
        (
            "geometry, no surface offset",
            MasksOptions {
                test: Test::Geometry,
                surface_bias: false,
                ..base.clone()
            },
        ),
        (
            "both",
            MasksOptions {
                test: Test::Both,
                ..base.clone()
            },
        ),
        (
            "mask-free source",
            MasksOptions {
                source: Source::Depth,
                ..base.clone()
            },
        ),
    ];
    let n = c.views.len() as f64;
    println!(
        "\n| mode | kept | precision | non-building recall | occluder recall | s (1 thread, best of {}) | ms/view |",
        a.repeat
    );
    println!("|---|---|---|---|---|---|---|");
    let mut json = Vec::new();
    for (i, (name, o)) in modes.iter().enumerate() {
        let out = a.out.join(format!("mode{i}"));
        let (secs, summary) = timed(&c, o, &out, 1, a.repeat);
        let s = if o.source == Source::Depth {
            score_free(&out, &a.scene, &truths, o)
        } else {
            score_sam(&out, &truths, o)
        };
        println!(
            "| {name} | {} | {:.3} | {:.3} ({}/{}) | {:.3} ({}/{}) | {:.1} | {:.0} |",
            s.kept,
            s.precision(),
            s.nb_recall(),
            s.nb_found,
            s.nb,
            s.occ_recall(),
            s.occ_found,
            s.occ,
            secs,
            1000.0 * secs / n
        );
        json.push(
            serde_json::json!({"mode": name, "score": s, "seconds": secs,
            "timing": summary.timing, "rules": summary.rules}),
        );
    }
    if a.sweep {
        let pool_threads = rayon::current_num_threads();
        let mut sweep = |title: &str, head: &str, runs: Vec<(String, MasksOptions)>| {
            println!(
                "\n{title}\n\n| {head} | kept | precision | non-building recall | occluder recall |"
            );
            println!(
                "|{}---|---|---|---|",
                "---|".repeat(head.matches('|').count() + 1)
            );
            for (label, o) in runs {
                let out = a.out.join("sweep");
                timed(&c, &o, &out, pool_threads, 1);
                let s = score_sam(&out, &truths, &o);
                println!(
                    "| {label} | {} | {:.3} | {:.3} | {:.3} |",
                    s.kept,
                    s.precision(),
                    s.nb_recall(),
                    s.occ_recall()
                );
                json.push(serde_json::json!({"sweep": title, "setting": label, "score": s}));
            }
        };
        sweep(
            "Geometry test, τ_occ (metres):",
            "τ_occ",
            [0.25, 0.5, 1.0, 2.0]
                .iter()
                .map(|&t| {
                    (
                        format!("{t}"),
                        MasksOptions {
                            test: Test::Geometry,
                            tau_occ_m: t,
                            ..base.clone()
                        },
                    )
                })
                .collect(),
        );
        let rhos = [0.5, 0.8, 0.9, 1.0];
        let mut runs = Vec::new();
        for (name, test) in [
            ("paper rule (features)", Test::Features),
            ("geometry", Test::Geometry),
        ] {
            for rho in rhos {
                runs.push((
                    format!("{name}, low overlap unchecked | {rho}"),
                    MasksOptions {
                        test,
                        rho,
                        low_overlap_check: false,
                        ..base.clone()
                    },
                ));
            }
        }
        sweep(
            &format!(
                "ρ with low-overlap masks kept unchecked (occluders: R_ov ≥ {RHO_EVAL} whatever ρ; with the low-overlap check ρ changes nothing measurable):"
            ),
            "test | ρ",
            runs,
        );
    }
    std::fs::create_dir_all(&a.out).unwrap();
    std::fs::write(
        a.out.join("bench.json"),
        serde_json::to_vec_pretty(&json).unwrap(),
    )
    .unwrap();
    println!("\nresults: {}", a.out.join("bench.json").display());
}
