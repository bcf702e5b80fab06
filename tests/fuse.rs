//! The fuse stage on the hand-built boxes scene (tests/common/boxes.rs) with a hand-written
//! raycast folder: a "building" band across the top of every image (sky there, so no image
//! group covers it) with a window in it. Expected maps, labels and features are computed here
//! from the files, independently of the stage.
use crate::boxes;

use std::path::{Path, PathBuf};

use boxes::{Built, H, W};
use gs4city::associate::{self, AssociateOptions};
use gs4city::citygml::Level;
use gs4city::fuse::{self, FuseOptions};
use gs4city::groups::GroupsFile;
use gs4city::labels::{LabelTable, Source};
use gs4city::semantics::Entity;
use ndarray::Array2;

fn entity(id: i32, class: &str, level: Level, parent: Option<i32>) -> Entity {
    Entity {
        id,
        object_id: format!("E{id}"),
        class: gs4city::semantics::Class::from_local_name(class).unwrap(),
        level,
        parent,
        building: 0,
        source: "test.gml".into(),
        lod: Some(3),
        attributes: Default::default(),
    }
}

/// Building 0, its wall 1, a window 2 in the wall.
fn entities() -> Vec<Entity> {
    vec![
        entity(0, "Building", Level::Feature, None),
        entity(1, "WallSurface", Level::Surface, Some(0)),
        entity(2, "Window", Level::Part, Some(1)),
    ]
}

const WIN_ROWS: std::ops::Range<usize> = 5..15;
const WIN_COLS: std::ops::Range<usize> = 20..40;

/// Writes the raycast folder: rows 0..30 are wall (feature 0, surface 1, city 1) with the
/// window (part 2, city 2) at `WIN_ROWS × WIN_COLS`.
fn raycast(b: &Built) -> PathBuf {
    let dir = b.dir.join("raycast");
    std::fs::create_dir_all(&dir).unwrap();
    let (w, h) = (W as usize, H as usize);
    for v in &b.views {
        let mut ids = vec![-1i32; 4 * w * h];
        for y in 0..30 {
            for x in 0..w {
                let p = y * w + x;
                let win = WIN_ROWS.contains(&y) && WIN_COLS.contains(&x);
                ids[p] = 0;
                ids[w * h + p] = 1;
                ids[2 * w * h + p] = if win { 2 } else { -1 };
                ids[3 * w * h + p] = if win { 2 } else { 1 };
            }
        }
        gs4city::npy::write(&dir.join(format!("{}.ids.npy", v.stem())), &[4, h, w], &ids).unwrap();
    }
    dir
}

fn associate(b: &Built) -> PathBuf {
    let out = b.dir.join("associate");
    let cache = b.open_cache();
    associate::run(
        &associate::AssociateInputs {
            views: &b.views,
            masks: &b.masks,
            features: Some(&b.features),
            sam: None,
            cache: &cache,
            ply: &b.ply,
            scale: 1.0,
        },
        &AssociateOptions::default(),
        &out,
    )
    .unwrap();
    out
}

fn fuse_run(
    b: &Built,
    assoc: &Path,
    ray: &Path,
    sam: &Path,
    snap: bool,
    out: &Path,
) -> fuse::FuseSummary {
    fuse::run(
        &fuse::FuseInputs {
            views: &b.views,
            associate: assoc,
            raycast: ray,
            entities: &entities(),
            sam: Some(sam),
            features: Some(&b.features),
            kept: Some(&b.masks),
        },
        &FuseOptions {
            snap,
            ..Default::default()
        },
        out,
    )
    .unwrap()
}

