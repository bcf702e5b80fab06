//! Identity training on a finished run folder: speed against error.
//!
//! ```text
//! cargo bench --bench train -- --run /work/runs/street_core --scene /work/scenes/street \
//!     [--exp sweep|softmax|predict|all] [--stride 2] [--top-k 0] [--out FILE.json]
//! ```
//! Reads the run's `render/` cache, `raycast/` maps (M_city) and `citymodel/`; builds the
//! training pixels once per (stride, top-k), then trains each configuration, scoring the 16 test
//! views against the scene's `gt/` (benchmarks may read it; the stage never does) at
//! checkpoints. Prints markdown tables; timings are wall-clock on a shared machine.
use std::path::{Path, PathBuf};
use std::time::Instant;

use gs4city::classes;
use gs4city::eval::{self, Counts};
use gs4city::labels::LabelTable;
use gs4city::lift::{self, LabelMaps};
use gs4city::render::cache::{Cache, ViewContrib};
use gs4city::scene::Split;
use gs4city::train::model::{self, Active, Grads};
use gs4city::train::{self, Init, Softmax, TrainOptions, knn, pool, predict};

struct Args {
    run: PathBuf,
    scene: PathBuf,
    exp: String,
    strides: Vec<usize>,
    top_ks: Vec<usize>,
    out: Option<PathBuf>,
    checkpoints: Vec<usize>,
    configs: String,
    /// Train on this fused folder (labels.json, <stem>.ids.npy) instead of M_city.
    fuse: Option<PathBuf>,
}

fn parse() -> Args {
    let mut a = Args {
        run: PathBuf::from("/work/runs/street_core"),
        scene: PathBuf::from("/work/scenes/street"),
        exp: "sweep".into(),
        strides: vec![2],
        top_ks: vec![0],
        out: None,
        checkpoints: vec![0, 250, 500, 1000, 2000, 3000],
        configs: "default".into(),
        fuse: None,
    };
    let v: Vec<String> = std::env::args().skip(1).collect();
    let list = |s: &str| s.split(',').map(|x| x.parse().expect("number")).collect();
    let mut i = 0;
    while i < v.len() {
        let val = v.get(i + 1).cloned().unwrap_or_default();
        match v[i].as_str() {
            "--run" => a.run = val.into(),
            "--scene" => a.scene = val.into(),
            "--exp" => a.exp = val,
            "--stride" => a.strides = list(&val),
            "--top-k" => a.top_ks = list(&val),
            "--out" => a.out = Some(val.into()),
            "--checkpoints" => a.checkpoints = list(&val),
            "--configs" => a.configs = val,
            "--fuse" => a.fuse = Some(val.into()),
            "--bench" => {
                i += 1;
                continue;
            }
            other => panic!("unknown argument {other}"),
        }
        i += 2;
    }
    a
}

/// Test views kept in memory with their GT.
struct TestSet {
    views: Vec<(String, ViewContrib, Vec<i32>)>,
}

fn fine_miou(counts: &[Counts]) -> (f64, f64, [Option<f64>; eval::N_FINE]) {
    let p = eval::paper(counts);
    let d = eval::dataset(counts);
    let per: [Option<f64>; eval::N_FINE] = std::array::from_fn(|k| p.class_iou[k].mean);
    (p.miou.mean.unwrap_or(0.0), d.fine.miou.unwrap_or(0.0), per)
}

/// Scores per-view class maps.
fn score(test: &TestSet, maps: &[Vec<i32>]) -> (f64, f64, [Option<f64>; eval::N_FINE]) {
    let counts: Vec<Counts> = test
        .views
        .iter()
        .zip(maps)
        .map(|((_, _, gt), p)| eval::accumulate(gt, p))
        .collect();
    fine_miou(&counts)
}

struct Ctx {
    cache: Cache,
    split: Split,
    maps: LabelMaps,
    table: LabelTable,
    ply: PathBuf,
    test: TestSet,
}

