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

/// The numbers of every `<gml:posList>` / `<gml:pos>` of a CityGML text, as x y z triples
/// (a plain text scan, no gs4city code).
fn gml_vertices(text: &str) -> Vec<[f64; 3]> {
    let mut v = Vec::new();
    for tag in ["<gml:posList", "<gml:pos "] {
        for part in text.split(tag).skip(1) {
            let body = &part[part.find('>').unwrap() + 1..part.find('<').unwrap()];
            let n: Vec<f64> = body
                .split_whitespace()
                .map(|x| x.parse().unwrap())
                .collect();
            v.extend(n.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
        }
    }
    v
}

fn gml_ids(text: &str) -> Vec<String> {
    text.split("gml:id=\"")
        .skip(1)
        .map(|p| p[..p.find('"').unwrap()].to_string())
        .collect()
}

/// `[city] blocks = [2, 2]` of the `small` preset: four copies of its two buildings with unique
/// ids, shifted by whole metres, and rendered as one world — a view taken at one copy shows the
/// buildings of another. Checked independently: the CityGML text of the copies (ids, vertex
/// shifts), the neighbours' vertices projected by hand through the COLMAP text cameras, and the
/// views' ground truth holding instances of the neighbours' buildings.
#[test]
fn city_blocks_copies_have_unique_ids_and_appear_in_each_others_views() {
    let mut cfg = SynthConfig::preset(synth::Preset::Small);
    cfg.city.blocks = [2, 2];
    cfg.splats.density = 15.0;
    cfg.ground.density = 1.0;
    cfg.cameras.width = 160;
    cfg.cameras.height = 120;
    cfg.objects.tree_gaussians = 300;
    let out = tmp("city22");
    let s = synth::run(&cfg, &out).unwrap();
    assert_eq!(s.buildings, 8);
    assert_eq!(s.views, 4 * 14);

    // The copies: file k·2 + i is copy k of input i; ids unique, each the input's id + `_r<k>`.
    let inputs: Vec<String> = ["ingolstadt_4018106.gml", "ingolstadt_4018133.gml"]
        .iter()
        .map(|f| std::fs::read_to_string(data(&format!("data/citygml/{f}"))).unwrap())
        .collect();
    let mut all_ids = std::collections::HashSet::new();
    let mut copies: Vec<Vec<[f64; 3]>> = vec![Vec::new(); 4];
    let mut shifts = Vec::new();
    for (k, copy) in copies.iter_mut().enumerate() {
        for (i, input) in inputs.iter().enumerate() {
            let name = format!(
                "{:02}_r{k}_ingolstadt_{}.gml",
                k * 2 + i,
                ["4018106", "4018133"][i]
            );
            let text = std::fs::read_to_string(out.join("citymodel").join(&name)).unwrap();
            let ids = gml_ids(&text);
            let want: Vec<String> = gml_ids(input)
                .iter()
                .map(|id| format!("{id}_r{k}"))
                .collect();
            assert_eq!(ids, want, "{name}");
            for id in ids {
                assert!(all_ids.insert(id.clone()), "{id} twice in the city");
            }
            let (a, b) = (gml_vertices(input), gml_vertices(&text));
            assert_eq!(a.len(), b.len());
            let d = [b[0][0] - a[0][0], b[0][1] - a[0][1]];
            for (p, q) in a.iter().zip(&b) {
                assert!((q[0] - p[0] - d[0]).abs() < 1e-6 && (q[1] - p[1] - d[1]).abs() < 1e-6);
                assert_eq!(q[2], p[2]);
            }
            assert_eq!(d, [d[0].round(), d[1].round()], "shift by whole metres");
            shifts.push(d);
            copy.extend(b);
        }
    }
    // Copy 1 is one step along x, copy 2 one along y, copy 3 both; the step clears the block.
    let (w, h) = (shifts[2][0], shifts[4][1]);
    assert!(w > 20.0 && h > 20.0 && shifts[2][1] == 0.0 && shifts[4][0] == 0.0);
    assert_eq!(shifts[6], [w, h]);

    // The cameras, read from the COLMAP text files by hand; the scene frame from alignment.json.
    let al: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("citymodel/alignment.json")).unwrap())
            .unwrap();
    let origin: Vec<f64> = serde_json::from_value(al["origin"].clone()).unwrap();
    assert_eq!(al["scale"], 1.0);
    assert_eq!(al["translation"], serde_json::json!([0.0, 0.0, 0.0]));
    let cams = std::fs::read_to_string(out.join("sparse/0/cameras.txt")).unwrap();
    let c: Vec<f64> = cams
        .lines()
        .find(|l| !l.starts_with('#'))
        .unwrap()
        .split_whitespace()
        .skip(2)
        .map(|x| x.parse().unwrap())
        .collect();
    let (wd, ht, fx, fy, cx, cy) = (c[0], c[1], c[2], c[3], c[4], c[5]);
    let images = std::fs::read_to_string(out.join("sparse/0/images.txt")).unwrap();
    let centre = |k: usize| {
        let (lo, hi) = copies[k]
            .iter()
            .fold(([f64::MAX; 2], [f64::MIN; 2]), |(lo, hi), p| {
                (
                    [lo[0].min(p[0]), lo[1].min(p[1])],
                    [hi[0].max(p[0]), hi[1].max(p[1])],
                )
            });
        [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0]
    };
    let centres: Vec<[f64; 2]> = (0..4).map(centre).collect();
    let instances: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("gt/instances.json")).unwrap()).unwrap();
    // seen[j][k]: a view taken at copy j shows copy k's buildings (projection, and the GT).
    let mut seen = [[false; 4]; 4];
    let mut seen_gt = [[false; 4]; 4];
    for l in images.lines().filter(|l| !l.starts_with('#')) {
        let f: Vec<&str> = l.split_whitespace().collect();
        if f.len() != 10 {
            continue;
        }
        let n: Vec<f64> = f[1..8].iter().map(|x| x.parse().unwrap()).collect();
        let (qw, qx, qy, qz) = (n[0], n[1], n[2], n[3]);
        let r = [
            [
                1.0 - 2.0 * (qy * qy + qz * qz),
                2.0 * (qx * qy - qw * qz),
                2.0 * (qx * qz + qw * qy),
            ],
            [
                2.0 * (qx * qy + qw * qz),
                1.0 - 2.0 * (qx * qx + qz * qz),
                2.0 * (qy * qz - qw * qx),
            ],
            [
                2.0 * (qx * qz - qw * qy),
                2.0 * (qy * qz + qw * qx),
                1.0 - 2.0 * (qx * qx + qy * qy),
            ],
        ];
        let t = [n[4], n[5], n[6]];
        // Camera centre −Rᵀt, back in the CityGML frame; its copy is the nearest block centre.
        let cc: Vec<f64> = (0..3)
            .map(|i| -(r[0][i] * t[0] + r[1][i] * t[1] + r[2][i] * t[2]) + origin[i])
            .collect();
        let own = (0..4)
            .min_by(|&a, &b| {
                let d =
                    |k: usize| (centres[k][0] - cc[0]).powi(2) + (centres[k][1] - cc[1]).powi(2);
                d(a).total_cmp(&d(b))
            })
            .unwrap();
        for k in (0..4).filter(|&k| k != own) {
            // The neighbour's vertices in front of the camera and inside the image; seen when
            // they span 8 px or more (a far block projects inside the image too, but tiny).
            let (mut lo, mut hi, mut n_in) = (f64::MAX, f64::MIN, 0);
            for p in &copies[k] {
                let q = [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
                let x: Vec<f64> = (0..3)
                    .map(|i| r[i][0] * q[0] + r[i][1] * q[1] + r[i][2] * q[2] + t[i])
                    .collect();
                let (u, v) = (fx * x[0] / x[2] + cx, fy * x[1] / x[2] + cy);
                if x[2] > 0.1 && (0.0..wd).contains(&u) && (0.0..ht).contains(&v) {
                    (lo, hi, n_in) = (lo.min(u), hi.max(u), n_in + 1);
                }
            }
            if n_in >= 10 && hi - lo >= 8.0 {
                seen[own][k] = true;
            }
        }
        // The view's truth: which copies' buildings are drawn in it.
        let stem = f[9].trim_end_matches(".png");
        let (_, inst) =
            gs4city::npy::read::<i32>(&out.join(format!("gt/{stem}.instance.npy"))).unwrap();
        for i in inst.iter().filter(|&&i| (0..1_000_000).contains(&i)) {
            // Derived ids (`<id>_r<k>/WallSurface[3]`) carry the copy before the first `/`.
            let id = instances[i.to_string()]["object_id"].as_str().unwrap();
            let head = id.split('/').next().unwrap();
            let k: usize = head.rsplit("_r").next().unwrap().parse().unwrap();
            if k != own {
                seen_gt[own][k] = true;
            }
        }
    }
    for k in 0..4 {
        assert!(
            (0..4).any(|j| j != k && seen[j][k] && seen_gt[j][k]),
            "no view of another copy shows copy {k}'s buildings: projected {seen:?}, truth {seen_gt:?}"
        );
    }
    let _ = std::fs::remove_dir_all(&out);
}
