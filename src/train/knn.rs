//! The k-nearest-neighbour graph over Gaussian centres for the 3D term. Geometry is frozen, so
//! the graph is built once (a k-d tree, `kiddo`), not per regularisation step as the reference
//! does with a brute-force distance matrix over a random subset.
use std::num::NonZero;

use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use rayon::prelude::*;

/// Per Gaussian, its `k` nearest other Gaussians (`N × k`, row-major), by Euclidean distance of
/// the centres computed in `f64`; ties go to the smaller index. With fewer than `k + 1`
/// Gaussians, `k` shrinks to `N − 1`.
#[derive(Debug, Clone, PartialEq)]
pub struct KnnGraph {
    pub k: usize,
    pub neighbours: Vec<u32>,
}

impl KnnGraph {
    /// Gaussian `g`'s neighbours.
    pub fn of(&self, g: usize) -> &[u32] {
        &self.neighbours[g * self.k..(g + 1) * self.k]
    }
}

/// Builds the graph (parallel queries, each independent: the result does not depend on the
/// thread count).
pub fn build(positions: &[[f32; 3]], k: usize) -> KnnGraph {
    let n = positions.len();
    let k = k.min(n.saturating_sub(1));
    if k == 0 {
        return KnnGraph {
            k,
            neighbours: Vec::new(),
        };
    }
    let tree: ImmutableKdTree<f32, u32, 3, 32> = ImmutableKdTree::new_from_slice(positions);
    // A few extra candidates so that ties at the k-th distance and the query point itself
    // (and duplicates of it) are resolved by index, not by tree order.
    let want = NonZero::new((k + 4).min(n)).expect("n ≥ 2");
    let d64 = |a: &[f32; 3], b: &[f32; 3]| -> f64 {
        (0..3)
            .map(|i| (f64::from(a[i]) - f64::from(b[i])).powi(2))
            .sum()
    };
    let neighbours: Vec<u32> = (0..n)
        .into_par_iter()
        .flat_map_iter(|g| {
            let q = &positions[g];
            let mut c: Vec<(f64, u32)> = tree
                .nearest_n::<SquaredEuclidean>(q, want)
                .into_iter()
                .filter(|x| x.item as usize != g)
                .map(|x| (d64(q, &positions[x.item as usize]), x.item))
                .collect();
            c.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            c.truncate(k);
            c.into_iter().map(|x| x.1)
        })
        .collect();
    debug_assert_eq!(neighbours.len(), n * k);
    KnnGraph { k, neighbours }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_brute_force_on_a_random_cloud() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let pts: Vec<[f32; 3]> = (0..2000)
            .map(|_| {
                [
                    rng.random_range(-5.0..5.0),
                    rng.random_range(-5.0..5.0),
                    rng.random_range(0.0..1.0),
                ]
            })
            .collect();
        let g = build(&pts, 5);
        for i in (0..pts.len()).step_by(37) {
            let mut all: Vec<(f64, u32)> = (0..pts.len())
                .filter(|&j| j != i)
                .map(|j| {
                    let d: f64 = (0..3)
                        .map(|a| (f64::from(pts[i][a]) - f64::from(pts[j][a])).powi(2))
                        .sum();
                    (d, j as u32)
                })
                .collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            let want: Vec<u32> = all[..5].iter().map(|x| x.1).collect();
            assert_eq!(g.of(i), &want[..], "point {i}");
        }
    }

    #[test]
    fn tiny_and_duplicate_clouds() {
        assert_eq!(build(&[[0.0; 3]], 5).k, 0);
        let g = build(&[[0.0; 3], [0.0; 3], [1.0, 0.0, 0.0]], 5);
        assert_eq!(g.k, 2);
        assert_eq!(g.of(0), &[1, 2]);
        assert_eq!(g.of(1), &[0, 2]);
        assert_eq!(g.of(2), &[0, 1]);
    }
}
