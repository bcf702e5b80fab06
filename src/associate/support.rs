//! View support and support-only masks (beyond the paper; steps 5 and 6 of docs/associate.md):
//! the SAM masks that the masks stage dropped only for quality or area are matched against the
//! pre-filter groups by the paper's rule (`R_geo > τ_geo` of their own α·T candidates, the group
//! their best match, feature cosine `> τ_sim`). A match adds a view to a group seen in fewer
//! than `m_view` views (view support); a support-only mask (`low_quality_support`) that matches
//! joins its group through the Gaussians: its candidates become fill members of the group. Such
//! masks never start a group.
use std::path::Path;

use super::filters::FarField;
use super::views::mask_features;
use super::{AssociateError, AssociateInputs, AssociateOptions, Stage, bank, candidates};
use crate::camera::View;
use crate::maskfile::{self, Rule};

/// A dropped mask that matched a pre-filter group.
pub(super) struct Hit {
    pub(super) group: usize,
    /// It adds a view to the group (view support: the group has no kept mask in the view).
    pub(super) view: bool,
    /// A support-only mask that joined the group.
    pub(super) joined: bool,
}

/// The pre-filter groups the dropped masks are matched against.
pub(super) struct Targets {
    /// Per pre-filter group: view support on, not far field, and seen in fewer than
    /// `min_views` views unless `support_pixels` ([`Support::eligible`]).
    pub(super) eligible: Vec<bool>,
    /// Per pre-filter group: not far field ([`Support::near`]).
    pub(super) near: Vec<bool>,
}

impl Targets {
    pub(super) fn new(fin: &bank::Finished, far: &FarField, opts: &AssociateOptions) -> Targets {
        let eligible: Vec<bool> = (0..fin.groups.len())
            .map(|gi| {
                opts.support
                    && !far.is_far(gi)
                    && (opts.support_pixels || fin.groups[gi].views.len() < opts.min_views)
            })
            .collect();
        let near: Vec<bool> = (0..fin.groups.len()).map(|gi| !far.is_far(gi)).collect();
        Targets { eligible, near }
    }

    /// Whether pass A of the transfer back matches dropped masks at all: SAM lists are given
    /// and some group is a target of the view support or of the support-only masks.
    pub(super) fn support_on(&self, inp: &AssociateInputs<'_>, opts: &AssociateOptions) -> bool {
        inp.sam.is_some()
            && ((opts.support && self.eligible.iter().any(|&w| w))
                || (opts.support_masks && self.near.iter().any(|&w| w)))
    }
}

/// Adds the Gaussians of joining support-only masks to the fill members
/// ([`AssociateOptions::support_masks`]): `joins[v]` = (group, candidates) per joining mask of
/// view `v`, `visible[v]` the view's visible Gaussians. Gaussian `g` becomes a member of `k`
/// when it is no member yet, no other group owns it, only `k`'s support-only masks claim it,
/// and they contain it in at least half of the views that see it and have a joining mask of
/// `k`, and in at least `min_views` views. Returns the number of Gaussians added. Order-free: counts only.
fn join_members(
    members: &mut [i32],
    owner: &[i32],
    joins: &[Vec<(usize, Vec<u32>)>],
    visible: &[Option<Vec<u64>>],
    min_views: u32,
) -> usize {
    // Per claimed Gaussian: (group, views containing it), or a conflict (usize::MAX).
    let mut claim: rustc_hash::FxHashMap<u32, (usize, u32)> = Default::default();
    for view in joins {
        let mut here: rustc_hash::FxHashSet<(u32, usize)> = Default::default();
        for (k, ids) in view {
            for &g in ids {
                if here.insert((g, *k)) {
                    let e = claim.entry(g).or_insert((*k, 0));
                    if e.0 != *k {
                        e.0 = usize::MAX;
                    }
                    e.1 += 1;
                }
            }
        }
    }
    let mut seen: rustc_hash::FxHashMap<u32, u32> = Default::default();
    for (view, bits) in joins.iter().zip(visible) {
        let bits = bits.as_deref().unwrap_or_default();
        let groups: rustc_hash::FxHashSet<usize> = view.iter().map(|(k, _)| *k).collect();
        for (&g, &(k, _)) in &claim {
            let vis = bits
                .get(g as usize / 64)
                .is_some_and(|w| w >> (g % 64) & 1 == 1);
            if k != usize::MAX && vis && groups.contains(&k) {
                *seen.entry(g).or_insert(0) += 1;
            }
        }
    }
    let mut added = 0;
    for (&g, &(k, n)) in &claim {
        let gi = g as usize;
        if k == usize::MAX || members[gi] >= 0 || (owner[gi] >= 0 && owner[gi] != k as i32) {
            continue;
        }
        if n >= min_views && 2 * n >= seen.get(&g).copied().unwrap_or(0) {
            members[gi] = k as i32;
            added += 1;
        }
    }
    added
}

