//! Transfer back (paper §3.2; step 8 of docs/associate.md): the group ids go back to every
//! view in two passes. Pass A makes each view's map over the pre-filter groups — the kept
//! masks composited, the pixels of matching dropped masks where asked, then the fill — and
//! collects the view support; after the filters, pass B turns the maps (held in memory) into
//! the kept groups' ids and writes them. Owns the fill members (which Gaussians of a group may label pixels) and the fill.
use std::collections::BTreeSet;

use rayon::prelude::*;

use super::support::{Hit, Support, Targets};
use super::views::{MaskView, load_cache_view, mask_view};
use super::{AssociateError, AssociateOptions, Stage, Tally, bank};
use crate::idmap;

/// The fill members (empty when the fill is off) from the per-view visible Gaussians of pass 1.
pub(super) fn members(
    opts: &AssociateOptions,
    fin: &bank::Finished,
    visible: &[Option<Vec<u64>>],
    views: usize,
) -> Vec<i32> {
    if opts.fill.is_some() {
        fill_members(fin, visible, views)
    } else {
        Vec::new()
    }
}

/// Members of the groups for the fill: Gaussian `g` of owner `k` (vote ownership) is a member
/// when, over the views where `g` is visible and `k` has a mask, `g` lies in `k`'s mask in at
/// least half. A Gaussian a group absorbed by accident — a wall Gaussian seen through a tree
/// once, a road Gaussian under an under-segmented mask — lies outside the group's masks in most
/// views that see both, and is not a member.
fn fill_members(fin: &bank::Finished, visible: &[Option<Vec<u64>>], views: usize) -> Vec<i32> {
    let n = fin.owner.len();
    let mut inside = vec![0u16; n];
    let mut seen = vec![0u16; n];
    let mut present: Vec<Vec<usize>> = vec![Vec::new(); views];
    for (o, &gi) in fin.observations.iter().zip(&fin.group_of) {
        present[o.view as usize].push(gi);
        for &g in &o.candidate.ids {
            if fin.owner[g as usize] == gi as i32 {
                inside[g as usize] = inside[g as usize].saturating_add(1);
            }
        }
    }
    for (v, bits) in visible.iter().enumerate() {
        let Some(bits) = bits else { continue };
        let groups: std::collections::HashSet<usize> = present[v].iter().copied().collect();
        for (word, &b) in bits.iter().enumerate() {
            let mut b = b;
            while b != 0 {
                let g = word * 64 + b.trailing_zeros() as usize;
                b &= b - 1;
                let k = fin.owner[g];
                if k >= 0 && groups.contains(&(k as usize)) {
                    seen[g] = seen[g].saturating_add(1);
                }
            }
        }
    }
    (0..n)
        .map(|g| {
            let k = fin.owner[g];
            if k >= 0 && inside[g] > 0 && 2 * u32::from(inside[g]) >= u32::from(seen[g]) {
                k
            } else {
                -1
            }
        })
        .collect()
}

/// The fill: every pixel of `map` still −1 takes the group `k` whose member Gaussians carry at
/// least `share` of the pixel's α·T mass (the largest such group; ties: the smaller index),
/// written as `−2 − k` (a filled pixel). With `over` (the groups that have a kept mask in the
/// view, [`AssociateOptions::fill_over_masks`]), a pixel of a kept mask's group also takes such
/// a `k` when `k` is another group and not in `over`. Returns the number of pixels filled.
fn fill(
    map: &mut [i32],
    c: &crate::cache::ViewContrib,
    owner: &[i32],
    share: f32,
    over: Option<&std::collections::HashSet<i32>>,
) -> u64 {
    let mut filled = 0;
    let mut acc: Vec<(i32, f32)> = Vec::with_capacity(16);
    for (p, m) in map.iter_mut().enumerate() {
        if *m >= 0 && over.is_none() {
            continue;
        }
        acc.clear();
        let (ids, ws) = c.pixel(p);
        for (&g, &w) in ids.iter().zip(ws) {
            let k = owner[g as usize];
            if k < 0 {
                continue;
            }
            match acc.iter_mut().find(|e| e.0 == k) {
                Some(e) => e.1 += w,
                None => acc.push((k, w)),
            }
        }
        let best = acc
            .iter()
            .copied()
            .fold(None::<(i32, f32)>, |b, x| match b {
                Some(b) if b.1 > x.1 || (b.1 == x.1 && b.0 < x.0) => Some(b),
                _ => Some(x),
            });
        if let Some((k, w)) = best
            && w >= share
            && (*m < 0 || (k != *m && over.is_some_and(|o| !o.contains(&k))))
        {
            *m = -2 - k;
            filled += 1;
        }
    }
    filled
}

