//! The simulated SAM masks and simulated CLIP features (`gs4city::synth::masks`): the
//! noise model's effects are measurable, and everything is deterministic.
use gs4city::classes;
use gs4city::sam as masks;
use gs4city::synth::masks::{
    self as simulate, FEATURE_DIM, FeatureNoise, MaskKind, MaskNoise, SimulatedMask,
    simulate_features, simulate_masks,
};
use ndarray::{Array2, s};

/// A façade view: roof, wall with 2×3 windows (two of them 2 px apart), a door, a road, a
/// car, a tree in front of it, a small person; −1 (sky) elsewhere. Returns (instance, class).
fn facade() -> (Array2<i32>, Array2<i32>) {
    let (h, w) = (120, 160);
    let mut inst = Array2::from_elem((h, w), -1);
    let mut cls = Array2::from_elem((h, w), classes::NONE);
    let mut put = |y: [usize; 2], x: [usize; 2], id: i32, c: i32| {
        inst.slice_mut(s![y[0]..y[1], x[0]..x[1]]).fill(id);
        cls.slice_mut(s![y[0]..y[1], x[0]..x[1]]).fill(c);
    };
    put([5, 20], [10, 110], 2, classes::ROOF);
    put([20, 100], [10, 110], 1, classes::WALL);
    let mut id = 10;
    for y in [30, 60] {
        for x in [20, 48, 64] {
            put([y, y + 12], [x, x + 14], id, classes::WINDOW);
            id += 1;
        }
    }
    put([80, 100], [95, 105], 20, classes::DOOR);
    put([100, 120], [0, 160], 100, classes::ROAD);
    put([85, 100], [112, 140], 50, classes::CAR);
    put([92, 98], [150, 153], 40, classes::PERSON);
    for y in 50..90 {
        for x in 120..155 {
            if (y as f64 - 70.0).powi(2) / 400.0 + (x as f64 - 137.0).powi(2) / 289.0 <= 1.0 {
                inst[[y, x]] = 30;
                cls[[y, x]] = classes::TREE;
            }
        }
    }
    (inst, cls)
}

fn ids(inst: &Array2<i32>) -> Vec<i32> {
    let mut v: Vec<i32> = inst.iter().copied().filter(|&i| i >= 0).collect();
    v.sort();
    v.dedup();
    v
}

fn run(cfg: &MaskNoise, seed: u64) -> Vec<SimulatedMask> {
    let (inst, cls) = facade();
    simulate_masks(inst.view(), cls.view(), cfg, seed)
}

fn pixels(m: &SimulatedMask) -> Array2<bool> {
    m.mask.segmentation.decode().unwrap()
}

fn count(m: &Array2<bool>) -> usize {
    m.iter().filter(|&&v| v).count()
}

#[test]
fn no_noise_gives_the_ground_truth_instances() {
    let (inst, cls) = facade();
    let out = simulate_masks(inst.view(), cls.view(), &MaskNoise::none(), 1);
    let want = ids(&inst);
    assert_eq!(out.len(), want.len());
    for (m, &id) in out.iter().zip(&want) {
        assert_eq!(m.source_instances, vec![id]);
        assert_eq!(m.kind, MaskKind::Instance);
        assert_eq!(pixels(m), inst.mapv(|v| v == id), "instance {id}");
        assert_eq!(m.mask.predicted_iou, 1.0);
        assert_eq!(m.mask.stability_score, 1.0);
        assert_eq!(m.damage, 0.0);
        let c = cls[[
            m.mask.point_coords[0][1] as usize,
            m.mask.point_coords[0][0] as usize,
        ]];
        assert_eq!(m.class, c, "class of {id}");
        assert_eq!(
            inst[[
                m.mask.point_coords[0][1] as usize,
                m.mask.point_coords[0][0] as usize
            ]],
            id
        );
        assert_eq!(m.mask.crop_box, Some([0, 0, 160, 120]));
    }
}

