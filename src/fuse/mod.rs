//! The `fuse` stage (paper §3.2, mask fusion and feature aggregation): per view, the associated
//! image groups and the city-model ids become one label map with image priority,
//!
//! ```text
//! M(u) = group(u) + Δ   where an associated group covers u,
//!        M_city(u)      else where the city model has an entity,
//!        −1             otherwise,
//! ```
//! with `Δ` = the entity count rounded up to a power of ten (≥ 10 000, [`crate::labels`]); ids
//! are int32 and an overflow is an error. Optionally ([`FuseOptions::snap`]) city-part snapping
//! ([`snap`]) moves window/door outlines to the image's own masks first.
//!
//! Each fused label gets a feature (`label_features.npy`, float32 L×D, row i ↔ `labels[i]`,
//! zero rows where a label has none): groups keep their running-mean feature; a city entity
//! averages the features of the SAM masks that cover it in the fused maps, each weighted by
//! `overlap² / mask area` (the overlap, discounted by how much of the mask lies elsewhere), then
//! normalised — the paper's crop-feature average with the masks standing in for the crops. Only
//! masks that look like a part of a building vote there: a mask whose feature is nearest to a
//! prompt of another class (a person, a car, a tree, the sky; `features/prompts.json`) shows
//! that object, not the surface behind it, even where its group did not survive the association
//! and its pixels kept the city label (without this a pedestrian in front of a wall made the
//! wall's feature a person's, and `text("a person")` selected the wall).
//!
//! Outputs (`docs/design.md`): `<stem>.ids.npy` (int32 H×W), `labels.json` ([`LabelTable`]: every city
//! entity and every group, with source, entity/group, class, level), `label_features.npy` (when
//! features exist), `summary.json` (last).
pub mod snap;

use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

pub use snap::{SnapLimits, SnapStats};

use crate::camera::View;
use crate::classes;
use crate::fsutil::{self, FsError};
use crate::groups::{GroupsError, GroupsFile};
use crate::idmap::{self, IdMapError};
use crate::labels::{self, LabelTable, LabelsError};
use crate::npy::{self, NpyError};
use crate::progress::Bar;
use crate::semantics::Entity;

/// Errors of the fuse stage. Each names the file at fault.
#[derive(Debug, thiserror::Error)]
pub enum FuseError {
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error(transparent)]
    Groups(#[from] GroupsError),
    #[error(transparent)]
    IdMap(#[from] IdMapError),
    #[error(transparent)]
    Labels(#[from] LabelsError),
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error(transparent)]
    Sam(#[from] crate::sam::SamError),
    #[error(transparent)]
    MaskFile(#[from] crate::maskfile::MaskFileError),
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// Options of the stage.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FuseOptions {
    /// City-part snapping (needs the scene's SAM lists and the masks stage's kept masks; on by
    /// default: it won on the misaligned and on the aligned benchmark, docs/associate.md).
    pub snap: bool,
    pub snap_limits: SnapLimits,
}

impl Default for FuseOptions {
    fn default() -> Self {
        FuseOptions {
            snap: true,
            snap_limits: SnapLimits::default(),
        }
    }
}

/// Everything the stage reads.
pub struct FuseInputs<'a> {
    /// The views to fuse (those the associate stage saw).
    pub views: &'a [View],
    /// The associate stage's folder.
    pub associate: &'a Path,
    /// The raycast stage's folder (`<stem>.ids.npy`, 4×H×W: feature, surface, part, city).
    pub raycast: &'a Path,
    /// `semantics.json`'s entities.
    pub entities: &'a [Entity],
    /// The scene's SAM lists (`masks/<stem>.json`): city features and snapping read them.
    pub sam: Option<&'a Path>,
    /// The scene's per-mask features (`features/<stem>.npy`).
    pub features: Option<&'a Path>,
    /// The masks stage's folder (kept masks): what it did not keep may be snapped.
    pub kept: Option<&'a Path>,
}

/// Time per step.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FuseTiming {
    /// Per-view fusion, snapping, city-feature overlaps and writing the maps (parallel wall time).
    pub views_s: f64,
    /// Label table and label features.
    pub labels_s: f64,
    pub total_s: f64,
}

/// The stage's `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FuseSummary {
    pub views: usize,
    pub delta: i32,
    pub labels: usize,
    pub city_labels: usize,
    pub image_labels: usize,
    /// Pixels over all views by source of their fused label.
    pub image_pixels: u64,
    pub city_pixels: u64,
    pub unlabelled_pixels: u64,
    /// Labels per class name.
    pub labels_per_class: BTreeMap<String, usize>,
    pub feature_dim: Option<usize>,
    /// City entities that received a feature.
    pub city_labels_with_features: usize,
    pub options: FuseOptions,
    pub snap: Option<SnapStats>,
    pub timing: FuseTiming,
    pub warnings: Vec<String>,
}

