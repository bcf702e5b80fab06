//! Whole groups of Gaussians culled per view before [`project::project`] runs on them.
//!
//! The drawable Gaussians (opacity ≥ 1/255: [`project::project`] culls every other one) are
//! grouped once per scene into cells of [`CELL`] Gaussians consecutive in Morton order of
//! their centres; each cell keeps the bounding box of its centres and the largest Frobenius
//! norm of their 3D covariances. Per view, a cell is skipped when every member is surely
//! culled by the projection:
//! * **behind the near plane**: the camera-frame `z` is linear in the centre, so its largest
//!   value over the box is taken at a corner; every member has `z ≤ NEAR`;
//! * **outside the tile grid**: with every corner in front (`z > NEAR`), a member's projected
//!   mean `f·x/z + c − ½` is a linear-fractional function of its centre, whose extremes over
//!   the box are taken at corners; its screen radius is at most the projection's cull
//!   bound with `‖J‖²_F ≤ (f_x²(1 + l_x²) + f_y²(1 + l_y²))/z_min²` (the Jacobian's clamp
//!   `|x/z| ≤ l_x = 1.3·tan fov_x`) and the cell's largest `‖Σ‖_F`, so a mean that far (plus
//!   a pixel) outside the grid is culled there.
//!
//! Skipping a cell therefore changes no output: the remaining Gaussians are projected in index
//! order as before, so depth ties break the same way (`tile::bin`).
use glam::DVec3;
use rayon::prelude::*;

use super::PreparedScene;
use super::project::{self, ALPHA_MIN, NEAR, TILE, ViewParams};
use super::tile::radix_sort_depth;

/// Gaussians per cell.
pub const CELL: usize = 256;

/// One cell: `members[start..end]` of [`CellIndex`], the box of their centres and the largest
/// `‖Σ‖_F` among them.
#[derive(Debug, Clone)]
struct Cell {
    start: usize,
    end: usize,
    lo: DVec3,
    hi: DVec3,
    sigma_f: f64,
}

/// The cells of a scene (see the module documentation).
#[derive(Debug, Clone, Default)]
pub struct CellIndex {
    /// Gaussian indices, cell after cell.
    members: Vec<u32>,
    cells: Vec<Cell>,
}

/// Spreads the low 21 bits of `v` to every third bit.
fn spread3(v: u64) -> u64 {
    let mut x = v & 0x1f_ffff;
    x = (x | (x << 32)) & 0x001f_0000_0000_ffff;
    x = (x | (x << 16)) & 0x001f_0000_ff00_00ff;
    x = (x | (x << 8)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x << 2)) & 0x1249_2492_4924_9249;
    x
}

