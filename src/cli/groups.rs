//! The option groups of the command line, each defined once here and flattened into the
//! commands that take it, and the `--config FILE.toml` file they make up (docs/config.md).
//!
//! A **tuning group** holds one stage's tuning and ablation switches (the paper's knobs, the
//! ablations of BENCHMARKS.md): [`RaycastTuning`], [`CacheTuning`], [`SegmentTuning`],
//! [`MasksTuning`], [`OpeningsTuning`], [`AssociateTuning`], [`FuseTuning`], [`VoteTuning`],
//! [`PriorTuning`], [`TrainTuning`], [`CheckTuning`] (and `refine::RefineOptions` as it is).
//! Each is at once
//!
//! * a set of flags of the stage's own command (`gs4city lift --no-centre-gate`, flattened with
//!   `#[command(flatten)]`), and
//! * a section of the config file (`[vote]` `no_centre_gate = true`): a key is the flag's name
//!   without `--`, `_` for `-`; a switch (`--no-centre-gate`) is `true` when given.
//!
//! `gs4city run` shows none of these flags (its help stays short): it reads them from
//! `--config`. A stage command reads the same file, and a flag given on its command line wins
//! over the file's key ([`merged`]). A group's `Default` is its stage's defaults (a test checks
//! that an empty command line parses to it), so every default lives in the stage's own
//! `*Options::default()`.
//!
//! A new option of a stage goes into its group here (with `apply`), and a new stage's group
//! into [`Config`] and docs/config.md (the test `docs_config_lists_every_key` checks that it
//! names every key). User options (`--scene`, `--out`, `--supervision`, …) stay with their
//! commands; the shared ones are [`RunRef`] (`--run R --scene S --mode M` of the commands that
//! read a run), [`SplitArgs`] (`--test-every N`, `--split S` of the labelling stages) and
//! [`ConfigArg`].
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::Context;
use clap::Args;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::associate::{AssociateOptions, CandidateMode};
use crate::cache::CacheOptions;
use crate::layout::Mode;
use crate::masks::{GsDepth, MasksOptions, Source, Test};
use crate::openings::{Add, Cues, OpeningsOptions};
use crate::refine::RefineOptions;
use crate::scene::Split;
use crate::segment::SegmentOptions;
use crate::train::predict::Rule;
use crate::train::{Init, Softmax, TrainOptions};
use crate::vote::VoteOptions;

/// A value of a snake_case serde enum from its name (`weighted`, `projected`, …): the clap
/// parser of the enums the stages define without clap.
fn named<T: DeserializeOwned>(s: &str) -> Result<T, String> {
    serde_json::from_value(serde_json::Value::String(s.to_string()))
        .map_err(|e| e.to_string().replace('`', ""))
}

/// The arguments given on this process's command line (clap ids = field names = config
/// keys), set once by [`super::main`]; empty when the CLI is used as a library.
static GIVEN: OnceLock<BTreeSet<String>> = OnceLock::new();

/// Records the ids of the arguments given on the command line.
pub(super) fn set_given(ids: BTreeSet<String>) {
    let _ = GIVEN.set(ids);
}

/// Whether argument `id` was given on the command line.
fn given(id: &str) -> bool {
    GIVEN.get().is_some_and(|g| g.contains(id))
}

/// `file`'s values, with each of `flags`' keys that `given` holds taken from `flags` instead:
/// a flag given on the command line wins over the config file's key, a default never does.
pub fn merged_with<T: Serialize + DeserializeOwned>(
    file: &T,
    flags: &T,
    given: impl Fn(&str) -> bool,
) -> T {
    // TOML values, not JSON: a non-finite number given on the command line (`--t-stop NaN`)
    // survives the merge and is refused by the stage's own check, naming the option.
    let mut base = toml::Value::try_from(file).expect("a group serialises");
    let over = toml::Value::try_from(flags).expect("a group serialises");
    if let (Some(b), Some(o)) = (base.as_table_mut(), over.as_table()) {
        for (k, v) in o {
            if given(k) {
                b.insert(k.clone(), v.clone());
            }
        }
    }
    base.try_into()
        .expect("a group deserialises from its own values")
}

/// [`merged_with`] the arguments of this process's command line.
pub fn merged<T: Serialize + DeserializeOwned>(file: &T, flags: &T) -> T {
    merged_with(file, flags, given)
}

/// `--config FILE.toml`: the tuning and ablation settings of every stage (docs/config.md).
#[derive(Debug, Clone, Args)]
pub struct ConfigArg {
    /// Tuning and ablation settings, one `[section]` per stage (docs/config.md; the ablations of
    /// BENCHMARKS.md are configs/ablation/*.toml).
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
}

impl ConfigArg {
    /// The file's settings, or every stage's defaults without `--config`.
    pub fn load(&self) -> anyhow::Result<Config> {
        match &self.config {
            Some(p) => Config::read(p),
            None => Ok(Config::default()),
        }
    }
}