/// A support-only mask's α·T candidates and feature, computed by pass 1 of the memory bank
/// while the view's lists are in memory ([`join_masks`]), so that the join does not read the
/// view's cache again.
pub(super) struct JoinMask {
    candidate: candidates::Candidate,
    feature: Option<Vec<f32>>,
}

/// The support-only masks of a view that may join a group ([`AssociateOptions::support_masks`]
/// with the fill and SAM lists on; none otherwise), with their α·T candidates
/// ([`candidates::weighted_one`], as [`Support::hits`] computes them) and features. `total` is
/// the view's per-Gaussian mass ([`candidates::view_mass`]).
pub(super) fn join_masks(
    inp: &AssociateInputs<'_>,
    opts: &AssociateOptions,
    view: &View,
    c: &crate::cache::ViewContrib,
    total: &[f32],
    centres: &[[f32; 3]],
) -> Result<Vec<JoinMask>, AssociateError> {
    if !(opts.support_masks && opts.fill.is_some()) {
        return Ok(Vec::new());
    }
    let Some(mut d) = dropped_masks(inp, opts, view, c.width, c.height)? else {
        return Ok(Vec::new());
    };
    let mut scratch = CandidateScratch::default();
    let mut out = Vec::new();
    for j in 0..d.sources.len() {
        if !d.only[j] {
            continue;
        }
        scratch.pixels(&d, j)?;
        let candidate = scratch.candidate(c, total, centres, &view.camera, opts);
        out.push(JoinMask {
            candidate,
            feature: d.feats[j].take(),
        });
    }
    Ok(out)
}

/// Support-only masks join their groups ([`AssociateOptions::support_masks`]): after pass 1,
/// before the transfer back, so that every view's fill sees the joins of all views. `masks[v]`
/// are view `v`'s support-only masks with their candidates ([`join_masks`], from pass 1); each
/// that matches a group by [`Support::best_match`] (the rule of [`Support::hits`]) joins it.
/// Adds the joining masks' Gaussians to `members` ([`join_members`]) and returns how many it
/// added (0 when the support-only masks, the fill or the SAM lists are off, or every group is
/// far field).
pub(super) fn join_support_masks(
    st: &Stage<'_>,
    fin: &bank::Finished,
    targets: &Targets,
    visible: &[Option<Vec<u64>>],
    masks: Vec<Result<Vec<JoinMask>, AssociateError>>,
    members: &mut [i32],
) -> Result<usize, AssociateError> {
    let (inp, opts) = (st.inp, st.opts);
    if !(opts.support_masks
        && opts.fill.is_some()
        && inp.sam.is_some()
        && targets.near.iter().any(|&w| w))
    {
        return Ok(0);
    }
    let sup = Support {
        fin,
        eligible: &targets.eligible,
        near: &targets.near,
        centres: st.centres,
        paint_joined: false,
        owner: &fin.owner,
    };
    // Per view: (group, candidates) of each joining mask.
    let mut joins: Vec<Vec<(usize, Vec<u32>)>> = Vec::with_capacity(masks.len());
    for (vi, view) in masks.into_iter().enumerate() {
        joins.push(
            view?
                .into_iter()
                .filter_map(|m| {
                    let k =
                        sup.best_match(opts, vi as u32, &m.candidate, m.feature.as_deref(), true)?;
                    Some((k, m.candidate.ids))
                })
                .collect(),
        );
    }
    Ok(join_members(
        members,
        &fin.owner,
        &joins,
        visible,
        opts.join_views,
    ))
}

/// The view support of the groups seen in fewer than `min_views` views
/// ([`AssociateOptions::support`]).
pub(super) struct Support<'a> {
    pub(super) fin: &'a bank::Finished,
    /// Per pre-filter group: whether dropped masks are matched against it (not far field; and
    /// seen in fewer than `min_views` views unless `support_pixels`).
    pub(super) eligible: &'a [bool],
    /// Per pre-filter group: not far field (what support-only masks may join).
    pub(super) near: &'a [bool],
    /// Label the pixels of joining support-only masks (else they only count as hits).
    pub(super) paint_joined: bool,
    /// Gaussian ownership the masks are matched against (the bank's).
    pub(super) owner: &'a [i32],
    pub(super) centres: &'a [[f32; 3]],
}