impl crate::layout::Summary for FuseSummary {}

/// What one view yields.
struct ViewOut {
    image: u64,
    city: u64,
    none: u64,
    snap: SnapStats,
    /// `(entity, weight, mask row)` of the SAM masks over city labels.
    city_votes: Vec<(i32, f64, usize)>,
    /// The view's SAM feature rows (row-major, `dim` each).
    features: Vec<f32>,
    dim: Option<usize>,
}

/// The prompts' unit vectors and classes (`features/prompts.json`), to tell which SAM masks
/// look like a part of a building.
struct PromptClasses {
    dim: usize,
    unit: Vec<f32>,
    class: Vec<i32>,
}

impl PromptClasses {
    fn read(features: &Path) -> Result<Option<PromptClasses>, FuseError> {
        let path = features.join("prompts.json");
        if !path.is_file() {
            return Ok(None);
        }
        let p = crate::sam::read_prompts_json(&path)?;
        let mut unit = Vec::with_capacity(p.prompts.len() * p.dim);
        let mut class = Vec::with_capacity(p.prompts.len());
        for (text, v) in &p.prompts {
            let n = v.iter().map(|&x| f64::from(x).powi(2)).sum::<f64>().sqrt();
            if v.len() != p.dim || !(n.is_finite() && n > 0.0) {
                return Err(FuseError::Invalid {
                    path: path.clone(),
                    why: format!(
                        "prompt {text:?}: not a finite non-zero vector of {} values",
                        p.dim
                    ),
                });
            }
            unit.extend(v.iter().map(|&x| (f64::from(x) / n) as f32));
            class.push(p.class_of(text));
        }
        Ok(Some(PromptClasses {
            dim: p.dim,
            unit,
            class,
        }))
    }

    /// Whether a mask feature's nearest prompt (by cosine) is of a building class (0–5).
    fn building_like(&self, f: &[f32]) -> bool {
        if f.len() != self.dim || self.class.is_empty() {
            return true;
        }
        let best = self
            .unit
            .chunks(self.dim)
            .map(|u| {
                u.iter()
                    .zip(f)
                    .map(|(&a, &b)| f64::from(a) * f64::from(b))
                    .sum::<f64>()
            })
            .enumerate()
            .fold(
                (0, f64::NEG_INFINITY),
                |a, (i, c)| if c > a.1 { (i, c) } else { a },
            )
            .0;
        classes::is_building(self.class[best])
    }
}

