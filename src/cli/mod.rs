//! The command line: the user commands (demo, run, query, view, export, check, scene, align,
//! tile, run-plan, merge, segment, features) and one subcommand per stage (`docs/design.md`),
//! listed after them. Only this module uses `anyhow`. Each subcommand parses its arguments,
//! validates them into a config, then runs. The option groups several commands share, and the
//! `--config` file of the stages' tuning and ablation switches, are [`groups`] (the place a new
//! option of a stage goes).
mod align;
mod associate;
mod check;
mod citymodel;
mod demo;
mod eval;
mod export;
mod features;
mod fuse;
pub mod groups;
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

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

pub use query::{NO_MATCH_STATUS, NoMatch};

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

/// The commands in the order a user meets them; the pipeline's stages and the tools behind
/// them are hidden from the main list and listed after it under their own heading
/// ([`command`]).
#[derive(Debug, Subcommand)]
enum Command {
    /// The demo: bundled data → simulated scene → every stage → report.html.
    #[command(after_help = "Example:\n  gs4city demo --out /tmp/gs4city-demo")]
    Demo(demo::DemoArgs),
    /// A scene folder through every stage (check → citymodel → raycast → render cache → masks
    /// → associate → fuse → lift → train (--mode learned) → eval (with gt/)), resuming complete
    /// stages; report.html.
    #[command(
        after_help = "Example:\n  gs4city run --scene S --out R\n  gs4city run --scene S --out R --mode learned --config configs/ablation/no-centre-gate.toml"
    )]
    Run(run::RunArgs),
    /// Select from a finished run (class, level, attribute, id, text, pick) → selection.json,
    /// view masks, PLY exports, SQLite.
    #[command(
        after_help = "Example:\n  gs4city query --run R --class Window --out Q\n  gs4city query --run R --where 'class=Window and measuredHeight>10' --views all --out Q\n\nExit status: 0 done, 1 error, 2 usage error, 3 a text term matched nothing (outputs written)."
    )]
    Query(query::QueryArgs),
    /// The browser viewer on 127.0.0.1: a run (colour by RGB/class/building, queries, click →
    /// building → surface → part and the point's coordinates) or a scene before any run (a
    /// click gives a point's scene coordinates).
    #[command(
        after_help = "Example:\n  gs4city view --run R --open\n  gs4city view --scene S --port 0"
    )]
    View(view::ViewArgs),
    /// Export a finished run (or a --where selection of it) as a georeferenced 3D Tiles 1.1
    /// tileset: glTF tiles with KHR_gaussian_splatting, per-splat building / surface / part
    /// feature ids (EXT_mesh_features) and property tables (EXT_structural_metadata).
    #[command(
        after_help = "Example:\n  gs4city export --run R --out T\n  gs4city export --run R --where 'class=Building' --color-by class --crs EPSG:25832 --out T"
    )]
    Export(export::ExportArgs),
    /// Check a scene folder before any stage runs: every problem at once, each naming its file.
    #[command(after_help = "Example:\n  gs4city check --scene S")]
    Check(check::CheckArgs),
    /// Scene folders: `scene import` builds one from a 3DGS training output, its COLMAP folder
    /// and the CityGML model.
    #[command(
        after_help = "Example:\n  gs4city scene import --model output --citygml lod3/ --out S"
    )]
    Scene(scene::SceneArgs),
    /// alignment.json from geo ↔ scene point pairs (Umeyama), or --refine it against the 3DGS
    /// scene (robust 7-DoF ICP).
    #[command(
        after_help = "Example:\n  gs4city align --points pairs.csv --out S/citymodel/alignment.json\n  gs4city align --refine --citymodel S/citymodel --ply S/point_cloud.ply --colmap S/sparse/0 --out R/align/alignment.json"
    )]
    Align(align::AlignArgs),
    #[command(flatten)]
    City(tile::CityCommand),
    /// SAM-family automatic masks of the scene's images on the CPU (ONNX models) →
    /// S/masks/<stem>.json.
    #[command(
        after_help = "Example:\n  gs4city segment --scene S --model models/mobile_sam --points-per-side 32"
    )]
    Segment(segment::SegmentArgs),
    /// CLIP features of the scene's SAM masks on the CPU (ONNX models) → S/features/<stem>.npy
    /// + prompts.json.
    #[command(after_help = "Example:\n  gs4city features --scene S --model models/clip-vit-b-32")]
    Features(features::FeaturesArgs),
    /// CityGML files → hierarchy table, triangulated aligned mesh (mesh.ply, semantics.json,
    /// summary.json).
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city citymodel S/citymodel --align S/citymodel/alignment.json --out R/citymodel"
    )]
    Citymodel(citymodel::CitymodelArgs),
    /// Two-pass raycasting of a citymodel mesh into every COLMAP view → per-view id maps and
    /// depth.
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city raycast --citymodel R/citymodel --colmap S/sparse/0 --overlays --images S/images --out R/raycast"
    )]
    Raycast(raycast::RaycastArgs),
    /// Render a 3DGS PLY (CPU, INRIA forward pass) into COLMAP views → PNG, depth .npy,
    /// features; or (--cache) the per-pixel contribution lists every later stage reuses.
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city render --ply S/point_cloud.ply --colmap S/sparse/0 --cache --out R/render"
    )]
    Render(render::RenderArgs),
    /// Filter the scene's SAM masks against the city model (paper §3.2; depth test; mask-free
    /// source).
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city masks --scene S --raycast R/raycast --cache R/render --citymodel R/citymodel --out R/masks"
    )]
    Masks(masks::MasksArgs),
    /// Link the kept masks of all views into scene-consistent groups through the Gaussians
    /// (memory bank).
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city associate --masks R/masks --features S/features --cache R/render --ply S/point_cloud.ply --colmap S/sparse/0 --citymodel R/citymodel --split S --out R/associate"
    )]
    Associate(associate::AssociateArgs),
    /// Fuse associated groups with the city-model ids (image priority, offset Δ) → fused label
    /// maps, labels.json.
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city fuse --associate R/associate --raycast R/raycast --citymodel R/citymodel --colmap S/sparse/0 --no-snap --split S --out R/fuse"
    )]
    Fuse(fuse::FuseArgs),
    /// Lift per-view labels into the Gaussians (closed-form weighted vote over the cache),
    /// predict test views.
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city lift --ply S/point_cloud.ply --colmap S/sparse/0 --cache R/render --citymodel R/citymodel --fuse R/fuse --split S --out R/lift"
    )]
    Lift(lift::LiftArgs),
    /// Learn per-Gaussian identity codes and a classifier from per-view labels (paper §3.3),
    /// starting from the vote; semantic PLY, test-view maps.
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city train --ply S/point_cloud.ply --colmap S/sparse/0 --cache R/render --citymodel R/citymodel --fuse R/fuse --split S --out R/train"
    )]
    Train(train::TrainArgs),
    /// Evaluate predicted class maps against ground truth → metrics.json, paper-shaped tables;
    /// or a run by queries (--by-query).
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city eval --pred R/lift --gt S/gt --out R/eval\n  gs4city eval --by-query --run R --out E"
    )]
    Eval(eval::EvalArgs),
    /// Write a SIMULATED scene folder (Gaussians, cameras, images, exact GT) from real CityGML.
    #[command(
        hide = true,
        after_help = "Example:\n  gs4city synth --preset small --out /tmp/small"
    )]
    Synth(synth::SynthArgs),
}

