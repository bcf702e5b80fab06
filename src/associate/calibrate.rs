//! The feature threshold `τ_sim` from the scene's own statistics: before the memory
//! bank runs, pairs of kept masks in different views are split by geometry alone — **linked**
//! when each puts at least half of its candidates' α·T mass on the other's candidates (the same
//! object seen twice), **unlinked** when they share no candidate Gaussian — and the cosine of
//! their features is compared between the two sets.
//!
//! * Features of one object **agree across views** when the [`LINKED_QUANTILE`] quantile of the
//!   linked cosines reaches the configured `τ_sim`: the configured value stays (90 % of the pairs
//!   geometry links pass the feature test; on `street` the quantile is 0.715 for τ_sim 0.7).
//! * Otherwise, when features still **separate** linked from unlinked pairs — the probability
//!   that a linked pair is more similar than an unlinked one (the AUC, Mann–Whitney) is at least
//!   [`MIN_AUC`] — `τ_sim` drops to that quantile.
//! * Otherwise the features carry no information the association can use: `τ_sim` = −1, a
//!   **geometry-only** association (the paper's `R_geo > τ_geo` alone), and a warning says so.
//! * With too few pairs of either kind, or no features, the configured value stays.
//!
//! Unlinked pairs share no Gaussian; they include parts of one large object seen in different
//! places (a road), which is why agreement is judged on the linked pairs first and the AUC only
//! decides between a lower threshold and none.
//!
//! Sampling keeps the cost bounded and deterministic: Gaussians enter the pair count through a
//! SplitMix64 hash sample sized to at most [`PAIR_BUDGET`] mask pairs, and unlinked pairs are a
//! strided sample of at most [`UNLINKED_MAX`]; nothing depends on the thread count.
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::bank::Observation;
use crate::hash::splitmix64;

/// Features separate when the AUC of linked against unlinked cosines reaches this.
pub const MIN_AUC: f64 = 0.75;
/// `τ_sim` is this quantile of the linked pairs' cosines.
pub const LINKED_QUANTILE: f64 = 0.10;
/// Each mask of a linked pair puts at least this share of its candidate mass on the other's.
pub const LINK_SHARE: f64 = 0.5;
/// At least this many pairs of each kind are needed to calibrate.
pub const MIN_PAIRS: usize = 20;
/// At most this many (mask, mask) entries are accumulated for the overlaps.
pub const PAIR_BUDGET: u64 = 20_000_000;
/// At most this many unlinked pairs are compared.
pub const UNLINKED_MAX: usize = 200_000;

/// Which rule chose `τ_sim`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CalibrationMode {
    /// From the features: the configured value where they agree, else the linked quantile.
    Features,
    /// Features do not separate: the feature test is off.
    GeometryOnly,
    /// Not enough evidence, no features, or calibration switched off: the configured value.
    Configured,
}

impl std::fmt::Display for CalibrationMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            CalibrationMode::Features => "features",
            CalibrationMode::GeometryOnly => "geometry_only",
            CalibrationMode::Configured => "configured",
        })
    }
}

/// How `τ_sim` was chosen (the associate summary's `calibration`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    pub mode: CalibrationMode,
    /// The value the association used.
    pub tau_sim: f64,
    /// The configured value (the cap).
    pub configured: f64,
    /// Linked and unlinked pairs with features on both sides.
    pub linked_pairs: usize,
    pub unlinked_pairs: usize,
    /// Quantiles 10/25/50/75/90 % of the cosines.
    pub linked_cosine: Option<[f32; 5]>,
    pub unlinked_cosine: Option<[f32; 5]>,
    /// P(cos linked > cos unlinked) (ties count half).
    pub auc: Option<f64>,
    /// One Gaussian in `sample` entered the overlaps (1 = all).
    pub sample: u64,
    pub why: String,
}

