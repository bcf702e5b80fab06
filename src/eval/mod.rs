//! Evaluation (GS4City §4, a stage): compares predicted per-view class maps with the
//! ground truth, at the coarse level (building vs non-building: IoU, accuracy, precision,
//! recall, F1) and the fine level (wall, roof, window, door, tree, person, car: per-class
//! IoU, precision, recall and mIoU), both with the paper's protocol (per image, then the
//! mean over images) and at the dataset level (counts summed over all images).
//!
//! Files: GT `<gt>/<stem>.class.npy` and prediction `<pred>/<stem>.class.npy`, int32 H×W
//! (`docs/design.md`). A missing prediction is an error; a prediction without GT is a warning. A
//! prediction of another size but the same aspect ratio (within 1 % or one pixel's rounding)
//! is resized to the GT size by nearest neighbour (pixel centres: source index
//! `⌊(2i+1)·src/(2·dst)⌋`, as PIL `Image.NEAREST`), with a warning; another aspect ratio is an
//! error (another image).
//! The metric arithmetic lives in [`metrics`] (pure functions over arrays).
pub mod by_query;
pub mod metrics;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::classes::{self, FINE};
use crate::fsutil::{self, FsError};
use crate::idmap;
use crate::npy::NpyError;
pub use metrics::{
    BinaryCounts, BinaryMetrics, ClassMetrics, Counts, DatasetMetrics, FineMetrics, Mean, N_FINE,
    OTHER_COL, PaperMetrics, accumulate, dataset, fine_metrics, paper,
};

use crate::idmap::CLASS_SUFFIX as SUFFIX;

/// Errors of the evaluation stage.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error(transparent)]
    IdMap(#[from] idmap::IdMapError),
    #[error(transparent)]
    Selection(#[from] crate::selection::SelectionError),
    #[error(transparent)]
    Cache(#[from] crate::cache::CacheError),
    #[error(
        "{path}: ground-truth value {value} at row {row}, column {col} is not a class id (−1..=11)"
    )]
    GtValue {
        path: PathBuf,
        value: i32,
        row: usize,
        col: usize,
    },
    #[error(
        "{path}: a {}×{} prediction for the {}×{} ground truth {}: another aspect ratio, so \
         another image (a prediction of another size is only resized when its shape is the \
         ground truth's)",
        pred[0], pred[1], gt[0], gt[1], gt_path.display()
    )]
    Shape {
        path: PathBuf,
        gt_path: PathBuf,
        pred: [usize; 2],
        gt: [usize; 2],
    },
    #[error("no prediction for ground-truth view '{stem}': expected {path}")]
    MissingPrediction { stem: String, path: PathBuf },
    #[error("{dir}: no ground-truth class maps (*{SUFFIX})")]
    NoGroundTruth { dir: PathBuf },
    #[error("{dir}: no ground truth for the requested view '{stem}'")]
    MissingGroundTruth { stem: String, dir: PathBuf },
}

/// The `<stem>` → path map of the `*.class.npy` files of a folder.
pub fn list_maps(dir: &Path) -> Result<BTreeMap<String, PathBuf>, EvalError> {
    Ok(idmap::list_class_maps(dir)?)
}

/// Reads an int32 H×W class map; returns `([H, W], data)`.
pub fn load_map(path: &Path) -> Result<([usize; 2], Vec<i32>), EvalError> {
    Ok(idmap::read_any_map(path)?)
}