#[allow(clippy::too_many_arguments)]
fn fuse_view(
    inp: &FuseInputs<'_>,
    opts: &FuseOptions,
    view: &View,
    delta: i32,
    class: &[i32],
    building: &[i32],
    prompts: Option<&PromptClasses>,
    out: &Path,
) -> Result<ViewOut, FuseError> {
    let stem = view.stem();
    let (w, h) = (
        view.camera.intrinsics.width as usize,
        view.camera.intrinsics.height as usize,
    );
    let npx = w * h;
    let ray = idmap::read_raycast(inp.raycast, &stem, w, h)?;
    let group = idmap::read_ids(inp.associate, &stem, w, h)?;
    let city = &ray[3 * npx..];
    let n_ent = inp.entities.len() as i32;
    if let Some(&bad) = ray.iter().find(|&&x| x < -1 || x >= n_ent) {
        return Err(FuseError::Invalid {
            path: idmap::ids_file(inp.raycast, &stem),
            why: format!(
                "id {bad} is not an entity of semantics.json ({n_ent} entities): a stale raycast?"
            ),
        });
    }
    let mut fused = vec![-1i32; npx];
    for q in 0..npx {
        let g = group[q];
        fused[q] = if g >= 0 {
            labels::image_id(delta, g as usize)?
        } else {
            city[q]
        };
    }
    let sam = match inp.sam {
        Some(dir) => {
            let path = dir.join(format!("{stem}.json"));
            if path.is_file() {
                crate::sam::read_sam_json_sized(&path, Some([h, w]))?
            } else {
                Vec::new()
            }
        }
        None => Vec::new(),
    };
    let mut snap_stats = SnapStats::default();
    if opts.snap && !sam.is_empty() {
        let kept: HashSet<i64> = match inp.kept {
            Some(dir) => {
                let path = dir.join(format!("{stem}.json"));
                if !path.is_file() {
                    return Err(FuseError::Invalid {
                        path,
                        why: "missing: the masks stage wrote no kept-mask file for this view"
                            .into(),
                    });
                }
                crate::maskfile::read_kept(&path)?
                    .iter()
                    .map(|k| k.source_index)
                    .collect()
            }
            None => HashSet::new(),
        };
        snap_stats = snap::snap_view(
            &mut fused,
            &group,
            &snap::RayChannels {
                feature: &ray[..npx],
                surface: &ray[npx..2 * npx],
                part: &ray[2 * npx..3 * npx],
            },
            &sam,
            &kept,
            &snap::Entities { class, building },
            &opts.snap_limits,
        );
    }
    // Feature votes of the SAM masks over the city labels of the fused map.
    let mut city_votes = Vec::new();
    let (mut features, mut dim) = (Vec::new(), None);
    if let (Some(dir), false) = (inp.features, sam.is_empty()) {
        let path = dir.join(format!("{stem}.npy"));
        let (_, d, data) = crate::sam::read_features(&path, Some(sam.len()))?;
        if d == 0 {
            return Err(FuseError::Invalid {
                path,
                why: format!("shape [{}, 0]: features of dimension 0", sam.len()),
            });
        }
        dim = Some(d);
        features = data;
        let mut counts: BTreeMap<i32, u64> = BTreeMap::new();
        for (i, m) in sam.iter().enumerate() {
            // A mask that shows a person, a car, a tree or the sky says nothing of the city
            // surface behind it (module docs).
            if prompts.is_some_and(|p| !p.building_like(&features[i * d..(i + 1) * d])) {
                continue;
            }
            counts.clear();
            let mut n = 0u64;
            let _ = &m.segmentation.for_each_pixel(|q| {
                n += 1;
                let l = fused[q];
                if (0..delta).contains(&l) {
                    *counts.entry(l).or_insert(0) += 1;
                }
            });
            for (&e, &c) in &counts {
                city_votes.push((e, (c as f64) * (c as f64) / n as f64, i));
            }
        }
    }
    idmap::write_ids(out, &stem, w, h, &fused)?;
    let image = group.iter().filter(|&&g| g >= 0).count() as u64;
    let none = fused.iter().filter(|&&l| l < 0).count() as u64;
    Ok(ViewOut {
        image,
        city: npx as u64 - image - none,
        none,
        snap: snap_stats,
        city_votes,
        features,
        dim,
    })
}