#[test]
fn erosion_shrinks_and_dilation_grows() {
    let (inst, _) = facade();
    let erode = MaskNoise {
        boundary_prob: 1.0,
        boundary_radius_px: [1, 1],
        dilate_prob: 0.0,
        ..MaskNoise::none()
    };
    let out = run(&erode, 5);
    let (mut gt_total, mut total) = (0, 0);
    for m in &out {
        let id = m.source_instances[0];
        let gt = inst.mapv(|v| v == id);
        let p = pixels(m);
        assert!(
            p.iter().zip(&gt).all(|(a, b)| !a || *b),
            "eroded {id} leaks"
        );
        assert!(count(&p) < count(&gt), "eroded {id} did not shrink");
        assert!(m.damage > 0.0 && m.mask.predicted_iou < 1.0);
        gt_total += count(&gt);
        total += count(&p);
    }
    assert!(total < gt_total);
    let dilate = MaskNoise {
        dilate_prob: 1.0,
        ..erode
    };
    for m in run(&dilate, 5) {
        let gt = inst.mapv(|v| v == m.source_instances[0]);
        let p = pixels(&m);
        assert!(
            gt.iter().zip(&p).all(|(a, b)| !a || *b),
            "dilation keeps the instance"
        );
        assert!(count(&p) >= count(&gt));
    }
}

#[test]
fn small_instances_are_missed() {
    let (inst, _) = facade();
    let cfg = MaskNoise {
        miss_small_prob: 1.0,
        small_area_px: 50,
        ..MaskNoise::none()
    };
    let out = run(&cfg, 3);
    let got: Vec<i32> = out.iter().map(|m| m.source_instances[0]).collect();
    assert!(!got.contains(&40), "the 18-pixel person must vanish");
    assert_eq!(got.len(), ids(&inst).len() - 1);
    // Probability 0 keeps it.
    let keep = MaskNoise {
        miss_small_prob: 0.0,
        ..cfg
    };
    assert!(run(&keep, 3).iter().any(|m| m.source_instances == vec![40]));
}

#[test]
fn scores_fall_monotonically_with_damage() {
    let mut last: Option<(f64, f64, f64)> = None;
    for r in 0..=5 {
        let cfg = MaskNoise {
            boundary_prob: 1.0,
            boundary_radius_px: [r, r],
            dilate_prob: 0.0,
            ..MaskNoise::none()
        };
        let out = run(&cfg, 9);
        let wall = out.iter().find(|m| m.source_instances == vec![1]).unwrap();
        let now = (
            wall.damage,
            wall.mask.predicted_iou,
            wall.mask.stability_score,
        );
        if let Some(prev) = last {
            assert!(
                now.0 > prev.0,
                "damage grows with the radius: {prev:?} → {now:?}"
            );
            assert!(
                now.1 < prev.1 && now.2 < prev.2,
                "scores fall: {prev:?} → {now:?}"
            );
        } else {
            assert_eq!(now, (0.0, 1.0, 1.0));
        }
        last = Some(now);
    }
    // Over all masks of a noisy run without jitter, the score is a decreasing function of damage.
    let cfg = MaskNoise {
        iou_jitter: 0.0,
        stability_jitter: 0.0,
        ..MaskNoise::default()
    };
    let mut v: Vec<(f64, f64)> = run(&cfg, 2)
        .iter()
        .map(|m| (m.damage, m.mask.predicted_iou))
        .collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    assert!(v.windows(2).all(|p| p[1].1 <= p[0].1));
}

#[test]
fn merges_join_neighbours() {
    let (inst, _) = facade();
    let cfg = MaskNoise {
        merge_prob: 1.0,
        merge_gap_px: 3,
        merge_max_instances: 2,
        ..MaskNoise::none()
    };
    let out = run(&cfg, 4);
    let merged: Vec<&SimulatedMask> = out.iter().filter(|m| m.kind == MaskKind::Merged).collect();
    assert!(!merged.is_empty());
    let mut seen = std::collections::BTreeSet::new();
    for m in &out {
        for &i in &m.source_instances {
            assert!(seen.insert(i), "instance {i} in two masks");
        }
    }
    assert_eq!(
        seen.len(),
        ids(&inst).len(),
        "every instance is in one mask"
    );
    for m in merged {
        assert_eq!(m.source_instances.len(), 2);
        let union = inst.mapv(|v| m.source_instances.contains(&v));
        assert_eq!(pixels(m), union);
        assert!(m.damage > 0.0 && m.mask.predicted_iou < 1.0);
    }
    // The two windows 2 px apart (ids 11 and 12) are neighbours at gap 3 but not at gap 1.
    let near = MaskNoise {
        merge_max_instances: 20,
        ..cfg.clone()
    };
    let all = run(&near, 4);
    assert!(
        all.iter()
            .any(|m| m.source_instances.contains(&11) && m.source_instances.contains(&12))
    );
}

