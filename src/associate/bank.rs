//! The memory bank (Gaga's 3D-aware grouping, with the paper's rule) and what makes it
//! order-robust: a consolidation pass over the finished bank.
//!
//! **Pass 1 (the paper).** Masks are offered one at a time. A mask `s` with candidate Gaussians
//! `C(s)` (weights `w_g`) is compared with every group `G_k` by
//! `R_geo(s, G_k) = Σ_{g ∈ C(s) ∩ G_k} w_g / Σ_{g ∈ C(s)} w_g` (the paper's `|C ∩ G| / |C|`
//! with weights; all weights are 1 for projected centres). With `k*` the best group, the mask
//! joins `k*` when `R_geo > τ_geo` and — when both have features — the cosine between the mask's
//! feature and the group's running-mean feature exceeds `τ_sim`; otherwise it starts a new
//! group. Groups own Gaussians exclusively: a group absorbs only candidates no group owns yet.
//!
//! **Pass 2 (consolidation).** With ownership final, every mask is compared again with every
//! group. It moves to the best group it now matches (the same rule, against the pass-1 group
//! means), and two groups it matches both (`R_geo > τ_geo` on each, features compatible with the
//! mask and with each other) are merged when at least [`BankOptions::merge_support`] masks from
//! distinct views say so. This repairs what the visiting order breaks: an object first seen in
//! two disjoint halves (two groups) that a later view shows whole, or a duplicate group opened
//! because a mask's feature disagreed with a young group's one-mask mean.
//!
//! Groups are then numbered canonically, by their first mask in (view name, mask index) order,
//! so ids do not depend on the visiting order either.
use std::collections::{BTreeMap, BTreeSet, HashMap};

use super::candidates::Candidate;

/// Thresholds of the bank.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BankOptions {
    pub tau_geo: f64,
    pub tau_sim: f64,
    /// Run pass 2.
    pub consolidate: bool,
    /// Masks (from distinct views) needed to merge two groups in pass 2.
    pub merge_support: usize,
}

/// One mask as the bank sees it.
#[derive(Debug, Clone)]
pub struct Observation {
    /// Canonical view index (views sorted by name).
    pub view: u32,
    /// Index of the mask in the view's kept-mask file.
    pub mask: u32,
    /// Unit feature (when the mask has one).
    pub feature: Option<Vec<f32>>,
    /// Prompt class of the mask (−1 unknown).
    pub class: i32,
    /// Visible pixels.
    pub pixels: u64,
    pub candidate: Candidate,
    /// `Σ w_g·μ_g` and `Σ w_g` over the candidate (f64).
    pub centroid_sum: [f64; 3],
    pub weight_sum: f64,
}

#[derive(Debug, Clone, Default)]
struct Group {
    feature_sum: Vec<f64>,
    features: u32,
}

impl Group {
    fn add_feature(&mut self, f: &[f32]) {
        if self.feature_sum.is_empty() {
            self.feature_sum = vec![0.0; f.len()];
        }
        for (s, &x) in self.feature_sum.iter_mut().zip(f) {
            *s += f64::from(x);
        }
        self.features += 1;
    }
}

/// Cosine between a unit feature and an (unnormalised) sum; `None` where either is missing.
fn cosine(f: &[f32], sum: &[f64]) -> Option<f64> {
    if sum.is_empty() || f.len() != sum.len() {
        return None;
    }
    let (mut dot, mut nn) = (0.0, 0.0);
    for (&a, &b) in f.iter().zip(sum) {
        dot += f64::from(a) * b;
        nn += b * b;
    }
    (nn > 0.0).then(|| dot / nn.sqrt())
}

fn cosine_sums(a: &[f64], b: &[f64]) -> Option<f64> {
    if a.is_empty() || a.len() != b.len() {
        return None;
    }
    let (mut dot, mut na, mut nb) = (0.0, 0.0, 0.0);
    for (&x, &y) in a.iter().zip(b) {
        dot += x * y;
        na += x * x;
        nb += y * y;
    }
    (na > 0.0 && nb > 0.0).then(|| dot / (na.sqrt() * nb.sqrt()))
}

/// The bank during and after pass 1.
pub struct Bank {
    opts: BankOptions,
    /// Owning group per Gaussian, −1 none.
    owner: Vec<i32>,
    groups: Vec<Group>,
    obs: Vec<Observation>,
    /// Pass-1 group per observation.
    assigned: Vec<u32>,
}