/// Runs the stage: fused maps, `labels.json`, `label_features.npy`, `summary.json` (last).
pub fn run(inp: &FuseInputs<'_>, opts: &FuseOptions, out: &Path) -> Result<FuseSummary, FuseError> {
    let t0 = Instant::now();
    let groups = GroupsFile::read(inp.associate)?;
    let group_features = groups.features(inp.associate)?;
    for (i, g) in groups.groups.iter().enumerate() {
        if g.id != i as i32 {
            return Err(FuseError::Invalid {
                path: inp.associate.join("groups.json"),
                why: format!("group {i} has id {}: ids must be 0, 1, 2, …", g.id),
            });
        }
    }
    let class = classes::table(inp.entities);
    let building: Vec<i32> = inp.entities.iter().map(|e| e.building).collect();
    let group_class: Vec<i32> = groups
        .groups
        .iter()
        .map(|g| {
            if g.class >= 0 {
                g.class
            } else {
                classes::OTHER
            }
        })
        .collect();
    let table = LabelTable::fused(inp.entities, &class, &group_class)?;
    let delta = table.delta;
    fsutil::create_dir(out)?;
    let _ = std::fs::remove_file(out.join("summary.json"));

    let mut views: Vec<&View> = inp.views.iter().collect();
    views.sort_by(|a, b| a.name.cmp(&b.name));
    let prompts = match inp.features {
        Some(dir) => PromptClasses::read(dir)?,
        None => None,
    };
    let t = Instant::now();
    let bar = Bar::new("fuse", views.len() as u64, "views");
    let outs: Vec<Result<ViewOut, FuseError>> = views
        .par_iter()
        .map(|v| {
            let r = fuse_view(
                inp,
                opts,
                v,
                delta,
                &class,
                &building,
                prompts.as_ref(),
                out,
            );
            bar.inc(1);
            r
        })
        .collect();
    bar.finish();
    let views_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let n_ent = inp.entities.len();
    let dim = groups.feature_dim;
    let mut city_sum: Vec<f64> = Vec::new();
    let mut view_dim: Option<usize> = None;
    let (mut image, mut city, mut none) = (0, 0, 0);
    let mut snap_total = SnapStats::default();
    for (o, v) in outs.into_iter().zip(&views) {
        let o = o?;
        image += o.image;
        city += o.city;
        none += o.none;
        snap_total.add(&o.snap);
        let Some(d) = o.dim else { continue };
        if let Some(e) = dim.or(view_dim)
            && e != d
        {
            return Err(FuseError::Invalid {
                path: inp
                    .features
                    .map(|f| f.join(format!("{}.npy", v.stem())))
                    .unwrap_or_default(),
                why: format!("features of dimension {d}, the groups' (or other views') have {e}"),
            });
        }
        view_dim = Some(d);
        if city_sum.is_empty() {
            city_sum = vec![0.0; n_ent * d];
        }
        for &(e, wt, row) in &o.city_votes {
            let f = &o.features[row * d..(row + 1) * d];
            let norm = f.iter().map(|&x| f64::from(x).powi(2)).sum::<f64>().sqrt();
            if norm < 1e-12 {
                continue;
            }
            let s = &mut city_sum[e as usize * d..(e as usize + 1) * d];
            for (a, &x) in s.iter_mut().zip(f) {
                *a += wt * f64::from(x) / norm;
            }
        }
    }
    let feature_dim = dim.or(view_dim);
    let mut with_features = 0;
    let features_path = out.join("label_features.npy");
    if let Some(d) = feature_dim {
        let mut rows = vec![0f32; table.labels.len() * d];
        for (i, l) in table.labels.iter().enumerate() {
            let row = &mut rows[i * d..(i + 1) * d];
            if let Some(e) = l.entity {
                if city_sum.is_empty() {
                    continue;
                }
                let s = &city_sum[e as usize * d..(e as usize + 1) * d];
                let norm = s.iter().map(|x| x * x).sum::<f64>().sqrt();
                if norm > 0.0 {
                    with_features += 1;
                    for (r, &x) in row.iter_mut().zip(s) {
                        *r = (x / norm) as f32;
                    }
                }
            } else if let (Some(g), Some(gf)) = (l.group, &group_features) {
                row.copy_from_slice(&gf[g as usize * d..(g as usize + 1) * d]);
            }
        }
        npy::write(&features_path, &[table.labels.len(), d], &rows)?;
    } else {
        let _ = std::fs::remove_file(&features_path);
    }
    table.write(&out.join("labels.json"))?;
    let labels_s = t.elapsed().as_secs_f64();

    let mut per_class = BTreeMap::new();
    for l in &table.labels {
        *per_class
            .entry(classes::name(l.class).to_string())
            .or_insert(0usize) += 1;
    }
    let mut warnings = Vec::new();
    let snapped = opts.snap && inp.sam.is_some() && inp.kept.is_some();
    if opts.snap && !snapped {
        warnings.push(
            "city-part snapping skipped: it needs the scene's SAM lists and the masks stage's kept masks"
                .to_string(),
        );
    }
    let summary = FuseSummary {
        views: views.len(),
        delta,
        labels: table.labels.len(),
        city_labels: n_ent,
        image_labels: groups.groups.len(),
        image_pixels: image,
        city_pixels: city,
        unlabelled_pixels: none,
        labels_per_class: per_class,
        feature_dim,
        city_labels_with_features: with_features,
        options: *opts,
        snap: snapped.then_some(snap_total),
        timing: FuseTiming {
            views_s,
            labels_s,
            total_s: t0.elapsed().as_secs_f64(),
        },
        warnings,
    };
    for w in &summary.warnings {
        log::warn!("fuse: {w}");
    }
    crate::layout::Summary::write(&summary, out)?;
    crate::progress::done(
        "fuse",
        &format!(
            "{} views fused: {} city + {} image labels (Δ = {delta}){}",
            summary.views,
            summary.city_labels,
            summary.image_labels,
            match &summary.snap {
                Some(s) => format!(", {} masks snapped", s.snapped),
                None => String::new(),
            }
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}
