//! The `masks` stage (paper §3.2, foundation-mask filtering): per view, the scene's SAM masks are
//! cleaned against the city model so that what remains is what the city model does not know
//! (trees, cars, people, foreground objects in front of façades).
//!
//! Per view and mask, in order (`docs/masks.md` has the details and the measurements):
//! 1. **quality and area** (paper Eq. S^qc): dropped when `predicted_iou < τ_q` (rule
//!    `quality`) or when the area is below `τ_a = ⌈area_frac · H·W⌉` pixels (`area`); a mask
//!    with `support_floor ≤ predicted_iou < τ_q` that every later rule would keep is dropped as
//!    `low_quality_support` instead (beyond the paper: the associate stage lets it join a group);
//! 2. **building-support overlap** `R_ov = |s ∩ Ω_feat| / |s|`, `Ω_feat` = pixels whose raycast
//!    feature id (channel 0 of `<stem>.ids.npy`) is not −1; below `ρ` the mask is kept as a
//!    non-building candidate (`low_overlap`) — unless the optional low-overlap check finds it
//!    is building after all (`low_overlap_building`);
//! 3. a high-overlap mask is disambiguated by the chosen **test**:
//!    * `features` (the paper): kept when `S_fore > S_city + δ` (`features_foreground`), else
//!      dropped (`features_building`);
//!    * `geometry` (beyond the paper, model-free): kept when at least `occluder_share` of its
//!      pixels with depth evidence have the 3DGS expected depth in front of the local
//!      city-model surface by more than `τ_occ` (`occluder`), else dropped (`on_surface`, or
//!      `no_depth` when too few of its pixels have evidence); see [`geometry`];
//!    * `both`: see [`Test::Both`];
//!    * `overlap`: no evidence at all; dropped (`high_overlap`).
//! 4. the **class** of a kept mask is the class of its best prompt (argmax cosine), −1 without
//!    features; the decisions hold the margin to the best prompt of another class.
//!
//! Without a `masks/` folder in the scene (or with `Source::Depth`), the masks are derived
//! without any foundation model: connected components of the pixels where the 3DGS stands in
//! front of the city model ([`geometry::components`], rule `depth_component`).
//!
//! The stage reads only the scene files `docs/design.md` allows ("Inputs the algorithms may read"):
//! the SAM list `<stem>.json` of each view, its features and the prompts.
//!
//! Output files (`docs/design.md`, "Stage contract"): per view `<stem>.json` = the kept masks in SAM
//! format, each with the extra keys `source_index`, `r_ov`, `rule`, `class` ([`KeptMask`]);
//! `<stem>.decisions.json` = one [`Decision`] per input mask; `overlay_<stem>.png` for a few
//! views; `summary.json` ([`MasksSummary`]) last.
pub mod geometry;
pub mod overlay;
pub mod prompts;
mod rules;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::cache::{Cache, CacheError};
use crate::camera::View;
use crate::fsutil::{self, FsError};
use crate::idmap;
use crate::imageio::{self, ImageError};
use crate::maskfile::{
    Decision, KeptMask, MaskFileError, Rule, decisions_file, kept_file, write_kept,
};
use crate::npy::NpyError;
use crate::progress::Bar;
use crate::sam::{self, Rle, SamError, SamMask};
use crate::scene::Scene;
use geometry::{ComponentParams, DepthTest, ViewCodes};
use prompts::{PromptInfo, PromptTable};
use rules::decide_sam;

/// Errors of the masks stage. Each names the file at fault.
#[derive(Debug, thiserror::Error)]
pub enum MasksError {
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error("{0}")]
    Unavailable(String),
    #[error(transparent)]
    Sam(#[from] SamError),
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error(transparent)]
    Cache(#[from] CacheError),
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    MaskFile(#[from] MaskFileError),
    #[error(transparent)]
    IdMap(#[from] crate::idmap::IdMapError),
}

/// Where the masks come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    /// The scene's SAM lists when it has `masks/`, else the mask-free source.
    Auto,
    /// The scene's SAM lists (`masks/<stem>.json`).
    Sam,
    /// Derived from the depth test alone, without any foundation model.
    Depth,
}

/// Which 3DGS depth the depth test compares with the city model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GsDepth {
    /// Median depth of the cache's lists ([`crate::cache::Cache::median_depth`]: the plane the
    /// render stage stores; from the lists and the centres of the scene's `point_cloud.ply` in a
    /// cache from before version 4).
    Median,
    /// The cache's expected depth `Σ w·z / (1 − T)`.
    Expected,
}

