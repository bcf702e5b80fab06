//! The command line: one subcommand per stage (`docs/design.md`). Only this module uses `anyhow`.
//! Each subcommand parses its arguments, validates them into a config, then runs.
mod align;
mod associate;
mod check;
mod citymodel;
mod demo;
mod eval;
mod fuse;
mod lift;
mod masks;
mod query;
mod raycast;
mod render;
mod run;
mod scene;
mod synth;
mod train;

use clap::{Parser, Subcommand};

/// gs4city: hierarchical CityGML LoD3 semantics for 3D Gaussian Splatting city scenes (CPU-only).
#[derive(Debug, Parser)]
#[command(name = "gs4city", version, about, long_about = None)]
pub struct Cli {
    /// More log output (-v: debug, -vv: trace).
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    verbose: u8,
    /// Only warnings and errors; no progress bars.
    #[arg(short, long, global = true, conflicts_with = "verbose")]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// CityGML files → hierarchy table, triangulated aligned mesh (mesh.ply, semantics.json, summary.json).
    Citymodel(citymodel::CitymodelArgs),
    /// Two-pass raycasting of a citymodel mesh into every COLMAP view → per-view id maps and depth.
    Raycast(raycast::RaycastArgs),
    /// Render a 3DGS PLY (CPU, INRIA forward pass) into COLMAP views → PNG, depth .npy, features;
    /// or (--cache) the per-pixel contribution lists every later stage reuses.
    Render(render::RenderArgs),
    /// Link the kept masks of all views into scene-consistent groups through the Gaussians (memory bank).
    Associate(associate::AssociateArgs),
    /// Fuse associated groups with the city-model ids (image priority, offset Δ) → fused label maps, labels.json.
    Fuse(fuse::FuseArgs),
    /// Lift per-view labels into the Gaussians (closed-form weighted vote over the cache), predict test views.
    Lift(lift::LiftArgs),
    /// Learn per-Gaussian identity codes and a classifier from per-view labels (paper §3.3), starting from the vote; semantic PLY, test-view maps.
    Train(train::TrainArgs),
    /// Filter the scene's SAM masks against the city model (paper §3.2; depth test; mask-free source).
    Masks(masks::MasksArgs),
    /// Scene folders: `scene import` builds one from a 3DGS training output, its COLMAP folder
    /// and the CityGML model.
    Scene(scene::SceneArgs),
    /// Check a scene folder before any stage runs: every problem at once, each naming its file.
    Check(check::CheckArgs),
    /// A scene folder through every stage (citymodel → raycast → render cache → lift → eval), resuming complete stages; report.html.
    Run(run::RunArgs),
    /// The demo: bundled data → simulated scene → every stage → report.html.
    Demo(demo::DemoArgs),
    /// alignment.json from geo ↔ scene point pairs (Umeyama), or --refine it against the 3DGS scene (robust 7-DoF ICP).
    Align(align::AlignArgs),
    /// Select from a finished run (class, level, attribute, id, text, pick) → selection.json, view masks, PLY exports, SQLite.
    Query(query::QueryArgs),
    /// Evaluate predicted class maps against ground truth → metrics.json, paper-shaped tables.
    Eval(eval::EvalArgs),
    /// Write a SIMULATED scene folder (Gaussians, cameras, images, exact GT) from real CityGML.
    Synth(synth::SynthArgs),
}

/// Parses the process arguments and runs the chosen subcommand.
pub fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    crate::progress::init(if cli.quiet {
        -1
    } else {
        cli.verbose.min(2) as i8
    });
    match cli.command {
        Command::Citymodel(args) => citymodel::run(&args),
        Command::Align(args) => align::run(&args),
        Command::Raycast(args) => raycast::run(&args),
        Command::Render(args) => render::run(&args),
        Command::Eval(args) => eval::run(&args),
        Command::Query(args) => query::run(&args),
        Command::Lift(args) => lift::run(&args),
        Command::Associate(args) => associate::run(&args),
        Command::Fuse(args) => fuse::run(&args),
        Command::Train(args) => train::run(&args),
        Command::Masks(args) => masks::run(&args),
        Command::Run(args) => run::run(&args),
        Command::Check(args) => check::run(&args),
        Command::Scene(args) => scene::run(&args),
        Command::Demo(args) => demo::run(&args),
        Command::Synth(args) => synth::run(&args),
    }
}