/// The masks of a view that the masks stage dropped for quality or area only (and the
/// support-only ones), with their SAM file and features: what the view support matches.
struct Dropped {
    /// SAM index of each.
    sources: Vec<i64>,
    /// Each is a support-only mask that may join a group ([`AssociateOptions::support_masks`]).
    only: Vec<bool>,
    sam: Vec<crate::sam::SamMask>,
    spath: std::path::PathBuf,
    feats: Vec<Option<Vec<f32>>>,
}

/// Reads view `view`'s dropped masks (`None` without SAM lists or without such masks): the
/// masks stage's decisions, the SAM file (checked against the `w × h` image) and the features.
fn dropped_masks(
    inp: &AssociateInputs<'_>,
    opts: &AssociateOptions,
    view: &View,
    w: usize,
    h: usize,
) -> Result<Option<Dropped>, AssociateError> {
    let Some(sam_dir) = inp.sam else {
        return Ok(None);
    };
    let stem = view.stem();
    let dpath = maskfile::decisions_file(inp.masks, &stem);
    if !dpath.is_file() {
        return Err(AssociateError::Invalid {
            path: dpath,
            why: "missing: the view support needs the masks stage's decisions".into(),
        });
    }
    // (SAM index, support-only) of the masks dropped for quality or area only.
    let (sources, only): (Vec<i64>, Vec<bool>) = maskfile::read_decisions(&dpath)?
        .iter()
        .filter(|d| {
            !d.kept
                && d.source_index >= 0
                && matches!(d.rule, Rule::Quality | Rule::Area | Rule::LowQualitySupport)
        })
        .map(|d| {
            let joins = opts.support_masks && d.rule == Rule::LowQualitySupport;
            (d.source_index, joins)
        })
        .unzip();
    if sources.is_empty() {
        return Ok(None);
    }
    let spath = sam_dir.join(format!("{stem}.json"));
    let sam = crate::sam::read_sam_json_sized(&spath, Some([h, w]))?;
    if let Some(&s) = sources.iter().find(|&&s| s as usize >= sam.len()) {
        return Err(AssociateError::Invalid {
            path: dpath,
            why: format!(
                "a decision has source_index {s}, {} lists {} masks",
                spath.display(),
                sam.len()
            ),
        });
    }
    let feats = match inp.features {
        Some(dir) => mask_features(&dir.join(format!("{stem}.npy")), &sources)?.1,
        None => vec![None; sources.len()],
    };
    Ok(Some(Dropped {
        sources,
        only,
        sam,
        spath,
        feats,
    }))
}

/// Scratch of the dropped masks' candidates: the mask's pixels, its inside flags and the
/// per-Gaussian accumulator (both all false / zero between masks).
#[derive(Default)]
struct CandidateScratch {
    px: Vec<u32>,
    in_mask: Vec<bool>,
    acc: Vec<f32>,
}

impl CandidateScratch {
    /// Decodes dropped mask `j`'s pixels into `px`.
    fn pixels(&mut self, d: &Dropped, j: usize) -> Result<(), AssociateError> {
        let si = d.sources[j] as usize;
        self.px.clear();
        let px = &mut self.px;
        for_each_pixel_checked(&d.sam[si].segmentation, &d.spath, si, |p| px.push(p as u32))
    }

    /// The α·T candidates of the pixels in `px` ([`candidates::weighted_one`]).
    fn candidate(
        &mut self,
        c: &crate::cache::ViewContrib,
        total: &[f32],
        centres: &[[f32; 3]],
        camera: &crate::camera::Camera,
        opts: &AssociateOptions,
    ) -> candidates::Candidate {
        self.in_mask.resize(c.width * c.height, false);
        self.acc.resize(c.gaussians, 0.0);
        for &p in &self.px {
            self.in_mask[p as usize] = true;
        }
        let cand = candidates::weighted_one(
            c,
            total,
            candidates::MaskPixels {
                list: &self.px,
                inside: &self.in_mask,
            },
            centres,
            camera,
            &opts.weighted,
            &mut self.acc,
        );
        for &p in &self.px {
            self.in_mask[p as usize] = false;
        }
        cand
    }
}

