//! `gs4city run`: a scene folder through every stage into a run folder.
use std::path::PathBuf;

use clap::Args;

use super::groups::{Config, ConfigArg};
use crate::run::{self, Mode, Quality, RunOptions, RunSummary, Supervision, ViewSelection};

/// `gs4city run`: the user's options only, under four headings; every tuning and ablation
/// switch of the stages is in `--config` (docs/config.md, [`super::groups`]).
#[derive(Debug, Args)]
pub struct RunArgs {
    /// Scene folder (`docs/design.md`): images/, sparse/0/, point_cloud.ply, citymodel/*.gml +
    /// alignment.json, optional masks/, features/, scene.json, gt/.
    #[arg(long, value_name = "S", help_heading = "Inputs")]
    pub scene: PathBuf,
    #[command(flatten, next_help_heading = "Inputs")]
    pub config: ConfigArg,
    /// A model folder: with SAM-family files (docs/segment.md), when the scene has no
    /// masks/<stem>.json, `gs4city segment` writes them first (config [segment]); with CLIP
    /// files (docs/features.md), `gs4city features` then writes the masks' features.
    #[arg(long, value_name = "DIR", help_heading = "Inputs")]
    pub model_dir: Option<PathBuf>,
    /// Run a scene without citymodel/alignment.json: the CityGML coordinates minus a local
    /// origin are the scene frame (a capture reconstructed in the city model's frame).
    #[arg(long, help_heading = "Inputs")]
    pub local_origin: bool,
    /// Output folder: one sub-folder per stage, run.json, report.html; not inside the scene.
    #[arg(long, value_name = "R", help_heading = "Outputs")]
    pub out: PathBuf,
    /// Rerun every stage even when its output is complete (by default a run resumes).
    #[arg(long, help_heading = "Outputs")]
    pub force: bool,
    /// Label supervision: fused (the city model fused with the scene's masks: also trees,
    /// cars, people; paper §3.2) or city (the city model alone, §3.1).
    #[arg(long, default_value = "fused", help_heading = "Supervision")]
    pub supervision: Supervision,
    /// Per-Gaussian labels that are evaluated and queried: vote (closed form) or learned
    /// (identity codes trained from the vote, paper §3.3; config [train]).
    #[arg(long, default_value = "vote", help_heading = "Supervision")]
    pub mode: Mode,
    /// Refine the alignment from the 3DGS scene first (robust ICP, `align --refine`, reach
    /// about 3 m); the whole run uses the refined transform (R/align/alignment.json).
    #[arg(long, help_heading = "Supervision")]
    pub refine_alignment: bool,
    /// Every N-th view (by name) is held back as a test view: not labelled, predicted as a
    /// novel view, evaluated against gt/ (3DGS's --eval: 8). Default: the test views the scene
    /// declares (scene.json; `gs4city synth` writes them), else every view trains.
    #[arg(long, value_name = "N", help_heading = "Supervision")]
    pub test_every: Option<usize>,
    /// How much work for the answer (docs/quality.md): full (every training view at full
    /// resolution, the longest lists), default (the cheapest setting within 0.5 fine-mIoU points
    /// of full on every scene measured: full's views, blending stopped at 80 % of a pixel's
    /// mass, contributions from α ≥ 1/32, lists to 90 % of the mass) or fast (a first look;
    /// costs points).
    #[arg(long, default_value = "default", help_heading = "Performance")]
    pub quality: Quality,
    /// Training views at 1/N of their resolution from the render to the vote (test views
    /// always at full resolution); default: the --quality preset's.
    #[arg(long, value_name = "N", help_heading = "Performance")]
    pub train_scale: Option<u32>,
    /// Training views: all, K (the fewest, greedily, that keep every Gaussian seen by K of
    /// them at a good angle, or by all that see it) or K:SHARE (the greedy views that meet
    /// SHARE of that demand); default: the --quality preset's.
    #[arg(long, value_name = "all|K[:SHARE]", help_heading = "Performance")]
    pub train_views: Option<ViewSelection>,
    /// Worker threads (default: every core).
    #[arg(long, value_name = "N", help_heading = "Performance")]
    pub threads: Option<usize>,
}

