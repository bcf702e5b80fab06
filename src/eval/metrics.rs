//! Pure evaluation metrics over label maps (class ids of `docs/design.md`), so that other stages
//! (`lift`, `run`) can evaluate in-process without files.
//!
//! * [`accumulate`] turns one (ground truth, prediction) pair of equal-length label maps
//!   into [`Counts`]: the coarse building/non-building confusion and the 7 × 8 fine
//!   confusion (rows: the [`FINE`] classes in GT, columns: the [`FINE`] classes predicted
//!   plus one column for any other prediction). Counts add up ([`Counts::add`]), so the
//!   dataset level is the sum over images.
//! * [`BinaryCounts::coarse_metrics`] and [`fine_metrics`] turn counts into ratios.
//! * [`paper`] averages per-image metrics over images (the paper's protocol), [`dataset`]
//!   takes the ratios of the summed counts.
//!
//! Ratio rules (the same everywhere): a ratio with a zero denominator is `None` (JSON
//! `null`) and is left out of any mean (the number of images behind each mean is kept),
//! except precision when the positive class is present in GT but never predicted: that
//! is 0 (the method missed it), never dropped.
use crate::classes::{FINE, is_building};

/// Number of fine evaluation classes ([`FINE`]).
pub const N_FINE: usize = FINE.len();
/// Column of the fine confusion for every prediction that is not a [`FINE`] class
/// (−1, ground surface, installation, road, water, other, unknown values).
pub const OTHER_COL: usize = N_FINE;

/// Index into [`FINE`] of a class id, `None` for every other value.
pub fn fine_index(id: i32) -> Option<usize> {
    FINE.iter().position(|&c| c == id)
}

/// Lookup of [`fine_index`] for ids 0..=11 (`OTHER_COL` for non-fine ids).
const FINE_LUT: [u8; 12] = {
    let mut lut = [OTHER_COL as u8; 12];
    let mut k = 0;
    while k < N_FINE {
        lut[FINE[k] as usize] = k as u8;
        k += 1;
    }
    lut
};

#[inline]
fn fine_col(id: i32) -> usize {
    if (0..12).contains(&id) {
        FINE_LUT[id as usize] as usize
    } else {
        OTHER_COL
    }
}

/// A binary confusion (positive = building at the coarse level, or one fine class).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct BinaryCounts {
    pub tp: u64,
    pub fp: u64,
    #[serde(rename = "fn")]
    pub fn_: u64,
    pub tn: u64,
}

/// Ratios of a binary confusion; `None` where undefined (see the module docs).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct BinaryMetrics {
    pub iou: Option<f64>,
    pub accuracy: Option<f64>,
    pub precision: Option<f64>,
    pub recall: Option<f64>,
    pub f1: Option<f64>,
}

/// Per-class ratios at the fine level (only over GT pixels of a fine class).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct ClassMetrics {
    pub iou: f64,
    pub precision: f64,
    pub recall: f64,
}

/// `num / den`, `None` when `den == 0`.
pub fn ratio(num: u64, den: u64) -> Option<f64> {
    (den > 0).then(|| num as f64 / den as f64)
}

/// Precision with the "never predicted but present counts as 0" rule.
fn precision(tp: u64, fp: u64, fn_: u64) -> Option<f64> {
    match ratio(tp, tp + fp) {
        None if tp + fn_ > 0 => Some(0.0),
        p => p,
    }
}

impl BinaryCounts {
    /// IoU `tp/(tp+fp+fn)`, accuracy `(tp+tn)/n`, precision `tp/(tp+fp)` (0 when the
    /// positive class is in GT but never predicted), recall `tp/(tp+fn)`, F1
    /// `2tp/(2tp+fp+fn)`; `None` for a zero denominator.
    pub fn coarse_metrics(&self) -> BinaryMetrics {
        let BinaryCounts { tp, fp, fn_, tn } = *self;
        BinaryMetrics {
            iou: ratio(tp, tp + fp + fn_),
            accuracy: ratio(tp + tn, tp + fp + fn_ + tn),
            precision: precision(tp, fp, fn_),
            recall: ratio(tp, tp + fn_),
            f1: ratio(2 * tp, 2 * tp + fp + fn_),
        }
    }