/// The calibration off: the configured value and why.
pub fn configured(tau_sim: f64, why: &str) -> Calibration {
    Calibration {
        mode: CalibrationMode::Configured,
        tau_sim,
        configured: tau_sim,
        linked_pairs: 0,
        unlinked_pairs: 0,
        linked_cosine: None,
        unlinked_cosine: None,
        auc: None,
        sample: 1,
        why: why.into(),
    }
}

/// Pairs of masks: indices into the observations, `a < b`, of different views.
pub type Pairs = Vec<(u32, u32)>;

/// Linked and unlinked pairs of `obs`, and the Gaussian sampling modulus used.
///
/// The overlaps are summed per mask `a` (in parallel, masks independent): over `a`'s sampled
/// Gaussians in ascending order, the shares of every later mask `b` of another view that lists
/// the same Gaussian, into a dense row. Every pair's sums and every mask's mass are added in
/// ascending Gaussian order, so the result does not depend on the thread count.
pub fn pairs(obs: &[Observation]) -> (Pairs, Pairs, u64) {
    // (Gaussian ≪ 32 | mask, share of the mask's candidate mass), sorted by Gaussian and then
    // mask (a stable sort: a Gaussian a candidate lists twice keeps its order).
    let mut entries: Vec<(u64, f32)> = Vec::new();
    for (i, o) in obs.iter().enumerate() {
        let total = o.candidate.mass();
        if total <= 0.0 {
            continue;
        }
        for (&g, &w) in o.candidate.ids.iter().zip(&o.candidate.weights) {
            entries.push((
                (u64::from(g) << 32) | i as u64,
                (f64::from(w) / total) as f32,
            ));
        }
    }
    entries.par_sort_by_key(|e| e.0);
    let gaussian = |e: usize| (entries[e].0 >> 32) as u32;
    let mask = |e: usize| (entries[e].0 & 0xffff_ffff) as usize;
    // Each entry's run end (the entries of its Gaussian), and the pair count before sampling.
    let mut run_end = vec![0usize; entries.len()];
    let mut count: u64 = 0;
    let mut r0 = 0;
    while r0 < entries.len() {
        let mut r1 = r0 + 1;
        while r1 < entries.len() && gaussian(r1) == gaussian(r0) {
            r1 += 1;
        }
        run_end[r0..r1].fill(r1);
        let l = (r1 - r0) as u64;
        count += l * l.saturating_sub(1) / 2;
        r0 = r1;
    }
    let sample = count.div_ceil(PAIR_BUDGET).max(1);
    let kept = |g: u32| sample == 1 || splitmix64(u64::from(g)) % sample == 0;
    // Per mask, its sampled entries in ascending Gaussian order.
    let mut of_mask: Vec<Vec<usize>> = vec![Vec::new(); obs.len()];
    for e in 0..entries.len() {
        if kept(gaussian(e)) {
            of_mask[mask(e)].push(e);
        }
    }
    // Per mask a: its sampled mass, and (b, shared mass of a, of b) for every later mask b
    // of another view, b ascending.
    type Row = (f64, Vec<(u32, f64, f64)>);
    let rows: Vec<Row> = (0..obs.len())
        .into_par_iter()
        .map_init(
            || (vec![(0.0f64, 0.0f64); obs.len()], vec![false; obs.len()]),
            |(sums, touched), a| {
                let mut mass = 0.0f64;
                let mut bs: Vec<u32> = Vec::new();
                for &e in &of_mask[a] {
                    let sa = f64::from(entries[e].1);
                    mass += sa;
                    for &(key, sb) in &entries[e + 1..run_end[e]] {
                        let b = (key & 0xffff_ffff) as usize;
                        if obs[a].view == obs[b].view {
                            continue;
                        }
                        if !touched[b] {
                            touched[b] = true;
                            bs.push(b as u32);
                        }
                        sums[b].0 += sa;
                        sums[b].1 += f64::from(sb);
                    }
                }
                bs.sort_unstable();
                let row = bs
                    .iter()
                    .map(|&b| {
                        let b = b as usize;
                        touched[b] = false;
                        let (x, y) = std::mem::take(&mut sums[b]);
                        (b as u32, x, y)
                    })
                    .collect();
                (mass, row)
            },
        )
        .collect();
    let mass: Vec<f64> = rows.iter().map(|r| r.0).collect();
    let mut linked: Vec<(u32, u32)> = Vec::new();
    for (a, (_, row)) in rows.iter().enumerate() {
        for &(b, sa, sb) in row {
            if mass[a] > 0.0
                && mass[b as usize] > 0.0
                && sa / mass[a] >= LINK_SHARE
                && sb / mass[b as usize] >= LINK_SHARE
            {
                linked.push((a as u32, b));
            }
        }
    }
    // Unlinked: a strided sample of the pairs of different views that share nothing.
    let n = obs.len() as u64;
    let all = n * n.saturating_sub(1) / 2;
    let stride = all.div_ceil(UNLINKED_MAX as u64).max(1);
    let mut unlinked = Vec::new();
    let mut k = 0u64;
    for a in 0..obs.len() {
        for b in a + 1..obs.len() {
            k += 1;
            if k % stride != 0 || obs[a].view == obs[b].view {
                continue;
            }
            // Pairs that share a Gaussian outside the sample are rare and count as unlinked.
            if rows[a]
                .1
                .binary_search_by_key(&(b as u32), |r| r.0)
                .is_err()
            {
                unlinked.push((a as u32, b as u32));
            }
        }
    }
    (linked, unlinked, sample)
}

