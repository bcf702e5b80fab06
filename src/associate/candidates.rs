//! Per-view inputs of the association: the kept masks composited into one label image, and each
//! mask's candidate Gaussian set `C(s)` — either the Gaussians that actually make the mask's
//! pixels (their α·T weights from the contributions cache), or the paper's projected centres with
//! the reference projector's depth filter (the front 20 % by camera depth in each cell of an
//! 8×8 grid over the image).
use serde::{Deserialize, Serialize};

use crate::cache::ViewContrib;
use crate::camera::Camera;
use crate::sam::{Rle, RleError};

/// How a mask's candidate Gaussians are found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum CandidateMode {
    /// The Gaussians that contribute to the mask's pixels (α·T of the contributions cache),
    /// weighted by the mass they put inside the mask.
    #[default]
    Weighted,
    /// The paper's way: Gaussian centres projected with the view's camera, inside the mask,
    /// front fraction by camera depth per grid cell; every candidate has weight 1.
    Projected,
}

/// The kept masks of one view, composited: larger masks are painted first and smaller ones on
/// top (a person in front of a car, a car on the road keep their own pixels); equal areas are
/// painted in file order, so the later one wins.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewMasks {
    pub width: usize,
    pub height: usize,
    /// Per pixel (row-major) the index of the visible mask in the file, −1 none.
    pub label: Vec<i32>,
    /// Visible pixels per mask (file order).
    pub visible: Vec<u64>,
}

/// Composites `masks` (all `[height, width]`, see [`ViewMasks`]). An error carries the index of
/// the mask whose RLE does not decode.
pub fn composite(
    masks: &[&Rle],
    width: usize,
    height: usize,
) -> Result<ViewMasks, (usize, RleError)> {
    let mut areas = Vec::with_capacity(masks.len());
    for (i, m) in masks.iter().enumerate() {
        areas.push(m.area().map_err(|e| (i, e))?);
    }
    let mut order: Vec<usize> = (0..masks.len()).collect();
    order.sort_by(|&a, &b| areas[b].cmp(&areas[a]).then(a.cmp(&b)));
    let mut label = vec![-1i32; width * height];
    for &i in &order {
        masks[i]
            .for_each_pixel(|p| label[p] = i as i32)
            .map_err(|e| (i, e))?;
    }
    let mut visible = vec![0u64; masks.len()];
    for &l in &label {
        if l >= 0 {
            visible[l as usize] += 1;
        }
    }
    Ok(ViewMasks {
        width,
        height,
        label,
        visible,
    })
}

/// One mask's candidate Gaussians, ids ascending, with their weights.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Candidate {
    pub ids: Vec<u32>,
    pub weights: Vec<f32>,
}

impl Candidate {
    /// Total weight.
    pub fn mass(&self) -> f64 {
        self.weights.iter().map(|&w| f64::from(w)).sum()
    }
}

/// Limits of the α·T candidates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WeightedLimits {
    /// A Gaussian belongs to a mask when more than this share of its α·T mass in the view falls
    /// on the mask's pixels (> 0.5: it belongs to at most one mask of a view).
    pub min_share: f32,
    /// … and that mass is at least this many pixels' worth (hidden Gaussians behind an object
    /// carry almost none) …
    pub min_mass: f32,
    /// … and its centre projects into the mask: a Gaussian on the hidden side of an object
    /// whose footprint tail shows beside the object's silhouette puts most of its visible mass
    /// on the neighbouring mask, but it lies inside the object.
    pub centre_inside: bool,
}

impl Default for WeightedLimits {
    fn default() -> Self {
        WeightedLimits {
            min_share: 0.5,
            min_mass: 0.1,
            centre_inside: true,
        }
    }
}

