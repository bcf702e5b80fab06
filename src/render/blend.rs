//! Front-to-back alpha blending of one 16×16 tile, INRIA's `renderCUDA` per pixel:
//! `power = −½(a·dx² + c·dy²) − b·dx·dy` (skip if > 0), `α = min(0.99, o·e^power)` (skip if
//! < 1/255), stop before adding when `T·(1−α) < 1e-4`. The loop runs Gaussian-outer,
//! pixel-inner, restricted to the box where `α ≥ 1/255` is possible; each pixel still sees
//! its Gaussians in the same order, so the result is the same as the per-pixel loop.
//! Also accumulates depth (`Σ w·z`), the median depth, feature channels (no background)
//! and the per-pixel contribution lists (all, or the top-k by weight plus the residual).
use super::project::{ALPHA_MIN, Projected, TILE};

const PIX: usize = TILE * TILE;
/// Gaussians gathered per batch.
const BATCH: usize = 32;
/// Transmittance below which a pixel stops.
pub const T_MIN: f32 = 1e-4;
/// Largest alpha of one Gaussian.
pub const ALPHA_MAX: f32 = 0.99;

/// Which per-pixel contribution lists to keep.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum ContributionMode {
    /// None (fastest).
    #[default]
    None,
    /// Every contributing Gaussian.
    All,
    /// The `k` largest weights per pixel (ties: the earlier in depth order), plus the
    /// dropped weight mass in `residual`.
    TopK(usize),
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
    pub rgb: Vec<f32>,
    pub trans: Vec<f32>,
    pub depth_acc: Vec<f32>,
    pub median: Vec<f32>,
    /// `PIX × channels`.
    pub features: Vec<f32>,
    /// Per pixel, in depth order.
    pub lists: Vec<Vec<Contribution>>,
    pub residual: Vec<f32>,
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
    pub mode: ContributionMode,
}

/// Top-k slot: insertion sequence, contribution.
#[derive(Clone, Copy)]
struct Slot {
    seq: u32,
    c: Contribution,
}

/// Blends tile `t` given its depth-sorted list of indices into `input.projected`.
pub fn blend_tile(input: &BlendInput<'_>, t: usize, list: &[u32]) -> TileOut {
    let tx = t % input.grid_x;
    let ty = t / input.grid_x;
    let x0 = tx * TILE;
    let y0 = ty * TILE;
    let w = TILE.min(input.width - x0);
    let h = TILE.min(input.height - y0);
    let ch = input.channels;
    let mut trans = vec![1.0f32; PIX];
    let mut rgb = vec![0.0f32; PIX * 3];
    let mut depth_acc = vec![0.0f32; PIX];
    let mut median = vec![f32::NAN; PIX];
    let mut features = vec![0.0f32; PIX * ch];
    let mut done = [true; PIX];
    for y in 0..h {
        for x in 0..w {
            done[y * TILE + x] = false;
        }
    }
    let mut alive = w * h;
    let keep_lists = input.mode != ContributionMode::None;
    let topk = match input.mode {
        ContributionMode::TopK(k) => Some(k),
        _ => None,
    };
    let mut lists: Vec<Vec<Contribution>> = if keep_lists && topk.is_none() {
        vec![Vec::new(); PIX]
    } else {
        Vec::new()
    };
    let mut slots: Vec<Vec<Slot>> = match topk {
        Some(k) => (0..PIX).map(|_| Vec::with_capacity(k.min(64))).collect(),
        None => Vec::new(),
    };
    let mut residual = vec![0.0f32; if topk.is_some() { PIX } else { 0 }];
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
            let xa = (mx - p.extent[0]).floor().max(0.0);
            let xb = (mx + p.extent[0]).ceil().min((w - 1) as f32);
            let ya = (my - p.extent[1]).floor().max(0.0);
            let yb = (my + p.extent[1]).ceil().min((h - 1) as f32);
            if !(xa <= xb && ya <= yb) {
                continue;
            }
            let (xa, xb, ya, yb) = (xa as usize, xb as usize, ya as usize, yb as usize);
            let [ca, cb, cc] = p.conic;
            let feat = &input.features[if ch > 0 { p.id as usize * ch } else { 0 }..][..ch];
            for y in ya..=yb {
                let dy = my - y as f32;
                for x in xa..=xb {
                    let k = y * TILE + x;
                    if done[k] {
                        continue;
                    }
                    let dx = mx - x as f32;
                    let power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
                    if power > 0.0 || power < p.power_min {
                        continue;
                    }
                    let alpha = ALPHA_MAX.min(p.opacity * power.exp());
                    if alpha < ALPHA_MIN {
                        continue;
                    }
                    let t_old = trans[k];
                    let t_new = t_old * (1.0 - alpha);
                    if t_new < T_MIN {
                        done[k] = true;
                        alive -= 1;
                        continue;
                    }
                    let wgt = alpha * t_old;
                    rgb[k * 3] += p.color[0] * wgt;
                    rgb[k * 3 + 1] += p.color[1] * wgt;
                    rgb[k * 3 + 2] += p.color[2] * wgt;
                    depth_acc[k] += p.depth * wgt;
                    if t_old >= 0.5 && t_new < 0.5 {
                        median[k] = p.depth;
                    }
                    for (o, f) in features[k * ch..(k + 1) * ch].iter_mut().zip(feat) {
                        *o += f * wgt;
                    }
                    if keep_lists {
                        let c = Contribution {
                            id: p.id,
                            weight: wgt,
                        };
                        match topk {
                            None => lists[k].push(c),
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
                    trans[k] = t_new;
                }
            }
        }
    }
    for k in 0..PIX {
        let tk = trans[k];
        for c in 0..3 {
            rgb[k * 3 + c] += tk * input.background[c];
        }
    }
    if topk.is_some() {
        lists = slots
            .into_iter()
            .map(|mut s| {
                s.sort_by_key(|s| s.seq);
                s.into_iter().map(|s| s.c).collect()
            })
            .collect();
    }
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
        lists,
        residual,
    }
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
