//! Association + fusion benchmark on a scene folder and a run folder of the core
//! pipeline (citymodel/, raycast/, render/ = contributions cache):
//!
//! ```text
//! cargo bench --bench associate -- --scene out/results/street/scene --run out/results/street/run \
//!     --masks out/results/street/run/masks --out out/results/street/assoc-bench \
//!     [--configs default,mview1,...] [--keep] [--quick]
//! ```
//! Kept masks come from the real masks stage (`gs4city::masks::run`, default options, all views):
//! `--masks DIR` is reused when it holds a finished masks folder, else the stage is run into it
//! first (as `gs4city run` feeds it). Per configuration: associate → fuse →
//! lift (vote over the fused labels) → eval on the test views, with the time of each step,
//! fine IoU per class (paper protocol), and association purity / completeness against the
//! simulation truth (`gt/`, read here only, never by the stages). Prints Markdown.
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::Instant;

use gs4city::alignment::Alignment;
use gs4city::associate::{self, AssociateOptions, CandidateMode};
use gs4city::cache::Cache;
use gs4city::fuse::{self, FuseOptions};
use gs4city::idmap::LabelMaps;
use gs4city::labels::LabelTable;
use gs4city::lift::{self, LiftOptions};
use gs4city::scene::Split;
use gs4city::{colmap, eval, npy, semantics};

struct Args {
    scene: PathBuf,
    run: PathBuf,
    out: PathBuf,
    masks: PathBuf,
    configs: Vec<String>,
    keep: bool,
    /// Association quality only (no fuse, lift, eval).
    quick: bool,
}

fn args() -> Args {
    let mut a = std::env::args().skip(1);
    let (mut scene, mut run, mut out, mut masks, mut configs, mut keep, mut quick) =
        (None, None, None, None, None, false, false);
    while let Some(x) = a.next() {
        match x.as_str() {
            "--scene" => scene = a.next().map(PathBuf::from),
            "--run" => run = a.next().map(PathBuf::from),
            "--out" => out = a.next().map(PathBuf::from),
            "--masks" => masks = a.next().map(PathBuf::from),
            "--configs" => configs = a.next(),
            "--keep" => keep = true,
            "--quick" => quick = true,
            _ => {} // `cargo bench` passes --bench
        }
    }
    Args {
        scene: scene.unwrap_or_else(|| "out/results/street/scene".into()),
        run: run.unwrap_or_else(|| "out/results/street/run".into()),
        out: out.unwrap_or_else(|| "out/results/street/assoc-bench".into()),
        masks: masks.unwrap_or_else(|| "out/results/street/run/masks".into()),
        configs: configs
            .unwrap_or_else(|| {
                "default,mview1,mview5,projected,single_pass,shuffle1,shuffle2,shuffle3,nosnap"
                    .into()
            })
            .split(',')
            .map(String::from)
            .collect(),
        keep,
        quick,
    }
}

