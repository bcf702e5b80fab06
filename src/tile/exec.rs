//! Running a plan's tiles: the record one tile's job leaves (`P/tiles/<name>/status.json`: done
//! or failed, time, CPU time, peak memory, disk), the removal of its contributions cache once
//! its run is done, and the local executor of `gs4city run-plan P --jobs N` (one `gs4city
//! run-plan P --tile I` process per tile, at most N at a time).
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::{Plan, TileError, TilePlan};

/// The record of a tile's job, in its folder.
pub const STATUS: &str = "status.json";

/// What one tile's job did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileStatus {
    pub tile: String,
    pub ok: bool,
    /// The error of a failed run (one line).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Wall-clock seconds of the run.
    pub seconds: f64,
    /// CPU seconds of the job's process (user + system).
    pub cpu_seconds: Option<f64>,
    /// Peak resident memory of the job's process (MB).
    pub peak_rss_mb: Option<f64>,
    /// Bytes of the tile folder at its largest (the run with its cache; links not followed).
    pub disk_bytes: u64,
    /// Bytes of the run's contributions cache (`run/render`).
    pub cache_bytes: u64,
    /// Whether the cache was removed after the run (its last consumer); `--keep-cache` keeps it.
    pub cache_removed: bool,
    /// Bytes of the per-view outputs the merge does not read ([`PRUNED`]), removed with the
    /// cache.
    #[serde(default)]
    pub pruned_bytes: u64,
    /// Bytes of the tile folder once its run is done (what the plan keeps of it).
    #[serde(default)]
    pub kept_bytes: u64,
}

/// The folders of a tile's run that only the run's own later stages read: the raycast's and the
/// openings' id and depth maps, the kept masks and the group maps. The merge reads the city
/// model's (or the openings') semantic table, the fused label table and the per-Gaussian labels;
/// a tile's completeness check reads the citymodel, fuse, lift and train stages only.
pub const PRUNED: [&str; 4] = ["raycast", "masks", "associate", "openings/raycast"];

impl TileStatus {
    /// Reads a tile's status; `None` when it has none.
    pub fn read(tile_dir: &Path) -> Result<Option<TileStatus>, TileError> {
        let p = tile_dir.join(STATUS);
        if !p.is_file() {
            return Ok(None);
        }
        Ok(Some(crate::fsutil::read_json(&p)?))
    }
}

/// Bytes of the files under `dir` (symbolic links counted as links, not followed).
pub fn disk_bytes(dir: &Path) -> u64 {
    let mut total = 0;
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in rd.flatten() {
            let Ok(m) = e.path().symlink_metadata() else {
                continue;
            };
            if m.is_dir() {
                stack.push(e.path());
            } else {
                total += m.len();
            }
        }
    }
    total
}