    fn add(&mut self, o: &BinaryCounts) {
        self.tp += o.tp;
        self.fp += o.fp;
        self.fn_ += o.fn_;
        self.tn += o.tn;
    }
}

/// Pixel counts of one image (or, summed, of a dataset).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Counts {
    /// GT pixels with a class (GT ≥ 0).
    pub valid: u64,
    /// GT pixels that are ignored (GT < 0).
    pub ignored: u64,
    /// Building (classes 0..=5) as positive over the valid pixels; a prediction of −1 or of
    /// any non-building value is negative.
    pub coarse: BinaryCounts,
    /// `fine[g][p]`: GT fine class index `g` predicted as fine class index `p`, or as
    /// anything else (`p = OTHER_COL`). Only GT pixels of a [`FINE`] class are counted.
    pub fine: [[u64; N_FINE + 1]; N_FINE],
}

impl Default for Counts {
    fn default() -> Self {
        Counts {
            valid: 0,
            ignored: 0,
            coarse: BinaryCounts::default(),
            fine: [[0; N_FINE + 1]; N_FINE],
        }
    }
}

impl Counts {
    /// Adds another image's counts (dataset-level accumulation).
    pub fn add(&mut self, o: &Counts) {
        self.valid += o.valid;
        self.ignored += o.ignored;
        self.coarse.add(&o.coarse);
        for (a, b) in self.fine.iter_mut().zip(&o.fine) {
            for (x, y) in a.iter_mut().zip(b) {
                *x += y;
            }
        }
    }

    /// GT pixels of fine class index `k`.
    pub fn fine_gt(&self, k: usize) -> u64 {
        self.fine[k].iter().sum()
    }

    /// Pixels predicted as fine class index `k` among the GT fine pixels.
    pub fn fine_pred(&self, k: usize) -> u64 {
        self.fine.iter().map(|row| row[k]).sum()
    }

    /// All GT pixels of a fine class.
    pub fn fine_pixels(&self) -> u64 {
        (0..N_FINE).map(|k| self.fine_gt(k)).sum()
    }

    /// The one-vs-rest confusion of fine class index `k` over the GT fine pixels.
    pub fn fine_class(&self, k: usize) -> BinaryCounts {
        let tp = self.fine[k][k];
        let gt = self.fine_gt(k);
        let pred = self.fine_pred(k);
        BinaryCounts {
            tp,
            fp: pred - tp,
            fn_: gt - tp,
            // In this order: `total − gt − pred` alone can go below zero before `+ tp`.
            tn: self.fine_pixels() + tp - gt - pred,
        }
    }
}

/// Counts one image. `gt` and `pred` are label maps of the same size (C order, any shape):
/// GT < 0 is ignored; the prediction −1 means "no class" (non-building, wrong wherever the
/// GT has a fine class). GT values above 11 are treated like a non-building, non-fine class
/// (the file loader rejects them).
///
/// # Panics
/// If `gt.len() != pred.len()`.
pub fn accumulate(gt: &[i32], pred: &[i32]) -> Counts {
    assert_eq!(gt.len(), pred.len(), "accumulate: maps of different sizes");
    let mut c = Counts::default();
    // [gt building][pred building] → tn, fp, fn, tp.
    let mut coarse = [[0u64; 2]; 2];
    for (&g, &p) in gt.iter().zip(pred) {
        if g < 0 {
            c.ignored += 1;
            continue;
        }
        coarse[is_building(g) as usize][is_building(p) as usize] += 1;
        let gf = fine_col(g);
        if gf < N_FINE {
            c.fine[gf][fine_col(p)] += 1;
        }
    }
    c.coarse = BinaryCounts {
        tp: coarse[1][1],
        fp: coarse[0][1],
        fn_: coarse[1][0],
        tn: coarse[0][0],
    };
    c.valid = coarse.iter().flatten().sum();
    c
}

