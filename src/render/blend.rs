//! Front-to-back alpha blending of one 16×16 tile, INRIA's `renderCUDA` per pixel:
//! `power = −½(a·dx² + c·dy²) − b·dx·dy` (skip if > 0), `α = min(0.99, o·e^power)` (skip if
//! < 1/255, or a higher `alpha_min` of the contributions cache), stop before adding when
//! `T·(1−α) < 1e-4`. The loop runs Gaussian-outer, pixel-inner, restricted to the box where
//! `α ≥ α_min` is possible; each pixel still sees
//! its Gaussians in the same order, so the result is the per-pixel loop's, up to the last bit
//! of `e^power` ([`exp_neg`], inlined, within 2 ulp of `expf`). [`blend_tile`] runs under the
//! widest instruction set the CPU has (`pulp`'s runtime dispatch: AVX2 + FMA where present).
//! Also accumulates depth (`Σ w·z`), the median depth, feature channels (no background)
//! and the per-pixel contribution lists (all, the top-k by weight, or the largest weights
//! up to a share `1 − ε` of the pixel's mass; plus the residual). An optional early stop
//! (`t_stop`) ends a pixel after the contribution that takes its T below it.
use super::project::{Projected, TILE};

const PIX: usize = TILE * TILE;
/// Gaussians gathered per batch.
const BATCH: usize = 32;
/// Transmittance below which a pixel stops.
pub const T_MIN: f32 = 1e-4;
/// Largest alpha of one Gaussian.
pub const ALPHA_MAX: f32 = 0.99;

/// Which per-pixel contribution lists to keep.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub enum ContributionMode {
    /// None (fastest).
    #[default]
    None,
    /// Every contributing Gaussian.
    All,
    /// The `k` largest weights per pixel (ties: the earlier in depth order), plus the
    /// dropped weight mass in `residual`.
    TopK(usize),
    /// The largest weights per pixel (ties: the earlier in depth order) until the kept mass
    /// reaches `1 − epsilon` of the pixel's total `Σ α·T`, at most `cap` of them (0 = no
    /// cap), plus the dropped mass in `residual` (see [`keep_mass`]).
    Mass { epsilon: f32, cap: usize },
}

/// One contribution: Gaussian index and weight `α·T`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contribution {
    pub id: u32,
    pub weight: f32,
}

/// The blended tile, pixel-major (`k = y·16 + x` in the tile).
pub struct TileOut {
    pub x0: usize,
    pub y0: usize,
    pub w: usize,
    pub h: usize,
    /// Colour planes (R, G, B), `PIX` each.
    pub rgb: [Vec<f32>; 3],
    pub trans: Vec<f32>,
    pub depth_acc: Vec<f32>,
    pub median: Vec<f32>,
    /// `PIX × channels`.
    pub features: Vec<f32>,
    /// Per pixel `k`, `items[offsets[k]..offsets[k + 1]]` in depth order (empty without lists).
    pub offsets: Vec<u32>,
    pub items: Vec<Contribution>,
    pub residual: Vec<f32>,
}

impl TileOut {
    /// Pixel `k`'s list.
    pub fn list(&self, k: usize) -> &[Contribution] {
        if self.offsets.is_empty() {
            return &[];
        }
        &self.items[self.offsets[k] as usize..self.offsets[k + 1] as usize]
    }
}

/// Inputs shared by all tiles of a view.
pub struct BlendInput<'a> {
    pub projected: &'a [Projected],
    pub features: &'a [f32],
    pub channels: usize,
    pub width: usize,
    pub height: usize,
    pub grid_x: usize,
    pub background: [f32; 3],
    /// Accumulate the colour and the median depth ([`super::RenderOptions::images`]).
    pub images: bool,
    pub mode: ContributionMode,
    /// A pixel stops after a contribution that takes its T below this
    /// ([`super::RenderOptions::t_stop`]; 0 = never, INRIA's own stop only).
    pub t_stop: f32,
    /// The smallest α that contributes ([`super::RenderOptions::alpha_min`]).
    pub alpha_min: f32,
}