/// The config file (docs/config.md): one section per stage, every key optional (absent = the
/// stage's default), an unknown section or key an error naming it, the file and its line.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    #[serde(default)]
    pub raycast: RaycastTuning,
    #[serde(default)]
    pub cache: CacheTuning,
    #[serde(default)]
    pub segment: SegmentTuning,
    #[serde(default)]
    pub masks: MasksTuning,
    #[serde(default)]
    pub openings: OpeningsTuning,
    #[serde(default)]
    pub associate: AssociateTuning,
    #[serde(default)]
    pub fuse: FuseTuning,
    #[serde(default)]
    pub vote: VoteTuning,
    #[serde(default)]
    pub prior: PriorTuning,
    #[serde(default)]
    pub train: TrainTuning,
    #[serde(default)]
    pub refine: RefineOptions,
    #[serde(default)]
    pub check: CheckTuning,
    /// The keys the file gives in `[cache]` (a run's `--quality` preset sets the others).
    #[serde(skip)]
    pub cache_keys: Vec<String>,
}

impl Config {
    /// Reads and parses `path`: an error is one line naming the file, the line and the key.
    pub fn read(path: &Path) -> anyhow::Result<Config> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("--config {}", path.display()))?;
        Config::parse(path, &text)
    }

    /// [`Config::read`] on text (`path` names it in errors).
    pub fn parse(path: &Path, text: &str) -> anyhow::Result<Config> {
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        let mut config: Config = Self::parse_sections(path, text)?;
        // The text parsed as a Config, so it is a TOML table whose `cache` (if any) is one.
        if let Ok(table) = text.parse::<toml::Table>()
            && let Some(cache) = table.get("cache").and_then(|c| c.as_table())
        {
            config.cache_keys = cache.keys().cloned().collect();
        }
        Ok(config)
    }

    fn parse_sections(path: &Path, text: &str) -> anyhow::Result<Config> {
        toml::from_str(text).map_err(|e| {
            // An unknown key is reported at its table: the line of the key itself is more use.
            let key_line = e
                .message()
                .strip_prefix("unknown field `")
                .and_then(|m| m.split('`').next())
                .and_then(|key| {
                    text.lines().position(|l| {
                        l.trim_start()
                            .strip_prefix(key)
                            .is_some_and(|r| r.trim_start().starts_with('='))
                    })
                })
                .map(|i| i + 1);
            let line = key_line
                .or_else(|| {
                    e.span()
                        .map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1)
                })
                .map(|l| format!(":{l}"))
                .unwrap_or_default();
            anyhow::anyhow!(
                "{}{line}: {} (docs/config.md lists the sections and keys)",
                path.display(),
                e.message().trim_end().replace('\n', " ").replace('`', "")
            )
        })
    }
}

/// Raycasting (paper §3.1): `gs4city raycast`, config `[raycast]`.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RaycastTuning {
    /// Depth tolerance τ of the part pass, in metres (× the alignment scale).
    #[arg(long, value_name = "M", default_value_t = crate::raycast::TAU_M)]
    pub tau: f64,
    /// Single-pass raycasting (no part pass): the paper's ablation of the two-pass rule.
    #[arg(long)]
    pub single_pass: bool,
}

impl Default for RaycastTuning {
    fn default() -> Self {
        RaycastTuning {
            tau: crate::raycast::TAU_M,
            single_pass: false,
        }
    }
}

/// The contributions cache (`gs4city render --cache`), config `[cache]`.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CacheTuning {
    /// Longest contribution list per pixel (0 = no bound); with `--epsilon 0` the top-k by α·T.
    #[arg(long, default_value_t = crate::cache::TOP_K)]
    pub top_k: usize,
    /// Mass rule: a pixel keeps its largest α·T until they reach 1 − ε of its mass (at most
    /// --top-k); 0 = plain top-k lists.
    #[arg(long, default_value_t = crate::cache::EPSILON)]
    pub epsilon: f32,
    /// Early stop of the blend: a pixel stops once its transmittance falls below T (what lies
    /// behind, at most T of its mass, is not listed); 0 = the rasterizer's own stop only (exact
    /// lists).
    #[arg(long, value_name = "T", default_value_t = crate::cache::T_STOP)]
    pub t_stop: f32,
    /// The smallest α a Gaussian contributes with: the rasterizer's 1/255, or higher, which
    /// leaves the faint tails of Gaussians out of the lists and the blend.
    #[arg(long, value_name = "A", default_value_t = crate::cache::INRIA_ALPHA_MIN)]
    pub alpha_min: f32,
}

impl Default for CacheTuning {
    fn default() -> Self {
        let d = CacheOptions::default();
        CacheTuning {
            top_k: d.top_k,
            epsilon: d.epsilon,
            t_stop: d.t_stop,
            alpha_min: d.alpha_min,
        }
    }
}

impl CacheTuning {
    /// The cache options.
    pub fn options(&self) -> CacheOptions {
        CacheOptions {
            top_k: self.top_k,
            epsilon: self.epsilon,
            t_stop: self.t_stop,
            alpha_min: self.alpha_min,
        }
    }
}

