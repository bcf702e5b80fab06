//! The paper's query-driven evaluation (§4: "each text query yields a binary prediction mask that
//! is compared against the corresponding ground truth"): the coarse level from the mask of a
//! "building" selection, each fine class from the mask of its own selection — the hybrid scheme:
//! semantic labels for the building classes (`category=wall|roof|window|door`), text queries
//! (`text("a tree")`, `"a person"`, `"a car"`) for the others where the run has per-label
//! features and the scene has the prompt, else their semantic labels (`category=tree` …).
//!
//! Masks are the query masks of [`crate::selection::masks`]; the arithmetic is the pure metric code of
//! [`crate::eval::metrics`]: per class `c`, the prediction map is `c` on the mask and −1
//! elsewhere, so the one-vs-rest confusion of `c` over the GT fine pixels is exactly that of the
//! class-map evaluation with this mask as class `c`. Masks of different classes may overlap, so
//! there is no single confusion matrix (the `confusion` field is empty).
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use super::{
    CoarseJson, Counts, DatasetJson, EvalError, FineJson, ImageJson, Mean, MetricsJson, N_FINE,
    PaperJson, accumulate, dataset, paper,
};
use crate::cache::Cache;
use crate::classes::{self, FINE};
use crate::selection::{MaskRule, SemanticRun, TextMatch, TextOptions};

/// The selection expression of the coarse "building" mask.
pub const BUILDING: &str = "class=Building or class=BuildingPart or category=wall or category=roof or category=window or category=door or category=ground_surface or category=installation";

/// The prompt used for a non-building fine class in text mode.
fn prompt_for(class: i32) -> Option<&'static str> {
    match class {
        classes::TREE => Some("a tree"),
        classes::PERSON => Some("a person"),
        classes::CAR => Some("a car"),
        _ => None,
    }
}

/// The selection of each fine class ([`FINE`] order): text for tree/person/car where the run
/// has label features and the scene's prompts hold the prompt, else the category.
pub fn class_queries(sr: &SemanticRun) -> [String; N_FINE] {
    std::array::from_fn(|k| {
        let c = FINE[k];
        let has_prompt = |p: &str| {
            sr.prompts
                .as_ref()
                .is_some_and(|(pr, _)| pr.prompts.keys().any(|k| k.trim().eq_ignore_ascii_case(p)))
        };
        match prompt_for(c) {
            Some(p) if sr.features.is_some() && has_prompt(p) => format!("text(\"{p}\")"),
            _ => format!("category={}", classes::name(c)),
        }
    })
}

/// `metrics_by_query.json`.
#[derive(Debug, Clone, Serialize)]
pub struct ByQuery {
    pub protocol: &'static str,
    pub mode: crate::layout::Mode,
    pub mask_rule: MaskRule,
    /// The selection behind each mask: `building`, then each fine class.
    pub queries: BTreeMap<&'static str, String>,
    /// Gaussians selected by each query.
    pub gaussians: BTreeMap<&'static str, usize>,
    /// The text terms' outcomes (score, threshold, negatives).
    pub text: Vec<TextMatch>,
    /// The metrics, in the layout of `eval/metrics.json` (no confusion matrix).
    pub metrics: MetricsJson,
    /// The printed tables.
    pub tables: String,
}

fn mean(xs: &[f64]) -> Mean {
    Mean {
        mean: super::metrics::mean_of(xs),
        images: xs.len(),
    }
}

/// Fine figures of one image (or the dataset) from the per-class counts `per[k]`.
fn fine_json(per: &[Counts; N_FINE]) -> FineJson {
    FineJson::per_class(|k| &per[k])
}