/// A configuration's options.
fn config(name: &str) -> (AssociateOptions, FuseOptions) {
    let mut a = AssociateOptions::default();
    let mut f = FuseOptions::default();
    for part in name.split('+') {
        match part {
            "default" => {}
            "mview1" => a.min_views = 1,
            "mview2" => a.min_views = 2,
            "nosupport" => a.support = false,
            "supportpixels" => a.support_pixels = true,
            "nosupportmasks" => a.support_masks = false,
            "massowner" => a.specific_owner = false,
            "nofillover" => a.fill_over_masks = false,
            "supportmaskpixels" => a.support_mask_pixels = true,
            s if s.starts_with("join") => a.join_views = s[4..].parse().unwrap(),
            "mview5" => a.min_views = 5,
            "projected" => a.candidates = CandidateMode::Projected,
            "projected_single" => {
                a.candidates = CandidateMode::Projected;
                a.consolidate = false;
            }
            "single_pass" => a.consolidate = false,
            "snap" => f.snap = true,
            "nosnap" => f.snap = false,
            "paper" => {
                // The paper's association: projected centres, one pass, no fill, no snapping.
                a.candidates = CandidateMode::Projected;
                a.consolidate = false;
                a.fill = None;
                f.snap = false;
            }
            "nofill" => a.fill = None,
            s if s.starts_with("shuffle") => {
                a.shuffle_seed = Some(s["shuffle".len()..].parse().expect("shuffleN"))
            }
            s if s.starts_with("single_shuffle") => {
                a.consolidate = false;
                a.shuffle_seed = Some(
                    s["single_shuffle".len()..]
                        .parse()
                        .expect("single_shuffleN"),
                );
            }
            s if s.starts_with("fill") => {
                a.fill = Some(s["fill".len()..].parse::<f32>().expect("fillNN") / 100.0)
            }
            s if s.starts_with("mf") => {
                a.merge_fraction = s["mf".len()..].parse::<f64>().expect("mfNN") / 100.0
            }
            s if s.starts_with("link") => {
                a.tau_link = s["link".len()..].parse::<f64>().expect("linkNN") / 100.0
            }
            s if s.starts_with("snapshare") => {
                f.snap = true;
                f.snap_limits.min_part_share =
                    s["snapshare".len()..].parse::<f64>().expect("snapshareNN") / 100.0;
            }
            s if s.starts_with("snapother") => {
                f.snap = true;
                f.snap_limits.max_other_part_share =
                    s["snapother".len()..].parse::<f64>().expect("snapotherNN") / 100.0;
            }
            s if s.starts_with("snapratio") => {
                f.snap = true;
                let r = s["snapratio".len()..].parse::<f64>().expect("snapratioNN") / 100.0;
                f.snap_limits.area_ratio = [1.0 / r, r];
            }
            s if s.starts_with("snapiou") => {
                f.snap = true;
                f.snap_limits.max_iou =
                    s["snapiou".len()..].parse::<f64>().expect("snapiouX") / 100.0;
            }
            s => panic!("unknown config {s}"),
        }
    }
    (a, f)
}

/// Purity and completeness of an associate folder against `gt/<stem>.instance.npy`.
#[derive(Debug, Default)]
struct Quality {
    purity: f64,
    /// Objects (tree, person, car): share of their pixels in their dominant group.
    completeness: f64,
    /// The same, over the object pixels some group covers.
    completeness_covered: f64,
    /// Mean over object instances of their completeness.
    completeness_mean: f64,
    /// All non-building instances (road, water, floaters included).
    completeness_nonbuilding: f64,
    per_class: BTreeMap<String, (f64, f64)>,
}

fn instance_classes(gt: &Path) -> HashMap<i32, String> {
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(gt.join("instances.json")).unwrap()).unwrap();
    v.as_object()
        .unwrap()
        .iter()
        .map(|(k, x)| (k.parse().unwrap(), x["class"].as_str().unwrap().to_string()))
        .collect()
}