fn context(a: &Args) -> Ctx {
    let cache = Cache::open(&a.run.join("render")).expect("cache");
    let split = Split::new(
        gs4city::colmap::read_model(&a.scene.join("sparse/0")).expect("colmap"),
        8,
    );
    let entities =
        gs4city::citymodel::read_semantics(&a.run.join("citymodel/semantics.json")).expect("sem");
    let (maps, table) = match &a.fuse {
        Some(f) => (
            LabelMaps::Fused(f.clone()),
            LabelTable::read(&f.join("labels.json")).expect("labels.json"),
        ),
        None => (
            LabelMaps::City(a.run.join("raycast")),
            LabelTable::city(&entities, &classes::table(&entities)).expect("table"),
        ),
    };
    let views = split
        .test
        .iter()
        .map(|v| {
            let c = cache.load(&v.stem()).expect("test view");
            let (_, gt) =
                gs4city::npy::read::<i32>(&a.scene.join(format!("gt/{}.class.npy", v.stem())))
                    .expect("gt");
            (v.stem(), c, gt)
        })
        .collect();
    Ctx {
        cache,
        split,
        maps,
        table,
        ply: a.scene.join("point_cloud.ply"),
        test: TestSet { views },
    }
}

/// Test-view class maps of a model (view candidates, or every class).
fn predict_all(
    ctx: &Ctx,
    m: &model::Model<f32>,
    class_ids: &[i32],
    exact: bool,
) -> (Vec<Vec<i32>>, Vec<Vec<i32>>) {
    let gclass = predict::gaussian_classes(m);
    let c = m.classes();
    ctx.test
        .views
        .iter()
        .map(|(_, v, _)| {
            let cand = if exact {
                (0..c as u32).collect()
            } else {
                predict::view_candidates(v, &gclass, c)
            };
            predict::predict_view(v, m, &cand, class_ids, &|l| ctx.table.class_of(l))
        })
        .unzip()
}

/// CPU seconds (user + system) of this process so far.
fn cpu_s() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let f: Vec<&str> = s
        .rsplit(')')
        .next()
        .unwrap_or("")
        .split_whitespace()
        .collect();
    let tick = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

fn fmt_row(name: &str, it: usize, secs: f64, r: (f64, f64, [Option<f64>; eval::N_FINE])) -> String {
    let per =
        r.2.iter()
            .take(4)
            .map(|x| x.map_or("–".into(), |v| format!("{:.1}", 100.0 * v)))
            .collect::<Vec<_>>()
            .join(" | ");
    format!(
        "| {name} | {it} | {secs:.1} | **{:.2}** | {:.2} | {per} |",
        100.0 * r.0,
        100.0 * r.1
    )
}

fn configs(name: &str) -> Vec<(String, TrainOptions)> {
    let d = TrainOptions {
        tol: 0.0,
        ..TrainOptions::default()
    };
    let with = |f: &dyn Fn(&mut TrainOptions)| {
        let mut o = d;
        f(&mut o);
        o
    };
    let mut v: Vec<(String, TrainOptions)> = Vec::new();
    for n in name.split(',') {
        match n {
            "default" => v.push(("default".into(), d)),
            "px2048" => v.push(("2048 px/it".into(), with(&|o| o.pixels = 2048))),
            "px32768" => v.push(("32768 px/it".into(), with(&|o| o.pixels = 32768))),
            "nokl" => v.push(("no 3D term".into(), with(&|o| o.kl_lambda = 0.0))),
            "exact" => v.push((
                "exact softmax".into(),
                with(&|o| o.softmax = Softmax::Exact),
            )),
            "random" => v.push(("random init".into(), with(&|o| o.init = Init::Random))),
            "lr10" => v.push((
                "lr ×10".into(),
                with(&|o| {
                    o.lr_codes *= 10.0;
                    o.lr_classifier *= 10.0
                }),
            )),
            "beta4" => v.push(("init β 4".into(), with(&|o| o.init_scale = 4.0))),
            "beta16" => v.push(("init β 16".into(), with(&|o| o.init_scale = 16.0))),
            other => panic!("unknown config {other}"),
        }
    }
    v
}