/// SAM-family automatic masks on the CPU (`gs4city segment`, `run --model-dir`), config
/// `[segment]`.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SegmentTuning {
    /// Points per side of the prompt grid.
    #[arg(long, default_value_t = SegmentOptions::default().points_per_side)]
    pub points_per_side: usize,
    /// Prompts per decoder call.
    #[arg(long, default_value_t = SegmentOptions::default().points_per_batch)]
    pub points_per_batch: usize,
    /// Masks whose predicted IoU is not above this are dropped.
    #[arg(long, default_value_t = SegmentOptions::default().pred_iou_thresh)]
    pub pred_iou_thresh: f32,
    /// Masks whose stability score is below this are dropped.
    #[arg(long, default_value_t = SegmentOptions::default().stability_score_thresh)]
    pub stability_score_thresh: f64,
    /// Box IoU above which NMS drops the lower-scored mask.
    #[arg(long, default_value_t = SegmentOptions::default().box_nms_thresh)]
    pub box_nms_thresh: f64,
    /// Holes and islands smaller than this many pixels (at the segmentation scale) are
    /// removed; 0 = off.
    #[arg(long, default_value_t = SegmentOptions::default().min_mask_region_area)]
    pub min_mask_region_area: usize,
    /// Downscale factor of the images before segmentation (the reference pipeline's
    /// default_scale).
    #[arg(long, default_value_t = SegmentOptions::default().scale)]
    pub scale: f64,
    /// Encoder threads and decoder workers (0 = every core, at most 8 decoder workers).
    #[arg(long, default_value_t = SegmentOptions::default().threads)]
    pub threads: usize,
    /// Decode every prompt with ONNX Runtime; by default SAM's decoder is computed natively
    /// from the export's weights when they are found and agree with ONNX Runtime on a probe.
    #[arg(long)]
    pub onnx_decoder: bool,
}

impl Default for SegmentTuning {
    fn default() -> Self {
        let d = SegmentOptions::default();
        SegmentTuning {
            points_per_side: d.points_per_side,
            points_per_batch: d.points_per_batch,
            pred_iou_thresh: d.pred_iou_thresh,
            stability_score_thresh: d.stability_score_thresh,
            box_nms_thresh: d.box_nms_thresh,
            min_mask_region_area: d.min_mask_region_area,
            scale: d.scale,
            threads: d.threads,
            onnx_decoder: d.onnx_decoder,
        }
    }
}

impl SegmentTuning {
    /// The segmentation options, validated.
    pub fn options(&self) -> anyhow::Result<SegmentOptions> {
        let o = SegmentOptions {
            points_per_side: self.points_per_side,
            points_per_batch: self.points_per_batch,
            pred_iou_thresh: self.pred_iou_thresh,
            stability_score_thresh: self.stability_score_thresh,
            box_nms_thresh: self.box_nms_thresh,
            min_mask_region_area: self.min_mask_region_area,
            scale: self.scale,
            threads: self.threads,
            onnx_decoder: self.onnx_decoder,
            ..SegmentOptions::default()
        };
        o.validate()?;
        Ok(o)
    }
}

/// Mask filtering against the city model (paper §3.2; `gs4city masks`), config `[masks]`.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MasksTuning {
    /// Mask source: auto (the scene's SAM lists when it has masks/, else the mask-free depth
    /// source), sam, depth.
    #[arg(long, value_parser = named::<Source>, default_value = "auto")]
    pub source: Source,
    /// Disambiguation of high-overlap masks: auto (both with features and a cache, else the one
    /// available, else overlap), features, geometry, both, overlap.
    #[arg(long, value_parser = named::<Test>, default_value = "auto")]
    pub test: Test,
    /// τ_q: minimum predicted_iou.
    #[arg(long, default_value_t = MasksOptions::default().tau_q)]
    pub tau_q: f64,
    /// Support-only floor: a mask with floor ≤ predicted_iou < τ_q that passes every other rule
    /// is recorded as `low_quality_support` (the associate stage may let it join a group).
    #[arg(long, default_value_t = MasksOptions::default().support_floor.unwrap_or(0.0))]
    pub support_floor: f64,
    /// No support-only masks: every predicted_iou < τ_q is `quality` (as in the paper).
    #[arg(long)]
    pub no_support_floor: bool,
    /// τ_a as a fraction of the image's pixels (τ_a = ⌈f·H·W⌉).
    #[arg(long, default_value_t = MasksOptions::default().area_frac)]
    pub area_frac: f64,
    /// ρ: building-support overlap from which a mask is disambiguated.
    #[arg(long, default_value_t = MasksOptions::default().rho)]
    pub rho: f64,
    /// δ: margin of S_fore over S_city.
    #[arg(long, default_value_t = MasksOptions::default().delta, allow_negative_numbers = true)]
    pub delta: f64,
    /// 3DGS depth of the depth test: median (of the cache's lists) or expected (the cache's
    /// Σw·z/(1−T)).
    #[arg(long, value_parser = named::<GsDepth>, default_value = "median")]
    pub gs_depth: GsDepth,
    /// τ_occ in metres (× the alignment scale): how far in front of the city surface the 3DGS
    /// must be.
    #[arg(long, default_value_t = MasksOptions::default().tau_occ_m)]
    pub tau_occ: f64,
    /// Relative depth tolerance (fraction of the city depth) added to τ_occ.
    #[arg(long, default_value_t = MasksOptions::default().tau_rel)]
    pub tau_rel: f64,
    /// Radius (pixels) of the local city surface the 3DGS depth is compared with.
    #[arg(long, default_value_t = MasksOptions::default().surface_radius_px)]
    pub surface_radius: usize,
    /// Do not subtract each city surface's median 3DGS − city depth offset (it absorbs most
    /// of a misalignment).
    #[arg(long)]
    pub no_surface_bias: bool,
    /// Pixels a surface needs for its own depth offset (else its building's, else none).
    #[arg(long, default_value_t = MasksOptions::default().bias_min_px)]
    pub bias_min_px: usize,
    /// The surface offsets are clamped to ± this many metres (× the alignment scale).
    #[arg(long, default_value_t = MasksOptions::default().bias_max_m)]
    pub bias_max: f64,
    /// Share of a mask's depth-evidence pixels that must be in front to call it an occluder.
    #[arg(long, default_value_t = MasksOptions::default().occluder_share)]
    pub occluder_share: f64,
    /// Share of a mask's pixels that need depth evidence for the depth test to decide.
    #[arg(long, default_value_t = MasksOptions::default().min_evidence)]
    pub min_evidence: f64,
    /// Keep every low-overlap mask unchecked (the paper's rule); by default low-overlap masks
    /// that the features or the depth show to be building are dropped.
    #[arg(long)]
    pub keep_low_overlap: bool,
    /// Mask-free source: minimum 3DGS alpha of a pixel.
    #[arg(long, default_value_t = MasksOptions::default().min_alpha)]
    pub min_alpha: f64,
    /// Mask-free source: relative depth jump that splits two neighbouring pixels.
    #[arg(long, default_value_t = MasksOptions::default().split_rel)]
    pub split_rel: f64,
    /// Mask-free source: radius (pixels) of the morphological opening of the candidate pixels.
    #[arg(long, default_value_t = MasksOptions::default().open_px)]
    pub open_px: usize,
    /// Overlay PNGs (kept masks coloured by rule) for this many views.
    #[arg(long, default_value_t = MasksOptions::default().overlays)]
    pub overlays: usize,
}