/// CPU seconds (user + system) of this process so far, from `/proc/self/stat` (clock ticks of
/// 1/100 s, Linux's `USER_HZ`).
pub fn cpu_seconds() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (which is in parentheses and may hold spaces).
    let rest = &s[s.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Whether a tile whose status says it succeeded still holds what the merge reads: its
/// `source.npy`, its run folder, and the outputs of the run's citymodel, fuse, lift and train
/// stages as its `run.json` records them (present, of the same size and content:
/// `layout::check_outputs`). `Err` is one line saying what is missing or changed.
pub fn check_outputs(tile_dir: &Path) -> Result<(), String> {
    use crate::layout::{RunRecord, Stage};
    let run = run_dir(tile_dir);
    if !run.is_dir() {
        return Err(format!(
            "its run folder {} is missing, though its {STATUS} says it succeeded",
            run.display()
        ));
    }
    let source = tile_dir.join("source.npy");
    if !source.is_file() {
        return Err(format!("{} is missing", source.display()));
    }
    let rec: RunRecord =
        crate::fsutil::read_json(&run.join("run.json")).map_err(|e| e.to_string())?;
    for stage in [Stage::Citymodel, Stage::Fuse, Stage::Lift, Stage::Train] {
        match rec.stages.get(stage.dir()) {
            Some(r) => {
                crate::layout::check_outputs(&stage.path(&run), &r.outputs)
                    .map_err(|why| format!("in its run folder {}: {why}", run.display()))?;
            }
            None if matches!(stage, Stage::Citymodel | Stage::Lift) => {
                return Err(format!(
                    "{} records no {stage} stage: its run did not finish",
                    run.join("run.json").display()
                ));
            }
            None => {}
        }
    }
    Ok(())
}

/// The run folder of a tile.
pub fn run_dir(tile_dir: &Path) -> PathBuf {
    tile_dir.join("run")
}

/// Records the end of a tile's run: measures the tile folder, removes the contributions cache
/// and the [`PRUNED`] folders unless `keep_cache`, and writes `status.json` (last). `error` is
/// the run's error, if any.
pub fn finish(
    tile_dir: &Path,
    tile: &TilePlan,
    seconds: f64,
    error: Option<String>,
    keep_cache: bool,
) -> Result<TileStatus, TileError> {
    let cache = run_dir(tile_dir).join("render");
    let cache_bytes = disk_bytes(&cache);
    let disk = disk_bytes(tile_dir);
    let remove = error.is_none() && !keep_cache && cache.is_dir();
    let gone = |dir: &Path| -> Result<u64, TileError> {
        let bytes = disk_bytes(dir);
        std::fs::remove_dir_all(dir).map_err(|err| TileError::Io {
            path: dir.to_path_buf(),
            err,
        })?;
        Ok(bytes)
    };
    let mut pruned_bytes = 0;
    if remove {
        gone(&cache)?;
        for p in PRUNED {
            let dir = run_dir(tile_dir).join(p);
            if dir.is_dir() {
                pruned_bytes += gone(&dir)?;
            }
        }
    }
    let st = TileStatus {
        tile: tile.name.clone(),
        ok: error.is_none(),
        error,
        seconds,
        cpu_seconds: cpu_seconds(),
        peak_rss_mb: crate::progress::peak_rss_mb(),
        disk_bytes: disk,
        cache_bytes,
        cache_removed: remove,
        pruned_bytes,
        kept_bytes: disk_bytes(tile_dir),
    };
    crate::fsutil::write_json(&tile_dir.join(STATUS), &st)?;
    Ok(st)
}

/// Removes a tile's old status before its job starts (so a job that dies leaves no success).
pub fn start(tile_dir: &Path) -> Result<(), TileError> {
    let p = tile_dir.join(STATUS);
    if p.exists() {
        std::fs::remove_file(&p).map_err(|err| TileError::Io { path: p, err })?;
    }
    Ok(())
}

/// What `run-plan` did.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PlanRun {
    /// Wall-clock seconds of all tiles with `jobs` in parallel.
    pub seconds: f64,
    pub jobs: usize,
    /// Tiles run now, and tiles whose earlier run was complete.
    pub ran: Vec<String>,
    pub reused: Vec<String>,
    /// Tiles whose job failed: name and the error of its status (or its exit).
    pub failed: Vec<(String, String)>,
}