/// Nearest-neighbour resize of a `src` (H×W) map to `dst` (H×W), sampling at pixel
/// centres: destination index `i` reads source index `⌊(2i+1)·src/(2·dst)⌋`.
pub fn resize_nearest(data: &[i32], src: [usize; 2], dst: [usize; 2]) -> Vec<i32> {
    assert_eq!(
        data.len(),
        src[0] * src[1],
        "resize_nearest: bad source size"
    );
    let index = |n_src: usize, n_dst: usize| -> Vec<usize> {
        (0..n_dst)
            .map(|i| ((2 * i + 1) * n_src / (2 * n_dst)).min(n_src - 1))
            .collect()
    };
    let (rows, cols) = (index(src[0], dst[0]), index(src[1], dst[1]));
    let mut out = Vec::with_capacity(dst[0] * dst[1]);
    for &r in &rows {
        let row = &data[r * src[1]..(r + 1) * src[1]];
        out.extend(cols.iter().map(|&c| row[c]));
    }
    out
}

/// The evaluation of one view.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageEval {
    pub stem: String,
    pub gt_size: [usize; 2],
    pub pred_size: [usize; 2],
    /// Prediction values outside −1..=11 (counted as wrong, non-building).
    pub unknown_pred_values: u64,
    pub counts: Counts,
}

impl ImageEval {
    pub fn resized(&self) -> bool {
        self.gt_size != self.pred_size
    }
}

/// Whether an `[h, w]` map is the ground truth's image at another resolution: the aspect
/// ratios agree within 1 % or within the rounding of one pixel on either side.
fn same_shape(pred: [usize; 2], gt: [usize; 2]) -> bool {
    let (ph, pw, gh, gw) = (pred[0] as f64, pred[1] as f64, gt[0] as f64, gt[1] as f64);
    let cross = (ph * gw - gh * pw).abs();
    cross <= 0.01 * gh * pw || cross <= gw + pw
}

/// Evaluates one view from its files.
pub fn evaluate_view(stem: &str, gt_path: &Path, pred_path: &Path) -> Result<ImageEval, EvalError> {
    let (gt_size, gt) = load_map(gt_path)?;
    if let Some(i) = gt.iter().position(|&v| !(-1..=11).contains(&v)) {
        return Err(EvalError::GtValue {
            path: gt_path.to_path_buf(),
            value: gt[i],
            row: i / gt_size[1],
            col: i % gt_size[1],
        });
    }
    let (pred_size, mut pred) = load_map(pred_path)?;
    if !same_shape(pred_size, gt_size) {
        return Err(EvalError::Shape {
            path: pred_path.to_path_buf(),
            gt_path: gt_path.to_path_buf(),
            pred: pred_size,
            gt: gt_size,
        });
    }
    if pred_size != gt_size {
        pred = resize_nearest(&pred, pred_size, gt_size);
    }
    let unknown_pred_values = pred.iter().filter(|&&v| !(-1..=11).contains(&v)).count() as u64;
    Ok(ImageEval {
        stem: stem.to_string(),
        gt_size,
        pred_size,
        unknown_pred_values,
        counts: accumulate(&gt, &pred),
    })
}

/// The evaluation of two folders.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    /// One per GT view, sorted by stem.
    pub images: Vec<ImageEval>,
    /// Prediction stems without GT (not evaluated).
    pub predictions_without_gt: Vec<String>,
    pub warnings: Vec<String>,
}

/// Pairs the class maps of `pred` and `gt` by stem and evaluates every GT view.
pub fn evaluate_dirs(pred: &Path, gt: &Path) -> Result<Evaluation, EvalError> {
    evaluate_dirs_for(pred, gt, None)
}