/// A group after the bank is finished (before the view-count and far-field filters).
#[derive(Debug, Clone, PartialEq)]
pub struct FinalGroup {
    /// Observations (indices into [`Finished::observations`]), in canonical order.
    pub members: Vec<usize>,
    /// Distinct canonical view indices.
    pub views: Vec<u32>,
    /// Gaussians owned.
    pub gaussians: usize,
    /// Mean of the members' features (unnormalised sum / count), empty without features.
    pub feature_mean: Vec<f64>,
    /// Pixel-weighted vote over the members' classes (−1 when none has one).
    pub class: i32,
    pub centroid: [f64; 3],
    pub pixels: u64,
}

/// Counts of the consolidation pass.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Consolidation {
    /// Groups after pass 1.
    pub pass1_groups: usize,
    /// Masks moved to another group.
    pub reassigned: usize,
    /// Group pairs merged.
    pub merges: usize,
    /// Groups after pass 2.
    pub groups: usize,
}

/// The finished bank.
pub struct Finished {
    pub observations: Vec<Observation>,
    /// Final group per observation (index into `groups`).
    pub group_of: Vec<usize>,
    /// Groups in canonical order.
    pub groups: Vec<FinalGroup>,
    pub consolidation: Consolidation,
}

impl Bank {
    /// An empty bank over `gaussians` Gaussians.
    pub fn new(gaussians: usize, opts: BankOptions) -> Bank {
        Bank {
            opts,
            owner: vec![-1; gaussians],
            groups: Vec::new(),
            obs: Vec::new(),
            assigned: Vec::new(),
        }
    }

    /// Weighted share of `c`'s mass per owning group (groups ascending) and the total mass.
    fn shares(&self, c: &Candidate) -> (Vec<(u32, f64)>, f64) {
        let mut per: HashMap<u32, f64> = HashMap::new();
        let mut total = 0.0;
        for (&g, &w) in c.ids.iter().zip(&c.weights) {
            let w = f64::from(w);
            total += w;
            let o = self.owner[g as usize];
            if o >= 0 {
                *per.entry(o as u32).or_insert(0.0) += w;
            }
        }
        let mut v: Vec<(u32, f64)> = per.into_iter().collect();
        v.sort_unstable_by_key(|x| x.0);
        (v, total)
    }

    /// Whether a mask's feature is compatible with a group (true where either lacks one).
    fn similar(&self, f: Option<&[f32]>, k: u32) -> bool {
        match f.and_then(|f| cosine(f, &self.groups[k as usize].feature_sum)) {
            Some(c) => c > self.opts.tau_sim,
            None => true,
        }
    }

    /// Offers one mask (pass 1); returns its group.
    pub fn offer(&mut self, o: Observation) -> u32 {
        let (shares, total) = self.shares(&o.candidate);
        let best = shares
            .iter()
            .copied()
            .fold(None::<(u32, f64)>, |b, x| match b {
                Some(b) if b.1 >= x.1 => Some(b),
                _ => Some(x),
            });
        let k = match best {
            Some((k, w))
                if total > 0.0
                    && w / total > self.opts.tau_geo
                    && self.similar(o.feature.as_deref(), k) =>
            {
                k
            }
            _ => {
                self.groups.push(Group::default());
                (self.groups.len() - 1) as u32
            }
        };
        for &g in &o.candidate.ids {
            let ow = &mut self.owner[g as usize];
            if *ow < 0 {
                *ow = k as i32;
            }
        }
        if let Some(f) = &o.feature {
            self.groups[k as usize].add_feature(f);
        }
        self.obs.push(o);
        self.assigned.push(k);
        k
    }

    /// Groups so far.
    pub fn groups(&self) -> usize {
        self.groups.len()
    }