/// Group index per (canonical view, mask index): per view, (mask index, pre-filter group) of
/// each mask the bank associated.
pub(super) fn masks_per_view(fin: &bank::Finished, views: usize) -> Vec<Vec<(u32, usize)>> {
    let mut per_view: Vec<Vec<(u32, usize)>> = vec![Vec::new(); views];
    for (o, &gi) in fin.observations.iter().zip(&fin.group_of) {
        per_view[o.view as usize].push((o.mask, gi));
    }
    per_view
}

/// One view's map over pre-filter group indices (a filled pixel is −2 − index), kept in
/// memory from pass A to pass B (the map of a 660×494 view takes 1.3 MB).
pub(super) struct PassAMap {
    w: usize,
    h: usize,
    map: Vec<i32>,
}

/// Transfer back, pass A: per view, the map over pre-filter group indices (a filled pixel is
/// −2 − index) and the view support's matches. Returns per pre-filter group the views the
/// view support adds, and the maps (in view order) for [`pass_b`]; the counts of matching
/// masks go to `tally`.
pub(super) fn pass_a(
    st: &Stage<'_>,
    fin: &bank::Finished,
    per_view: &[Vec<(u32, usize)>],
    targets: &Targets,
    members: &[i32],
    tally: &mut Tally,
) -> Result<(Vec<BTreeSet<u32>>, Vec<PassAMap>), AssociateError> {
    let (inp, opts, views) = (st.inp, st.opts, st.views);
    let support_on = targets.support_on(inp, opts);
    let pass_a: Vec<Result<(Vec<Hit>, PassAMap), AssociateError>> = views
        .par_iter()
        .zip(per_view)
        .enumerate()
        .map(|(vi, (v, assigned))| {
            let MaskView {
                stem,
                w,
                h,
                kept,
                vm,
            } = mask_view(inp.masks, v)?;
            let mut gi_of = vec![-1i32; kept.len()];
            for &(m, gi) in assigned {
                gi_of[m as usize] = gi as i32;
            }
            let mut map: Vec<i32> = vm
                .label
                .iter()
                .map(|&l| if l >= 0 { gi_of[l as usize] } else { -1 })
                .collect();
            let mut hits = Vec::new();
            if opts.fill.is_some() || support_on {
                let c = load_cache_view(inp, &stem, w, h)?;
                if support_on {
                    let sup = Support {
                        fin,
                        eligible: &targets.eligible,
                        near: &targets.near,
                        centres: st.centres,
                        paint_joined: opts.support_mask_pixels,
                        owner: &fin.owner,
                    };
                    hits = sup.hits(inp, opts, v, vi as u32, &c, &mut map)?;
                }
                if let Some(share) = opts.fill {
                    let present: std::collections::HashSet<i32> =
                        assigned.iter().map(|&(_, gi)| gi as i32).collect();
                    let over = opts.fill_over_masks.then_some(&present);
                    fill(&mut map, &c, members, share, over);
                }
            }
            Ok((hits, PassAMap { w, h, map }))
        })
        .collect();
    let mut support: Vec<std::collections::BTreeSet<u32>> =
        vec![Default::default(); fin.groups.len()];
    let (mut support_masks, mut joined_masks) = (0, 0);
    let mut maps = Vec::with_capacity(views.len());
    for (vi, r) in pass_a.into_iter().enumerate() {
        let (hits, map) = r?;
        maps.push(map);
        for hit in hits {
            if hit.view {
                support[hit.group].insert(vi as u32);
                support_masks += 1;
            }
            joined_masks += usize::from(hit.joined);
        }
    }
    tally.support_masks = support_masks;
    tally.joined_masks = joined_masks;
    Ok((support, maps))
}

