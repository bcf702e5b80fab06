//! The `lift` stage: the closed-form weighted vote (FlashSplat) that lifts per-view label maps —
//! the fused maps of the `fuse` stage, or `M_city` of the raycast alone — into the Gaussians,
//! through the contributions cache.
//!
//! For every Gaussian `i` and label `n` (a fused label id, or background −1 for pixels no label
//! covers) the vote accumulates `A[i][n] = Σ_views Σ_pixels α_i·T_i · [M(p) = n]` (in `f64`) over
//! the pixels whose cached list holds the Gaussian. The votes are L1-normalised per Gaussian, a
//! bias `γ` is added to the background entry, and the argmax is taken (ties: the smaller id).
//! Views are processed in name order and pixels in raster order, so the result does not depend
//! on the thread count. Test views are predicted per pixel from the same cache: the label whose
//! Gaussians carry the most weight, where the transmitted remainder `1 − α` and the truncated mass
//! vote for "none".
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::View;
use crate::citymodel::Entity;
use crate::classes;
use crate::labels::LabelTable;
use crate::progress::Bar;
use crate::render::cache::{Cache, CacheError, ViewContrib};

/// The background label (a pixel no label covers).
pub const BACKGROUND: i32 = -1;

/// Errors of the lift stage.
#[derive(Debug, thiserror::Error)]
pub enum LiftError {
    #[error(transparent)]
    Cache(#[from] CacheError),
    #[error(transparent)]
    Npy(#[from] crate::npy::NpyError),
    #[error("{path}: {why}")]
    Labels { path: PathBuf, why: String },
    #[error("invalid option: {0}")]
    Options(String),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Fs(#[from] crate::fsutil::FsError),
    #[error(transparent)]
    Image(#[from] crate::imageio::ImageError),
}

/// Options of the vote.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LiftOptions {
    /// Background bias γ ∈ [−1, 1], added to the normalised background vote.
    pub gamma: f32,
}

impl Default for LiftOptions {
    fn default() -> Self {
        LiftOptions { gamma: 0.0 }
    }
}

impl LiftOptions {
    /// Checks γ.
    pub fn validate(&self) -> Result<(), LiftError> {
        if !(-1.0..=1.0).contains(&self.gamma) {
            return Err(LiftError::Options(format!(
                "gamma must lie in [-1, 1], got {}",
                self.gamma
            )));
        }
        Ok(())
    }
}

/// Where the per-view label maps come from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum LabelMaps {
    /// `M_city`: channel 3 of a raycast folder's `<stem>.ids.npy` (4×H×W).
    City(PathBuf),
    /// A fuse folder's `<stem>.ids.npy` (H×W).
    Fused(PathBuf),
}

impl LabelMaps {
    /// The label map of view `stem` (`width × height`, row-major).
    pub fn read(&self, stem: &str, width: usize, height: usize) -> Result<Vec<i32>, LiftError> {
        let (path, channels) = match self {
            LabelMaps::City(d) => (d.join(format!("{stem}.ids.npy")), 4),
            LabelMaps::Fused(d) => (d.join(format!("{stem}.ids.npy")), 1),
        };
        let (shape, data) = crate::npy::read::<i32>(&path)?;
        let ok = if channels == 4 {
            shape == [4, height, width]
        } else {
            shape == [height, width]
        };
        if !ok {
            return Err(LiftError::Labels {
                path,
                why: format!(
                    "shape {shape:?}, expected {} for this camera",
                    if channels == 4 {
                        format!("[4, {height}, {width}] (feature, surface, part, city)")
                    } else {
                        format!("[{height}, {width}]")
                    }
                ),
            });
        }
        let npx = width * height;
        Ok(data[(channels - 1) * npx..].to_vec())
    }
}

/// Per-Gaussian label votes: a few inline slots, and per Gaussian an overflow list for the
/// rare rest (looked up by Gaussian, so reading all votes stays linear). Weights are `f64`:
/// a Gaussian can collect millions of small terms.
pub struct Votes {
    slots: Vec<[(i32, f64); SLOTS]>,
    overflow: HashMap<u32, Vec<(i32, f64)>>,
}

const SLOTS: usize = 4;
const EMPTY: i32 = i32::MIN;

impl Votes {
    /// Empty votes for `n` Gaussians.
    pub fn new(n: usize) -> Votes {
        Votes {
            slots: vec![[(EMPTY, 0.0); SLOTS]; n],
            overflow: HashMap::new(),
        }
    }

    /// Adds weight `w` for `label` to Gaussian `g`.
    #[inline]
    pub fn add(&mut self, g: u32, label: i32, w: f64) {
        let s = &mut self.slots[g as usize];
        for slot in s.iter_mut() {
            if slot.0 == label {
                slot.1 += w;
                return;
            }
            if slot.0 == EMPTY {
                *slot = (label, w);
                return;
            }
        }
        let list = self.overflow.entry(g).or_default();
        match list.iter_mut().find(|e| e.0 == label) {
            Some(e) => e.1 += w,
            None => list.push((label, w)),
        }
    }

    /// All `(label, weight)` votes of Gaussian `g`, in a deterministic order.
    pub fn of(&self, g: u32) -> Vec<(i32, f64)> {
        let mut v: Vec<(i32, f64)> = self.slots[g as usize]
            .iter()
            .copied()
            .filter(|s| s.0 != EMPTY)
            .collect();
        if v.len() == SLOTS
            && let Some(extra) = self.overflow.get(&g)
        {
            let mut extra = extra.clone();
            extra.sort_by_key(|e| e.0);
            v.extend(extra);
        }
        v
    }

    /// Votes kept in overflow lists.
    pub fn overflow_votes(&self) -> usize {
        self.overflow.values().map(Vec::len).sum()
    }

    /// Accumulates one view: `labels[p]` is pixel `p`'s label (or background).
    pub fn accumulate(&mut self, c: &ViewContrib, labels: &[i32]) {
        for (p, &label) in labels.iter().enumerate() {
            let (ids, ws) = c.pixel(p);
            for (&g, &w) in ids.iter().zip(ws) {
                self.add(g, label, f64::from(w));
            }
        }
    }
}

/// The label chosen for one Gaussian.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Assignment {
    /// Label id, or −1 (background, or no vote at all).
    pub label: i32,
    /// Normalised vote of the winning label (0 when there was no vote).
    pub confidence: f32,
    /// Total vote weight.
    pub weight: f64,
}

/// Chooses, per Gaussian, the label with the largest normalised vote (+γ on background).
/// Ties go to the smaller label id.
pub fn assign(votes: &Votes, n: usize, gamma: f32) -> Vec<Assignment> {
    let gamma = f64::from(gamma);
    (0..n as u32)
        .map(|g| {
            let v = votes.of(g);
            let total: f64 = v.iter().map(|x| x.1).sum();
            if total <= 0.0 {
                return Assignment {
                    label: BACKGROUND,
                    confidence: 0.0,
                    weight: 0.0,
                };
            }
            let mut best = (BACKGROUND, f64::NEG_INFINITY);
            let mut bg_seen = false;
            let mut consider = |label: i32, score: f64| {
                if score > best.1 || (score == best.1 && label < best.0) {
                    best = (label, score);
                }
            };
            for &(label, w) in &v {
                let mut s = w / total;
                if label == BACKGROUND {
                    s += gamma;
                    bg_seen = true;
                }
                consider(label, s);
            }
            if !bg_seen {
                consider(BACKGROUND, gamma);
            }
            let conf = v
                .iter()
                .find(|x| x.0 == best.0)
                .map_or(0.0, |x| x.1 / total);
            Assignment {
                label: best.0,
                confidence: conf as f32,
                weight: total,
            }
        })
        .collect()
}

/// Timings and counts of a vote.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct VoteStats {
    pub views: usize,
    pub load_s: f64,
    pub accumulate_s: f64,
    pub assign_s: f64,
    pub contributions: u64,
    pub overflow_votes: usize,
}