/// As [`evaluate_dirs`], restricted to the GT views named in `stems` (e.g. the test views);
/// a named stem without GT is an error.
pub fn evaluate_dirs_for(
    pred: &Path,
    gt: &Path,
    stems: Option<&[String]>,
) -> Result<Evaluation, EvalError> {
    let mut gts = list_maps(gt)?;
    if let Some(stems) = stems {
        for s in stems {
            if !gts.contains_key(s) {
                return Err(EvalError::MissingGroundTruth {
                    stem: s.clone(),
                    dir: gt.to_path_buf(),
                });
            }
        }
        gts.retain(|k, _| stems.contains(k));
    }
    if gts.is_empty() {
        return Err(EvalError::NoGroundTruth {
            dir: gt.to_path_buf(),
        });
    }
    let preds = list_maps(pred)?;
    let pairs = gts
        .iter()
        .map(|(stem, g)| match preds.get(stem) {
            Some(p) => Ok((stem, g, p)),
            None => Err(EvalError::MissingPrediction {
                stem: stem.clone(),
                path: pred.join(format!("{stem}{SUFFIX}")),
            }),
        })
        .collect::<Result<Vec<_>, _>>()?;
    let images = pairs
        .par_iter()
        .map(|(stem, g, p)| evaluate_view(stem, g, p))
        .collect::<Result<Vec<_>, _>>()?;
    let predictions_without_gt: Vec<String> = preds
        .keys()
        .filter(|s| !gts.contains_key(*s))
        .cloned()
        .collect();
    let mut warnings = Vec::new();
    if !predictions_without_gt.is_empty() {
        warnings.push(format!(
            "{} prediction(s) without ground truth, not evaluated: {}",
            predictions_without_gt.len(),
            list_some(&predictions_without_gt)
        ));
    }
    let resized: Vec<String> = images
        .iter()
        .filter(|i| i.resized())
        .map(|i| {
            format!(
                "{} ({}×{} → {}×{})",
                i.stem, i.pred_size[0], i.pred_size[1], i.gt_size[0], i.gt_size[1]
            )
        })
        .collect();
    if !resized.is_empty() {
        warnings.push(format!(
            "{} prediction(s) of another size than their GT, resized (nearest) to the GT size: {}",
            resized.len(),
            list_some(&resized)
        ));
    }
    let unknown: Vec<String> = images
        .iter()
        .filter(|i| i.unknown_pred_values > 0)
        .map(|i| format!("{} ({} px)", i.stem, i.unknown_pred_values))
        .collect();
    if !unknown.is_empty() {
        warnings.push(format!(
            "{} prediction(s) hold values outside −1..=11, counted as wrong non-building: {}",
            unknown.len(),
            list_some(&unknown)
        ));
    }
    let no_valid: Vec<String> = images
        .iter()
        .filter(|i| i.counts.valid == 0)
        .map(|i| i.stem.clone())
        .collect();
    if !no_valid.is_empty() {
        warnings.push(format!(
            "{} view(s) have no valid GT pixel (all −1), skipped in the per-image means: {}",
            no_valid.len(),
            list_some(&no_valid)
        ));
    }
    Ok(Evaluation {
        images,
        predictions_without_gt,
        warnings,
    })
}

fn list_some(items: &[String]) -> String {
    const MAX: usize = 10;
    let mut s = items[..items.len().min(MAX)].join(", ");
    if items.len() > MAX {
        s.push_str(&format!(", … ({} more)", items.len() - MAX));
    }
    s
}

// ---------------------------------------------------------------------------------------
// metrics.json

type ByClass<T> = BTreeMap<&'static str, T>;

pub(crate) fn by_class<T>(f: impl Fn(usize) -> T) -> ByClass<T> {
    FINE.iter()
        .enumerate()
        .map(|(k, &c)| (classes::name(c), f(k)))
        .collect()
}

/// Coarse counts and ratios.
#[derive(Debug, Clone, Serialize)]
pub struct CoarseJson {
    #[serde(flatten)]
    pub counts: BinaryCounts,
    #[serde(flatten)]
    pub metrics: BinaryMetrics,
}

/// Fine counts and ratios of one image or of the dataset.
#[derive(Debug, Clone, Serialize)]
pub struct FineJson {
    /// GT pixels of a fine class.
    pub pixels: u64,
    pub miou: Option<f64>,
    pub classes_present: Vec<&'static str>,
    pub iou: ByClass<Option<f64>>,
    pub precision: ByClass<Option<f64>>,
    pub recall: ByClass<Option<f64>>,
    pub gt_pixels: ByClass<u64>,
    pub pred_pixels: ByClass<u64>,
    pub tp: ByClass<u64>,
    /// Rows: GT class in `fine_classes` order; columns: predicted class in that order, then
    /// "other" (any prediction that is not a fine class, −1 included).
    pub confusion: Vec<Vec<u64>>,
}

