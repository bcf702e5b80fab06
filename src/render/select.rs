//! Which training views a run needs: the views (greedy) that keep every Gaussian seen by
//! `min(k, n)` of them at a good angle, where `n` is the number of training views that see it
//! at all, or a share of that demand ([`crate::cache::ViewSelection::Cover`]). The
//! association and the vote then work on those views only, and the render, the raycast and
//! every per-view stage skip the others.
//!
//! **Visibility** is a proxy computed before anything is rendered: each Gaussian centre of
//! the render's cells that the view cannot skip ([`super::cull`]) is projected into the view
//! (the full lens model); a coarse depth buffer of cells of [`CELL`] pixels keeps the nearest centre of the
//! Gaussians with opacity ≥ [`OCCLUDER_OPACITY`] per cell; a Gaussian (opacity ≥
//! [`SEEN_OPACITY`]) whose centre falls in the image is *seen* when its depth is within
//! [`DEPTH_TOLERANCE`] (relative) of its cell's nearest centre and the angle is good: for the
//! unit direction `d` from the camera to the centre and the covariance `Σ`,
//! `2·dᵀΣd / tr Σ ≤ 1 − c²` with `c` = [`MIN_COS`] — for a flat disc (the usual Gaussian on a
//! surface) `2·dᵀΣd / tr Σ = sin²θ` of the angle θ between `d` and the disc's normal, so the
//! test is `|cos θ| ≥ c`; an isotropic Gaussian (2/3) always passes.
//!
//! **The cover** is the greedy set multicover with lazy gains: each Gaussian's demand is
//! `min(k, n)`; the view that meets the most remaining demand is taken (ties: the earlier
//! view), each of its Gaussians' demand drops by one, until none remains; the chosen views
//! are the shortest prefix of that order that meets `share` of the demand. Gains only shrink,
//! so a stale gain is an upper bound and only the top of the heap is recomputed. Views are in
//! the order given and each view's visibility is its own, so the choice does not depend on
//! the number of threads.
use std::cmp::Reverse;
use std::collections::BinaryHeap;

use glam::DVec3;
use rayon::prelude::*;

use super::PreparedScene;
use crate::cache::ViewCover;
use crate::camera::View;

/// Side of the depth buffer's cells, in pixels of the view.
pub const CELL: usize = 8;
/// Gaussians at least this opaque hide what lies behind them in the depth buffer.
pub const OCCLUDER_OPACITY: f32 = 0.5;
/// Gaussians below this opacity need no view.
pub const SEEN_OPACITY: f32 = 0.05;
/// A centre up to this share deeper than its cell's nearest centre is seen.
pub const DEPTH_TOLERANCE: f64 = 0.05;
/// The smallest `|cos|` between the view direction and a flat Gaussian's normal that counts.
pub const MIN_COS: f64 = 0.25;

/// The Gaussians `view` sees at a good angle (module docs), as a bit set over the scene.
pub fn visible(scene: &PreparedScene, view: &View) -> Vec<u64> {
    let n = scene.len();
    let cam = &view.camera;
    let (w, h) = (
        cam.intrinsics.width as usize,
        cam.intrinsics.height as usize,
    );
    let (cw, ch) = (w.div_ceil(CELL), h.div_ceil(CELL));
    let mut zbuf = vec![f64::INFINITY; cw * ch];
    // Only the Gaussians of the render's cells that the view cannot skip (`cull`: every
    // other one projects outside the image or behind the camera).
    let mut bits = vec![0u64; n.div_ceil(64)];
    scene
        .cells()
        .mark_visible(&super::project::ViewParams::new(cam), &mut bits);
    // Per candidate Gaussian its index, cell and depth.
    let mut at: Vec<(u32, u32, f32)> = Vec::new();
    for (wi, word) in bits.iter_mut().enumerate() {
        let mut b = std::mem::take(word);
        while b != 0 {
            let g = wi * 64 + b.trailing_zeros() as usize;
            b &= b - 1;
            let o = scene.opacity[g];
            if o < SEEN_OPACITY {
                continue;
            }
            let p = scene.positions[g];
            let q = cam.pose.world_to_camera(DVec3::new(
                f64::from(p[0]),
                f64::from(p[1]),
                f64::from(p[2]),
            ));
            let Some(px) = cam.pixel_containing(q, w, h) else {
                continue;
            };
            let cell = (px / w / CELL) * cw + (px % w) / CELL;
            at.push((g as u32, cell as u32, q.z as f32));
            if o >= OCCLUDER_OPACITY && q.z < zbuf[cell] {
                zbuf[cell] = q.z;
            }
        }
    }
    let centre = cam.pose.center();
    let limit = 1.0 - MIN_COS * MIN_COS;
    for &(g, cell, z) in &at {
        let g = g as usize;
        if f64::from(z) > zbuf[cell as usize] * (1.0 + DEPTH_TOLERANCE) {
            continue;
        }
        let p = scene.positions[g];
        let Some(d) = (DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) - centre)
            .try_normalize()
        else {
            continue;
        };
        let [xx, xy, xz, yy, yz, zz] = scene.cov3d[g].map(f64::from);
        let along = d.x * d.x * xx
            + d.y * d.y * yy
            + d.z * d.z * zz
            + 2.0 * (d.x * d.y * xy + d.x * d.z * xz + d.y * d.z * yz);
        let trace = xx + yy + zz;
        if 2.0 * along <= limit * trace {
            bits[g / 64] |= 1 << (g % 64);
        }
    }
    bits
}

