//! `gs4city align`: an alignment from geo ↔ scene point pairs (Umeyama), from the photos' EXIF
//! GPS (`--exif`, robust), or with `--refine` the refinement of a city model's alignment
//! against the 3DGS scene (robust 7-DoF ICP).
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use glam::DVec3;

use crate::alignment::{self as align, Alignment};
use crate::citymodel;
use crate::mesh::TriMesh;
use crate::refine::{self, CityFrame, RefineOptions, RefineSources};
use crate::semantics;
use crate::{colmap, fsutil};

#[derive(Debug, Args)]
pub struct AlignArgs {
    /// CSV of point pairs: geo_x geo_y geo_z scene_x scene_y scene_z per line (≥ 3 pairs).
    #[arg(
        long,
        required_unless_present_any = ["refine", "exif"],
        conflicts_with_all = ["refine", "exif"]
    )]
    points: Option<PathBuf>,
    /// Fit the alignment to the photos' EXIF GPS: the scene folder (images/ with GPS tags,
    /// sparse/0); the CRS is its city model's (citymodel/), else the photos' UTM zone
    /// (docs/align-exif.md).
    #[arg(long, value_name = "S", conflicts_with = "refine")]
    exif: Option<PathBuf>,
    /// Refine the city model's alignment against the 3DGS scene (robust 7-DoF point-to-plane
    /// ICP of Gaussian centres to the mesh); writes alignment.json and summary.json beside it.
    #[arg(long, requires_all = ["citymodel", "ply"])]
    refine: bool,
    /// With --refine: the scene's citymodel/ folder (CityGML files + alignment.json), or the
    /// output folder of the `citymodel` stage (mesh.ply, semantics.json, alignment.json).
    #[arg(long, value_name = "DIR", requires = "refine")]
    citymodel: Option<PathBuf>,
    /// With --refine: the pre-trained 3DGS scene (INRIA PLY).
    #[arg(long, value_name = "PLY", requires = "refine")]
    ply: Option<PathBuf>,
    /// With --refine: a COLMAP model (e.g. SCENE/sparse/0); Gaussians farther than
    /// `max_camera_distance_m` from every camera are ignored.
    #[arg(long, value_name = "SPARSE_DIR", requires = "refine")]
    colmap: Option<PathBuf>,
    /// With --refine: start from this alignment.json instead of the citymodel folder's.
    #[arg(long, value_name = "JSON", requires = "refine")]
    initial: Option<PathBuf>,
    /// With --refine: a JSON object of refine options (keys of summary.json's `options`).
    #[arg(long, value_name = "JSON", requires = "refine")]
    options: Option<PathBuf>,
    /// With --refine: rigid (6 DoF), keep the initial scale.
    #[arg(long, requires = "refine")]
    rigid: bool,
    /// Where to write alignment.json.
    #[arg(long)]
    out: PathBuf,
}

fn print_estimate(est: &align::Estimate) {
    println!(
        "alignment from {} point pairs: scale {:.6}, residuals rms {:.4}, max {:.4} (scene units)",
        est.residuals.len(),
        est.alignment.scale,
        est.rms,
        est.max
    );
    for w in &est.warnings {
        log::warn!("{w}");
    }
}

/// Point-pair estimation (also used by `gs4city citymodel --align-points`).
pub(super) fn estimate_from_points(csv: &Path) -> anyhow::Result<align::Estimate> {
    let est = align::estimate(csv, &align::read_pairs(csv)?)?;
    print_estimate(&est);
    Ok(est)
}

pub fn run(args: &AlignArgs) -> anyhow::Result<()> {
    if args.refine {
        return run_refine(args);
    }
    if let Some(scene) = &args.exif {
        return run_exif(scene, &args.out);
    }
    let Some(points) = &args.points else {
        bail!("give --points CSV (point-pair estimation) or --refine");
    };
    let est = estimate_from_points(points)?;
    for (i, r) in est.residuals.iter().enumerate() {
        println!("  pair {:>3}: {:.4}", i + 1, r);
    }
    fsutil::write_json(&args.out, &est.alignment.to_json())?;
    println!("wrote {}", args.out.display());
    Ok(())
}

