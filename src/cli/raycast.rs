//! The `raycast` subcommand: arguments, validation and the call into
//! [`crate::raycast::run`].
use std::path::PathBuf;

use anyhow::{Context, bail};

use crate::alignment::Alignment;
use crate::raycast::RaycastOptions;
use crate::{colmap, mesh::TriMesh, raycast};

/// Two-pass raycasting of the city mesh into every COLMAP view.
#[derive(Debug, Clone, clap::Args)]
pub struct RaycastArgs {
    /// Output folder of the `citymodel` stage (reads mesh.ply and alignment.json).
    #[arg(long, value_name = "DIR")]
    pub citymodel: PathBuf,
    /// COLMAP sparse model folder (cameras, images: .bin or .txt).
    #[arg(long, value_name = "SPARSE_DIR")]
    pub colmap: PathBuf,
    #[command(flatten)]
    pub config: super::groups::ConfigArg,
    #[command(flatten, next_help_heading = "Raycasting (config [raycast])")]
    pub tuning: super::groups::RaycastTuning,
    /// Also write `<stem>.overlay.png` per view: the city ids in colour over the image (for a
    /// person to look at; no stage reads them).
    #[arg(long)]
    pub overlays: bool,
    /// Images for the overlays (default: <colmap dir>/../../images if it exists).
    #[arg(long, value_name = "DIR", requires = "overlays")]
    pub images: Option<PathBuf>,
    /// Output folder.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

/// Parses the inputs, validates them, runs the stage, writes `summary.json` and prints a table.
pub fn run(args: &RaycastArgs) -> anyhow::Result<()> {
    let t = super::groups::merged(&args.config.load()?.raycast, &args.tuning);
    crate::check::non_negative("tau", t.tau)?;
    let mesh_path = args.citymodel.join("mesh.ply");
    let mesh = TriMesh::read_ply(&mesh_path)
        .with_context(|| format!("reading the city mesh {}", mesh_path.display()))?;
    let entities = crate::semantics::read(&args.citymodel.join("semantics.json"))?;
    crate::semantics::check_mesh_labels(&mesh_path, &mesh, &entities)?;
    let scale = Alignment::read(&args.citymodel.join("alignment.json"))?.scale;
    let views = colmap::read_model(&args.colmap)
        .with_context(|| format!("reading COLMAP model {}", args.colmap.display()))?;
    if views.is_empty() {
        bail!("{}: the COLMAP model has no images", args.colmap.display());
    }
    let images = match &args.images {
        Some(d) if !d.is_dir() => bail!("--images {}: not a directory", d.display()),
        Some(d) => Some(d.clone()),
        None => args
            .colmap
            .join("../../images")
            .canonicalize()
            .ok()
            .filter(|d| d.is_dir()),
    };
    let opts = RaycastOptions {
        tau: t.tau * scale,
        single_pass: t.single_pass,
    };
    let overlays = match args.overlays {
        true => raycast::Overlays::On(images.as_deref()),
        false => raycast::Overlays::Off,
    };
    let summary = raycast::run(&mesh, &views, &opts, overlays, &args.out).context("raycasting")?;
    println!(
        "{} views, {} rays, {:.1} Mrays/s, scene build {:.3} s ({} faces, {} part faces), τ = {} m = {} scene units{}",
        summary.views,
        summary.rays,
        summary.rays_per_second / 1e6,
        summary.scene_build_seconds,
        summary.faces,
        summary.part_faces,
        t.tau,
        opts.tau,
        if opts.single_pass {
            ", single pass"
        } else {
            ""
        }
    );
    println!(
        "{:<32} {:>11} {:>10} {:>10} {:>10} {:>8}",
        "view", "size", "hit px", "part px", "recov px", "recov"
    );
    for v in &summary.per_view {
        println!(
            "{:<32} {:>11} {:>10} {:>10} {:>10} {:>8}",
            v.name,
            format!("{}x{}", v.width, v.height),
            v.hit_pixels,
            v.part_pixels,
            v.recovered_pixels,
            v.recovered_parts
        );
    }
    Ok(())
}