impl Default for MasksTuning {
    fn default() -> Self {
        let d = MasksOptions::default();
        MasksTuning {
            source: d.source,
            test: d.test,
            tau_q: d.tau_q,
            support_floor: d.support_floor.unwrap_or(0.0),
            no_support_floor: d.support_floor.is_none(),
            area_frac: d.area_frac,
            rho: d.rho,
            delta: d.delta,
            gs_depth: d.gs_depth,
            tau_occ: d.tau_occ_m,
            tau_rel: d.tau_rel,
            surface_radius: d.surface_radius_px,
            no_surface_bias: !d.surface_bias,
            bias_min_px: d.bias_min_px,
            bias_max: d.bias_max_m,
            occluder_share: d.occluder_share,
            min_evidence: d.min_evidence,
            keep_low_overlap: !d.low_overlap_check,
            min_alpha: d.min_alpha,
            split_rel: d.split_rel,
            open_px: d.open_px,
            overlays: d.overlays,
        }
    }
}

impl MasksTuning {
    /// The masks stage's options, validated.
    pub fn options(&self) -> anyhow::Result<MasksOptions> {
        let o = MasksOptions {
            source: self.source,
            test: self.test,
            tau_q: self.tau_q,
            support_floor: (!self.no_support_floor).then_some(self.support_floor),
            area_frac: self.area_frac,
            rho: self.rho,
            delta: self.delta,
            gs_depth: self.gs_depth,
            tau_occ_m: self.tau_occ,
            tau_rel: self.tau_rel,
            surface_radius_px: self.surface_radius,
            surface_bias: !self.no_surface_bias,
            bias_min_px: self.bias_min_px,
            bias_max_m: self.bias_max,
            occluder_share: self.occluder_share,
            min_evidence: self.min_evidence,
            low_overlap_check: !self.keep_low_overlap,
            min_alpha: self.min_alpha,
            split_rel: self.split_rel,
            open_px: self.open_px,
            overlays: self.overlays,
        };
        o.validate()?;
        Ok(o)
    }
}

/// Windows and doors the images show but the city model lacks (docs/completeness.md), config
/// `[openings]` (the stage has no command of its own; `gs4city run` runs it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OpeningsTuning {
    /// `missing` (add the openings the model lacks to the semantic table and raycast the
    /// completed model again) or `off` (the completeness report only).
    pub add: Add,
    /// Where candidates come from: `features`, `geometry` or `both`.
    pub cues: Cues,
    /// m_view of the openings: an opening is added when at least this many training views show it.
    pub m_view: usize,
}

impl Default for OpeningsTuning {
    fn default() -> Self {
        let d = OpeningsOptions::default();
        OpeningsTuning {
            add: d.add,
            cues: d.cues,
            m_view: d.m_view,
        }
    }
}

impl OpeningsTuning {
    /// The openings stage's options, validated.
    pub fn options(&self) -> anyhow::Result<OpeningsOptions> {
        let o = OpeningsOptions {
            add: self.add,
            cues: self.cues,
            m_view: self.m_view,
            ..OpeningsOptions::default()
        };
        o.validate()?;
        Ok(o)
    }
}