impl RunArgs {
    /// Validated options: the user's flags and the `--config` file's sections.
    pub fn options(&self) -> anyhow::Result<RunOptions> {
        let cfg = self.config.load()?;
        run_options(&cfg, self)
    }
}

/// The run's options from a config file and the run's own flags.
fn run_options(cfg: &Config, a: &RunArgs) -> anyhow::Result<RunOptions> {
    crate::check::non_negative("tau", cfg.raycast.tau)?;
    let lift = super::groups::vote_options(&cfg.vote, &cfg.prior)?;
    let preset = a.quality.work();
    // The `[cache]` keys the config gives override the preset's lists, key by key.
    fn pick<T>(given: bool, file: T, preset: T) -> T {
        if given { file } else { preset }
    }
    let given = |key: &str| cfg.cache_keys.iter().any(|k| k == key);
    let file = cfg.cache.options();
    let cache = crate::cache::CacheOptions {
        top_k: pick(given("top_k"), file.top_k, preset.top_k),
        epsilon: pick(given("epsilon"), file.epsilon, preset.epsilon),
        t_stop: pick(given("t_stop"), file.t_stop, preset.t_stop),
        alpha_min: pick(given("alpha_min"), file.alpha_min, preset.alpha_min),
    };
    cache.validate()?;
    let train_scale = a.train_scale.unwrap_or(preset.train_scale);
    let max = crate::camera::MAX_DOWNSCALE as u32;
    if !(1..=max).contains(&train_scale) {
        anyhow::bail!("--train-scale must be 1 to {max}, got {train_scale}");
    }
    let train = cfg.train.options(&cfg.vote)?;
    let check = crate::inspect::CheckOptions {
        max_offset_m: cfg.check.max_offset,
        local_origin: a.local_origin,
        ..Default::default()
    };
    check.validate()?;
    cfg.refine.validate()?;
    Ok(RunOptions {
        tau_m: cfg.raycast.tau,
        single_pass: cfg.raycast.single_pass,
        top_k: cache.top_k,
        epsilon: cache.epsilon,
        t_stop: cache.t_stop,
        alpha_min: cache.alpha_min,
        train_scale,
        views: a.train_views.unwrap_or(preset.views),
        lift,
        supervision: a.supervision,
        masks: cfg.masks.options()?,
        openings: cfg.openings.options()?,
        associate: cfg.associate.options()?,
        fuse: cfg.fuse.options(),
        mode: a.mode,
        train,
        test_every: a.test_every,
        local_origin: a.local_origin,
        refine_alignment: a.refine_alignment,
        refine: cfg.refine.clone(),
        check,
        force: a.force,
    })
}

/// Prints the stage table and the metrics tables of a run.
pub fn print_run(s: &RunSummary) {
    println!("{:<10} {:>9}  output", "stage", "seconds");
    for r in &s.stages {
        println!(
            "{:<10} {:>9.2}  {}{}",
            r.stage,
            r.seconds,
            r.out.display(),
            if r.resumed { "  (resumed)" } else { "" }
        );
    }
    if let Some(e) = &s.eval {
        println!(
            "\n{} test views, {} predictions\n{}",
            e.images,
            e.mode.as_deref().unwrap_or("?"),
            e.tables
        );
        if let Some(t) = &e.by_query_tables {
            println!("query-driven (one selection per class, the paper's protocol)\n{t}");
        }
    }
    println!("report: {}", s.report.display());
}

pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    let cfg = args.config.load()?;
    let opts = run_options(&cfg, args)?;
    if let Some(n) = args.threads {
        crate::check::at_least("threads", n, 1)?;
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .map_err(|e| anyhow::anyhow!("--threads {n}: {e}"))?;
    }
    if let Some(dir) = &args.model_dir {
        let masks = args.scene.join("masks");
        let has_masks = std::fs::read_dir(&masks).is_ok_and(|rd| {
            rd.filter_map(|e| e.ok())
                .any(|e| e.path().extension().is_some_and(|x| x == "json"))
        });
        if !has_masks {
            let t = std::time::Instant::now();
            let seg = crate::segment::run(&args.scene, dir, &cfg.segment.options()?)?;
            crate::progress::done(
                "segment",
                &format!(
                    "{} images segmented ({} masks) into {}",
                    seg.segmented,
                    seg.masks,
                    masks.display()
                ),
                t.elapsed().as_secs_f64(),
            );
        }
        // CLIP features when the folder has a CLIP model and the scene has masks but no features
        let prompts = args.scene.join("features/prompts.json");
        if crate::segment::clip::has_any(dir) && !prompts.is_file() {
            let t = std::time::Instant::now();
            let f = crate::segment::features::run(
                &args.scene,
                dir,
                &crate::segment::FeaturesOptions::default(),
            )?;
            super::features::report(&f, t.elapsed().as_secs_f64());
        }
    }
    let s = run::run(&args.scene, &args.out, &opts).map_err(|e| match e {
        // Kept as itself, so that the exit status says "busy" (`lock::EXIT_BUSY`).
        run::RunError::Lock(l) => anyhow::Error::from(l),
        e => e.into(),
    })?;
    print_run(&s);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;
    use std::path::Path;

    #[derive(Debug, Parser)]
    struct Cmd {
        #[command(flatten)]
        run: RunArgs,
    }

    /// The run options of `--quality Q` (none: the default) with a config file of `toml`.
    fn options(quality: Option<&str>, toml: &str) -> RunOptions {
        let mut argv = vec!["x", "--scene", "S", "--out", "R"];
        if let Some(q) = quality {
            argv.extend(["--quality", q]);
        }
        let a = Cmd::try_parse_from(argv).unwrap().run;
        let cfg = Config::parse(Path::new("c.toml"), toml).unwrap();
        run_options(&cfg, &a).unwrap()
    }

    /// The presets' lists, and a `[cache]` key of the config file overriding only itself.
    #[test]
    fn the_quality_presets_set_the_lists_and_a_config_key_overrides_only_itself() {
        let d = options(None, "");
        let inria = 1.0f32 / 255.0;
        assert_eq!(
            (d.top_k, d.epsilon, d.t_stop, d.alpha_min),
            (32, 0.1, 0.2, 0.03125)
        );
        assert_eq!((d.train_scale, d.views), (1, ViewSelection::All));
        let f = options(Some("full"), "");
        assert_eq!(
            (f.top_k, f.epsilon, f.t_stop, f.alpha_min),
            (32, 0.05, 0.02, inria)
        );
        let fast = options(Some("fast"), "");
        assert_eq!(
            (fast.t_stop, fast.alpha_min, fast.train_scale),
            (0.02, inria, 2)
        );
        // One key given: the others stay the preset's.
        let k = options(None, "[cache]\ntop_k = 16\n");
        assert_eq!(
            (k.top_k, k.epsilon, k.t_stop, k.alpha_min),
            (16, 0.1, 0.2, 0.03125)
        );
        let a = options(Some("full"), "[cache]\nalpha_min = 0.0625\n");
        assert_eq!((a.t_stop, a.alpha_min), (0.02, 0.0625));
        let low = Config::parse(Path::new("c.toml"), "[cache]\nalpha_min = 0.001\n").unwrap();
        let argv = ["x", "--scene", "S", "--out", "R"];
        let err = run_options(&low, &Cmd::try_parse_from(argv).unwrap().run).unwrap_err();
        assert!(err.to_string().contains("alpha_min"), "{err}");
        let t = options(Some("full"), "[cache]\nt_stop = 0.05\n");
        assert_eq!((t.top_k, t.epsilon, t.t_stop), (32, 0.05, 0.05));
        // A key given with the value another preset has is still the user's.
        let same = options(None, "[cache]\nt_stop = 0.02\n");
        assert_eq!(same.t_stop, 0.02);
        // The default run's options are the library's default.
        assert_eq!(d, RunOptions::default());
    }
}