/// Runs the vote over `views` (their cached lists and label maps); one assignment per Gaussian.
pub fn vote(
    cache: &Cache,
    views: &[View],
    maps: &LabelMaps,
    opts: &LiftOptions,
) -> Result<(Vec<Assignment>, VoteStats), LiftError> {
    opts.validate()?;
    let n = cache.summary.gaussians;
    let mut votes = Votes::new(n);
    let mut stats = VoteStats {
        views: views.len(),
        ..Default::default()
    };
    let bar = Bar::new("lift", views.len() as u64, "views");
    // Two slots, reused: view i is accumulated from one while view i + 1 is loaded into the
    // other (the accumulation order stays fixed; the memory is allocated once).
    let load = |v: &View, s: &mut (ViewContrib, Vec<u8>, Vec<i32>)| -> Result<(), LiftError> {
        cache.load_into(&v.stem(), &mut s.0, &mut s.1)?;
        s.2 = maps.read(&v.stem(), s.0.width, s.0.height)?;
        Ok(())
    };
    let mut slots: [(ViewContrib, Vec<u8>, Vec<i32>); 2] =
        std::array::from_fn(|_| (ViewContrib::empty(), Vec::new(), Vec::new()));
    let t = Instant::now();
    if let Some(v) = views.first() {
        load(v, &mut slots[0])?;
    }
    stats.load_s += t.elapsed().as_secs_f64();
    for i in 0..views.len() {
        let [a, b] = &mut slots;
        let (cur, next) = if i % 2 == 0 { (a, b) } else { (b, a) };
        let (loaded, acc_s) = rayon::join(
            || views.get(i + 1).map(|v| load(v, next)).transpose(),
            || {
                let t = Instant::now();
                votes.accumulate(&cur.0, &cur.2);
                t.elapsed().as_secs_f64()
            },
        );
        stats.accumulate_s += acc_s;
        stats.contributions += cur.0.entries() as u64;
        loaded?;
        bar.inc(1);
    }
    bar.finish();
    let t = Instant::now();
    let a = assign(&votes, n, opts.gamma);
    stats.assign_s = t.elapsed().as_secs_f64();
    stats.overflow_votes = votes.overflow_votes();
    Ok((a, stats))
}

