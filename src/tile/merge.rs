//! `gs4city merge P --out M`: the tiles' labels as one run folder that `gs4city query --run M`
//! reads.
//!
//! * Entities: each building's hierarchy comes from the tile that owns it, appended tile by tile
//!   (`M/citymodel/semantics.json`); a tile's city label is mapped to the merged entity with the
//!   same object id (a neighbour in its margin maps to its owner's entity).
//! * Labels: city labels are the merged entity ids; the image labels (associated mask groups) of
//!   tile `t` become `Δ + offset_t + group`, `offset_t` the groups of the tiles before it
//!   (recorded in `M/summary.json`); groups of neighbouring tiles that are one object cut by a
//!   border are then joined into one instance, the smallest of their ids ([`super::join`]: the
//!   rule, `joins` in the summary); `M/fuse/labels.json`, and `label_features.npy` when every
//!   tile has features (a joined instance's are its first group's).
//! * Gaussians: each is labelled by the tile whose core holds it (`source.npy`), so
//!   `M/lift/gaussians.npy` and `semantic.ply` have one row per input Gaussian in input order.
//! * Test views (default): the plan's test views are rendered from the full scene into
//!   `M/render` (the contributions cache, so `query --views` works) and predicted from the merged
//!   labels (`M/lift/<stem>.class.npy`); with `gt/` they are evaluated into `M/eval` (simulation
//!   truth is read there only).
//!
//! A tile that failed or is missing is named, and the merge stops unless `allow_missing`: then
//! its core Gaussians stay −1 and the summary lists the holes.
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::exec::{TileStatus, disk_bytes, run_dir};
use super::{Plan, TileError};
use crate::labels::{Label, LabelTable, Source};
use crate::semantics::Entity;

/// Options of `gs4city merge`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MergeOptions {
    /// Merge what is there and list the holes instead of refusing a partial city.
    pub allow_missing: bool,
    /// Render and predict the plan's test views (and evaluate them with `gt/`).
    pub test_views: bool,
}

/// One tile in the merge.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TileMerge {
    pub tile: String,
    /// `merged`, `empty` (nothing to run: core Gaussians −1), `failed` or `missing`.
    pub state: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub why: Option<String>,
    /// Offset of its image labels: global id = Δ + offset + group.
    pub image_offset: i64,
    pub image_labels: usize,
    pub owned_entities: usize,
    pub core_gaussians: usize,
    pub seconds: Option<f64>,
    pub cpu_seconds: Option<f64>,
    pub peak_rss_mb: Option<f64>,
    pub disk_bytes: Option<u64>,
}

/// `M/summary.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MergeSummary {
    pub plan: PathBuf,
    pub scene: PathBuf,
    pub gaussians: usize,
    /// Gaussians with a label ≠ −1.
    pub labelled: usize,
    /// Gaussians in the cores of failed or missing tiles (−1).
    pub in_holes: usize,
    pub entities: usize,
    pub labels: usize,
    pub delta: i32,
    pub tiles: Vec<TileMerge>,
    /// Failed or missing tiles (merged with --allow-missing).
    pub holes: Vec<String>,
    /// Tiles' totals: CPU seconds, the largest peak memory and disk of one tile.
    pub tiles_cpu_seconds: f64,
    pub tile_peak_rss_mb_max: Option<f64>,
    pub tile_disk_bytes_max: u64,
    /// The merge's own time, peak memory and output size.
    pub seconds: f64,
    pub peak_rss_mb: Option<f64>,
    pub disk_bytes: u64,
    /// Test views predicted (and their dataset-level fine mIoU, paper-protocol fine mIoU with gt/).
    pub test_views: Vec<String>,
    pub fine_miou: Option<f64>,
    pub paper_fine_miou: Option<f64>,
    /// The fraction of the join rule ([`super::join::JOIN_FRACTION`]).
    #[serde(default)]
    pub join_fraction: f64,
    /// Image groups joined into a group of another tile (groups − instances they became).
    #[serde(default)]
    pub joined_groups: usize,
    /// The pairs of groups that met the join rule.
    #[serde(default)]
    pub joins: Vec<super::join::Join>,
}

impl crate::layout::Summary for MergeSummary {}

