//! Identity training on a finished run folder: speed against error.
//!
//! ```text
//! cargo bench --bench train -- --run out/results/street/run --scene out/results/street/scene \
//!     [--fuse FUSE_DIR] [--exp sweep|softmax|simfuse|all] [--stride 2] [--top-k 0] \
//!     [--checkpoints 0,500,…] [--configs default,lr=10:mu=0.5,…|none] \
//!     [--rules gaussians,label,class] [--holdout 8] [--out FILE.json]
//! ```
//! Reads the run's `render/` cache, `raycast/` maps (M_city) or the `--fuse` folder, and
//! `citymodel/`; builds the training pixels once per (stride, top-k), then trains each
//! configuration, scoring the 16 test views against the scene's `gt/` (benchmarks may read it;
//! the stage never does) at checkpoints with each prediction rule. `--holdout N` keeps every
//! N-th training view out of the vote and of training and scores it against its own label
//! map's classes (the selection signal) and against the truth. Prints markdown tables; timings
//! are CPU seconds on a shared machine.
use std::path::{Path, PathBuf};
use std::time::Instant;

use gs4city::cache::{Cache, ViewContrib};
use gs4city::classes;
use gs4city::eval::{self, Counts};
use gs4city::idmap::LabelMaps;
use gs4city::labels::LabelTable;
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
    /// Every N-th training view is held out (not voted, not trained on) and scored against
    /// the training label maps' classes: the selection set (0 = none).
    holdout: usize,
    /// Predictors scored at each checkpoint: label, class, gaussians.
    rules: Vec<predict::Rule>,
}

