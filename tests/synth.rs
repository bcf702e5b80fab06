//! `synth`: determinism, truth semantics, GT consistency (windows, occluders), config errors.
//! Tiny configurations (one bundled building, few small views) keep this fast.
use crate::common::files;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::DVec3;
use gs4city::camera::{Camera, Pose};
use gs4city::classes;
use gs4city::render::PreparedScene;
use gs4city::splat::Gaussians;
use gs4city::synth::{self, SynthConfig, gt};

fn data(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)
}

fn tiny(seed: u64) -> SynthConfig {
    let mut c = SynthConfig {
        seed,
        citygml: vec![data("data/citygml/ingolstadt_4018133.gml")],
        ..Default::default()
    };
    c.splats.density = 25.0;
    c.ground.density = 2.0;
    c.ground.margin = 8.0;
    c.objects.trees = 1;
    c.objects.cars = 1;
    c.objects.persons = 1;
    c.objects.occluder_fraction = 1.0;
    c.objects.tree_gaussians = 600;
    c.cameras.width = 200;
    c.cameras.height = 150;
    c.cameras.orbit_views = 2;
    c.cameras.orbit_radius = [30.0, 35.0];
    c.cameras.street_views = 1;
    c.output.contact_views = 2;
    c
}

fn tmp(name: &str) -> PathBuf {
    let d = crate::common::temp_dir().join(format!("gs4city_synth_{}_{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn summary_without_timings(bytes: &[u8]) -> serde_json::Value {
    let mut v: serde_json::Value = serde_json::from_slice(bytes).unwrap();
    v.as_object_mut().unwrap().remove("timing");
    v
}

#[test]
fn same_seed_identical_other_seed_differs() {
    let (a, b, c) = (tmp("a"), tmp("b"), tmp("c"));
    synth::run(&tiny(7), &a).unwrap();
    synth::run(&tiny(7), &b).unwrap();
    synth::run(&tiny(8), &c).unwrap();
    let (fa, fb, fc) = (files(&a), files(&b), files(&c));
    assert_eq!(fa.keys().collect::<Vec<_>>(), fb.keys().collect::<Vec<_>>());
    for (k, v) in &fa {
        if k == "summary.json" {
            assert_eq!(summary_without_timings(v), summary_without_timings(&fb[k]));
        } else {
            assert!(
                v == &fb[k],
                "{k} differs between two runs with the same seed"
            );
        }
    }
    // The folder is complete (DESIGN.md).
    for k in [
        "point_cloud.ply",
        "sparse/0/cameras.bin",
        "sparse/0/images.txt",
        "gt/gaussians.npy",
        "gt/instances.json",
        "citymodel/alignment.json",
        "citymodel/00_ingolstadt_4018133.gml",
        "images/orbit_000.png",
        "gt/orbit_000.class.npy",
        "gt/orbit_000.instance.npy",
        "gt/orbit_000.hier.npy",
        "contact_sheet.png",
    ] {
        assert!(fa.contains_key(k), "missing {k}");
    }
    assert_ne!(fa["point_cloud.ply"], fc["point_cloud.ply"]);
    assert_ne!(fa["gt/gaussians.npy"], fc["gt/gaussians.npy"]);
    // The COLMAP model reads back; every 8th view is a test view.
    let views = gs4city::colmap::read_model(&a.join("sparse/0")).unwrap();
    assert_eq!(views.len(), 3);
    let s: serde_json::Value = serde_json::from_slice(&fa["summary.json"]).unwrap();
    assert_eq!(s["test_views"], serde_json::json!(["orbit_000.png"]));
    assert_eq!(s["simulated"], true);
    // Zero noise: the alignment handed over is the true one.
    assert_eq!(s["alignment_given"], s["alignment_true"]);

    // Semantics: building pixels' instances are entities of the true city model, with the
    // class the entity has, and the hierarchy's finest level is that instance.
    let cm = gs4city::citymodel::run(
        &[a.join("citymodel/00_ingolstadt_4018133.gml")],
        &Default::default(),
    )
    .unwrap();
    let mut building_px = 0;
    for v in &views {
        let stem = v.stem();
        let (shape, class) =
            gs4city::npy::read::<i32>(&a.join(format!("gt/{stem}.class.npy"))).unwrap();
        let (_, inst) =
            gs4city::npy::read::<i32>(&a.join(format!("gt/{stem}.instance.npy"))).unwrap();
        let (hs, hier) = gs4city::npy::read::<i32>(&a.join(format!("gt/{stem}.hier.npy"))).unwrap();
        assert_eq!(shape, vec![150, 200]);
        assert_eq!(hs, vec![3, 150, 200]);
        let n = class.len();
        for p in 0..n {
            if classes::is_building(class[p]) {
                building_px += 1;
                let e = inst[p];
                assert!(e >= 0 && (e as usize) < cm.entities.len(), "instance {e}");
                assert_eq!(classes::of_entity(&cm.entities, e), class[p]);
                let finest = [hier[2 * n + p], hier[n + p], hier[p]]
                    .into_iter()
                    .find(|&x| x >= 0);
                assert_eq!(finest, Some(e));
                assert_eq!(
                    cm.entities[hier[p] as usize].level,
                    gs4city::citygml::Level::Feature
                );
            } else {
                assert!(
                    e_none_or_sim(inst[p]),
                    "non-building pixel with instance {}",
                    inst[p]
                );
                assert_eq!(hier[p], -1);
            }
        }
    }
    assert!(building_px > 1000, "{building_px} building pixels");
    for d in [a, b, c] {
        let _ = std::fs::remove_dir_all(d);
    }
}

fn e_none_or_sim(i: i32) -> bool {
    i == -1 || i >= synth::world::FIRST_INSTANCE
}

fn subset(
    g: &Gaussians,
    truth: &[[i32; 5]],
    keep: impl Fn(&[i32; 5]) -> bool,
) -> (Gaussians, Vec<[i32; 5]>) {
    let mut out = Gaussians {
        sh_degree: g.sh_degree,
        ..Default::default()
    };
    let mut t = Vec::new();
    let r = g.rest_per_gaussian();
    for (i, tr) in truth.iter().enumerate() {
        if keep(tr) {
            out.positions.push(g.positions[i]);
            out.f_dc.push(g.f_dc[i]);
            out.f_rest.extend_from_slice(&g.f_rest[i * r..(i + 1) * r]);
            out.opacity.push(g.opacity[i]);
            out.scale.push(g.scale[i]);
            out.rotation.push(g.rotation[i]);
            t.push(*tr);
        }
    }
    (out, t)
}

fn labels(g: &Gaussians, truth: &[[i32; 5]], cam: &Camera) -> gt::ViewLabels {
    let scene = PreparedScene::new(g).unwrap();
    gt::label_view(&scene, truth, cam, [0.0; 3], 0.5).unwrap()
}

#[test]
fn visible_windows_are_in_gt_and_occluders_hide_openings() {
    let cfg = tiny(3);
    let sim = synth::build_scene(&cfg).unwrap();
    let g = &sim.builder.g;
    let truth = &sim.builder.truth;
    let (city_g, city_t) = subset(g, truth, |t| classes::is_building(t[0]));
    assert!(city_g.len() > 1000 && city_g.len() < g.len());

    // Windows: every opening covering ≥ 50 px in a render of the city Gaussians alone (and not
    // hidden there by a simulated object in the full GT) appears in the full GT.
    let mut checked = 0;
    for v in &sim.views {
        let full = labels(g, truth, &v.camera);
        let city = labels(&city_g, &city_t, &v.camera);
        let mut px: BTreeMap<i32, (usize, usize, usize)> = BTreeMap::new();
        for p in 0..city.instance.len() {
            if matches!(city.class[p], classes::WINDOW | classes::DOOR) {
                let e = px.entry(city.instance[p]).or_default();
                e.0 += 1;
                if classes::is_building(full.class[p]) || full.class[p] < 0 {
                    e.1 += 1;
                }
                if full.instance[p] == city.instance[p] {
                    e.2 += 1;
                }
            }
        }
        for (id, (n, unhidden, in_gt)) in px {
            if n >= 50 && unhidden >= 50 {
                checked += 1;
                assert!(
                    in_gt > 0,
                    "view {}: opening {id} ({n} px alone) missing from GT",
                    v.name
                );
            }
        }
    }
    assert!(checked >= 3, "only {checked} openings checked");

    // Occluders: look at each occluded opening from in front; where the occluder alone is
    // opaque and nearer than the city surface, the GT says tree/car/person.
    let occ: Vec<_> = sim
        .world
        .objects
        .iter()
        .filter(|o| o.occludes.is_some())
        .collect();
    assert!(!occ.is_empty());
    let mut hidden_openings = 0;
    for o in occ {
        let id = o.occludes.unwrap();
        let f = sim.city.openings.iter().find(|f| f.entity == id).unwrap();
        let nh = DVec3::new(f.normal.x, f.normal.y, 0.0).normalize();
        let eye = f.centroid + nh * 14.0;
        let cam = Camera {
            intrinsics: sim.views[0].camera.intrinsics,
            pose: Pose::look_at(eye, f.centroid, DVec3::Z).unwrap(),
        };
        let full = labels(g, truth, &cam);
        let city = labels(&city_g, &city_t, &cam);
        let (og, ot) = subset(g, truth, |t| t[1] == o.instance);
        let scene = PreparedScene::new(&og).unwrap();
        let alone = gs4city::render::render_view(&scene, &cam, &Default::default()).unwrap();
        let city_r = gs4city::render::render_view(
            &PreparedScene::new(&city_g).unwrap(),
            &cam,
            &Default::default(),
        )
        .unwrap();
        let class = ot[0][0];
        let (mut total, mut agree, mut not_city) = (0, 0, 0);
        let mut other: BTreeMap<i32, usize> = BTreeMap::new();
        for p in 0..full.class.len() {
            let nearer =
                city_r.alpha[p] < 0.5 || alone.median_depth[p] < city_r.median_depth[p] - 0.5;
            if alone.alpha[p] > 0.95 && nearer {
                total += 1;
                if full.class[p] == class {
                    agree += 1;
                } else {
                    *other.entry(full.class[p]).or_default() += 1;
                }
                if !classes::is_building(full.class[p]) {
                    not_city += 1;
                }
                if matches!(city.class[p], classes::WINDOW | classes::DOOR)
                    && full.class[p] == class
                {
                    hidden_openings += 1;
                }
            }
        }
        assert!(total > 20, "occluder {} covers only {total} px", o.instance);
        // What the occluder covers is never building in the GT; mostly it is the occluder
        // itself (another simulated object may stand in front of it).
        assert!(
            not_city as f64 >= 0.98 * total as f64,
            "occluder {}: {not_city}/{total} {other:?}",
            o.instance
        );
        assert!(
            agree as f64 >= 0.75 * total as f64,
            "occluder {}: {agree}/{total} {other:?}",
            o.instance
        );
    }
    assert!(hidden_openings > 0, "no occluder hides an opening pixel");
}

#[test]
fn alignment_noise_has_the_configured_size() {
    use rand::SeedableRng;
    let a = gs4city::alignment::Alignment::local(DVec3::new(678000.0, 5403000.0, 400.0));
    let noise = synth::config::Noise {
        translation_m: 0.5,
        rotation_deg: 1.0,
        scale: 0.01,
    };
    let c = DVec3::new(10.0, 20.0, 5.0);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let p = synth::perturb(&a, &noise, c, &mut rng);
    let angle = ((p.rotation * a.rotation.transpose()).to_cols_array()[0]
        + (p.rotation * a.rotation.transpose()).to_cols_array()[4]
        + (p.rotation * a.rotation.transpose()).to_cols_array()[8]
        - 1.0)
        / 2.0;
    assert!((angle.acos().to_degrees() - 1.0).abs() < 1e-6);
    assert!(((p.scale - 1.0).abs() - 0.01).abs() < 1e-12);
    // The scene centre moves by exactly the translation error.
    let geo_c = c + a.origin;
    assert!(((p.apply(geo_c) - a.apply(geo_c)).length() - 0.5).abs() < 1e-6);
    let zero = synth::perturb(&a, &Default::default(), c, &mut rng);
    assert_eq!(zero, a);
}

#[test]
fn bad_config_names_key_and_file() {
    let d = tmp("cfg");
    std::fs::create_dir_all(&d).unwrap();
    let f = d.join("synth.toml");
    std::fs::write(&f, "[splats]\ndensty = 3\n").unwrap();
    let e = SynthConfig::load(&f, SynthConfig::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("densty") && e.contains("synth.toml"), "{e}");
    std::fs::write(&f, "[cameras]\norbit_radius = [50.0, 40.0]\n").unwrap();
    let e = SynthConfig::load(&f, SynthConfig::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("cameras.orbit_radius") && e.contains("synth.toml"),
        "{e}"
    );
    std::fs::write(
        &f,
        "seed = 5\ncitygml = [\"x.gml\"]\n[splats]\ndensity = 3.0\n",
    )
    .unwrap();
    let c = SynthConfig::load(&f, SynthConfig::default()).unwrap();
    assert_eq!((c.seed, c.splats.density, c.ground.density), (5, 3.0, 8.0));
    assert_eq!(c.citygml, vec![d.join("x.gml")]);
    let _ = std::fs::remove_dir_all(d);
}
