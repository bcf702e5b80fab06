//! View support and support-only masks (beyond the paper; steps 5 and 6 of docs/associate.md):
//! the SAM masks that the masks stage dropped only for quality or area are matched against the
//! pre-filter groups by the paper's rule (`R_geo > τ_geo` of their own α·T candidates, the group
//! their best match, feature cosine `> τ_sim`). A match adds a view to a group seen in fewer
//! than `m_view` views (view support); a support-only mask (`low_quality_support`) that matches
//! joins its group through the Gaussians: its candidates become fill members of the group. Such
//! masks never start a group.
use std::path::Path;

use rayon::prelude::*;

use super::filters::FarField;
use super::views::{load_cache_view, mask_features};
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
    /// Its α·T candidates (support-only masks only).
    pub(super) gaussians: Vec<u32>,
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

/// Support-only masks join their groups ([`AssociateOptions::support_masks`]): a pass over the
/// views before the transfer back, so that every view's fill sees the joins of all views. Adds
/// the joining masks' Gaussians to `members` ([`join_members`]) and returns how many it added
/// (0 when the support-only masks, the fill or the SAM lists are off, or every group is far
/// field).
pub(super) fn join_support_masks(
    st: &Stage<'_>,
    fin: &bank::Finished,
    targets: &Targets,
    visible: &[Option<Vec<u64>>],
    members: &mut [i32],
) -> Result<usize, AssociateError> {
    let (inp, opts, views) = (st.inp, st.opts, st.views);
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
        joined_only: true,
        owner: &fin.owner,
    };
    // Per view: (group, candidates) of each joining mask.
    type Joins = Vec<(usize, Vec<u32>)>;
    let joins: Vec<Result<Joins, AssociateError>> = views
        .par_iter()
        .enumerate()
        .map(|(vi, v)| {
            let stem = v.stem();
            let (w, h) = (
                v.camera.intrinsics.width as usize,
                v.camera.intrinsics.height as usize,
            );
            let c = load_cache_view(inp, &stem, w, h)?;
            let mut scratch = vec![-1i32; w * h];
            Ok(sup
                .hits(inp, opts, v, vi as u32, &c, &mut scratch)?
                .into_iter()
                .filter(|h| h.joined)
                .map(|h| (h.group, h.gaussians))
                .collect())
        })
        .collect();
    let joins = joins.into_iter().collect::<Result<Vec<_>, _>>()?;
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
    /// Label the pixels of joining support-only masks (else only record their candidates).
    pub(super) paint_joined: bool,
    /// Match only the support-only masks.
    pub(super) joined_only: bool,
    /// Gaussian ownership the masks are matched against (the bank's).
    pub(super) owner: &'a [i32],
    pub(super) centres: &'a [[f32; 3]],
}

impl Support<'_> {
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
        let Some(sam_dir) = inp.sam else {
            return Ok(Vec::new());
        };
        let stem = view.stem();
        let (w, h) = (c.width, c.height);
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
            return Ok(Vec::new());
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
        let owner = self.owner;
        let weak = |k: usize| self.eligible[k] && !self.fin.groups[k].views.contains(&vi);
        // A support-only mask may join any group that is not far field.
        let wants = |k: usize, joins: bool| (joins && self.near[k]) || weak(k);
        // Larger masks first (ties: file order), so a smaller one paints over them.
        let mut order: Vec<usize> = (0..sources.len()).collect();
        order.sort_by(|&a, &b| {
            sam[sources[b] as usize]
                .area
                .cmp(&sam[sources[a] as usize].area)
                .then(a.cmp(&b))
        });
        let mut painted = vec![false; w * h];
        let total = candidates::view_mass(c);
        let mut acc = vec![0f32; c.gaussians];
        let mut in_mask = vec![false; w * h];
        let mut px: Vec<u32> = Vec::new();
        let mut hits = Vec::new();
        for j in order {
            if self.joined_only && !only[j] {
                continue;
            }
            let si = sources[j];
            px.clear();
            for_each_pixel_checked(&sam[si as usize].segmentation, &spath, si as usize, |p| {
                px.push(p as u32)
            })?;
            // Only masks on some weak group's Gaussians are worth their candidates.
            let touches = px.iter().any(|&p| {
                c.pixel(p as usize).0.iter().any(|&g| {
                    let o = owner[g as usize];
                    o >= 0 && wants(o as usize, only[j])
                })
            });
            if !touches {
                continue;
            }
            for &p in &px {
                in_mask[p as usize] = true;
            }
            let cand = candidates::weighted_one(
                c,
                &total,
                candidates::MaskPixels {
                    list: &px,
                    inside: &in_mask,
                },
                self.centres,
                &view.camera,
                &opts.weighted,
                &mut acc,
            );
            for &p in &px {
                in_mask[p as usize] = false;
            }
            let (shares, mass) = bank::shares_under(owner, &cand);
            let best = bank::best_share(&shares);
            if let Some((k, m)) = best
                && mass > 0.0
                && m / mass > opts.tau_geo
                && wants(k as usize, only[j])
            {
                let similar = feats[j].as_deref().is_none_or(|f| {
                    bank::cosine(f, &self.fin.groups[k as usize].feature_mean)
                        .is_none_or(|c| c > opts.tau_sim)
                });
                if similar {
                    // A view of the group only where it has no kept mask (view support).
                    hits.push(Hit {
                        group: k as usize,
                        view: weak(k as usize),
                        joined: only[j],
                        gaussians: if only[j] {
                            cand.ids.clone()
                        } else {
                            Vec::new()
                        },
                    });
                    if opts.support_pixels || (only[j] && self.paint_joined) {
                        for &p in &px {
                            let p = p as usize;
                            if map[p] == -1 || painted[p] {
                                map[p] = k as i32;
                                painted[p] = true;
                            }
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
    rle.for_each_pixel(f).map_err(|source| AssociateError::Rle {
        path: path.to_path_buf(),
        index,
        source,
    })
}