/// Contributions a pixel keeps in its own slots of [`Scratch::slots`]; the rest of a longer
/// list goes to [`Scratch::spill`].
pub(crate) const SLOTS: usize = 32;

/// Per-thread scratch of [`blend_tile`] (All and Mass lists): each pixel's first [`SLOTS`]
/// contributions in its own slots (blending order), the rest tagged with the pixel in `spill`
/// (blending order) and gathered by pixel in `spilled`, one long list assembled in `long`,
/// and the mass rule's keys.
#[derive(Default)]
struct Scratch {
    slots: Vec<Contribution>,
    spill: Vec<(u16, Contribution)>,
    spilled: Vec<Contribution>,
    long: Vec<Contribution>,
    keys: Vec<u64>,
}

thread_local! {
    static SCRATCH: std::cell::Cell<Scratch> = const {
        std::cell::Cell::new(Scratch {
            slots: Vec::new(),
            spill: Vec::new(),
            spilled: Vec::new(),
            long: Vec::new(),
            keys: Vec::new(),
        })
    };
}

/// Top-k slot: insertion sequence, contribution.
#[derive(Clone, Copy)]
struct Slot {
    seq: u32,
    c: Contribution,
}

use crate::fastmath::exp_neg;

/// The α of 8 pixels of a row, `x = x0..x0 + 8`, at vertical offset `dy` from the mean: INRIA's
/// `power = −½(a·dx² + c·dy²) − b·dx·dy`, `α = min(0.99, o·e^power)`; returns the lanes that
/// pass (bit i: not `power > 0`, `power < power_min` or `α < 1/255`). Branch-free, so the
/// lanes vectorise; each lane computes exactly the scalar expression.
#[inline(always)]
fn row_alpha(
    out: &mut [f32; 8],
    x0: usize,
    [mx, dy]: [f32; 2],
    conic: [f32; 3],
    o: f32,
    pmin: f32,
    amin: f32,
) -> u32 {
    let [ca, cb, cc] = conic;
    // Lane i's bit where it passes, in the same vector loop (an OR of the lanes after it is
    // a vector reduction; bits drawn from the stored α one at a time stayed scalar).
    let mut bits = [0u32; 8];
    for (i, (a, bit)) in out.iter_mut().zip(bits.iter_mut()).enumerate() {
        let dx = mx - (x0 + i) as f32;
        let power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
        let alpha = ALPHA_MAX.min(o * exp_neg(power));
        let skip = power > 0.0 || power < pmin || alpha < amin;
        *a = if skip { 0.0 } else { alpha };
        *bit = if skip { 0 } else { 1 << i };
    }
    bits.iter().fold(0, |x, &y| x | y)
}

/// Blends tile `t` given its depth-sorted list of indices into `input.projected`, with the
/// widest vector instructions the CPU offers (runtime dispatch; same results on every path
/// but for the vector width).
pub fn blend_tile(input: &BlendInput<'_>, t: usize, list: &[u32]) -> TileOut {
    pulp::Arch::new().dispatch(BlendOp { input, t, list })
}

/// [`blend_tile`]'s arguments as a `pulp` operation: `with_simd` is inlined into a function
/// compiled for the detected instruction set, and [`blend_tile_impl`] into it.
struct BlendOp<'a, 'b> {
    input: &'a BlendInput<'b>,
    t: usize,
    list: &'a [u32],
}

impl pulp::WithSimd for BlendOp<'_, '_> {
    type Output = TileOut;
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) -> TileOut {
        blend_tile_impl(self.input, self.t, self.list)
    }
}