/// How high-overlap masks are disambiguated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Test {
    /// `both` with features and a cache, `features` or `geometry` with one of them,
    /// `overlap` with neither.
    Auto,
    /// The paper's vision-language rule `S_fore > S_city + δ`.
    Features,
    /// The model-free depth test.
    Geometry,
    /// Kept when the depth test says occluder and the features do not say building
    /// (`S_city ≤ S_fore + δ`), or when the features say foreground and the depth has no
    /// evidence against it (`no_depth`). See `docs/masks.md` for why (measurements).
    Both,
    /// No disambiguation: every high-overlap mask is dropped.
    Overlap,
}

macro_rules! parse_enum {
    ($t:ty, $($name:literal => $v:expr),+) => {
        impl FromStr for $t {
            type Err = String;
            fn from_str(s: &str) -> Result<Self, String> {
                match s {
                    $($name => Ok($v),)+
                    _ => Err(format!("{s:?} is not one of {}", [$($name),+].join(", "))),
                }
            }
        }
    };
}
parse_enum!(Source, "auto" => Source::Auto, "sam" => Source::Sam, "depth" => Source::Depth);
parse_enum!(GsDepth, "median" => GsDepth::Median, "expected" => GsDepth::Expected);
parse_enum!(Test, "auto" => Test::Auto, "features" => Test::Features, "geometry" => Test::Geometry,
    "both" => Test::Both, "overlap" => Test::Overlap);

/// Options of the stage (defaults: `docs/design.md` and `docs/masks.md`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MasksOptions {
    pub source: Source,
    pub test: Test,
    /// `τ_q` on `predicted_iou`.
    pub tau_q: f64,
    /// Support-only floor (beyond the paper): a SAM mask with `floor ≤ predicted_iou < τ_q`
    /// that passes every other rule is dropped with the rule `low_quality_support` instead of
    /// `quality` — not trusted enough to found a group, but the associate stage may let it join
    /// one (`docs/associate.md`). `None`: every `predicted_iou < τ_q` is `quality`, as before.
    #[serde(default = "default_support_floor")]
    pub support_floor: Option<f64>,
    /// `τ_a = ⌈area_frac · H·W⌉` pixels.
    pub area_frac: f64,
    /// `ρ`: high overlap from here on.
    pub rho: f64,
    /// `δ`: the feature margin.
    pub delta: f64,
    /// Which 3DGS depth is compared with the city model.
    pub gs_depth: GsDepth,
    /// `τ_occ` in metres (× the alignment scale in the scene frame).
    pub tau_occ_m: f64,
    /// Relative depth tolerance (fraction of the city depth) added to `τ_occ`.
    pub tau_rel: f64,
    /// Radius (pixels) of the local city surface the 3DGS depth is compared with.
    pub surface_radius_px: usize,
    /// Subtract each city surface's median 3DGS − city depth offset before the comparison
    /// (absorbs most of a misalignment; [`geometry::surface_bias`]).
    pub surface_bias: bool,
    /// Pixels a surface needs for its own offset (else its building's, else none).
    pub bias_min_px: usize,
    /// Offsets are clamped to ± this many metres (× the alignment scale).
    pub bias_max_m: f64,
    /// Share of a mask's evidence pixels that must be in front for `occluder`.
    pub occluder_share: f64,
    /// Share of a mask's pixels that must have depth evidence for the depth test to decide.
    pub min_evidence: f64,
    /// Also drop low-overlap masks that the evidence shows to be building.
    pub low_overlap_check: bool,
    /// Mask-free source: minimum 3DGS alpha of a pixel.
    pub min_alpha: f64,
    /// Mask-free source: relative 3DGS depth jump that splits two neighbours.
    pub split_rel: f64,
    /// Mask-free source: radius (pixels) of the morphological opening of the candidates.
    pub open_px: usize,
    /// Overlay PNGs for this many views (evenly spaced over the sorted views).
    pub overlays: usize,
}

