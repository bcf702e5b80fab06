//! Benchmark of `gs4city query` (plain `Instant`, no criterion): `cargo bench --bench query`.
//!
//! 1. **Calibration of the text "no match"** on the SIMULATED street scene: per-mask features
//!    (`features/<stem>.npy`, simulated CLIP) grouped by their ground-truth source instance across
//!    views (`masks/<stem>.sim.json`, simulation truth, read here for scoring only) stand in for
//!    the per-label features of the fuse stage (a group = the normalised mean of its masks'
//!    features, as the association's running mean). For every prompt of `features/prompts.json`
//!    with a target class (`synth::masks::PROMPTS`), the relevancy of every group: the groups of
//!    the target class should reach the threshold, all others (what a query for an *absent*
//!    class sees) should not. Printed for single masks and for groups of ≥ 3 masks.
//! 2. **Timing** on a finished street run (`GS4CITY_QUERY_RUN`, default `out/results/street/run`):
//!    loading, selection, PLY export, one view's mask, a full query with the 16 test-view masks.
//!
//! Prints Markdown. The machine is shared: times are the best of N repetitions.
use std::path::{Path, PathBuf};
use std::time::Instant;

use gs4city::query::{self, QueryOptions, Request, Views};
use gs4city::selection::text::{self, LabelFeatures, TextOptions};
use gs4city::selection::{self, MaskRule, SemanticRun};
use gs4city::{sam, synth};

fn best_of<T>(n: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..n {
        let t = Instant::now();
        let r = f();
        best = best.min(t.elapsed().as_secs_f64());
        out = Some(r);
    }
    (best, out.expect("n > 0"))
}

#[path = "../tests/common/sim_labels.rs"]
mod sim_labels;

/// (true class, feature) per simulated label.
type Labelled = Vec<(i32, Vec<f32>)>;

fn calibration(scene: &Path) {
    let prompts = sam::read_prompts_json(&scene.join("features/prompts.json")).unwrap();
    let (singles, groups) = sim_labels::simulated_labels(scene);
    let pairs = |v: Vec<sim_labels::SimLabel>, min: usize| -> Labelled {
        v.into_iter()
            .filter(|l| l.masks >= min)
            .map(|l| (l.class, l.feature))
            .collect()
    };
    let opts = TextOptions::default();
    let sets: [(&str, Labelled); 2] = [
        ("single masks (raw simulated features)", pairs(singles, 1)),
        (
            "instance groups of ≥ 3 masks (simulated label features)",
            pairs(groups, 3),
        ),
    ];
    println!(
        "## Text relevancy on the SIMULATED street features (T = {}, synonyms: cosine ≥ {})\n",
        opts.temperature, opts.synonym_cos
    );
    for (name, set) in sets {
        let d = set[0].1.len();
        let flat: Vec<f32> = set.iter().flat_map(|x| x.1.iter().copied()).collect();
        let feats = LabelFeatures::new(Path::new("simulated"), d, &flat).unwrap();
        println!("### {name}: {} labels\n", set.len());
        let ids: Vec<i32> = (0..set.len() as i32).collect();
        let car =
            text::build_query(&prompts, Path::new("prompts.json"), Ok("a car"), &opts).unwrap();
        let (t_score, _) = best_of(3, || text::score_labels(&car, &feats, &ids, &opts));
        println!(
            "Scoring every label for \"a car\" ({} negatives, D = {d}): {t_score:.3} s (best of 3).\n",
            car.negatives.len()
        );
        println!(
            "| prompt | target class | positives | min / median positive relevancy | max relevancy of the rest (its class) | rest ≥ 0.5 |"
        );
        println!("|---|---|---|---|---|---|");
        let grid = [0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95];
        let mut pos_all: Vec<f64> = Vec::new();
        let mut neg_all: Vec<f64> = Vec::new();
        let mut worst_neg_per_prompt: Vec<f64> = Vec::new();
        for (p, target) in synth::masks::PROMPTS {
            if !prompts.prompts.contains_key(p) {
                continue;
            }
            let q = text::build_query(&prompts, Path::new("prompts.json"), Ok(p), &opts).unwrap();
            let is_pos = |c: i32| match target {
                Some(t) => c == t,
                None => gs4city::classes::is_building(c),
            };
            let mut pos = Vec::new();
            let mut neg = Vec::new();
            let mut worst = (0.0f64, -1);
            for (row, (c, _)) in feats.rows.iter().zip(&set) {
                let Some(f) = row else { continue };
                let r = text::relevancy(&q, f, opts.temperature).0;
                if is_pos(*c) {
                    pos.push(r);
                } else {
                    neg.push(r);
                    if r > worst.0 {
                        worst = (r, *c);
                    }
                }
            }
            pos.sort_by(f64::total_cmp);
            println!(
                "| {p} | {} | {} | {} | {:.4} ({}) | {} |",
                target.map_or("building (0–5)", gs4city::classes::name),
                pos.len(),
                if pos.is_empty() {
                    "—".into()
                } else {
                    format!("{:.4} / {:.4}", pos[0], pos[pos.len() / 2])
                },
                worst.0,
                gs4city::classes::name(worst.1),
                neg.iter().filter(|&&r| r >= 0.5).count()
            );
            // The aggregate covers the prompts of one class: "a building" is a hypernym of the
            // wall / roof / window … prompts, which win against it (docs/query.md).
            if target.is_some() {
                worst_neg_per_prompt.push(worst.0);
                pos_all.extend(pos);
                neg_all.extend(neg);
            }
        }
        println!("\nPrompts with one target class (all but \"a building\"):");
        println!(
            "\n| threshold τ | positives ≥ τ (recall) | others ≥ τ (false matches) | prompts with a false match |"
        );
        println!("|---|---|---|---|");
        for t in grid {
            let rec = pos_all.iter().filter(|&&r| r >= t).count();
            let fm = neg_all.iter().filter(|&&r| r >= t).count();
            let pf = worst_neg_per_prompt.iter().filter(|&&r| r >= t).count();
            println!(
                "| {t} | {rec} / {} ({:.2} %) | {fm} / {} | {pf} / {} |",
                pos_all.len(),
                100.0 * rec as f64 / pos_all.len().max(1) as f64,
                neg_all.len(),
                worst_neg_per_prompt.len()
            );
        }
        println!();
    }
}

