//! `gs4city run`: a scene folder through every stage into a run folder.
use std::path::PathBuf;

use clap::Args;

use crate::lift::LiftOptions;
use crate::masks::{Source, Test};
use crate::run::{self, Mode, Quality, RunOptions, RunSummary, Supervision, ViewSelection};

/// The work knobs of a run (docs/quality.md): a preset and its single knobs.
#[derive(Debug, Args)]
#[command(next_help_heading = "Work (docs/quality.md)")]
pub struct WorkArgs {
    /// How much work for the answer (docs/quality.md): full (every training view at full
    /// resolution), default (the cheapest setting within 0.5 fine-mIoU points of full on
    /// every scene measured: full's, for now) or fast (a first look; costs points). The
    /// options below override single knobs of the preset.
    #[arg(long, default_value = "default")]
    pub quality: Quality,
    /// Training views at 1/N of their resolution from the render to the vote (test views
    /// always at full resolution); default: the --quality preset's.
    #[arg(long, value_name = "N")]
    pub train_scale: Option<u32>,
    /// Training views: all, K (the fewest, greedily, that keep every Gaussian seen by K of
    /// them at a good angle, or by all that see it) or K:SHARE (the greedy views that meet
    /// SHARE of that demand); default: the --quality preset's.
    #[arg(long, value_name = "all|K[:SHARE]")]
    pub train_views: Option<ViewSelection>,
    /// Longest contribution list per pixel in the cache (0 = no bound); with `--epsilon 0`
    /// the top-k by α·T; default: the --quality preset's.
    #[arg(long)]
    pub top_k: Option<usize>,
    /// Mass rule of the cache: a pixel keeps its largest α·T until they reach 1 − ε of its
    /// mass (at most --top-k); 0 = plain top-k lists; default: the --quality preset's.
    #[arg(long)]
    pub epsilon: Option<f32>,
    /// Early stop of the cache's blend: a pixel stops once its transmittance falls below T
    /// (what lies behind, at most T of its mass, is not listed); 0 = the rasterizer's own
    /// stop only (exact lists); default: the --quality preset's.
    #[arg(long, value_name = "T")]
    pub t_stop: Option<f32>,
}

