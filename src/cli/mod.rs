//! The command line: one subcommand per stage (`docs/design.md`). Only this module uses `anyhow`.
//! Each subcommand parses its arguments, validates them into a config, then runs.
mod align;
mod associate;
mod check;
mod citymodel;
mod demo;
mod eval;
mod export;
mod features;
mod fuse;
mod lift;
mod masks;
mod query;
mod raycast;
mod render;
mod run;
mod scene;
mod segment;
mod synth;
mod tile;
mod train;
mod view;

use clap::{Parser, Subcommand};

/// gs4city: hierarchical CityGML LoD3 semantics for 3D Gaussian Splatting city scenes (CPU-only).
#[derive(Debug, Parser)]
#[command(name = "gs4city", version, about, long_about = None)]
pub struct Cli {
    /// More log output (-v: debug, -vv: trace).
    #[arg(short, long, global = true, action = clap::ArgAction::Count, help_heading = "Global options")]
    verbose: u8,
    /// Only warnings and errors; no progress bars.
    #[arg(
        short,
        long,
        global = true,
        conflicts_with = "verbose",
        help_heading = "Global options"
    )]
    quiet: bool,
    /// Die with process PID (set by the `gs4city` process that starts this one).
    #[arg(long, global = true, hide = true, value_name = "PID")]
    owned_by: Option<u32>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// CityGML files → hierarchy table, triangulated aligned mesh (mesh.ply, semantics.json, summary.json).
    #[command(
        after_help = "Example:\n  gs4city citymodel S/citymodel --align S/citymodel/alignment.json --out R/citymodel"
    )]
    Citymodel(citymodel::CitymodelArgs),
    /// Two-pass raycasting of a citymodel mesh into every COLMAP view → per-view id maps and depth.
    #[command(
        after_help = "Example:\n  gs4city raycast --citymodel R/citymodel --colmap S/sparse/0 --images S/images --out R/raycast"
    )]
    Raycast(raycast::RaycastArgs),
    /// Render a 3DGS PLY (CPU, INRIA forward pass) into COLMAP views → PNG, depth .npy, features;
    /// or (--cache) the per-pixel contribution lists every later stage reuses.
    #[command(
        after_help = "Example:\n  gs4city render --ply S/point_cloud.ply --colmap S/sparse/0 --cache --out R/render"
    )]
    Render(render::RenderArgs),
    /// Link the kept masks of all views into scene-consistent groups through the Gaussians (memory bank).
    #[command(
        after_help = "Example:\n  gs4city associate --masks R/masks --features S/features --cache R/render --ply S/point_cloud.ply --colmap S/sparse/0 --citymodel R/citymodel --out R/associate"
    )]
    Associate(associate::AssociateArgs),
    /// Fuse associated groups with the city-model ids (image priority, offset Δ) → fused label maps, labels.json.
    #[command(
        after_help = "Example:\n  gs4city fuse --associate R/associate --raycast R/raycast --citymodel R/citymodel --colmap S/sparse/0 --out R/fuse"
    )]
    Fuse(fuse::FuseArgs),
    /// Lift per-view labels into the Gaussians (closed-form weighted vote over the cache), predict test views.
    #[command(
        after_help = "Example:\n  gs4city lift --ply S/point_cloud.ply --colmap S/sparse/0 --cache R/render --citymodel R/citymodel --fuse R/fuse --out R/lift"
    )]
    Lift(lift::LiftArgs),
    /// Learn per-Gaussian identity codes and a classifier from per-view labels (paper §3.3), starting from the vote; semantic PLY, test-view maps.
    #[command(
        after_help = "Example:\n  gs4city train --ply S/point_cloud.ply --colmap S/sparse/0 --cache R/render --citymodel R/citymodel --fuse R/fuse --out R/train"
    )]
    Train(train::TrainArgs),
    /// Filter the scene's SAM masks against the city model (paper §3.2; depth test; mask-free source).
    #[command(
        after_help = "Example:\n  gs4city masks --scene S --raycast R/raycast --cache R/render --citymodel R/citymodel --out R/masks"
    )]
    Masks(masks::MasksArgs),
    /// Scene folders: `scene import` builds one from a 3DGS training output, its COLMAP folder
    /// and the CityGML model.
    #[command(
        after_help = "Example:\n  gs4city scene import --model output/street --citygml lod3/ --alignment alignment.json --out S"
    )]
    Scene(scene::SceneArgs),
    /// Check a scene folder before any stage runs: every problem at once, each naming its file.
    #[command(after_help = "Example:\n  gs4city check --scene S")]
    Check(check::CheckArgs),
    /// A scene folder through every stage (check → citymodel → raycast → render cache → masks → associate → fuse → lift → train (--mode learned) → eval (with gt/)), resuming complete stages; report.html.
    #[command(
        after_help = "Example:\n  gs4city run --scene S --out R\n  gs4city run --scene S --out R --mode learned --test-every 8"
    )]
    Run(run::RunArgs),
    /// The demo: bundled data → simulated scene → every stage → report.html.
    #[command(after_help = "Example:\n  gs4city demo --out /tmp/gs4city-demo")]
    Demo(demo::DemoArgs),
    /// alignment.json from geo ↔ scene point pairs (Umeyama), or --refine it against the 3DGS scene (robust 7-DoF ICP).
    #[command(
        after_help = "Example:\n  gs4city align --points pairs.csv --out S/citymodel/alignment.json\n  gs4city align --refine --citymodel S/citymodel --ply S/point_cloud.ply --colmap S/sparse/0 --out R/align"
    )]
    Align(align::AlignArgs),
    /// Select from a finished run (class, level, attribute, id, text, pick) → selection.json, view masks, PLY exports, SQLite.
    #[command(
        after_help = "Example:\n  gs4city query --run R --class Window --out Q\n  gs4city query --run R --where 'class=Window and measuredHeight>10' --views all --out Q"
    )]
    Query(query::QueryArgs),
    /// Evaluate predicted class maps against ground truth → metrics.json, paper-shaped tables.
    #[command(after_help = "Example:\n  gs4city eval --pred R/lift --gt S/gt --out R/eval")]
    Eval(eval::EvalArgs),
    /// SAM-family automatic masks of the scene's images on the CPU (ONNX models) → S/masks/<stem>.json.
    #[command(
        after_help = "Example:\n  gs4city segment --scene S --model models/mobile_sam --points-per-side 32"
    )]
    Segment(segment::SegmentArgs),
    /// CLIP features of the scene's SAM masks on the CPU (ONNX models) → S/features/<stem>.npy + prompts.json.
    #[command(after_help = "Example:\n  gs4city features --scene S --model models/clip-vit-b-32")]
    Features(features::FeaturesArgs),
    /// Write a SIMULATED scene folder (Gaussians, cameras, images, exact GT) from real CityGML.
    #[command(after_help = "Example:\n  gs4city synth --preset small --out /tmp/small")]
    Synth(synth::SynthArgs),
    /// Serve a finished run to the browser on 127.0.0.1: colour by RGB/class/building, queries, click → building → surface → part.
    #[command(after_help = "Example:\n  gs4city view R --port 0\n  gs4city view R --open")]
    View(view::ViewArgs),
    #[command(flatten)]
    City(tile::CityCommand),
    #[command(flatten)]
    Export(export::ExportCommand),
}

