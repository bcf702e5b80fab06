//! Reading the views (paper §3.2, step 1 of docs/associate.md) and pass 1 of the memory bank:
//! each view's kept masks, checked against the camera and composited into one label image
//! (smaller masks on top), their features, the view of the contributions cache, and the
//! candidate Gaussians `C(s)` of every visible mask ([`CandidateMode`]). Pass 1 reads the views
//! in parallel blocks and offers their masks to the bank in the visiting order.
use std::path::Path;
use std::time::Instant;

use rand::SeedableRng;
use rand::seq::SliceRandom;
use rayon::prelude::*;

use super::{
    AssociateError, AssociateInputs, AssociateOptions, BankOptions, CandidateMode, Stage, Tally,
    bank, candidates,
};
use crate::camera::View;
use crate::maskfile::{self, KeptMask};
use crate::progress::Bar;

/// One view's kept masks (checked against the image size) and their composite.
pub(super) struct MaskView {
    pub(super) stem: String,
    pub(super) w: usize,
    pub(super) h: usize,
    pub(super) kept: Vec<KeptMask>,
    pub(super) vm: candidates::ViewMasks,
}

/// Reads `view`'s kept-mask file from `masks_dir` and composites it.
pub(super) fn mask_view(masks_dir: &Path, view: &View) -> Result<MaskView, AssociateError> {
    let stem = view.stem();
    let (w, h) = (
        view.camera.intrinsics.width as usize,
        view.camera.intrinsics.height as usize,
    );
    let path = maskfile::kept_file(masks_dir, &stem);
    if !path.is_file() {
        return Err(AssociateError::Invalid {
            path,
            why: "missing: the masks stage wrote no kept-mask file for this view".into(),
        });
    }
    let kept = maskfile::read_kept(&path)?;
    for (i, k) in kept.iter().enumerate() {
        if k.sam.segmentation.size != [h, w] {
            return Err(AssociateError::Invalid {
                path,
                why: format!(
                    "mask {i}: size {:?} differs from the image size [{h}, {w}]",
                    k.sam.segmentation.size
                ),
            });
        }
    }
    let rles: Vec<&crate::sam::Rle> = kept.iter().map(|k| &k.sam.segmentation).collect();
    let vm = candidates::composite(&rles, w, h).map_err(|(index, err)| AssociateError::Rle {
        path: path.clone(),
        index,
        err,
    })?;
    Ok(MaskView {
        stem,
        w,
        h,
        kept,
        vm,
    })
}

/// Dimension, per-mask unit features (None: no feature), count of all-zero rows.
pub(crate) type MaskFeatures = (usize, Vec<Option<Vec<f32>>>, usize);

/// Per-mask features of a view (`features/<stem>.npy`), rows at the kept masks' source indices,
/// normalised. Returns the dimension, the features and the count of zero rows (no feature).
pub(crate) fn mask_features(path: &Path, sources: &[i64]) -> Result<MaskFeatures, AssociateError> {
    let (rows, d, data) = crate::sam::read_features(path, None)?;
    let bad = |why: String| AssociateError::Invalid {
        path: path.to_path_buf(),
        why,
    };
    if d == 0 {
        return Err(bad(format!(
            "shape [{rows}, 0], expected [masks, D] with D ≥ 1"
        )));
    }
    let mut zero = 0;
    let mut out = Vec::with_capacity(sources.len());
    for &s in sources {
        if s < 0 {
            out.push(None);
            continue;
        }
        let r = s as usize;
        if r >= rows {
            return Err(bad(format!(
                "{rows} feature rows, but a kept mask has source_index {s}"
            )));
        }
        let row = &data[r * d..(r + 1) * d];
        let norm = row
            .iter()
            .map(|&x| f64::from(x) * f64::from(x))
            .sum::<f64>()
            .sqrt();
        if norm < 1e-12 {
            zero += 1;
            out.push(None);
        } else {
            out.push(Some(
                row.iter().map(|&x| (f64::from(x) / norm) as f32).collect(),
            ));
        }
    }
    Ok((d, out, zero))
}

/// Counts of the kept masks: of one view, and summed over the views by pass 1.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct MaskCounts {
    /// Kept masks read.
    pub(super) masks: usize,
    /// Masks hidden by smaller masks on top of them.
    pub(super) hidden: usize,
    /// Visible masks without candidate Gaussians.
    pub(super) without_candidates: usize,
    /// Masks with a feature.
    pub(super) with_features: usize,
    /// Masks whose feature row is all zero (associated without a feature).
    pub(super) zero_features: usize,
}