/// The greedy cover of `views` for `k` views per Gaussian, stopped once `share` of the demand
/// is met (module docs).
pub fn cover(scene: &PreparedScene, views: &[View], k: u32, share: f32) -> ViewCover {
    let t = std::time::Instant::now();
    let sets: Vec<Vec<u64>> = views.par_iter().map(|v| visible(scene, v)).collect();
    let mut c = choose(&sets, scene.len(), k, share);
    c.seconds = t.elapsed().as_secs_f64();
    c
}

/// The greedy multicover of the bit sets `sets` over `n` items, `k` per item (module docs):
/// every set with any gain in the greedy's order (`order`, `gains`), and the first of them
/// that meet `share` of the demand (`chosen`, ascending).
pub fn choose(sets: &[Vec<u64>], n: usize, k: u32, share: f32) -> ViewCover {
    let k = k.max(1);
    let words = n.div_ceil(64);
    let mut count = vec![0u32; n];
    for s in sets {
        for (wi, &b) in s.iter().enumerate() {
            let mut b = b;
            while b != 0 {
                count[wi * 64 + b.trailing_zeros() as usize] += 1;
                b &= b - 1;
            }
        }
    }
    let mut remaining: Vec<u32> = count.iter().map(|&c| c.min(k)).collect();
    let demand: u64 = remaining.iter().map(|&r| u64::from(r)).sum();
    let seen = count.iter().filter(|&&c| c > 0).count();
    let mut need = vec![0u64; words];
    for (g, &r) in remaining.iter().enumerate() {
        if r > 0 {
            need[g / 64] |= 1 << (g % 64);
        }
    }
    let gain = |s: &[u64], need: &[u64]| -> u64 {
        s.iter()
            .zip(need)
            .map(|(a, b)| u64::from((a & b).count_ones()))
            .sum()
    };
    // (gain, earlier view first): a max-heap of upper bounds.
    let mut heap: BinaryHeap<(u64, Reverse<usize>)> = sets
        .iter()
        .enumerate()
        .map(|(i, s)| (gain(s, &need), Reverse(i)))
        .collect();
    let (mut order, mut gains) = (Vec::new(), Vec::new());
    while let Some((stale, Reverse(i))) = heap.pop() {
        if stale == 0 {
            break;
        }
        let fresh = gain(&sets[i], &need);
        if fresh == 0 {
            continue;
        }
        if heap.peek().is_some_and(|&top| (fresh, Reverse(i)) < top) {
            heap.push((fresh, Reverse(i)));
            continue;
        }
        order.push(i);
        gains.push(fresh);
        for (wi, &b) in sets[i].iter().enumerate() {
            let mut b = b & need[wi];
            while b != 0 {
                let g = wi * 64 + b.trailing_zeros() as usize;
                b &= b - 1;
                remaining[g] -= 1;
                if remaining[g] == 0 {
                    need[wi] &= !(1 << (g % 64));
                }
            }
        }
    }
    // The shortest prefix of the greedy order that meets `share` of the demand (in integers:
    // met ≥ ⌈share · demand⌉, all of it for share 1).
    let target = ((f64::from(share) * demand as f64).ceil() as u64).min(demand);
    let (mut met, mut take) = (0u64, 0usize);
    while met < target && take < order.len() {
        met += gains[take];
        take += 1;
    }
    let mut chosen = order[..take].to_vec();
    chosen.sort_unstable();
    let chosen_views: u64 = chosen
        .iter()
        .map(|&i| {
            sets[i]
                .iter()
                .map(|b| u64::from(b.count_ones()))
                .sum::<u64>()
        })
        .sum();
    let all_views: u64 = count.iter().map(|&c| u64::from(c)).sum();
    let per = |x: u64| {
        if seen > 0 {
            x as f64 / seen as f64
        } else {
            0.0
        }
    };
    ViewCover {
        k,
        share,
        chosen,
        offered: sets.len(),
        seen,
        demand,
        gains,
        order,
        mean_views_offered: per(all_views),
        mean_views_chosen: per(chosen_views),
        seconds: 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Distortion, Intrinsics, Pose};
    use crate::splat::Gaussians;
    use rand::{Rng, SeedableRng};

    /// The plain greedy multicover, every gain recomputed every round (no heap), each set
    /// taken at most once: the order the sets are taken in and their gains.
    fn plain_greedy(sets: &[Vec<bool>], k: u32) -> (Vec<usize>, Vec<usize>) {
        let n = sets[0].len();
        let mut rem: Vec<u32> = (0..n)
            .map(|g| (sets.iter().filter(|s| s[g]).count() as u32).min(k))
            .collect();
        let (mut order, mut got) = (Vec::new(), Vec::new());
        loop {
            let gains: Vec<usize> = sets
                .iter()
                .enumerate()
                .map(|(i, s)| {
                    if order.contains(&i) {
                        0
                    } else {
                        (0..n).filter(|&g| s[g] && rem[g] > 0).count()
                    }
                })
                .collect();
            let best = (0..sets.len()).max_by_key(|&i| (gains[i], std::cmp::Reverse(i)));
            match best {
                Some(i) if gains[i] > 0 => {
                    order.push(i);
                    got.push(gains[i]);
                    for g in 0..n {
                        if sets[i][g] && rem[g] > 0 {
                            rem[g] -= 1;
                        }
                    }
                }
                _ => break,
            }
        }
        (order, got)
    }

    #[test]
    fn the_lazy_cover_is_the_plain_greedy_and_meets_the_demand_asked_for() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for round in 0..40 {
            let (m, n): (usize, usize) = (rng.random_range(1..25), rng.random_range(1..300));
            let sets: Vec<Vec<bool>> = (0..m)
                .map(|_| {
                    let p: f64 = rng.random_range(0.0..0.6);
                    (0..n).map(|_| rng.random_bool(p)).collect()
                })
                .collect();
            let bits: Vec<Vec<u64>> = sets
                .iter()
                .map(|s| {
                    let mut b = vec![0u64; n.div_ceil(64)];
                    for (g, &x) in s.iter().enumerate() {
                        if x {
                            b[g / 64] |= 1 << (g % 64);
                        }
                    }
                    b
                })
                .collect();
            for k in 1..=4 {
                let (order, gains) = plain_greedy(&sets, k);
                let demand: usize = (0..n)
                    .map(|g| (sets.iter().filter(|s| s[g]).count()).min(k as usize))
                    .sum();
                for share in [0.3f32, 0.9, 1.0] {
                    let c = choose(&bits, n, k, share);
                    assert_eq!(c.order, order, "round {round}, k {k}");
                    assert_eq!(c.gains, gains.iter().map(|&g| g as u64).collect::<Vec<_>>());
                    assert_eq!(c.demand, demand as u64);
                    // The shortest prefix of the order whose gains reach share · demand.
                    let mut take = 0;
                    while (gains[..take].iter().sum::<usize>() as f64)
                        < f64::from(share) * demand as f64
                    {
                        take += 1;
                    }
                    let mut want = order[..take].to_vec();
                    want.sort_unstable();
                    assert_eq!(c.chosen, want, "round {round}, k {k}, share {share}");
                    if share == 1.0 {
                        for g in 0..n {
                            let all = sets.iter().filter(|s| s[g]).count() as u32;
                            let got = c.chosen.iter().filter(|&&i| sets[i][g]).count() as u32;
                            assert!(got >= all.min(k), "item {g}: {got} of {all}, k {k}");
                        }
                    }
                    let seen = (0..n).filter(|&g| sets.iter().any(|s| s[g])).count();
                    assert_eq!((c.seen, c.offered, c.k), (seen, m, k));
                }
            }
        }
    }

    fn logit(p: f32) -> f32 {
        (p / (1.0 - p)).ln()
    }

    #[test]
    fn a_view_sees_the_near_wall_not_the_one_behind_nor_a_disc_edge_on() {
        // Camera at the origin looking along +z (x right, y down), 96×72, focal 80.
        let cam = Camera {
            intrinsics: Intrinsics {
                width: 96,
                height: 72,
                fx: 80.0,
                fy: 80.0,
                cx: 48.0,
                cy: 36.0,
                distortion: Distortion::None,
            },
            pose: Pose {
                rotation: glam::DMat3::IDENTITY,
                translation: glam::DVec3::ZERO,
            },
        };
        let mut g = Gaussians::default();
        let mut add = |p: [f32; 3], opacity: f32, scale: [f32; 3]| {
            g.positions.push(p);
            g.f_dc.push([0.0; 3]);
            g.opacity.push(logit(opacity));
            g.scale.push(scale.map(f32::ln));
            g.rotation.push([1.0, 0.0, 0.0, 0.0]);
        };
        let facing = [0.1, 0.1, 0.001];
        // Wall A at z = 10 (discs facing the camera), every 0.25 m (none on the image's
        // border): every 8-px cell (1 m) holds some.
        let mut wall_a = Vec::new();
        for i in -28..=28 {
            for j in -20..=20 {
                wall_a.push([i as f32 * 0.25 + 0.125, j as f32 * 0.25 + 0.125, 10.0]);
            }
        }
        for &p in &wall_a {
            add(p, 0.95, facing);
        }
        // Wall B at z = 20, behind it; then an isotropic blob in front (opacity 0.3: seen, but
        // hides nothing), a disc edge-on (normal along x), a faint Gaussian.
        for i in -24..=24 {
            for j in -18..=18 {
                add([i as f32 * 0.5, j as f32 * 0.5, 20.0], 0.95, facing);
            }
        }
        let blob = wall_a.len() + 49 * 37;
        add([0.3, 0.2, 5.0], 0.3, [0.2, 0.2, 0.2]);
        add([1.1, 0.6, 10.0], 0.95, [0.001, 0.1, 0.1]);
        add([-1.0, 0.4, 10.0], 0.01, [0.2, 0.2, 0.2]);
        let scene = PreparedScene::new(&g).unwrap();
        let view = View {
            image_id: 1,
            camera_id: 1,
            name: "v.png".into(),
            camera: cam,
        };
        let bits = visible(&scene, &view);
        let seen: Vec<usize> = (0..scene.len())
            .filter(|&i| bits[i / 64] >> (i % 64) & 1 == 1)
            .collect();
        // By hand: the wall-A centres inside the image (u = 80x/z + 48 in [0, 96), v = 80y/z +
        // 36 in [0, 72)), and the blob.
        let mut want: Vec<usize> = wall_a
            .iter()
            .enumerate()
            .filter(|(_, p)| {
                let (u, v) = (80.0 * p[0] / 10.0 + 48.0, 80.0 * p[1] / 10.0 + 36.0);
                (0.0..96.0).contains(&u) && (0.0..72.0).contains(&v)
            })
            .map(|(i, _)| i)
            .collect();
        want.push(blob);
        assert_eq!(seen, want);
        // Two such views: one meets a demand of 1, both are needed for 2; an empty view never.
        let mut away = view.clone();
        away.camera.pose.rotation = glam::DMat3::from_rotation_y(std::f64::consts::PI);
        let c = cover(&scene, &[view.clone(), away.clone(), view.clone()], 1, 1.0);
        assert_eq!(c.chosen, vec![0]);
        let c = cover(&scene, &[away, view.clone(), view], 2, 1.0);
        assert_eq!(c.chosen, vec![1, 2]);
        assert_eq!(c.seen, want.len());
    }
}