/// Pixel indices per mask (counting sort of the label image), masks in file order.
fn pixels_per_mask(vm: &ViewMasks) -> (Vec<usize>, Vec<u32>) {
    let n = vm.visible.len();
    let mut start = vec![0usize; n + 1];
    for (i, &v) in vm.visible.iter().enumerate() {
        start[i + 1] = start[i] + v as usize;
    }
    let mut fill = start.clone();
    let mut px = vec![0u32; start[n]];
    for (p, &l) in vm.label.iter().enumerate() {
        if l >= 0 {
            let f = &mut fill[l as usize];
            px[*f] = p as u32;
            *f += 1;
        }
    }
    (start, px)
}

/// The α·T mass of every Gaussian over a whole view (in pixels' worth of colour).
pub fn view_mass(c: &ViewContrib) -> Vec<f32> {
    let mut total = vec![0f32; c.gaussians];
    for (&g, &w) in c.lists.ids.iter().zip(&c.lists.weights) {
        total[g as usize] += w;
    }
    total
}

/// Bitset (64 Gaussians per word) of the Gaussians whose view mass is at least `min_mass`.
pub fn visible_set(total: &[f32], min_mass: f32) -> Vec<u64> {
    let mut bits = vec![0u64; total.len().div_ceil(64)];
    for (g, &t) in total.iter().enumerate() {
        if t >= min_mass && t > 0.0 {
            bits[g / 64] |= 1 << (g % 64);
        }
    }
    bits
}

/// Adds each Gaussian's α·T on `pixels` into `acc` and lists the Gaussians it touched, sorted,
/// in `touched` (cleared first). The caller takes the sums back out of `acc` (leaving it zero).
fn mass_on(c: &ViewContrib, pixels: &[u32], acc: &mut [f32], touched: &mut Vec<u32>) {
    touched.clear();
    for &p in pixels {
        let (ids, ws) = c.pixel(p as usize);
        for (&g, &w) in ids.iter().zip(ws) {
            let a = &mut acc[g as usize];
            if *a == 0.0 {
                touched.push(g);
            }
            *a += w;
        }
    }
    touched.sort_unstable();
}

/// The α·T candidates of every mask of a view (file order): per mask, the Gaussians whose mass
/// inside the mask passes [`WeightedLimits`], weighted by that mass (in pixels). `total` is
/// [`view_mass`] of the view. With `lim.centre_inside`, a Gaussian also needs its centre to
/// project into the mask (through `camera`'s lens model, to the pixel containing it); only the Gaussians
/// that pass the mass tests are projected.
pub fn weighted(
    c: &ViewContrib,
    total: &[f32],
    centres: &[[f32; 3]],
    camera: &Camera,
    vm: &ViewMasks,
    lim: &WeightedLimits,
) -> Vec<Candidate> {
    debug_assert_eq!(c.pixels(), vm.label.len());
    let (start, px) = pixels_per_mask(vm);
    let mut acc = vec![0f32; c.gaussians];
    let mut touched: Vec<u32> = Vec::new();
    (0..vm.visible.len())
        .map(|m| {
            mass_on(
                c,
                &px[start[m]..start[m + 1]],
                acc.as_mut_slice(),
                &mut touched,
            );
            let mut out = Candidate::default();
            for &g in &touched {
                let a = std::mem::take(&mut acc[g as usize]);
                if a >= lim.min_mass
                    && a > lim.min_share * total[g as usize]
                    && (!lim.centre_inside
                        || centre_pixel(&centres[g as usize], camera, vm.width, vm.height)
                            .is_some_and(|(p, _)| vm.label[p] == m as i32))
                {
                    out.ids.push(g);
                    out.weights.push(a);
                }
            }
            out
        })
        .collect()
}

/// One mask's pixels: their row-major indices, and a per-pixel membership flag (image size).
#[derive(Debug, Clone, Copy)]
pub struct MaskPixels<'a> {
    pub list: &'a [u32],
    pub inside: &'a [bool],
}

