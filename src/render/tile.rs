//! Tile binning and depth sorting: every projected Gaussian is listed in each 16×16 tile
//! of its rectangle, and every tile's list is in front-to-back order, ties broken by the
//! Gaussian index (the same order INRIA's radix sort on `tile ≪ 32 | depth` gives, made
//! deterministic). One global sort by `(depth, index)` followed by a counting scatter
//! into the tiles replaces the per-pair sort.
use super::project::Projected;

/// Per-tile lists of indices into the projected array, in CSR form.
#[derive(Debug, Clone, Default)]
pub struct TileBins {
    /// `offsets[t]..offsets[t + 1]` indexes `items` for tile `t` (row-major tiles).
    pub offsets: Vec<usize>,
    pub items: Vec<u32>,
}

impl TileBins {
    pub fn tile(&self, t: usize) -> &[u32] {
        &self.items[self.offsets[t]..self.offsets[t + 1]]
    }
}

/// Stable LSD radix sort of `(depth_bits << 32) | index` keys on the upper 32 bits
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
pub fn bin(projected: &[Projected], grid_x: usize, grid_y: usize) -> TileBins {
    // Depths are > 0.2, so their bit patterns order like the values.
    let mut keys: Vec<u64> = projected
        .iter()
        .enumerate()
        .map(|(i, p)| (u64::from(p.depth.to_bits()) << 32) | i as u64)
        .collect();
    radix_sort_depth(&mut keys);
    let tiles = grid_x * grid_y;
    let mut counts = vec![0usize; tiles + 1];
    for p in projected {
        let [x0, y0, x1, y1] = p.rect;
        for ty in y0..y1 {
            let row = ty as usize * grid_x;
            for tx in x0..x1 {
                counts[row + tx as usize] += 1;
            }
        }
    }
    let mut offsets = vec![0usize; tiles + 1];
    for t in 0..tiles {
        offsets[t + 1] = offsets[t] + counts[t];
    }
    let mut cursor = offsets[..tiles].to_vec();
    let mut items = vec![0u32; offsets[tiles]];
    for key in keys {
        let i = (key & 0xffff_ffff) as u32;
        let [x0, y0, x1, y1] = projected[i as usize].rect;
        for ty in y0..y1 {
            let row = ty as usize * grid_x;
            for tx in x0..x1 {
                let t = row + tx as usize;
                items[cursor[t]] = i;
                cursor[t] += 1;
            }
        }
    }
    TileBins { offsets, items }
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