/// The heading of the hidden commands' list in `gs4city --help`.
pub const STAGES_HEADING: &str = "Pipeline stages and tools";

/// The command line: [`Cli`] with the hidden commands (the stages `run` chains, `eval`,
/// `synth`) listed after the user commands under [`STAGES_HEADING`], each with its first help
/// line (clap 4 gives subcommands one heading; this is the second).
pub fn command() -> clap::Command {
    let cmd = Cli::command();
    let hidden: Vec<(String, String)> = cmd
        .get_subcommands()
        .filter(|c| c.is_hide_set())
        .map(|c| {
            let about = c.get_about().map(|a| a.to_string()).unwrap_or_default();
            (c.get_name().to_string(), about)
        })
        .collect();
    let width = hidden.iter().map(|h| h.0.len()).max().unwrap_or(0);
    let mut text = format!(
        "{STAGES_HEADING} (the steps `run` chains, one at a time; `gs4city help <command>`):\n"
    );
    for (name, about) in &hidden {
        let first = about.split(". ").next().unwrap_or("").trim_end_matches('.');
        text.push_str(&format!("  {name:<width$}  {first}\n"));
    }
    cmd.after_help(text)
}

/// The ids of the arguments given on the command line in `m` and its chosen subcommands.
fn given_ids(m: &clap::ArgMatches) -> std::collections::BTreeSet<String> {
    let mut out = std::collections::BTreeSet::new();
    let mut cur = Some(m);
    while let Some(m) = cur {
        for id in m.ids() {
            if m.value_source(id.as_str()) == Some(clap::parser::ValueSource::CommandLine) {
                out.insert(id.as_str().to_string());
            }
        }
        cur = m.subcommand().map(|(_, sub)| sub);
    }
    out
}

