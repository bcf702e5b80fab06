//! `gs4city citymodel`.
use std::path::PathBuf;

use clap::Args;

use crate::alignment::Alignment;
use crate::citymodel;

#[derive(Debug, Args)]
pub struct CitymodelArgs {
    /// CityGML files, or directories searched recursively for *.gml / *.xml.
    #[arg(required = true)]
    files: Vec<PathBuf>,
    /// alignment.json: georeferenced CRS → scene frame. Default: subtract a local origin only.
    #[arg(long, conflicts_with = "align_points")]
    align: Option<PathBuf>,
    /// Estimate the alignment from a CSV of point pairs (geo_x geo_y geo_z scene_x scene_y scene_z).
    #[arg(long)]
    align_points: Option<PathBuf>,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: &CitymodelArgs) -> anyhow::Result<()> {
    // Validate.
    let found = citymodel::collect_files(&args.files)?;
    for w in &found.warnings {
        log::warn!("{w}");
    }
    let files = found.files;
    let mut estimate = None;
    let alignment = match (&args.align, &args.align_points) {
        (Some(path), _) => Some(Alignment::read(path)?),
        (None, Some(csv)) => {
            let est = super::align::estimate_from_points(csv)?;
            let a = est.alignment;
            estimate = Some(est);
            Some(a)
        }
        (None, None) => {
            log::warn!(
                "no --align or --align-points: the mesh stays in the CityGML coordinates minus a \
                 local origin, which matches a 3DGS scene only if it was reconstructed in that frame"
            );
            None
        }
    };
    // Run.
    let mut out = citymodel::run(&files, &citymodel::Options { alignment })?;
    if let Some(est) = &estimate {
        out.summary.estimated_from = Some(serde_json::json!({
            "points": args.align_points,
            "residuals": est.residuals,
            "rms": est.rms,
            "max": est.max,
        }));
    }
    citymodel::write(&out, &args.out)?;
    let s = &out.summary;
    println!("{:<14} {:>8}", "files", files.len());
    for (key, n) in [
        ("buildings", s.buildings),
        ("building_parts", s.building_parts),
        ("installations", s.installations),
        ("surfaces_total", s.surfaces_total),
        ("windows", s.windows),
        ("doors", s.doors),
        ("polygons", s.polygons),
        ("holes", s.holes),
        ("triangles", s.triangles),
        ("skipped", s.skipped.count),
        ("warnings", s.warnings.count),
    ] {
        println!("{key:<14} {n:>8}");
    }
    println!(
        "parse {:.2} s ({:.1} MB/s), triangulate {:.2} s → {}",
        s.timing.parse_s,
        s.timing.parse_mb_per_s,
        s.timing.triangulate_s,
        args.out.display()
    );
    Ok(())
}