impl MaskCounts {
    fn add(&mut self, o: &MaskCounts) {
        self.masks += o.masks;
        self.hidden += o.hidden;
        self.without_candidates += o.without_candidates;
        self.with_features += o.with_features;
        self.zero_features += o.zero_features;
    }
}

/// What the per-view phase yields for the bank.
struct ViewWork {
    /// Gaussians visible in the view (only for the fill).
    visible: Option<Vec<u64>>,
    /// Its support-only masks with their candidates, for the join after pass 1
    /// ([`super::support::join_masks`]; an error is raised only if the join runs).
    join_masks: Result<Vec<super::support::JoinMask>, AssociateError>,
    observations: Vec<bank::Observation>,
    counts: MaskCounts,
    dim: Option<usize>,
}

/// Loads a cache view and checks its size against the camera.
pub(super) fn load_cache_view(
    inp: &AssociateInputs<'_>,
    stem: &str,
    w: usize,
    h: usize,
) -> Result<crate::cache::ViewContrib, AssociateError> {
    let c = inp.cache.load(stem)?;
    if (c.width, c.height) != (w, h) {
        return Err(AssociateError::Invalid {
            path: crate::cache::cache_file(&inp.cache.dir, stem),
            why: format!(
                "{}×{} pixels, the camera has {w}×{h}: the cache is stale",
                c.width, c.height
            ),
        });
    }
    Ok(c)
}

/// Reads one view and computes its observations.
fn view_work(
    inp: &AssociateInputs<'_>,
    opts: &AssociateOptions,
    centres: &[[f32; 3]],
    view: &View,
    canonical: u32,
) -> Result<ViewWork, AssociateError> {
    let MaskView {
        stem,
        w,
        h,
        kept,
        vm,
    } = mask_view(inp.masks, view)?;
    let (dim, feats, zero) = match inp.features {
        Some(dir) if !kept.is_empty() => {
            let fp = dir.join(format!("{stem}.npy"));
            let sources: Vec<i64> = kept.iter().map(|k| k.source_index).collect();
            let (d, f, z) = mask_features(&fp, &sources)?;
            (Some(d), f, z)
        }
        _ => (None, vec![None; kept.len()], 0),
    };
    // The cache view (α·T candidates, and the visible Gaussians for the fill).
    let need_cache = opts.candidates == CandidateMode::Weighted || opts.fill.is_some();
    let cache_view = if need_cache {
        Some(load_cache_view(inp, &stem, w, h)?)
    } else {
        None
    };
    let total = cache_view.as_ref().map(candidates::view_mass);
    let cands = match (opts.candidates, &cache_view, &total) {
        (CandidateMode::Weighted, Some(c), Some(t)) => {
            candidates::weighted(c, t, centres, &view.camera, &vm, &opts.weighted)
        }
        _ => candidates::projected(centres, &view.camera, &vm, &opts.projected),
    };
    let visible = match (&total, opts.fill) {
        (Some(t), Some(_)) => Some(candidates::visible_set(t, opts.weighted.min_mass)),
        _ => None,
    };
    let join_masks = match (&cache_view, &total) {
        (Some(c), Some(t)) => super::support::join_masks(inp, opts, view, c, t, centres),
        _ => Ok(Vec::new()),
    };
    let mut out = ViewWork {
        visible,
        join_masks,
        observations: Vec::new(),
        counts: MaskCounts {
            masks: kept.len(),
            hidden: 0,
            without_candidates: 0,
            with_features: feats.iter().filter(|f| f.is_some()).count(),
            zero_features: zero,
        },
        dim,
    };
    for (i, (cand, feature)) in cands.into_iter().zip(feats).enumerate() {
        if vm.visible[i] == 0 {
            out.counts.hidden += 1;
            continue;
        }
        if cand.ids.is_empty() {
            out.counts.without_candidates += 1;
            continue;
        }
        let (mut cs, mut ws) = ([0.0f64; 3], 0.0f64);
        for (&g, &wt) in cand.ids.iter().zip(&cand.weights) {
            let p = centres[g as usize];
            let wt = f64::from(wt);
            for k in 0..3 {
                cs[k] += wt * f64::from(p[k]);
            }
            ws += wt;
        }
        out.observations.push(bank::Observation {
            view: canonical,
            mask: i as u32,
            feature,
            class: kept[i].class,
            pixels: vm.visible[i],
            candidate: cand,
            centroid_sum: cs,
            weight_sum: ws,
        });
    }
    Ok(out)
}