/// Parses the process arguments and runs the chosen subcommand.
pub fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    if let Some(parent) = cli.owned_by {
        crate::children::die_with_parent(parent).map_err(anyhow::Error::msg)?;
    }
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
        Command::View(args) => view::run(&args),
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
        Command::Segment(args) => segment::run(&args),
        Command::Features(args) => features::run(&args),
        Command::City(cmd) => tile::run(&cmd),
        Command::Export(cmd) => export::run(&cmd),
    }
}

#[cfg(test)]
mod tests {
    use clap::{CommandFactory, Parser};

    /// Every subcommand's `--help` ends with an example, and every example parses.
    #[test]
    fn every_command_has_an_example_that_parses() {
        let cmd = super::Cli::command();
        let mut seen = 0;
        let mut stack: Vec<&clap::Command> = cmd.get_subcommands().collect();
        while let Some(sub) = stack.pop() {
            if sub.get_subcommands().next().is_some() {
                stack.extend(sub.get_subcommands());
                continue;
            }
            let help = sub
                .get_after_help()
                .unwrap_or_else(|| panic!("`{}` has no example", sub.get_name()))
                .to_string();
            for line in help
                .lines()
                .filter(|l| l.trim_start().starts_with("gs4city "))
            {
                let mut words = Vec::new();
                let mut quoted: Option<String> = None;
                for w in line.split_whitespace() {
                    match &mut quoted {
                        Some(q) => {
                            q.push(' ');
                            q.push_str(w.trim_end_matches('\''));
                            if w.ends_with('\'') {
                                words.push(quoted.take().unwrap());
                            }
                        }
                        None if w.starts_with('\'') && !(w.len() > 1 && w.ends_with('\'')) => {
                            quoted = Some(w.trim_start_matches('\'').to_string())
                        }
                        None if w == "\\" => {}
                        None => words.push(w.trim_matches('\'').to_string()),
                    }
                }
                if let Err(e) = super::Cli::try_parse_from(&words) {
                    panic!("example `{line}` does not parse: {e}");
                }
                seen += 1;
            }
        }
        assert!(seen >= 17, "{seen} examples");
    }
}
