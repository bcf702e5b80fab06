//! `synth`: a SIMULATED scene folder (`docs/design.md`) with exact ground truth, built from real
//! CityGML: Gaussians on the true city model (textured, windows/doors recessed, glass
//! view-dependent), a ground plane, water, trees, cars, persons (some occluding openings),
//! floaters; drone-orbit and street-level PINHOLE cameras (COLMAP bin + txt); images from the
//! project's own rasterizer; per-view GT from the Gaussians' truth (top-1 α·T); the real
//! CityGML handed to the pipeline with a perturbed alignment; `summary.json`; a contact sheet.
//!
//! Submodules: [`config`] (TOML, presets), [`gaussians`] (builder, truth), [`city`] (building
//! Gaussians), [`world`] (ground, objects, floaters), [`cameras`], [`gt`] (labels, contact sheet),
//! [`blocks`] (`[city]`: copies of the input blocks side by side).
//! Deterministic: every random draw comes from one seeded ChaCha8 stream per part.
pub mod blocks;
pub mod cameras;
pub mod city;
pub mod config;
pub mod features;
pub mod gaussians;
pub mod gt;
pub mod masks;
pub mod model_edit;
pub mod world;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DVec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde_json::json;

pub use config::{Preset, SynthConfig};
use gaussians::{Builder, Truth};

use crate::alignment::Alignment;
use crate::camera::{Camera, Pose, View};
use crate::citygml::{self, CityModel};
use crate::citymodel;
use crate::classes;
use crate::render::PreparedScene;
use crate::semantics::Entity;