/// Cross-view association (paper §3.2; `gs4city associate`), config `[associate]`.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AssociateTuning {
    /// How a mask's candidate Gaussians are found: weighted (the Gaussians contributing to the
    /// mask's pixels, by α·T) or projected (centres, front 20 % per cell: the paper's way).
    #[arg(long, value_parser = named::<CandidateMode>, default_value = "weighted")]
    pub candidates: CandidateMode,
    /// Geometric overlap R_geo a mask needs to join a group.
    #[arg(long, default_value_t = AssociateOptions::default().tau_geo)]
    pub tau_geo: f64,
    /// Feature cosine a mask needs to join a group (when features exist): the cap of the value
    /// calibrated on the scene's own mask pairs, or the value itself with --no-calibrate.
    #[arg(long, default_value_t = AssociateOptions::default().tau_sim)]
    pub tau_sim: f64,
    /// Use --tau-sim as given instead of calibrating it (docs/associate.md, "Calibration").
    #[arg(long)]
    pub no_calibrate: bool,
    /// m_view: groups seen in fewer views are dropped (the paper's is 3).
    #[arg(long, default_value_t = AssociateOptions::default().min_views)]
    pub min_views: usize,
    /// Groups farther than this many metres (× alignment scale) from every camera are dropped.
    #[arg(long, default_value_t = AssociateOptions::default().far_field_m)]
    pub far_field: f64,
    /// Skip the consolidation pass (the paper's single pass, order-dependent).
    #[arg(long)]
    pub no_consolidate: bool,
    /// Visit the views in this seeded random order (to measure order robustness).
    #[arg(long, value_name = "SEED")]
    pub shuffle_seed: Option<u64>,
    /// No view support from dropped masks (the paper's rule: only kept masks count).
    #[arg(long)]
    pub no_support: bool,
    /// With the view support, also label a matching dropped mask's unlabelled pixels with its
    /// group (off by default: the dropped masks' outlines are poor).
    #[arg(long)]
    pub support_pixels: bool,
    /// Support-only masks (`low_quality_support`) do not join groups (the ablation).
    #[arg(long)]
    pub no_support_masks: bool,
    /// Plain-mass ownership: a Gaussian belongs to the group whose masks put the most α·T on it
    /// (without this, a mask's mass counts per mask pixel, so a small object's mask beats a
    /// large mask that swallows it in more views).
    #[arg(long)]
    pub mass_owner: bool,
    /// The fill labels only pixels no kept mask labels.
    #[arg(long)]
    pub no_fill_over_masks: bool,
    /// Joining support-only masks also label their own unlabelled pixels with the group.
    #[arg(long)]
    pub support_mask_pixels: bool,
}

impl Default for AssociateTuning {
    fn default() -> Self {
        let d = AssociateOptions::default();
        AssociateTuning {
            candidates: d.candidates,
            tau_geo: d.tau_geo,
            tau_sim: d.tau_sim,
            no_calibrate: !d.calibrate,
            min_views: d.min_views,
            far_field: d.far_field_m,
            no_consolidate: !d.consolidate,
            shuffle_seed: d.shuffle_seed,
            no_support: !d.support,
            support_pixels: d.support_pixels,
            no_support_masks: !d.support_masks,
            mass_owner: !d.specific_owner,
            no_fill_over_masks: !d.fill_over_masks,
            support_mask_pixels: d.support_mask_pixels,
        }
    }
}

impl AssociateTuning {
    /// The association's options, validated.
    pub fn options(&self) -> anyhow::Result<AssociateOptions> {
        let o = AssociateOptions {
            candidates: self.candidates,
            tau_geo: self.tau_geo,
            tau_sim: self.tau_sim,
            calibrate: !self.no_calibrate,
            min_views: self.min_views,
            far_field_m: self.far_field,
            consolidate: !self.no_consolidate,
            shuffle_seed: self.shuffle_seed,
            support: !self.no_support,
            support_pixels: self.support_pixels,
            support_masks: !self.no_support_masks,
            specific_owner: !self.mass_owner,
            fill_over_masks: !self.no_fill_over_masks,
            support_mask_pixels: self.support_mask_pixels,
            ..AssociateOptions::default()
        };
        o.validate()?;
        Ok(o)
    }
}

/// Fusion (paper §3.2; `gs4city fuse`), config `[fuse]`.
#[derive(Debug, Clone, Default, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FuseTuning {
    /// No city-part snapping of windows and doors to the image's own masks.
    #[arg(long)]
    pub no_snap: bool,
}

impl FuseTuning {
    /// The fusion's options.
    pub fn options(&self) -> crate::fuse::FuseOptions {
        crate::fuse::FuseOptions {
            snap: !self.no_snap,
            ..Default::default()
        }
    }
}

/// The vote's gates and background bias (`gs4city lift`, and the vote `gs4city train` starts
/// from), config `[vote]`.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VoteTuning {
    /// Background bias γ in [-1, 1] (FlashSplat), added to the normalised background vote.
    /// Default: −1 with fused (mask) supervision, −0.5 with the city model alone.
    #[arg(long, allow_negative_numbers = true)]
    pub gamma: Option<f32>,
    /// Depth gate of city votes in metres: a Gaussian more than this in front of the city
    /// surface its pixel's ray hits takes no vote from that surface's label; 0 = off (with the
    /// centre gate).
    #[arg(long, value_name = "M", default_value_t = crate::vote::CITY_GATE_M)]
    pub city_gate_m: f32,
    /// No centre gate of city votes: without this, a city-labelled pixel gives no vote to a
    /// Gaussian whose centre projects onto a city label of another class in the same view.
    #[arg(long)]
    pub no_centre_gate: bool,
}

impl Default for VoteTuning {
    fn default() -> Self {
        let d = VoteOptions::default();
        VoteTuning {
            gamma: d.gamma,
            city_gate_m: d.city_gate_m,
            no_centre_gate: !d.centre_gate,
        }
    }
}

impl VoteTuning {
    /// Sets the vote's γ and gates in `o`.
    pub fn apply(&self, o: &mut VoteOptions) {
        o.gamma = self.gamma;
        o.city_gate_m = self.city_gate_m;
        o.centre_gate = !self.no_centre_gate;
    }
}