fn parse() -> Args {
    let mut a = Args {
        run: PathBuf::from("out/results/street/run"),
        scene: PathBuf::from("out/results/street/scene"),
        exp: "sweep".into(),
        strides: vec![2],
        top_ks: vec![0],
        out: None,
        checkpoints: vec![0, 250, 500, 1000, 2000, 3000],
        configs: "default".into(),
        fuse: None,
        holdout: 0,
        rules: vec![
            predict::Rule::Label,
            predict::Rule::Class,
            predict::Rule::Gaussians,
        ],
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
            "--holdout" => a.holdout = val.parse().expect("number"),
            "--rules" => {
                a.rules = val
                    .split(',')
                    .map(|r| match r {
                        "label" => predict::Rule::Label,
                        "class" => predict::Rule::Class,
                        "gaussians" => predict::Rule::Gaussians,
                        _ => panic!("unknown rule {r}"),
                    })
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

    maps: LabelMaps,
    table: LabelTable,
    ply: PathBuf,
    test: TestSet,
    /// The views trained on (the split's training views less the held-out ones).
    train: Vec<gs4city::camera::View>,
    /// Held-out training views with the classes of their training label maps as truth.
    val: TestSet,
    /// The same held-out views with the simulation truth (scoring only).
    val_gt: TestSet,
}

fn context(a: &Args) -> Ctx {
    let cache = Cache::open(&a.run.join("render")).expect("cache");
    let split = Split::new(
        gs4city::colmap::read_model(&a.scene.join("sparse/0")).expect("colmap"),
        8,
    );
    let entities = gs4city::semantics::read(&a.run.join("citymodel/semantics.json")).expect("sem");
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
    let (mut train, mut val, mut val_gt) = (Vec::new(), Vec::new(), Vec::new());
    for (i, v) in split.train.iter().enumerate() {
        if a.holdout > 0 && i % a.holdout == a.holdout - 1 {
            let c = cache.load(&v.stem()).expect("held-out view");
            let labels = maps.read(&v.stem(), c.width, c.height).expect("label map");
            let truth = labels.iter().map(|&l| table.class_of(l)).collect();
            let (_, gt) =
                gs4city::npy::read::<i32>(&a.scene.join(format!("gt/{}.class.npy", v.stem())))
                    .expect("gt");
            val_gt.push((v.stem(), c.clone(), gt));
            val.push((v.stem(), c, truth));
        } else {
            train.push(v.clone());
        }
    }
    Ctx {
        cache,

        maps,
        table,
        ply: a.scene.join("point_cloud.ply"),
        test: TestSet { views },
        train,
        val: TestSet { views: val },
        val_gt: TestSet { views: val_gt },
    }
}

/// Class maps of a model over `set` (view candidates, or every class), read with `rule`.
fn predict_all(
    ctx: &Ctx,
    set: &TestSet,
    m: &model::Model<f32>,
    gclass: &[u32],
    class_ids: &[i32],
    exact: bool,
    rule: predict::Rule,
) -> (Vec<Vec<i32>>, Vec<Vec<i32>>) {
    let c = m.classes();
    let gl: Vec<i32> = gclass.iter().map(|&k| class_ids[k as usize]).collect();
    let gc: Vec<i32> = gl.iter().map(|&l| ctx.table.class_of(l)).collect();
    set.views
        .iter()
        .map(|(_, v, _)| {
            if rule == predict::Rule::Gaussians {
                return gs4city::cache::predict(v, &gl, &gc);
            }
            let cand = if exact {
                (0..c as u32).collect()
            } else {
                predict::view_candidates(v, gclass, c)
            };
            let by_class = rule == predict::Rule::Class;
            predict::predict_view(v, m, &cand, class_ids, &|l| ctx.table.class_of(l), by_class)
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
            "none" => {}
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
            "class05" => v.push(("class term μ 0.5".into(), with(&|o| o.class_weight = 0.5))),
            "class1" => v.push(("class term μ 1".into(), with(&|o| o.class_weight = 1.0))),
            "lr10class" => v.push((
                "lr ×10, class term μ 0.5".into(),
                with(&|o| {
                    o.lr_codes *= 10.0;
                    o.lr_classifier *= 10.0;
                    o.class_weight = 0.5
                }),
            )),
            // `lr=F:mu=F:px=N:kl=F:beta=F:m=N:every=N`: learning rates ×F, class term μ, pixels
            // per iteration, λ, initial β, Gaussians per 3D step, iterations between 3D steps.
            other if other.contains('=') => {
                let mut o = d;
                for kv in other.split(':') {
                    let (k, x) = kv.split_once('=').expect("key=value");
                    let x: f64 = x.parse().expect("number");
                    match k {
                        "lr" => {
                            o.lr_codes *= x;
                            o.lr_classifier *= x
                        }
                        "mu" => o.class_weight = x,
                        "px" => o.pixels = x as usize,
                        "kl" => o.kl_lambda = x,
                        "beta" => o.init_scale = x,
                        "m" => o.kl_samples = x as usize,
                        "every" => o.kl_every = x as usize,
                        _ => panic!("unknown key {k}"),
                    }
                }
                v.push((other.to_string(), o));
            }
            other => panic!("unknown config {other}"),
        }
    }
    v
}

/// Pixels where `pred` differs from `base`: (changed, of them right in `pred`, right in `base`),
/// against `truth` (pixels with truth < 0 skipped).
fn changes(set: &TestSet, base: &[Vec<i32>], pred: &[Vec<i32>]) -> (usize, usize, usize) {
    let (mut n, mut good, mut bad) = (0, 0, 0);
    for (((_, _, gt), b), p) in set.views.iter().zip(base).zip(pred) {
        for ((&g, &x), &y) in gt.iter().zip(b).zip(p) {
            if g >= 0 && x != y {
                n += 1;
                good += usize::from(y == g);
                bad += usize::from(x == g);
            }
        }
    }
    (n, good, bad)
}

/// A fraction as a percentage with two decimals; "–" for NaN (no held-out views).
fn pct(x: f64) -> String {
    if x.is_nan() {
        "–".into()
    } else {
        format!("{:.2}", 100.0 * x)
    }
}

fn per_class(r: &(f64, f64, [Option<f64>; eval::N_FINE])) -> String {
    r.2.iter()
        .map(|x| x.map_or("–".into(), |v| format!("{:.1}", 100.0 * v)))
        .collect::<Vec<_>>()
        .join(" | ")
}

fn sweep(a: &Args, ctx: &Ctx, out: &mut Vec<serde_json::Value>) {
    let rules: Vec<(&str, predict::Rule)> = a
        .rules
        .iter()
        .map(|&r| match r {
            predict::Rule::Label => ("code→label", r),
            predict::Rule::Class => ("code→class", r),
            predict::Rule::Gaussians => ("Gaussian labels, vote rule", r),
        })
        .collect();
    for &stride in &a.strides {
        for &top_k in &a.top_ks {
            let t = Instant::now();
            let pool = pool::build(
                &ctx.cache, &ctx.train, &ctx.maps, &ctx.table, None, stride, top_k, 0.0,
            )
            .expect("pool");
            let pool_s = t.elapsed().as_secs_f64();
            let (g, _) = gs4city::splat::read_ply(&ctx.ply, &Default::default()).expect("ply");
            let t = Instant::now();
            let graph = knn::build(&g.positions, 5);
            let knn_s = t.elapsed().as_secs_f64();
            drop(g);
            println!(
                "\n### stride {stride}, top-k {} — {} training views, {} held out; {} training pixels ({:.0} MB), {} classes; read+vote {pool_s:.1} s, kNN {knn_s:.1} s\n",
                if top_k == 0 {
                    "as cached".to_string()
                } else {
                    top_k.to_string()
                },
                ctx.train.len(),
                ctx.val.views.len(),
                pool.pixels(),
                pool.bytes() as f64 / 1e6,
                pool.class_ids.len()
            );
            // The vote, predicted as `lift` does.
            let vote_label: Vec<i32> = pool.vote.iter().map(|x| x.label).collect();
            let vote_class: Vec<i32> = vote_label.iter().map(|&l| ctx.table.class_of(l)).collect();
            let vote_maps = |set: &TestSet| -> Vec<Vec<i32>> {
                set.views
                    .iter()
                    .map(|(_, v, _)| {
                        let v = pool::truncate(v, top_k);
                        gs4city::cache::predict(&v, &vote_label, &vote_class).0
                    })
                    .collect()
            };
            let (vt, vv) = (vote_maps(&ctx.test), vote_maps(&ctx.val));
            let rv = score(&ctx.test, &vt);
            let rvv = if ctx.val.views.is_empty() {
                f64::NAN
            } else {
                score(&ctx.val, &vv).0
            };
            println!(
                "| config | it. | train CPU s | mean CE/ln C | predictor | test fine mIoU | held-out mIoU vs maps (vs truth) | wall | roof | window | door | tree | person | car | test px changed vs vote (right now / right before) |"
            );
            println!("|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|");
            println!(
                "| vote (lift) | – | – | – | vote | **{:.2}** | {} | {} | |",
                100.0 * rv.0,
                pct(rvv),
                per_class(&rv)
            );
            out.push(serde_json::json!({"stride": stride, "top_k": top_k, "config": "vote", "miou": rv.0, "miou_dataset": rv.1, "heldout": rvv, "per_class": rv.2}));
            if !ctx.val.views.is_empty() {
                // What the supervision itself scores against the truth on the held-out views,
                // and what the vote from the other views scores there.
                let fused: Vec<Vec<i32>> =
                    ctx.val.views.iter().map(|(_, _, t)| t.clone()).collect();
                let rf = score(&ctx.val_gt, &fused);
                let rg = score(&ctx.val_gt, &vv);
                println!(
                    "| held-out views vs truth: the training label maps themselves | | | | maps | ({:.2}) | | {} | |",
                    100.0 * rf.0,
                    per_class(&rf)
                );
                println!(
                    "| held-out views vs truth: the vote of the other views | | | | vote | ({:.2}) | | {} | |",
                    100.0 * rg.0,
                    per_class(&rg)
                );
                out.push(serde_json::json!({"config": "ceiling", "maps_vs_truth": rf.0, "vote_vs_truth": rg.0, "maps_per_class": rf.2, "vote_per_class": rg.2}));
            }
            for (name, opts) in configs(&a.configs) {
                let vc = train::vote_classes(&pool);
                let m = train::init_model(pool.vote.len(), pool.class_ids.len(), &vc, &opts);
                let mut tr = train::Trainer::new(&pool, &graph, m, vc, &opts);
                tr.group = train::eval_groups(&pool.class_ids, &ctx.table);
                let mut cpu = 0.0;
                for &cp in &a.checkpoints {
                    let c0 = cpu_s();
                    let (mut ce, mut n) = (0.0, 0usize);
                    while tr.iteration < cp {
                        ce += tr.step().ce;
                        n += 1;
                    }
                    cpu += cpu_s() - c0;
                    let ce = if n > 0 {
                        format!("{:.4}", ce / n as f64)
                    } else {
                        "–".into()
                    };
                    let gclass = predict::gaussian_classes(&tr.model);
                    let moved = gclass
                        .iter()
                        .zip(&pool.vote)
                        .filter(|(c, a)| pool.class_ids[**c as usize] != a.label)
                        .count();
                    println!(
                        "| {name} | {cp} | | | ({moved} Gaussians changed label from the vote) | | | | | | | | | | |"
                    );
                    for &(rname, rule) in &rules {
                        let exact = opts.exact_predict;
                        let (tm, _) = predict_all(
                            ctx,
                            &ctx.test,
                            &tr.model,
                            &gclass,
                            &pool.class_ids,
                            exact,
                            rule,
                        );
                        let r = score(&ctx.test, &tm);
                        let rh = if ctx.val.views.is_empty() {
                            f64::NAN
                        } else {
                            let (hm, _) = predict_all(
                                ctx,
                                &ctx.val,
                                &tr.model,
                                &gclass,
                                &pool.class_ids,
                                exact,
                                rule,
                            );
                            score(&ctx.val, &hm).0
                        };
                        let (nc, good, bad) = changes(&ctx.test, &vt, &tm);
                        let rhg = if ctx.val.views.is_empty() {
                            f64::NAN
                        } else {
                            let (hm, _) = predict_all(
                                ctx,
                                &ctx.val_gt,
                                &tr.model,
                                &gclass,
                                &pool.class_ids,
                                exact,
                                rule,
                            );
                            score(&ctx.val_gt, &hm).0
                        };
                        println!(
                            "| {name} | {cp} | {cpu:.1} | {ce} | {rname} | **{:.2}** | {} ({}) | {} | {nc} ({good} / {bad}) |",
                            100.0 * r.0,
                            pct(rh),
                            pct(rhg),
                            per_class(&r)
                        );
                        out.push(serde_json::json!({"stride": stride, "top_k": top_k, "config": name, "rule": rule,
                            "pixels": opts.pixels, "iterations": cp, "cpu_s": cpu, "ce": ce, "miou": r.0, "miou_dataset": r.1,
                            "heldout": rh, "heldout_truth": rhg, "per_class": r.2, "changed": nc, "changed_right": good, "changed_was_right": bad}));
                    }
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
        &ctx.cache, &ctx.train, &ctx.maps, &ctx.table, None, 4, 0, 0.0,
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
    let (cand, _) = predict_all(
        ctx,
        &ctx.test,
        &tr.model,
        &predict::gaussian_classes(&tr.model),
        &pool.class_ids,
        false,
        predict::Rule::Label,
    );
    let tc = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (full, _) = predict_all(
        ctx,
        &ctx.test,
        &tr.model,
        &predict::gaussian_classes(&tr.model),
        &pool.class_ids,
        true,
        predict::Rule::Label,
    );
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
    let entities = gs4city::semantics::read(&a.run.join("citymodel/semantics.json")).expect("sem");
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