fn cosine(a: &[f32], b: &[f32]) -> f32 {
    // Unit features: the dot product, summed in f64.
    a.iter()
        .zip(b)
        .map(|(&x, &y)| f64::from(x) * f64::from(y))
        .sum::<f64>() as f32
}

/// Quantiles 10/25/50/75/90 % of sorted values (nearest rank).
fn quantiles(sorted: &[f32]) -> [f32; 5] {
    [0.10, 0.25, 0.50, 0.75, 0.90].map(|q| quantile(sorted, q))
}

fn quantile(sorted: &[f32], q: f64) -> f32 {
    let i = ((q * (sorted.len() - 1) as f64).round() as usize).min(sorted.len() - 1);
    sorted[i]
}

/// P(x > y) for x from `pos`, y from `neg`, ties half (Mann–Whitney U / |pos|·|neg|).
pub fn auc(pos: &[f32], neg: &[f32]) -> f64 {
    let mut all: Vec<(f32, bool)> = pos
        .iter()
        .map(|&x| (x, true))
        .chain(neg.iter().map(|&y| (y, false)))
        .collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    // Mid-ranks over ties.
    let mut rank_sum = 0.0f64;
    let mut i = 0;
    while i < all.len() {
        let mut j = i;
        while j < all.len() && all[j].0 == all[i].0 {
            j += 1;
        }
        let mid = (i + j + 1) as f64 / 2.0; // ranks i+1..=j
        rank_sum += mid * all[i..j].iter().filter(|e| e.1).count() as f64;
        i = j;
    }
    let (p, n) = (pos.len() as f64, neg.len() as f64);
    (rank_sum - p * (p + 1.0) / 2.0) / (p * n)
}