#[test]
fn image_priority_fusion_labels_and_features() {
    let b = boxes::build("fuse", |_, _| false);
    let ray = raycast(&b);
    let assoc = associate(&b);
    let out = b.dir.join("fuse");
    let s = fuse_run(&b, &assoc, &ray, &b.sam, false, &out);
    let groups = GroupsFile::read(&assoc).unwrap();
    assert_eq!(s.delta, 10_000);
    assert_eq!((s.city_labels, s.image_labels), (3, groups.groups.len()));
    let npx = (W * H) as usize;
    let mut image_px = 0;
    for v in &b.views {
        let stem = v.stem();
        let g = boxes::read_map(&assoc.join(format!("{stem}.ids.npy")));
        let r = boxes::read_map(&ray.join(format!("{stem}.ids.npy")));
        let f = boxes::read_map(&out.join(format!("{stem}.ids.npy")));
        for p in 0..npx {
            let expect = if g[p] >= 0 {
                g[p] + 10_000
            } else {
                r[3 * npx + p]
            };
            assert_eq!(f[p], expect, "{stem} pixel {p}");
            image_px += u64::from(g[p] >= 0);
        }
    }
    assert_eq!(s.image_pixels, image_px);
    // The label table: every entity (class wall, wall, window) and every group (its class).
    let t = LabelTable::read(&out.join("labels.json")).unwrap();
    assert_eq!(t.delta, 10_000);
    assert_eq!(t.labels.len(), 3 + groups.groups.len());
    assert_eq!((t.class_of(0), t.class_of(1), t.class_of(2)), (0, 0, 2));
    assert_eq!(t.get(2).unwrap().level, Some(Level::Part));
    for g in &groups.groups {
        let l = t.get(10_000 + g.id).unwrap();
        assert_eq!(
            (l.source, l.group, l.class),
            (Source::Image, Some(g.id), g.class)
        );
    }
    // Label features: groups keep theirs; the wall gets the overlap²/area-weighted mean of the
    // SAM masks over it. No SAM mask reaches the band here (it is sky), so the wall has none.
    let (shape, lf) = gs4city::npy::read::<f32>(&out.join("label_features.npy")).unwrap();
    assert_eq!(shape, vec![t.labels.len(), boxes::DIM]);
    let gf = groups.features(&assoc).unwrap().unwrap();
    for (i, l) in t.labels.iter().enumerate() {
        let row = &lf[i * boxes::DIM..(i + 1) * boxes::DIM];
        match l.group {
            Some(g) => assert_eq!(
                row,
                &gf[g as usize * boxes::DIM..(g as usize + 1) * boxes::DIM]
            ),
            None => assert!(row.iter().all(|&x| x == 0.0), "entity {:?}", l.entity),
        }
    }
}

#[test]
fn city_features_average_the_masks_over_each_entity() {
    // One extra SAM mask per view over the wall band (feature e0) and one over the window
    // (feature e1): the window's feature is dominated by the window mask (weight overlap²/area).
    let b = boxes::build("cityfeat", |_, _| false);
    let ray = raycast(&b);
    let assoc = associate(&b);
    let sam2 = b.dir.join("sam2");
    let feat2 = b.dir.join("features2");
    std::fs::create_dir_all(&sam2).unwrap();
    std::fs::create_dir_all(&feat2).unwrap();
    let (w, h) = (W as usize, H as usize);
    let band = Array2::from_shape_fn((h, w), |(y, _)| y < 30);
    let win = Array2::from_shape_fn((h, w), |(y, x)| {
        WIN_ROWS.contains(&y) && WIN_COLS.contains(&x)
    });
    let fa = [1.0f32, 0.0, 0.0, 0.0];
    let fb = [0.0f32, 1.0, 0.0, 0.0];
    for v in &b.views {
        let stem = v.stem();
        let masks = vec![
            gs4city::sam::SamMask::from_mask(&band, 0.9, 0.9, vec![]),
            gs4city::sam::SamMask::from_mask(&win, 0.9, 0.9, vec![]),
        ];
        gs4city::sam::write_sam_json(&sam2.join(format!("{stem}.json")), &masks).unwrap();
        gs4city::sam::write_features_npy(
            &feat2.join(format!("{stem}.npy")),
            4,
            &[fa.to_vec(), fb.to_vec()],
        )
        .unwrap();
    }
    let out = b.dir.join("fuse2");
    // Features of the groups (dim 4) and of these masks (dim 4) agree in dimension.
    let s = fuse::run(
        &fuse::FuseInputs {
            views: &b.views,
            associate: &assoc,
            raycast: &ray,
            entities: &entities(),
            sam: Some(&sam2),
            features: Some(&feat2),
            kept: Some(&b.masks),
        },
        &FuseOptions {
            snap: false,
            ..Default::default()
        },
        &out,
    )
    .unwrap();
    assert_eq!(s.city_labels_with_features, 2);
    let (_, lf) = gs4city::npy::read::<f32>(&out.join("label_features.npy")).unwrap();
    // Wall (entity 1): band mask overlap 30·160 − 200 = 4600 px of 4800 → weight 4600²/4800;
    // the window mask does not touch the wall. → exactly fa.
    assert_eq!(&lf[4..8], &fa);
    // Window (entity 2): band mask 200²/4800 ≈ 8.33, window mask 200²/200 = 200 (per view):
    // normalise(8.33·fa + 200·fb).
    let (wa, wb) = (200.0f64 * 200.0 / 4800.0, 200.0f64);
    let n = (wa * wa + wb * wb).sqrt();
    assert!((f64::from(lf[8]) - wa / n).abs() < 1e-5 && (f64::from(lf[9]) - wb / n).abs() < 1e-5);
    // The building entity (0) is never the fused label of a pixel: no feature.
    assert!(lf[0..4].iter().all(|&x| x == 0.0));
}