#[inline(always)]
fn blend_tile_impl(input: &BlendInput<'_>, t: usize, list: &[u32]) -> TileOut {
    let tx = t % input.grid_x;
    let ty = t / input.grid_x;
    let x0 = tx * TILE;
    let y0 = ty * TILE;
    let w = TILE.min(input.width - x0);
    let h = TILE.min(input.height - y0);
    let ch = input.channels;
    let images = input.images;
    let amin = input.alpha_min;
    let mut trans = vec![1.0f32; PIX];
    let mut rgb = [vec![0.0f32; PIX], vec![0.0f32; PIX], vec![0.0f32; PIX]];
    let mut depth_acc = vec![0.0f32; PIX];
    let mut median = vec![f32::NAN; PIX];
    let mut features = vec![0.0f32; PIX * ch];
    // Per row, bit x set while pixel x is inside the image and not yet saturated.
    let mut live = [0u32; TILE];
    for row in live.iter_mut().take(h) {
        *row = (1u32 << w) - 1;
    }
    let mut alive = w * h;
    let keep_lists = input.mode != ContributionMode::None;
    let topk = match input.mode {
        ContributionMode::TopK(k) => Some(k),
        _ => None,
    };
    // All and Mass: every contribution in its pixel's slots (or the spill), in blending
    // order. The tile's scratch is reused from the previous tile on this thread (taken, and
    // put back at the end): grown once, not reallocated per tile.
    let mut scratch = SCRATCH.take();
    let mut lens = [0u32; PIX];
    if keep_lists && topk.is_none() {
        scratch
            .slots
            .resize(PIX * SLOTS, Contribution { id: 0, weight: 0.0 });
        scratch.spill.clear();
    }
    let mut slots: Vec<Vec<Slot>> = match topk {
        Some(k) => (0..PIX).map(|_| Vec::with_capacity(k.min(64))).collect(),
        None => Vec::new(),
    };
    let mut residual = vec![0.0f32; if keep_lists { PIX } else { 0 }];
    let mut mins = vec![0usize; if topk.is_some() { PIX } else { 0 }];
    let mut seq = 0u32;

    // Gaussians are fetched in batches: the gather's loads are independent of each other, so
    // their cache misses overlap (the CPU analogue of the reference kernel's shared-memory
    // batches), and the blend then reads the batch from L1.
    let mut batch = [Projected::CULLED; BATCH];
    for chunk in list.chunks(BATCH) {
        if alive == 0 {
            break;
        }
        for (slot, &pi) in batch.iter_mut().zip(chunk) {
            *slot = input.projected[pi as usize];
        }
        for p in &batch[..chunk.len()] {
            if alive == 0 {
                break;
            }
            // Mean relative to the tile origin, exact enough in f32.
            let mx = (p.mean[0] - x0 as f64) as f32;
            let my = (p.mean[1] - y0 as f64) as f32;
            let xa = (mx - p.extent[0]).ceil().max(0.0);
            let xb = (mx + p.extent[0]).floor().min((w - 1) as f32);
            let ya = (my - p.extent[1]).ceil().max(0.0);
            let yb = (my + p.extent[1]).floor().min((h - 1) as f32);
            if !(xa <= xb && ya <= yb) {
                continue;
            }
            let (ya, yb) = (ya as usize, yb as usize);
            let (o, pmin, z) = (p.opacity, p.power_min, p.depth);
            let [cr, cg, cbl] = p.color;
            let feat = &input.features[if ch > 0 { p.id as usize * ch } else { 0 }..][..ch];
            let (xa, xb) = (xa as usize, xb as usize);
            // Bits xa..=xb, and which 8-pixel halves of a row the box reaches.
            let span = (u32::MAX >> (31 - xb)) & !((1u32 << xa) - 1);
            let halves = [xa < 8, xb >= 8];
            for (y, live_row) in live.iter_mut().enumerate().take(yb + 1).skip(ya) {
                let row = *live_row & span;
                if row == 0 {
                    continue;
                }
                let dy = my - y as f32;
                // The α of the row's pixels, 8 lanes at a time (0 where the pixel is skipped).
                let mut halves_alpha = [[0.0f32; 8]; TILE / 8];
                let mut pass = 0u32;
                for (half, lanes) in halves_alpha.iter_mut().enumerate() {
                    if halves[half] {
                        pass |= row_alpha(lanes, half * 8, [mx, dy], p.conic, o, pmin, amin)
                            << (half * 8);
                    }
                }
                let alphas = halves_alpha.as_flattened();
                let mut hits = row & pass;
                while hits != 0 {
                    let x = hits.trailing_zeros() as usize;
                    hits &= hits - 1;
                    let k = y * TILE + x;
                    let alpha = alphas[x];
                    let t_old = trans[k];
                    let t_new = t_old * (1.0 - alpha);
                    if t_new < T_MIN {
                        *live_row &= !(1u32 << x);
                        alive -= 1;
                        continue;
                    }
                    let wgt = alpha * t_old;
                    if images {
                        rgb[0][k] += cr * wgt;
                        rgb[1][k] += cg * wgt;
                        rgb[2][k] += cbl * wgt;
                        if t_old >= 0.5 && t_new < 0.5 {
                            median[k] = z;
                        }
                    }
                    depth_acc[k] += z * wgt;
                    trans[k] = t_new;
                    if ch > 0 {
                        for (o, f) in features[k * ch..(k + 1) * ch].iter_mut().zip(feat) {
                            *o += f * wgt;
                        }
                    }
                    if keep_lists {
                        let c = Contribution {
                            id: p.id,
                            weight: wgt,
                        };
                        match topk {
                            None => {
                                let n = lens[k] as usize;
                                if n < SLOTS {
                                    scratch.slots[k * SLOTS + n] = c;
                                } else {
                                    scratch.spill.push((k as u16, c));
                                }
                                lens[k] += 1;
                            }
                            Some(kk) => {
                                push_topk(
                                    &mut slots[k],
                                    &mut mins[k],
                                    &mut residual[k],
                                    kk,
                                    Slot { seq, c },
                                );
                                seq = seq.wrapping_add(1);
                            }
                        }
                    }
                    if t_new < input.t_stop {
                        *live_row &= !(1u32 << x);
                        alive -= 1;
                    }
                }
            }
        }
    }
    for k in 0..PIX {
        let tk = trans[k];
        for (plane, bg) in rgb.iter_mut().zip(input.background) {
            plane[k] += tk * bg;
        }
    }
    let (mut offsets, mut items) = (Vec::new(), Vec::new());
    if keep_lists {
        offsets = vec![0u32; PIX + 1];
        if topk.is_some() {
            for (k, s) in slots.iter_mut().enumerate() {
                s.sort_by_key(|s| s.seq);
                items.extend(s.iter().map(|s| s.c));
                offsets[k + 1] = items.len() as u32;
            }
        } else {
            let Scratch {
                slots,
                spill,
                spilled,
                long,
                keys,
            } = &mut scratch;
            // The spilled tails gathered by pixel (a stable counting sort keeps each pixel's
            // blending = depth order).
            let mut tail = [0u32; PIX + 1];
            if !spill.is_empty() {
                for &(k, _) in spill.iter() {
                    tail[k as usize + 1] += 1;
                }
                for k in 0..PIX {
                    tail[k + 1] += tail[k];
                }
                spilled.clear();
                spilled.resize(spill.len(), Contribution { id: 0, weight: 0.0 });
                let mut cursor = tail;
                for &(k, c) in spill.iter() {
                    spilled[cursor[k as usize] as usize] = c;
                    cursor[k as usize] += 1;
                }
            }
            let total: usize = lens.iter().map(|&n| n as usize).sum();
            items.reserve(total);
            for k in 0..PIX {
                let n = lens[k] as usize;
                let head = &slots[k * SLOTS..k * SLOTS + n.min(SLOTS)];
                // Pixel k's whole list in blending order.
                let l: &[Contribution] = if n <= SLOTS {
                    head
                } else {
                    long.clear();
                    long.extend_from_slice(head);
                    long.extend_from_slice(&spilled[tail[k] as usize..tail[k + 1] as usize]);
                    long
                };
                match input.mode {
                    ContributionMode::Mass { epsilon, cap } => {
                        residual[k] = keep_mass(l, epsilon, cap, keys, &mut items);
                    }
                    _ => items.extend_from_slice(l),
                }
                offsets[k + 1] = items.len() as u32;
            }
        }
    }
    SCRATCH.set(scratch);
    TileOut {
        x0,
        y0,
        w,
        h,
        rgb,
        trans,
        depth_acc,
        median,
        features,
        offsets,
        items,
        residual,
    }
}