impl CellIndex {
    /// Groups the drawable Gaussians of `scene` (deterministic: Morton order of a 1024³ grid
    /// over their centres' box, ties by index).
    pub fn new(scene: &PreparedScene) -> CellIndex {
        let drawable: Vec<u32> = (0..scene.len())
            .into_par_iter()
            .filter(|&i| scene.opacity[i] >= ALPHA_MIN && finite(scene, i))
            .map(|i| i as u32)
            .collect();
        if drawable.is_empty() {
            return CellIndex::default();
        }
        let pos = |i: u32| DVec3::from_array(scene.positions[i as usize].map(f64::from));
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for &i in &drawable {
            lo = lo.min(pos(i));
            hi = hi.max(pos(i));
        }
        let scale = (hi - lo).max(DVec3::splat(f64::MIN_POSITIVE));
        // 10 bits per axis: a 1024³ grid, far finer than a cell of 256 needs.
        let q = |v: f64, l: f64, s: f64| (((v - l) / s) * 1023.0).clamp(0.0, 1023.0) as u64;
        let mut keys: Vec<u64> = drawable
            .par_iter()
            .map(|&i| {
                let p = pos(i);
                let code = spread3(q(p.x, lo.x, scale.x))
                    | (spread3(q(p.y, lo.y, scale.y)) << 1)
                    | (spread3(q(p.z, lo.z, scale.z)) << 2);
                (code << 32) | u64::from(i)
            })
            .collect();
        // Stable on the code, the keys starting in index order: ties stay by index.
        radix_sort_depth(&mut keys);
        let members: Vec<u32> = keys.iter().map(|&k| k as u32).collect();
        let cells = members
            .par_chunks(CELL)
            .enumerate()
            .map(|(c, chunk)| {
                let (mut lo, mut hi) =
                    (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
                let mut sigma_f = 0.0f64;
                for &i in chunk {
                    lo = lo.min(pos(i));
                    hi = hi.max(pos(i));
                    sigma_f =
                        sigma_f.max(project::frobenius(&scene.cov3d[i as usize].map(f64::from)));
                }
                Cell {
                    start: c * CELL,
                    end: c * CELL + chunk.len(),
                    lo,
                    hi,
                    sigma_f,
                }
            })
            .collect();
        CellIndex { members, cells }
    }

    /// Marks in `keep` (one bit per Gaussian, cleared by the caller) the members of every
    /// cell that view `v` cannot skip; returns how many Gaussians were marked.
    pub fn mark_visible(&self, v: &ViewParams, keep: &mut [u64]) -> usize {
        let mut marked = 0;
        for c in &self.cells {
            if skipped(c, v) {
                continue;
            }
            for &i in &self.members[c.start..c.end] {
                keep[i as usize / 64] |= 1u64 << (i % 64);
            }
            marked += c.end - c.start;
        }
        marked
    }
}

/// Whether Gaussian `i`'s centre and covariance are finite (the scene preparation gives every
/// other Gaussian opacity 0; checked again so that the cells' boxes stay finite).
fn finite(scene: &PreparedScene, i: usize) -> bool {
    scene.positions[i].iter().all(|v| v.is_finite()) && scene.cov3d[i].iter().all(|v| v.is_finite())
}

/// Whether every Gaussian of `c` is surely culled by [`project::project`] in view `v`.
fn skipped(c: &Cell, v: &ViewParams) -> bool {
    let (fx, fy) = (v.fx, v.fy);
    if !(fx > 0.0 && fy > 0.0 && fx.is_finite() && fy.is_finite()) {
        return false;
    }
    let (mut zmin, mut zmax) = (f64::INFINITY, f64::NEG_INFINITY);
    let (mut rx, mut ry) = (
        [f64::INFINITY, f64::NEG_INFINITY],
        [f64::INFINITY, f64::NEG_INFINITY],
    );
    let mut mag = v.trans.abs().max_element();
    let mut ts = [DVec3::ZERO; 8];
    for (k, t) in ts.iter_mut().enumerate() {
        let p = DVec3::new(
            if k & 1 == 0 { c.lo.x } else { c.hi.x },
            if k & 2 == 0 { c.lo.y } else { c.hi.y },
            if k & 4 == 0 { c.lo.z } else { c.hi.z },
        );
        *t = v.rot * p + v.trans;
        mag = mag.max(p.abs().max_element());
        zmin = zmin.min(t.z);
        zmax = zmax.max(t.z);
    }
    // f64 rounding of a member's `z` against the corners': far below this margin.
    let eps = 1e-9 * (1.0 + mag);
    if zmax < NEAR - eps {
        return true;
    }
    // Every corner in front (NaN is not).
    let in_front = zmin > NEAR + eps && zmax.is_finite();
    if !in_front {
        return false;
    }
    for t in &ts {
        rx = [rx[0].min(t.x / t.z), rx[1].max(t.x / t.z)];
        ry = [ry[0].min(t.y / t.z), ry[1].max(t.y / t.z)];
    }
    let (limx, limy) = (1.3 * v.tan_fovx, 1.3 * v.tan_fovy);
    let jf = (fx * fx * (1.0 + limx * limx) + fy * fy * (1.0 + limy * limy)) / (zmin * zmin);
    let r = project::radius_bound(jf * c.sigma_f);
    // One pixel more, plus a relative margin, for the rounding of a member's own mean.
    let grow = |m: f64| r + 1.0 + 1e-9 * m.abs();
    let x = [fx * rx[0] + v.cx - 0.5, fx * rx[1] + v.cx - 0.5];
    let y = [fy * ry[0] + v.cy - 0.5, fy * ry[1] + v.cy - 0.5];
    let (wx, wy) = ((v.grid_x * TILE) as f64, (v.grid_y * TILE) as f64);
    x[1] + grow(x[1]) < 0.0
        || y[1] + grow(y[1]) < 0.0
        || x[0] - grow(x[0]) > wx
        || y[0] - grow(y[0]) > wy
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::render::tests::{camera_at, random_centre, random_scene};
    use rand::{Rng, SeedableRng};

    /// Every Gaussian the cull leaves out is one the projection culls; the cull leaves out
    /// some (else this test proves nothing) and keeps some.
    #[test]
    fn every_skipped_gaussian_is_one_the_projection_culls() {
        let scene = random_scene(30_000, 40.0, 3);
        let cells = CellIndex::new(&scene);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (mut skipped_total, mut kept_total) = (0usize, 0usize);
        for k in 0..40 {
            let c = random_centre(&mut rng, 30.0);
            let f = rng.random_range(15.0..2000.0);
            let cam = camera_at(
                c,
                rng.random_range(-3.1..3.1),
                rng.random_range(-1.5..1.5),
                160,
                120,
                f,
            );
            let v = ViewParams::new(&cam);
            let mut keep = vec![0u64; scene.len().div_ceil(64)];
            let kept = cells.mark_visible(&v, &mut keep);
            kept_total += kept;
            for i in 0..scene.len() {
                if keep[i / 64] >> (i % 64) & 1 == 1 {
                    continue;
                }
                skipped_total += 1;
                for aa in [false, true] {
                    assert!(
                        project::project(&scene, i, &v, aa, 0).is_none(),
                        "view {k}: Gaussian {i} was skipped but projects"
                    );
                }
            }
        }
        assert!(skipped_total > 100_000, "{skipped_total} skipped");
        assert!(kept_total > 10_000, "{kept_total} kept");
    }

    #[test]
    fn spread3_puts_bit_k_at_3k() {
        for k in 0..21 {
            assert_eq!(spread3(1 << k), 1 << (3 * k));
        }
        assert_eq!(spread3(0x1f_ffff).count_ones(), 21);
    }
}