/// The CRS named by the first city model file of `S/citymodel/` that names one.
fn scene_crs(scene: &Path) -> anyhow::Result<Option<(String, String)>> {
    let dir = scene.join("citymodel");
    if !dir.is_dir() {
        return Ok(None);
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .with_context(|| format!("cannot list {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| crate::cityjson::is_model_file(p))
        .collect();
    files.sort();
    for f in files {
        let m = crate::cityjson::read_any(&f)?;
        if let Some(srs) = m.srs_name {
            return Ok(Some((srs, format!("the city model {}", f.display()))));
        }
    }
    Ok(None)
}

fn run_exif(scene: &Path, out: &Path) -> anyhow::Result<()> {
    let sparse = [scene.join("sparse/0"), scene.join("sparse")]
        .into_iter()
        .find(|d| colmap::read_cameras(d).is_ok())
        .ok_or_else(|| {
            anyhow::anyhow!("{}: no COLMAP model in sparse/0 or sparse", scene.display())
        })?;
    let views = colmap::read_model(&sparse)?;
    let crs = scene_crs(scene)?;
    let f = crate::geotag::fit(
        &scene.join("images"),
        &views,
        crs.as_ref().map(|(c, s)| (c.as_str(), s.as_str())),
    )?;
    let fit = &f.fit;
    println!(
        "alignment from the GPS of {} photos in {}: {}; {} registered photos without GPS",
        f.cameras.len(),
        f.crs,
        f.crs_source,
        f.without_gps.len()
    );
    match fit.vertical {
        align::Vertical::Level(_) => println!(
            "vertical: the cameras' up (level photos); GPS altitudes set the height offset only"
        ),
        align::Vertical::Free => println!(
            "vertical: from the GPS altitudes (the cameras do not agree on an up): a phone's altitude error tilts the fit"
        ),
    }
    println!("camera residuals (GPS − fitted camera position, metres):");
    println!(
        "  {:<24} {:>10} {:>10} {:>10}",
        "image", "horizontal", "vertical", "3D"
    );
    for (c, (r, inlier)) in f.cameras.iter().zip(fit.residuals.iter().zip(&fit.inliers)) {
        println!(
            "  {:<24} {:>10.2} {:>+10.2} {:>10.2}{}",
            c.name,
            r.truncate().length(),
            -r.z,
            r.length(),
            if *inlier { "" } else { "  outlier" }
        );
    }
    let worst = fit
        .residuals
        .iter()
        .zip(&fit.inliers)
        .enumerate()
        .filter(|(_, (_, i))| **i)
        .max_by(|a, b| {
            a.1.0
                .truncate()
                .length()
                .total_cmp(&b.1.0.truncate().length())
        })
        .map(|(i, (r, _))| (f.cameras[i].name.clone(), r.truncate().length()));
    println!(
        "RMS over {} inliers: horizontal {:.2} m, vertical {:.2} m, 3D {:.2} m; inlier bound {:.2} m; scale {:.6} scene units per metre",
        fit.inliers.iter().filter(|b| **b).count(),
        fit.rms[0],
        fit.rms[1],
        fit.rms[2],
        fit.threshold,
        fit.alignment.scale
    );
    if let Some((name, r)) = worst {
        println!("worst inlier: {name} ({r:.2} m horizontal)");
    }
    for w in &fit.warnings {
        log::warn!("{w}");
    }
    fsutil::write_json(out, &fit.alignment.to_json())?;
    println!("wrote {}", out.display());
    Ok(())
}

/// The city model in the scene frame of its alignment: from CityGML (the stage runs in
/// memory) or from a `citymodel` stage output folder.
struct City {
    mesh: TriMesh,
    entities: Vec<semantics::Entity>,
    alignment: Alignment,
    source: &'static str,
}

fn load_city(dir: &Path, initial: Option<&Path>) -> anyhow::Result<City> {
    if !dir.is_dir() {
        bail!("--citymodel {}: not a directory", dir.display());
    }
    let own = dir.join("alignment.json");
    let align_path = initial.unwrap_or(&own);
    if !align_path.is_file() {
        bail!(
            "{}: no alignment.json to start from (the refinement needs an initial alignment)",
            align_path.display()
        );
    }
    let alignment = Alignment::read(align_path)?;
    let has_gml = std::fs::read_dir(dir)
        .with_context(|| format!("cannot list {}", dir.display()))?
        .filter_map(|e| e.ok())
        .any(|e| crate::cityjson::is_model_file(&e.path()));
    if has_gml {
        let found = citymodel::collect_files(&[dir.to_path_buf()])?;
        for w in &found.warnings {
            log::warn!("{w}");
        }
        let files = found.files;
        let out = citymodel::run(
            &files,
            &citymodel::Options {
                alignment: Some(alignment),
            },
        )?;
        return Ok(City {
            mesh: out.mesh,
            entities: out.entities,
            alignment,
            source: "CityGML",
        });
    }
    let (mesh_path, sem_path) = (dir.join("mesh.ply"), dir.join("semantics.json"));
    if !mesh_path.is_file() || !sem_path.is_file() {
        bail!(
            "{}: neither CityGML files nor a citymodel stage output (mesh.ply + semantics.json)",
            dir.display()
        );
    }
    if initial.is_some() {
        bail!(
            "--initial needs CityGML in --citymodel: {} holds a mesh already aligned by its own alignment.json",
            dir.display()
        );
    }
    Ok(City {
        mesh: TriMesh::read_ply(&mesh_path)?,
        entities: semantics::read(&sem_path)?,
        alignment,
        source: "mesh.ply",
    })
}

fn run_refine(args: &AlignArgs) -> anyhow::Result<()> {
    // Parse.
    let (Some(cm_dir), Some(ply)) = (&args.citymodel, &args.ply) else {
        bail!("--refine needs --citymodel DIR and --ply FILE");
    };
    let mut opts = match &args.options {
        None => RefineOptions::default(),
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            serde_json::from_str(&text)
                .with_context(|| format!("{}: not refine options", p.display()))?
        }
    };
    if args.rigid {
        opts.estimate_scale = false;
    }
    // Validate.
    opts.validate()?;
    let out_dir = match args.out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let summary_path = out_dir.join("summary.json");
    let input_alignment = args
        .initial
        .clone()
        .unwrap_or_else(|| cm_dir.join("alignment.json"));
    if same_file(&args.out, &input_alignment) {
        bail!(
            "--out {} is the input alignment; write the refined one elsewhere",
            args.out.display()
        );
    }
    if summary_path.is_file() && !written_by_refine(&summary_path) {
        bail!(
            "{}: exists and was not written by `align --refine`; refusing to overwrite it (choose another --out folder)",
            summary_path.display()
        );
    }
    if !ply.is_file() {
        bail!("--ply {}: no such file", ply.display());
    }
    let t0 = Instant::now();
    let city = load_city(cm_dir, args.initial.as_deref())?;
    let load_s = t0.elapsed().as_secs_f64();
    let centres: Option<Vec<DVec3>> = match &args.colmap {
        None => None,
        Some(dir) => {
            let views = colmap::read_model(dir)
                .with_context(|| format!("reading COLMAP model {}", dir.display()))?;
            if views.is_empty() {
                bail!("{}: the COLMAP model has no images", dir.display());
            }
            Some(views.iter().map(|v| v.camera.pose.center()).collect())
        }
    };
    // Run.
    let summary = refine::run(
        &CityFrame {
            mesh: &city.mesh,
            entities: &city.entities,
            initial: &city.alignment,
            load_s,
        },
        RefineSources {
            citymodel: cm_dir.clone(),
            city_source: city.source.into(),
            initial_alignment: Some(input_alignment.clone()),
            ply: ply.clone(),
            ply_report: None,
            colmap: args.colmap.clone(),
            cameras: None,
        },
        centres.as_deref(),
        &opts,
        &args.out,
        &out_dir,
    )
    .with_context(|| {
        format!(
            "refining {} against {}",
            input_alignment.display(),
            ply.display()
        )
    })?;
    let out = &summary.refine;
    let s = &out.selection;
    println!(
        "Gaussians: {} → opaque {} → flat {} → in range {} → sampled {}; target triangles {} ({} hidden/degenerate left out)",
        s.gaussians,
        s.opaque,
        s.opaque_flat,
        s.in_camera_range,
        s.sampled,
        s.target_triangles,
        s.excluded_triangles
    );
    println!(
        "ICP: {} iterations, converged; eigenvalue ratio {:.2e}",
        out.iterations, out.conditioning.ratio
    );
    let c = &out.correction;
    println!(
        "correction: vertices moved rms {:.4} m (max {:.4}), rotation {:.4}°, scale {:+.4} %",
        c.rms_m, c.max_m, c.rotation_deg, c.scale_pct
    );
    for (name, r) in [("before", &out.before), ("after", &out.after)] {
        println!(
            "{name:<6} matched {:>7} of {:>7}  median {:.4} m  rms {:.4} m  within 2/5/10 cm {:>5.1}/{:>5.1}/{:>5.1} %",
            r.matched,
            r.points,
            r.median_m,
            r.rms_m,
            100.0 * r.within_2cm,
            100.0 * r.within_5cm,
            100.0 * r.within_10cm
        );
    }
    for w in &out.warnings {
        println!("warning: {w}");
    }
    println!(
        "time: city model {:.2} s, PLY {:.2} s, select {:.2} s, BVH {:.2} s, ICP {:.2} s, stats {:.2} s; total {:.2} s",
        out.timings.load_citymodel_s,
        out.timings.read_ply_s,
        out.timings.select_s,
        out.timings.bvh_s,
        out.timings.icp_s,
        out.timings.stats_s,
        t0.elapsed().as_secs_f64()
    );
    println!(
        "wrote {} and {}",
        args.out.display(),
        summary_path.display()
    );
    Ok(())
}

fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

fn written_by_refine(path: &Path) -> bool {
    std::fs::read(path)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .is_some_and(|v| v["stage"] == "align_refine")
}
