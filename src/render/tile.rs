//! Tile binning and depth sorting: every projected Gaussian is listed in each 16×16 tile
//! of its rectangle, and every tile's list is in front-to-back order, ties broken by the
//! Gaussian index (the same order INRIA's radix sort on `tile ≪ 32 | depth` gives, made
//! deterministic). One global sort by `(depth, index)` followed by a counting scatter
//! into the tiles replaces the per-pair sort.
use super::project::Projected;
use rayon::prelude::*;

/// Per-tile lists of indices into the projected array, in CSR form.
#[derive(Debug, Clone, Default)]
pub struct TileBins {
    /// `offsets[t]..offsets[t + 1]` indexes `items` for tile `t` (row-major tiles).
    pub offsets: Vec<usize>,
    pub items: Vec<u32>,
    /// Gaussians with a non-empty tile rectangle.
    pub visible: usize,
}

impl TileBins {
    pub fn tile(&self, t: usize) -> &[u32] {
        &self.items[self.offsets[t]..self.offsets[t + 1]]
    }
}

/// Stable LSD radix sort of `(k << 32) | index` keys (`k`: a depth's bits, a Morton code) on the upper 32 bits
/// (three passes of 11/11/10 bits). The keys start in index order, so equal depths stay
/// in index order: the result equals a full sort of the 64-bit keys.
pub fn radix_sort_depth(keys: &mut Vec<u64>) {
    let mut tmp = vec![0u64; keys.len()];
    for (shift, bits) in [(32u32, 11u32), (43, 11), (54, 10)] {
        let mask = (1u64 << bits) - 1;
        let mut counts = vec![0usize; (1 << bits) + 1];
        for &k in keys.iter() {
            counts[((k >> shift) & mask) as usize + 1] += 1;
        }
        if counts.iter().filter(|&&c| c > 0).count() <= 1 {
            continue; // every key has the same digit: the pass would not move anything
        }
        for b in 0..(1 << bits) {
            counts[b + 1] += counts[b];
        }
        for &k in keys.iter() {
            let d = ((k >> shift) & mask) as usize;
            tmp[counts[d]] = k;
            counts[d] += 1;
        }
        std::mem::swap(keys, &mut tmp);
    }
}

/// Sorts `projected` by `(depth, index)` and bins it into a `grid_x × grid_y` tile grid.
///
/// After the sort, the rectangles are gathered in sorted order and bands of tile rows are
/// filled in parallel, each by sequential scans; concatenating the bands gives the same
/// lists for any number of bands.
pub fn bin(projected: &[Projected], grid_x: usize, grid_y: usize) -> TileBins {
    // Depths are > 0.2, so their bit patterns order like the values.
    let mut keys: Vec<u64> = projected
        .par_iter()
        .enumerate()
        .filter(|(_, p)| p.is_visible())
        .map(|(i, p)| (u64::from(p.depth.to_bits()) << 32) | i as u64)
        .collect();
    let visible = keys.len();
    radix_sort_depth(&mut keys);
    let sorted: Vec<(u32, [u32; 4])> = keys
        .par_iter()
        .map(|&k| {
            let i = (k & 0xffff_ffff) as u32;
            (i, projected[i as usize].rect)
        })
        .collect();
    drop(keys);
    let bands = (rayon::current_num_threads() * 2).clamp(1, grid_y.max(1));
    let rows_per = grid_y.div_ceil(bands).max(1);
    let parts: Vec<(Vec<usize>, Vec<u32>)> = (0..bands)
        .into_par_iter()
        .map(|b| {
            let r0 = (b * rows_per).min(grid_y) as u32;
            let r1 = ((b + 1) * rows_per).min(grid_y) as u32;
            let tiles = (r1 - r0) as usize * grid_x;
            let mut offsets = vec![0usize; tiles + 1];
            for (_, r) in &sorted {
                for ty in r[1].max(r0)..r[3].min(r1) {
                    let row = (ty - r0) as usize * grid_x + 1;
                    for tx in r[0]..r[2] {
                        offsets[row + tx as usize] += 1;
                    }
                }
            }
            for t in 0..tiles {
                offsets[t + 1] += offsets[t];
            }
            let mut cursor = offsets[..tiles].to_vec();
            let mut items = vec![0u32; offsets[tiles]];
            for &(i, r) in &sorted {
                for ty in r[1].max(r0)..r[3].min(r1) {
                    let row = (ty - r0) as usize * grid_x;
                    for tx in r[0]..r[2] {
                        let t = row + tx as usize;
                        items[cursor[t]] = i;
                        cursor[t] += 1;
                    }
                }
            }
            (offsets, items)
        })
        .collect();
    let mut offsets = Vec::with_capacity(grid_x * grid_y + 1);
    offsets.push(0usize);
    let total: usize = parts.iter().map(|p| p.1.len()).sum();
    let mut items = Vec::with_capacity(total);
    for (offs, its) in parts {
        let base = items.len();
        offsets.extend(offs[1..].iter().map(|o| o + base));
        items.extend_from_slice(&its);
    }
    TileBins {
        offsets,
        items,
        visible,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn radix_sort_equals_full_sort_with_index_ties() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let depths: Vec<f32> = (0..5000)
            .map(|_| {
                if rng.random_bool(0.2) {
                    1.5
                } else {
                    rng.random_range(0.2f32..1e4)
                }
            })
            .collect();
        let mut keys: Vec<u64> = depths
            .iter()
            .enumerate()
            .map(|(i, d)| (u64::from(d.to_bits()) << 32) | i as u64)
            .collect();
        let mut expected = keys.clone();
        expected.sort_unstable();
        radix_sort_depth(&mut keys);
        assert_eq!(keys, expected);
    }
}
