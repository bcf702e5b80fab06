//! The loss budget per class: where the fine mIoU points are lost. Benchmarks may read the
//! simulation truth; no stage does.
//!
//! ```text
//! cargo bench --bench budget -- --scene S --run NAME=RUN [--run NAME=RUN …] [--every 8] [--abstain 0.5,0.7] [--refuse TMP]
//! ```
//! `--refuse TMP` adds, per run, a re-fusion (the vote as a prior): the run's
//! voted labels (`lift/gaussians.npy`) are rendered into every training view with the
//! pipeline's pixel rule, the fused pixels no label covers take the rendered label (only an
//! image group's, then any), the repaired maps are written under `TMP/NAME`, and the gated
//! vote of `lift` runs again over them; next to it, the same vote over the run's own maps.
//! `--abstain θ,…` adds, per run and θ, the test views predicted with the Gaussians whose
//! `label_confidence` (`lift/semantic.ply`) is below θ abstaining: their weight leaves the
//! pixel's competition instead of voting for their class (per-Gaussian "unknown").
//! All runs must share the scene's geometry (the same `point_cloud.ply` and cameras; the
//! perception may differ). Rows:
//! - **(0) truth Gaussians → pixel rule**: the simulator's own per-Gaussian classes
//!   (`gt/gaussians.npy`) rendered through the cache with the pipeline's pixel rule (the class
//!   whose Gaussians weigh most), and **(0′) … → top-1**: the class of each pixel's heaviest
//!   Gaussian (the rule the simulator's truth maps are drawn with) — what a perfect per-Gaussian
//!   labelling gives under each rule;
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
    abstain: Vec<f32>,
    refuse: Option<PathBuf>,
}