/// Appends to `out` the entries of one pixel's depth-ordered `list` that the mass rule keeps
/// (in depth order) and returns the mass it drops. Largest weights first (ties: the earlier
/// in depth order) until the kept sum reaches `(1 − ε)·Σ list` or `cap` entries are kept
/// (0 = no cap). `keys` is scratch. Lists of up to 64 entries are ordered by counting
/// ranks, longer ones by sorting keys; both give the same entries and the same sums.
pub fn keep_mass(
    list: &[Contribution],
    epsilon: f32,
    cap: usize,
    keys: &mut Vec<u64>,
    out: &mut Vec<Contribution>,
) -> f32 {
    let cap = if cap == 0 { usize::MAX } else { cap };
    if list.len() <= 1 && cap >= 1 {
        out.extend_from_slice(list);
        return 0.0;
    }
    let total: f32 = list.iter().map(|c| c.weight).sum();
    let target = (1.0 - epsilon) * total;
    if list.len() <= RANKED {
        return keep_mass_ranked(list, total, target, cap, out);
    }
    // Weights are positive: their bit patterns order like the values. Descending keys put
    // the larger weight first and, among equal weights, the smaller list index.
    keys.clear();
    keys.extend(
        list.iter()
            .enumerate()
            .map(|(j, c)| (u64::from(c.weight.to_bits()) << 32) | u64::from(!(j as u32))),
    );
    keys.sort_unstable_by(|a, b| b.cmp(a));
    let (mut kept, mut m) = (0.0f32, 0usize);
    while m < keys.len() && m < cap && kept < target {
        kept += f32::from_bits((keys[m] >> 32) as u32);
        m += 1;
    }
    if m == list.len() {
        out.extend_from_slice(list);
        return 0.0;
    }
    if m == 0 {
        return total;
    }
    // The kept entries are those whose key is at least the last kept one's: one scan in
    // depth order, no second sort.
    let cut = keys[m - 1];
    let mut dropped = 0.0f32;
    for (j, c) in list.iter().enumerate() {
        if (u64::from(c.weight.to_bits()) << 32) | u64::from(!(j as u32)) >= cut {
            out.push(*c);
        } else {
            dropped += c.weight;
        }
    }
    dropped
}