impl Default for MasksOptions {
    fn default() -> Self {
        MasksOptions {
            source: Source::Auto,
            test: Test::Auto,
            tau_q: 0.7,
            support_floor: default_support_floor(),
            area_frac: 3e-5,
            rho: 0.8,
            delta: 0.05,
            gs_depth: GsDepth::Median,
            tau_occ_m: 0.5,
            tau_rel: 0.0,
            surface_radius_px: 2,
            surface_bias: true,
            bias_min_px: 64,
            bias_max_m: 1.0,
            occluder_share: 0.5,
            min_evidence: 0.1,
            low_overlap_check: true,
            min_alpha: 0.5,
            split_rel: 0.05,
            open_px: 3,
            overlays: 4,
        }
    }
}

fn default_support_floor() -> Option<f64> {
    Some(0.3)
}

impl MasksOptions {
    /// Checks ranges.
    pub fn validate(&self) -> Result<(), MasksError> {
        let unit = [
            ("tau_q", self.tau_q),
            ("area_frac", self.area_frac),
            ("rho", self.rho),
            ("occluder_share", self.occluder_share),
            ("min_evidence", self.min_evidence),
            ("min_alpha", self.min_alpha),
        ];
        for (k, v) in unit {
            crate::check::unit(k, v)?;
        }
        if let Some(f) = self.support_floor {
            crate::check::unit("support_floor", f)?;
        }
        use crate::check::End;
        crate::check::range(
            "delta",
            self.delta,
            End::Open(f64::NEG_INFINITY),
            End::Open(f64::INFINITY),
        )?;
        for (k, v) in [
            ("tau_occ_m", self.tau_occ_m),
            ("tau_rel", self.tau_rel),
            ("bias_max_m", self.bias_max_m),
            ("split_rel", self.split_rel),
        ] {
            crate::check::non_negative(k, v)?;
        }
        crate::check::range(
            "surface_radius_px",
            self.surface_radius_px,
            End::Closed(0.0),
            End::Closed(16.0),
        )?;
        Ok(())
    }

    /// `τ_a` in pixels for an `h×w` image (at least 1).
    pub fn min_area_px(&self, h: usize, w: usize) -> u64 {
        ((self.area_frac * (h * w) as f64).ceil() as u64).max(1)
    }
}

/// What the stage reads.
#[derive(Debug, Clone, Copy)]
pub struct MasksInputs<'a> {
    pub scene: &'a Scene,
    /// The views to filter (their stems name every per-view file).
    pub views: &'a [View],
    /// A `gs4city raycast` folder (`<stem>.ids.npy`, `<stem>.depth.npy`).
    pub raycast: &'a Path,
    /// The contributions cache (expected 3DGS depth and alpha); needed by the depth test
    /// and the mask-free source.
    pub cache: Option<&'a Cache>,
    /// `alignment.json`'s scale (scene units per metre).
    pub alignment_scale: f64,
}

/// Per-view counts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewSummary {
    pub stem: String,
    pub width: usize,
    pub height: usize,
    /// `τ_a` of this view.
    pub min_area_px: u64,
    /// Masks in the input list (components found, for the mask-free source).
    pub input: usize,
    pub kept: usize,
    /// Count per rule.
    pub rules: BTreeMap<String, usize>,
    /// Wall-clock seconds of this view (load, decide, write).
    pub seconds: f64,
}

/// Timings of the stage (seconds; per-view parts summed over views and threads).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MasksTiming {
    /// Reading the Gaussian centres (median depth only).
    pub ply_s: f64,
    /// Reading the per-view files (raycast, cache, SAM list, features).
    pub load_s: f64,
    /// The 3DGS median depth and the depth states.
    pub depth_s: f64,
    pub decide_s: f64,
    pub write_s: f64,
    pub overlay_s: f64,
    pub total_s: f64,
}