/// The vote's city-model prior in 3D (`gs4city lift`), config `[prior]`.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PriorTuning {
    /// Weight of the city-model prior: each Gaussian within --model-prior-m of a city-model
    /// triangle gets one vote for that triangle's label, of this share of the median Gaussian's
    /// vote weight; 0 = off.
    #[arg(long, default_value_t = crate::vote::MODEL_PRIOR)]
    pub model_prior: f32,
    /// Reach of the city-model prior in metres.
    #[arg(long, value_name = "M", default_value_t = crate::vote::MODEL_PRIOR_M)]
    pub model_prior_m: f32,
}

impl Default for PriorTuning {
    fn default() -> Self {
        let d = VoteOptions::default();
        PriorTuning {
            model_prior: d.model_prior,
            model_prior_m: d.model_prior_m,
        }
    }
}

impl PriorTuning {
    /// Sets the prior in `o`.
    pub fn apply(&self, o: &mut VoteOptions) {
        o.model_prior = self.model_prior;
        o.model_prior_m = self.model_prior_m;
    }
}

/// The vote's options from its two groups, validated.
pub fn vote_options(vote: &VoteTuning, prior: &PriorTuning) -> anyhow::Result<VoteOptions> {
    let mut o = VoteOptions::default();
    vote.apply(&mut o);
    prior.apply(&mut o);
    o.validate()?;
    Ok(o)
}

/// The test-view rule of a train command's prediction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RuleArg {
    Label,
    Class,
    Gaussians,
}

/// Identity learning (paper §3.3; `gs4city train`, `run --mode learned`), config `[train]`.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainTuning {
    /// Most iterations (one view and --pixels pixels each).
    #[arg(long, default_value_t = TrainOptions::default().iterations)]
    pub iterations: usize,
    /// Pixels sampled per iteration.
    #[arg(long, default_value_t = TrainOptions::default().pixels)]
    pub pixels: usize,
    /// Training pixels lie on a grid of this stride (1 = every pixel, 2 = a quarter, …).
    #[arg(long, default_value_t = TrainOptions::default().stride)]
    pub stride: usize,
    /// Cut the cached contribution lists to their K largest weights (0 = as cached).
    #[arg(long, default_value_t = TrainOptions::default().top_k)]
    pub top_k: usize,
    /// Sampled negative classes per softmax (cost independent of the number of labels).
    #[arg(long, default_value_t = 64, conflicts_with = "exact_softmax")]
    pub negatives: usize,
    /// Evaluate the softmax over every class during training (exact; cost grows with K).
    #[arg(long)]
    pub exact_softmax: bool,
    /// Predict test views over every class (exact; slower with many labels).
    #[arg(long)]
    pub exact_predict: bool,
    /// How test views are predicted: gaussians (each Gaussian's learned label rendered with the
    /// vote's pixel rule; best measured, docs/train.md), label (rendered code → classifier →
    /// the label of the largest logit, the paper's rule) or class (the class of largest total
    /// probability).
    #[arg(long, value_parser = named::<RuleArg>, default_value = "gaussians")]
    pub rule: RuleArg,
    /// Weight μ ∈ [0, 1] of the class-level term of the 2D loss; 0 = the label cross-entropy
    /// alone.
    #[arg(long, default_value_t = TrainOptions::default().class_weight)]
    pub class_weight: f64,
    /// Code dimension D.
    #[arg(long, default_value_t = TrainOptions::default().dim)]
    pub dim: usize,
    /// Adam learning rate of the codes.
    #[arg(long, default_value_t = TrainOptions::default().lr_codes)]
    pub lr_codes: f64,
    /// Adam learning rate of the classifier.
    #[arg(long, default_value_t = TrainOptions::default().lr_classifier)]
    pub lr_classifier: f64,
    /// Weight λ of the 3D KNN-KL term (0 = off).
    #[arg(long, default_value_t = TrainOptions::default().kl_lambda)]
    pub kl_lambda: f64,
    /// The 3D term every N iterations (0 = never).
    #[arg(long, default_value_t = TrainOptions::default().kl_every)]
    pub kl_every: usize,
    /// Neighbours per Gaussian in the 3D term.
    #[arg(long, default_value_t = TrainOptions::default().kl_k)]
    pub kl_k: usize,
    /// Gaussians sampled per 3D step.
    #[arg(long, default_value_t = TrainOptions::default().kl_samples)]
    pub kl_samples: usize,
    /// Start from random codes instead of the vote (the reference's start; for comparison).
    #[arg(long)]
    pub random_init: bool,
    /// Stop when the windowed loss falls by less than this fraction twice in a row (0 = never).
    #[arg(long, default_value_t = TrainOptions::default().tol)]
    pub tol: f64,
    /// Iterations per loss window.
    #[arg(long, default_value_t = TrainOptions::default().window)]
    pub window: usize,
    /// Random seed (same seed and inputs → same outputs, any thread count).
    #[arg(long, default_value_t = TrainOptions::default().seed)]
    pub seed: u64,
}