#[test]
fn snapping_moves_a_misaligned_window_to_its_image_mask() {
    // The scene's SAM list gains, per view, a window mask shifted 8 columns right of the raycast
    // window; the masks stage (here: the kept files) did not keep it.
    let b = boxes::build("snap", |_, _| false);
    let ray = raycast(&b);
    let assoc = associate(&b);
    let sam2 = b.dir.join("sam-snap");
    let feat2 = b.dir.join("features-snap");
    std::fs::create_dir_all(&sam2).unwrap();
    std::fs::create_dir_all(&feat2).unwrap();
    let (w, h) = (W as usize, H as usize);
    let shifted = |y: usize, x: usize| WIN_ROWS.contains(&y) && (28..48).contains(&x);
    for v in &b.views {
        let stem = v.stem();
        let mut list = gs4city::sam::read_sam_json(&b.sam.join(format!("{stem}.json"))).unwrap();
        let mut feats: Vec<Vec<f32>> = {
            let (shape, d) =
                gs4city::npy::read::<f32>(&b.features.join(format!("{stem}.npy"))).unwrap();
            d.chunks(shape[1]).map(|c| c.to_vec()).collect()
        };
        list.push(gs4city::sam::SamMask::from_mask(
            &Array2::from_shape_fn((h, w), |(y, x)| shifted(y, x)),
            0.9,
            0.95,
            vec![],
        ));
        feats.push(vec![0.0, 0.0, 0.0, 1.0]);
        gs4city::sam::write_sam_json(&sam2.join(format!("{stem}.json")), &list).unwrap();
        gs4city::sam::write_features_npy(&feat2.join(format!("{stem}.npy")), 4, &feats).unwrap();
    }
    let run = |snap: bool, out: &Path| {
        fuse::run(
            &fuse::FuseInputs {
                views: &b.views,
                associate: &assoc,
                raycast: &ray,
                entities: &entities(),
                sam: Some(&sam2),
                features: Some(&feat2),
                kept: Some(&b.masks),
            },
            &FuseOptions {
                snap,
                ..Default::default()
            },
            out,
        )
        .unwrap()
    };
    let off = run(false, &b.dir.join("snap-off"));
    assert!(off.snap.is_none());
    let on = run(true, &b.dir.join("snap-on"));
    let st = on.snap.unwrap();
    // IoU 120/280 ≈ 0.43 < 0.6: snapped in every view; 80 px move to the window, 80 back to wall.
    assert_eq!(st.snapped, b.views.len());
    assert_eq!(
        (st.pixels_to_part, st.pixels_to_surface),
        (80 * b.views.len() as u64, 80 * b.views.len() as u64)
    );
    for v in &b.views {
        let f = boxes::read_map(&b.dir.join(format!("snap-on/{}.ids.npy", v.stem())));
        for y in 0..30 {
            for x in 0..w {
                let expect = if shifted(y, x) { 2 } else { 1 };
                assert_eq!(f[y * w + x], expect, "({y}, {x})");
            }
        }
    }
}

#[test]
fn bad_inputs_are_errors_naming_the_file() {
    let b = boxes::build("fusebad", |_, _| false);
    let ray = raycast(&b);
    let assoc = associate(&b);
    // A raycast map of the wrong shape.
    let stem = b.views[3].stem();
    gs4city::npy::write(
        &ray.join(format!("{stem}.ids.npy")),
        &[H as usize, W as usize],
        &vec![0i32; (W * H) as usize],
    )
    .unwrap();
    let e = fuse::run(
        &fuse::FuseInputs {
            views: &b.views,
            associate: &assoc,
            raycast: &ray,
            entities: &entities(),
            sam: None,
            features: None,
            kept: None,
        },
        &FuseOptions::default(),
        &b.dir.join("bad1"),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains(&format!("{stem}.ids.npy")) && e.contains("shape"),
        "{e}"
    );
    // An entity id the semantics table does not have (a stale raycast).
    let ray = raycast(&b);
    let mut ids = boxes::read_map(&ray.join(format!("{stem}.ids.npy")));
    ids[0] = 7;
    gs4city::npy::write(
        &ray.join(format!("{stem}.ids.npy")),
        &[4, H as usize, W as usize],
        &ids,
    )
    .unwrap();
    let e = fuse::run(
        &fuse::FuseInputs {
            views: &b.views,
            associate: &assoc,
            raycast: &ray,
            entities: &entities(),
            sam: None,
            features: None,
            kept: None,
        },
        &FuseOptions::default(),
        &b.dir.join("bad2"),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains(&format!("{stem}.ids.npy")) && e.contains("stale"),
        "{e}"
    );
    assert!(!b.dir.join("bad2/summary.json").exists());
}

/// Removes the wall-clock fields (`timing`, per-view `seconds`) of a summary, recursively.
fn strip_timings(v: &mut serde_json::Value) {
    match v {
        serde_json::Value::Object(o) => {
            o.remove("timing");
            o.remove("seconds");
            o.values_mut().for_each(strip_timings);
        }
        serde_json::Value::Array(a) => a.iter_mut().for_each(strip_timings),
        _ => {}
    }
}