impl FineJson {
    fn new(c: &Counts) -> FineJson {
        let mut f = FineJson::per_class(|_| c);
        f.confusion = c.fine.iter().map(|r| r.to_vec()).collect();
        f
    }

    /// The fine figures where class `k`'s come from `counts_of(k)`: the same counts for every
    /// class in a class-map evaluation, one query mask per class in [`by_query`] (masks of
    /// different classes may overlap, so there is no confusion matrix: it is left empty).
    pub fn per_class<'a>(counts_of: impl Fn(usize) -> &'a Counts) -> FineJson {
        let m: [Option<ClassMetrics>; N_FINE] =
            std::array::from_fn(|k| fine_metrics(counts_of(k)).classes[k]);
        let ious: Vec<f64> = m.iter().flatten().map(|c| c.iou).collect();
        let get = |f: fn(&ClassMetrics) -> f64| by_class(|k| m[k].as_ref().map(f));
        FineJson {
            pixels: counts_of(0).fine_pixels(),
            miou: metrics::mean_of(&ious),
            classes_present: FINE
                .iter()
                .enumerate()
                .filter(|(k, _)| m[*k].is_some())
                .map(|(_, &id)| classes::name(id))
                .collect(),
            iou: get(|c| c.iou),
            precision: get(|c| c.precision),
            recall: get(|c| c.recall),
            gt_pixels: by_class(|k| counts_of(k).fine_gt(k)),
            pred_pixels: by_class(|k| counts_of(k).fine_pred(k)),
            tp: by_class(|k| counts_of(k).fine[k][k]),
            confusion: vec![],
        }
    }
}

/// One per-image row of `metrics.json`.
#[derive(Debug, Clone, Serialize)]
pub struct ImageJson {
    pub stem: String,
    pub gt_size: [usize; 2],
    pub pred_size: [usize; 2],
    pub resized: bool,
    pub valid_pixels: u64,
    pub ignored_pixels: u64,
    pub unknown_pred_values: u64,
    /// `null` when the image has no valid GT pixel (skipped at the coarse level).
    pub coarse: Option<CoarseJson>,
    /// `null` when the image has no GT pixel of a fine class (skipped at the fine level).
    pub fine: Option<FineJson>,
}

/// The paper protocol section of `metrics.json`.
#[derive(Debug, Clone, Serialize)]
pub struct PaperJson {
    pub images_coarse: usize,
    pub images_fine: usize,
    pub coarse_skipped_no_valid_gt: usize,
    pub fine_skipped_no_fine_gt: usize,
    pub coarse: BTreeMap<&'static str, Mean>,
    pub miou: Mean,
    pub iou: ByClass<Mean>,
    pub precision: ByClass<Mean>,
    pub recall: ByClass<Mean>,
}

/// The dataset-level section of `metrics.json`.
#[derive(Debug, Clone, Serialize)]
pub struct DatasetJson {
    pub valid_pixels: u64,
    pub ignored_pixels: u64,
    pub coarse: CoarseJson,
    pub fine: FineJson,
}

/// `metrics.json`.
#[derive(Debug, Clone, Serialize)]
pub struct MetricsJson {
    /// Which predictions were scored (`run --mode`: `vote` or `learned`), where known.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mode: Option<String>,
    pub definitions: BTreeMap<&'static str, &'static str>,
    pub fine_classes: Vec<&'static str>,
    pub confusion_columns: Vec<&'static str>,
    pub images: usize,
    pub predictions_without_gt: Vec<String>,
    pub resized_predictions: usize,
    pub paper: PaperJson,
    pub dataset: DatasetJson,
    pub per_image: Vec<ImageJson>,
}