/// The α·T candidates of ONE mask given by its pixel indices, on its own (not composited with
/// the view's other masks): the Gaussians whose mass on those pixels passes [`WeightedLimits`]
/// (the centre test checks only the Gaussians that pass the mass tests), weighted by that mass.
/// `acc` is scratch of length `c.gaussians`, all zero on entry and on return.
pub fn weighted_one(
    c: &ViewContrib,
    total: &[f32],
    mask: MaskPixels<'_>,
    centres: &[[f32; 3]],
    camera: &Camera,
    lim: &WeightedLimits,
    acc: &mut [f32],
) -> Candidate {
    let mut touched: Vec<u32> = Vec::new();
    mass_on(c, mask.list, acc, &mut touched);
    let mut out = Candidate::default();
    for &g in &touched {
        let a = std::mem::take(&mut acc[g as usize]);
        if a >= lim.min_mass && a > lim.min_share * total[g as usize] {
            let inside = !lim.centre_inside
                || centre_pixel(&centres[g as usize], camera, c.width, c.height)
                    .is_some_and(|(p, _)| mask.inside[p]);
            if inside {
                out.ids.push(g);
                out.weights.push(a);
            }
        }
    }
    out
}

/// The row-major pixel containing a projected centre and its camera depth.
fn centre_pixel(c: &[f32; 3], camera: &Camera, w: usize, h: usize) -> Option<(usize, f64)> {
    let p = glam::DVec3::new(f64::from(c[0]), f64::from(c[1]), f64::from(c[2]));
    let q = camera.pose.world_to_camera(p);
    camera.pixel_containing(q, w, h).map(|px| (px, q.z))
}

/// Options of the projected-centre candidates (the reference projector's).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProjectedLimits {
    /// Share of a mask's projected centres kept per grid cell, nearest first (at least one).
    pub front_fraction: f64,
    /// The image is cut into `grid × grid` cells.
    pub grid: usize,
}

impl Default for ProjectedLimits {
    fn default() -> Self {
        ProjectedLimits {
            front_fraction: 0.2,
            grid: 8,
        }
    }
}