/// Evaluates the query masks of `stems` against `gt_dir/<stem>.class.npy`.
pub fn evaluate(
    sr: &SemanticRun,
    cache: &Cache,
    gt_dir: &Path,
    stems: &[String],
    rule: MaskRule,
    text: TextOptions,
) -> Result<ByQuery, EvalError> {
    let fine_q = class_queries(sr);
    let mut texts = Vec::new();
    let mut selections = Vec::with_capacity(1 + N_FINE);
    let mut gaussians = BTreeMap::new();
    let mut queries = BTreeMap::new();
    for (name, q) in std::iter::once(("building", BUILDING.to_string())).chain(
        FINE.iter()
            .zip(&fine_q)
            .map(|(&c, q)| (classes::name(c), q.clone())),
    ) {
        let (_, sel) = sr.select_text("--by-query", &q, text)?;
        texts.extend(sel.text.iter().cloned());
        let s = sr.gaussian_selection(&sel.labels);
        gaussians.insert(name, s.iter().filter(|&&x| x).count());
        queries.insert(name, q);
        selections.push(s);
    }
    // Every selection's mask of a view in one pass over its lists.
    let together = {
        let selected: Vec<&[bool]> = selections.iter().map(Vec::as_slice).collect();
        crate::selection::masks::Selections::new(&sr.class_of, &selected)
    };
    let gts = super::list_maps(gt_dir)?;
    let bar = crate::progress::Bar::new("eval", stems.len() as u64, "views");
    // One view's row, coarse counts and per-class counts.
    type ViewEval = (ImageJson, Counts, [Counts; N_FINE]);
    // The views in parallel, each from its own reading of the cache (one decoded view per
    // running task in memory); collected in view order (every view is evaluated, then the
    // first error in that order is returned).
    let per_view = |stem: &String| -> Result<ViewEval, EvalError> {
        let gpath = gts.get(stem).ok_or_else(|| EvalError::MissingGroundTruth {
            stem: stem.clone(),
            dir: gt_dir.to_path_buf(),
        })?;
        let (gsize, gt) = super::load_map(gpath)?;
        if let Some(i) = gt.iter().position(|&v| !(-1..=11).contains(&v)) {
            return Err(EvalError::GtValue {
                path: gpath.clone(),
                value: gt[i],
                row: i / gsize[1],
                col: i % gsize[1],
            });
        }
        let c = cache.load(stem)?;
        let psize = [c.height, c.width];
        let masks = together.masks(&c, rule);
        let pred_map = |m: &[u8], class: i32| -> Vec<i32> {
            let p: Vec<i32> = m.iter().map(|&x| if x != 0 { class } else { -1 }).collect();
            if psize == gsize {
                p
            } else {
                super::resize_nearest(&p, psize, gsize)
            }
        };
        let cb = accumulate(&gt, &pred_map(&masks[0], classes::WALL));
        let pc: [Counts; N_FINE] =
            std::array::from_fn(|k| accumulate(&gt, &pred_map(&masks[1 + k], FINE[k])));
        let image = ImageJson {
            stem: stem.clone(),
            gt_size: gsize,
            pred_size: psize,
            resized: psize != gsize,
            valid_pixels: cb.valid,
            ignored_pixels: cb.ignored,
            unknown_pred_values: 0,
            coarse: (cb.valid > 0).then(|| CoarseJson {
                counts: cb.coarse,
                metrics: cb.coarse.coarse_metrics(),
            }),
            fine: (cb.fine_pixels() > 0).then(|| fine_json(&pc)),
        };
        bar.inc(1);
        Ok((image, cb, pc))
    };
    let done: Vec<Result<ViewEval, EvalError>> = stems.par_iter().map(per_view).collect();
    let mut coarse: Vec<Counts> = Vec::with_capacity(done.len());
    let mut per: Vec<[Counts; N_FINE]> = Vec::with_capacity(done.len());
    let mut images = Vec::with_capacity(done.len());
    for d in done {
        let (image, cb, pc) = d?;
        images.push(image);
        coarse.push(cb);
        per.push(pc);
    }
    bar.finish();
    // Paper protocol: coarse from the building masks; per class over the images holding it;
    // image mIoU over the classes present in that image.
    let pc = paper(&coarse);
    let class_counts = |k: usize| -> Vec<Counts> { per.iter().map(|p| p[k].clone()).collect() };
    let class_paper: Vec<super::PaperMetrics> =
        (0..N_FINE).map(|k| paper(&class_counts(k))).collect();
    let image_miou: Vec<f64> = images
        .iter()
        .filter_map(|i| i.fine.as_ref().and_then(|f| f.miou))
        .collect();
    let d_coarse = dataset(&coarse);
    let summed: [Counts; N_FINE] = std::array::from_fn(|k| dataset(&class_counts(k)).counts);
    let mut definitions = super::definitions();
    definitions.insert(
        "by_query",
        "Query-driven evaluation (paper section 4): coarse = the mask of the `building` selection predicted as building; each fine class c = the mask of its own selection predicted as c, -1 elsewhere; one-vs-rest counts per class as in the class-map evaluation. Masks of different classes may overlap, so there is no confusion matrix.",
    );
    definitions.remove("confusion");
    let metrics = MetricsJson {
        mode: Some(sr.mode.dir().to_string()),
        definitions,
        fine_classes: FINE.iter().map(|&c| classes::name(c)).collect(),
        confusion_columns: vec![],
        images: images.len(),
        predictions_without_gt: vec![],
        resized_predictions: images.iter().filter(|i| i.resized).count(),
        paper: PaperJson {
            images_coarse: images.len() - pc.coarse_skipped,
            images_fine: images.len() - pc.fine_skipped,
            coarse_skipped_no_valid_gt: pc.coarse_skipped,
            fine_skipped_no_fine_gt: pc.fine_skipped,
            coarse: BTreeMap::from([
                ("iou", pc.iou),
                ("accuracy", pc.accuracy),
                ("precision", pc.precision),
                ("recall", pc.recall),
                ("f1", pc.f1),
            ]),
            miou: mean(&image_miou),
            iou: super::by_class(|k| class_paper[k].class_iou[k]),
            precision: super::by_class(|k| class_paper[k].class_precision[k]),
            recall: super::by_class(|k| class_paper[k].class_recall[k]),
        },
        dataset: DatasetJson {
            valid_pixels: d_coarse.counts.valid,
            ignored_pixels: d_coarse.counts.ignored,
            coarse: CoarseJson {
                counts: d_coarse.counts.coarse,
                metrics: d_coarse.coarse,
            },
            fine: fine_json(&summed),
        },
        per_image: images,
    };
    let tables = super::tables(&metrics);
    Ok(ByQuery {
        protocol: "by-query",
        mode: sr.mode,
        mask_rule: rule,
        queries,
        gaussians,
        text: texts,
        metrics,
        tables,
    })
}
