//! `gs4city scene import`: a scene folder from a 3DGS training output, the COLMAP folder it was
//! trained from and the CityGML model (README, "Run it on your own capture").
use std::path::PathBuf;

use clap::{Args, Subcommand};

use crate::scene::{self, ImportSpec};

#[derive(Debug, Args)]
pub struct SceneArgs {
    #[command(subcommand)]
    pub command: SceneCommand,
}

#[derive(Debug, Subcommand)]
pub enum SceneCommand {
    /// Build a scene folder by links (or copies) from a 3DGS training output, its COLMAP
    /// folder and the CityGML model; then checks it (`gs4city check`). Importing again into
    /// the same folder replaces what the earlier import made.
    #[command(
        after_help = "Example:\n  gs4city scene import --model output --citygml lod3/ --out S\n  gs4city scene import --ply splat.ply --source data --citygml lod3/ --alignment alignment.json --out S"
    )]
    Import(ImportArgs),
}

#[derive(Debug, Args)]
pub struct ImportArgs {
    /// A 3DGS training output (INRIA `train.py -m` folder: point_cloud/iteration_N/point_cloud.ply,
    /// cameras.json, cfg_args).
    #[arg(long, value_name = "DIR", required_unless_present = "ply")]
    pub model: Option<PathBuf>,
    /// The iteration of the training output (default: the highest).
    #[arg(long, value_name = "N", requires = "model")]
    pub iteration: Option<u32>,
    /// A 3DGS PLY in the INRIA layout instead of (or overriding) the training output's, e.g.
    /// nerfstudio's `ns-export gaussian-splat` or gsplat's PLY export.
    #[arg(long, value_name = "PLY")]
    pub ply: Option<PathBuf>,
    /// The COLMAP folder the 3DGS scene was trained from (sparse/0/, images/); default: the
    /// source_path recorded in the training output's cfg_args.
    #[arg(long, value_name = "DIR", required_unless_present = "model")]
    pub source: Option<PathBuf>,
    /// CityGML files, or folders holding them.
    #[arg(long, value_name = "PATH", required = true, num_args = 1..)]
    pub citygml: Vec<PathBuf>,
    /// alignment.json (CityGML CRS → scene frame), copied; without it the scene is imported
    /// for `gs4city align` to write S/citymodel/alignment.json next.
    #[arg(long, value_name = "JSON")]
    pub alignment: Option<PathBuf>,
    /// SAM automatic masks per view (masks/<stem>.json).
    #[arg(long, value_name = "DIR")]
    pub masks: Option<PathBuf>,
    /// Per-mask features (features/<stem>.npy, prompts.json).
    #[arg(long, value_name = "DIR")]
    pub features: Option<PathBuf>,
    /// Copy the files instead of linking them.
    #[arg(long)]
    pub copy: bool,
    /// Import into a folder that holds other files (its parts are replaced, the rest stays);
    /// a folder an earlier import wrote is imported into again without it.
    #[arg(long)]
    pub force: bool,
    /// The scene folder (new, empty, or an earlier import's).
    #[arg(long, value_name = "S")]
    pub out: PathBuf,
}

pub fn run(args: &SceneArgs) -> anyhow::Result<()> {
    match &args.command {
        SceneCommand::Import(a) => import(a),
    }
}

fn import(a: &ImportArgs) -> anyhow::Result<()> {
    let spec = ImportSpec {
        model: a.model.clone(),
        iteration: a.iteration,
        ply: a.ply.clone(),
        source: a.source.clone(),
        citygml: a.citygml.clone(),
        alignment: a.alignment.clone(),
        masks: a.masks.clone(),
        features: a.features.clone(),
        copy: a.copy,
        force: a.force,
    };
    let r = scene::import(&spec, &a.out)?;
    if r.reimported {
        println!(
            "scene {}: imported again (the earlier import's parts replaced)",
            a.out.display()
        );
    }
    for (part, src) in &r.parts {
        println!("{:<28} ← {}", part, src.display());
    }
    for m in r
        .missing
        .iter()
        .filter(|m| *m != "citymodel/alignment.json")
    {
        println!("not found: {m}");
    }
    // The check says what is missing or wrong, and what it is for; an alignment still to be
    // written (the next step of the guide) is no error here.
    let pending = !a.out.join("citymodel/alignment.json").is_file();
    let report = crate::inspect::check(
        &a.out,
        &crate::inspect::CheckOptions {
            local_origin: false,
            pending_alignment: pending,
            ..Default::default()
        },
    );
    super::check::print_report(&report, log::log_enabled!(log::Level::Info));
    let errors = report.of(crate::inspect::Severity::Error).count();
    if errors > 0 {
        anyhow::bail!(
            "scene {}: written, but {errors} problems must be fixed before `gs4city run` \
             (above; `gs4city check --scene {}` lists them again)",
            a.out.display(),
            a.out.display()
        );
    }
    let s = a.out.display();
    if pending {
        println!(
            "scene {s}: imported; next, its alignment: collect ground-control points (`gs4city view --scene {s}` gives a clicked point's scene coordinates), then `gs4city align --points pairs.csv --out {s}/citymodel/alignment.json`"
        );
    } else {
        println!("scene {s}: ready (gs4city run --scene {s} --out R)");
    }
    Ok(())
}