/// Chooses `τ_sim` for the observations (see the module docs).
pub fn calibrate(obs: &[Observation], configured_tau: f64) -> Calibration {
    if obs.iter().all(|o| o.feature.is_none()) {
        return configured(configured_tau, "no mask has a feature");
    }
    let (linked, unlinked, sample) = pairs(obs);
    let cos = |ps: &[(u32, u32)]| -> Vec<f32> {
        let mut v: Vec<f32> = ps
            .iter()
            .filter_map(
                |&(a, b)| match (&obs[a as usize].feature, &obs[b as usize].feature) {
                    (Some(x), Some(y)) => Some(cosine(x, y)),
                    _ => None,
                },
            )
            .collect();
        v.sort_by(|a, b| a.total_cmp(b));
        v
    };
    let (pos, neg) = (cos(&linked), cos(&unlinked));
    let mut c = configured(configured_tau, "");
    c.linked_pairs = pos.len();
    c.unlinked_pairs = neg.len();
    c.sample = sample;
    if pos.len() < MIN_PAIRS || neg.len() < MIN_PAIRS {
        c.why = format!(
            "too few mask pairs to calibrate ({} linked by geometry, {} unlinked; {MIN_PAIRS} of each needed): the configured τ_sim",
            pos.len(),
            neg.len()
        );
        return c;
    }
    c.linked_cosine = Some(quantiles(&pos));
    c.unlinked_cosine = Some(quantiles(&neg));
    let a = auc(&pos, &neg);
    c.auc = Some(a);
    let q = quantile(&pos, LINKED_QUANTILE);
    if f64::from(q) >= configured_tau {
        c.mode = CalibrationMode::Features;
        c.why = format!(
            "features of one object agree across views: {:.0} % of the mask pairs geometry links have cosine ≥ {q:.3} ≥ the configured τ_sim {configured_tau} (AUC {a:.2})",
            (1.0 - LINKED_QUANTILE) * 100.0
        );
    } else if a < MIN_AUC {
        c.mode = CalibrationMode::GeometryOnly;
        c.tau_sim = -1.0;
        c.why = format!(
            "features do not separate masks that geometry links from masks it does not (AUC {a:.2} < {MIN_AUC}; median cosine {:.2} linked, {:.2} unlinked): geometry-only association (τ_sim off)",
            quantile(&pos, 0.5),
            quantile(&neg, 0.5)
        );
    } else {
        c.mode = CalibrationMode::Features;
        c.tau_sim = f64::from(q);
        c.why = format!(
            "features of one object disagree across views ({:.0} % quantile of the linked cosines {q:.3} < the configured τ_sim {configured_tau}) but still separate linked from unlinked mask pairs (AUC {a:.2}): τ_sim = {q:.3}",
            LINKED_QUANTILE * 100.0
        );
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::associate::candidates::Candidate;

    fn obs(view: u32, ids: &[u32], feature: Option<Vec<f32>>) -> Observation {
        Observation {
            view,
            mask: 0,
            feature,
            class: -1,
            pixels: 1,
            candidate: Candidate {
                ids: ids.to_vec(),
                weights: vec![1.0; ids.len()],
            },
            centroid_sum: [0.0; 3],
            weight_sum: ids.len() as f64,
        }
    }

    /// The pairs of random masks by the definition, pair by pair: each mask's share of every
    /// Gaussian, the shared mass summed over the common Gaussians in ascending order, linked
    /// when both sides reach [`LINK_SHARE`]; unlinked by the same stride over the pairs of
    /// different views that share none (no sampling at this size).
    #[test]
    fn pairs_are_the_pair_by_pair_definition_at_any_thread_count() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let o: Vec<Observation> = (0..90)
            .map(|i| {
                // 10 objects of 40 Gaussians seen in 9 views; each mask most of one object
                // and a few Gaussians of a neighbour (some pairs just above or below the link
                // share).
                let obj = (i % 10) as u32;
                let mut ids: Vec<u32> = (0..40)
                    .filter(|_| rng.random_bool(0.8))
                    .map(|g| obj * 40 + g)
                    .collect();
                ids.extend((0..(rng.random_range(0..30))).map(|g| ((obj + 1) % 10) * 40 + g));
                ids.sort_unstable();
                ids.dedup();
                ids.reverse();
                let mut m = obs((i / 10) as u32, &ids, None);
                m.candidate.weights = ids.iter().map(|_| rng.random_range(0.01f32..1.0)).collect();
                if i == 7 {
                    m.candidate.weights.iter_mut().for_each(|w| *w = 0.0);
                }
                m
            })
            .collect();
        // Per mask: Gaussian → share, and the mass in ascending Gaussian order.
        let share: Vec<std::collections::BTreeMap<u32, f32>> = o
            .iter()
            .map(|m| {
                let total = m.candidate.mass();
                if total <= 0.0 {
                    return Default::default();
                }
                let w = m.candidate.ids.iter().zip(&m.candidate.weights);
                w.map(|(&g, &w)| (g, (f64::from(w) / total) as f32))
                    .collect()
            })
            .collect();
        let mass: Vec<f64> = share
            .iter()
            .map(|s| s.values().map(|&x| f64::from(x)).sum())
            .collect();
        let (mut want_linked, mut shares_any) = (Vec::new(), Vec::new());
        for a in 0..o.len() {
            for b in a + 1..o.len() {
                if o[a].view == o[b].view {
                    continue;
                }
                let common: Vec<u32> = share[a]
                    .keys()
                    .filter(|g| share[b].contains_key(g))
                    .copied()
                    .collect();
                if common.is_empty() {
                    continue;
                }
                shares_any.push((a as u32, b as u32));
                let sa: f64 = common.iter().map(|g| f64::from(share[a][g])).sum();
                let sb: f64 = common.iter().map(|g| f64::from(share[b][g])).sum();
                if mass[a] > 0.0
                    && mass[b] > 0.0
                    && sa / mass[a] >= LINK_SHARE
                    && sb / mass[b] >= LINK_SHARE
                {
                    want_linked.push((a as u32, b as u32));
                }
            }
        }
        let n = o.len() as u64;
        let stride = (n * (n - 1) / 2).div_ceil(UNLINKED_MAX as u64).max(1);
        let mut want_unlinked = Vec::new();
        let mut k = 0u64;
        for a in 0..o.len() as u32 {
            for b in a + 1..o.len() as u32 {
                k += 1;
                let (va, vb) = (o[a as usize].view, o[b as usize].view);
                if k % stride == 0 && va != vb && shares_any.binary_search(&(a, b)).is_err() {
                    want_unlinked.push((a, b));
                }
            }
        }
        assert!(want_linked.len() > 100 && want_unlinked.len() > 100);
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let (linked, unlinked, sample) = pool.install(|| pairs(&o));
            assert_eq!(sample, 1);
            assert_eq!(linked, want_linked, "{threads} threads");
            assert_eq!(unlinked, want_unlinked, "{threads} threads");
        }
    }

    #[test]
    fn auc_of_separated_mixed_and_tied_sets() {
        assert_eq!(auc(&[0.9, 0.8], &[0.1, 0.2, 0.3]), 1.0);
        assert_eq!(auc(&[0.1], &[0.9]), 0.0);
        // Ties count half: one tie of 2·2 comparisons.
        assert_eq!(auc(&[0.5, 0.7], &[0.5, 0.1]), (1.0 + 0.5 + 1.0 + 1.0) / 4.0);
    }

    #[test]
    fn pairs_by_geometry() {
        // Object A seen in views 0 and 1 (the same Gaussians), object B in view 2; a second mask
        // of view 1 shares 2 of its 4 Gaussians with A: 0.5 of the mass each way, linked to A's
        // view-0 mask at exactly the link share, and never to A's mask of its own view.
        let o = vec![
            obs(0, &[1, 2, 3, 4], None),
            obs(1, &[1, 2, 3, 4], None),
            obs(2, &[10, 11], None),
            obs(1, &[3, 4, 20, 21], None),
        ];
        let (linked, unlinked, sample) = pairs(&o);
        assert_eq!(sample, 1);
        // (0,1): all shared. (0,3): 2 of 4 each way = 0.5 ≥ LINK_SHARE. (1,3) same view.
        assert_eq!(linked, vec![(0, 1), (0, 3)]);
        // Different views sharing nothing: (0,2), (1,2), (2,3).
        assert_eq!(unlinked, vec![(0, 2), (1, 2), (2, 3)]);
    }

    fn unit(v: &[f32]) -> Vec<f32> {
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.iter().map(|x| x / n).collect()
    }

    #[test]
    fn separating_features_calibrate_and_useless_ones_turn_the_test_off() {
        // 30 objects, each seen in 2 views (linked pairs). Features: the object's own direction
        // (separating), one direction for every mask (uninformative but consistent), or a
        // direction of each mask's own (noise: two views of one object are orthogonal).
        let build = |kind: u8| {
            let mut o = Vec::new();
            for k in 0..30u32 {
                for v in 0..2 {
                    let mut f = vec![0.0f32; 64];
                    match kind {
                        0 => {
                            f[k as usize % 64] = 1.0;
                            f[(k as usize + 1) % 64] = 0.2;
                        }
                        1 => f[0] = 1.0,
                        _ => f[(2 * k + v) as usize] = 1.0,
                    }
                    o.push(obs(2 * k + v, &[100 * k, 100 * k + 1], Some(unit(&f))));
                }
            }
            o
        };
        let c = calibrate(&build(0), 0.7);
        assert_eq!(c.mode, CalibrationMode::Features, "{c:?}");
        assert_eq!(c.linked_pairs, 30);
        assert!(c.auc.unwrap() > 0.95, "{c:?}");
        // Linked cosines are 1 ≥ 0.7: the configured value stays.
        assert_eq!(c.tau_sim, 0.7);
        // One direction for all: every pair agrees, nothing blocks a join: the value stays.
        let c = calibrate(&build(1), 0.7);
        assert_eq!(
            (c.mode, c.tau_sim, c.auc),
            (CalibrationMode::Features, 0.7, Some(0.5))
        );
        // Noise: linked pairs disagree and do not separate (all cosines 0): geometry only.
        let c = calibrate(&build(2), 0.7);
        assert_eq!(c.mode, CalibrationMode::GeometryOnly, "{c:?}");
        assert_eq!(c.auc, Some(0.5));
        assert_eq!(c.tau_sim, -1.0);
        // No features: the configured value.
        let none: Vec<Observation> = (0..4).map(|v| obs(v, &[1], None)).collect();
        assert_eq!(calibrate(&none, 0.7).mode, CalibrationMode::Configured);
    }

    /// Features of a semantic network (`segment --semantic`): each mask's mean class
    /// probabilities over 20 classes, the two views of an object close (±0.03 per class),
    /// objects of 4 classes. Linked pairs agree (cosine ≈ 1), so the configured `τ_sim` stays;
    /// two objects of one class are as alike as two views of one (features cannot tell
    /// instances apart: geometry does).
    #[test]
    fn class_probability_features_keep_the_configured_threshold() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(20);
        let mut o = Vec::new();
        for k in 0..30u32 {
            for v in 0..2 {
                let mut f: Vec<f32> = (0..20).map(|_| rng.random_range(0.0..0.03f32)).collect();
                f[(k % 4) as usize * 3] += 0.8;
                let sum: f32 = f.iter().sum();
                let p: Vec<f32> = f.iter().map(|x| x / sum).collect();
                o.push(obs(2 * k + v, &[100 * k, 100 * k + 1], Some(unit(&p))));
            }
        }
        let c = calibrate(&o, 0.7);
        assert_eq!(
            (c.mode, c.tau_sim),
            (CalibrationMode::Features, 0.7),
            "{c:?}"
        );
        assert!(c.linked_cosine.unwrap()[0] > 0.99, "{c:?}");
        // unlinked pairs of one class (a quarter of them) are as similar as linked ones: the
        // 90 % quantile of the unlinked cosines is as high as the linked pairs'
        assert!(c.unlinked_cosine.unwrap()[4] > 0.99, "{c:?}");
    }
}