fn quality(assoc: &Path, gt: &Path, stems: &[String], classes: &HashMap<i32, String>) -> Quality {
    let mut n: HashMap<(i32, i32), u64> = HashMap::new();
    let mut inst_total: HashMap<i32, u64> = HashMap::new();
    for s in stems {
        let (_, g) = npy::read::<i32>(&assoc.join(format!("{s}.ids.npy"))).unwrap();
        let (_, t) = npy::read::<i32>(&gt.join(format!("{s}.instance.npy"))).unwrap();
        for (&a, &b) in g.iter().zip(&t) {
            *inst_total.entry(b).or_insert(0) += 1;
            if a >= 0 {
                *n.entry((a, b)).or_insert(0) += 1;
            }
        }
    }
    let mut by_group: HashMap<i32, (u64, u64)> = HashMap::new();
    let mut by_inst: HashMap<i32, (u64, u64)> = HashMap::new(); // (best, covered)
    for (&(a, b), &c) in &n {
        let e = by_group.entry(a).or_insert((0, 0));
        e.0 = e.0.max(c);
        e.1 += c;
        let e = by_inst.entry(b).or_insert((0, 0));
        e.0 = e.0.max(c);
        e.1 += c;
    }
    let (best, all) = by_group
        .values()
        .fold((0, 0), |s, v| (s.0 + v.0, s.1 + v.1));
    let mut q = Quality {
        purity: best as f64 / all.max(1) as f64,
        ..Default::default()
    };
    let objects = ["tree", "person", "car"];
    let (mut ob, mut oc, mut ot, mut nb, mut nt) = (0u64, 0u64, 0u64, 0u64, 0u64);
    let mut means = Vec::new();
    let mut per: BTreeMap<String, (u64, u64)> = BTreeMap::new();
    for (&i, &total) in &inst_total {
        let Some(class) = classes.get(&i) else {
            continue;
        };
        if i < 1_000_000 {
            continue; // city instances
        }
        let (b, c) = by_inst.get(&i).copied().unwrap_or((0, 0));
        nb += b;
        nt += total;
        if objects.contains(&class.as_str()) {
            ob += b;
            oc += c;
            ot += total;
            means.push(b as f64 / total.max(1) as f64);
            let e = per.entry(class.clone()).or_insert((0, 0));
            e.0 += b;
            e.1 += total;
        }
    }
    q.completeness = ob as f64 / ot.max(1) as f64;
    q.completeness_covered = ob as f64 / oc.max(1) as f64;
    q.completeness_mean = means.iter().sum::<f64>() / means.len().max(1) as f64;
    q.completeness_nonbuilding = nb as f64 / nt.max(1) as f64;
    // Per-class purity of groups whose dominant instance has that class, and completeness.
    let mut pur: BTreeMap<String, (u64, u64)> = BTreeMap::new();
    let mut dom: HashMap<i32, (i32, u64)> = HashMap::new();
    for (&(a, b), &c) in &n {
        let e = dom.entry(a).or_insert((b, 0));
        if c > e.1 || (c == e.1 && b < e.0) {
            *e = (b, c);
        }
    }
    for (a, (b, _)) in &dom {
        if let Some(cl) = classes.get(b)
            && objects.contains(&cl.as_str())
        {
            let (best, all) = by_group[a];
            let e = pur.entry(cl.clone()).or_insert((0, 0));
            e.0 += best;
            e.1 += all;
        }
    }
    for (cl, (b, t)) in per {
        let p = pur
            .get(&cl)
            .map_or(f64::NAN, |x| x.0 as f64 / x.1.max(1) as f64);
        q.per_class.insert(cl, (p, b as f64 / t.max(1) as f64));
    }
    q
}

/// Symmetric best-match agreement of two associate folders (1 = identical partitions).
fn agreement(a: &Path, b: &Path, stems: &[String]) -> f64 {
    let mut n: HashMap<(i32, i32), u64> = HashMap::new();
    for s in stems {
        let (_, x) = npy::read::<i32>(&a.join(format!("{s}.ids.npy"))).unwrap();
        let (_, y) = npy::read::<i32>(&b.join(format!("{s}.ids.npy"))).unwrap();
        for (&p, &q) in x.iter().zip(&y) {
            if p >= 0 || q >= 0 {
                *n.entry((p, q)).or_insert(0) += 1;
            }
        }
    }
    let mut ra: HashMap<i32, u64> = HashMap::new();
    let mut rb: HashMap<i32, u64> = HashMap::new();
    let mut total = 0;
    for (&(p, q), &c) in &n {
        let e = ra.entry(p).or_insert(0);
        *e = (*e).max(c);
        let e = rb.entry(q).or_insert(0);
        *e = (*e).max(c);
        total += c;
    }
    let sa: u64 = ra.values().sum();
    let sb: u64 = rb.values().sum();
    (sa + sb) as f64 / (2 * total.max(1)) as f64
}