/// Fine-level ratios of one image's (or the dataset's summed) counts.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FineMetrics {
    /// Per [`FINE`] class; `None` where the class has no GT pixel.
    pub classes: [Option<ClassMetrics>; N_FINE],
    /// Mean IoU over the classes present in GT; `None` when none is.
    pub miou: Option<f64>,
}

/// Per-class IoU, precision and recall over the GT fine pixels, for the classes present
/// in GT (a present class never predicted has IoU 0 and precision 0), and their mean IoU.
pub fn fine_metrics(c: &Counts) -> FineMetrics {
    let mut m = FineMetrics::default();
    let mut ious = Vec::new();
    for (k, slot) in m.classes.iter_mut().enumerate() {
        let b = c.fine_class(k);
        if b.tp + b.fn_ == 0 {
            continue;
        }
        let cm = ClassMetrics {
            iou: b.tp as f64 / (b.tp + b.fp + b.fn_) as f64,
            precision: precision(b.tp, b.fp, b.fn_).unwrap_or(0.0),
            recall: b.tp as f64 / (b.tp + b.fn_) as f64,
        };
        ious.push(cm.iou);
        *slot = Some(cm);
    }
    m.miou = mean_of(&ious);
    m
}

/// The mean of `xs`, none when empty.
pub fn mean_of(xs: &[f64]) -> Option<f64> {
    (!xs.is_empty()).then(|| xs.iter().sum::<f64>() / xs.len() as f64)
}

/// A mean over images and how many images it is taken over.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Mean {
    pub mean: Option<f64>,
    pub images: usize,
}

impl Mean {
    fn of(values: impl Iterator<Item = Option<f64>>) -> Mean {
        let xs: Vec<f64> = values.flatten().collect();
        Mean {
            mean: mean_of(&xs),
            images: xs.len(),
        }
    }
}

/// The paper's protocol: per image, then the mean over images.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PaperMetrics {
    /// Images with no valid GT pixel (left out of every coarse mean).
    pub coarse_skipped: usize,
    /// Images with no GT pixel of a fine class (left out of every fine mean).
    pub fine_skipped: usize,
    pub iou: Mean,
    pub accuracy: Mean,
    pub precision: Mean,
    pub recall: Mean,
    pub f1: Mean,
    /// Mean over images of the image mIoU (mean over the fine classes present in its GT).
    pub miou: Mean,
    /// Per fine class: mean over the images whose GT holds the class.
    pub class_iou: [Mean; N_FINE],
    pub class_precision: [Mean; N_FINE],
    pub class_recall: [Mean; N_FINE],
}

/// Averages per-image metrics over images (the paper's protocol, REFERENCE.md §6).
pub fn paper(images: &[Counts]) -> PaperMetrics {
    let coarse: Vec<BinaryMetrics> = images
        .iter()
        .filter(|c| c.valid > 0)
        .map(|c| c.coarse.coarse_metrics())
        .collect();
    let fine: Vec<FineMetrics> = images
        .iter()
        .filter(|c| c.fine_pixels() > 0)
        .map(fine_metrics)
        .collect();
    let per_class = |f: fn(&ClassMetrics) -> f64| -> [Mean; N_FINE] {
        std::array::from_fn(|k| Mean::of(fine.iter().map(|m| m.classes[k].as_ref().map(f))))
    };
    PaperMetrics {
        coarse_skipped: images.len() - coarse.len(),
        fine_skipped: images.len() - fine.len(),
        iou: Mean::of(coarse.iter().map(|m| m.iou)),
        accuracy: Mean::of(coarse.iter().map(|m| m.accuracy)),
        precision: Mean::of(coarse.iter().map(|m| m.precision)),
        recall: Mean::of(coarse.iter().map(|m| m.recall)),
        f1: Mean::of(coarse.iter().map(|m| m.f1)),
        miou: Mean::of(fine.iter().map(|m| m.miou)),
        class_iou: per_class(|c| c.iou),
        class_precision: per_class(|c| c.precision),
        class_recall: per_class(|c| c.recall),
    }
}