#[test]
fn splits_partition_the_instance() {
    let (inst, _) = facade();
    let cfg = MaskNoise {
        split_prob: 1.0,
        split_min_area_px: 100,
        split_max_parts: 3,
        ..MaskNoise::none()
    };
    let out = run(&cfg, 6);
    for id in ids(&inst) {
        let parts: Vec<&SimulatedMask> = out
            .iter()
            .filter(|m| m.source_instances == vec![id])
            .collect();
        let gt = inst.mapv(|v| v == id);
        if count(&gt) < 100 {
            assert_eq!(parts.len(), 1);
            continue;
        }
        assert!(
            (2..=3).contains(&parts.len()),
            "instance {id}: {} parts",
            parts.len()
        );
        let mut cover = Array2::<u8>::zeros(gt.dim());
        for p in &parts {
            assert_eq!(p.kind, MaskKind::Split);
            assert!(p.damage > 0.0);
            cover.zip_mut_with(&pixels(p), |c, &v| *c += u8::from(v));
        }
        assert_eq!(cover.mapv(|c| c == 1), gt, "parts of {id} partition it");
        assert!(cover.iter().all(|&c| c <= 1));
    }
}

#[test]
fn false_positives_lie_on_walls() {
    let (inst, _) = facade();
    let cfg = MaskNoise {
        false_positive_rate: 4.0,
        ..MaskNoise::none()
    };
    let out = run(&cfg, 8);
    let fp: Vec<&SimulatedMask> = out
        .iter()
        .filter(|m| m.kind == MaskKind::FalsePositive)
        .collect();
    assert!(fp.len() >= 2, "{} blobs", fp.len());
    for m in fp {
        assert!(m.source_instances.is_empty());
        assert_eq!(m.class, classes::WALL);
        let p = pixels(m);
        assert!(
            p.iter().zip(&inst).all(|(a, &i)| !a || i == 1),
            "blob off the wall"
        );
        assert!(m.damage > 0.5 && m.mask.predicted_iou < 0.5);
    }
    assert_eq!(
        out.iter().filter(|m| m.kind == MaskKind::Instance).count(),
        ids(&inst).len()
    );
}

#[test]
fn deterministic_for_seed_and_thread_count() {
    let cfg = MaskNoise {
        merge_prob: 0.3,
        split_prob: 0.3,
        false_positive_rate: 1.0,
        ..MaskNoise::default()
    };
    let a = run(&cfg, 42);
    assert_eq!(a, run(&cfg, 42));
    assert_ne!(a, run(&cfg, 43));
    for threads in [1, 3] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        assert_eq!(pool.install(|| run(&cfg, 42)), a, "{threads} threads");
    }
    // Sorted by (kind, sources, bbox, …).
    assert!(
        a.windows(2)
            .all(|p| (p[0].kind, &p[0].source_instances) <= (p[1].kind, &p[1].source_instances))
    );
}