/// `summary.json` of the stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MasksSummary {
    /// `sam` or `depth` (resolved).
    pub source: Source,
    /// `features`, `geometry`, `both` or `overlap` (resolved; `overlap` also for `depth`).
    pub test: Test,
    pub options: MasksOptions,
    pub alignment_scale: f64,
    /// `τ_occ` in scene units.
    pub tau_occ: f64,
    /// Whether per-mask features were used (also for the classes).
    pub features: bool,
    /// The prompts, resolved (empty without features).
    pub prompts: Vec<PromptInfo>,
    pub input: usize,
    pub kept: usize,
    /// Count per rule over all views.
    pub rules: BTreeMap<String, usize>,
    /// Overlay files written (names inside the output folder).
    pub overlays: Vec<String>,
    pub views: Vec<ViewSummary>,
    pub timing: MasksTiming,
    /// Loud lines: the stage kept (almost) nothing.
    #[serde(default)]
    pub warnings: Vec<String>,
}

impl crate::layout::Summary for MasksSummary {}

/// The loud line when the stage keeps no mask of many (the fused supervision falls back to the
/// city model alone), with the rules that dropped them and what to change.
fn collapse_warning(input: usize, kept: usize, rules: &BTreeMap<String, usize>) -> Option<String> {
    if input == 0 || kept > 0 {
        return None;
    }
    let mut by: Vec<(&String, &usize)> = rules.iter().collect();
    by.sort_by(|a, b| b.1.cmp(a.1).then(a.0.cmp(b.0)));
    let top: Vec<String> = by.iter().take(3).map(|(r, n)| format!("{r} {n}")).collect();
    Some(format!(
        "masks COLLAPSED: all {input} masks dropped ({}); the fused supervision is the city model alone. Check --tau-q (quality), --area-frac (area), --rho (overlap with the city model) and the alignment (on_surface / features_building mean the masks lie on the model's surfaces)",
        top.join(", ")
    ))
}

/// The file name of a view's overlay.
pub fn overlay_name(stem: &str) -> String {
    format!("overlay_{stem}.png")
}

/// Everything resolved once for all views.
struct Plan<'a> {
    inp: MasksInputs<'a>,
    opts: &'a MasksOptions,
    source: Source,
    test: Test,
    prompts: Option<PromptTable>,
    depth: DepthTest,
    /// Gaussian centres (for the median depth of a cache without its plane).
    positions: Option<Vec<[f32; 3]>>,
    overlay_stems: Vec<String>,
    out: &'a Path,
}

/// The per-view result.
struct ViewOut {
    summary: ViewSummary,
    load_s: f64,
    depth_s: f64,
    decide_s: f64,
    write_s: f64,
    overlay_s: f64,
}