impl WorkArgs {
    /// The preset with the knobs given on the command line, checked.
    pub fn work(&self) -> anyhow::Result<run::Work> {
        let preset = self.quality.work();
        let work = run::Work {
            train_scale: self.train_scale.unwrap_or(preset.train_scale),
            views: self.train_views.unwrap_or(preset.views),
            top_k: self.top_k.unwrap_or(preset.top_k),
            epsilon: self.epsilon.unwrap_or(preset.epsilon),
            t_stop: self.t_stop.unwrap_or(preset.t_stop),
        };
        let max = crate::camera::MAX_DOWNSCALE as u32;
        if !(1..=max).contains(&work.train_scale) {
            anyhow::bail!("--train-scale must be 1 to {max}, got {}", work.train_scale);
        }
        crate::cache::CacheOptions {
            top_k: work.top_k,
            epsilon: work.epsilon,
            t_stop: work.t_stop,
        }
        .validate()
        .map_err(|e| anyhow::anyhow!("cache options: {e}"))?;
        Ok(work)
    }
}

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Scene folder (`docs/design.md`): images/, sparse/0/, point_cloud.ply, citymodel/*.gml +
    /// alignment.json, optional masks/, features/, gt/.
    #[arg(long)]
    pub scene: PathBuf,
    /// A model folder: with SAM-family files (docs/segment.md), when the scene has no
    /// masks/<stem>.json, `gs4city segment` writes them (into the scene's masks/, default
    /// options) before the run; with CLIP files (docs/features.md), when the scene has no
    /// features/prompts.json, `gs4city features` then writes the masks' features.
    #[arg(long, value_name = "DIR")]
    pub model_dir: Option<PathBuf>,
    /// Points per side of the prompt grid of that segmentation (`gs4city segment --points-per-side`).
    #[arg(long, default_value_t = crate::segment::SegmentOptions::default().points_per_side)]
    pub segment_points_per_side: usize,
    /// Part-pass depth tolerance τ in metres.
    #[arg(long, default_value_t = 0.5)]
    pub tau: f64,
    /// Single-pass raycasting (no part pass), for comparison.
    #[arg(long)]
    pub single_pass: bool,
    /// Background bias γ of the vote, in [-1, 1].
    /// Default: −1 with fused (mask) supervision, −0.5 with the city model alone.
    #[arg(long, allow_negative_numbers = true)]
    pub gamma: Option<f32>,
    /// Depth gate of city votes in metres: a Gaussian more than this in front of the city
    /// surface its pixel's ray hits takes no vote from that surface's label; 0 = off.
    #[arg(long, default_value_t = crate::vote::CITY_GATE_M)]
    pub city_gate_m: f32,
    /// No centre gate of city votes: without this, a city-labelled pixel gives no vote to a
    /// Gaussian whose centre projects onto a city label of another class in the same view (a
    /// wall Gaussian straddling a door's outline takes no door votes); part of the depth gate
    /// (off with it).
    #[arg(long)]
    pub no_centre_gate: bool,
    /// Weight of the city-model prior in 3D: each Gaussian within --model-prior-m of a
    /// city-model triangle gets one vote for that triangle's label, of this share of the median
    /// Gaussian's vote weight (well-seen Gaussians outweigh it, barely seen ones follow the
    /// model); 0 = off.
    #[arg(long, default_value_t = crate::vote::MODEL_PRIOR)]
    pub model_prior: f32,
    /// Reach of the city-model prior in metres.
    #[arg(long, default_value_t = crate::vote::MODEL_PRIOR_M)]
    pub model_prior_m: f32,
    /// Every N-th view (by name) is held back as a test view, not voted on and predicted as a
    /// novel view (default 8, 3DGS --eval); 0 = every view trains (a capture without ground
    /// truth loses nothing to evaluation then). The split never depends on gt/.
    #[arg(long, value_name = "N")]
    pub test_every: Option<usize>,
    /// Run a scene without citymodel/alignment.json: CityGML coordinates minus a local origin.
    #[arg(long)]
    pub local_origin: bool,
    /// Refine the alignment from the 3DGS scene first (robust ICP, `align --refine`); the whole
    /// run uses the refined transform (R/align/alignment.json, recorded in run.json).
    #[arg(long)]
    pub refine_alignment: bool,
    /// Label supervision: fused (the city model fused with the scene's filtered, associated
    /// masks: also trees, cars, people; paper §3.2) or city (the city model alone, §3.1).
    #[arg(long, default_value = "fused")]
    pub supervision: Supervision,
    /// Mask source of the masks stage: auto (the scene's SAM lists when it has masks/, else
    /// the mask-free depth source), sam, depth.
    #[arg(long, default_value = "auto")]
    pub masks_source: Source,
    /// Test of the masks stage for masks on the building: auto, features, geometry, both, overlap.
    #[arg(long, default_value = "auto")]
    pub masks_test: Test,
    /// τ_q of the masks stage: SAM masks with a lower predicted_iou are dropped.
    #[arg(long, default_value_t = crate::masks::MasksOptions::default().tau_q)]
    pub tau_q: f64,
    /// m_view: an associated group must be seen in at least this many views.
    #[arg(long, default_value_t = crate::associate::AssociateOptions::default().min_views)]
    pub min_views: usize,
    /// Openings (windows, doors) the images show but the city model lacks: missing (add them
    /// to the semantic table under their wall and raycast the completed model again) or off
    /// (the completeness report only); docs/completeness.md. Their m_view: --opening-views.
    #[arg(long, default_value = "missing")]
    pub openings: crate::openings::Add,
    /// m_view of the openings stage: an opening the model lacks is added when at least this
    /// many training views show it (the association's m_view is --min-views).
    #[arg(long, default_value_t = crate::openings::OpeningsOptions::default().m_view)]
    pub opening_views: usize,
    /// Where opening candidates come from: features (dropped building masks whose best prompt
    /// is a window or door prompt), geometry (regions recessed behind the wall in the 3DGS
    /// depth) or both; docs/completeness.md.
    #[arg(long, default_value = "both")]
    pub opening_cues: crate::openings::Cues,
    /// No city-part snapping of windows and doors to the image's own masks in the fuse stage.
    #[arg(long)]
    pub no_snap: bool,
    /// Support-only masks (fail only τ_q) do not join associated groups (the ablation).
    #[arg(long)]
    pub no_support_masks: bool,
    /// Feature cosine τ_sim of the association: the cap of the value calibrated on the scene's
    /// own mask pairs, or the value itself with --no-calibrate.
    #[arg(long, default_value_t = crate::associate::AssociateOptions::default().tau_sim)]
    pub tau_sim: f64,
    /// Use --tau-sim as given instead of calibrating it on the scene (docs/associate.md).
    #[arg(long)]
    pub no_calibrate: bool,
    /// Per-Gaussian labels that are evaluated and queried: vote (closed form) or learned
    /// (identity codes trained from the vote, the train stage).
    #[arg(long, default_value = "vote")]
    pub mode: Mode,
    /// Training iterations of --mode learned.
    #[arg(long, default_value_t = crate::train::TrainOptions::default().iterations)]
    pub iterations: usize,
    /// The scene check that runs first: largest plausible distance (metres, lower quartile)
    /// between opaque Gaussian centres and the city model (`gs4city check --max-offset`).
    #[arg(long, default_value_t = crate::inspect::CheckOptions::default().max_offset_m)]
    pub max_offset: f64,
    /// Rerun every stage even when its output is complete.
    #[arg(long)]
    pub force: bool,
    /// Output folder (one sub-folder per stage, run.json, report.html); not inside the scene.
    #[arg(long)]
    pub out: PathBuf,
    // The work knobs, last: their help heading applies to every option after them.
    #[command(flatten)]
    pub work: WorkArgs,
}

impl RunArgs {
    /// Validated options.
    pub fn options(&self) -> anyhow::Result<RunOptions> {
        if !(self.tau.is_finite() && self.tau >= 0.0) {
            anyhow::bail!(
                "--tau must be a finite number ≥ 0 (metres), got {}",
                crate::numfmt::Num(self.tau)
            );
        }
        let lift = LiftOptions {
            gamma: self.gamma,
            city_gate_m: self.city_gate_m,
            centre_gate: !self.no_centre_gate,
            model_prior: self.model_prior,
            model_prior_m: self.model_prior_m,
        };
        lift.validate()?;
        let work = self.work.work()?;
        let d = RunOptions::default();
        let masks = crate::masks::MasksOptions {
            source: self.masks_source,
            test: self.masks_test,
            tau_q: self.tau_q,
            ..d.masks.clone()
        };
        masks.validate()?;
        let associate = crate::associate::AssociateOptions {
            min_views: self.min_views,
            support_masks: !self.no_support_masks,
            tau_sim: self.tau_sim,
            calibrate: !self.no_calibrate,
            ..d.associate
        };
        associate.validate()?;
        let fuse = crate::fuse::FuseOptions {
            snap: !self.no_snap,
            ..d.fuse
        };
        let train = crate::train::TrainOptions {
            iterations: self.iterations,
            city_gate_m: self.city_gate_m,
            centre_gate: !self.no_centre_gate,
            ..d.train
        };
        train.validate()?;
        let check = crate::inspect::CheckOptions {
            max_offset_m: self.max_offset,
            local_origin: self.local_origin,
            ..Default::default()
        };
        check.validate()?;
        let openings = crate::openings::OpeningsOptions {
            add: self.openings,
            cues: self.opening_cues,
            m_view: self.opening_views,
            ..Default::default()
        };
        openings.validate()?;
        let opts = RunOptions {
            tau_m: self.tau,
            single_pass: self.single_pass,
            top_k: work.top_k,
            epsilon: work.epsilon,
            t_stop: work.t_stop,
            train_scale: work.train_scale,
            views: work.views,
            lift,
            supervision: self.supervision,
            masks,
            openings,
            associate,
            fuse,
            mode: self.mode,
            train,
            test_every: self.test_every,
            local_origin: self.local_origin,
            refine_alignment: self.refine_alignment,
            refine: Default::default(),
            check,
            force: self.force,
        };
        Ok(opts)
    }
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
    let opts = args.options()?;
    if let Some(dir) = &args.model_dir {
        let masks = args.scene.join("masks");
        let has_masks = std::fs::read_dir(&masks).is_ok_and(|rd| {
            rd.filter_map(|e| e.ok())
                .any(|e| e.path().extension().is_some_and(|x| x == "json"))
        });
        if !has_masks {
            let t = std::time::Instant::now();
            let seg = crate::segment::run(
                &args.scene,
                dir,
                &crate::segment::SegmentOptions {
                    points_per_side: args.segment_points_per_side,
                    ..Default::default()
                },
            )?;
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
    let s = run::run(&args.scene, &args.out, &opts)?;
    print_run(&s);
    Ok(())
}