#[test]
fn default_noise_writes_valid_sam_files_with_provenance() {
    let out = run(&MaskNoise::default(), 11);
    assert!(!out.is_empty());
    for m in &out {
        assert!((0.0..=1.0).contains(&m.mask.predicted_iou));
        assert!((0.0..=1.0).contains(&m.mask.stability_score));
        assert!(m.mask.area > 0);
    }
    let dir = crate::common::temp_dir().join(format!("gs4city-sim-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let sam: Vec<_> = out.iter().map(|m| m.mask.clone()).collect();
    masks::write_sam_json(&dir.join("v.json"), &sam).unwrap();
    assert_eq!(
        masks::read_sam_json_sized(&dir.join("v.json"), Some([120, 160])).unwrap(),
        sam
    );
    simulate::write_simulation_truth(&dir.join("v.sim.json"), &out).unwrap();
    let f = FeatureNoise::default();
    let prov = simulate::provenance(&MaskNoise::default(), Some(&f), 11);
    simulate::write_provenance(&dir, &prov).unwrap();
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join(simulate::PROVENANCE_FILE)).unwrap())
            .unwrap();
    assert_eq!(v["simulated"], true);
    assert!(v["what"].as_str().unwrap().contains("SIMULATED"));
    let back: MaskNoise = serde_json::from_value(v["mask_noise"].clone()).unwrap();
    assert_eq!(back, MaskNoise::default());
    // Unknown keys in a noise config are errors, missing keys take defaults.
    assert!(serde_json::from_str::<MaskNoise>(r#"{"merge_probb": 1}"#).is_err());
    let partial: MaskNoise = serde_json::from_str(r#"{"merge_prob": 0.5}"#).unwrap();
    assert_eq!(partial.merge_prob, 0.5);
    assert_eq!(partial.split_prob, MaskNoise::default().split_prob);
    std::fs::remove_dir_all(&dir).unwrap();
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| f64::from(*x) * f64::from(*y))
        .sum()
}

#[test]
fn simulated_features_cluster_by_class() {
    let cfg = FeatureNoise::default();
    let cls: Vec<i32> = (0..200).map(|i| [0, 1, 2, 3, 6, 7, 8, 9][i % 8]).collect();
    let (f, prompts) = simulate_features(&cls, &cfg, 5);
    assert_eq!(f.len(), cls.len());
    assert!(prompts.simulated);
    for v in &f {
        assert_eq!(v.len(), FEATURE_DIM);
        assert!((dot(v, v) - 1.0).abs() < 1e-5);
    }
    // Each class prompt is nearest its own class's features.
    let target = |c: i32| match c {
        0 => "a wall of a building",
        1 => "a roof",
        2 => "a window of a building",
        3 => "a door",
        6 => "a tree",
        7 => "a person",
        8 => "a car",
        _ => "a road",
    };
    let mut correct = 0;
    for (v, &c) in f.iter().zip(&cls) {
        let best = prompts
            .prompts
            .iter()
            .filter(|(t, _)| !matches!(t.as_str(), "a building" | "a facade of a building"))
            .max_by(|a, b| dot(v, a.1).total_cmp(&dot(v, b.1)))
            .unwrap();
        correct += usize::from(best.0 == target(c));
    }
    assert_eq!(correct, cls.len(), "default noise keeps classes separable");
    // Cosine to the prototype ≈ 1/√(1+σ²).
    let p = simulate::class_prototype(&cfg, 6);
    let mean: f64 = f
        .iter()
        .zip(&cls)
        .filter(|(_, c)| **c == 6)
        .map(|(v, _)| dot(v, &p))
        .sum::<f64>()
        / 25.0;
    assert!((mean - 1.0 / (1.0f64 + 0.36).sqrt()).abs() < 0.03, "{mean}");
    // "a building" is closer to walls than to cars.
    let b = &prompts.prompts["a building"];
    assert!(
        dot(b, &simulate::class_prototype(&cfg, 0))
            > dot(b, &simulate::class_prototype(&cfg, 8)) + 0.3
    );
    // Deterministic; prompts do not depend on the per-view seed.
    let (f2, p2) = simulate_features(&cls, &cfg, 5);
    assert_eq!(f, f2);
    let (f3, p3) = simulate_features(&cls, &cfg, 6);
    assert_ne!(f, f3);
    assert_eq!(prompts, p2);
    assert_eq!(prompts, p3);
    // Files.
    let dir = crate::common::temp_dir().join(format!("gs4city-feat-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    masks::write_features_npy(&dir.join("f.npy"), FEATURE_DIM, &f).unwrap();
    let (shape, data) = gs4city::npy::read::<f32>(&dir.join("f.npy")).unwrap();
    assert_eq!(shape, vec![200, FEATURE_DIM]);
    assert_eq!(&data[FEATURE_DIM..2 * FEATURE_DIM], f[1].as_slice());
    masks::write_features_npy(&dir.join("e.npy"), FEATURE_DIM, &[]).unwrap();
    assert_eq!(
        gs4city::npy::read::<f32>(&dir.join("e.npy")).unwrap().0,
        vec![0, FEATURE_DIM]
    );
    masks::write_prompts_json(&dir.join("p.json"), &prompts).unwrap();
    assert_eq!(
        masks::read_prompts_json(&dir.join("p.json")).unwrap(),
        prompts
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
