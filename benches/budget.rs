//! The loss budget per class: where the fine mIoU points are lost (issue 23, BENCHMARKS.md
//! "Loss budget"). Benchmarks may read the simulation truth; no stage does.
//!
//! ```text
//! cargo bench --bench budget -- --scene S --run NAME=RUN [--run NAME=RUN …] [--every 8]
//! ```
//! All runs must share the scene's geometry (the same `point_cloud.ply` and cameras; the
//! perception may differ). Rows:
//! - **(a) truth → vote**: the vote of the *ground-truth class maps* of the training views over
//!   the first run's contributions cache, predicted on the test views with the pipeline's pixel
//!   rule — the limit of the Gaussians and the cache;
//! - per run, **supervision**: the class maps the run lifts from (`fuse/` when present, else
//!   `M_city`), scored on the *training* views — what the vote is given;
//! - per run, **test**: the run's test-view class maps (`lift/`) — what the pipeline delivers.
//!
//! A run over an oracle-perception scene (`data/synth/perception_oracle.toml`: one exact mask
//! per instance, noise-free features) gives (b), the limit of association and fusion.
//! "leak %" is the share of the pixels of non-fine truth classes (road, ground, water, other)
//! given a fine class — what the fine metrics do not see. Then, per run, the confusion of its
//! test views (dataset counts, % of each truth class).
use std::path::{Path, PathBuf};

use gs4city::cache::{Cache, predict_map};
use gs4city::classes;
use gs4city::eval::{self, Counts};
use gs4city::idmap::LabelMaps;
use gs4city::labels::LabelTable;
use gs4city::scene::Split;
use gs4city::vote::{Votes, assign};

struct Args {
    scene: PathBuf,
    runs: Vec<(String, PathBuf)>,
    every: usize,
}

fn parse() -> Args {
    let mut a = Args {
        scene: PathBuf::new(),
        runs: Vec::new(),
        every: 8,
    };
    let v: Vec<String> = std::env::args().skip(1).collect();
    let mut i = 0;
    while i < v.len() {
        let val = v.get(i + 1).cloned().unwrap_or_default();
        match v[i].as_str() {
            "--scene" => a.scene = val.into(),
            "--run" => {
                let (n, r) = val.split_once('=').expect("--run NAME=RUN");
                a.runs.push((n.to_string(), r.into()));
            }
            "--every" => a.every = val.parse().expect("number"),
            "--bench" => {
                i += 1;
                continue;
            }
            other => panic!("unknown argument {other}"),
        }
        i += 2;
    }
    assert!(!a.runs.is_empty(), "at least one --run NAME=RUN");
    a
}

fn gt(scene: &Path, stem: &str) -> Vec<i32> {
    gs4city::npy::read::<i32>(&scene.join(format!("gt/{stem}.class.npy")))
        .expect("gt class map")
        .1
}

/// Pixels of a non-fine truth class (road, ground, water, other; not the unlabelled −1) that
/// `pred` gives a fine class, and all such pixels: what the fine metrics do not see.
fn leak(truth: &[i32], pred: &[i32]) -> (u64, u64) {
    let mut l = (0, 0);
    for (&t, &p) in truth.iter().zip(pred) {
        if t >= 0 && !classes::FINE.contains(&t) {
            l.1 += 1;
            l.0 += u64::from(classes::FINE.contains(&p));
        }
    }
    l
}

/// One row: paper fine mIoU, dataset fine mIoU, the leak, per fine class paper IoU
/// (precision / recall).
fn row(name: &str, counts: &[Counts], leak: (u64, u64)) {
    let p = eval::paper(counts);
    let d = eval::dataset(counts);
    let f = |x: Option<f64>| x.map_or("–".to_string(), |x| format!("{:.1}", 100.0 * x));
    let cells: Vec<String> = (0..eval::N_FINE)
        .map(|k| {
            format!(
                "{} ({}/{})",
                f(p.class_iou[k].mean),
                f(p.class_precision[k].mean),
                f(p.class_recall[k].mean)
            )
        })
        .collect();
    println!(
        "| {name} | {} | {} | {:.1} | {} |",
        f(p.miou.mean),
        f(d.fine.miou),
        100.0 * leak.0 as f64 / leak.1.max(1) as f64,
        cells.join(" | ")
    );
}