/// Longest list [`keep_mass`] orders by counting ranks (a bit per entry in a `u64`).
const RANKED: usize = 64;

/// [`keep_mass`] for 2..=[`RANKED`] entries without a sort: entry `i`'s rank is the number of
/// entries whose weight's bit pattern is larger (counted eight entries at a time, which the
/// compiler vectorises), equal weights share a rank and fill it in depth order, so
/// `order[r]` is the entry at position `r` of the sort by (weight descending, index
/// ascending). The kept mass and the dropped mass are summed in the same orders as the
/// sorting path sums them.
fn keep_mass_ranked(
    list: &[Contribution],
    total: f32,
    target: f32,
    cap: usize,
    out: &mut Vec<Contribution>,
) -> f32 {
    let n = list.len();
    debug_assert!((2..=RANKED).contains(&n));
    // Unsigned order of the bit patterns (as the sorting path's keys) through a signed
    // comparison: flip the sign bit.
    let mut w = [i32::MIN; RANKED];
    for (x, c) in w.iter_mut().zip(list) {
        *x = (c.weight.to_bits() ^ 0x8000_0000) as i32;
    }
    let mut rank = [0u8; RANKED];
    for (block, ranks) in w
        .chunks_exact(8)
        .zip(rank.chunks_exact_mut(8))
        .take(n.div_ceil(8))
    {
        let mut r = [0i32; 8];
        for &wj in &w[..n] {
            for (rl, &wl) in r.iter_mut().zip(block) {
                *rl += i32::from(wj > wl);
            }
        }
        for (o, &x) in ranks.iter_mut().zip(&r) {
            *o = x as u8;
        }
    }
    let mut order = [0u8; RANKED];
    let seen = rank[..n].iter().fold(0u64, |s, &r| s | (1u64 << (r % 64)));
    if seen == u64::MAX >> (RANKED - n) {
        // Distinct weights (nearly always): the ranks are a permutation.
        for (i, &r) in rank[..n].iter().enumerate() {
            order[usize::from(r)] = i as u8;
        }
    } else {
        let mut used = [0u8; RANKED];
        for (i, &r) in rank[..n].iter().enumerate() {
            let r = usize::from(r);
            order[(r + usize::from(used[r])) % RANKED] = i as u8;
            used[r] += 1;
        }
    }
    let (mut kept, mut m) = (0.0f32, 0usize);
    while m < n && m < cap && kept < target {
        kept += list[usize::from(order[m])].weight;
        m += 1;
    }
    if m == n {
        out.extend_from_slice(list);
        return 0.0;
    }
    if m == 0 {
        return total;
    }
    let keep = order[..m].iter().fold(0u64, |k, &i| k | (1u64 << i));
    let mut bits = keep;
    while bits != 0 {
        out.push(list[bits.trailing_zeros() as usize]);
        bits &= bits - 1;
    }
    let mut rest = !keep & (u64::MAX >> (RANKED - n));
    let mut dropped = 0.0f32;
    while rest != 0 {
        dropped += list[rest.trailing_zeros() as usize].weight;
        rest &= rest - 1;
    }
    dropped
}