/// Dataset level: the ratios of the counts summed over all images.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetMetrics {
    pub counts: Counts,
    pub coarse: BinaryMetrics,
    /// Classes absent from the whole GT are `None` and excluded from `miou`.
    pub fine: FineMetrics,
}

/// Sums the counts over images and takes the ratios.
pub fn dataset(images: &[Counts]) -> DatasetMetrics {
    let mut counts = Counts::default();
    for c in images {
        counts.add(c);
    }
    DatasetMetrics {
        coarse: counts.coarse.coarse_metrics(),
        fine: fine_metrics(&counts),
        counts,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::classes::*;

    const EPS: f64 = 1e-12;

    fn close(a: Option<f64>, b: f64) -> bool {
        a.is_some_and(|a| (a - b).abs() < EPS)
    }

    #[test]
    fn lut_matches_fine_order() {
        for id in -3..15 {
            assert_eq!(fine_col(id), fine_index(id).unwrap_or(OTHER_COL), "id {id}");
        }
    }

    #[test]
    fn perfect_prediction() {
        let gt = [WALL, ROOF, WINDOW, DOOR, TREE, PERSON, CAR, ROAD, NONE];
        let c = accumulate(&gt, &gt);
        // 8 valid (the −1 is ignored), 4 building (wall roof window door) all hit,
        // 4 non-building (tree person car road) all correct.
        assert_eq!((c.valid, c.ignored), (8, 1));
        assert_eq!(
            c.coarse,
            BinaryCounts {
                tp: 4,
                fp: 0,
                fn_: 0,
                tn: 4
            }
        );
        let m = c.coarse.coarse_metrics();
        for v in [m.iou, m.accuracy, m.precision, m.recall, m.f1] {
            assert!(close(v, 1.0));
        }
        let f = fine_metrics(&c);
        assert!(close(f.miou, 1.0));
        assert!(f.classes.iter().all(|c| c.is_some_and(|c| c.iou == 1.0)));
    }

    #[test]
    fn all_wrong_and_no_prediction() {
        // GT: 2 wall, 2 tree. Prediction swaps building-ness: tree on walls, roof on trees.
        let gt = [WALL, WALL, TREE, TREE];
        let pred = [TREE, TREE, ROOF, ROOF];
        let c = accumulate(&gt, &pred);
        // tp 0, fp 2 (trees predicted roof), fn 2 (walls predicted tree), tn 0.
        let m = c.coarse.coarse_metrics();
        assert!(close(m.iou, 0.0) && close(m.accuracy, 0.0) && close(m.f1, 0.0));
        assert!(close(m.precision, 0.0) && close(m.recall, 0.0));
        let f = fine_metrics(&c);
        // wall: tp 0, fn 2, fp 0 (nobody predicted wall) → IoU 0, precision 0 (missed).
        // tree: tp 0, fn 2, fp 2 (walls predicted tree) → IoU 0, precision 0.
        assert!(close(f.miou, 0.0));
        assert_eq!(f.classes.iter().flatten().count(), 2);

        // −1 everywhere: nothing is building, no fine class is predicted.
        let none = [NONE; 4];
        let c = accumulate(&gt, &none);
        // tp 0, fp 0, fn 2, tn 2 → IoU 0, acc 0.5, precision 0 (buildings missed), recall 0.
        let m = c.coarse.coarse_metrics();
        assert!(close(m.iou, 0.0) && close(m.accuracy, 0.5) && close(m.precision, 0.0));
        assert!(close(m.recall, 0.0) && close(m.f1, 0.0));
        assert!(close(fine_metrics(&c).miou, 0.0));
        assert_eq!(c.fine[0][OTHER_COL], 2);
    }

    #[test]
    fn undefined_ratios_are_none_not_nan() {
        // No building anywhere, nothing predicted as building: IoU, precision, recall and
        // F1 are 0/0 → None; accuracy is 1.
        let c = accumulate(&[TREE, ROAD], &[TREE, NONE]);
        let m = c.coarse.coarse_metrics();
        assert_eq!(
            (m.iou, m.precision, m.recall, m.f1),
            (None, None, None, None)
        );
        assert!(close(m.accuracy, 1.0));
        // All GT ignored: nothing valid at all.
        let c = accumulate(&[NONE, NONE], &[WALL, CAR]);
        assert_eq!(c.valid, 0);
        assert_eq!(c.coarse.coarse_metrics(), BinaryMetrics::default());
        assert_eq!(fine_metrics(&c).miou, None);
        let p = paper(&[c.clone(), accumulate(&[WALL], &[WALL])]);
        assert_eq!((p.coarse_skipped, p.fine_skipped), (1, 1));
        assert!(close(p.iou.mean, 1.0) && p.iou.images == 1);
    }

    #[test]
    fn class_never_predicted_counts_zero() {
        // GT: 3 wall, 1 window; prediction: all wall. Window is present, never predicted.
        let c = accumulate(&[WALL, WALL, WALL, WINDOW], &[WALL; 4]);
        let f = fine_metrics(&c);
        // wall: tp 3, fp 1, fn 0 → IoU 3/4, precision 3/4, recall 1.
        let w = f.classes[0].unwrap();
        assert!((w.iou - 0.75).abs() < EPS && (w.precision - 0.75).abs() < EPS);
        // window: IoU 0, precision 0. mIoU = (0.75 + 0) / 2 = 0.375.
        let win = f.classes[fine_index(WINDOW).unwrap()].unwrap();
        assert_eq!((win.iou, win.precision, win.recall), (0.0, 0.0, 0.0));
        assert!(close(f.miou, 0.375));
        // Absent classes are None, not 0.
        assert!(f.classes[fine_index(CAR).unwrap()].is_none());
    }

    #[test]
    fn paper_vs_dataset() {
        // Image A: 1 wall pixel, predicted wall (IoU_wall 1).
        // Image B: 3 wall pixels, 1 car pixel, all predicted car.
        //   wall: tp 0 fn 3 → 0; car: tp 1, fp 3 → IoU 1/4, precision 1/4. mIoU_B = 1/8.
        // Paper mIoU = (1 + 1/8) / 2 = 9/16; paper wall IoU = (1 + 0)/2 = 1/2; car = 1/4
        // (one image). Dataset: wall tp 1, fn 3, fp 0 → 1/4; car tp 1 fp 3 → 1/4;
        // dataset mIoU = 1/4.
        let a = accumulate(&[WALL], &[WALL]);
        let b = accumulate(&[WALL, WALL, WALL, CAR], &[CAR; 4]);
        let p = paper(&[a.clone(), b.clone()]);
        assert!(close(p.miou.mean, 9.0 / 16.0) && p.miou.images == 2);
        assert!(close(p.class_iou[0].mean, 0.5) && p.class_iou[0].images == 2);
        let car = fine_index(CAR).unwrap();
        assert!(close(p.class_iou[car].mean, 0.25) && p.class_iou[car].images == 1);
        assert!(close(p.class_precision[car].mean, 0.25));
        assert_eq!(p.class_iou[1].mean, None);
        let d = dataset(&[a, b]);
        assert!(close(d.fine.miou, 0.25));
        // Coarse dataset: building GT 4 (walls), predicted building 1 → tp 1, fn 3, fp 0,
        // tn 1 (the car pixel) → IoU 1/4, acc 2/5, precision 1, recall 1/4.
        let m = d.coarse;
        assert!(close(m.iou, 0.25) && close(m.accuracy, 0.4));
        assert!(close(m.precision, 1.0) && close(m.recall, 0.25));
    }
}