fn main() {
    let args = args();
    gs4city::progress::init(-1);
    let scene = &args.scene;
    let run = &args.run;
    let gt = scene.join("gt");
    let views = colmap::read_model(&scene.join("sparse/0")).unwrap();
    let split = Split::new(views, 8);
    let train_stems: Vec<String> = split.train.iter().map(|v| v.stem()).collect();
    let test_stems = split.test_stems();
    let entities = semantics::read(&run.join("citymodel/semantics.json")).unwrap();
    let scale = Alignment::read(&run.join("citymodel/alignment.json"))
        .unwrap()
        .scale;
    let cache = Cache::open(&run.join("render")).unwrap();
    let classes = instance_classes(&gt);
    std::fs::create_dir_all(&args.out).unwrap();

    // The masks stage's kept masks (run once, then reused).
    if !args.masks.join("summary.json").is_file() {
        let t = Instant::now();
        let sc = gs4city::scene::Scene::open(scene).unwrap();
        let all = colmap::read_model(&scene.join("sparse/0")).unwrap();
        let m = gs4city::masks::run(
            &gs4city::masks::MasksInputs {
                scene: &sc,
                views: &all,
                raycast: &run.join("raycast"),
                cache: Some(&cache),
                alignment_scale: scale,
            },
            &gs4city::masks::MasksOptions::default(),
            &args.masks,
        )
        .unwrap();
        println!(
            "masks stage: kept {} masks in {:.1} s → {}",
            m.kept,
            t.elapsed().as_secs_f64(),
            args.masks.display()
        );
    }
    let masks_dir = &args.masks;

    println!();
    println!(
        "| config | groups | assoc s | fuse s | lift s | purity | compl. | compl. (covered) | compl. mean/inst | compl. non-bldg | mIoU | wall | roof | window | door | tree | person | car | agreement vs default |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for name in &args.configs {
        let (aopt, fopt) = config(name);
        let dir = args.out.join(name);
        let (ad, fd, ld, ed) = (
            dir.join("associate"),
            dir.join("fuse"),
            dir.join("lift"),
            dir.join("eval"),
        );
        let a = associate::run(
            &associate::AssociateInputs {
                views: &split.train,
                masks: masks_dir,
                features: Some(&scene.join("features")),
                sam: Some(&scene.join("masks")),
                cache: &cache,
                ply: &scene.join("point_cloud.ply"),
                scale,
            },
            &aopt,
            &ad,
        )
        .unwrap();
        if args.quick {
            let q = quality(&ad, &gt, &train_stems, &classes);
            println!(
                "| {name} | {} | {:.1} | – | – | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | – | – | – | – | – | – | – | – | – |",
                a.groups,
                a.timing.total_s,
                q.purity,
                q.completeness,
                q.completeness_covered,
                q.completeness_mean,
                q.completeness_nonbuilding
            );
            eprintln!(
                "{name}: {:?} {:?} per-class {:?}",
                a.timing, a.consolidation, q.per_class
            );
            continue;
        }
        let f = fuse::run(
            &fuse::FuseInputs {
                views: &split.train,
                associate: &ad,
                raycast: &run.join("raycast"),
                entities: &entities,
                sam: Some(&scene.join("masks")),
                features: Some(&scene.join("features")),
                kept: Some(masks_dir),
            },
            &fopt,
            &fd,
        )
        .unwrap();
        let labels = LabelTable::read(&fd.join("labels.json")).unwrap();
        let l = lift::run(
            &lift::LiftInputs {
                ply: &scene.join("point_cloud.ply"),
                cache: &cache,
                train: &split.train,
                test: &split.test,
                maps: &LabelMaps::Fused(fd.clone()),
                labels: &labels,
                entities: &entities,
                city_depth: None,
                city_mesh: None,
            },
            &LiftOptions::default(),
            &ld,
        )
        .unwrap();
        let (_, m) = eval::run_for(&ld, &gt, &ed, Some(&test_stems), Some("vote")).unwrap();
        let q = quality(&ad, &gt, &train_stems, &classes);
        let agree =
            if name != "default" && args.out.join("default/associate/summary.json").is_file() {
                format!(
                    "{:.4}",
                    agreement(&args.out.join("default/associate"), &ad, &train_stems)
                )
            } else {
                "–".into()
            };
        let pc = |c: &str| {
            m.paper.iou[c]
                .mean
                .map_or("–".to_string(), |x| format!("{:.1}", 100.0 * x))
        };
        println!(
            "| {name} | {} | {:.1} | {:.1} | {:.1} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.1} | {} | {} | {} | {} | {} | {} | {} | {agree} |",
            a.groups,
            a.timing.total_s,
            f.timing.total_s,
            l.timing.total_s,
            q.purity,
            q.completeness,
            q.completeness_covered,
            q.completeness_mean,
            q.completeness_nonbuilding,
            100.0 * m.paper.miou.mean.unwrap_or(f64::NAN),
            pc("wall"),
            pc("roof"),
            pc("window"),
            pc("door"),
            pc("tree"),
            pc("person"),
            pc("car"),
        );
        eprintln!(
            "{name}: associate timing {:?}; consolidation {:?}; dropped {} (views) {} (far); per-class (purity, completeness) {:?}; fuse {:?}; snap {:?}; lift vote {:.1} s",
            a.timing,
            a.consolidation,
            a.dropped_min_views,
            a.dropped_far_field,
            q.per_class,
            f.timing,
            f.snap,
            l.timing.vote_s
        );
        if !args.keep {
            let _ = std::fs::remove_file(ld.join("semantic.ply"));
        }
    }
}
