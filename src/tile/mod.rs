//! City scale (an orchestrator): a scene folder as a plan of tiles that run anywhere and merge
//! into one semantic scene — `gs4city tile`, `gs4city run-plan`, `gs4city merge`; docs/tile.md.
//!
//! The plan lives in the georeferenced ground plane of the city model (its CRS's x, y): a grid of
//! `size` × `size` m cores over the footprint centres of the buildings (the outer tiles' cores
//! reach to infinity outward, so every Gaussian has one core). A tile owns the buildings whose
//! footprint centre lies in its core; it gets
//! * the Gaussians within `margin` of its core (one streaming pass, [`cut`]) and their original
//!   indices (`source.npy`);
//! * the CityGML objects it owns plus the neighbours whose footprint box reaches into core +
//!   margin (so occlusion stays right; [`gml`]);
//! * the views (minus the plan's test views) in which its owned buildings or its core Gaussians
//!   project into the image, in front of the camera and not hidden behind the box of a building
//!   near the tile (a coarse visibility test), and of which the tile takes a share of the screen
//!   ([`TileOptions::min_share`]: a view that only glimpses a tile far behind another does not
//!   join it; each tile keeps its [`TileOptions::min_views`] best views);
//! * links to their images, SAM lists and features (never copies).
//!
//! Each tile is a scene folder `P/tiles/<name>/scene`, run with `gs4city run --test-every 0`
//! (the plan's test views are held back from every tile). [`exec`] runs one tile and records
//! its cost; [`merge`] joins the tiles' labels into one run folder (and, by [`join`], the groups
//! of neighbouring tiles that are one object cut by a border); [`slurm`] writes the batch
//! scripts.
pub mod crop;
pub mod cut;
pub mod exec;
pub mod gml;
pub mod join;
pub mod merge;
pub mod slurm;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::alignment::Alignment;
use crate::camera::View;
use crate::scene::{Scene, Split};

