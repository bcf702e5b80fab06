//! The `lift` stage: the closed-form weighted vote (FlashSplat) that lifts the city-model
//! labels of the training views (`M_city` of the raycast stage) into the Gaussians.
//!
//! For every Gaussian `i` and label `n` (a city-model entity id, or background for pixels the
//! city model does not cover) the vote accumulates `A[i][n] = Σ_views Σ_pixels α_i·T_i · [M(p) = n]`
//! over the pixels the Gaussian contributes to. The labels are then L1-normalised per Gaussian,
//! a bias `γ` is added to the background entry, and the argmax is taken. Views are processed in
//! name order and pixels in raster order, so the result does not depend on the thread count.
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use crate::camera::View;
use crate::citymodel::Entity;
use crate::classes;
use crate::render::{self, ContributionMode, PreparedScene, RenderOptions};

/// The background label (a pixel without city model).
pub const BACKGROUND: i32 = -1;

/// Errors of the lift stage.
#[derive(Debug, thiserror::Error)]
pub enum LiftError {
    #[error(transparent)]
    Render(#[from] render::RenderError),
    #[error(transparent)]
    Npy(#[from] crate::npy::NpyError),
    #[error("{path}: {why}")]
    Labels { path: PathBuf, why: String },
    #[error("invalid option: {0}")]
    Options(String),
    #[error(transparent)]
    Colmap(#[from] crate::colmap::ColmapError),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    CityModel(#[from] crate::citymodel::CityModelError),
    #[error(transparent)]
    Fs(#[from] crate::fsutil::FsError),
    #[error(transparent)]
    Image(#[from] crate::imageio::ImageError),
}

/// Everything `gs4city lift` needs.
#[derive(Debug, Clone)]
pub struct LiftConfig {
    pub ply: PathBuf,
    pub colmap: PathBuf,
    pub raycast: PathBuf,
    pub citymodel: PathBuf,
    pub out: PathBuf,
    pub options: LiftOptions,
    /// Every `test_every`-th view (sorted by name, index 0 first) is a test view (3DGS `--eval`
    /// convention); 0 = no test views.
    pub test_every: usize,
    /// Contribution list length used to predict the test-view maps.
    pub predict_k: usize,
}

impl LiftOptions {
    /// From command-line values: `top_k` contributions per pixel (0 = all) and γ.
    pub fn new(top_k: usize, gamma: f32) -> LiftOptions {
        let contributions = if top_k == 0 {
            ContributionMode::All
        } else {
            ContributionMode::TopK(top_k)
        };
        LiftOptions {
            contributions,
            gamma,
        }
    }
}

/// The test-view stems recorded in a lift output folder's `summary.json` (empty when absent).
pub fn test_views(lift_dir: &Path) -> Vec<String> {
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(lift_dir.join("summary.json")).unwrap_or_default())
            .unwrap_or_default();
    summary["test_views"]
        .as_array()
        .map(|v| {
            v.iter()
                .filter_map(|s| s.as_str().map(String::from))
                .collect()
        })
        .unwrap_or_default()
}

/// Splits views (sorted by name) into (train, test): index `i % every == 0` is a test view.
pub fn split_views(mut views: Vec<View>, every: usize) -> (Vec<View>, Vec<View>) {
    views.sort_by(|a, b| a.name.cmp(&b.name));
    if every == 0 {
        return (views, Vec::new());
    }
    let (mut train, mut test) = (Vec::new(), Vec::new());
    for (i, v) in views.into_iter().enumerate() {
        if i % every == 0 {
            test.push(v)
        } else {
            train.push(v)
        }
    }
    (train, test)
}

/// Runs the stage: vote over the training views, write the semantic PLY
/// (`point_cloud_semantic.ply`: the input properties plus `instance_id feature_id surface_id
/// part_id class_id` and `label_confidence`), `gaussians.npy` (int32 N×5: class, instance,
/// feature, surface, part), per test view `<stem>.class.npy`, `<stem>.instance.npy` and
/// `<stem>.class.png`, and `summary.json` last.
pub fn run(cfg: &LiftConfig) -> Result<serde_json::Value, LiftError> {
    let t0 = Instant::now();
    let views = crate::colmap::read_model(&cfg.colmap)?;
    let (train, test) = split_views(views, cfg.test_every);
    if train.is_empty() {
        return Err(LiftError::Options(
            "no training views (every view is a test view)".into(),
        ));
    }
    let (mut gaussians, _report) = crate::splat::read_ply(&cfg.ply, &Default::default())?;
    let scene = PreparedScene::new(&gaussians)?;
    let entities = crate::citymodel::read_semantics(&cfg.citymodel.join("semantics.json"))?;
    let chain = hierarchy(&entities);
    let t_load = t0.elapsed().as_secs_f64();

    let (assignments, stats) = lift(&scene, &train, &cfg.raycast, &cfg.options)?;
    let mut labels = Vec::with_capacity(assignments.len());
    for a in &assignments {
        labels.push(
            match usize::try_from(a.label).ok().and_then(|i| chain.get(i)) {
                Some(l) => *l,
                None if a.label < 0 => GaussianLabel::NONE,
                None => {
                    return Err(LiftError::Labels {
                        path: cfg.raycast.clone(),
                        why: format!(
                            "label {} is not an entity of {}",
                            a.label,
                            cfg.citymodel.join("semantics.json").display()
                        ),
                    });
                }
            },
        );
    }

    crate::fsutil::create_dir(&cfg.out)?;
    let t = Instant::now();
    let int_prop = |name: &str, f: &dyn Fn(&GaussianLabel) -> i32| crate::splat::ExtraProperty {
        name: name.to_string(),
        kind: crate::splat::ScalarKind::I32,
        values: labels.iter().map(|l| f(l) as f64).collect(),
    };
    let new_props = vec![
        int_prop("instance_id", &|l| l.instance),
        int_prop("feature_id", &|l| l.feature),
        int_prop("surface_id", &|l| l.surface),
        int_prop("part_id", &|l| l.part),
        int_prop("class_id", &|l| l.class),
        crate::splat::ExtraProperty {
            name: "label_confidence".into(),
            kind: crate::splat::ScalarKind::F32,
            values: assignments.iter().map(|a| a.confidence as f64).collect(),
        },
    ];
    gaussians
        .extras
        .retain(|e| !new_props.iter().any(|p| p.name == e.name));
    gaussians.extras.extend(new_props);
    crate::splat::write_ply(
        &cfg.out.join("point_cloud_semantic.ply"),
        &gaussians,
        crate::splat::PlyEncoding::BinaryLittleEndian,
    )?;
    let table: Vec<i32> = labels
        .iter()
        .flat_map(|l| [l.class, l.instance, l.feature, l.surface, l.part])
        .collect();
    crate::npy::write(&cfg.out.join("gaussians.npy"), &[labels.len(), 5], &table)?;
    let t_write = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let mut test_stems = Vec::new();
    for v in &test {
        let (class, inst) = predict_view(&scene, &v.camera, &labels, cfg.predict_k)?;
        let (w, h) = (
            v.camera.intrinsics.width as usize,
            v.camera.intrinsics.height as usize,
        );
        let stem = v.stem();
        crate::npy::write(&cfg.out.join(format!("{stem}.class.npy")), &[h, w], &class)?;
        crate::npy::write(
            &cfg.out.join(format!("{stem}.instance.npy")),
            &[h, w],
            &inst,
        )?;
        let img = ndarray::Array3::from_shape_fn((h, w, 3), |(y, x, c)| {
            classes::color(class[y * w + x])[c]
        });
        crate::imageio::write_png(&cfg.out.join(format!("{stem}.class.png")), &img)?;
        test_stems.push(stem);
    }
    let t_predict = t.elapsed().as_secs_f64();

    let mut per_class = std::collections::BTreeMap::new();
    for l in &labels {
        *per_class.entry(classes::name(l.class)).or_insert(0usize) += 1;
    }
    let summary = serde_json::json!({
        "gaussians": labels.len(),
        "assigned": labels.iter().filter(|l| l.instance >= 0).count(),
        "gaussians_per_class": per_class,
        "train_views": train.iter().map(|v| v.stem()).collect::<Vec<_>>(),
        "test_views": test_stems,
        "options": cfg.options,
        "predict_k": cfg.predict_k,
        "stats": stats,
        "timing": {
            "load_s": t_load,
            "render_s": stats.render_s,
            "accumulate_s": stats.accumulate_s,
            "assign_s": stats.assign_s,
            "write_s": t_write,
            "predict_test_views_s": t_predict,
            "total_s": t0.elapsed().as_secs_f64(),
        },
    });
    crate::fsutil::write_json(&cfg.out.join("summary.json"), &summary)?;
    Ok(summary)
}

/// Options of the vote.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LiftOptions {
    /// Contribution lists per pixel: `TopK(k)` bounds memory and time; `All` is exact.
    pub contributions: ContributionMode,
    /// Background bias γ ∈ [−1, 1], added to the normalised background vote.
    pub gamma: f32,
}

impl Default for LiftOptions {
    fn default() -> Self {
        LiftOptions {
            contributions: ContributionMode::TopK(16),
            gamma: 0.0,
        }
    }
}

/// Per-Gaussian label votes: a few inline slots, and per Gaussian an overflow list for the
/// rare rest (looked up by Gaussian, so reading all votes stays linear).
pub struct Votes {
    slots: Vec<[(i32, f32); SLOTS]>,
    overflow: HashMap<u32, Vec<(i32, f32)>>,
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
    pub fn add(&mut self, g: u32, label: i32, w: f32) {
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
    pub fn of(&self, g: u32) -> Vec<(i32, f32)> {
        let mut v: Vec<(i32, f32)> = self.slots[g as usize]
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

    /// Accumulates one view: `labels[p]` is the pixel's label (entity id or background).
    pub fn accumulate(&mut self, contributions: &render::Contributions, labels: &[i32]) {
        for (p, &label) in labels.iter().enumerate() {
            let (ids, ws) = contributions.pixel(p);
            for (&g, &w) in ids.iter().zip(ws) {
                self.add(g, label, w);
            }
        }
    }
}

/// The label chosen for one Gaussian.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Assignment {
    /// Entity id, or −1 (background, or no vote at all).
    pub label: i32,
    /// Normalised vote of the winning label (0 when there was no vote).
    pub confidence: f32,
    /// Total vote weight.
    pub weight: f32,
}

/// Chooses, per Gaussian, the label with the largest normalised vote (+γ on background).
/// Ties go to the smaller label id.
pub fn assign(votes: &Votes, n: usize, gamma: f32) -> Vec<Assignment> {
    (0..n as u32)
        .map(|g| {
            let v = votes.of(g);
            let total: f32 = v.iter().map(|x| x.1).sum();
            if total <= 0.0 {
                return Assignment {
                    label: BACKGROUND,
                    confidence: 0.0,
                    weight: 0.0,
                };
            }
            let mut best = (BACKGROUND, f32::NEG_INFINITY);
            let mut bg_seen = false;
            let mut consider = |label: i32, score: f32| {
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
                confidence: conf,
                weight: total,
            }
        })
        .collect()
}

/// Per-Gaussian hierarchy and class of an assigned entity label.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GaussianLabel {
    pub instance: i32,
    pub feature: i32,
    pub surface: i32,
    pub part: i32,
    pub class: i32,
}

impl GaussianLabel {
    pub const NONE: GaussianLabel = GaussianLabel {
        instance: -1,
        feature: -1,
        surface: -1,
        part: -1,
        class: -1,
    };
}

/// The hierarchy chain of each entity: nearest feature/surface/part ancestor-or-self.
pub fn hierarchy(entities: &[Entity]) -> Vec<GaussianLabel> {
    let classes = classes::table(entities);
    let mut out: Vec<GaussianLabel> = Vec::with_capacity(entities.len());
    for (i, e) in entities.iter().enumerate() {
        let mut l = match e.parent {
            Some(p) if (p as usize) < i => out[p as usize],
            _ => GaussianLabel::NONE,
        };
        let id = i as i32;
        match e.level {
            crate::citygml::Level::Feature => {
                l.feature = id;
                l.surface = -1;
                l.part = -1;
            }
            crate::citygml::Level::Surface => {
                l.surface = id;
                l.part = -1;
            }
            crate::citygml::Level::Part => l.part = id,
        }
        l.instance = id;
        l.class = classes[i];
        out.push(l);
    }
    out
}

/// Timings and counts of a lift.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LiftStats {
    pub train_views: usize,
    pub render_s: f64,
    pub accumulate_s: f64,
    pub assign_s: f64,
    pub contributions: u64,
    pub overflow_votes: usize,
}

/// Reads the `M_city` channel (index 3) of a raycast `<stem>.ids.npy` (4×H×W int32).
pub fn read_city_labels(path: &Path, width: usize, height: usize) -> Result<Vec<i32>, LiftError> {
    let (shape, data) = crate::npy::read::<i32>(path)?;
    if shape != [4, height, width] {
        return Err(LiftError::Labels {
            path: path.to_path_buf(),
            why: format!(
                "shape {shape:?}, expected [4, {height}, {width}] (feature, surface, part, city) for this camera"
            ),
        });
    }
    Ok(data[3 * width * height..].to_vec())
}

/// Runs the vote over the training `views`, reading each view's labels from
/// `raycast_dir/<stem>.ids.npy`; returns one assignment per Gaussian.
pub fn lift(
    scene: &PreparedScene,
    views: &[View],
    raycast_dir: &Path,
    opts: &LiftOptions,
) -> Result<(Vec<Assignment>, LiftStats), LiftError> {
    if !(-1.0..=1.0).contains(&opts.gamma) {
        return Err(LiftError::Options(format!(
            "gamma must lie in [-1, 1], got {}",
            opts.gamma
        )));
    }
    if opts.contributions == ContributionMode::None {
        return Err(LiftError::Options(
            "the vote needs contribution lists (TopK or All)".into(),
        ));
    }
    let mut votes = Votes::new(scene.len());
    let mut stats = LiftStats {
        train_views: views.len(),
        ..Default::default()
    };
    let ropts = RenderOptions {
        features: false,
        contributions: opts.contributions,
        ..Default::default()
    };
    for view in views {
        let k = &view.camera.intrinsics;
        let labels = read_city_labels(
            &raycast_dir.join(format!("{}.ids.npy", view.stem())),
            k.width as usize,
            k.height as usize,
        )?;
        let t = Instant::now();
        let out = render::render_view(scene, &view.camera, &ropts)?;
        stats.render_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        if let Some(c) = &out.contributions {
            stats.contributions += c.ids.len() as u64;
            votes.accumulate(c, &labels);
        }
        stats.accumulate_s += t.elapsed().as_secs_f64();
    }
    let t = Instant::now();
    let a = assign(&votes, scene.len(), opts.gamma);
    stats.assign_s = t.elapsed().as_secs_f64();
    stats.overflow_votes = votes.overflow.values().map(Vec::len).sum();
    Ok((a, stats))
}

/// Per-pixel predicted label maps of one view: for each pixel, the label whose Gaussians carry
/// the largest total weight, where the transmitted remainder and unlabelled Gaussians vote for
/// −1. Returns `(class map, instance map)`.
pub fn predict_view(
    scene: &PreparedScene,
    camera: &crate::camera::Camera,
    labels: &[GaussianLabel],
    k: usize,
) -> Result<(Vec<i32>, Vec<i32>), LiftError> {
    let ropts = RenderOptions {
        features: false,
        contributions: ContributionMode::TopK(k),
        ..Default::default()
    };
    let out = render::render_view(scene, camera, &ropts)?;
    let c = out
        .contributions
        .as_ref()
        .expect("contributions were requested");
    let n = out.width * out.height;
    let mut class = vec![-1; n];
    let mut inst = vec![-1; n];
    let mut acc: Vec<(i32, f32)> = Vec::with_capacity(k + 2);
    let pick = |acc: &mut Vec<(i32, f32)>, rest: f32| -> i32 {
        acc.sort_by_key(|x| x.0);
        let mut best = (
            -1,
            rest + acc.iter().filter(|x| x.0 == -1).map(|x| x.1).sum::<f32>(),
        );
        let mut i = 0;
        while i < acc.len() {
            let l = acc[i].0;
            let mut w = 0.0;
            while i < acc.len() && acc[i].0 == l {
                w += acc[i].1;
                i += 1;
            }
            if l != -1 && w > best.1 {
                best = (l, w);
            }
        }
        best.0
    };
    for p in 0..n {
        let (ids, ws) = c.pixel(p);
        let rest = 1.0 - out.alpha[p] + c.residual[p];
        acc.clear();
        acc.extend(
            ids.iter()
                .zip(ws)
                .map(|(&g, &w)| (labels[g as usize].class, w)),
        );
        class[p] = pick(&mut acc, rest);
        acc.clear();
        acc.extend(
            ids.iter()
                .zip(ws)
                .map(|(&g, &w)| (labels[g as usize].instance, w)),
        );
        inst[p] = pick(&mut acc, rest);
    }
    Ok((class, inst))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vote_argmax_normalisation_and_gamma() {
        let mut v = Votes::new(3);
        v.add(0, 7, 0.6);
        v.add(0, BACKGROUND, 0.4);
        v.add(1, 7, 0.3);
        v.add(1, BACKGROUND, 0.5);
        for l in 10..20 {
            v.add(2, l, 0.01 * l as f32); // overflows the inline slots
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
}