fn sweep(a: &Args, ctx: &Ctx, out: &mut Vec<serde_json::Value>) {
    for &stride in &a.strides {
        for &top_k in &a.top_ks {
            let t = Instant::now();
            let pool = pool::build(
                &ctx.cache,
                &ctx.split.train,
                &ctx.maps,
                &ctx.table,
                stride,
                top_k,
                0.0,
            )
            .expect("pool");
            let pool_s = t.elapsed().as_secs_f64();
            let (g, _) = gs4city::splat::read_ply(&ctx.ply, &Default::default()).expect("ply");
            let t = Instant::now();
            let graph = knn::build(&g.positions, 5);
            let knn_s = t.elapsed().as_secs_f64();
            drop(g);
            println!(
                "\n### stride {stride}, top-k {} — {} training pixels ({:.0} MB), {} classes; read+vote {pool_s:.1} s, kNN {knn_s:.1} s\n",
                if top_k == 0 {
                    "as cached".to_string()
                } else {
                    top_k.to_string()
                },
                pool.pixels(),
                pool.bytes() as f64 / 1e6,
                pool.class_ids.len()
            );
            // The vote, predicted as `lift` does.
            let vote_label: Vec<i32> = pool.vote.iter().map(|x| x.label).collect();
            let vote_class: Vec<i32> = vote_label.iter().map(|&l| ctx.table.class_of(l)).collect();
            let vote_maps: Vec<Vec<i32>> = ctx
                .test
                .views
                .iter()
                .map(|(_, v, _)| {
                    let v = pool::truncate(v, top_k);
                    lift::predict(&v, &vote_label, &vote_class).0
                })
                .collect();
            let rv = score(&ctx.test, &vote_maps);
            println!(
                "| config | iterations | train s | fine mIoU paper | fine mIoU dataset | wall | roof | window | door |"
            );
            println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
            println!("{}", fmt_row("vote (lift)", 0, 0.0, rv));
            out.push(serde_json::json!({"stride": stride, "top_k": top_k, "config": "vote", "miou": rv.0, "miou_dataset": rv.1}));
            for (name, opts) in configs(&a.configs) {
                let vc = train::vote_classes(&pool);
                let m = train::init_model(pool.vote.len(), pool.class_ids.len(), &vc, &opts);
                let mut tr = train::Trainer::new(&pool, &graph, m, vc, &opts);
                let (mut secs, mut cpu) = (0.0, 0.0);
                for &cp in &a.checkpoints {
                    let t = Instant::now();
                    let c0 = cpu_s();
                    while tr.iteration < cp {
                        tr.step();
                    }
                    secs += t.elapsed().as_secs_f64();
                    cpu += cpu_s() - c0;
                    let (cm, _) = predict_all(ctx, &tr.model, &pool.class_ids, false);
                    let r = score(&ctx.test, &cm);
                    // The learned per-Gaussian labels, predicted with the vote's pixel rule.
                    let gl: Vec<i32> = predict::gaussian_classes(&tr.model)
                        .iter()
                        .map(|&c| pool.class_ids[c as usize])
                        .collect();
                    let gc: Vec<i32> = gl.iter().map(|&l| ctx.table.class_of(l)).collect();
                    let lm: Vec<Vec<i32>> = ctx
                        .test
                        .views
                        .iter()
                        .map(|(_, v, _)| lift::predict(&pool::truncate(v, top_k), &gl, &gc).0)
                        .collect();
                    let rl = score(&ctx.test, &lm);
                    println!(
                        "{} {cpu:.1} cpu-s | {:.2} |",
                        fmt_row(&name, cp, secs, r),
                        100.0 * rl.0
                    );
                    out.push(serde_json::json!({"stride": stride, "top_k": top_k, "config": name,
                        "pixels": opts.pixels, "iterations": cp, "train_s": secs, "cpu_s": cpu, "miou": r.0, "miou_dataset": r.1,
                        "miou_labels_vote_rule": rl.0, "times": tr.times}));
                }
                eprintln!("{name}: {:?}", tr.times);
            }
        }
    }
}