/// Digest of every file of `dir` (summary.json without its timings).
fn digests(dir: &Path) -> std::collections::BTreeMap<String, u64> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            let bytes = std::fs::read(&p).unwrap();
            let h = if name == "summary.json" {
                let mut v: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
                strip_timings(&mut v);
                xxhash_rust::xxh3::xxh3_64(v.to_string().as_bytes())
            } else {
                xxhash_rust::xxh3::xxh3_64(&bytes)
            };
            (name, h)
        })
        .collect()
}

#[test]
fn outputs_do_not_depend_on_simulation_truth() {
    // A small SIMULATED scene (synth), the core pipeline on it, then masks (the real stage,
    // default options) → associate (with the view support) → fuse (with snapping) twice: with
    // the simulation truth in the scene folder, and after deleting gt/, masks/*.sim.json,
    // masks/README.json and summary.json.
    let dir = boxes::tmp("truth");
    let scene = dir.join("scene");
    let run = dir.join("run");
    let cfg = dir.join("tiny.toml");
    std::fs::write(
        &cfg,
        "[cameras]\nwidth = 240\nheight = 180\norbit_views = 8\nstreet_views = 2\n\n[splats]\ndensity = 15.0\n\n[objects]\ntree_gaussians = 400\n",
    )
    .unwrap();
    let bin = env!("CARGO_BIN_EXE_gs4city");
    let ok = |args: &[&std::ffi::OsStr]| {
        let st = std::process::Command::new(bin)
            .args(args)
            .arg("-q")
            .status()
            .unwrap();
        assert!(st.success(), "{args:?}");
    };
    ok(&[
        "synth".as_ref(),
        "--preset".as_ref(),
        "small".as_ref(),
        "--config".as_ref(),
        cfg.as_os_str(),
        "--out".as_ref(),
        scene.as_os_str(),
    ]);
    ok(&[
        "run".as_ref(),
        "--scene".as_ref(),
        scene.as_os_str(),
        "--out".as_ref(),
        run.as_os_str(),
    ]);
    let views = gs4city::colmap::read_model(&scene.join("sparse/0")).unwrap();
    let split = gs4city::scene::Split::new(views, 8);
    let entities = gs4city::semantics::read(&run.join("citymodel/semantics.json")).unwrap();
    let cache = gs4city::cache::Cache::open(&run.join("render")).unwrap();
    let pass = |tag: &str| -> PathBuf {
        let out = dir.join(tag);
        let masks = out.join("masks");
        let sc = gs4city::scene::Scene::open(&scene).unwrap();
        let all = gs4city::colmap::read_model(&scene.join("sparse/0")).unwrap();
        gs4city::masks::run(
            &gs4city::masks::MasksInputs {
                scene: &sc,
                views: &all,
                raycast: &run.join("raycast"),
                cache: Some(&cache),
                alignment_scale: 1.0,
            },
            &gs4city::masks::MasksOptions::default(),
            &masks,
        )
        .unwrap();
        let a = associate::run(
            &associate::AssociateInputs {
                views: &split.train,
                masks: &masks,
                features: Some(&scene.join("features")),
                sam: Some(&scene.join("masks")),
                cache: &cache,
                ply: &scene.join("point_cloud.ply"),
                scale: 1.0,
            },
            &AssociateOptions::default(),
            &out.join("associate"),
        )
        .unwrap();
        assert!(a.groups > 0, "{a:?}");
        fuse::run(
            &fuse::FuseInputs {
                views: &split.train,
                associate: &out.join("associate"),
                raycast: &run.join("raycast"),
                entities: &entities,
                sam: Some(&scene.join("masks")),
                features: Some(&scene.join("features")),
                kept: Some(&masks),
            },
            &FuseOptions {
                snap: true,
                ..Default::default()
            },
            &out.join("fuse"),
        )
        .unwrap();
        out
    };
    let first = pass("with-truth");
    std::fs::remove_dir_all(scene.join("gt")).unwrap();
    std::fs::remove_file(scene.join("summary.json")).unwrap();
    std::fs::remove_file(scene.join("masks/README.json")).unwrap();
    for e in std::fs::read_dir(scene.join("masks")).unwrap() {
        let p = e.unwrap().path();
        if p.to_string_lossy().ends_with(".sim.json") {
            std::fs::remove_file(p).unwrap();
        }
    }
    let second = pass("without-truth");
    for sub in ["masks", "associate", "fuse"] {
        let (a, b) = (digests(&first.join(sub)), digests(&second.join(sub)));
        assert!(a.len() > 3, "{sub}: {a:?}");
        assert_eq!(a, b, "{sub}");
    }
}