impl Support<'_> {
    /// Whether group `k` lacks a kept mask in view `vi` and the view support may add one.
    fn weak(&self, k: usize, vi: u32) -> bool {
        self.eligible[k] && !self.fin.groups[k].views.contains(&vi)
    }

    /// Whether a dropped mask of view `vi` may match group `k`: a support-only mask (`joins`)
    /// any group that is not far field, every dropped mask a weak one.
    fn wants(&self, k: usize, vi: u32, joins: bool) -> bool {
        (joins && self.near[k]) || self.weak(k, vi)
    }

    /// The paper's rule for a dropped mask of view `vi` with candidates `cand`: the group that
    /// owns the largest share of their mass, when that share passes `τ_geo`, the mask may match
    /// it ([`Support::wants`]) and its feature (if any) is `τ_sim`-similar to the group's.
    fn best_match(
        &self,
        opts: &AssociateOptions,
        vi: u32,
        cand: &candidates::Candidate,
        feature: Option<&[f32]>,
        joins: bool,
    ) -> Option<usize> {
        let (shares, mass) = bank::shares_under(self.owner, cand);
        let (k, m) = bank::best_share(&shares)?;
        let k = k as usize;
        if !(mass > 0.0 && m / mass > opts.tau_geo && self.wants(k, vi, joins)) {
            return None;
        }
        let similar = feature.is_none_or(|f| {
            bank::cosine(f, &self.fin.groups[k].feature_mean).is_none_or(|c| c > opts.tau_sim)
        });
        similar.then_some(k)
    }

    /// The eligible groups that masks of view `vi` dropped for quality or area only match (one
    /// entry per matching mask; only groups without a kept mask in the view). With
    /// `support_pixels`, a matching mask's pixels where `map` is −1 (or another dropped mask
    /// painted them: larger masks first, so the smaller wins) take its group.
    pub(super) fn hits(
        &self,
        inp: &AssociateInputs<'_>,
        opts: &AssociateOptions,
        view: &View,
        vi: u32,
        c: &crate::cache::ViewContrib,
        map: &mut [i32],
    ) -> Result<Vec<Hit>, AssociateError> {
        let Some(d) = dropped_masks(inp, opts, view, c.width, c.height)? else {
            return Ok(Vec::new());
        };
        let owner = self.owner;
        // Larger masks first (ties: file order), so a smaller one paints over them.
        let mut order: Vec<usize> = (0..d.sources.len()).collect();
        order.sort_by(|&a, &b| {
            d.sam[d.sources[b] as usize]
                .area
                .cmp(&d.sam[d.sources[a] as usize].area)
                .then(a.cmp(&b))
        });
        let mut painted = vec![false; c.width * c.height];
        let total = candidates::view_mass(c);
        let mut scratch = CandidateScratch::default();
        let mut hits = Vec::new();
        for j in order {
            scratch.pixels(&d, j)?;
            // Only masks on some weak group's Gaussians are worth their candidates (a mask on
            // none cannot match: its best group owns one of its candidates, all of them in
            // its pixels' lists).
            let touches = scratch.px.iter().any(|&p| {
                c.pixel(p as usize).0.iter().any(|&g| {
                    let o = owner[g as usize];
                    o >= 0 && self.wants(o as usize, vi, d.only[j])
                })
            });
            if !touches {
                continue;
            }
            let cand = scratch.candidate(c, &total, self.centres, &view.camera, opts);
            if let Some(k) = self.best_match(opts, vi, &cand, d.feats[j].as_deref(), d.only[j]) {
                // A view of the group only where it has no kept mask (view support).
                hits.push(Hit {
                    group: k,
                    view: self.weak(k, vi),
                    joined: d.only[j],
                });
                if opts.support_pixels || (d.only[j] && self.paint_joined) {
                    for &p in &scratch.px {
                        let p = p as usize;
                        if map[p] == -1 || painted[p] {
                            map[p] = k as i32;
                            painted[p] = true;
                        }
                    }
                }
            }
        }
        Ok(hits)
    }
}

/// [`crate::sam::Rle::for_each_pixel`] with the file and mask index in the error.
fn for_each_pixel_checked(
    rle: &crate::sam::Rle,
    path: &Path,
    index: usize,
    f: impl FnMut(usize),
) -> Result<(), AssociateError> {
    rle.for_each_pixel(f).map_err(|err| AssociateError::Rle {
        path: path.to_path_buf(),
        index,
        err,
    })
}