fn parse() -> Args {
    let mut a = Args {
        scene: PathBuf::new(),
        runs: Vec::new(),
        every: 8,
        abstain: Vec::new(),
        refuse: None,
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
            "--refuse" => a.refuse = Some(val.into()),
            "--abstain" => {
                a.abstain = val
                    .split(',')
                    .map(|x| x.parse().expect("--abstain θ,…"))
                    .collect()
            }
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

/// The class map of a cached view with the Gaussians of confidence in (0, θ) abstaining: per
/// pixel the class with the largest summed weight of the other Gaussians, or −1 when the
/// pixel's rest (1 − α, the truncated mass) and its background-class Gaussians weigh at least
/// as much (the pipeline's pixel rule, `cache::predict_map`, without the abstaining weight).
fn abstaining(c: &gs4city::cache::ViewContrib, class: &[i32], conf: &[f32], th: f32) -> Vec<i32> {
    (0..c.pixels())
        .map(|p| {
            let (ids, ws) = c.pixel(p);
            let mut sums: Vec<(i32, f32)> = Vec::new();
            let mut none = 1.0 - c.alpha[p] + c.lists.residual[p];
            for (&g, &w) in ids.iter().zip(ws) {
                let (k, q) = (class[g as usize], conf[g as usize]);
                if q > 0.0 && q < th {
                    continue;
                }
                if k < 0 {
                    none += w;
                } else if let Some(e) = sums.iter_mut().find(|e| e.0 == k) {
                    e.1 += w;
                } else {
                    sums.push((k, w));
                }
            }
            sums.into_iter()
                .filter(|e| e.1 > none)
                .max_by(|x, y| x.1.total_cmp(&y.1).then(y.0.cmp(&x.0)))
                .map_or(-1, |e| e.0)
        })
        .collect()
}

/// Per pixel the class of its heaviest listed Gaussian (first of equal weights), or −1 where
/// the pixel's α is below 0.5 (the simulator's `output.min_alpha` default): how the truth maps
/// are drawn.
fn heaviest(c: &gs4city::cache::ViewContrib, class: &[i32]) -> Vec<i32> {
    (0..c.pixels())
        .map(|p| {
            let (ids, ws) = c.pixel(p);
            let mut best: Option<(u32, f32)> = None;
            for (&g, &w) in ids.iter().zip(ws) {
                if best.is_none_or(|b| w > b.1) {
                    best = Some((g, w));
                }
            }
            match best {
                Some((g, _)) if c.alpha[p] >= 0.5 => class[g as usize],
                _ => -1,
            }
        })
        .collect()
}

/// Per pixel the class of the Gaussian at which the accumulated α·T (lists in depth order)
/// reaches ½ — the visible surface at the median depth (`cache::median_gaussian`) — or −1
/// where the kept weights never do.
fn median_rule(c: &gs4city::cache::ViewContrib, class: &[i32]) -> Vec<i32> {
    (0..c.pixels())
        .map(|p| gs4city::cache::median_gaussian(c, p).map_or(-1, |g| class[g as usize]))
        .collect()
}

/// The counts and the leak of a per-view prediction `rule` over the test views (stem, truth).
fn scored(
    cache: &Cache,
    views: &[(String, Vec<i32>)],
    rule: impl Fn(&gs4city::cache::ViewContrib) -> Vec<i32>,
) -> (Vec<Counts>, (u64, u64)) {
    let (mut counts, mut lk) = (Vec::new(), (0, 0));
    for (stem, truth) in views {
        let pred = rule(&cache.load(stem).expect("cached test view"));
        counts.push(eval::accumulate(truth, &pred));
        let l = leak(truth, &pred);
        lk = (lk.0 + l.0, lk.1 + l.1);
    }
    (counts, lk)
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

/// The run's voted labels and their classes (`lift/gaussians.npy`, one row per Gaussian).
fn run_labels(run: &Path) -> (Vec<i32>, Vec<i32>) {
    let (_, table) = gs4city::npy::read::<i32>(&run.join("lift/gaussians.npy"))
        .expect("the run's lift/gaussians.npy");
    table.chunks(2).map(|r| (r[0], r[1])).unzip()
}

/// `lift`'s gated vote (default options) over a run's training views, for re-fusion.
struct Revote<'a> {
    ply: PathBuf,
    cache: &'a Cache,
    split: &'a Split,
    s: &'a Supervision,
    entities: Vec<gs4city::semantics::Entity>,
    raycast: PathBuf,
    mesh: PathBuf,
    scale: f64,
}

impl<'a> Revote<'a> {
    fn new(
        scene: &Path,
        run: &Path,
        split: &'a Split,
        cache: &'a Cache,
        s: &'a Supervision,
    ) -> Self {
        // The model the run lifted with: the openings stage's, where it completed the model.
        let pick = |a: &str, b: &str| {
            let p = run.join(a);
            if p.exists() { p } else { run.join(b) }
        };
        let cm: serde_json::Value =
            serde_json::from_slice(&std::fs::read(run.join("citymodel/summary.json")).unwrap())
                .unwrap();
        Revote {
            ply: gs4city::scene::Scene::open(scene).expect("scene").ply,
            cache,
            split,
            s,
            entities: gs4city::semantics::read(&pick(
                "openings/semantics.json",
                "citymodel/semantics.json",
            ))
            .expect("semantics.json"),
            raycast: pick("openings/raycast", "raycast"),
            mesh: pick("openings/mesh.ply", "citymodel/mesh.ply"),
            scale: cm["scale"].as_f64().unwrap_or(1.0),
        }
    }

    /// The per-Gaussian classes of the vote over `maps`.
    fn classes(&self, maps: &LabelMaps) -> Vec<i32> {
        let inp = gs4city::vote::VoteInputs {
            ply: &self.ply,
            cache: self.cache,
            train: &self.split.train,
            test: &self.split.test,
            maps,
            labels: &self.s.table,
            entities: &self.entities,
            city_depth: Some((&self.raycast, self.scale)),
            city_mesh: Some((&self.mesh, self.scale)),
        };
        let opts = gs4city::vote::VoteOptions::default();
        let gate = gs4city::vote::CityGate::for_inputs(&inp, opts.city_gate_m, opts.centre_gate)
            .expect("gate");
        let prior =
            gs4city::vote::ModelPrior::for_inputs(&inp, &opts, gate.as_ref().map(|g| g.centres()))
                .expect("prior");
        let (asg, _) = gs4city::vote::vote(
            self.cache,
            &self.split.train,
            maps,
            gate.as_ref(),
            prior.as_ref(),
            &opts,
        )
        .expect("vote");
        asg.iter().map(|a| self.s.table.class_of(a.label)).collect()
    }

    /// Re-fusion with the vote as a prior: `label` (the run's vote) is rendered
    /// into every training view with the pipeline's pixel rule, and a fused pixel no label
    /// covers takes the rendered label (`images_only`: only an image group's, i.e. person,
    /// car, tree). Writes the repaired maps into `tmp` and returns their number of repaired
    /// pixels.
    fn repair(&self, label: &[i32], tmp: &Path, images_only: bool) -> u64 {
        std::fs::create_dir_all(tmp).unwrap();
        let mut changed = 0u64;
        for v in &self.split.train {
            let c = self.cache.load(&v.stem()).expect("cached training view");
            let fused = self
                .s
                .maps
                .read(&v.stem(), c.width, c.height)
                .expect("label map");
            let rendered = predict_map(&c, label);
            let repaired: Vec<i32> = fused
                .iter()
                .zip(&rendered)
                .map(|(&f, &r)| {
                    if f < 0 && r >= 0 && (!images_only || r >= self.s.table.delta) {
                        changed += 1;
                        r
                    } else {
                        f
                    }
                })
                .collect();
            gs4city::npy::write(
                &tmp.join(format!("{}.ids.npy", v.stem())),
                &[c.height, c.width],
                &repaired,
            )
            .unwrap();
        }
        changed
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

    let test_views: Vec<(String, Vec<i32>)> = split
        .test
        .iter()
        .map(|v| (v.stem(), gt(&a.scene, &v.stem())))
        .collect();
    // (0) The simulator's per-Gaussian truth, rendered by the pixel rule, the top-1 rule and
    // the median rule.
    let (shape, flat) =
        gs4city::npy::read::<i32>(&a.scene.join("gt/gaussians.npy")).expect("gt/gaussians.npy");
    assert_eq!(shape[0], n, "gt/gaussians.npy rows = the cache's Gaussians");
    let truth_class: Vec<i32> = flat.chunks(shape[1]).map(|r| r[0]).collect();
    let (c, l) = scored(&cache, &test_views, |c| predict_map(c, &truth_class));
    row("(0) truth Gaussians → pixel rule (test)", &c, l);
    let (c, l) = scored(&cache, &test_views, |c| heaviest(c, &truth_class));
    row("(0′) truth Gaussians → top-1 (test)", &c, l);
    let (c, l) = scored(&cache, &test_views, |c| median_rule(c, &truth_class));
    row("(0″) truth Gaussians → median rule (test)", &c, l);

    // (a) The truth's class maps as supervision: label = class.
    let mut votes = Votes::new(n);
    for v in &split.train {
        let c = cache.load(&v.stem()).expect("cached training view");
        votes.accumulate(&c, &gt(&a.scene, &v.stem()));
    }
    let label: Vec<i32> = assign(&votes, n, 0.0).iter().map(|x| x.label).collect();
    drop(votes);
    let (counts, lk) = scored(&cache, &test_views, |c| predict_map(c, &label));
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
        let sup_counts = sup;
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
        {
            let (_, class) = run_labels(run);
            let (rows, lk) = scored(&cache, &test_views, |c| heaviest(c, &class));
            row(&format!("{name}: test (vote), top-1 rule"), &rows, lk);
            let (rows, lk) = scored(&cache, &test_views, |c| median_rule(c, &class));
            row(&format!("{name}: test (vote), median rule"), &rows, lk);
        }
        if !a.abstain.is_empty() {
            let (_, class) = run_labels(run);
            let (g, _) =
                gs4city::splat::read_ply(&run.join("lift/semantic.ply"), &Default::default())
                    .expect("the run's lift/semantic.ply");
            let conf = g
                .extra("label_confidence")
                .expect("label_confidence")
                .values
                .iter()
                .map(|&x| x as f32)
                .collect::<Vec<f32>>();
            for &th in &a.abstain {
                let (rows, lk) = scored(&cache, &test_views, |c| abstaining(c, &class, &conf, th));
                let abstained = conf.iter().filter(|&&x| x > 0.0 && x < th).count();
                row(
                    &format!("{name}: test, confidence < {th} abstains ({abstained} Gaussians)"),
                    &rows,
                    lk,
                );
            }
        }
        if let Some(tmp) = &a.refuse {
            let revote = Revote::new(&a.scene, run, &split, &cache, &s);
            let before = revote.classes(&s.maps);
            let (rows, lk) = scored(&cache, &test_views, |c| predict_map(c, &before));
            row(
                &format!("{name}: test, today's vote over the run's maps"),
                &rows,
                lk,
            );
            let (label, _) = run_labels(run);
            for images_only in [true, false] {
                let dir = tmp.join(format!("{name}-{images_only}"));
                let changed = revote.repair(&label, &dir, images_only);
                let after = revote.classes(&LabelMaps::Fused(dir));
                let (rows, lk) = scored(&cache, &test_views, |c| predict_map(c, &after));
                let what = if images_only {
                    "image groups"
                } else {
                    "any label"
                };
                row(
                    &format!(
                        "{name}: test, re-fused ({changed} unlabelled training pixels take the rendered vote's label, {what})"
                    ),
                    &rows,
                    lk,
                );
            }
        }
        per_run.push((format!("{name}: supervision"), sup_counts));
        per_run.push((name.clone(), test));
    }
    confusion("(a) truth class maps → vote", &truth_counts);
    for (name, test) in &per_run {
        confusion(name, test);
    }
}