/// What pass 1 of the memory bank leaves.
pub(super) struct PassOne {
    /// The bank after pass 1 (before the consolidation).
    pub(super) bank: bank::Bank,
    /// Per view (canonical index): its visible Gaussians (only for the fill).
    pub(super) visible: Vec<Option<Vec<u64>>>,
    /// Per view (canonical index): its support-only masks ([`super::support::join_masks`]).
    pub(super) join_masks: Vec<Result<Vec<super::support::JoinMask>, AssociateError>>,
    /// How τ_sim was chosen; the bank used its value.
    pub(super) calibration: super::calibrate::Calibration,
}

/// Pass 1 of the memory bank: the views are read in parallel blocks ([`view_work`]), τ_sim is
/// calibrated on all their masks ([`super::calibrate`], unless switched off), and the masks are
/// offered to the bank in the visiting order (by name, or a seeded shuffle). The counts and times
/// go to `tally`.
pub(super) fn pass_one(st: &Stage<'_>, tally: &mut Tally) -> Result<PassOne, AssociateError> {
    let (inp, opts, views, centres) = (st.inp, st.opts, st.views, st.centres);
    // Visiting order: by name, or a seeded shuffle.
    let mut order: Vec<u32> = (0..views.len() as u32).collect();
    if let Some(seed) = opts.shuffle_seed {
        order.shuffle(&mut rand_chacha::ChaCha8Rng::seed_from_u64(seed));
    }
    let bar = Bar::new("associate", views.len() as u64, "views");
    let (mut views_s, mut bank_s) = (0.0, 0.0);
    let mut counts = MaskCounts::default();
    let mut dim: Option<usize> = None;
    let mut observations: Vec<bank::Observation> = Vec::new();
    let mut visible: Vec<Option<Vec<u64>>> = vec![None; views.len()];
    let mut join_masks: Vec<Result<Vec<super::support::JoinMask>, AssociateError>> =
        (0..views.len()).map(|_| Ok(Vec::new())).collect();
    let chunk = rayon::current_num_threads().max(1) * 2;
    for block in order.chunks(chunk) {
        let t = Instant::now();
        let works: Vec<Result<ViewWork, AssociateError>> = block
            .par_iter()
            .map(|&vi| view_work(inp, opts, centres, views[vi as usize], vi))
            .collect();
        views_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        for (wk, &vi) in works.into_iter().zip(block) {
            let wk = wk?;
            if let (Some(a), Some(b)) = (dim, wk.dim)
                && a != b
            {
                return Err(AssociateError::Invalid {
                    path: inp
                        .features
                        .map(|d| d.join(format!("{}.npy", views[vi as usize].stem())))
                        .unwrap_or_default(),
                    why: format!("features of dimension {b}, other views have {a}"),
                });
            }
            dim = dim.or(wk.dim);
            counts.add(&wk.counts);
            visible[vi as usize] = wk.visible;
            join_masks[vi as usize] = wk.join_masks;
            observations.extend(wk.observations);
            bar.inc(1);
        }
        bank_s += t.elapsed().as_secs_f64();
    }
    bar.finish();
    let t = Instant::now();
    let calibration = if opts.calibrate {
        super::calibrate::calibrate(&observations, opts.tau_sim)
    } else {
        super::calibrate::configured(opts.tau_sim, "calibration off: the configured τ_sim")
    };
    tally.timing.calibrate_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut bank = bank::Bank::new(
        centres.len(),
        BankOptions {
            tau_geo: opts.tau_geo,
            tau_sim: calibration.tau_sim,
            consolidate: opts.consolidate,
            merge_support: opts.merge_support,
            merge_fraction: opts.merge_fraction,
            tau_link: opts.tau_link,
            specific_owner: opts.specific_owner,
        },
    );
    let offered = observations.len();
    for o in observations {
        bank.offer(o);
    }
    bank_s += t.elapsed().as_secs_f64();
    tally.counts = counts;
    tally.dim = dim;
    tally.offered = offered;
    tally.timing.views_s = views_s;
    tally.timing.bank_s = bank_s;
    Ok(PassOne {
        bank,
        visible,
        join_masks,
        calibration,
    })
}