impl Default for TrainTuning {
    fn default() -> Self {
        let d = TrainOptions::default();
        TrainTuning {
            iterations: d.iterations,
            pixels: d.pixels,
            stride: d.stride,
            top_k: d.top_k,
            negatives: match d.softmax {
                Softmax::Sampled { negatives } => negatives,
                Softmax::Exact => 64,
            },
            exact_softmax: d.softmax == Softmax::Exact,
            exact_predict: d.exact_predict,
            rule: match d.rule {
                Rule::Label => RuleArg::Label,
                Rule::Class => RuleArg::Class,
                Rule::Gaussians => RuleArg::Gaussians,
            },
            class_weight: d.class_weight,
            dim: d.dim,
            lr_codes: d.lr_codes,
            lr_classifier: d.lr_classifier,
            kl_lambda: d.kl_lambda,
            kl_every: d.kl_every,
            kl_k: d.kl_k,
            kl_samples: d.kl_samples,
            random_init: d.init == Init::Random,
            tol: d.tol,
            window: d.window,
            seed: d.seed,
        }
    }
}

impl TrainTuning {
    /// The training's options with the vote's γ and gates, validated.
    pub fn options(&self, vote: &VoteTuning) -> anyhow::Result<TrainOptions> {
        let mut v = VoteOptions::default();
        vote.apply(&mut v);
        let o = TrainOptions {
            dim: self.dim,
            iterations: self.iterations,
            pixels: self.pixels,
            stride: self.stride,
            top_k: self.top_k,
            softmax: if self.exact_softmax {
                Softmax::Exact
            } else {
                Softmax::Sampled {
                    negatives: self.negatives,
                }
            },
            lr_codes: self.lr_codes,
            lr_classifier: self.lr_classifier,
            kl_lambda: self.kl_lambda,
            kl_every: self.kl_every,
            kl_k: self.kl_k,
            kl_samples: self.kl_samples,
            init: if self.random_init {
                Init::Random
            } else {
                Init::Vote
            },
            gamma: v.gamma,
            city_gate_m: v.city_gate_m,
            centre_gate: v.centre_gate,
            window: self.window,
            tol: self.tol,
            seed: self.seed,
            exact_predict: self.exact_predict,
            rule: match self.rule {
                RuleArg::Label => Rule::Label,
                RuleArg::Class => Rule::Class,
                RuleArg::Gaussians => Rule::Gaussians,
            },
            class_weight: self.class_weight,
            ..TrainOptions::default()
        };
        o.validate()?;
        Ok(o)
    }
}

/// The scene check's alignment verdict (`gs4city check`, the first step of `run`), config
/// `[check]`.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CheckTuning {
    /// Largest plausible distance (metres, lower quartile) between opaque Gaussian centres and
    /// the nearest city-model surface; beyond it the alignment is reported as off.
    #[arg(long, value_name = "M", default_value_t = crate::inspect::CheckOptions::default().max_offset_m)]
    pub max_offset: f64,
}

impl Default for CheckTuning {
    fn default() -> Self {
        CheckTuning {
            max_offset: crate::inspect::CheckOptions::default().max_offset_m,
        }
    }
}

/// `--test-every N` / `--split S` of the stages that label training views and predict test
/// views (lift, train, associate, fuse).
#[derive(Debug, Clone, Args)]
pub struct SplitArgs {
    /// Every N-th view (sorted by name) is a test view: not labelled, predicted as a novel view
    /// (3DGS's --eval: 8). Default: the split of --split, else every view trains.
    #[arg(long, value_name = "N", conflicts_with = "split")]
    pub test_every: Option<usize>,
    /// The test views a scene folder declares (S/scene.json: `gs4city synth` writes them), as
    /// `gs4city run --scene S` uses them.
    #[arg(long, value_name = "S")]
    pub split: Option<PathBuf>,
}

impl SplitArgs {
    /// The training and test views of `views`.
    pub fn split(&self, views: Vec<crate::camera::View>) -> anyhow::Result<Split> {
        let split = match (&self.test_every, &self.split) {
            (Some(n), _) => Split::new(views, *n),
            (None, Some(s)) => {
                let root = if s.is_file() {
                    s.parent().unwrap_or(Path::new(".")).to_path_buf()
                } else {
                    s.clone()
                };
                crate::scene::SceneMeta::read(&root)?
                    .with_context(|| {
                        format!(
                            "--split {}: no {} there",
                            s.display(),
                            crate::scene::SceneMeta::FILE
                        )
                    })?
                    .split(&root, views)?
            }
            (None, None) => Split::new(views, 0),
        };
        if split.train.is_empty() {
            anyhow::bail!("no training views: every view is a test view");
        }
        Ok(split)
    }
}

/// `--run R [--scene S] [--mode M]`: a finished run, for the commands that read one (query,
/// export, eval --by-query).
#[derive(Debug, Clone, Args)]
pub struct RunRef {
    /// A run folder (`gs4city run --scene S --out R`).
    #[arg(long, value_name = "R")]
    pub run: PathBuf,
    /// The scene folder the run was made from; default: the one recorded in R/run.json.
    #[arg(long, value_name = "S")]
    pub scene: Option<PathBuf>,
    /// Which per-Gaussian labels: vote (R/lift) or learned (R/train); default: learned when
    /// R/train/gaussians.npy exists.
    #[arg(long)]
    pub mode: Option<Mode>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct All {
        #[command(flatten)]
        raycast: RaycastTuning,
        #[command(flatten)]
        segment: SegmentTuning,
        #[command(flatten)]
        masks: MasksTuning,
        #[command(flatten)]
        associate: AssociateTuning,
        #[command(flatten)]
        fuse: FuseTuning,
        #[command(flatten)]
        vote: VoteTuning,
        #[command(flatten)]
        prior: PriorTuning,
        #[command(flatten)]
        check: CheckTuning,
    }