/// The definitions written into `metrics.json`.
pub fn definitions() -> BTreeMap<&'static str, &'static str> {
    BTreeMap::from([
        (
            "pixels",
            "Only GT pixels with a class (GT >= 0) are evaluated; GT -1 is ignored. A prediction -1 means 'no class'. Predictions of another size are resized to the GT size by nearest neighbour at pixel centres (src = floor((2i+1)*n_src/(2*n_dst))).",
        ),
        (
            "coarse",
            "Building = class 0..=5 (wall roof window door ground_surface installation), positive; everything else, prediction -1 included, is non-building. iou = tp/(tp+fp+fn), accuracy = (tp+tn)/(tp+fp+fn+tn), precision = tp/(tp+fp), recall = tp/(tp+fn), f1 = 2tp/(2tp+fp+fn).",
        ),
        (
            "fine",
            "Only GT pixels of a fine class (wall roof window door tree person car) are evaluated; a prediction of any other value there (-1 included) is wrong. Per class c (one vs rest over those pixels): iou = tp/(tp+fp+fn), precision = tp/(tp+fp), recall = tp/(tp+fn). Predictions on GT pixels of non-fine classes are not counted.",
        ),
        (
            "undefined",
            "A ratio with a zero denominator is null and left out of every mean, except precision when the positive class is present in GT but never predicted, which is 0. A class present in GT but never predicted has IoU 0.",
        ),
        (
            "paper",
            "The paper protocol (REFERENCE.md section 6): metrics per image, then the mean over images. Coarse means skip images without a valid GT pixel. Image mIoU = mean IoU over the fine classes present in that image's GT; paper miou = mean of image mIoU over images with a fine GT pixel. Per-class values = mean over the images whose GT holds the class. Each mean carries the number of images behind it.",
        ),
        (
            "dataset",
            "Counts (coarse confusion, 7x8 fine confusion) summed over all images, then the ratios. Classes absent from the whole GT are null and excluded from the dataset miou = mean IoU over the classes present in the GT.",
        ),
        (
            "confusion",
            "confusion[g][p]: GT fine class g (fine_classes order) predicted as fine class p; the last column ('other') counts every prediction that is not a fine class.",
        ),
    ])
}

/// Builds `metrics.json` from an evaluation.
pub fn metrics_json(ev: &Evaluation) -> MetricsJson {
    let counts: Vec<Counts> = ev.images.iter().map(|i| i.counts.clone()).collect();
    let p = paper(&counts);
    let d = dataset(&counts);
    let coarse = BTreeMap::from([
        ("iou", p.iou),
        ("accuracy", p.accuracy),
        ("precision", p.precision),
        ("recall", p.recall),
        ("f1", p.f1),
    ]);
    MetricsJson {
        mode: None,
        definitions: definitions(),
        fine_classes: FINE.iter().map(|&c| classes::name(c)).collect(),
        confusion_columns: FINE
            .iter()
            .map(|&c| classes::name(c))
            .chain(["other"])
            .collect(),
        images: ev.images.len(),
        predictions_without_gt: ev.predictions_without_gt.clone(),
        resized_predictions: ev.images.iter().filter(|i| i.resized()).count(),
        paper: PaperJson {
            images_coarse: ev.images.len() - p.coarse_skipped,
            images_fine: ev.images.len() - p.fine_skipped,
            coarse_skipped_no_valid_gt: p.coarse_skipped,
            fine_skipped_no_fine_gt: p.fine_skipped,
            coarse,
            miou: p.miou,
            iou: by_class(|k| p.class_iou[k]),
            precision: by_class(|k| p.class_precision[k]),
            recall: by_class(|k| p.class_recall[k]),
        },
        dataset: DatasetJson {
            valid_pixels: d.counts.valid,
            ignored_pixels: d.counts.ignored,
            coarse: CoarseJson {
                counts: d.counts.coarse,
                metrics: d.coarse,
            },
            fine: FineJson::new(&d.counts),
        },
        per_image: ev
            .images
            .iter()
            .map(|i| ImageJson {
                stem: i.stem.clone(),
                gt_size: i.gt_size,
                pred_size: i.pred_size,
                resized: i.resized(),
                valid_pixels: i.counts.valid,
                ignored_pixels: i.counts.ignored,
                unknown_pred_values: i.unknown_pred_values,
                coarse: (i.counts.valid > 0).then(|| CoarseJson {
                    counts: i.counts.coarse,
                    metrics: i.counts.coarse.coarse_metrics(),
                }),
                fine: (i.counts.fine_pixels() > 0).then(|| FineJson::new(&i.counts)),
            })
            .collect(),
    }
}

