//! Tile binning and depth sorting: every projected Gaussian is listed in each 16×16 tile
//! of its rectangle, and every tile's list is in front-to-back order, ties broken by the
//! Gaussian index (the same order INRIA's radix sort on `tile ≪ 32 | depth` gives, made
//! deterministic). One global sort by `(depth, index)` followed by a counting scatter
//! into the tiles replaces the per-pair sort.
use rayon::prelude::*;

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

/// Sorts `projected` by `(depth, index)` and bins it into a `grid_x × grid_y` tile grid.
pub fn bin(projected: &[Projected], grid_x: usize, grid_y: usize) -> TileBins {
    // Depths are > 0.2, so their bit patterns order like the values.
    let mut keys: Vec<u64> = projected
        .iter()
        .enumerate()
        .map(|(i, p)| (u64::from(p.depth.to_bits()) << 32) | i as u64)
        .collect();
    keys.par_sort_unstable();
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