/// Errors of the synth stage.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error("config {path}: {why}")]
    Config { path: PathBuf, why: String },
    #[error("{0}")]
    Input(String),
    #[error(transparent)]
    CityGml(#[from] citygml::CityGmlError),
    #[error(transparent)]
    CityJson(#[from] crate::cityjson::CityJsonError),
    #[error(transparent)]
    Sam(#[from] crate::sam::SamError),
    #[error(transparent)]
    CityModel(#[from] citymodel::CityModelError),
    #[error(transparent)]
    Render(#[from] crate::render::RenderError),
    #[error(transparent)]
    Fs(#[from] crate::fsutil::FsError),
    #[error(transparent)]
    Npy(#[from] crate::npy::NpyError),
    #[error(transparent)]
    Image(#[from] crate::imageio::ImageError),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Colmap(#[from] crate::colmap::ColmapError),
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    #[error("copy {from} → {to}: {err}")]
    Copy {
        from: PathBuf,
        to: PathBuf,
        err: std::io::Error,
    },
}

/// The simulated scene in the scene frame.
pub struct SimScene {
    pub files: Vec<PathBuf>,
    pub entities: Vec<Entity>,
    pub truth_alignment: Alignment,
    pub builder: Builder,
    pub views: Vec<View>,
    pub city: city::CityInfo,
    pub world: world::WorldInfo,
    pub timings: BTreeMap<&'static str, f64>,
}

fn rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    r.set_stream(stream);
    r
}

/// The true alignment: origin = floored bbox minimum of the used polygons, then the
/// configured rotation about z, scale and translation.
fn true_alignment(models: &[CityModel], cfg: &SynthConfig) -> Alignment {
    let mut lo = DVec3::splat(f64::INFINITY);
    for m in models {
        for p in m.used_polygons() {
            for q in p.exterior.points.iter().filter(|q| q.is_finite()) {
                lo = lo.min(*q);
            }
        }
    }
    Alignment {
        origin: if lo.is_finite() {
            lo.floor()
        } else {
            DVec3::ZERO
        },
        scale: cfg.alignment.scale,
        rotation: DMat3::from_rotation_z(cfg.alignment.rotation_deg.to_radians()),
        translation: DVec3::from_array(cfg.alignment.translation),
    }
}

/// Builds the simulated scene (Gaussians, truth, cameras) without writing anything.
pub fn build_scene(cfg: &SynthConfig) -> Result<SimScene, SynthError> {
    let files = config::collect_files(&cfg.citygml)?;
    let texture_dirs = files
        .iter()
        .map(|f| f.parent().unwrap_or(Path::new(".")).to_path_buf())
        .collect::<Vec<_>>();
    build_scene_from(cfg, files, &texture_dirs)
}

/// [`build_scene`] on the given CityGML files, each with the folder its texture URIs are
/// relative to.
fn build_scene_from(
    cfg: &SynthConfig,
    files: Vec<PathBuf>,
    texture_dirs: &[PathBuf],
) -> Result<SimScene, SynthError> {
    let mut timings = BTreeMap::new();
    let t0 = Instant::now();
    let models: Vec<CityModel> = files
        .par_iter()
        .map(|f| crate::cityjson::read_any(f))
        .collect::<Result<_, _>>()?;
    let truth_alignment = true_alignment(&models, cfg);
    let cm = citymodel::run(
        &files,
        &citymodel::Options {
            alignment: Some(truth_alignment),
        },
    )?;
    let n_obj: usize = models.iter().map(|m| m.objects.len()).sum();
    if n_obj != cm.entities.len() {
        return Err(SynthError::Input(format!(
            "entity table mismatch: {n_obj} objects read, citymodel has {}",
            cm.entities.len()
        )));
    }
    timings.insert("read_citygml_s", t0.elapsed().as_secs_f64());

    let t1 = Instant::now();
    let mut b = Builder::new();
    let city = city::build(
        texture_dirs,
        &models,
        &cm.entities,
        truth_alignment.origin,
        &cfg.splats,
        &mut rng(cfg.seed, 1),
        &mut b,
    )?;
    let map = world::GroundMap::new(&city, cfg.ground.margin);
    let water = world::ground(
        &map,
        &cfg.ground,
        &cfg.splats,
        &mut rng(cfg.seed, 2),
        &mut b,
    );
    let mut world = world::objects(&map, &city, &cfg.objects, &mut rng(cfg.seed, 3), &mut b);
    world.water = water;
    timings.insert("gaussians_s", t1.elapsed().as_secs_f64());

    let t2 = Instant::now();
    let cams = cameras::generate(&cfg.cameras, &city, &map, &mut rng(cfg.seed, 5));
    // Local metric frame → scene frame: p_s = s·R·p_l + t.
    let (s, r, t) = (
        truth_alignment.scale,
        truth_alignment.rotation,
        truth_alignment.translation,
    );
    b.transform(s, r, t);
    let mut counters = BTreeMap::new();
    let mut views: Vec<View> = cams
        .iter()
        .map(|c| {
            let k = counters.entry(c.kind).or_insert(0usize);
            let name = format!("{}_{:03}.png", c.kind, *k);
            *k += 1;
            let rc = c.camera.pose.rotation * r.transpose();
            View {
                image_id: 0,
                camera_id: 1,
                name,
                camera: Camera {
                    intrinsics: c.camera.intrinsics,
                    pose: Pose {
                        rotation: rc,
                        translation: s * c.camera.pose.translation - rc * t,
                    },
                },
            }
        })
        .collect();
    views.sort_by(|a, b| a.name.cmp(&b.name));
    for (i, v) in views.iter_mut().enumerate() {
        v.image_id = i as u32 + 1;
    }
    timings.insert("cameras_s", t2.elapsed().as_secs_f64());
    Ok(SimScene {
        files,
        entities: cm.entities,
        truth_alignment,
        builder: b,
        views,
        city,
        world,
        timings,
    })
}

/// The alignment handed to the pipeline: the true one perturbed about the scene centre `c`
/// by a rotation of exactly `rotation_deg` about a random axis, a translation of exactly
/// `translation_m` (scene units = metres·scale) in a random direction and a relative scale
/// error of ±`scale`. Zero noise returns the true alignment unchanged.
pub fn perturb(a: &Alignment, noise: &config::Noise, c: DVec3, rng: &mut ChaCha8Rng) -> Alignment {
    let unit = |rng: &mut ChaCha8Rng| loop {
        let v = DVec3::new(
            rng.random::<f64>() * 2.0 - 1.0,
            rng.random::<f64>() * 2.0 - 1.0,
            rng.random::<f64>() * 2.0 - 1.0,
        );
        let l = v.length();
        if l > 1e-3 && l <= 1.0 {
            return v / l;
        }
    };
    let axis = unit(rng);
    let dir = unit(rng);
    let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
    if noise.rotation_deg == 0.0 && noise.translation_m == 0.0 && noise.scale == 0.0 {
        return *a;
    }
    let rn = DMat3::from_axis_angle(axis, noise.rotation_deg.to_radians());
    let e = 1.0 + sign * noise.scale;
    let tn = dir * noise.translation_m * a.scale;
    Alignment {
        origin: a.origin,
        scale: a.scale * e,
        rotation: rn * a.rotation,
        translation: c + e * (rn * (a.translation - c)) + tn,
    }
}

fn count_by_class(truth: &[Truth]) -> BTreeMap<String, usize> {
    let mut m = BTreeMap::new();
    for t in truth {
        *m.entry(classes::name(t[0]).to_string()).or_insert(0) += 1;
    }
    m
}

/// `summary.json` of a simulated scene: what was simulated, with the truth (alignment, objects,
/// masks provenance). Simulation truth: read by tests and benchmarks, never by a stage.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SynthSummary {
    pub simulated: bool,
    pub note: String,
    pub seed: u64,
    pub citygml: Vec<String>,
    pub citymodel_copies: Vec<String>,
    pub gaussians: usize,
    pub gaussians_per_class: BTreeMap<String, usize>,
    pub textured_gaussians: usize,
    pub textures_found: Vec<String>,
    pub textures_missing: Vec<String>,
    pub polygons_skipped: usize,
    pub buildings: usize,
    pub openings: usize,
    pub objects: serde_json::Value,
    pub water: bool,
    pub floaters: usize,
    pub views: usize,
    pub view_names: Vec<String>,
    pub test_views: Vec<String>,
    pub pixels_per_class: BTreeMap<String, u64>,
    pub per_view: Vec<serde_json::Value>,
    pub alignment_true: serde_json::Value,
    pub alignment_given: serde_json::Value,
    pub noise: serde_json::Value,
    pub simulated_masks: serde_json::Value,
    pub timing: BTreeMap<String, f64>,
    pub config: serde_json::Value,
    /// `[city]`: the grid of copies and the file of each (null for one block).
    #[serde(default)]
    pub city_blocks: serde_json::Value,
}

/// Builds the scene and writes the whole folder; returns `summary.json`.
pub fn run(cfg: &SynthConfig, out: &Path) -> Result<SynthSummary, SynthError> {
    let t_all = Instant::now();
    let _ = std::fs::remove_file(out.join("summary.json"));
    // `[city]`: the copies are written into a staging folder, read as the inputs, copied into
    // `citymodel/` like any input and removed at the end.
    let staging = out.join(".city_blocks");
    let _ = std::fs::remove_dir_all(&staging);
    let originals = config::collect_files(&cfg.citygml)?;
    let (whole, mut sim, city_blocks) = if cfg.city.copies() > 1 {
        crate::fsutil::create_dir(&staging)?;
        let reps = blocks::replicate(&originals, &cfg.city, &staging)?;
        let whole = blocks::whole_city(cfg);
        let dirs: Vec<PathBuf> = reps.iter().map(|r| r.texture_dir.clone()).collect();
        let sim = build_scene_from(&whole, reps.iter().map(|r| r.path.clone()).collect(), &dirs)?;
        let info = json!({
            "blocks": cfg.city.blocks, "spacing_m": cfg.city.spacing,
            "copies": reps.iter().map(|r| json!({"copy": r.copy, "source": r.source.display().to_string(),
                "file": r.path.file_name().map(|n| n.to_string_lossy().into_owned())})).collect::<Vec<_>>(),
            "note": "SIMULATED city: copies of the input CityGML blocks side by side, ids suffixed _r<copy>; object and view counts per copy",
        });
        (whole, sim, info)
    } else {
        (cfg.clone(), build_scene(cfg)?, serde_json::Value::Null)
    };
    let cfg = &whole;
    let t_w = Instant::now();
    for d in ["", "images", "gt", "citymodel", "sparse"] {
        crate::fsutil::create_dir(&out.join(d))?;
    }
    let g = &sim.builder.g;
    crate::splat::write_ply(
        &out.join("point_cloud.ply"),
        g,
        crate::splat::PlyEncoding::BinaryLittleEndian,
    )?;
    let flat: Vec<i32> = sim.builder.truth.iter().flatten().copied().collect();
    crate::npy::write(
        &out.join("gt/gaussians.npy"),
        &[sim.builder.truth.len(), 5],
        &flat,
    )?;
    // COLMAP: both encodings in sparse/0 (read_model prefers .bin).
    let sparse = out.join("sparse/0");
    crate::colmap::write_model(&sparse, &sim.views, true)?;
    crate::colmap::write_model(&sparse, &sim.views, false)?;
    sim.timings
        .insert("write_scene_s", t_w.elapsed().as_secs_f64());

    // Render images and GT.
    let t_r = Instant::now();
    let scene = PreparedScene::new(g)?;
    let mut px_class: BTreeMap<String, u64> = BTreeMap::new();
    let mut sheet_views = Vec::new();
    let n_sheet = cfg.output.contact_views.min(sim.views.len());
    let sheet_pick: Vec<usize> = (0..n_sheet)
        .map(|i| i * sim.views.len() / n_sheet.max(1))
        .collect();
    let mut per_view = Vec::new();
    // SIMULATED foundation-model outputs (docs/sam.md): SAM-format masks from the GT
    // instances through the noise model, and CLIP-like features per mask.
    crate::fsutil::create_dir(&out.join("masks"))?;
    crate::fsutil::create_dir(&out.join("features"))?;
    masks::write_provenance(
        &out.join("masks"),
        &masks::provenance(&cfg.masks, Some(&cfg.features), cfg.seed),
    )?;
    let mut n_masks = 0usize;
    let mut prompts = None;
    let bar = crate::progress::Bar::new("synth", sim.views.len() as u64, "views");
    for (vi, v) in sim.views.iter().enumerate() {
        bar.inc(1);
        let l = gt::label_view(
            &scene,
            &sim.builder.truth,
            &v.camera,
            cfg.cameras.background,
            cfg.output.min_alpha,
        )?;
        let stem = v.stem();
        crate::imageio::write_png(&out.join("images").join(&v.name), &l.rgb)?;
        let (h, w) = (l.height, l.width);
        crate::npy::write(&out.join(format!("gt/{stem}.class.npy")), &[h, w], &l.class)?;
        crate::npy::write(
            &out.join(format!("gt/{stem}.instance.npy")),
            &[h, w],
            &l.instance,
        )?;
        crate::npy::write(
            &out.join(format!("gt/{stem}.hier.npy")),
            &[3, h, w],
            &l.hier,
        )?;
        let inst_a = ndarray::ArrayView2::from_shape((h, w), &l.instance).expect("H×W map");
        let class_a = ndarray::ArrayView2::from_shape((h, w), &l.class).expect("H×W map");
        let view_seed = cfg
            .seed
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .wrapping_add(vi as u64);
        let sim_masks = masks::simulate_masks(inst_a, class_a, &cfg.masks, view_seed);
        let sam: Vec<crate::sam::SamMask> = sim_masks.iter().map(|m| m.mask.clone()).collect();
        crate::sam::write_sam_json(&out.join(format!("masks/{stem}.json")), &sam)?;
        masks::write_simulation_truth(&out.join(format!("masks/{stem}.sim.json")), &sim_masks)?;
        let mask_classes: Vec<i32> = sim_masks.iter().map(|m| m.class).collect();
        let (feats, p) = masks::simulate_features(&mask_classes, &cfg.features, view_seed);
        crate::sam::write_features_npy(
            &out.join(format!("features/{stem}.npy")),
            masks::FEATURE_DIM,
            &feats,
        )?;
        prompts = Some(p);
        n_masks += sam.len();
        let mut counts: BTreeMap<String, u64> = BTreeMap::new();
        for &c in &l.class {
            *counts.entry(classes::name(c).to_string()).or_insert(0) += 1;
        }
        for (k, n) in &counts {
            *px_class.entry(k.clone()).or_insert(0) += n;
        }
        per_view.push(json!({"name": v.name, "pixels": counts}));
        if sheet_pick.contains(&vi) {
            sheet_views.push((l.rgb, l.class));
        }
    }
    bar.finish();
    if let Some(p) = &prompts {
        crate::sam::write_prompts_json(&out.join("features/prompts.json"), p)?;
    }
    if let Some(sheet) = gt::contact_sheet(&sheet_views) {
        crate::imageio::write_png(&out.join("contact_sheet.png"), &sheet)?;
    }
    sim.timings
        .insert("render_gt_s", t_r.elapsed().as_secs_f64());

    // City model handed to the pipeline: copies (index-prefixed to keep the order, and so
    // the entity ids) and the perturbed alignment.
    let t_c = Instant::now();
    let mut copied = Vec::new();
    let mut dropped = Vec::new();
    // Index-prefixed names as wide as the largest index, so that name order is input order.
    let width = 2.max(sim.files.len().saturating_sub(1).to_string().len());
    for (i, f) in sim.files.iter().enumerate() {
        if cfg.model.drop_openings > 0.0 {
            // The edited model, as CityJSON (the truth was built from the full one).
            let full = crate::cityjson::read_any(f)?;
            let (edited, gone) =
                model_edit::drop_openings(&full, cfg.model.drop_openings, cfg.seed);
            dropped.extend(gone);
            let stem = f
                .file_stem()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_else(|| format!("{i}"));
            let dst = out
                .join("citymodel")
                .join(format!("{i:0width$}_{stem}.city.json"));
            crate::cityjson::write(&dst, &edited)?;
            copied.push(dst.file_name().map(|n| n.to_string_lossy().into_owned()));
            continue;
        }
        let name = f
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| format!("{i}.gml"));
        let dst = out.join("citymodel").join(format!("{i:0width$}_{name}"));
        std::fs::copy(f, &dst).map_err(|err| SynthError::Copy {
            from: f.clone(),
            to: dst.clone(),
            err,
        })?;
        copied.push(dst.file_name().map(|n| n.to_string_lossy().into_owned()));
    }
    let centre = {
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for p in &sim.builder.g.positions {
            let q = DVec3::from_array(p.map(f64::from));
            lo = lo.min(q);
            hi = hi.max(q);
        }
        if lo.is_finite() {
            (lo + hi) * 0.5
        } else {
            DVec3::ZERO
        }
    };
    let given = perturb(
        &sim.truth_alignment,
        &cfg.noise,
        centre,
        &mut rng(cfg.seed, 6),
    );
    crate::fsutil::write_json(&out.join("citymodel/alignment.json"), &given.to_json())?;
    if cfg.model.drop_openings > 0.0 {
        crate::fsutil::write_json(
            &out.join("gt/model_edit.json"),
            &json!({
                "SIMULATED": true,
                "note": "simulation truth, for scoring only: the openings removed from the pipeline's city model (citymodel/*.city.json); gt/ keeps them",
                "drop_openings": cfg.model.drop_openings,
                "seed": cfg.seed,
                "dropped": dropped,
            }),
        )?;
    }
    let _ = std::fs::remove_dir_all(&staging);
    sim.timings
        .insert("citymodel_copy_s", t_c.elapsed().as_secs_f64());

    // Instances.
    let mut inst: BTreeMap<String, serde_json::Value> = BTreeMap::new();
    let mut used: std::collections::BTreeSet<i32> = Default::default();
    for t in &sim.builder.truth {
        used.insert(t[1]);
    }
    for &i in &used {
        let v = if i >= world::FIRST_INSTANCE {
            let kind = match i {
                world::ROAD_INSTANCE => "road",
                world::PAVEMENT_INSTANCE => "pavement",
                world::GRASS_INSTANCE => "grass",
                world::WATER_INSTANCE => "water",
                world::FLOATER_INSTANCE => "floaters",
                _ => "object",
            };
            let obj = sim.world.objects.iter().find(|o| o.instance == i);
            let class = match (kind, obj) {
                ("water", _) => "water",
                ("floaters", _) => "other",
                (_, Some(o)) => o.class,
                _ => "road",
            };
            json!({"class": class, "kind": kind, "simulated": true,
                   "occludes": obj.and_then(|o| o.occludes)})
        } else {
            let e = &sim.entities[i as usize];
            json!({"class": classes::name(classes::of_entity(&sim.entities, i)),
                   "object_id": e.object_id, "citygml_class": e.class,
                   "building": e.building, "source_index":
                   sim.files.iter().position(|f| f.display().to_string() == e.source)})
        };
        inst.insert(i.to_string(), v);
    }
    crate::fsutil::write_json(&out.join("gt/instances.json"), &inst)?;

    let n = sim.views.len();
    // The test split, declared in scene.json (3DGS's every 8th view by name): an input of the
    // pipeline like the images, not simulation truth.
    let split = crate::scene::Split::new(sim.views.clone(), cfg.cameras.test_every);
    let test_views: Vec<&str> = split.test.iter().map(|v| v.name.as_str()).collect();
    crate::scene::SceneMeta {
        simulated: true,
        generator: format!(
            "gs4city synth (seed {}, {} views, every {}th a test view)",
            cfg.seed, n, cfg.cameras.test_every
        ),
        test_views: Some(test_views.iter().map(|s| s.to_string()).collect()),
        imported: Default::default(),
    }
    .write(out)?;
    sim.timings.insert("total_s", t_all.elapsed().as_secs_f64());
    let summary = SynthSummary {
        simulated: true,
        note: "SIMULATED scene: Gaussians, images and ground truth are synthetic (gs4city synth); only the CityGML files are real.".into(),
        seed: cfg.seed,
        citygml: originals.iter().map(|f| f.display().to_string()).collect(),
        citymodel_copies: copied.into_iter().flatten().collect(),
        gaussians: sim.builder.len(),
        gaussians_per_class: count_by_class(&sim.builder.truth),
        textured_gaussians: sim.city.textured_gaussians,
        textures_found: sim.city.textures_found.clone(),
        textures_missing: sim.city.textures_missing.clone(),
        polygons_skipped: sim.city.polygons_skipped,
        buildings: sim.city.buildings.len(),
        openings: sim.city.openings.len(),
        objects: serde_json::to_value(&sim.world.objects).unwrap_or_default(),
        water: sim.world.water,
        floaters: sim.world.floaters,
        views: n,
        view_names: sim.views.iter().map(|v| v.name.clone()).collect(),
        test_views: test_views.iter().map(|s| s.to_string()).collect(),
        pixels_per_class: px_class,
        per_view,
        alignment_true: sim.truth_alignment.to_json(),
        alignment_given: given.to_json(),
        noise: serde_json::to_value(&cfg.noise).unwrap_or_default(),
        simulated_masks: json!({ "masks": n_masks, "mask_noise": cfg.masks, "feature_noise": cfg.features,
            "note": "SIMULATED Segment-Anything masks and CLIP-like features (docs/sam.md); no SAM or CLIP model was run" }),
        timing: sim.timings.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
        config: serde_json::to_value(cfg).unwrap_or_default(),
        city_blocks,
    };
    crate::fsutil::write_json(&out.join("summary.json"), &summary)?;
    crate::progress::done(
        "synth",
        &format!(
            "SIMULATED scene: {} Gaussians, {} views ({} test)",
            summary.gaussians,
            summary.views,
            summary.test_views.len()
        ),
        t_all.elapsed().as_secs_f64(),
    );
    Ok(summary)
}