/// Per-pixel predicted label and class maps of one cached view: for each pixel the label whose
/// Gaussians carry the largest weight, where `1 − α`, the truncated mass and unlabelled
/// Gaussians vote for −1; the class map is computed the same way over the Gaussians' classes.
/// Returns `(class map, label map)`.
pub fn predict(c: &ViewContrib, label: &[i32], class: &[i32]) -> (Vec<i32>, Vec<i32>) {
    (0..c.pixels())
        .into_par_iter()
        .with_min_len(4096)
        .map_init(Vec::new, |groups, p| {
            (
                pixel_value(c, p, class, groups),
                pixel_value(c, p, label, groups),
            )
        })
        .unzip()
}

/// One map of [`predict`]: per pixel, the value of `of` (per Gaussian) whose Gaussians carry
/// the largest weight, or −1 where `1 − α`, the truncated mass and the Gaussians valued −1
/// weigh more. Pixels are independent (parallel; the sums per pixel run in a fixed order).
pub fn predict_map(c: &ViewContrib, of: &[i32]) -> Vec<i32> {
    let mut out = Vec::new();
    (0..c.pixels())
        .into_par_iter()
        .with_min_len(4096)
        .map_init(Vec::new, |groups, p| pixel_value(c, p, of, groups))
        .collect_into_vec(&mut out);
    out
}

/// Pixel `p`'s value of `of` by [`pick_label`]; `groups` is scratch.
fn pixel_value(c: &ViewContrib, p: usize, of: &[i32], groups: &mut Vec<(i32, f32)>) -> i32 {
    let (ids, ws) = c.pixel(p);
    let rest = 1.0 - c.alpha[p] + c.lists.residual[p];
    pick_label(
        ids.iter().zip(ws).map(|(&g, &w)| (of[g as usize], w)),
        groups,
        rest,
    )
}

