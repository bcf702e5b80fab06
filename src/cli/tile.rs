//! `gs4city tile`, `gs4city run-plan`, `gs4city merge`: a city as tiles that run anywhere (here,
//! or as a Slurm job array) and merge into one semantic scene (`crate::tile`, docs/tile.md).
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Args, Parser, Subcommand};

use crate::tile::{self, Plan, TileOptions, exec, merge};

#[derive(Debug, Subcommand)]
pub enum CityCommand {
    /// A tile plan of a scene: per tile a scene folder (cropped PLY cut in one streaming pass,
    /// COLMAP and CityGML subsets, linked images), plan.json, Slurm batch scripts.
    #[command(
        after_help = "Example:\n  gs4city tile --scene S --size 150 --margin 25 --out P\n  bash P/slurm.sh    (or: gs4city run-plan P --jobs 2)"
    )]
    Tile(TileArgs),
    /// Run a tile plan here: every tile (N at a time), then the merge; or one tile (--tile I,
    /// what each Slurm array task runs).
    #[command(
        after_help = "Example:\n  gs4city run-plan P --jobs 2\n  gs4city run-plan P --tile 3"
    )]
    RunPlan(RunPlanArgs),
    /// Merge a plan's tiles into one run folder (global label ids, one semantic.ply, labels
    /// for query --run M); a failed or missing tile is refused unless --allow-missing.
    #[command(
        after_help = "Example:\n  gs4city merge P --out M\n  gs4city query --run M --class Window --out Q"
    )]
    Merge(MergeArgs),
}

#[derive(Debug, Args)]
pub struct TileArgs {
    /// Scene folder (with citymodel/alignment.json).
    #[arg(long)]
    pub scene: PathBuf,
    /// Side of a tile's core in metres (the city model's ground plane).
    #[arg(long, default_value_t = TileOptions::default().size_m)]
    pub size: f64,
    /// Margin around each core in metres (Gaussians and neighbouring buildings within it join).
    #[arg(long, default_value_t = TileOptions::default().margin_m)]
    pub margin: f64,
    /// Every N-th view by name is a test view of the whole plan, held back from every tile
    /// (as `gs4city run`); 0 = none. Default: the test views the scene declares (scene.json),
    /// else none.
    #[arg(long, value_name = "N")]
    pub test_every: Option<usize>,
    /// Share of a view's screen a tile must take for the view to join it (a coarse screen grid,
    /// each cell won by the nearest visible sample point); 0 = every view that sees the tile.
    #[arg(long, default_value_t = TileOptions::default().min_share)]
    pub min_share: f64,
    /// Views each tile keeps whatever their share (its best), when that many see it.
    #[arg(long, default_value_t = TileOptions::default().min_views)]
    pub min_views: usize,
    /// A view joins a tile cropped to the window of its image where the tile shows when that
    /// window is smaller than this share of the image (e.g. 0.3); 0 = every view whole.
    #[arg(long, default_value_t = TileOptions::default().crop_below)]
    pub crop_below: f64,
    /// Options of each tile's `gs4city run`, as one string (e.g. "--supervision city" or
    /// "--config ablation.toml").
    #[arg(long, default_value = "", allow_hyphen_values = true)]
    pub run_args: String,
    /// Plan folder to create.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct RunPlanArgs {
    /// Plan folder (`gs4city tile --out P`).
    pub plan: PathBuf,
    /// Tiles run in parallel.
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Run this tile alone (its index in plan.json; the Slurm array index) and do not merge.
    #[arg(long, conflicts_with = "jobs")]
    pub tile: Option<usize>,
    /// Keep each tile's contributions cache and per-view maps (raycast, masks, groups; removed by
    /// default once its run is done: the merge does not read them).
    #[arg(long)]
    pub keep_cache: bool,
    /// Rerun tiles that already finished.
    #[arg(long)]
    pub force: bool,
    /// Merge into this folder (default: P/merged).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Do not render and predict the plan's test views in the merge.
    #[arg(long)]
    pub no_test_views: bool,
}

#[derive(Debug, Args)]
pub struct MergeArgs {
    /// Plan folder.
    pub plan: PathBuf,
    /// Merged run folder (replaced when it exists).
    #[arg(long)]
    pub out: PathBuf,
    /// Merge a partial city: failed or missing tiles become holes (their Gaussians −1), listed.
    #[arg(long)]
    pub allow_missing: bool,
    /// Do not render and predict the plan's test views.
    #[arg(long)]
    pub no_test_views: bool,
}

/// `gs4city run`'s options alone, to parse a plan's run arguments.
#[derive(Debug, Parser)]
struct RunOnly {
    #[command(flatten)]
    run: super::run::RunArgs,
}