/// Sampled vs exact softmax on the same batches: loss and gradient error.
fn softmax_error(ctx: &Ctx, out: &mut Vec<serde_json::Value>) {
    let opts = TrainOptions::default();
    let pool = pool::build(
        &ctx.cache,
        &ctx.split.train,
        &ctx.maps,
        &ctx.table,
        4,
        0,
        0.0,
    )
    .expect("pool");
    let (g, _) = gs4city::splat::read_ply(&ctx.ply, &Default::default()).expect("ply");
    let graph = knn::build(&g.positions, 5);
    drop(g);
    let vc = train::vote_classes(&pool);
    let c = pool.class_ids.len();
    // Train a little first, so the classifier is not the initial one.
    let m = train::init_model(pool.vote.len(), c, &vc, &opts);
    let mut tr = train::Trainer::new(&pool, &graph, m, vc, &opts);
    println!("\n### sampled vs exact softmax ({c} classes), same batches\n");
    println!(
        "| after iterations | negatives | active classes | CE exact | CE sampled | rel. loss error | grad cos (codes) | grad rel. error (codes) | time exact ms | time sampled ms |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for stage in [0usize, 500] {
        while tr.iteration < stage {
            tr.step();
        }
        for negatives in [16usize, 64, 256] {
            let (mut le, mut ls, mut dot, mut ne, mut ns, mut diff) =
                (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
            let (mut te, mut ts, mut act) = (0.0, 0.0, 0usize);
            let reps = 8;
            for _ in 0..reps {
                let (batch, a) = tr.sample_batch();
                let members = a.members.clone();
                let sampled = Active::sampled(c, members, negatives, &mut tr.rng);
                act += sampled.members.len();
                let scale = 1.0 / (batch.len() as f64 * (c as f64).ln());
                let mut ge = Grads::new(&tr.model);
                let t = Instant::now();
                le += model::cross_entropy(&tr.model, &batch, &Active::full(c), scale, &mut ge);
                te += t.elapsed().as_secs_f64();
                let mut gs = Grads::new(&tr.model);
                let t = Instant::now();
                ls += model::cross_entropy(&tr.model, &batch, &sampled, scale, &mut gs);
                ts += t.elapsed().as_secs_f64();
                for (x, y) in ge.codes.iter().zip(&gs.codes) {
                    let (x, y) = (f64::from(*x), f64::from(*y));
                    dot += x * y;
                    ne += x * x;
                    ns += y * y;
                    diff += (x - y) * (x - y);
                }
            }
            let cos = dot / (ne.sqrt() * ns.sqrt());
            let rel = (diff / ne).sqrt();
            println!(
                "| {stage} | {negatives} | {} | {:.5} | {:.5} | {:.2e} | {cos:.5} | {rel:.3} | {:.1} | {:.1} |",
                act / reps,
                le / reps as f64,
                ls / reps as f64,
                ((ls - le) / le).abs(),
                1e3 * te / reps as f64,
                1e3 * ts / reps as f64
            );
            out.push(serde_json::json!({"exp": "softmax", "after": stage, "negatives": negatives,
                "ce_exact": le / reps as f64, "ce_sampled": ls / reps as f64, "grad_cos": cos, "grad_rel": rel,
                "ms_exact": 1e3 * te / reps as f64, "ms_sampled": 1e3 * ts / reps as f64}));
        }
    }
    // Prediction over the view's candidate classes vs every class.
    let t = Instant::now();
    let (cand, _) = predict_all(ctx, &tr.model, &pool.class_ids, false);
    let tc = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (full, _) = predict_all(ctx, &tr.model, &pool.class_ids, true);
    let tf = t.elapsed().as_secs_f64();
    let (mut diff, mut total) = (0usize, 0usize);
    for (a, b) in cand.iter().zip(&full) {
        total += a.len();
        diff += a.iter().zip(b).filter(|(x, y)| x != y).count();
    }
    println!(
        "\nTest-view prediction after {} iterations: view candidates vs every class: {diff} of {total} pixels differ in class ({:.4} %); {tc:.1} s vs {tf:.1} s for 16 views (incl. the per-Gaussian argmax).",
        tr.iteration,
        100.0 * diff as f64 / total as f64
    );
    out.push(serde_json::json!({"exp": "predict", "differ": diff, "pixels": total, "s_candidates": tc, "s_exact": tf}));
}

/// Writes a SIMULATED fused folder into `out`: per view, the GT instance as an image label
/// (`Δ + instance − 10⁶`) where the GT class is non-building (perfect masks of trees, cars,
/// persons, ground, water, other), else the run's `M_city`; `labels.json` lists every id. A
/// stand-in for the `fuse` stage's output, built from simulation truth: benchmark only.
fn simulate_fused(a: &Args, out: &Path) {
    let entities =
        gs4city::citymodel::read_semantics(&a.run.join("citymodel/semantics.json")).expect("sem");
    let city = LabelTable::city(&entities, &classes::table(&entities)).expect("table");
    let delta = city.delta;
    std::fs::create_dir_all(out).expect("mkdir");
    let mut image: std::collections::BTreeMap<i32, i32> = Default::default();
    let (mut replaced, mut total) = (0usize, 0usize);
    for v in gs4city::colmap::read_model(&a.scene.join("sparse/0")).expect("colmap") {
        let stem = v.stem();
        let (shape, ids) =
            gs4city::npy::read::<i32>(&a.run.join(format!("raycast/{stem}.ids.npy"))).expect("ids");
        let npx = shape[1] * shape[2];
        let (_, class) =
            gs4city::npy::read::<i32>(&a.scene.join(format!("gt/{stem}.class.npy"))).expect("gt");
        let (_, inst) = gs4city::npy::read::<i32>(&a.scene.join(format!("gt/{stem}.instance.npy")))
            .expect("gt");
        let fused: Vec<i32> = (0..npx)
            .map(|p| {
                let c = class[p];
                if c >= classes::TREE && inst[p] >= 1_000_000 {
                    let id = delta + (inst[p] - 1_000_000);
                    image.entry(id).or_insert(c);
                    replaced += 1;
                    id
                } else {
                    ids[3 * npx + p]
                }
            })
            .collect();
        total += npx;
        gs4city::npy::write(&out.join(format!("{stem}.ids.npy")), &shape[1..], &fused).expect("w");
    }
    let mut labels = city.labels.clone();
    for (&id, &c) in &image {
        labels.push(gs4city::labels::Label {
            id,
            source: gs4city::labels::Source::Image,
            entity: None,
            group: Some(id - delta),
            class: c,
            level: None,
        });
    }
    LabelTable::new(delta, labels)
        .expect("table")
        .write(&out.join("labels.json"))
        .expect("labels.json");
    println!(
        "SIMULATED fused labels → {}: {} image labels, {replaced} of {total} pixels ({:.1} %) take an image label",
        out.display(),
        image.len(),
        100.0 * replaced as f64 / total as f64
    );
}

fn main() {
    let a = parse();
    if a.exp == "simfuse" {
        simulate_fused(&a, a.out.as_deref().expect("--out DIR"));
        return;
    }
    let ctx = context(&a);
    let mut out = Vec::new();
    if a.exp == "sweep" || a.exp == "all" {
        sweep(&a, &ctx, &mut out);
    }
    if a.exp == "softmax" || a.exp == "all" {
        softmax_error(&ctx, &mut out);
    }
    if let Some(p) = &a.out {
        std::fs::write(p, serde_json::to_string_pretty(&out).expect("json")).expect("write");
    }
}