fn timing(run: &Path) {
    let rec: gs4city::run::store::RunRecord =
        gs4city::fsutil::read_json(&run.join("run.json")).unwrap();
    let (t_open, sr) = best_of(5, || SemanticRun::open(run, &rec.scene, None).unwrap());
    println!(
        "## Timing on {} ({} Gaussians, {} entities, {} labels; mode {:?})\n",
        run.display(),
        sr.label_of.len(),
        sr.entities.len(),
        sr.labels.labels.len(),
        sr.mode
    );
    println!("| step | best of N (s) |\n|---|---|");
    println!("| load (semantics.json, gaussians.npy, label table) | {t_open:.3} |");
    let building = sr
        .entities
        .iter()
        .find(|e| e.class == gs4city::semantics::Class::Building)
        .unwrap()
        .object_id
        .clone();
    for q in [
        "class=Window",
        "measuredHeight > 15",
        "class=Building",
        &format!("class=Window and within(\"{building}\")"),
        "not (class=RoofSurface or category=window) and level=surface",
    ] {
        let (t, (_, sel)) = best_of(5, || {
            sr.select_text("--where", q, TextOptions::default())
                .unwrap()
        });
        let (tg, g) = best_of(5, || sr.gaussian_selection(&sel.labels));
        println!(
            "| select `{q}` ({} labels, {} Gaussians) + per-Gaussian mask {tg:.3} | {t:.3} |",
            sel.labels.len(),
            g.iter().filter(|&&x| x).count()
        );
    }
    let (_, sel) = sr
        .select_text("--where", "class=Window", TextOptions::default())
        .unwrap();
    let selected = sr.gaussian_selection(&sel.labels);
    let tmp = std::env::temp_dir().join(format!("gs4city-bench-query-{}", std::process::id()));
    let mut k = 0;
    let (t_exp, counts) = best_of(5, || {
        k += 1;
        let d = tmp.join(format!("export{k}"));
        std::fs::create_dir_all(&d).unwrap();
        let opts = query::ExportOptions::default();
        let cols = query::columns(&sr);
        query::export::export(&sr.scene.ply, &cols, &selected, &opts, None, &d)
            .unwrap()
            .0
    });
    println!(
        "| export `class=Window`: extract.ply {} + remove.ply {} (byte split, fresh folder) | {t_exp:.3} |",
        counts.extracted, counts.removed
    );
    let bytes = std::fs::read(&sr.scene.ply).unwrap();
    let (t_split, _) = best_of(5, || {
        query::export::split_bytes(&sr.scene.ply, &bytes, &selected).unwrap()
    });
    println!(
        "| … of which the split in memory ({:.0} MB) | {t_split:.3} |",
        bytes.len() as f64 / 1e6
    );
    let (t_typed, _) = best_of(3, || {
        let (g, _) =
            gs4city::splat::ply::read_ply_bytes(&sr.scene.ply, &bytes, &Default::default())
                .unwrap();
        (
            query::export::subset(&g, &selected, true),
            query::export::subset(&g, &selected, false),
        )
    });
    println!("| typed path instead (read + two subsets, no write) | {t_typed:.3} |");
    let cache = sr.cache().unwrap();
    let stem = sr.test_views().unwrap()[0].clone();
    let (t_load, c) = best_of(3, || cache.load(&stem).unwrap());
    let one = selection::masks::Selections::new(&sr.class_of, &[&selected]);
    let (t_arg, _) = best_of(3, || one.masks(&c, MaskRule::Argmax));
    let (t_maj, _) = best_of(3, || one.masks(&c, MaskRule::Majority));
    println!(
        "| one view `{stem}` ({}×{}): cache load {t_load:.3}, argmax mask {t_arg:.3}, majority mask {t_maj:.3} | {:.3} |",
        c.width,
        c.height,
        t_load + t_arg
    );
    let opts = QueryOptions {
        export: true,
        ..Default::default()
    };
    let (t_full, s) = best_of(2, || {
        k += 1;
        query::run(
            &sr,
            &Request::Select(selection::grammar::parse("class=Window").unwrap()),
            &opts,
            &tmp.join(format!("full{k}")),
        )
        .unwrap()
    });
    println!(
        "| full `query --class Window --export` (select {:.3}, export {:.3}, {} masks {:.3}, SQLite {:.3}) | {t_full:.3} |",
        s.timing.select_s,
        s.timing.export_s,
        s.views.len(),
        s.timing.masks_s,
        s.timing.sqlite_s
    );
    let none = QueryOptions {
        export: true,
        views: Views::None,
        sqlite: false,
        ..Default::default()
    };
    let (t_sel_exp, _) = best_of(5, || {
        k += 1;
        let t = Instant::now();
        let sr2 = SemanticRun::open(run, &rec.scene, None).unwrap();
        query::run(
            &sr2,
            &Request::Select(selection::grammar::parse("class=Window").unwrap()),
            &none,
            &tmp.join(format!("sel{k}")),
        )
        .unwrap();
        t.elapsed().as_secs_f64()
    });
    println!("| load + select + export, no masks (the ≤ 1 s target) | {t_sel_exp:.3} |");
    let _ = std::fs::remove_dir_all(&tmp);
}

fn main() {
    let run = std::env::var_os("GS4CITY_QUERY_RUN")
        .map_or_else(|| PathBuf::from("out/results/street/run"), PathBuf::from);
    println!(
        "Command: `cargo bench --bench query` (GS4CITY_QUERY_RUN={}). Shared machine: best of N.\n",
        run.display()
    );
    let scene = gs4city::fsutil::read_json::<gs4city::run::store::RunRecord>(&run.join("run.json"))
        .map(|r| r.scene);
    match scene {
        Ok(scene) if scene.join("masks").is_dir() => calibration(&scene),
        _ => println!(
            "(no run/scene with masks at {}: calibration skipped)",
            run.display()
        ),
    }
    if run.join("render/summary.json").is_file() {
        timing(&run);
    } else {
        println!("(no finished run at {}: timing skipped)", run.display());
    }
}