/// The run options of tile `scene` → `out`: the plan's run arguments, every view training
/// (the plan's test views are not in the tile).
fn tile_run_options(
    run_args: &[String],
    scene: &std::path::Path,
    out: &std::path::Path,
) -> anyhow::Result<crate::run::RunOptions> {
    let mut argv: Vec<String> = vec!["run".into()];
    argv.extend(run_args.iter().cloned());
    argv.extend([
        "--scene".into(),
        scene.display().to_string(),
        "--out".into(),
        out.display().to_string(),
        "--test-every".into(),
        "0".into(),
    ]);
    let r = RunOnly::try_parse_from(&argv)
        .map_err(|e| anyhow::anyhow!("the plan's run arguments {run_args:?}: {e}"))?;
    r.run.options()
}

pub fn run(cmd: &CityCommand) -> anyhow::Result<()> {
    match cmd {
        CityCommand::Tile(a) => tile_cmd(a),
        CityCommand::RunPlan(a) => run_plan(a),
        CityCommand::Merge(a) => merge_cmd(a),
    }
}

fn tile_cmd(a: &TileArgs) -> anyhow::Result<()> {
    let run_args: Vec<String> = a.run_args.split_whitespace().map(String::from).collect();
    let opts = TileOptions {
        size_m: a.size,
        margin_m: a.margin,
        test_every: a.test_every,
        min_share: a.min_share,
        min_views: a.min_views,
        crop_below: a.crop_below,
        run_args,
        ..TileOptions::default()
    };
    // The run arguments are checked now, not in the tiles' jobs.
    tile_run_options(&opts.run_args, &a.scene, &a.out)?;
    let exe = std::env::current_exe().ok();
    let plan = tile::plan(&a.scene, &a.out, &opts, exe.as_deref())?;
    for w in &plan.warnings {
        eprintln!("warning: {w}");
    }
    println!(
        "{} tiles ({}×{} of {} m, margin {} m), {} runnable, {} Gaussians, {} test views held back",
        plan.tiles.len(),
        plan.grid.nx,
        plan.grid.ny,
        plan.grid.size,
        plan.grid.margin,
        plan.tiles.iter().filter(|t| t.runnable).count(),
        plan.gaussians,
        plan.test_views.len()
    );
    println!(
        "{:<9} {:>6} {:>10} {:>10} {:>6} {:>8}",
        "tile", "owned", "gaussians", "core", "views", "mem MB"
    );
    for t in &plan.tiles {
        println!(
            "{:<9} {:>6} {:>10} {:>10} {:>6} {:>8}{}",
            t.name,
            t.owned.len(),
            t.gaussians,
            t.core_gaussians,
            t.views,
            t.resources.mem_mb,
            t.why_not
                .as_ref()
                .map(|w| format!("  (not run: {w})"))
                .unwrap_or_default()
        );
    }
    println!(
        "plan: {}  (Slurm: bash {}; here: gs4city run-plan {} --jobs N)",
        a.out.join(tile::PLAN).display(),
        a.out.join("slurm.sh").display(),
        a.out.display()
    );
    Ok(())
}

fn run_plan(a: &RunPlanArgs) -> anyhow::Result<()> {
    if let Some(i) = a.tile {
        return run_one(a, i);
    }
    let exe = std::env::current_exe().context("finding the gs4city binary")?;
    let r = exec::run_tiles(&a.plan, &exe, a.jobs, a.keep_cache, a.force).map_err(busy_aware)?;
    println!(
        "{} tiles run, {} reused, {} failed, in {:.1} s with {} jobs",
        r.ran.len(),
        r.reused.len(),
        r.failed.len(),
        r.seconds,
        r.jobs
    );
    for (t, why) in &r.failed {
        eprintln!("tile {t} failed: {why}");
    }
    crate::fsutil::write_json(&a.plan.join("run-plan.json"), &r)?;
    if !r.failed.is_empty() {
        anyhow::bail!(
            "{} of the plan's tiles failed ({}); not merged (fix and rerun `gs4city run-plan {}`, or `gs4city merge {} --out M --allow-missing`)",
            r.failed.len(),
            r.failed
                .iter()
                .map(|(t, _)| t.as_str())
                .collect::<Vec<_>>()
                .join(", "),
            a.plan.display(),
            a.plan.display()
        );
    }
    let out = a.out.clone().unwrap_or_else(|| a.plan.join("merged"));
    let s = merge::merge(
        &a.plan,
        &out,
        &merge::MergeOptions {
            allow_missing: false,
            test_views: !a.no_test_views,
        },
    )
    .map_err(busy_aware)?;
    print_merge(&s, &out);
    Ok(())
}