/// The exit status of an error: [`NO_MATCH_STATUS`] for a text query that matched nothing,
/// [`crate::lock::EXIT_BUSY`] for a folder another process holds, 1 otherwise.
pub fn exit_status(err: &anyhow::Error) -> u8 {
    if err.downcast_ref::<NoMatch>().is_some() {
        NO_MATCH_STATUS
    } else if err.chain().any(|e| {
        // A folder locked by another process: a temporary failure (run-plan retries it).
        e.downcast_ref::<crate::lock::LockError>()
            .is_some_and(|l| l.is_busy())
    }) {
        crate::lock::EXIT_BUSY
    } else {
        1
    }
}

/// Parses the process arguments and runs the chosen subcommand.
pub fn main() -> anyhow::Result<()> {
    let m = command().get_matches();
    groups::set_given(given_ids(&m));
    let cli = Cli::from_arg_matches(&m).unwrap_or_else(|e| e.exit());
    if let Some(parent) = cli.owned_by {
        crate::children::die_with_parent(parent).map_err(anyhow::Error::msg)?;
    }
    crate::progress::init(if cli.quiet {
        -1
    } else {
        cli.verbose.min(2) as i8
    });
    match cli.command {
        Command::Demo(args) => demo::run(&args),
        Command::Run(args) => run::run(&args),
        Command::Query(args) => query::run(&args),
        Command::View(args) => view::run(&args),
        Command::Export(args) => export::run(&args),
        Command::Check(args) => check::run(&args),
        Command::Scene(args) => scene::run(&args),
        Command::Align(args) => align::run(&args),
        Command::City(cmd) => tile::run(&cmd),
        Command::Segment(args) => segment::run(&args),
        Command::Features(args) => features::run(&args),
        Command::Citymodel(args) => citymodel::run(&args),
        Command::Raycast(args) => raycast::run(&args),
        Command::Render(args) => render::run(&args),
        Command::Masks(args) => masks::run(&args),
        Command::Associate(args) => associate::run(&args),
        Command::Fuse(args) => fuse::run(&args),
        Command::Lift(args) => lift::run(&args),
        Command::Train(args) => train::run(&args),
        Command::Eval(args) => eval::run(&args),
        Command::Synth(args) => synth::run(&args),
    }
}

#[cfg(test)]
mod tests {
    use clap::{CommandFactory, Parser};