/// Transfer back, pass B: pre-filter indices of pass A's maps (in view order) → kept group
/// ids (`keep_id`, −1 for dropped groups), written as each view's `<stem>.ids.npy`. The
/// labelled and filled pixels go to `tally`.
pub(super) fn pass_b(
    st: &Stage<'_>,
    maps: Vec<PassAMap>,
    keep_id: &[i32],
    tally: &mut Tally,
) -> Result<(), AssociateError> {
    let (views, out) = (st.views, st.out);
    let labelled: Vec<Result<(u64, u64), AssociateError>> = views
        .par_iter()
        .zip(maps)
        .map(|(v, PassAMap { w, h, mut map })| {
            let stem = v.stem();
            let (mut lab, mut filled) = (0u64, 0u64);
            for m in map.iter_mut() {
                let (gi, by_fill) = match *m {
                    x if x >= 0 => (x as usize, false),
                    -1 => continue,
                    x => ((-2 - x) as usize, true),
                };
                *m = keep_id[gi];
                if *m >= 0 {
                    lab += 1;
                    filled += u64::from(by_fill);
                }
            }
            idmap::write_ids(out, &stem, w, h, &map)?;
            Ok((lab, filled))
        })
        .collect();
    let (mut labelled_pixels, mut filled_pixels) = (0, 0);
    for l in labelled {
        let (a, b) = l?;
        labelled_pixels += a;
        filled_pixels += b;
    }
    tally.labelled_pixels = labelled_pixels;
    tally.filled_pixels = filled_pixels;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache::Contributions;
    use crate::cache::ViewContrib;

    /// 1×4 view; Gaussian 0 is a member of group 0 (the road), Gaussian 1 of group 1 (a person).
    fn view() -> ViewContrib {
        ViewContrib {
            width: 4,
            height: 1,
            k: 0,
            gaussians: 2,
            lists: Contributions {
                offsets: vec![0, 2, 4, 6, 8],
                ids: vec![1, 0, 1, 0, 1, 0, 1, 0],
                weights: vec![0.8, 0.1, 0.8, 0.1, 0.6, 0.1, 0.4, 0.5],
                residual: vec![0.0; 4],
            },
            alpha: vec![0.9, 0.9, 0.7, 0.9],
            depth: vec![1.0; 4],
            median: Vec::new(),
        }
    }

    #[test]
    fn fill_over_masks_relabels_only_pixels_of_a_group_absent_from_the_view() {
        let members = [0, 1];
        // Pixels 0, 1, 3 lie in a kept mask of group 0; pixel 2 in none.
        let kept = [0, 0, -1, 0];
        // Without `over`: only the unlabelled pixel 2 is filled (0.6 of group 1 ≥ 0.5).
        let mut map = kept.to_vec();
        assert_eq!(fill(&mut map, &view(), &members, 0.5, None), 1);
        assert_eq!(map, vec![0, 0, -3, 0]);
        // Group 1 has no kept mask in the view: pixels 0 and 1 (0.8 of group 1) take it too;
        // pixel 3 (0.4 < 0.5) keeps its mask's group.
        let present: std::collections::HashSet<i32> = [0].into_iter().collect();
        let mut map = kept.to_vec();
        assert_eq!(fill(&mut map, &view(), &members, 0.5, Some(&present)), 3);
        assert_eq!(map, vec![-3, -3, -3, 0]);
        // Group 1 has a kept mask in the view: its mask already says where it is.
        let present: std::collections::HashSet<i32> = [0, 1].into_iter().collect();
        let mut map = kept.to_vec();
        assert_eq!(fill(&mut map, &view(), &members, 0.5, Some(&present)), 1);
        assert_eq!(map, vec![0, 0, -3, 0]);
    }
}