    #[derive(Debug, Parser)]
    struct Cache {
        #[command(flatten)]
        cache: CacheTuning,
    }

    #[derive(Debug, Parser)]
    struct Train {
        #[command(flatten)]
        train: TrainTuning,
    }

    /// Each group's defaults are its stage's: an empty command line parses to the group's
    /// `Default` (built from the stage's `*Options::default()`), and that gives back the
    /// stage's default options.
    #[test]
    fn an_empty_command_line_is_every_stage_default() {
        let a = All::try_parse_from(["x"]).unwrap();
        assert_eq!(a.raycast, RaycastTuning::default());
        assert_eq!(a.segment, SegmentTuning::default());
        assert_eq!(a.masks, MasksTuning::default());
        assert_eq!(a.associate, AssociateTuning::default());
        assert_eq!(a.fuse, FuseTuning::default());
        assert_eq!(a.vote, VoteTuning::default());
        assert_eq!(a.prior, PriorTuning::default());
        assert_eq!(a.check, CheckTuning::default());
        let c = Cache::try_parse_from(["x"]).unwrap().cache;
        assert_eq!(c, CacheTuning::default());
        let t = Train::try_parse_from(["x"]).unwrap().train;
        assert_eq!(t, TrainTuning::default());
        assert_eq!(a.masks.options().unwrap(), MasksOptions::default());
        assert_eq!(a.associate.options().unwrap(), AssociateOptions::default());
        assert_eq!(t.options(&a.vote).unwrap(), TrainOptions::default());
        assert_eq!(
            vote_options(&a.vote, &a.prior).unwrap(),
            VoteOptions::default()
        );
        assert_eq!(c.options(), CacheOptions::default());
        assert_eq!(a.segment.options().unwrap(), SegmentOptions::default());
        assert_eq!(
            OpeningsTuning::default().options().unwrap(),
            OpeningsOptions::default()
        );
        assert_eq!(
            a.fuse.options().snap,
            crate::fuse::FuseOptions::default().snap
        );
    }

    /// A flag given on the command line wins over the file's key; a flag left at its default
    /// does not.
    #[test]
    fn a_given_flag_wins_over_the_file_a_default_does_not() {
        let file: Config = Config::parse(
            Path::new("c.toml"),
            "[vote]\nno_centre_gate = true\ncity_gate_m = 0.25\n[associate]\nmin_views = 3\n",
        )
        .unwrap();
        assert!(file.vote.no_centre_gate);
        assert_eq!(file.vote.gamma, None);
        assert_eq!(file.associate.min_views, 3);
        assert_eq!(file.associate.tau_sim, AssociateOptions::default().tau_sim);
        let flags = All::try_parse_from(["x", "--gamma", "-0.5", "--city-gate-m", "0.5"]).unwrap();
        let given = |k: &str| ["gamma", "city_gate_m"].contains(&k);
        let m = merged_with(&file.vote, &flags.vote, given);
        assert_eq!(
            m,
            VoteTuning {
                gamma: Some(-0.5),
                city_gate_m: 0.5,
                no_centre_gate: true,
            }
        );
        // Nothing given: the file.
        assert_eq!(merged_with(&file.vote, &flags.vote, |_| false), file.vote);
    }

    /// Unknown sections and keys and wrong types are one line naming the file, the line and
    /// the key.
    #[test]
    fn config_errors_name_file_line_and_key() {
        for (text, line, what) in [
            ("[vote]\ncentre_gate = false\n", ":2:", "centre_gate"),
            ("[vote]\n\n[votes]\n", ":3:", "votes"),
            (
                "[associate]\nmin_views = \"three\"\n",
                ":2:",
                "invalid type",
            ),
            ("[masks]\nsource = \"clip\"\n", ":2:", "clip"),
        ] {
            let e = Config::parse(Path::new("c.toml"), text)
                .unwrap_err()
                .to_string();
            assert!(
                e.starts_with("c.toml") && e.contains(line) && e.contains(what),
                "{text:?}: {e}"
            );
            assert_eq!(e.lines().count(), 1, "{e}");
        }
    }

    /// docs/config.md names every section and key of the file, and the ablation configs in
    /// configs/ parse.
    #[test]
    fn docs_config_lists_every_key_and_the_configs_parse() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let doc = std::fs::read_to_string(root.join("docs/config.md")).unwrap();
        let all = serde_json::to_value(Config::default()).unwrap();
        for (section, keys) in all.as_object().unwrap() {
            assert!(doc.contains(&format!("[{section}]")), "[{section}]");
            for k in keys.as_object().unwrap().keys() {
                assert!(
                    doc.contains(&format!("`{k}`")),
                    "docs/config.md does not name [{section}] `{k}`"
                );
            }
        }
        let mut n = 0;
        for e in walk(&root.join("configs")) {
            if e.extension().is_some_and(|x| x == "toml") {
                Config::read(&e).unwrap_or_else(|err| panic!("{err}"));
                n += 1;
            }
        }
        assert!(n >= 8, "{n} configs");
    }

    fn walk(d: &Path) -> Vec<PathBuf> {
        let mut out = Vec::new();
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                out.extend(walk(&p));
            } else {
                out.push(p);
            }
        }
        out
    }
}