// ---------------------------------------------------------------------------------------
// The printed tables

/// Class order of the paper's tables.
const TABLE_ORDER: [i32; 7] = [
    classes::DOOR,
    classes::ROOF,
    classes::WALL,
    classes::WINDOW,
    classes::CAR,
    classes::PERSON,
    classes::TREE,
];

fn pct(v: Option<f64>) -> String {
    v.map_or_else(|| "—".to_string(), |v| format!("{:.2}", 100.0 * v))
}

/// Table 1 (coarse IoU Acc Prec Rec | mIoU and per-class IoU) and Table 2 (per-class
/// precision) of the paper, in %, one row per protocol; "—" where undefined.
pub fn tables(m: &MetricsJson) -> String {
    let names: Vec<&str> = TABLE_ORDER.iter().map(|&c| classes::name(c)).collect();
    let mut s = String::new();
    let head: Vec<String> = ["IoU", "Acc", "Prec", "Rec", "mIoU"]
        .iter()
        .map(|h| h.to_string())
        .chain(names.iter().map(|n| capitalise(n)))
        .collect();
    s.push_str(&format!("Table 1 (%)        | Coarse{:>25} | Fine\n", ""));
    s.push_str(&format!("{:<18} |", "protocol"));
    for (i, h) in head.iter().enumerate() {
        if i == 4 {
            s.push_str(" |");
        }
        s.push_str(&format!(" {h:>7}"));
    }
    s.push('\n');
    let paper_row: Vec<Option<f64>> = ["iou", "accuracy", "precision", "recall"]
        .iter()
        .map(|k| m.paper.coarse[k].mean)
        .chain([m.paper.miou.mean])
        .chain(
            TABLE_ORDER
                .iter()
                .map(|&c| m.paper.iou[classes::name(c)].mean),
        )
        .collect();
    let d = &m.dataset;
    let data_row: Vec<Option<f64>> = [
        d.coarse.metrics.iou,
        d.coarse.metrics.accuracy,
        d.coarse.metrics.precision,
        d.coarse.metrics.recall,
        d.fine.miou,
    ]
    .into_iter()
    .chain(TABLE_ORDER.iter().map(|&c| d.fine.iou[classes::name(c)]))
    .collect();
    for (label, row) in [("paper (per image)", &paper_row), ("dataset", &data_row)] {
        s.push_str(&format!("{label:<18} |"));
        for (i, v) in row.iter().enumerate() {
            if i == 4 {
                s.push_str(" |");
            }
            s.push_str(&format!(" {:>7}", pct(*v)));
        }
        s.push('\n');
    }
    s.push_str("\nTable 2 precision (%)");
    for n in &names {
        s.push_str(&format!(" {:>7}", capitalise(n)));
    }
    s.push('\n');
    for (label, vals) in [
        (
            "paper (per image)",
            TABLE_ORDER
                .iter()
                .map(|&c| m.paper.precision[classes::name(c)].mean)
                .collect::<Vec<_>>(),
        ),
        (
            "dataset",
            TABLE_ORDER
                .iter()
                .map(|&c| d.fine.precision[classes::name(c)])
                .collect(),
        ),
    ] {
        s.push_str(&format!("{label:<21}"));
        for v in vals {
            s.push_str(&format!(" {:>7}", pct(v)));
        }
        s.push('\n');
    }
    s
}