/// Runs the stage over `inp.views` into `out` (see the module docs); `summary.json` is
/// written last (a stale one is removed first).
pub fn run(
    inp: &MasksInputs<'_>,
    opts: &MasksOptions,
    out: &Path,
) -> Result<MasksSummary, MasksError> {
    let t0 = Instant::now();
    opts.validate()?;
    crate::check::positive("the alignment scale", inp.alignment_scale)?;
    let source = match opts.source {
        Source::Auto if inp.scene.masks.is_some() => Source::Sam,
        Source::Auto => Source::Depth,
        s => s,
    };
    let prompts_file = inp.scene.prompts_file();
    let have_features = source == Source::Sam && prompts_file.is_some();
    let have_depth = inp.cache.is_some();
    let test = match (source, opts.test) {
        (Source::Depth, _) => Test::Overlap,
        (_, Test::Auto) => match (have_features, have_depth) {
            (true, true) => Test::Both,
            (true, false) => Test::Features,
            (false, true) => Test::Geometry,
            (false, false) => Test::Overlap,
        },
        (_, t) => t,
    };
    let root = inp.scene.root.display();
    if source == Source::Sam && inp.scene.masks.is_none() {
        return Err(MasksError::Unavailable(format!(
            "source sam: the scene {root} has no masks/ folder"
        )));
    }
    if matches!(test, Test::Features | Test::Both) && prompts_file.is_none() {
        return Err(MasksError::Unavailable(format!(
            "test {test:?}: the scene {root} has no features/prompts.json (use the geometry test)"
        )));
    }
    if (matches!(test, Test::Geometry | Test::Both) || source == Source::Depth) && !have_depth {
        return Err(MasksError::Unavailable(
            "the depth test and the mask-free source need the 3DGS depth: give the contributions cache (--cache)".into(),
        ));
    }
    // Features are used for the test and for the classes whenever the scene has them.
    let prompts = match (&prompts_file, source) {
        (Some(p), Source::Sam) => Some(PromptTable::new(p, &sam::read_prompts_json(p)?)?),
        _ => None,
    };
    fsutil::create_dir(out)?;
    let _ = std::fs::remove_file(out.join("summary.json"));
    let scale = inp.alignment_scale;
    let depth = DepthTest {
        tau: (opts.tau_occ_m * scale) as f32,
        tau_rel: opts.tau_rel as f32,
        radius: opts.surface_radius_px,
        bias: opts.surface_bias,
        bias_min_px: opts.bias_min_px,
        bias_max: (opts.bias_max_m * scale) as f32,
    };
    let needs_depth = source == Source::Depth || matches!(test, Test::Geometry | Test::Both);
    let t_ply = Instant::now();
    // The cache is checked against the scene's PLY: through the Gaussians' centres where they
    // are read (the median depth of a cache without its plane), else through the PLY's header
    // alone.
    let stale = |found: usize, cache: &Cache| MasksError::Invalid {
        path: inp.scene.ply.clone(),
        why: format!(
            "{found} Gaussians, but the cache {} was built for {}: the cache is stale",
            cache.dir.display(),
            cache.summary.gaussians
        ),
    };
    let positions = match (needs_depth, opts.gs_depth, inp.cache) {
        (true, GsDepth::Median, Some(cache)) if !cache.summary.median_depth => {
            let (g, _) = crate::splat::read_ply(&inp.scene.ply, &crate::splat::ReadOptions::KEEP)?;
            if g.len() != cache.summary.gaussians {
                return Err(stale(g.len(), cache));
            }
            Some(g.positions)
        }
        _ => None,
    };
    if let (true, Some(cache), None) = (needs_depth, inp.cache, &positions) {
        let found = crate::splat::read_count(&inp.scene.ply)?;
        if found != cache.summary.gaussians {
            return Err(stale(found, cache));
        }
    }
    let ply_s = t_ply.elapsed().as_secs_f64();
    let mut stems: Vec<String> = inp.views.iter().map(View::stem).collect();
    stems.sort();
    let k = opts.overlays.min(stems.len());
    let overlay_stems: Vec<String> = (0..k).map(|i| stems[i * stems.len() / k].clone()).collect();
    let plan = Plan {
        inp: *inp,
        opts,
        source,
        test,
        prompts,
        depth,
        positions,
        overlay_stems,
        out,
    };
    // progress: one tick per view.
    let bar = Bar::new("masks", inp.views.len() as u64, "views");
    let results: Vec<ViewOut> = inp
        .views
        .par_iter()
        .map(|v| {
            let r = view(&plan, v);
            bar.inc(1);
            r
        })
        .collect::<Result<_, _>>()?;
    bar.finish();
    let mut views: Vec<ViewSummary> = Vec::with_capacity(results.len());
    let mut timing = MasksTiming {
        ply_s,
        ..Default::default()
    };
    let mut rules = BTreeMap::new();
    for r in results {
        timing.load_s += r.load_s;
        timing.depth_s += r.depth_s;
        timing.decide_s += r.decide_s;
        timing.write_s += r.write_s;
        timing.overlay_s += r.overlay_s;
        for (k, n) in &r.summary.rules {
            *rules.entry(k.clone()).or_insert(0) += n;
        }
        views.push(r.summary);
    }
    views.sort_by(|a, b| a.stem.cmp(&b.stem));
    timing.total_s = t0.elapsed().as_secs_f64();
    let summary = MasksSummary {
        source,
        test,
        options: opts.clone(),
        alignment_scale: scale,
        tau_occ: opts.tau_occ_m * scale,
        features: plan.prompts.is_some(),
        prompts: plan
            .prompts
            .as_ref()
            .map(|p| p.info.clone())
            .unwrap_or_default(),
        input: views.iter().map(|v| v.input).sum(),
        kept: views.iter().map(|v| v.kept).sum(),
        rules,
        overlays: plan.overlay_stems.iter().map(|s| overlay_name(s)).collect(),
        views,
        timing,
        warnings: Vec::new(),
    };
    let mut summary = summary;
    summary.warnings.extend(collapse_warning(
        summary.input,
        summary.kept,
        &summary.rules,
    ));
    for w in &summary.warnings {
        log::warn!("{w}");
    }
    crate::layout::Summary::write(&summary, out)?;
    crate::progress::done(
        "masks",
        &format!(
            "kept {} of {} masks ({:?} source, {:?} test) in {} views",
            summary.kept,
            summary.input,
            source,
            test,
            summary.views.len()
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}

/// One view: load, decide, write.
fn view(plan: &Plan<'_>, v: &View) -> Result<ViewOut, MasksError> {
    let t0 = Instant::now();
    let inp = &plan.inp;
    let opts = plan.opts;
    let stem = v.stem();
    let (h, w) = (
        v.camera.intrinsics.height as usize,
        v.camera.intrinsics.width as usize,
    );
    let ids = idmap::read_raycast(inp.raycast, &stem, w, h)?;
    let feature = &ids[..h * w];
    let needs_depth =
        plan.source == Source::Depth || matches!(plan.test, Test::Geometry | Test::Both);
    // Depth states and (for the mask-free source) the 3DGS depth and alpha.
    let mut gs_depth_alpha = None;
    let mut depth_s = 0.0;
    let states = if needs_depth {
        let city = idmap::read_depth(inp.raycast, &stem, w, h)?;
        let cache = inp.cache.expect("checked in run");
        let (c, gs) = match plan.opts.gs_depth {
            GsDepth::Median => {
                cache.median_depth(&stem, plan.positions.as_deref(), &v.camera.pose)?
            }
            GsDepth::Expected => {
                let mut c = cache.load_planes(&stem)?;
                let d = std::mem::take(&mut c.depth);
                (c, d)
            }
        };
        cache.check_size(&stem, (c.width, c.height), (w, h))?;
        let t = Instant::now();
        let surface = &ids[h * w..2 * h * w];
        let s = geometry::classify(&city, &gs, feature, surface, h, w, &plan.depth);
        depth_s = t.elapsed().as_secs_f64();
        gs_depth_alpha = Some((gs, c.alpha));
        Some(s)
    } else {
        None
    };
    let sam_list = match plan.source {
        Source::Sam => {
            let path = kept_file(inp.scene.masks.as_ref().expect("checked in run"), &stem);
            if !path.is_file() {
                return Err(MasksError::Invalid {
                    path,
                    why: "missing: the scene's masks/ folder has no SAM list for this view".into(),
                });
            }
            Some(sam::read_sam_json_sized(&path, Some([h, w]))?)
        }
        _ => None,
    };
    let features = match (&plan.prompts, &sam_list) {
        (Some(p), Some(list)) => {
            let ppath = inp.scene.prompts_file().expect("prompts exist");
            let path = inp
                .scene
                .features
                .as_ref()
                .map(|d| d.join(format!("{stem}.npy")))
                .unwrap_or_else(|| inp.scene.root.join("features").join(format!("{stem}.npy")));
            Some(sam::read_view_features(&path, list.len(), p.dim, &ppath)?)
        }
        _ => None,
    };
    let load_s = t0.elapsed().as_secs_f64() - depth_s;
    let t1 = Instant::now();
    let codes = ViewCodes::new(feature, states.as_deref(), h, w);
    let min_area = opts.min_area_px(h, w);
    let (kept, decisions) = match &sam_list {
        Some(list) => decide_sam(plan, &codes, list, features.as_deref(), min_area)?,
        None => {
            let (gs, alpha) = gs_depth_alpha.as_ref().expect("depth source has depth");
            depth_source(
                plan,
                &codes,
                states.as_deref().expect("depth"),
                gs,
                alpha,
                h,
                w,
                min_area,
            )?
        }
    };
    let decide_s = t1.elapsed().as_secs_f64();
    let t2 = Instant::now();
    write_kept(&kept_file(plan.out, &stem), &kept)?;
    fsutil::write_json(&decisions_file(plan.out, &stem), &decisions)?;
    let write_s = t2.elapsed().as_secs_f64();
    let t3 = Instant::now();
    if plan.overlay_stems.contains(&stem) {
        let image = inp
            .scene
            .images
            .as_ref()
            .map(|d| d.join(&v.name))
            .and_then(|p| {
                imageio::read_rgb_sized(&p, w, h)
                    .map_err(|e| log::warn!("masks: {e}: its overlay is drawn on grey"))
                    .ok()
            });
        overlay::write(&plan.out.join(overlay_name(&stem)), image, h, w, &kept)?;
    }
    let overlay_s = t3.elapsed().as_secs_f64();
    let mut rules = BTreeMap::new();
    for d in &decisions {
        *rules.entry(d.rule.name().to_string()).or_insert(0) += 1;
    }
    Ok(ViewOut {
        summary: ViewSummary {
            stem,
            width: w,
            height: h,
            min_area_px: min_area,
            input: decisions.len(),
            kept: kept.len(),
            rules,
            seconds: t0.elapsed().as_secs_f64(),
        },
        load_s,
        depth_s,
        decide_s,
        write_s,
        overlay_s,
    })
}

impl Plan<'_> {
    fn depth_used(&self) -> bool {
        matches!(self.test, Test::Geometry | Test::Both)
    }
}

/// The mask-free source: components of "in front of the city model" pixels.
#[allow(clippy::too_many_arguments)]
fn depth_source(
    plan: &Plan<'_>,
    codes: &ViewCodes,
    states: &[u8],
    gs: &[f32],
    alpha: &[f32],
    h: usize,
    w: usize,
    min_area: u64,
) -> Result<(Vec<KeptMask>, Vec<Decision>), MasksError> {
    let opts = plan.opts;
    let comps = geometry::components(
        states,
        gs,
        alpha,
        h,
        w,
        &ComponentParams {
            min_alpha: opts.min_alpha as f32,
            split_rel: opts.split_rel as f32,
            tau: plan.depth.tau,
            min_area: min_area as usize,
            open_px: opts.open_px,
        },
    )?;
    let mut kept = Vec::with_capacity(comps.len());
    let mut decisions = Vec::with_capacity(comps.len());
    for comp in comps {
        let rle = Rle::encode_region(h, w, comp.y0, comp.x0, comp.window.view());
        let runs = rle.counts().expect("freshly encoded");
        let c = codes.count(&runs);
        let sam = SamMask::from_rle(rle, 1.0, 1.0, Vec::new()).expect("freshly encoded");
        let mut scores = BTreeMap::new();
        scores.insert("area".to_string(), c.area as f64);
        scores.insert("front_share".to_string(), c.front_share());
        decisions.push(Decision {
            source_index: -1,
            kept: true,
            rule: Rule::DepthComponent,
            r_ov: c.r_ov(),
            scores,
        });
        kept.push(KeptMask {
            sam,
            source_index: -1,
            r_ov: c.r_ov(),
            rule: Rule::DepthComponent,
            class: crate::classes::NONE,
        });
    }
    Ok((kept, decisions))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stage_that_keeps_nothing_says_so_with_its_largest_rules() {
        let rules: BTreeMap<String, usize> = [("area", 2), ("on_surface", 1), ("quality", 3)]
            .into_iter()
            .map(|(k, n)| (k.to_string(), n))
            .collect();
        let w = collapse_warning(6, 0, &rules).unwrap();
        assert!(
            w.starts_with("masks COLLAPSED: all 6 masks dropped (quality 3, area 2, on_surface 1)"),
            "{w}"
        );
        assert!(w.contains("--tau-q") && w.contains("--area-frac"), "{w}");
        // One kept mask, or no input at all, is no collapse.
        assert_eq!(collapse_warning(6, 1, &rules), None);
        assert_eq!(collapse_warning(0, 0, &BTreeMap::new()), None);
    }
}