/// Runs every runnable tile of the plan in `plan_dir` that has no successful status yet (all of
/// them with `force`, which also forces every stage of their runs), `jobs` at a time, each as
/// `exe run-plan P --tile I [--keep-cache] [--force]` with its output in the tile's `log.txt`.
///
/// The jobs die with this process (`crate::children`: killing `run-plan` kills its tiles). A
/// tile whose folder another process holds locked (another `run-plan` running it) is waited
/// for, then taken as that process left it: reused when it succeeded (unless `force`), run
/// otherwise.
pub fn run_tiles(
    plan_dir: &Path,
    exe: &Path,
    jobs: usize,
    keep_cache: bool,
    force: bool,
) -> Result<PlanRun, TileError> {
    let plan = Plan::read(plan_dir)?;
    let t0 = Instant::now();
    let mut todo: Vec<&TilePlan> = Vec::new();
    let mut reused = Vec::new();
    for t in plan.tiles.iter().filter(|t| t.runnable) {
        let dir = Plan::tile_dir(plan_dir, t);
        if !dir.is_dir() {
            return Err(TileError::Invalid(format!(
                "tile {}: its folder {} is missing; the plan is damaged (make it again with `gs4city tile`)",
                t.name,
                dir.display()
            )));
        }
        if crate::lock::FolderLock::holder(&dir).is_none()
            && matches!(TileStatus::read(&dir)?, Some(s) if s.ok && !force)
        {
            reused.push(t.name.clone());
        } else {
            todo.push(t);
        }
    }
    let bar = crate::progress::Bar::new("run-plan", todo.len() as u64, "tiles");
    let mut running: Vec<(&TilePlan, Child)> = Vec::new();
    let mut ran = Vec::new();
    let mut failed = Vec::new();
    // Tiles not started yet, in plan order; and those found locked by another process (each
    // with whether that was said already).
    let mut queue: std::collections::VecDeque<&TilePlan> = todo.into_iter().collect();
    let mut waiting: Vec<(&TilePlan, bool)> = Vec::new();
    loop {
        // Tiles another process held: take them back once it let go.
        let mut k = 0;
        while k < waiting.len() {
            let (t, said) = waiting[k];
            let dir = Plan::tile_dir(plan_dir, t);
            match crate::lock::FolderLock::holder(&dir) {
                Some(who) => {
                    if !said {
                        log::warn!("tile {}: run by {who}; waiting for it", t.name);
                        waiting[k].1 = true;
                    }
                    k += 1;
                }
                None => {
                    waiting.swap_remove(k);
                    match TileStatus::read(&dir)? {
                        Some(s) if s.ok && !force => {
                            reused.push(t.name.clone());
                            bar.inc(1);
                        }
                        _ => queue.push_front(t),
                    }
                }
            }
        }
        while running.len() < jobs.max(1) {
            let Some(t) = queue.pop_front() else { break };
            let dir = Plan::tile_dir(plan_dir, t);
            if crate::lock::FolderLock::holder(&dir).is_some() {
                waiting.push((t, false));
                continue;
            }
            let log_path = dir.join("log.txt");
            let log = std::fs::File::create(&log_path).map_err(|err| TileError::Io {
                path: log_path.clone(),
                err,
            })?;
            let err_log = log.try_clone().map_err(|err| TileError::Io {
                path: log_path.clone(),
                err,
            })?;
            // Spawned from this thread (the command's main thread), which lives as long as the
            // plan: the children's parent-death signal is tied to it.
            let mut cmd = crate::children::command(exe);
            cmd.arg("run-plan")
                .arg(plan_dir)
                .arg("--tile")
                .arg(t.index.to_string());
            if keep_cache {
                cmd.arg("--keep-cache");
            }
            if force {
                cmd.arg("--force");
            }
            let child = cmd
                .stdin(Stdio::null())
                .stdout(log)
                .stderr(err_log)
                .spawn()
                .map_err(|err| TileError::Io {
                    path: exe.to_path_buf(),
                    err,
                })?;
            running.push((t, child));
        }
        if running.is_empty() && waiting.is_empty() && queue.is_empty() {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
        let mut k = 0;
        while k < running.len() {
            let done = running[k].1.try_wait().map_err(|err| TileError::Io {
                path: exe.to_path_buf(),
                err,
            })?;
            let Some(exit) = done else {
                k += 1;
                continue;
            };
            let (t, _) = running.swap_remove(k);
            if exit.code() == Some(i32::from(crate::lock::EXIT_BUSY)) {
                // Another process took the tile between the look and the start: wait for it.
                waiting.push((t, false));
                continue;
            }
            let dir = Plan::tile_dir(plan_dir, t);
            let status = TileStatus::read(&dir).ok().flatten();
            match status {
                Some(s) if s.ok && exit.success() => ran.push(t.name.clone()),
                Some(s) => failed.push((
                    t.name.clone(),
                    s.error.unwrap_or_else(|| format!("exited with {exit}")),
                )),
                None => failed.push((
                    t.name.clone(),
                    format!(
                        "exited with {exit} and wrote no {STATUS} (see {})",
                        dir.join("log.txt").display()
                    ),
                )),
            }
            bar.inc(1);
        }
    }
    bar.finish();
    ran.sort();
    reused.sort();
    failed.sort();
    Ok(PlanRun {
        seconds: t0.elapsed().as_secs_f64(),
        jobs,
        ran,
        reused,
        failed,
    })
}