    /// `gs4city --help` lists the user commands first, in the order a user meets them, then
    /// the stages under their own heading; `gs4city run --help` shows at most 15 options, each
    /// under one of its four headings (or the global options).
    #[test]
    fn help_lists_user_commands_first_and_run_has_few_grouped_options() {
        let cmd = super::command();
        let visible: Vec<&str> = cmd
            .get_subcommands()
            .filter(|c| !c.is_hide_set())
            .map(|c| c.get_name())
            .collect();
        let user = [
            "demo", "run", "query", "view", "export", "check", "scene", "align", "tile",
            "run-plan", "merge", "segment", "features",
        ];
        assert_eq!(visible, user);
        let stages = [
            "citymodel",
            "raycast",
            "render",
            "masks",
            "associate",
            "fuse",
            "lift",
            "train",
            "eval",
            "synth",
        ];
        let hidden: Vec<&str> = cmd
            .get_subcommands()
            .filter(|c| c.is_hide_set())
            .map(|c| c.get_name())
            .collect();
        assert_eq!(hidden, stages);
        // The rendered help: every user command, then the heading, then every stage, in order.
        let help = super::command().render_long_help().to_string();
        let at = |name: &str, from: usize| {
            help[from..]
                .find(&format!("\n  {name} "))
                .map(|p| p + from)
                .unwrap_or_else(|| panic!("`{name}` not listed after byte {from}:\n{help}"))
        };
        let mut pos = 0;
        for name in user {
            pos = at(name, pos);
        }
        let heading = help
            .find(super::STAGES_HEADING)
            .expect("the stages' heading");
        assert!(heading > pos, "{help}");
        let mut pos = heading;
        for name in stages {
            pos = at(name, pos);
        }
        // `run --help`: ≤ 15 options, each under a heading of its own kind.
        let run = super::command().find_subcommand("run").unwrap().clone();
        let mut run = run;
        run.build();
        let shown: Vec<(String, Option<String>)> = run
            .get_arguments()
            .filter(|a| !a.is_hide_set() && !a.is_positional())
            .map(|a| {
                (
                    a.get_id().to_string(),
                    a.get_help_heading().map(str::to_string),
                )
            })
            .collect();
        assert!(shown.len() <= 15, "{} options: {shown:?}", shown.len());
        let headings = [
            "Inputs",
            "Outputs",
            "Supervision",
            "Performance",
            "Global options",
        ];
        for (id, h) in &shown {
            assert!(
                id == "help" || h.as_deref().is_some_and(|h| headings.contains(&h)),
                "--{id} under {h:?}"
            );
        }
        for h in &headings[..4] {
            assert!(shown.iter().any(|(_, x)| x.as_deref() == Some(*h)), "{h}");
        }
        // The run's help text shows them in that order, --out among the first.
        let text = run.render_help().to_string();
        let order: Vec<usize> = headings[..4]
            .iter()
            .map(|h| {
                text.find(&format!("{h}:"))
                    .unwrap_or_else(|| panic!("{h}:\n{text}"))
            })
            .collect();
        assert!(order.windows(2).all(|w| w[0] < w[1]), "{text}");
    }

    /// The documents' `gs4city run` commands parse as written (an ablation that still named a
    /// switch `run` no longer has would not), and every `configs/….toml` they name exists and
    /// parses: BENCHMARKS.md's ablation rows reproduce through `--config`.
    #[test]
    fn documented_run_commands_parse_and_name_existing_configs() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let mut files = vec![root.join("BENCHMARKS.md"), root.join("README.md")];
        for e in std::fs::read_dir(root.join("docs")).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "md") {
                files.push(p);
            }
        }
        let (mut commands, mut configs) = (0, 0);
        for f in &files {
            let text = std::fs::read_to_string(f).unwrap();
            let mut in_code = false;
            for line in text.lines() {
                if line.trim_start().starts_with("```") {
                    in_code = !in_code;
                    continue;
                }
                for (i, _) in line.match_indices("configs/") {
                    let rest = &line[i..];
                    let end = rest.find(".toml").map(|e| e + 5);
                    if let Some(end) = end {
                        let path = root.join(&rest[..end]);
                        super::groups::Config::read(&path)
                            .unwrap_or_else(|e| panic!("{}: `{}`: {e}", f.display(), &rest[..end]));
                        configs += 1;
                    }
                }
                let cmd = line.split('#').next().unwrap().trim();
                // Synopses (`[--x]`, `a|b`) are not commands.
                if !in_code
                    || !cmd.starts_with("gs4city run ")
                    || cmd.contains(['[', '|', '…', '&'])
                {
                    continue;
                }
                let words: Vec<&str> = cmd.split_whitespace().collect();
                if let Err(e) = super::Cli::try_parse_from(&words) {
                    panic!("{}: `{cmd}` does not parse: {e}", f.display());
                }
                commands += 1;
            }
        }
        assert!(
            commands >= 5 && configs >= 5,
            "{commands} commands, {configs} configs"
        );
    }

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