/// One tile's job: its run, then its status (time, CPU, peak memory, disk) and the removal of
/// its cache.
fn run_one(a: &RunPlanArgs, i: usize) -> anyhow::Result<()> {
    let plan = Plan::read(&a.plan)?;
    let t = plan.tiles.get(i).with_context(|| {
        format!(
            "{}: the plan has {} tiles (0–{}), not tile {i}",
            a.plan.join(tile::PLAN).display(),
            plan.tiles.len(),
            plan.tiles.len().saturating_sub(1)
        )
    })?;
    let dir = Plan::tile_dir(&a.plan, t);
    if !dir.is_dir() {
        anyhow::bail!(
            "tile {} ({i}): its folder {} is missing; the plan is damaged (make it again with `gs4city tile`)",
            t.name,
            dir.display()
        );
    }
    // One job per tile at a time (a second one, or a second run-plan, is refused with the
    // holder's name and `lock::EXIT_BUSY`); held until the status is written.
    let _lock = crate::lock::FolderLock::exclusive(&dir)?;
    exec::start(&dir)?;
    let t0 = Instant::now();
    if !t.runnable {
        exec::finish(&dir, t, 0.0, None, a.keep_cache)?;
        println!(
            "tile {}: nothing to run ({})",
            t.name,
            t.why_not.as_deref().unwrap_or("")
        );
        return Ok(());
    }
    let scene = dir.join("scene");
    let out = exec::run_dir(&dir);
    let result = tile_run_options(&plan.options.run_args, &scene, &out).and_then(|mut o| {
        o.force = o.force || a.force;
        Ok(crate::run::run(&scene, &out, &o)?)
    });
    let error = result.as_ref().err().map(|e| format!("{e:#}"));
    let st = exec::finish(&dir, t, t0.elapsed().as_secs_f64(), error, a.keep_cache)?;
    let _summary = result.with_context(|| format!("tile {} ({i})", t.name))?;
    println!(
        "tile {}: done in {:.1} s ({:.1} CPU s), peak memory {:.0} MB, disk {:.1} MB{}",
        t.name,
        st.seconds,
        st.cpu_seconds.unwrap_or(f64::NAN),
        st.peak_rss_mb.unwrap_or(f64::NAN),
        st.disk_bytes as f64 / 1e6,
        if st.cache_removed {
            format!(" (cache of {:.1} MB removed)", st.cache_bytes as f64 / 1e6)
        } else {
            String::new()
        }
    );
    Ok(())
}

/// A tile error as `anyhow` carries it: a lock held by another process kept as itself, so that
/// `gs4city` exits with `lock::EXIT_BUSY`.
fn busy_aware(e: tile::TileError) -> anyhow::Error {
    match e {
        tile::TileError::Lock(l) => l.into(),
        e => e.into(),
    }
}

fn merge_cmd(a: &MergeArgs) -> anyhow::Result<()> {
    let s = merge::merge(
        &a.plan,
        &a.out,
        &merge::MergeOptions {
            allow_missing: a.allow_missing,
            test_views: !a.no_test_views,
        },
    )
    .map_err(busy_aware)?;
    print_merge(&s, &a.out);
    Ok(())
}

fn print_merge(s: &merge::MergeSummary, out: &std::path::Path) {
    println!(
        "merged {} tiles: {} of {} Gaussians labelled, {} entities, {} labels (Δ {})",
        s.tiles.iter().filter(|t| t.state == "merged").count(),
        s.labelled,
        s.gaussians,
        s.entities,
        s.labels,
        s.delta
    );
    for h in &s.holes {
        println!("HOLE: {h}");
    }
    if s.in_holes > 0 {
        println!("{} Gaussians lie in holes (label −1)", s.in_holes);
    }
    println!(
        "objects cut by tile borders: {} groups joined into a neighbouring tile's ({} pairs with common Gaussians ≥ {} of both groups' in the shared margin)",
        s.joined_groups,
        s.joins.len(),
        s.join_fraction
    );
    println!(
        "tiles: {:.1} CPU s in all, peak memory of one tile ≤ {:.0} MB, disk of one tile ≤ {:.1} MB; merge: {:.1} s, peak {:.0} MB",
        s.tiles_cpu_seconds,
        s.tile_peak_rss_mb_max.unwrap_or(f64::NAN),
        s.tile_disk_bytes_max as f64 / 1e6,
        s.seconds,
        s.peak_rss_mb.unwrap_or(f64::NAN)
    );
    if let (Some(p), Some(d)) = (s.paper_fine_miou, s.fine_miou) {
        println!(
            "test views ({}): fine mIoU {:.2} (paper protocol), {:.2} (dataset level)",
            s.test_views.len(),
            100.0 * p,
            100.0 * d
        );
    }
    println!(
        "merged run: {} (gs4city query --run {} …)",
        out.display(),
        out.display()
    );
}