/// The label of one pixel from its `(label, weight)` entries in list order: the label with the
/// largest summed weight (sums in list order), ties to the smaller label; −1 when `rest` plus
/// the entries labelled −1 weigh at least as much. `groups` is scratch.
fn pick_label(
    entries: impl Iterator<Item = (i32, f32)>,
    groups: &mut Vec<(i32, f32)>,
    rest: f32,
) -> i32 {
    groups.clear();
    // From −0.0, as `Iterator::sum` does.
    let mut background = -0.0f32;
    for (l, w) in entries {
        if l == -1 {
            background += w;
            continue;
        }
        match groups.iter_mut().find(|g| g.0 == l) {
            Some(g) => g.1 += w,
            None => groups.push((l, 0.0 + w)),
        }
    }
    let mut best = (-1, rest + background);
    for &(l, w) in groups.iter() {
        if w > best.1 || (w == best.1 && best.0 != -1 && l < best.0) {
            best = (l, w);
        }
    }
    best.0
}

/// Writes the test-view predictions `<stem>.class.npy`, `<stem>.instance.npy` (int32 H×W: class
/// and label per pixel) and `<stem>.class.png` into `out` from per-pixel maps made by `predict`.
pub fn write_prediction(
    out: &Path,
    stem: &str,
    width: usize,
    height: usize,
    class_map: &[i32],
    label_map: &[i32],
) -> Result<(), LiftError> {
    crate::npy::write(
        &out.join(format!("{stem}.class.npy")),
        &[height, width],
        class_map,
    )?;
    crate::npy::write(
        &out.join(format!("{stem}.instance.npy")),
        &[height, width],
        label_map,
    )?;
    let img = ndarray::Array3::from_shape_fn((height, width, 3), |(y, x, c)| {
        classes::color(class_map[y * width + x])[c]
    });
    crate::imageio::write_png(&out.join(format!("{stem}.class.png")), &img)?;
    Ok(())
}

/// Per-Gaussian results written by `lift` and `train`.
pub struct GaussianLabels<'a> {
    /// Fused label id per Gaussian (−1 none).
    pub label: &'a [i32],
    /// Class id per Gaussian (−1 none).
    pub class: &'a [i32],
    /// Extra per-Gaussian float properties for `semantic.ply` (e.g. `label_confidence`,
    /// `obj_dc_0..15`).
    pub extra: Vec<(String, Vec<f32>)>,
}

/// Writes `gaussians.npy` (int32 N×2: label, class) and `semantic.ply` (the input PLY plus
/// `label`, `class`, the city hierarchy `feature_id surface_id part_id` of city labels, and the
/// extra float properties).
pub fn write_gaussians(
    ply: &Path,
    out: &Path,
    g: &GaussianLabels<'_>,
    labels: &LabelTable,
    entities: &[Entity],
) -> Result<(), LiftError> {
    let (mut gaussians, _) = crate::splat::read_ply(ply, &Default::default())?;
    let n = gaussians.len();
    if g.label.len() != n || g.class.len() != n {
        return Err(LiftError::Labels {
            path: ply.to_path_buf(),
            why: format!(
                "{n} Gaussians in the PLY, {} labels: the PLY changed since the cache was built",
                g.label.len()
            ),
        });
    }
    let chain = crate::citymodel::chains(entities);
    let hier = |l: i32| -> crate::mesh::FaceLabel {
        labels
            .get(l)
            .and_then(|x| x.entity)
            .and_then(|e| chain.get(e as usize).copied())
            .unwrap_or(crate::mesh::FaceLabel::NONE)
    };
    let int_prop = |name: &str, f: &dyn Fn(usize) -> i32| crate::splat::ExtraProperty {
        name: name.to_string(),
        kind: crate::splat::ScalarKind::I32,
        values: (0..n).map(|i| f64::from(f(i))).collect(),
    };
    let mut props = vec![
        int_prop("label", &|i| g.label[i]),
        int_prop("class", &|i| g.class[i]),
        int_prop("feature_id", &|i| hier(g.label[i]).feature),
        int_prop("surface_id", &|i| hier(g.label[i]).surface),
        int_prop("part_id", &|i| hier(g.label[i]).part),
    ];
    for (name, values) in &g.extra {
        props.push(crate::splat::ExtraProperty {
            name: name.clone(),
            kind: crate::splat::ScalarKind::F32,
            values: values.iter().map(|&v| f64::from(v)).collect(),
        });
    }
    gaussians
        .extras
        .retain(|e| !props.iter().any(|p| p.name == e.name));
    gaussians.extras.extend(props);
    crate::splat::write_ply(
        &out.join("semantic.ply"),
        &gaussians,
        crate::splat::PlyEncoding::BinaryLittleEndian,
    )?;
    let table: Vec<i32> = (0..n).flat_map(|i| [g.label[i], g.class[i]]).collect();
    crate::npy::write(&out.join("gaussians.npy"), &[n, 2], &table)?;
    Ok(())
}