    /// Pass 2 (when enabled) and the final, canonically numbered groups.
    pub fn finish(self) -> Finished {
        let n = self.groups.len();
        let mut cons = Consolidation {
            pass1_groups: n,
            ..Default::default()
        };
        let mut target: Vec<u32> = self.assigned.clone();
        let mut parent: Vec<u32> = (0..n as u32).collect();
        fn find(p: &mut [u32], mut x: u32) -> u32 {
            while p[x as usize] != x {
                p[x as usize] = p[p[x as usize] as usize];
                x = p[x as usize];
            }
            x
        }
        if self.opts.consolidate {
            // Support per group pair: the distinct views of the masks that match both.
            let mut support: BTreeMap<(u32, u32), BTreeSet<u32>> = BTreeMap::new();
            for (i, o) in self.obs.iter().enumerate() {
                let (shares, total) = self.shares(&o.candidate);
                if total <= 0.0 {
                    continue;
                }
                let eligible: Vec<(u32, f64)> = shares
                    .into_iter()
                    .filter(|&(k, w)| {
                        w / total > self.opts.tau_geo && self.similar(o.feature.as_deref(), k)
                    })
                    .collect();
                if let Some(&(k, _)) = eligible
                    .iter()
                    .fold(None::<&(u32, f64)>, |b, x| match b {
                        Some(b) if b.1 >= x.1 => Some(b),
                        _ => Some(x),
                    })
                    && k != target[i]
                {
                    target[i] = k;
                    cons.reassigned += 1;
                }
                for (a, &(ka, _)) in eligible.iter().enumerate() {
                    for &(kb, _) in &eligible[a + 1..] {
                        support.entry((ka, kb)).or_default().insert(o.view);
                    }
                }
            }
            for ((a, b), views) in &support {
                if views.len() < self.opts.merge_support.max(1) {
                    continue;
                }
                let fa = &self.groups[*a as usize].feature_sum;
                let fb = &self.groups[*b as usize].feature_sum;
                if cosine_sums(fa, fb).is_some_and(|c| c <= self.opts.tau_sim) {
                    continue;
                }
                let (ra, rb) = (find(&mut parent, *a), find(&mut parent, *b));
                if ra != rb {
                    let (lo, hi) = (ra.min(rb), ra.max(rb));
                    parent[hi as usize] = lo;
                    cons.merges += 1;
                }
            }
        }
        // Final group of every observation: the root of its target.
        let root: Vec<u32> = (0..n as u32).map(|k| find(&mut parent, k)).collect();
        let obs_root: Vec<u32> = target.iter().map(|&k| root[k as usize]).collect();
        // Canonical order: by the first member in (view, mask) order.
        let mut first: BTreeMap<u32, (u32, u32)> = BTreeMap::new();
        for (o, &r) in self.obs.iter().zip(&obs_root) {
            let key = (o.view, o.mask);
            first
                .entry(r)
                .and_modify(|f| *f = (*f).min(key))
                .or_insert(key);
        }
        let mut roots: Vec<(u32, (u32, u32))> = first.into_iter().collect();
        roots.sort_by_key(|x| x.1);
        let index: HashMap<u32, usize> = roots
            .iter()
            .enumerate()
            .map(|(i, &(r, _))| (r, i))
            .collect();
        let mut groups: Vec<FinalGroup> = roots
            .iter()
            .map(|_| FinalGroup {
                members: Vec::new(),
                views: Vec::new(),
                gaussians: 0,
                feature_mean: Vec::new(),
                class: -1,
                centroid: [0.0; 3],
                pixels: 0,
            })
            .collect();
        let mut order: Vec<usize> = (0..self.obs.len()).collect();
        order.sort_by_key(|&i| (self.obs[i].view, self.obs[i].mask));
        let mut group_of = vec![0usize; self.obs.len()];
        for &i in &order {
            let gi = index[&obs_root[i]];
            group_of[i] = gi;
            groups[gi].members.push(i);
        }
        for &o in &self.owner {
            if o >= 0
                && let Some(&gi) = index.get(&root[o as usize])
            {
                groups[gi].gaussians += 1;
            }
        }
        for g in &mut groups {
            let mut views = BTreeSet::new();
            let mut votes: BTreeMap<i32, u64> = BTreeMap::new();
            let (mut cs, mut ws) = ([0.0f64; 3], 0.0f64);
            let mut fsum: Vec<f64> = Vec::new();
            let mut nf = 0u32;
            for &i in &g.members {
                let o = &self.obs[i];
                views.insert(o.view);
                g.pixels += o.pixels;
                if o.class >= 0 {
                    *votes.entry(o.class).or_insert(0) += o.pixels;
                }
                for (c, s) in cs.iter_mut().zip(o.centroid_sum) {
                    *c += s;
                }
                ws += o.weight_sum;
                if let Some(f) = &o.feature {
                    if fsum.is_empty() {
                        fsum = vec![0.0; f.len()];
                    }
                    for (s, &x) in fsum.iter_mut().zip(f) {
                        *s += f64::from(x);
                    }
                    nf += 1;
                }
            }
            g.views = views.into_iter().collect();
            // Most pixels wins; ties: the smaller class id (BTreeMap order, strict >).
            g.class = votes
                .iter()
                .fold((-1, 0u64), |b, (&c, &v)| if v > b.1 { (c, v) } else { b })
                .0;
            g.centroid = if ws > 0.0 {
                cs.map(|c| c / ws)
            } else {
                [f64::NAN; 3]
            };
            if nf > 0 {
                g.feature_mean = fsum.into_iter().map(|s| s / f64::from(nf)).collect();
            }
        }
        cons.groups = groups.len();
        Finished {
            observations: self.obs,
            group_of,
            groups,
            consolidation: cons,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn obs(view: u32, mask: u32, ids: &[u32], feature: Option<Vec<f32>>) -> Observation {
        Observation {
            view,
            mask,
            feature,
            class: 8,
            pixels: ids.len() as u64,
            candidate: Candidate {
                ids: ids.to_vec(),
                weights: vec![1.0; ids.len()],
            },
            centroid_sum: [ids.len() as f64, 0.0, 0.0],
            weight_sum: ids.len() as f64,
        }
    }

    fn opts(consolidate: bool) -> BankOptions {
        BankOptions {
            tau_geo: 0.2,
            tau_sim: 0.7,
            consolidate,
            merge_support: 2,
        }
    }

    /// Partition of observations (by (view, mask)) into final groups.
    fn partition(f: &Finished) -> Vec<Vec<(u32, u32)>> {
        let mut p: Vec<Vec<(u32, u32)>> = f
            .groups
            .iter()
            .map(|g| {
                let mut v: Vec<(u32, u32)> = g
                    .members
                    .iter()
                    .map(|&i| (f.observations[i].view, f.observations[i].mask))
                    .collect();
                v.sort_unstable();
                v
            })
            .collect();
        p.sort();
        p
    }

    #[test]
    fn overlap_joins_and_exclusive_ownership() {
        let mut b = Bank::new(20, opts(false));
        assert_eq!(b.offer(obs(0, 0, &[0, 1, 2, 3], None)), 0);
        // 2 of 5 = 0.4 > 0.2: joins, absorbs 4 only (0–3 stay).
        assert_eq!(b.offer(obs(1, 0, &[2, 3, 4, 7, 8], None)), 0);
        // 1 of 6 ≈ 0.17 ≤ 0.2: new group, owns only the unowned ones (10–14, not 4).
        assert_eq!(b.offer(obs(2, 0, &[4, 10, 11, 12, 13, 14], None)), 1);
        let f = b.finish();
        assert_eq!(f.groups[0].gaussians, 7); // 0, 1, 2, 3, 4, 7, 8
        assert_eq!(f.groups[1].gaussians, 5);
        assert_eq!(f.groups[0].views, vec![0, 1]);
        assert_eq!(f.group_of, vec![0, 0, 1]);
    }

    #[test]
    fn dissimilar_features_open_a_new_group() {
        let mut b = Bank::new(6, opts(false));
        let car = Some(vec![1.0, 0.0]);
        let tree = Some(vec![0.0, 1.0]);
        assert_eq!(b.offer(obs(0, 0, &[0, 1, 2], car.clone())), 0);
        assert_eq!(b.offer(obs(1, 0, &[0, 1, 2], tree)), 1);
        assert_eq!(b.offer(obs(2, 0, &[0, 1, 2], car)), 0);
    }

    #[test]
    fn halves_seen_first_are_merged_by_consolidation_in_any_order() {
        // An object of Gaussians 0..8 seen as two disjoint halves (views 0, 1), then whole
        // (views 2, 3). Pass 1 in this order leaves two groups; visiting the whole views first
        // gives one. Consolidation gives one either way.
        let left = [0u32, 1, 2, 3];
        let right = [4u32, 5, 6, 7];
        let whole: Vec<u32> = (0..8).collect();
        let seq = |order: &[u32], consolidate: bool| {
            let mut b = Bank::new(8, opts(consolidate));
            for &v in order {
                let ids: &[u32] = match v {
                    0 => &left,
                    1 => &right,
                    _ => &whole,
                };
                b.offer(obs(v, 0, ids, None));
            }
            b.finish()
        };
        assert_eq!(seq(&[0, 1, 2, 3], false).groups.len(), 2);
        assert_eq!(seq(&[2, 3, 0, 1], false).groups.len(), 1);
        let a = seq(&[0, 1, 2, 3], true);
        let b = seq(&[3, 1, 2, 0], true);
        assert_eq!(a.groups.len(), 1);
        assert_eq!(partition(&a), partition(&b));
        assert_eq!(a.consolidation.merges, 1);
        // One straddling view is not enough support.
        let c = seq(&[0, 1, 2], true);
        assert_eq!(c.groups.len(), 2);
    }
}