/// The confusion of summed counts as % of each truth class.
fn confusion(name: &str, counts: &[Counts]) {
    let d = eval::dataset(counts);
    println!("\n{name}: test-view confusion, % of each truth class's pixels (dataset)\n");
    let names: Vec<&str> = classes::FINE.iter().map(|&c| classes::name(c)).collect();
    println!(
        "| truth \\ predicted | {} | none/other |",
        names.join(" | ")
    );
    println!("|---|{}---|", "---|".repeat(names.len()));
    for (k, n) in names.iter().enumerate() {
        let r = &d.counts.fine[k];
        let total: u64 = r.iter().sum();
        if total == 0 {
            continue;
        }
        let cells: Vec<String> = r
            .iter()
            .map(|&x| format!("{:.1}", 100.0 * x as f64 / total as f64))
            .collect();
        println!("| {n} | {} |", cells.join(" | "));
    }
}

/// The class maps a run lifts from, for view `stem`.
struct Supervision {
    maps: LabelMaps,
    table: LabelTable,
}

fn supervision(run: &Path) -> Supervision {
    let fuse = run.join("fuse");
    if fuse.join("labels.json").exists() {
        return Supervision {
            table: LabelTable::read(&fuse.join("labels.json")).expect("labels.json"),
            maps: LabelMaps::Fused(fuse),
        };
    }
    let entities = gs4city::semantics::read(&run.join("citymodel/semantics.json")).expect("sem");
    Supervision {
        table: LabelTable::city(&entities, &classes::table(&entities)).expect("table"),
        maps: LabelMaps::City(run.join("raycast")),
    }
}

fn main() {
    let a = parse();
    let views = gs4city::colmap::read_model(&a.scene.join("sparse/0")).expect("colmap");
    let split = Split::new(views, a.every);
    let cache = Cache::open(&a.runs[0].1.join("render")).expect("cache of the first run");
    let n = cache.summary.gaussians;
    println!(
        "scene {} · {} training / {} test views · {n} Gaussians · cache of {}\n",
        a.scene.display(),
        split.train.len(),
        split.test.len(),
        a.runs[0].1.display()
    );
    println!(
        "| source | fine mIoU (paper) | fine mIoU (dataset) | leak % | {} |",
        classes::FINE
            .iter()
            .map(|&c| format!("{} IoU (P/R)", classes::name(c)))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    println!("|---|---|---|---|{}", "---|".repeat(classes::FINE.len()));

    // (a) The truth's class maps as supervision: label = class.
    let mut votes = Votes::new(n);
    for v in &split.train {
        let c = cache.load(&v.stem()).expect("cached training view");
        votes.accumulate(&c, &gt(&a.scene, &v.stem()));
    }
    let label: Vec<i32> = assign(&votes, n, 0.0).iter().map(|x| x.label).collect();
    drop(votes);
    let mut test_views = Vec::new();
    let mut counts = Vec::new();
    let mut lk = (0, 0);
    for v in &split.test {
        let c = cache.load(&v.stem()).expect("cached test view");
        let truth = gt(&a.scene, &v.stem());
        let pred = predict_map(&c, &label);
        counts.push(eval::accumulate(&truth, &pred));
        let l = leak(&truth, &pred);
        lk = (lk.0 + l.0, lk.1 + l.1);
        test_views.push((v.stem(), truth));
    }
    row("(a) truth class maps → vote (test)", &counts, lk);
    let truth_counts = counts;

    let mut per_run = Vec::new();
    for (name, run) in &a.runs {
        let s = supervision(run);
        let mut sup = Vec::new();
        let mut lk = (0, 0);
        for v in &split.train {
            let truth = gt(&a.scene, &v.stem());
            let c = cache.load(&v.stem()).expect("cached training view");
            let l = s
                .maps
                .read(&v.stem(), c.width, c.height)
                .expect("label map");
            let cls: Vec<i32> = l.iter().map(|&x| s.table.class_of(x)).collect();
            sup.push(eval::accumulate(&truth, &cls));
            let l = leak(&truth, &cls);
            lk = (lk.0 + l.0, lk.1 + l.1);
        }
        row(&format!("{name}: supervision (training views)"), &sup, lk);
        let mut test = Vec::new();
        let mut lk = (0, 0);
        for (stem, truth) in &test_views {
            let (_, pred) = gs4city::npy::read::<i32>(&run.join(format!("lift/{stem}.class.npy")))
                .expect("the run's lift test-view class map");
            test.push(eval::accumulate(truth, &pred));
            let l = leak(truth, &pred);
            lk = (lk.0 + l.0, lk.1 + l.1);
        }
        row(&format!("{name}: test (vote)"), &test, lk);
        per_run.push((name.clone(), test));
    }
    confusion("(a) truth class maps → vote", &truth_counts);
    for (name, test) in &per_run {
        confusion(name, test);
    }
}