fn capitalise(s: &str) -> String {
    let mut c = s.chars();
    c.next()
        .map(|f| f.to_uppercase().chain(c).collect())
        .unwrap_or_default()
}

// ---------------------------------------------------------------------------------------
// The stage

/// The stage's `summary.json`: the headline numbers and the rendered tables.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct EvalSummary {
    /// Which predictions were scored (`vote` or `learned`), where known.
    pub mode: Option<String>,
    pub pred: PathBuf,
    pub gt: PathBuf,
    /// The views evaluated when restricted (`--views`, a run's test views).
    pub views: Option<Vec<String>>,
    pub images: usize,
    pub resized_predictions: usize,
    pub predictions_without_gt: usize,
    pub coarse_skipped_no_valid_gt: usize,
    pub fine_skipped_no_fine_gt: usize,
    /// Paper protocol: `coarse_iou`, `coarse_accuracy`, `coarse_precision`, `coarse_recall`,
    /// `miou` (fractions; null where undefined).
    pub paper: BTreeMap<String, Option<f64>>,
    /// Dataset level, the same keys.
    pub dataset: BTreeMap<String, Option<f64>>,
    /// Per-class IoU (paper protocol), by fine class name.
    pub paper_iou: BTreeMap<String, Option<f64>>,
    /// Table 1 and Table 2 of the paper as printed ([`tables`]).
    pub tables: String,
    /// The paper's query-driven evaluation (a mask per query: "building" and each fine class),
    /// printed the same way, where it was computed (`gs4city run`: `metrics_by_query.json`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub by_query_tables: Option<String>,
    /// The dataset-level confusion of the fine classes (the `dataset.fine.confusion` of
    /// `metrics.json`), for the report; absent in summaries written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confusion: Option<Confusion>,
    pub seconds: f64,
    pub warnings: Vec<String>,
}

impl crate::layout::Summary for EvalSummary {}

/// A confusion matrix of pixel counts: rows the ground-truth classes, columns the predicted ones.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Confusion {
    pub rows: Vec<String>,
    pub columns: Vec<String>,
    pub counts: Vec<Vec<u64>>,
}

/// Evaluates `pred` against `gt`, writes `<out>/metrics.json` and `<out>/summary.json`;
/// returns the summary and the full metrics.
pub fn run(pred: &Path, gt: &Path, out: &Path) -> Result<(EvalSummary, MetricsJson), EvalError> {
    run_for(pred, gt, out, None, None)
}