/// Errors of tiling, running and merging a plan; each names the file or tile at fault.
#[derive(Debug, thiserror::Error)]
pub enum TileError {
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error("{path}: {err}")]
    Io { path: PathBuf, err: std::io::Error },
    #[error(transparent)]
    Fs(#[from] crate::fsutil::FsError),
    #[error(transparent)]
    Ply(#[from] crate::ply::PlyError),
    #[error(transparent)]
    Splat(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Colmap(#[from] crate::colmap::ColmapError),
    #[error(transparent)]
    CityGml(#[from] crate::citygml::CityGmlError),
    #[error(transparent)]
    Alignment(#[from] crate::alignment::AlignError),
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    #[error(transparent)]
    Npy(#[from] crate::npy::NpyError),
    #[error(transparent)]
    Labels(#[from] crate::labels::LabelsError),
    #[error(transparent)]
    Semantics(#[from] crate::semantics::SemanticsError),
    #[error(transparent)]
    Render(#[from] crate::render::RenderError),
    #[error(transparent)]
    Cache(#[from] crate::cache::CacheError),
    #[error(transparent)]
    Prediction(#[from] crate::prediction::PredictionError),
    #[error(transparent)]
    Eval(#[from] crate::eval::EvalError),
    #[error(transparent)]
    Lock(#[from] crate::lock::LockError),
    #[error(transparent)]
    Sam(#[from] crate::sam::SamError),
    #[error(transparent)]
    Image(#[from] crate::imageio::ImageError),
}

/// The file that describes a plan.
pub const PLAN: &str = "plan.json";

/// Options of `gs4city tile`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileOptions {
    /// Side of a tile's core in metres (the city model's ground plane).
    pub size_m: f64,
    /// Margin around the core in metres: Gaussians and neighbouring buildings within it join
    /// the tile.
    pub margin_m: f64,
    /// Every `test_every`-th view by name is a test view of the whole plan, held back from every
    /// tile (as `gs4city run`; 0 = none). `None`: the test views the scene declares
    /// (`scene.json`; none: every view trains).
    #[serde(default)]
    pub test_every: Option<usize>,
    /// Opaque core Gaussians per tile sampled for the view test.
    pub sample: usize,
    /// Sample points that must be visible for a view to join a tile.
    pub min_visible: usize,
    /// Share of a view's screen (cells of a coarse grid won by the nearest visible sample point)
    /// a tile must take for the view to join it; 0 = every view that sees `min_visible` points
    /// (the default: on the street every smaller view set cost accuracy, BENCHMARKS.md).
    #[serde(default)]
    pub min_share: f64,
    /// Views a tile keeps whatever their share (its best by screen cells won), when that many
    /// see it.
    #[serde(default)]
    pub min_views: usize,
    /// A view joins a tile cropped to the window of its image where the tile shows (the
    /// screen cells the tile wins, [`CROP_PAD_CELLS`] cells around them) when that window is
    /// smaller than this share of the image ([`crop`]); 0 = every view whole (the default:
    /// 0.3 keeps the street's accuracy and cuts the CPU time, but the time still grows faster
    /// than the city, BENCHMARKS.md "Tiles").
    #[serde(default)]
    pub crop_below: f64,
    /// Options of each tile's `gs4city run` (its command-line words; `--test-every 0` is added).
    #[serde(default)]
    pub run_args: Vec<String>,
}

impl Default for TileOptions {
    fn default() -> Self {
        TileOptions {
            size_m: 150.0,
            margin_m: 25.0,
            test_every: None,
            sample: 2048,
            min_visible: 3,
            min_share: 0.0,
            min_views: 8,
            crop_below: 0.0,
            run_args: Vec::new(),
        }
    }
}

impl TileOptions {
    /// Checks the ranges (one line naming the option).
    pub fn validate(&self) -> Result<(), TileError> {
        use crate::check::{End, range};
        range("size", self.size_m, End::Closed(1.0), End::Closed(1e6))?;
        range("margin", self.margin_m, End::Closed(0.0), End::Closed(1e6))?;
        range(
            "sample",
            self.sample as f64,
            End::Closed(16.0),
            End::Closed(1e7),
        )?;
        range(
            "min-share",
            self.min_share,
            End::Closed(0.0),
            End::Closed(1.0),
        )?;
        range(
            "crop-below",
            self.crop_below,
            End::Closed(0.0),
            End::Closed(1.0),
        )?;
        Ok(())
    }
}

/// The tile grid in the ground plane: cores `[ox + i·size, ox + (i+1)·size)` in x (and y), the
/// outer ones open outward.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    pub origin: [f64; 2],
    pub size: f64,
    pub margin: f64,
    pub nx: usize,
    pub ny: usize,
}

impl Grid {
    fn cell(v: f64, o: f64, size: f64, n: usize) -> usize {
        let c = ((v - o) / size).floor();
        if c.is_nan() || c < 0.0 {
            0
        } else {
            (c as usize).min(n - 1)
        }
    }

    /// The tile (row-major, `iy · nx + ix`) whose core holds ground point `(x, y)`; a point with
    /// a non-finite coordinate belongs to tile 0.
    pub fn core_of(&self, x: f64, y: f64) -> usize {
        let ix = Grid::cell(x, self.origin[0], self.size, self.nx);
        let iy = Grid::cell(y, self.origin[1], self.size, self.ny);
        iy * self.nx + ix
    }

    /// The core `[x0, y0, x1, y1]` of tile `t`, infinite where it is open.
    pub fn core(&self, t: usize) -> [f64; 4] {
        let (ix, iy) = (t % self.nx, t / self.nx);
        let lo = |i: usize, o: f64| {
            if i == 0 {
                f64::NEG_INFINITY
            } else {
                o + i as f64 * self.size
            }
        };
        let hi = |i: usize, o: f64, n: usize| {
            if i + 1 == n {
                f64::INFINITY
            } else {
                o + (i + 1) as f64 * self.size
            }
        };
        [
            lo(ix, self.origin[0]),
            lo(iy, self.origin[1]),
            hi(ix, self.origin[0], self.nx),
            hi(iy, self.origin[1], self.ny),
        ]
    }

    /// Every tile whose core + margin holds `(x, y)` (its core tile among them), ascending.
    pub fn tiles_within(&self, x: f64, y: f64, out: &mut Vec<usize>) {
        let core = self.core_of(x, y);
        if !(x.is_finite() && y.is_finite()) {
            out.push(core);
            return;
        }
        let (cx, cy) = (core % self.nx, core / self.nx);
        let reach = (self.margin / self.size).ceil() as usize + 1;
        for iy in cy.saturating_sub(reach)..(cy + reach + 1).min(self.ny) {
            for ix in cx.saturating_sub(reach)..(cx + reach + 1).min(self.nx) {
                let t = iy * self.nx + ix;
                let c = self.core(t);
                let dx = (c[0] - x).max(x - c[2]).max(0.0);
                let dy = (c[1] - y).max(y - c[3]).max(0.0);
                if t == core || (dx <= self.margin && dy <= self.margin) {
                    out.push(t);
                }
            }
        }
    }

    /// Whether a ground box `[x0, y0, x1, y1]` reaches into tile `t`'s core + margin.
    pub fn box_reaches(&self, t: usize, b: [f64; 4]) -> bool {
        let c = self.core(t);
        b[2] >= c[0] - self.margin
            && b[0] <= c[2] + self.margin
            && b[3] >= c[1] - self.margin
            && b[1] <= c[3] + self.margin
    }
}

/// What a tile's job asks a scheduler for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Resources {
    pub cpus: usize,
    pub mem_mb: u64,
    pub time_min: u64,
}

/// One tile of a plan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TilePlan {
    pub index: usize,
    /// `t<iy>_<ix>`: its folder under `P/tiles/`.
    pub name: String,
    pub ix: usize,
    pub iy: usize,
    /// The core `[x0, y0, x1, y1]` in the ground plane (`null` = open).
    pub core: [Option<f64>; 4],
    /// Object ids of the buildings it owns.
    pub owned: Vec<String>,
    /// Object ids of the neighbours inside its margin.
    pub neighbours: Vec<String>,
    pub gaussians: usize,
    pub core_gaussians: usize,
    pub views: usize,
    /// Views that see the tile but take less than `min_share` of their screen there (left out).
    #[serde(default)]
    pub views_glimpsing: usize,
    /// Views that join it cropped to the window where it shows ([`TileOptions::crop_below`]).
    #[serde(default)]
    pub views_cropped: usize,
    /// Whether the tile has a scene to run (buildings and views); the core Gaussians of a tile
    /// that has none are labelled −1 by the merge.
    pub runnable: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub why_not: Option<String>,
    pub resources: Resources,
}

/// `plan.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Plan {
    pub program: String,
    pub version: String,
    /// The scene folder (canonical).
    pub scene: PathBuf,
    pub options: TileOptions,
    pub grid: Grid,
    /// Gaussians of the scene's PLY (one row per Gaussian in the merged `semantic.ply`).
    pub gaussians: usize,
    /// Size of the scene's PLY in bytes (the merge checks it is the same file).
    pub ply_bytes: u64,
    /// The plan's test views (image names), held back from every tile.
    pub test_views: Vec<String>,
    /// The `gs4city` binary that wrote the plan (the batch scripts run it unless `GS4CITY` is set).
    pub exe: Option<PathBuf>,
    pub tiles: Vec<TilePlan>,
    /// Seconds and peak memory (MB) of the planning and the cut.
    pub seconds: f64,
    pub peak_rss_mb: Option<f64>,
    /// Objects renamed because another file of the city model uses their id (`id~n`, as
    /// `gs4city run` names them), one line each naming both files.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

impl Plan {
    /// Reads `P/plan.json` (one clear line when `P` is no plan).
    pub fn read(plan_dir: &Path) -> Result<Plan, TileError> {
        let p = plan_dir.join(PLAN);
        if !p.is_file() {
            return Err(TileError::Invalid(format!(
                "{}: missing; {} is not a tile plan (make one with `gs4city tile --scene S --out {}`)",
                p.display(),
                plan_dir.display(),
                plan_dir.display()
            )));
        }
        Ok(crate::fsutil::read_json(&p)?)
    }

    /// The folder of tile `t`.
    pub fn tile_dir(plan_dir: &Path, t: &TilePlan) -> PathBuf {
        plan_dir.join("tiles").join(&t.name)
    }
}

/// The resources of a tile job, from the street's 60 m tiles (BENCHMARKS.md, "Tiles": peak
/// 334 MB at 107 k Gaussians / 48 views to 505 MB at 535 k / 83 views, 13–52 CPU s): memory
/// 512 MB + 0.6 kB per Gaussian + 2 MB per view, doubled for safety and rounded up to 512 MB;
/// time 10 min + 2 min per 10⁵ Gaussians × 100 views.
pub fn resources(gaussians: usize, views: usize) -> Resources {
    let mb = 512.0 + 0.6e-3 * gaussians as f64 + 2.0 * views as f64;
    let mem_mb = ((2.0 * mb / 512.0).ceil() * 512.0) as u64;
    let minutes = 10.0 + 2.0 * (gaussians as f64 / 1e5) * (views as f64 / 100.0);
    Resources {
        cpus: 2,
        mem_mb,
        time_min: minutes.ceil() as u64,
    }
}

/// The points of `points` that view `v` sees: projected inside the image, in front of the
/// camera, and with no occluder box (scene frame, other than one containing the point) on the
/// segment from the camera. `f` gets each one's pixel and depth and returns whether to go on.
fn visible(
    v: &View,
    points: &[DVec3],
    occluders: &[(DVec3, DVec3)],
    mut f: impl FnMut([f64; 2], f64) -> bool,
) {
    let k = &v.camera.intrinsics;
    let eye = v.camera.pose.center();
    // A box that holds the camera (a street between the wings of one building's box) hides
    // nothing: the test is too coarse to tell inside from outside there.
    let pad = DVec3::splat(0.25);
    let occluders: Vec<(DVec3, DVec3)> = occluders
        .iter()
        .copied()
        .filter(|&(lo, hi)| !(eye.cmpge(lo - pad).all() && eye.cmple(hi + pad).all()))
        .collect();
    for &p in points {
        let pc = v.camera.pose.world_to_camera(p);
        let Some(px) = v.camera.project(pc) else {
            continue;
        };
        if !(px.x >= 0.0 && px.y >= 0.0 && px.x < f64::from(k.width) && px.y < f64::from(k.height))
        {
            continue;
        }
        let hidden = occluders.iter().any(|&(lo, hi)| {
            let inside = p.cmpge(lo - pad).all() && p.cmple(hi + pad).all();
            !inside && segment_hits_box(eye, p, lo, hi)
        });
        if !hidden && !f([px.x, px.y], pc.z) {
            return;
        }
    }
}

/// Whether view `v` sees at least `need` of `points` ([`visible`]).
fn sees(v: &View, points: &[DVec3], occluders: &[(DVec3, DVec3)], need: usize) -> bool {
    let mut seen = 0;
    visible(v, points, occluders, |_, _| {
        seen += 1;
        seen < need
    });
    seen >= need
}

/// Cells per image row of the coarse screen grid of the share test.
const SHARE_CELLS_X: usize = 32;

/// Cells of the screen grid added on each side of the cells a tile wins to make the window a
/// view is cropped to ([`TileOptions::crop_below`]): room for an object of the tile that
/// reaches past its sample points.
pub const CROP_PAD_CELLS: usize = 1;

/// What a tile needs for the view test: its sample points and the boxes that may hide them.
struct TileSight {
    points: Vec<DVec3>,
    occluders: Vec<(DVec3, DVec3)>,
}

/// What one view shows of one candidate tile on the coarse screen grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Shown {
    /// Cells the tile wins (its share of the view).
    won: usize,
    /// The box `[cx0, cy0, cx1, cy1]` (inclusive) of the cells it wins, or, when it wins
    /// none, of the cells its visible sample points fall in.
    cells: [usize; 4],
}

/// Per tile of `cands` (indices into `sights`), the cells of a coarse screen grid of view `v`
/// (32 across, square) whose nearest visible sample point belongs to that tile — the tile's
/// share of what the view shows — and the box of those cells. Ties go to the first tile of
/// `cands`.
fn screen_cells(v: &View, cands: &[usize], sights: &[TileSight]) -> Vec<Shown> {
    let k = &v.camera.intrinsics;
    let cell = f64::from(k.width) / SHARE_CELLS_X as f64;
    let rows = ((f64::from(k.height) / cell).ceil() as usize).max(1);
    let mut nearest = vec![(f64::INFINITY, usize::MAX); SHARE_CELLS_X * rows];
    let empty = [usize::MAX, usize::MAX, 0, 0];
    let grow = |b: &mut [usize; 4], cx: usize, cy: usize| {
        *b = [b[0].min(cx), b[1].min(cy), b[2].max(cx), b[3].max(cy)];
    };
    let mut seen = vec![empty; cands.len()];
    for (ci, &t) in cands.iter().enumerate() {
        visible(v, &sights[t].points, &sights[t].occluders, |px, depth| {
            let cx = ((px[0] / cell) as usize).min(SHARE_CELLS_X - 1);
            let cy = ((px[1] / cell) as usize).min(rows - 1);
            grow(&mut seen[ci], cx, cy);
            let c = &mut nearest[cy * SHARE_CELLS_X + cx];
            if depth < c.0 {
                *c = (depth, ci);
            }
            true
        });
    }
    let mut out: Vec<Shown> = vec![
        Shown {
            won: 0,
            cells: empty
        };
        cands.len()
    ];
    for (i, &(_, ci)) in nearest.iter().enumerate() {
        if ci != usize::MAX {
            out[ci].won += 1;
            grow(&mut out[ci].cells, i % SHARE_CELLS_X, i / SHARE_CELLS_X);
        }
    }
    for (o, s) in out.iter_mut().zip(seen) {
        if o.won == 0 {
            o.cells = s;
        }
    }
    out
}

/// The window a view is cropped to for a tile it shows in `cells` ([`Shown::cells`]): those
/// cells and [`CROP_PAD_CELLS`] around them, in pixels, clipped to the image; `None` (the whole
/// view) when the window is not smaller than `crop_below` of the image.
fn crop_window(v: &View, cells: [usize; 4], crop_below: f64) -> Option<crop::Window> {
    let k = &v.camera.intrinsics;
    if cells[0] > cells[2] || cells[1] > cells[3] {
        return None;
    }
    let cell = f64::from(k.width) / SHARE_CELLS_X as f64;
    let px = |c: usize, lim: u32| ((c as f64 * cell).floor() as u32).min(lim);
    let p = CROP_PAD_CELLS;
    let w = crop::Window {
        x0: px(cells[0].saturating_sub(p), k.width),
        y0: px(cells[1].saturating_sub(p), k.height),
        x1: px(cells[2] + 1 + p, k.width),
        y1: px(cells[3] + 1 + p, k.height),
    };
    let full = u64::from(k.width) * u64::from(k.height);
    (w.x1 > w.x0 && w.y1 > w.y0 && (w.area() as f64) < crop_below * full as f64).then_some(w)
}

/// The training views of each tile, as indices into `views` (ascending) with the window each
/// joins through (`None`: the whole view; [`crop_window`]), and per tile the number of views
/// left out as glimpsing. A view joins each tile of which it sees `min_visible` sample points
/// and that takes at least `min_share` of its screen cells ([`screen_cells`]); a tile that gets
/// fewer than `min_views` so takes its best remaining views (most cells won).
#[allow(clippy::type_complexity)]
fn assign_views(
    views: &[View],
    sights: &[TileSight],
    opts: &TileOptions,
) -> (Vec<Vec<(usize, Option<crop::Window>)>>, Vec<usize>) {
    use rayon::prelude::*;
    let n_tiles = sights.len();
    let bar = crate::progress::Bar::new("tile: views", views.len() as u64, "views");
    let per_view: Vec<Vec<(usize, Shown)>> = views
        .par_iter()
        .map(|v| {
            let cands: Vec<usize> = (0..n_tiles)
                .filter(|&t| {
                    !sights[t].points.is_empty()
                        && sees(v, &sights[t].points, &sights[t].occluders, opts.min_visible)
                })
                .collect();
            let shown = screen_cells(v, &cands, sights);
            bar.inc(1);
            cands.into_iter().zip(shown).collect()
        })
        .collect();
    bar.finish();
    let mut chosen = vec![Vec::new(); n_tiles];
    let mut glimpsing = vec![0; n_tiles];
    let mut rest: Vec<Vec<(usize, usize, [usize; 4])>> = vec![Vec::new(); n_tiles];
    for (vi, seen) in per_view.iter().enumerate() {
        let total: usize = seen.iter().map(|&(_, s)| s.won).sum();
        for &(t, s) in seen {
            let share = if total == 0 {
                0.0
            } else {
                s.won as f64 / total as f64
            };
            if share >= opts.min_share {
                chosen[t].push((vi, s.cells));
            } else {
                rest[t].push((s.won, vi, s.cells));
            }
        }
    }
    let mut out = vec![Vec::new(); n_tiles];
    for t in 0..n_tiles {
        rest[t].sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        let need = opts.min_views.saturating_sub(chosen[t].len());
        let extra: Vec<(usize, [usize; 4])> = rest[t]
            .iter()
            .take(need)
            .map(|&(_, vi, c)| (vi, c))
            .collect();
        glimpsing[t] = rest[t].len() - extra.len();
        chosen[t].extend(extra);
        chosen[t].sort_unstable_by_key(|&(vi, _)| vi);
        out[t] = chosen[t]
            .iter()
            .map(|&(vi, c)| (vi, crop_window(&views[vi], c, opts.crop_below)))
            .collect();
    }
    (out, glimpsing)
}

/// Slab test of segment `a → b` against box `[lo, hi]`.
fn segment_hits_box(a: DVec3, b: DVec3, lo: DVec3, hi: DVec3) -> bool {
    let d = b - a;
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for k in 0..3 {
        if d[k].abs() < 1e-12 {
            if a[k] < lo[k] || a[k] > hi[k] {
                return false;
            }
            continue;
        }
        let (mut u, mut w) = ((lo[k] - a[k]) / d[k], (hi[k] - a[k]) / d[k]);
        if u > w {
            std::mem::swap(&mut u, &mut w);
        }
        t0 = t0.max(u);
        t1 = t1.min(w);
        if t0 > t1 {
            return false;
        }
    }
    true
}

/// Most tiles a plan may hold (100,000 tiles of 150 m cover 2,250 km²).
pub const MAX_TILES: usize = 100_000;

/// The error of a grid of more than [`MAX_TILES`] tiles: the extent, and the footprint farthest
/// from the footprints' median centre (the usual cause: one building in another CRS).
fn too_many_tiles(
    feet: &[gml::Footprint],
    files: &[PathBuf],
    n: [f64; 2],
    [lo, hi]: [[f64; 2]; 2],
    size: f64,
) -> TileError {
    let median = |k: usize| {
        let mut v: Vec<f64> = feet.iter().map(|f| f.centre[k]).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let m = [median(0), median(1)];
    let dist = |f: &gml::Footprint| (f.centre[0] - m[0]).hypot(f.centre[1] - m[1]);
    let far = feet
        .iter()
        .max_by(|a, b| dist(a).total_cmp(&dist(b)))
        .expect("footprints checked non-empty");
    let file = files
        .get(far.file)
        .map(|p| p.display().to_string())
        .unwrap_or_default();
    TileError::Invalid(format!(
        "the city model's footprints span {:.0} × {:.0} m: {:.0} × {:.0} tiles of {size} m, more than \
         {MAX_TILES}; the footprint farthest from the others is {} in {file}, {:.0} m from their \
         median centre (a building in another CRS?): remove it, or choose a larger --size",
        hi[0] - lo[0],
        hi[1] - lo[1],
        n[0],
        n[1],
        far.id,
        dist(far),
    ))
}

/// Writes the tile plan of scene `scene_dir` into `out` (which must not exist): one scene folder
/// per tile, `plan.json`, and the Slurm batch scripts. Built in `out.partial` and renamed, so a
/// failed plan leaves nothing that looks done. `exe` is the `gs4city` binary the batch
/// scripts run.
pub fn plan(
    scene_dir: &Path,
    out: &Path,
    opts: &TileOptions,
    exe: Option<&Path>,
) -> Result<Plan, TileError> {
    let t0 = Instant::now();
    opts.validate()?;
    let scene_dir = scene_dir.canonicalize().map_err(|err| TileError::Io {
        path: scene_dir.to_path_buf(),
        err,
    })?;
    if out.exists() {
        return Err(TileError::Invalid(format!(
            "{}: exists; a plan is written into a new folder (remove it or choose another --out)",
            out.display()
        )));
    }
    let scene = Scene::open(&scene_dir)?;
    let Some(al_path) = &scene.alignment else {
        return Err(TileError::Invalid(format!(
            "{}: no citymodel/alignment.json; tiles are laid out in the city model's ground plane, so the scene needs its alignment (`gs4city align`)",
            scene_dir.display()
        )));
    };
    let al = Alignment::read(al_path)?;
    let gml::Footprints {
        feet,
        names: renamed,
        warnings,
    } = gml::footprints(&scene.gml, &al)?;
    if feet.is_empty() {
        return Err(TileError::Invalid(format!(
            "{}: the city model holds no object with geometry to tile",
            scene_dir.join("citymodel").display()
        )));
    }
    let views = crate::colmap::read_model(&scene.sparse)?;
    let split = match opts.test_every {
        Some(every) => Split::new(views, every),
        None => scene.declared_split(views)?,
    };
    let test_views: Vec<String> = split.test.iter().map(|v| v.name.clone()).collect();

    // The grid over the footprint centres, centred on them.
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for f in &feet {
        for k in 0..2 {
            lo[k] = lo[k].min(f.centre[k]);
            hi[k] = hi[k].max(f.centre[k]);
        }
    }
    // Counted in f64 before anything is allocated: one footprint far from the others (a
    // building in another CRS) would otherwise ask for millions of tiles.
    let n = |k: usize| ((hi[k] - lo[k]) / opts.size_m).ceil().max(1.0);
    if n(0) * n(1) > MAX_TILES as f64 {
        return Err(too_many_tiles(
            &feet,
            &scene.gml,
            [n(0), n(1)],
            [lo, hi],
            opts.size_m,
        ));
    }
    let (nx, ny) = (n(0) as usize, n(1) as usize);
    let grid = Grid {
        origin: [
            lo[0] - (nx as f64 * opts.size_m - (hi[0] - lo[0])) / 2.0,
            lo[1] - (ny as f64 * opts.size_m - (hi[1] - lo[1])) / 2.0,
        ],
        size: opts.size_m,
        margin: opts.margin_m,
        nx,
        ny,
    };
    let n_tiles = nx * ny;
    let names: Vec<String> = (0..n_tiles)
        .map(|t| format!("t{:03}_{:03}", t / nx, t % nx))
        .collect();

    let partial = out.with_file_name(format!(
        "{}.partial",
        out.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "plan".into())
    ));
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(|err| TileError::Io {
            path: partial.clone(),
            err,
        })?;
    }
    let dirs: Vec<PathBuf> = names
        .iter()
        .map(|n| partial.join("tiles").join(n))
        .collect();
    for d in &dirs {
        crate::fsutil::create_dir(&d.join("scene"))?;
    }
    let (cuts, gaussians) = cut::cut(&scene.ply, &al, &grid, &dirs, &names, opts.sample)?;
    let ply_bytes = std::fs::metadata(&scene.ply)
        .map_err(|err| TileError::Io {
            path: scene.ply.clone(),
            err,
        })?
        .len();

    let all_ids: Vec<BTreeSet<u64>> = (0..scene.gml.len())
        .map(|fi| {
            feet.iter()
                .filter(|f| f.file == fi)
                .map(|f| f.offset)
                .collect()
        })
        .collect();
    let owners: Vec<Vec<&gml::Footprint>> = (0..n_tiles)
        .map(|t| {
            feet.iter()
                .filter(|f| grid.core_of(f.centre[0], f.centre[1]) == t)
                .collect()
        })
        .collect();
    let near: Vec<Vec<&gml::Footprint>> = (0..n_tiles)
        .map(|t| {
            feet.iter()
                .filter(|f| {
                    grid.core_of(f.centre[0], f.centre[1]) != t && grid.box_reaches(t, f.ground)
                })
                .collect()
        })
        .collect();
    let sights: Vec<TileSight> = (0..n_tiles)
        .map(|t| {
            if owners[t].is_empty() && near[t].is_empty() {
                return TileSight {
                    points: Vec::new(),
                    occluders: Vec::new(),
                };
            }
            let occluders = owners[t]
                .iter()
                .chain(&near[t])
                .map(|f| (f.scene_min, f.scene_max))
                .collect();
            let mut points: Vec<DVec3> = owners[t]
                .iter()
                .flat_map(|f| f.samples.iter().copied())
                .collect();
            points.extend(cuts[t].sample.iter().copied());
            TileSight { points, occluders }
        })
        .collect();
    let (view_sets, glimpsing) = assign_views(&split.train, &sights, opts);
    let bar = crate::progress::Bar::new("tile: scenes", n_tiles as u64, "tiles");
    let mut tiles = Vec::with_capacity(n_tiles);
    for t in 0..n_tiles {
        let dir = &dirs[t];
        let sdir = dir.join("scene");
        let owned = &owners[t];
        let neighbours = &near[t];
        let tile_views: Vec<(&View, Option<crop::Window>)> = view_sets[t]
            .iter()
            .map(|&(vi, w)| (&split.train[vi], w))
            .collect();
        let why_not = if owned.is_empty() && neighbours.is_empty() {
            Some("no building in its core or margin".to_string())
        } else if tile_views.is_empty() {
            Some("no training view sees it".to_string())
        } else {
            None
        };
        if why_not.is_none() {
            write_tile_scene(
                &scene,
                &sdir,
                &tile_views,
                owned,
                neighbours,
                &all_ids,
                &renamed,
            )?;
        }
        let c = grid.core(t);
        let fin = |v: f64| v.is_finite().then_some(v);
        tiles.push(TilePlan {
            index: t,
            name: names[t].clone(),
            ix: t % nx,
            iy: t / nx,
            core: [fin(c[0]), fin(c[1]), fin(c[2]), fin(c[3])],
            owned: owned.iter().map(|f| f.id.clone()).collect(),
            neighbours: neighbours.iter().map(|f| f.id.clone()).collect(),
            gaussians: cuts[t].gaussians,
            core_gaussians: cuts[t].core,
            views: tile_views.len(),
            views_glimpsing: glimpsing[t],
            views_cropped: tile_views.iter().filter(|(_, w)| w.is_some()).count(),
            runnable: why_not.is_none(),
            why_not,
            resources: resources(cuts[t].gaussians, tile_views.len()),
        });
        bar.inc(1);
    }
    bar.finish();
    let mut plan = Plan {
        program: "gs4city".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        scene: scene_dir.clone(),
        options: opts.clone(),
        grid,
        gaussians,
        ply_bytes,
        test_views,
        exe: exe.map(Path::to_path_buf),
        tiles,
        seconds: 0.0,
        peak_rss_mb: None,
        warnings,
    };
    slurm::write(&partial, out, &plan)?;
    plan.seconds = t0.elapsed().as_secs_f64();
    plan.peak_rss_mb = crate::progress::peak_rss_mb();
    crate::fsutil::write_json(&partial.join(PLAN), &plan)?;
    std::fs::rename(&partial, out).map_err(|err| TileError::Io {
        path: out.to_path_buf(),
        err,
    })?;
    crate::progress::done(
        "tile",
        &format!(
            "{} tiles ({} runnable) of {} Gaussians",
            plan.tiles.len(),
            plan.tiles.iter().filter(|t| t.runnable).count(),
            gaussians
        ),
        plan.seconds,
    );
    Ok(plan)
}

/// The scene folder of one tile: the CityGML subset and alignment, the COLMAP subset, links to
/// the images, SAM lists and features of its whole views and the cropped ones of the views
/// that join it through a window ([`crop`]; the PLY is already cut).
fn write_tile_scene(
    scene: &Scene,
    sdir: &Path,
    views: &[(&View, Option<crop::Window>)],
    owned: &[&gml::Footprint],
    neighbours: &[&gml::Footprint],
    all_ids: &[BTreeSet<u64>],
    renamed: &[Vec<(u64, String)>],
) -> Result<(), TileError> {
    let cm = sdir.join("citymodel");
    crate::fsutil::create_dir(&cm)?;
    for (fi, src) in scene.gml.iter().enumerate() {
        let keep: BTreeSet<u64> = owned
            .iter()
            .chain(neighbours)
            .filter(|f| f.file == fi)
            .map(|f| f.offset)
            .collect();
        let name = src.file_name().unwrap_or_default();
        gml::write_subset(src, &all_ids[fi], &keep, &renamed[fi], &cm.join(name))?;
    }
    if let Some(a) = &scene.alignment {
        let to = cm.join("alignment.json");
        std::fs::copy(a, &to).map_err(|err| TileError::Io { path: to, err })?;
    }
    // A cropped view has a camera of its own, numbered after the scene's.
    let mut next_camera = views.iter().map(|(v, _)| v.camera_id).max().unwrap_or(0);
    let mut model = Vec::with_capacity(views.len());
    for &(v, w) in views {
        match w {
            Some(w) => {
                next_camera = next_camera.checked_add(1).ok_or_else(|| {
                    TileError::Invalid(format!(
                        "{}: camera ids reach {}; no id is left for a cropped view",
                        scene.sparse.display(),
                        u32::MAX
                    ))
                })?;
                let c = crop::cropped_view(v, w, next_camera);
                crop::write_cropped(scene, sdir, v, &c, w)?;
                model.push(c);
            }
            None => model.push(v.clone()),
        }
    }
    crate::colmap::write_model(&sdir.join("sparse/0"), &model, true)?;
    for v in views.iter().filter(|(_, w)| w.is_none()).map(|(v, _)| v) {
        if let Some(images) = &scene.images {
            let src = images.join(&v.name);
            if src.is_file() {
                gml::link(&src, &sdir.join("images").join(&v.name))?;
            }
        }
        let stem = v.stem();
        if let Some(f) = scene.sam_file(&stem) {
            gml::link(&f, &sdir.join("masks").join(format!("{stem}.json")))?;
        }
        if let Some(f) = scene.feature_file(&stem) {
            gml::link(&f, &sdir.join("features").join(format!("{stem}.npy")))?;
        }
    }
    if let Some(p) = scene.prompts_file() {
        gml::link(&p, &sdir.join("features/prompts.json"))?;
    }
    // A tile of a SIMULATED scene is simulated too (its report says so). Its views are the
    // plan's training views only (the test views are held back from every tile), so it
    // declares no test views; nor is it an import.
    let meta = crate::scene::SceneMeta {
        test_views: None,
        imported: Default::default(),
        ..scene.meta.clone()
    };
    if meta != crate::scene::SceneMeta::default() {
        meta.write(sdir)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_point_has_one_core_and_the_margin_is_a_square_ring() {
        let g = Grid {
            origin: [0.0, 0.0],
            size: 10.0,
            margin: 2.0,
            nx: 3,
            ny: 2,
        };
        assert_eq!(g.core_of(-100.0, -5.0), 0);
        assert_eq!(g.core_of(15.0, 5.0), 1);
        assert_eq!(g.core_of(29.99, 19.99), 5);
        assert_eq!(g.core_of(1e9, 1e9), 5);
        assert_eq!(g.core_of(f64::NAN, 3.0), 0);
        let mut v = Vec::new();
        g.tiles_within(11.0, 9.0, &mut v);
        // Core tile 1; within 2 m of tile 0 (x < 10) and of tiles 3, 4 (y ≥ 10).
        assert_eq!(v, vec![0, 1, 3, 4]);
        v.clear();
        g.tiles_within(15.0, 5.0, &mut v);
        assert_eq!(v, vec![1]);
        v.clear();
        g.tiles_within(12.5, 5.0, &mut v);
        assert_eq!(v, vec![1]);
        assert!(segment_hits_box(
            DVec3::ZERO,
            DVec3::new(10.0, 0.0, 0.0),
            DVec3::new(4.0, -1.0, -1.0),
            DVec3::new(5.0, 1.0, 1.0)
        ));
        assert!(!segment_hits_box(
            DVec3::ZERO,
            DVec3::new(3.0, 0.0, 0.0),
            DVec3::new(4.0, -1.0, -1.0),
            DVec3::new(5.0, 1.0, 1.0)
        ));
    }

    /// A SIMULATED pinhole view (320 × 240, f = 160, at the origin looking down +z): the
    /// screen grid has cells of 10 px, 32 × 24.
    fn view_320() -> View {
        use crate::camera::{Camera, Distortion, Intrinsics, Pose};
        View {
            image_id: 1,
            camera_id: 1,
            name: "v.png".into(),
            camera: Camera {
                intrinsics: Intrinsics {
                    width: 320,
                    height: 240,
                    fx: 160.0,
                    fy: 160.0,
                    cx: 160.0,
                    cy: 120.0,
                    distortion: Distortion::None,
                },
                pose: Pose {
                    rotation: glam::DMat3::IDENTITY,
                    translation: DVec3::ZERO,
                },
            },
        }
    }

    /// The point at depth `z` that projects to pixel `(u, v)` of [`view_320`].
    fn at(u: f64, v: f64, z: f64) -> DVec3 {
        DVec3::new((u - 160.0) * z / 160.0, (v - 120.0) * z / 160.0, z)
    }

    #[test]
    fn a_view_joins_each_tile_through_the_window_of_the_cells_it_wins() {
        // Tile 0 at 10 m in cells (1, 1), (2, 1), (1, 2); tile 1 at 20 m in cell (1, 1)
        // (behind tile 0's point there: tile 0 wins it) and cells (20, 10), (21, 11); tile 2
        // at 30 m only in cells tile 0 wins (it wins none: its window is the cells it is seen
        // in); tile 3 has two points in view (fewer than 3: not a candidate).
        let sights = vec![
            TileSight {
                points: vec![
                    at(15.0, 15.0, 10.0),
                    at(25.0, 15.0, 10.0),
                    at(15.0, 25.0, 10.0),
                ],
                occluders: Vec::new(),
            },
            TileSight {
                points: vec![
                    at(12.0, 18.0, 20.0),
                    at(205.0, 105.0, 20.0),
                    at(215.0, 115.0, 20.0),
                ],
                occluders: Vec::new(),
            },
            TileSight {
                points: vec![
                    at(11.0, 11.0, 30.0),
                    at(29.0, 11.0, 30.0),
                    at(19.0, 19.0, 30.0),
                ],
                occluders: Vec::new(),
            },
            TileSight {
                points: vec![
                    at(300.0, 200.0, 5.0),
                    at(310.0, 210.0, 5.0),
                    at(0.0, 0.0, -5.0),
                ],
                occluders: Vec::new(),
            },
        ];
        let v = view_320();
        let shown = screen_cells(&v, &[0, 1, 2], &sights);
        // Hand count: tile 0 wins its 3 cells, tile 1 its 2 cells off tile 0's, tile 2 none.
        assert_eq!(
            shown,
            vec![
                Shown {
                    won: 3,
                    cells: [1, 1, 2, 2]
                },
                Shown {
                    won: 2,
                    cells: [20, 10, 21, 11]
                },
                Shown {
                    won: 0,
                    cells: [1, 1, 2, 1]
                },
            ]
        );
        // One cell (10 px) around the cells, clipped at the image's edge.
        let w = |x0, y0, x1, y1| Some(crop::Window { x0, y0, x1, y1 });
        assert_eq!(crop_window(&v, [1, 1, 2, 2], 0.75), w(0, 0, 40, 40));
        assert_eq!(
            crop_window(&v, [20, 10, 21, 11], 0.75),
            w(190, 90, 230, 130)
        );
        assert_eq!(
            crop_window(&v, [31, 23, 31, 23], 0.75),
            w(300, 220, 320, 240)
        );
        // A window not smaller than `crop_below` of the image (1600 of 76 800 px ≥ 1 %): whole.
        assert_eq!(crop_window(&v, [1, 1, 2, 2], 0.01), None);
        assert_eq!(crop_window(&v, [1, 1, 2, 2], 0.0), None);

        // The plan's assignment: every candidate joins (min-share 0), cropped; tile 3 not.
        let opts = TileOptions {
            min_share: 0.0,
            min_views: 0,
            crop_below: 0.3,
            ..TileOptions::default()
        };
        let (sets, glimpsing) = assign_views(std::slice::from_ref(&v), &sights, &opts);
        assert_eq!(
            sets,
            vec![
                vec![(0, w(0, 0, 40, 40))],
                vec![(0, w(190, 90, 230, 130))],
                vec![(0, w(0, 0, 40, 30))],
                vec![],
            ]
        );
        assert_eq!(glimpsing, vec![0, 0, 0, 0]);
        // Shares 3/5 and 2/5 (tile 2: 0): at min-share 0.5 only tile 0 keeps the view.
        let opts = TileOptions {
            min_share: 0.5,
            ..opts
        };
        let (sets, glimpsing) = assign_views(std::slice::from_ref(&v), &sights, &opts);
        assert_eq!(
            sets,
            vec![vec![(0, w(0, 0, 40, 40))], vec![], vec![], vec![]]
        );
        assert_eq!(glimpsing, vec![0, 1, 1, 0]);
    }
}