/// Everything the stage reads.
pub struct LiftInputs<'a> {
    /// The pre-trained 3DGS PLY the cache was built from.
    pub ply: &'a Path,
    pub cache: &'a Cache,
    pub train: &'a [View],
    pub test: &'a [View],
    pub maps: &'a LabelMaps,
    pub labels: &'a LabelTable,
    pub entities: &'a [Entity],
}

/// Timing of the stage.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LiftTiming {
    pub vote_s: f64,
    pub write_s: f64,
    pub predict_s: f64,
    pub total_s: f64,
}

/// The stage's `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LiftSummary {
    pub gaussians: usize,
    /// Gaussians with a label.
    pub assigned: usize,
    pub gaussians_per_class: BTreeMap<String, usize>,
    pub train_views: Vec<String>,
    pub test_views: Vec<String>,
    pub options: LiftOptions,
    pub labels_source: LabelMaps,
    pub stats: VoteStats,
    pub timing: LiftTiming,
}

impl LiftSummary {
    /// Reads a lift folder's `summary.json`.
    pub fn read(dir: &Path) -> Result<Self, crate::fsutil::FsError> {
        crate::fsutil::read_json(&dir.join("summary.json"))
    }
}

/// Runs the stage: the vote over the training views, `gaussians.npy`, `semantic.ply`, the
/// test-view predictions, and `summary.json` (last).
pub fn run(inp: &LiftInputs<'_>, opts: &LiftOptions, out: &Path) -> Result<LiftSummary, LiftError> {
    let t0 = Instant::now();
    if inp.train.is_empty() {
        return Err(LiftError::Options(
            "no training views (every view is a test view)".into(),
        ));
    }
    crate::fsutil::create_dir(out)?;
    let _ = std::fs::remove_file(out.join("summary.json"));
    let (assignments, stats) = vote(inp.cache, inp.train, inp.maps, opts)?;
    let t_vote = t0.elapsed().as_secs_f64();
    let label: Vec<i32> = assignments.iter().map(|a| a.label).collect();
    let class: Vec<i32> = label.iter().map(|&l| inp.labels.class_of(l)).collect();
    if let Some(l) = label
        .iter()
        .find(|&&l| l >= 0 && inp.labels.get(l).is_none())
    {
        return Err(LiftError::Labels {
            path: match inp.maps {
                LabelMaps::City(d) | LabelMaps::Fused(d) => d.clone(),
            },
            why: format!("label {l} of a label map is not in the label table"),
        });
    }
    let t = Instant::now();
    write_gaussians(
        inp.ply,
        out,
        &GaussianLabels {
            label: &label,
            class: &class,
            extra: vec![(
                "label_confidence".into(),
                assignments.iter().map(|a| a.confidence).collect(),
            )],
        },
        inp.labels,
        inp.entities,
    )?;
    let write_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (mut c, mut buf) = (ViewContrib::empty(), Vec::new());
    for v in inp.test {
        inp.cache.load_into(&v.stem(), &mut c, &mut buf)?;
        let (cm, lm) = predict(&c, &label, &class);
        write_prediction(out, &v.stem(), c.width, c.height, &cm, &lm)?;
    }
    let predict_s = t.elapsed().as_secs_f64();
    let mut per_class = BTreeMap::new();
    for &c in &class {
        *per_class
            .entry(classes::name(c).to_string())
            .or_insert(0usize) += 1;
    }
    let summary = LiftSummary {
        gaussians: label.len(),
        assigned: label.iter().filter(|&&l| l >= 0).count(),
        gaussians_per_class: per_class,
        train_views: inp.train.iter().map(|v| v.stem()).collect(),
        test_views: inp.test.iter().map(|v| v.stem()).collect(),
        options: *opts,
        labels_source: inp.maps.clone(),
        stats,
        timing: LiftTiming {
            vote_s: t_vote,
            write_s,
            predict_s,
            total_s: t0.elapsed().as_secs_f64(),
        },
    };
    crate::fsutil::write_json(&out.join("summary.json"), &summary)?;
    crate::progress::done(
        "lift",
        &format!(
            "{} of {} Gaussians labelled from {} views, {} test views predicted",
            summary.assigned,
            summary.gaussians,
            inp.train.len(),
            inp.test.len()
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The rule written the plain way: sort by label, sum each run, keep the first strict
    /// maximum over the background (rest + the −1 entries).
    fn pick_by_sorting(entries: &[(i32, f32)], rest: f32) -> i32 {
        let mut acc = entries.to_vec();
        acc.sort_by_key(|x| x.0);
        let bg: f32 = acc.iter().filter(|x| x.0 == -1).map(|x| x.1).sum();
        let mut best = (-1, rest + bg);
        for chunk in acc.chunk_by(|a, b| a.0 == b.0) {
            let w = chunk.iter().fold(0.0f32, |s, x| s + x.1);
            if chunk[0].0 != -1 && w > best.1 {
                best = (chunk[0].0, w);
            }
        }
        best.0
    }

    #[test]
    fn pixel_labels_match_the_sorting_rule_including_ties() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut groups = Vec::new();
        for case in 0..20_000 {
            let n = rng.random_range(0..20);
            // Few labels and weights from a small set: many exact ties.
            let entries: Vec<(i32, f32)> = (0..n)
                .map(|_| {
                    (
                        rng.random_range(-1..4) * if case % 2 == 0 { 1 } else { 1000 },
                        [0.125f32, 0.25, 0.1, 0.3, 0.0][rng.random_range(0..5)],
                    )
                })
                .collect();
            let rest = [0.0f32, 0.25, 0.5, 1.0][rng.random_range(0..4)];
            assert_eq!(
                pick_label(entries.iter().copied(), &mut groups, rest),
                pick_by_sorting(&entries, rest),
                "{entries:?} rest {rest}"
            );
        }
    }

    #[test]
    fn vote_argmax_normalisation_and_gamma() {
        let mut v = Votes::new(3);
        v.add(0, 7, 0.6);
        v.add(0, BACKGROUND, 0.4);
        v.add(1, 7, 0.3);
        v.add(1, BACKGROUND, 0.5);
        for l in 10..20 {
            v.add(2, l, 0.01 * f64::from(l)); // overflows the inline slots
        }
        let a = assign(&v, 3, 0.0);
        assert_eq!(a[0].label, 7);
        assert!((a[0].confidence - 0.6).abs() < 1e-6);
        assert_eq!(a[1].label, BACKGROUND);
        assert_eq!(a[2].label, 19, "overflow votes count");
        // γ = 0.3 moves Gaussian 0 (0.6 vs 0.4 + 0.3) to background; γ = −0.3 moves Gaussian 1 to 7.
        assert_eq!(assign(&v, 3, 0.3)[0].label, BACKGROUND);
        assert_eq!(assign(&v, 3, -0.3)[1].label, 7);
        // No vote at all: background with zero confidence.
        let empty = assign(&Votes::new(1), 1, 0.0);
        assert_eq!(
            empty[0],
            Assignment {
                label: BACKGROUND,
                confidence: 0.0,
                weight: 0.0
            }
        );
    }

    #[test]
    fn long_sums_stay_exact_in_f64() {
        // 30 million votes of 1e-7 (= 3.0) for one label and one vote of 2.5 for another: a
        // sequential f32 sum stalls at 2.0 (NumPy `cumsum(dtype=float32)` gives 2.0), which
        // would hand the Gaussian to the wrong label.
        let mut v = Votes::new(1);
        for _ in 0..30_000_000 {
            v.add(0, 1, 1e-7);
        }
        v.add(0, 2, 2.5);
        let votes = v.of(0);
        let w1 = votes.iter().find(|x| x.0 == 1).unwrap().1;
        assert!((w1 - 3.0).abs() < 1e-6, "{w1}");
        assert_eq!(assign(&v, 1, 0.0)[0].label, 1);
    }
}