/// As [`run`], restricted to the GT views named in `stems` (predictions of other views are
/// ignored), recording `mode` (which predictions these are) in both files.
pub fn run_for(
    pred: &Path,
    gt: &Path,
    out: &Path,
    stems: Option<&[String]>,
    mode: Option<&str>,
) -> Result<(EvalSummary, MetricsJson), EvalError> {
    let t0 = Instant::now();
    fsutil::create_dir(out)?;
    let _ = std::fs::remove_file(out.join("summary.json"));
    let mut ev = evaluate_dirs_for(pred, gt, stems)?;
    if stems.is_some() {
        ev.predictions_without_gt.clear();
        ev.warnings.retain(|w| !w.contains("without ground truth"));
    }
    let mut m = metrics_json(&ev);
    m.mode = mode.map(String::from);
    fsutil::write_json(&out.join("metrics.json"), &m)?;
    let headline = |coarse: [Option<f64>; 4], miou: Option<f64>| {
        BTreeMap::from([
            ("coarse_iou".to_string(), coarse[0]),
            ("coarse_accuracy".to_string(), coarse[1]),
            ("coarse_precision".to_string(), coarse[2]),
            ("coarse_recall".to_string(), coarse[3]),
            ("miou".to_string(), miou),
        ])
    };
    let pc = |k: &str| m.paper.coarse[k].mean;
    let dc = &m.dataset.coarse.metrics;
    let summary = EvalSummary {
        mode: mode.map(String::from),
        pred: pred.to_path_buf(),
        gt: gt.to_path_buf(),
        views: stems.map(|s| s.to_vec()),
        images: m.images,
        resized_predictions: m.resized_predictions,
        predictions_without_gt: m.predictions_without_gt.len(),
        coarse_skipped_no_valid_gt: m.paper.coarse_skipped_no_valid_gt,
        fine_skipped_no_fine_gt: m.paper.fine_skipped_no_fine_gt,
        paper: headline(
            [pc("iou"), pc("accuracy"), pc("precision"), pc("recall")],
            m.paper.miou.mean,
        ),
        dataset: headline(
            [dc.iou, dc.accuracy, dc.precision, dc.recall],
            m.dataset.fine.miou,
        ),
        paper_iou: FINE
            .iter()
            .map(|&c| {
                (
                    classes::name(c).to_string(),
                    m.paper.iou[classes::name(c)].mean,
                )
            })
            .collect(),
        tables: tables(&m),
        by_query_tables: None,
        confusion: Some(Confusion {
            rows: m.fine_classes.iter().map(|c| c.to_string()).collect(),
            columns: m.confusion_columns.iter().map(|c| c.to_string()).collect(),
            counts: m.dataset.fine.confusion.clone(),
        }),
        seconds: t0.elapsed().as_secs_f64(),
        warnings: ev.warnings.clone(),
    };
    crate::layout::Summary::write(&summary, out)?;
    crate::progress::done(
        "eval",
        &format!(
            "{} views, fine mIoU {} (paper protocol)",
            summary.images,
            m.paper
                .miou
                .mean
                .map_or("—".to_string(), |v| format!("{:.1} %", 100.0 * v))
        ),
        summary.seconds,
    );
    Ok((summary, m))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_resize_pixel_centres() {
        // 2×2 → 4×4: every source pixel becomes a 2×2 block.
        let up = resize_nearest(&[1, 2, 3, 4], [2, 2], [4, 4]);
        assert_eq!(up, vec![1, 1, 2, 2, 1, 1, 2, 2, 3, 3, 4, 4, 3, 3, 4, 4]);
        // 1×4 → 1×2: centres 0.5·2 = 1 → src ⌊(1·4)/4⌋ = 1, ⌊(3·4)/4⌋ = 3.
        assert_eq!(resize_nearest(&[0, 1, 2, 3], [1, 4], [1, 2]), vec![1, 3]);
        // Same size is the identity.
        let id: Vec<i32> = (0..12).collect();
        assert_eq!(resize_nearest(&id, [3, 4], [3, 4]), id);
        // 1×3 → 1×2: ⌊1·3/4⌋ = 0, ⌊3·3/4⌋ = 2.
        assert_eq!(resize_nearest(&[7, 8, 9], [1, 3], [1, 2]), vec![7, 9]);
    }

    #[test]
    fn table_has_both_rows() {
        let c = accumulate(&[0, 1, 6], &[0, -1, 6]);
        let ev = Evaluation {
            images: vec![ImageEval {
                stem: "a".into(),
                gt_size: [1, 3],
                pred_size: [1, 3],
                unknown_pred_values: 0,
                counts: c,
            }],
            predictions_without_gt: vec![],
            warnings: vec![],
        };
        let t = tables(&metrics_json(&ev));
        assert!(t.contains("paper (per image)") && t.contains("dataset"));
        assert!(t.contains("Door") && t.contains("Tree") && t.contains('—'));
        // Coarse: tp 1 (wall), fn 1 (roof → −1), tn 1 → IoU 50.00.
        assert!(t.contains("50.00"));
    }
}