/// Index of the slot to evict next: the smallest weight, among equals the latest, so that
/// earlier contributions win ties.
fn min_slot(slots: &[Slot]) -> usize {
    let mut m = 0;
    for (i, x) in slots.iter().enumerate() {
        let best = &slots[m];
        if x.c.weight < best.c.weight || (x.c.weight == best.c.weight && x.seq > best.seq) {
            m = i;
        }
    }
    m
}

/// Offers `s` to a pixel's top-`k` set; `min` caches [`min_slot`] once the set is full,
/// so a contribution that does not make the cut costs O(1).
fn push_topk(slots: &mut Vec<Slot>, min: &mut usize, residual: &mut f32, k: usize, s: Slot) {
    if slots.len() < k {
        slots.push(s);
        if slots.len() == k {
            *min = min_slot(slots);
        }
        return;
    }
    if k == 0 {
        *residual += s.c.weight;
        return;
    }
    if s.c.weight > slots[*min].c.weight {
        *residual += slots[*min].c.weight;
        slots[*min] = s;
        *min = min_slot(slots);
    } else {
        *residual += s.c.weight;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The mass rule computed the plain way: indices sorted by weight (descending, the
    /// earlier first on ties), summed until the target or the cap, kept in depth order; a
    /// lone entry is always kept.
    fn keep_mass_by_sorting(list: &[Contribution], epsilon: f32, cap: usize) -> (Vec<u32>, f32) {
        let cap = if cap == 0 { usize::MAX } else { cap };
        if list.len() <= 1 {
            return (list.iter().map(|c| c.id).collect(), 0.0);
        }
        let total: f32 = list.iter().map(|c| c.weight).sum();
        let mut order: Vec<usize> = (0..list.len()).collect();
        order.sort_by(|&a, &b| list[b].weight.total_cmp(&list[a].weight).then(a.cmp(&b)));
        let mut keep = vec![false; list.len()];
        let mut kept = 0.0f32;
        for (m, &j) in order.iter().enumerate() {
            if m >= cap || kept >= (1.0 - epsilon) * total {
                break;
            }
            kept += list[j].weight;
            keep[j] = true;
        }
        let ids = (0..list.len())
            .filter(|&j| keep[j])
            .map(|j| list[j].id)
            .collect();
        let dropped = (0..list.len())
            .filter(|&j| !keep[j])
            .map(|j| list[j].weight)
            .sum();
        (ids, dropped)
    }

    #[test]
    fn keep_mass_keeps_what_sorting_keeps() {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        let (mut keys, mut out) = (Vec::new(), Vec::new());
        let mut partial = 0;
        for case in 0..6000 {
            let n = match case % 5 {
                0 => (next() % 4) as usize,
                1 => (next() % 24) as usize,
                // Both sides of the ranked path's longest list.
                2 => 33 + (next() % 400) as usize,
                _ => (next() % 70) as usize,
            };
            let list: Vec<Contribution> = (0..n)
                .map(|j| Contribution {
                    id: j as u32 * 7 + 1,
                    weight: match case % 5 {
                        // Few distinct weights: ties decide.
                        3 => [0.25f32, 0.125, 0.004][(next() % 3) as usize],
                        // A long tail of tiny weights, as behind an opaque surface.
                        4 if j > 3 => (next() % 1000) as f32 * 1e-7 + 1e-6,
                        _ => (next() % 1_000_000) as f32 * 1e-6 + 1e-4,
                    },
                })
                .collect();
            let epsilon = [0.0f32, 0.02, 0.05, 0.1, 0.5, 0.99][(next() % 6) as usize];
            let cap = [0usize, 1, 4, 16, 32][(next() % 5) as usize];
            out.clear();
            let dropped = keep_mass(&list, epsilon, cap, &mut keys, &mut out);
            let (ids, want) = keep_mass_by_sorting(&list, epsilon, cap);
            let got: Vec<u32> = out.iter().map(|c| c.id).collect();
            assert_eq!(got, ids, "case {case}: n {n}, epsilon {epsilon}, cap {cap}");
            assert!(dropped == want, "case {case}: {dropped} vs {want}");
            partial += usize::from(!got.is_empty() && got.len() < n);
        }
        assert!(partial > 2000, "{partial}");
    }

    #[test]
    fn topk_keeps_largest_earliest_on_ties_and_counts_the_rest() {
        let (mut slots, mut min, mut residual) = (Vec::new(), 0, 0.0f32);
        for (seq, w) in [0.1f32, 0.3, 0.3, 0.2, 0.3, 0.05].into_iter().enumerate() {
            let c = Contribution {
                id: seq as u32 * 10,
                weight: w,
            };
            push_topk(
                &mut slots,
                &mut min,
                &mut residual,
                2,
                Slot { seq: seq as u32, c },
            );
        }
        let mut kept: Vec<u32> = slots.iter().map(|s| s.c.id).collect();
        kept.sort();
        assert_eq!(kept, vec![10, 20]);
        assert!((residual - (0.1 + 0.2 + 0.3 + 0.05)).abs() < 1e-6);
        let (mut none, mut m0, mut r0) = (Vec::new(), 0, 0.0f32);
        let c = Contribution { id: 1, weight: 0.5 };
        push_topk(&mut none, &mut m0, &mut r0, 0, Slot { seq: 0, c });
        assert!(none.is_empty() && r0 == 0.5);
    }
}