/// The projected-centre candidates of every mask of a view (file order): every centre in front
/// of the camera is projected through the lens model to the pixel containing it; per mask and
/// grid cell, the `front_fraction` nearest by camera depth are kept (⌊fraction·n⌋, at least 1,
/// as the reference); weight 1 each.
pub fn projected(
    centres: &[[f32; 3]],
    camera: &Camera,
    vm: &ViewMasks,
    lim: &ProjectedLimits,
) -> Vec<Candidate> {
    let (w, h) = (vm.width, vm.height);
    let grid = lim.grid.max(1);
    let (cw, ch) = (w.div_ceil(grid), h.div_ceil(grid));
    // (mask, cell, depth bits, id): positive f32 depths order like their bit patterns.
    let mut hits: Vec<(u32, u32, u32, u32)> = Vec::new();
    for (g, c) in centres.iter().enumerate() {
        let Some((p, z)) = centre_pixel(c, camera, w, h) else {
            continue;
        };
        let m = vm.label[p];
        if m < 0 {
            continue;
        }
        let (x, y) = (p % w, p / w);
        let cell = (y / ch) * grid + x / cw;
        hits.push((m as u32, cell as u32, (z as f32).to_bits(), g as u32));
    }
    hits.sort_unstable();
    let mut out = vec![Candidate::default(); vm.visible.len()];
    let mut i = 0;
    while i < hits.len() {
        let (m, cell) = (hits[i].0, hits[i].1);
        let mut j = i;
        while j < hits.len() && hits[j].0 == m && hits[j].1 == cell {
            j += 1;
        }
        let keep = ((lim.front_fraction * (j - i) as f64) as usize).max(1);
        out[m as usize]
            .ids
            .extend(hits[i..i + keep].iter().map(|x| x.3));
        i = j;
    }
    for c in &mut out {
        c.ids.sort_unstable();
        c.weights = vec![1.0; c.ids.len()];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache::Contributions;
    use ndarray::Array2;

    fn rle(h: usize, w: usize, set: &[(usize, usize)]) -> Rle {
        let mut a = Array2::from_elem((h, w), false);
        for &(y, x) in set {
            a[[y, x]] = true;
        }
        Rle::encode(&a)
    }

    #[test]
    fn pixels_are_row_major_and_smaller_masks_win() {
        let big = rle(3, 4, &[(0, 0), (0, 1), (1, 1), (2, 3), (1, 3)]);
        let small = rle(3, 4, &[(1, 1), (2, 3)]);
        let mut seen = Vec::new();
        big.for_each_pixel(|p| seen.push(p)).unwrap();
        seen.sort_unstable();
        assert_eq!(seen, vec![0, 1, 5, 7, 11]);
        let vm = composite(&[&big, &small], 4, 3).unwrap();
        assert_eq!(vm.label, vec![0, 0, -1, -1, -1, 1, -1, 0, -1, -1, -1, 1]);
        assert_eq!(vm.visible, vec![3, 2]);
        // Order of the list does not matter: the smaller mask still wins.
        let vm2 = composite(&[&small, &big], 4, 3).unwrap();
        assert_eq!(vm2.visible, vec![2, 3]);
    }

    #[test]
    fn weighted_candidates_need_a_majority_share_and_some_mass() {
        // 1×3 image; mask 0 = pixels 0 and 1, pixel 2 unmasked.
        // Gaussian 0: all mass in the mask. Gaussian 1: 0.3 in, 0.5 out (minority).
        // Gaussian 2: in the mask but only 0.05 of mass (hidden). Gaussian 3: outside only.
        let c = ViewContrib {
            width: 3,
            height: 1,
            k: 0,
            gaussians: 4,
            lists: Contributions {
                offsets: vec![0, 3, 5, 7],
                ids: vec![0, 1, 2, 0, 1, 1, 3],
                weights: vec![0.5, 0.3, 0.05, 0.4, 0.0, 0.5, 0.9],
                residual: vec![0.0; 3],
            },
            alpha: vec![0.85, 0.4, 1.0],
            depth: vec![1.0; 3],
            median: Vec::new(),
        };
        let vm = ViewMasks {
            width: 3,
            height: 1,
            label: vec![0, 0, -1],
            visible: vec![2],
        };
        let total = view_mass(&c);
        let loose_centre = WeightedLimits {
            centre_inside: false,
            ..Default::default()
        };
        // Identity pose, fx = 1, cx = 0, cy = ½: a centre (x, 0, 1) lands in pixel ⌊x⌋ of the
        // row. Gaussians 0 and 2 project into the mask, 1 into pixel 2 (outside it), 3 behind.
        let camera = Camera {
            intrinsics: crate::camera::Intrinsics {
                width: 3,
                height: 1,
                fx: 1.0,
                fy: 1.0,
                cx: 0.0,
                cy: 0.5,
                distortion: crate::camera::Distortion::None,
            },
            pose: crate::camera::Pose {
                rotation: glam::DMat3::IDENTITY,
                translation: glam::DVec3::ZERO,
            },
        };
        let centres = [
            [0.5, 0.0, 1.0],
            [2.5, 0.0, 1.0],
            [1.5, 0.0, 1.0],
            [0.5, 0.0, -1.0],
        ];
        let cand = weighted(&c, &total, &centres, &camera, &vm, &loose_centre);
        assert_eq!(cand[0].ids, vec![0]);
        assert!((cand[0].weights[0] - 0.9).abs() < 1e-6);
        let loose = WeightedLimits {
            min_share: 0.3,
            min_mass: 0.01,
            centre_inside: false,
        };
        assert_eq!(
            weighted(&c, &total, &centres, &camera, &vm, &loose)[0].ids,
            vec![0, 1, 2]
        );
        // Centres: Gaussian 1's centre projects outside the mask.
        let strict = WeightedLimits {
            centre_inside: true,
            ..loose
        };
        assert_eq!(
            weighted(&c, &total, &centres, &camera, &vm, &strict)[0].ids,
            vec![0, 2]
        );
        // Visible: Gaussians 0 (0.9), 1 (0.8), 3 (0.9); not 2 (0.05).
        assert_eq!(visible_set(&total, 0.1), vec![0b1011]);
    }
}