/// The contribution lists a tile's run used: the cache's keys of its `run.json` options
/// (`top_k`, `epsilon`, `t_stop`, `alpha_min`; absent keys as in a run.json before they existed).
fn tile_lists(run: &Path) -> Result<crate::cache::CacheOptions, TileError> {
    let path = run.join("run.json");
    let bad = |why: String| TileError::Invalid(format!("{}: {why}", path.display()));
    let rec: crate::layout::RunRecord = crate::fsutil::read_json(&path)?;
    let lists: crate::cache::CacheOptions =
        serde_json::from_value(rec.options).map_err(|e| bad(e.to_string()))?;
    lists.validate().map_err(|e| bad(e.to_string()))?;
    Ok(lists)
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TileError + '_ {
    move |err| TileError::Io {
        path: path.to_path_buf(),
        err,
    }
}

/// Merges the plan in `plan_dir` into the run folder `out` (replaced when it exists; built in
/// a sibling `.partial` folder and renamed when complete).
pub fn merge(plan_dir: &Path, out: &Path, opts: &MergeOptions) -> Result<MergeSummary, TileError> {
    let t0 = Instant::now();
    let plan = Plan::read(plan_dir)?;
    let scene = crate::scene::Scene::open(&plan.scene)?;
    let ply_bytes = std::fs::metadata(&scene.ply).map_err(io(&scene.ply))?.len();
    if ply_bytes != plan.ply_bytes {
        return Err(TileError::Invalid(format!(
            "{}: {ply_bytes} bytes, the plan was cut from {} bytes; the scene changed since `gs4city tile`",
            scene.ply.display(),
            plan.ply_bytes
        )));
    }

    // Which tiles can be merged.
    let mut rows = Vec::with_capacity(plan.tiles.len());
    let mut holes = Vec::new();
    let mut statuses = Vec::with_capacity(plan.tiles.len());
    for t in &plan.tiles {
        let dir = Plan::tile_dir(plan_dir, t);
        let mut row = TileMerge {
            tile: t.name.clone(),
            state: "merged".into(),
            why: None,
            image_offset: 0,
            image_labels: 0,
            owned_entities: 0,
            core_gaussians: t.core_gaussians,
            seconds: None,
            cpu_seconds: None,
            peak_rss_mb: None,
            disk_bytes: None,
        };
        let mut status = None;
        if !t.runnable {
            row.state = "empty".into();
            row.why = t.why_not.clone();
        } else if !dir.is_dir() {
            row.state = "missing".into();
            row.why = Some(format!("its folder {} is missing", dir.display()));
        } else {
            match TileStatus::read(&dir)? {
                None => {
                    row.state = "missing".into();
                    row.why = Some(format!(
                        "it has not run ({} has no {})",
                        dir.display(),
                        super::exec::STATUS
                    ));
                }
                Some(s) if !s.ok => {
                    row.state = "failed".into();
                    row.why = Some(s.error.clone().unwrap_or_else(|| "failed".into()));
                }
                Some(s) => match super::exec::check_outputs(&dir) {
                    Err(why) => {
                        row.state = "missing".into();
                        row.why = Some(why);
                    }
                    Ok(()) => {
                        row.seconds = Some(s.seconds);
                        row.cpu_seconds = s.cpu_seconds;
                        row.peak_rss_mb = s.peak_rss_mb;
                        row.disk_bytes = Some(s.disk_bytes);
                        status = Some(s);
                    }
                },
            }
        }
        if row.state == "failed" || row.state == "missing" {
            holes.push(format!(
                "tile {} {}: {}",
                t.name,
                row.state,
                row.why.as_deref().unwrap_or("")
            ));
        }
        statuses.push(status);
        rows.push(row);
    }
    if !holes.is_empty() && !opts.allow_missing {
        return Err(TileError::Invalid(format!(
            "{}: {} of {} tiles cannot be merged — {}; rerun them (`gs4city run-plan {}`) or pass --allow-missing to merge the rest and list the holes",
            plan_dir.display(),
            holes.len(),
            plan.tiles.len(),
            holes.join("; "),
            plan_dir.display()
        )));
    }

    // Global entities: owned buildings, tile by tile.
    struct TileRun {
        t: usize,
        entities: Vec<Entity>,
        labels: LabelTable,
        features: Option<(usize, Vec<f32>)>,
    }
    let mut runs = Vec::new();
    let mut global: Vec<Entity> = Vec::new();
    let mut by_object: HashMap<String, i32> = HashMap::new();
    let mut owner_row: Vec<(usize, usize)> = Vec::new(); // (run index, tile entity id)
    for (t, tp) in plan.tiles.iter().enumerate() {
        if statuses[t].is_none() {
            continue;
        }
        let rd = run_dir(&Plan::tile_dir(plan_dir, tp));
        let entities = crate::semantics::read(&crate::layout::semantics_file(&rd))?;
        let fuse = rd.join("fuse/labels.json");
        let labels = if fuse.is_file() {
            LabelTable::read(&fuse)?
        } else {
            LabelTable::city(&entities, &crate::classes::table(&entities))?
        };
        let fpath = rd.join("fuse/label_features.npy");
        let features = if fpath.is_file() {
            let (shape, data) = crate::npy::read::<f32>(&fpath)?;
            match shape[..] {
                [l, d] if l == labels.labels.len() => Some((d, data)),
                _ => {
                    return Err(TileError::Invalid(format!(
                        "{}: shape {shape:?}, expected one row per label of {}",
                        fpath.display(),
                        fuse.display()
                    )));
                }
            }
        } else {
            None
        };
        let owned: std::collections::HashSet<&str> = tp.owned.iter().map(String::as_str).collect();
        let mut map: HashMap<i32, i32> = HashMap::new();
        let ri = runs.len();
        for e in &entities {
            let root = &entities[e.building as usize].object_id;
            if !owned.contains(root.as_str()) {
                continue;
            }
            let id = global.len() as i32;
            map.insert(e.id, id);
            let mut g = e.clone();
            g.id = id;
            g.parent = e.parent.map(|p| map[&p]);
            g.building = map[&e.building];
            by_object.insert(e.object_id.clone(), id);
            owner_row.push((ri, e.id as usize));
            global.push(g);
            rows[t].owned_entities += 1;
        }
        runs.push(TileRun {
            t,
            entities,
            labels,
            features,
        });
    }
    let delta = crate::labels::delta_for(global.len())?;
    let classes = crate::classes::table(&global);
    let mut table: Vec<Label> = LabelTable::city(&global, &classes)?.labels;
    let mut offset: i64 = 0;
    // Tile label id → global label id, per run.
    let mut maps: Vec<HashMap<i32, i32>> = Vec::with_capacity(runs.len());
    for r in &runs {
        let mut m = HashMap::new();
        let mut groups = 0usize;
        for l in &r.labels.labels {
            let g = match l.source {
                Source::City => r
                    .entities
                    .get(l.id as usize)
                    .and_then(|e| by_object.get(&e.object_id).copied())
                    .unwrap_or(-1),
                Source::Image => {
                    let group = i64::from(l.id - r.labels.delta);
                    let id = i64::from(delta) + offset + group;
                    let id = i32::try_from(id).map_err(|_| {
                        TileError::Invalid(format!(
                            "label ids overflow int32 at tile {} (Δ {delta} + offset {offset} + group {group})",
                            plan.tiles[r.t].name
                        ))
                    })?;
                    table.push(Label {
                        id,
                        source: Source::Image,
                        entity: None,
                        group: Some(id - delta),
                        class: l.class,
                        level: None,
                    });
                    groups = groups.max(group as usize + 1);
                    id
                }
            };
            m.insert(l.id, g);
        }
        rows[r.t].image_offset = offset;
        rows[r.t].image_labels = groups;
        offset += groups as i64;
        maps.push(m);
    }
    // Objects cut by a border: groups of neighbouring tiles joined into one instance.
    let joined = {
        // Only image labels take part: a tile's city labels map to merged entities.
        let image: Vec<HashMap<i32, i32>> = runs
            .iter()
            .zip(&maps)
            .map(|(r, m)| {
                m.iter()
                    .filter(|&(&l, _)| l >= r.labels.delta)
                    .map(|(&l, &g)| (l, g))
                    .collect()
            })
            .collect();
        let tiles: Vec<super::join::TileLabels> = runs
            .iter()
            .zip(&image)
            .map(|(r, m)| {
                let tdir = Plan::tile_dir(plan_dir, &plan.tiles[r.t]);
                let rd = run_dir(&tdir);
                let mode = crate::layout::Mode::default_for(&rd);
                super::join::TileLabels {
                    tile: r.t as u32,
                    source: tdir.join("source.npy"),
                    gaussians: rd.join(mode.dir()).join("gaussians.npy"),
                    image_ids: m,
                }
            })
            .collect();
        let class: HashMap<i32, i32> = table
            .iter()
            .filter(|l| l.source == Source::Image)
            .map(|l| (l.id, l.class))
            .collect();
        let sightings = super::join::sightings(plan.gaussians, &tiles)?;
        super::join::join(
            sightings,
            |id| class.get(&id).copied().unwrap_or(-1),
            super::join::JOIN_FRACTION,
        )
    };
    table.retain(|l| !joined.root.contains_key(&l.id));
    let labels = LabelTable::new(delta, table).map_err(|why| {
        TileError::Invalid(format!("the merged label table is inconsistent: {why}"))
    })?;

    // Per-Gaussian labels from each tile's core.
    let n = plan.gaussians;
    let (mut label, mut class) = (vec![-1i32; n], vec![-1i32; n]);
    let mut owner = vec![false; n];
    for (ri, r) in runs.iter().enumerate() {
        let tp = &plan.tiles[r.t];
        let tdir = Plan::tile_dir(plan_dir, tp);
        let spath = tdir.join("source.npy");
        let (sshape, source) = crate::npy::read::<i64>(&spath)?;
        let mode = crate::layout::Mode::default_for(&run_dir(&tdir));
        let gpath = run_dir(&tdir).join(mode.dir()).join("gaussians.npy");
        let (gshape, gl) = crate::npy::read::<i32>(&gpath)?;
        if sshape.len() != 2 || gshape.len() != 2 || sshape[0] != gshape[0] {
            return Err(TileError::Invalid(format!(
                "tile {}: {} has shape {sshape:?} but {} has {gshape:?}; the tile's run is not of its cut PLY",
                tp.name,
                spath.display(),
                gpath.display()
            )));
        }
        for (s, g) in source.chunks_exact(2).zip(gl.chunks_exact(2)) {
            if s[1] == 0 {
                continue;
            }
            let i = usize::try_from(s[0])
                .ok()
                .filter(|&i| i < n)
                .ok_or_else(|| {
                    TileError::Invalid(format!(
                        "{}: index {} is outside the scene's {n} Gaussians",
                        spath.display(),
                        s[0]
                    ))
                })?;
            if owner[i] {
                return Err(TileError::Invalid(format!(
                    "{}: Gaussian {i} lies in two tiles' cores; the plan is damaged",
                    spath.display()
                )));
            }
            owner[i] = true;
            label[i] = if g[0] < 0 {
                -1
            } else {
                maps[ri].get(&g[0]).map_or(-1, |&m| joined.id(m))
            };
            class[i] = g[1];
        }
    }
    let labelled = label.iter().filter(|&&l| l >= 0).count();
    let in_holes: usize = rows
        .iter()
        .filter(|r| r.state == "failed" || r.state == "missing")
        .map(|r| r.core_gaussians)
        .sum();

    // The run folder.
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "merged".into());
    let partial = out.with_file_name(format!(".{name}.partial"));
    // One merge into `out` at a time, and none while a command reads it.
    let mut lock = crate::lock::FolderLock::exclusive(out)?;
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(io(&partial))?;
    }
    let (cm, fuse, lift) = (
        partial.join("citymodel"),
        partial.join("fuse"),
        partial.join("lift"),
    );
    for d in [&cm, &fuse, &lift] {
        crate::fsutil::create_dir(d)?;
    }
    crate::semantics::write(&cm.join("semantics.json"), &global)?;
    labels.write(&fuse.join("labels.json"))?;
    let dims: Vec<Option<usize>> = runs
        .iter()
        .map(|r| r.features.as_ref().map(|f| f.0))
        .collect();
    if let Some(Some(d)) = dims.first().copied() {
        if !runs.is_empty() && dims.iter().all(|x| *x == Some(d)) {
            let mut feats = vec![0f32; labels.labels.len() * d];
            for (gid, &(ri, te)) in owner_row.iter().enumerate() {
                let (_, data) = runs[ri].features.as_ref().expect("all tiles have features");
                if let Some(trow) = runs[ri].labels.row(te as i32) {
                    feats[gid * d..(gid + 1) * d].copy_from_slice(&data[trow * d..(trow + 1) * d]);
                }
            }
            for (ri, r) in runs.iter().enumerate() {
                let (_, data) = r.features.as_ref().expect("all tiles have features");
                for (trow, l) in r.labels.labels.iter().enumerate() {
                    // A joined instance keeps the features of its first group.
                    if l.source == Source::Image && !joined.root.contains_key(&maps[ri][&l.id]) {
                        let g = labels.row(maps[ri][&l.id]).expect("merged image label");
                        feats[g * d..(g + 1) * d].copy_from_slice(&data[trow * d..(trow + 1) * d]);
                    }
                }
            }
            crate::npy::write(
                &fuse.join("label_features.npy"),
                &[labels.labels.len(), d],
                &feats,
            )?;
        }
    }
    let gl = crate::prediction::GaussianLabels {
        label: &label,
        class: &class,
        extra: Vec::new(),
    };
    crate::prediction::write_gaussians(&scene.ply, &lift, &gl, &labels, &global)?;

    let mut test_views = Vec::new();
    let (mut fine, mut paper) = (None, None);
    if opts.test_views && !plan.test_views.is_empty() {
        let views: Vec<crate::camera::View> = crate::colmap::read_model(&scene.sparse)?
            .into_iter()
            .filter(|v| plan.test_views.contains(&v.name))
            .collect();
        let (mut g, _) = crate::splat::read_ply(&scene.ply, &crate::splat::ReadOptions::KEEP)?;
        crate::splat::ply::hide_invalid(&mut g);
        let prepared = crate::render::PreparedScene::new(&g)?;
        drop(g);
        let render = partial.join("render");
        // The lists the tiles' runs used, so that the test views are predicted as those runs
        // predict theirs (the cache's defaults when no tile was merged).
        let lists = match runs.first() {
            Some(r) => tile_lists(&run_dir(&Plan::tile_dir(plan_dir, &plan.tiles[r.t])))?,
            None => crate::cache::CacheOptions::default(),
        };
        crate::render::cache::build(&prepared, &views, &lists, &render)?;
        drop(prepared);
        let cache = crate::cache::Cache::open(&render)?;
        for v in &views {
            let stem = v.stem();
            let c = cache.load(&stem)?;
            let (cmap, lmap) = crate::cache::predict(&c, &label, &class);
            let k = &v.camera.intrinsics;
            crate::prediction::write_prediction(
                &lift,
                &stem,
                k.width as usize,
                k.height as usize,
                &cmap,
                &lmap,
            )?;
            test_views.push(stem);
        }
        if let Some(gt) = &scene.gt {
            let (s, _) = crate::eval::run_for(
                &lift,
                gt,
                &partial.join("eval"),
                Some(&test_views),
                Some("vote"),
            )?;
            fine = s.dataset.get("miou").copied().flatten();
            paper = s.paper.get("miou").copied().flatten();
        }
    }
    let record = serde_json::json!({
        "program": "gs4city",
        "version": env!("CARGO_PKG_VERSION"),
        "scene": plan.scene,
        "options": {"merge": opts, "plan": plan_dir.canonicalize().map_err(io(plan_dir))?},
        "stages": {},
    });
    crate::fsutil::write_json(&partial.join("run.json"), &record)?;

    let ok = || statuses.iter().flatten();
    let mut summary = MergeSummary {
        plan: plan_dir.to_path_buf(),
        scene: plan.scene.clone(),
        gaussians: n,
        labelled,
        in_holes,
        entities: global.len(),
        labels: labels.labels.len(),
        delta,
        tiles: rows,
        holes,
        tiles_cpu_seconds: ok().filter_map(|s| s.cpu_seconds).sum(),
        tile_peak_rss_mb_max: ok().filter_map(|s| s.peak_rss_mb).reduce(f64::max),
        tile_disk_bytes_max: ok().map(|s| s.disk_bytes).max().unwrap_or(0),
        seconds: 0.0,
        peak_rss_mb: None,
        disk_bytes: 0,
        test_views,
        fine_miou: fine,
        paper_fine_miou: paper,
        join_fraction: super::join::JOIN_FRACTION,
        joined_groups: joined.root.len(),
        joins: joined.joins,
    };
    summary.seconds = t0.elapsed().as_secs_f64();
    summary.peak_rss_mb = crate::progress::peak_rss_mb();
    summary.disk_bytes = disk_bytes(&partial);
    crate::layout::Summary::write(&summary, &partial)?;
    lock.replace_folder(out, &partial)?;
    crate::progress::done(
        "merge",
        &format!(
            "{} tiles, {labelled} of {n} Gaussians labelled",
            summary.tiles.len()
        ),
        summary.seconds,
    );
    Ok(summary)
}
