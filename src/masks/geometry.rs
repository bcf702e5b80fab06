//! The geometric (model-free) evidence of the masks stage: where the pre-trained 3DGS scene
//! stands in front of, on, or behind the city-model surface, per pixel; the per-mask counts
//! over a SAM mask's run-length encoding; and the mask-free source (connected components of
//! "in front of the city model" pixels, split at depth discontinuities).
//!
//! Depths are z-depths along the camera axis in scene units: the raycast's city-model depth
//! (NaN = no hit) and the cache's expected 3DGS depth (NaN where the accumulated alpha is
//! below 1e-3). The 3DGS depth is compared with the city-model **surface** near the pixel,
//! not with the pixel's own hit alone: the local minimum and maximum of the finite city depths
//! in a `(2r+1)²` window. That absorbs a misregistration of up to `r` pixels, the blur of
//! the rendered depth across steep (grazing) depth gradients, and silhouettes; recessed
//! windows (3DGS behind the opening's polygon) are "behind" or "on the surface", never "in
//! front".
use ndarray::Array2;

use super::MasksError;
use crate::imageio;

/// No evidence: no city hit at the pixel, or no 3DGS depth.
pub const NONE: u8 = 0;
/// 3DGS within the tolerance of the local city surface.
pub const SURFACE: u8 = 1;
/// 3DGS in front of the nearest local city surface by more than the tolerance.
pub const FRONT: u8 = 2;
/// 3DGS behind the farthest local city surface by more than the tolerance.
pub const BEHIND: u8 = 3;

/// Tolerances of the depth comparison (scene units).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthTest {
    /// Absolute tolerance `τ_occ` (metres × alignment scale).
    pub tau: f32,
    /// Relative tolerance, a fraction of the city depth, added to `tau` (rendering and
    /// alignment errors grow with distance).
    pub tau_rel: f32,
    /// Window radius `r` (pixels) of the local city surface.
    pub radius: usize,
    /// Subtract each city surface's median 3DGS − city depth offset first (see [`classify`]).
    pub bias: bool,
    /// A surface needs this many pixels with both depths for its own offset (else its
    /// building's, else none).
    pub bias_min_px: usize,
    /// Offsets are clamped to `±bias_max` (scene units): a misalignment of a few decimetres
    /// moves a surface by about that much, an occluder covering most of a surface by metres.
    pub bias_max: f32,
}

impl DepthTest {
    fn tol(&self, depth: f32) -> f32 {
        self.tau + self.tau_rel * depth
    }
}

/// Sliding minimum and maximum of the finite city depths `d` (`h×w`, row-major) over
/// `(2r+1)²` windows (clamped at the border); `+∞`/`−∞` where a window holds none.
/// Separable: a row pass then a column pass, `O(h·w·r)`. Every building counts (restricting
/// the window to the centre pixel's building was measured: it turns the blur of a nearer
/// neighbour's 3DGS across a seam into false occluders, `docs/masks.md`).
pub fn local_surface(d: &[f32], h: usize, w: usize, r: usize) -> (Vec<f32>, Vec<f32>) {
    let n = h * w;
    let lo0: Vec<f32> = d
        .iter()
        .map(|&v| if v.is_finite() { v } else { f32::INFINITY })
        .collect();
    let hi0: Vec<f32> = d
        .iter()
        .map(|&v| if v.is_finite() { v } else { f32::NEG_INFINITY })
        .collect();
    if r == 0 {
        return (lo0, hi0);
    }
    let (mut lo1, mut hi1) = (vec![0f32; n], vec![0f32; n]);
    for y in 0..h {
        let row = y * w;
        for x in 0..w {
            let (a, b) = (x.saturating_sub(r), (x + r).min(w - 1));
            let (mut mn, mut mx) = (f32::INFINITY, f32::NEG_INFINITY);
            for k in a..=b {
                mn = mn.min(lo0[row + k]);
                mx = mx.max(hi0[row + k]);
            }
            lo1[row + x] = mn;
            hi1[row + x] = mx;
        }
    }
    let (mut lo, mut hi) = (vec![0f32; n], vec![0f32; n]);
    for y in 0..h {
        let (a, b) = (y.saturating_sub(r), (y + r).min(h - 1));
        for x in 0..w {
            let (mut mn, mut mx) = (f32::INFINITY, f32::NEG_INFINITY);
            for k in a..=b {
                mn = mn.min(lo1[k * w + x]);
                mx = mx.max(hi1[k * w + x]);
            }
            lo[y * w + x] = mn;
            hi[y * w + x] = mx;
        }
    }
    (lo, hi)
}

/// Median of the values of each key (`0..nkeys`) that has at least `min_px` of them (NaN for
/// the others): a counting sort by key, then a selection per key — `O(n + nkeys)`.
fn medians_by_key(items: &[(u32, f32)], nkeys: usize, min_px: usize) -> Vec<f32> {
    let mut start = vec![0usize; nkeys + 1];
    for &(k, _) in items {
        start[k as usize + 1] += 1;
    }
    for k in 0..nkeys {
        start[k + 1] += start[k];
    }
    let mut fill = start.clone();
    let mut buf = vec![0f32; items.len()];
    for &(k, v) in items {
        buf[fill[k as usize]] = v;
        fill[k as usize] += 1;
    }
    (0..nkeys)
        .map(|k| {
            let v = &mut buf[start[k]..start[k + 1]];
            if v.len() < min_px.max(1) {
                return f32::NAN;
            }
            let m = v.len() / 2;
            *v.select_nth_unstable_by(m, f32::total_cmp).1
        })
        .collect()
}

/// The per-pixel depth offset `b`: the median of `gs − city` over the pixels (with both
/// depths) of the pixel's city surface (raycast surface id; the building's id where it has
/// none), when that surface has at least `min_px` of them; else the building's median under
/// the same condition; else 0; clamped to `±max`. A rigid misalignment of the city model
/// shifts each planar surface's depth smoothly; its median absorbs most of that shift, while
/// occluders — usually a minority of a surface's pixels — stay outliers. Where an occluder
/// covers most of a surface the median is the occluder's, and the clamp keeps it from
/// swallowing it.
pub fn surface_bias(
    city: &[f32],
    gs: &[f32],
    feature: &[i32],
    surface: &[i32],
    min_px: usize,
    max: f32,
) -> Vec<f32> {
    // Ids are entity indices (≥ 0); a hit without a feature id has no offset.
    let key = |p: usize| {
        if surface[p] >= 0 {
            surface[p]
        } else {
            feature[p]
        }
    };
    let (mut by_surface, mut by_feature) = (Vec::new(), Vec::new());
    let mut nkeys = 0usize;
    for p in 0..city.len() {
        if city[p].is_finite() && gs[p].is_finite() && feature[p] >= 0 {
            let d = gs[p] - city[p];
            let k = key(p) as u32;
            by_surface.push((k, d));
            by_feature.push((feature[p] as u32, d));
            nkeys = nkeys.max(k as usize + 1).max(feature[p] as usize + 1);
        }
    }
    // Ids are entity indices, so they stay below a few times the pixel count; larger ones
    // (a damaged or foreign raycast) are renumbered densely first, so that nothing is sized
    // by an id. The medians are the same: each key keeps its values in the same order.
    let dense: Option<Vec<u32>> = (nkeys > 2 * by_surface.len() + 1024).then(|| {
        let mut d: Vec<u32> = by_surface
            .iter()
            .chain(&by_feature)
            .map(|&(k, _)| k)
            .collect();
        d.sort_unstable();
        d.dedup();
        for (k, _) in by_surface.iter_mut().chain(by_feature.iter_mut()) {
            *k = d.binary_search(k).expect("collected above") as u32;
        }
        nkeys = d.len();
        d
    });
    let index = |k: i32| match &dense {
        None => Some(k as usize),
        Some(d) => d.binary_search(&(k as u32)).ok(),
    };
    let ms = medians_by_key(&by_surface, nkeys, min_px);
    let mf = medians_by_key(&by_feature, nkeys, min_px);
    (0..city.len())
        .map(|p| {
            if feature[p] < 0 {
                return 0.0;
            }
            let s = index(key(p))
                .and_then(|i| ms.get(i))
                .copied()
                .unwrap_or(f32::NAN);
            let b = if s.is_nan() {
                index(feature[p])
                    .and_then(|i| mf.get(i))
                    .copied()
                    .unwrap_or(f32::NAN)
            } else {
                s
            };
            if b.is_nan() { 0.0 } else { b.clamp(-max, max) }
        })
        .collect()
}

/// The depth state of every pixel (row-major, `h×w`): [`NONE`], [`SURFACE`], [`FRONT`] or
/// [`BEHIND`]. A pixel has evidence when the city model is hit there and the 3DGS depth is
/// finite; the 3DGS depth (less the surface offset when `t.bias`) is compared with the
/// [`local_surface`] range widened by the tolerance.
pub fn classify(
    city: &[f32],
    gs: &[f32],
    feature: &[i32],
    surface: &[i32],
    h: usize,
    w: usize,
    t: &DepthTest,
) -> Vec<u8> {
    let (lo, hi) = local_surface(city, h, w, t.radius);
    let bias = t
        .bias
        .then(|| surface_bias(city, gs, feature, surface, t.bias_min_px, t.bias_max));
    city.iter()
        .zip(gs)
        .enumerate()
        .map(|(p, (&c, &g))| {
            if !c.is_finite() || !g.is_finite() {
                return NONE;
            }
            let g = g - bias.as_ref().map_or(0.0, |b| b[p]);
            let tol = t.tol(c);
            if g < lo[p] - tol {
                FRONT
            } else if g > hi[p] + tol {
                BEHIND
            } else {
                SURFACE
            }
        })
        .collect()
}

/// Bit of [`ViewCodes`] marking the building-support region `Ω_feat`.
const FEAT_BIT: u8 = 0b100;

/// Per pixel in **column-major** order (the order of COCO RLE runs): bit 2 = `Ω_feat`
/// (feature id ≠ −1), bits 0–1 = the depth state. Lets a mask's statistics be summed over
/// its runs without decoding it.
#[derive(Debug, Clone)]
pub struct ViewCodes {
    pub h: usize,
    pub w: usize,
    codes: Vec<u8>,
}

/// What one mask covers (pixel counts).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MaskCounts {
    pub area: u64,
    /// Pixels in `Ω_feat`.
    pub feat: u64,
    pub surface: u64,
    pub front: u64,
    pub behind: u64,
}

impl MaskCounts {
    /// `R_ov = |s ∩ Ω_feat| / |s|` (0 for an empty mask).
    pub fn r_ov(&self) -> f64 {
        ratio(self.feat, self.area)
    }
    /// Pixels with depth evidence.
    pub fn evidence(&self) -> u64 {
        self.surface + self.front + self.behind
    }
    /// Share of the evidence pixels where the 3DGS is in front of the city surface.
    pub fn front_share(&self) -> f64 {
        ratio(self.front, self.evidence())
    }
    pub fn surface_share(&self) -> f64 {
        ratio(self.surface, self.evidence())
    }
    pub fn behind_share(&self) -> f64 {
        ratio(self.behind, self.evidence())
    }
}

/// `a / b`, 0 when `b` is 0.
pub(super) fn ratio(a: u64, b: u64) -> f64 {
    if b == 0 { 0.0 } else { a as f64 / b as f64 }
}

impl ViewCodes {
    /// From the feature channel (`h×w` row-major, −1 = none) and optional depth states
    /// (row-major, from [`classify`]).
    pub fn new(feature: &[i32], states: Option<&[u8]>, h: usize, w: usize) -> ViewCodes {
        let mut codes = vec![0u8; h * w];
        for x in 0..w {
            for y in 0..h {
                let p = y * w + x;
                let mut c = if feature[p] >= 0 { FEAT_BIT } else { 0 };
                if let Some(s) = states {
                    c |= s[p];
                }
                codes[x * h + y] = c;
            }
        }
        ViewCodes { h, w, codes }
    }

    /// Sums a mask's pixels from its run lengths (zeros first, column-major; the caller has
    /// checked they sum to `h·w`).
    pub fn count(&self, runs: &[u32]) -> MaskCounts {
        let mut m = MaskCounts::default();
        let mut pos = 0usize;
        let mut hist = [0u64; 8];
        for (k, &c) in runs.iter().enumerate() {
            let c = c as usize;
            if k % 2 == 1 {
                for &code in &self.codes[pos..pos + c] {
                    hist[code as usize] += 1;
                }
            }
            pos += c;
        }
        for (code, &n) in hist.iter().enumerate() {
            let code = code as u8;
            m.area += n;
            if code & FEAT_BIT != 0 {
                m.feat += n;
            }
            match code & 0b11 {
                SURFACE => m.surface += n,
                FRONT => m.front += n,
                BEHIND => m.behind += n,
                _ => {}
            }
        }
        m
    }
}

/// Parameters of the mask-free source.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ComponentParams {
    /// Pixels need at least this 3DGS accumulated alpha.
    pub min_alpha: f32,
    /// Two 8-neighbours are split when their 3DGS depths differ by more than
    /// `max(tau, split_rel · nearer depth)`.
    pub split_rel: f32,
    pub tau: f32,
    /// Components smaller than this (pixels) are dropped.
    pub min_area: usize,
    /// Radius of the morphological opening (erode, then dilate; OpenCV, elliptical kernel)
    /// applied to the candidate pixels first: strips thinner than about `2·open_px` pixels —
    /// the 3DGS spilling a few pixels over a nearer city-model silhouette at close range —
    /// vanish. 0 = none.
    pub open_px: usize,
}

/// One component of the mask-free source: its pixels as a window at `(y0, x0)`.
#[derive(Debug, Clone, PartialEq)]
pub struct Component {
    pub y0: usize,
    pub x0: usize,
    pub window: Array2<bool>,
    pub area: usize,
}

/// The mask-free source: 8-connected components (OpenCV) of the [`FRONT`] pixels with enough
/// alpha, split at 3DGS depth discontinuities. Of every 8-neighbour pair across a
/// discontinuity the farther pixel is held out before labelling (so no 8-path crosses one);
/// held-out pixels then join the neighbouring component whose depth is continuous with
/// theirs and nearest (one raster pass over the labels of the first step). Components in
/// OpenCV's label order (raster order of their first pixel); those under `min_area` dropped.
pub fn components(
    states: &[u8],
    gs: &[f32],
    alpha: &[f32],
    h: usize,
    w: usize,
    p: &ComponentParams,
) -> Result<Vec<Component>, MasksError> {
    let n = h * w;
    let mut fg: Vec<bool> = (0..n)
        .map(|i| states[i] == FRONT && alpha[i] >= p.min_alpha && gs[i].is_finite())
        .collect();
    if p.open_px > 0 {
        let m = Array2::from_shape_vec((h, w), fg.clone()).expect("h·w values");
        let opened = imageio::dilate(&imageio::erode(&m, p.open_px)?, p.open_px)?;
        for (f, o) in fg.iter_mut().zip(opened.iter()) {
            *f &= *o;
        }
    }
    let jump = |a: f32, b: f32| (a - b).abs() > p.tau.max(p.split_rel * a.min(b));
    let mut held = vec![false; n];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if !fg[i] {
                continue;
            }
            // Right, down-left, down, down-right: every 8-pair once.
            let nb = [
                (x + 1 < w).then(|| i + 1),
                (y + 1 < h && x > 0).then(|| i + w - 1),
                (y + 1 < h).then(|| i + w),
                (y + 1 < h && x + 1 < w).then(|| i + w + 1),
            ];
            for j in nb.into_iter().flatten() {
                if fg[j] && jump(gs[i], gs[j]) {
                    let far = if gs[i] > gs[j] { i } else { j };
                    held[far] = true;
                }
            }
        }
    }
    let core = Array2::from_shape_fn((h, w), |(y, x)| {
        let i = y * w + x;
        u8::from(fg[i] && !held[i])
    });
    let (labels, _) = imageio::connected_components(&core).map_err(|e| MasksError::Invalid {
        path: "<connected components>".into(),
        why: e.to_string(),
    })?;
    let mut lab: Vec<i32> = labels.iter().copied().collect();
    let first = lab.clone();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if !(fg[i] && held[i]) {
                continue;
            }
            let mut best: Option<(f32, i32)> = None;
            for dy in -1i64..=1 {
                for dx in -1i64..=1 {
                    let (yy, xx) = (y as i64 + dy, x as i64 + dx);
                    if (dy, dx) == (0, 0) || yy < 0 || xx < 0 || yy >= h as i64 || xx >= w as i64 {
                        continue;
                    }
                    let j = yy as usize * w + xx as usize;
                    if first[j] > 0 && !jump(gs[i], gs[j]) {
                        let d = (gs[i] - gs[j]).abs();
                        if best.is_none_or(|(bd, bl)| d < bd || (d == bd && first[j] < bl)) {
                            best = Some((d, first[j]));
                        }
                    }
                }
            }
            if let Some((_, l)) = best {
                lab[i] = l;
            }
        }
    }
    let nl = lab.iter().copied().max().unwrap_or(0).max(0) as usize;
    // Bounding boxes and areas.
    let mut bb = vec![(usize::MAX, usize::MAX, 0usize, 0usize, 0usize); nl + 1];
    for y in 0..h {
        for x in 0..w {
            let l = lab[y * w + x];
            if l > 0 {
                let b = &mut bb[l as usize];
                b.0 = b.0.min(y);
                b.1 = b.1.min(x);
                b.2 = b.2.max(y);
                b.3 = b.3.max(x);
                b.4 += 1;
            }
        }
    }
    let mut out = Vec::new();
    for (l, &(y0, x0, y1, x1, area)) in bb.iter().enumerate().skip(1) {
        if area == 0 || area < p.min_area {
            continue;
        }
        let window = Array2::from_shape_fn((y1 - y0 + 1, x1 - x0 + 1), |(yy, xx)| {
            lab[(y0 + yy) * w + x0 + xx] == l as i32
        });
        out.push(Component {
            y0,
            x0,
            window,
            area,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute-force window minimum/maximum.
    fn brute(d: &[f32], h: usize, w: usize, r: usize) -> (Vec<f32>, Vec<f32>) {
        let mut lo = vec![f32::INFINITY; h * w];
        let mut hi = vec![f32::NEG_INFINITY; h * w];
        for y in 0..h {
            for x in 0..w {
                for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
                    for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                        let v = d[yy * w + xx];
                        if v.is_finite() {
                            lo[y * w + x] = lo[y * w + x].min(v);
                            hi[y * w + x] = hi[y * w + x].max(v);
                        }
                    }
                }
            }
        }
        (lo, hi)
    }

    #[test]
    fn local_surface_equals_brute_force_with_nans() {
        let (h, w) = (7, 9);
        let d: Vec<f32> = (0..h * w)
            .map(|i| {
                if i % 5 == 0 || (20..26).contains(&i) {
                    f32::NAN
                } else {
                    ((i * 37) % 23) as f32 * 0.5
                }
            })
            .collect();
        for r in 0..4 {
            assert_eq!(local_surface(&d, h, w, r), brute(&d, h, w, r), "r {r}");
        }
    }

    fn test(radius: usize, bias: bool) -> DepthTest {
        DepthTest {
            tau: 0.5,
            tau_rel: 0.0,
            radius,
            bias,
            bias_min_px: 3,
            bias_max: 2.0,
        }
    }

    #[test]
    fn states_against_the_local_surface() {
        // A wall at 10 m whose right half is a recessed window at 10.15 m; one pixel column
        // without a city hit; 3DGS: on the wall, 1 m in front, on the window, 0.15 m behind
        // the window's polygon, no hit, 1.5 m behind.
        let (h, w) = (1, 6);
        let city = [10.0, 10.0, 10.15, 10.15, f32::NAN, 10.0];
        let gs = [10.05, 9.0, 10.15, 10.3, 8.0, 11.5];
        let f = [0, 0, 0, 0, -1, 0];
        let s = [1, 1, 1, 1, -1, 1];
        assert_eq!(
            classify(&city, &gs, &f, &s, h, w, &test(1, false)),
            vec![SURFACE, FRONT, SURFACE, SURFACE, NONE, BEHIND]
        );
        // A relative tolerance of 10 % makes the 1 m offset "on the surface".
        let tr = DepthTest {
            tau_rel: 0.1,
            ..test(1, false)
        };
        assert_eq!(classify(&city, &gs, &f, &s, h, w, &tr)[1], SURFACE);
    }

    #[test]
    fn the_surface_offset_absorbs_a_misalignment_but_not_an_occluder() {
        // A misaligned roof: the 3DGS lies 1 m in front of the city surface everywhere, and a
        // tree 4 m in front over two of its eight pixels.
        let (h, w) = (1, 8);
        let city = [20.0f32; 8];
        let mut gs = [19.0f32; 8];
        gs[5] = 16.0;
        gs[6] = 16.0;
        let f = [0; 8];
        let s = [3; 8];
        let without = classify(&city, &gs, &f, &s, h, w, &test(0, false));
        assert!(without.iter().all(|&v| v == FRONT));
        let with = classify(&city, &gs, &f, &s, h, w, &test(0, true));
        assert_eq!(
            with,
            vec![
                SURFACE, SURFACE, SURFACE, SURFACE, SURFACE, FRONT, FRONT, SURFACE
            ]
        );
        // Offsets per surface, the building's for a small surface, none under the minimum.
        let s2 = [3, 3, 3, 3, 3, 3, 4, 4];
        let b = surface_bias(&city, &gs, &f, &s2, 3, 2.0);
        assert_eq!(b, vec![-1.0; 8]);
        let b = surface_bias(&city, &gs, &f, &s2, 9, 2.0);
        assert_eq!(b, vec![0.0; 8]);
        // A tree covering six of eight pixels: the median is the tree's (−4), clamped to −2,
        // so the tree stays in front (16 − (−2) = 18 < 20 − 0.5).
        let mut gs2 = [16.0f32; 8];
        gs2[0] = 20.0;
        gs2[1] = 20.0;
        let b = surface_bias(&city, &gs2, &f, &s, 3, 2.0);
        assert_eq!(b, vec![-2.0; 8]);
        let st = classify(&city, &gs2, &f, &s, h, w, &test(0, true));
        assert_eq!(st[2..], [FRONT; 6]);
    }

    #[test]
    fn huge_ids_give_the_offsets_of_small_ones_without_sizing_anything_by_them() {
        // Two surfaces of one building, six pixels each with depth offsets; one surface's pixels
        // are too few on their own (min 5), so they take the building's median.
        let n = 12;
        let city = vec![20.0f32; n];
        let gs: Vec<f32> = (0..n).map(|i| 20.0 + (i % 5) as f32 * 0.3 - 0.6).collect();
        let small_f = vec![1i32; n];
        let small_s: Vec<i32> = (0..n).map(|i| if i < 8 { 4 } else { 6 }).collect();
        // The same partition under ids near i32::MAX (a damaged raycast would hold these).
        let big = |k: i32| i32::MAX - 10 + k;
        let big_f: Vec<i32> = small_f.iter().map(|&k| big(k)).collect();
        let big_s: Vec<i32> = small_s.iter().map(|&k| big(k)).collect();
        let want = surface_bias(&city, &gs, &small_f, &small_s, 5, 2.0);
        let got = surface_bias(&city, &gs, &big_f, &big_s, 5, 2.0);
        assert_eq!(got, want);
        // Surface 4 has its own median (8 pixels), surface 6 the building's (4 < 5 pixels).
        let mut own: Vec<f32> = gs[..8].iter().map(|g| g - 20.0).collect();
        own.sort_by(f32::total_cmp);
        let mut all: Vec<f32> = gs.iter().map(|g| g - 20.0).collect();
        all.sort_by(f32::total_cmp);
        assert_eq!(want[0], own[4]);
        assert_eq!(want[11], all[6]);
    }

    #[test]
    fn counts_over_runs_equal_counts_over_pixels() {
        let (h, w) = (5, 4);
        let feature: Vec<i32> = (0..h * w)
            .map(|i| if i % 3 == 0 { 7 } else { -1 })
            .collect();
        let states: Vec<u8> = (0..h * w).map(|i| (i % 4) as u8).collect();
        let codes = ViewCodes::new(&feature, Some(&states), h, w);
        let mask = Array2::from_shape_fn((h, w), |(y, x)| (y * 3 + x * 5) % 4 != 0);
        let rle = crate::sam::Rle::encode(&mask);
        let c = codes.count(&rle.counts().unwrap());
        let mut e = MaskCounts::default();
        for y in 0..h {
            for x in 0..w {
                if mask[[y, x]] {
                    let p = y * w + x;
                    e.area += 1;
                    e.feat += u64::from(feature[p] >= 0);
                    match states[p] {
                        SURFACE => e.surface += 1,
                        FRONT => e.front += 1,
                        BEHIND => e.behind += 1,
                        _ => {}
                    }
                }
            }
        }
        assert_eq!(c, e);
    }

    #[test]
    fn components_split_at_depth_jumps_and_regrow_held_pixels() {
        // Two objects in front of a wall touching each other: a person at 5 m (left) and a
        // car at 8 m (right); plus a one-pixel speck dropped by the area filter.
        let (h, w) = (4, 8);
        let mut states = vec![SURFACE; h * w];
        let mut gs = vec![20.0f32; h * w];
        for y in 0..3 {
            for x in 0..6 {
                states[y * w + x] = FRONT;
                gs[y * w + x] = if x < 3 { 5.0 } else { 8.0 };
            }
        }
        states[3 * w + 7] = FRONT;
        gs[3 * w + 7] = 9.0;
        let alpha = vec![1.0f32; h * w];
        let p = ComponentParams {
            min_alpha: 0.5,
            split_rel: 0.1,
            tau: 0.5,
            min_area: 2,
            open_px: 0,
        };
        let c = components(&states, &gs, &alpha, h, w, &p).unwrap();
        assert_eq!(c.len(), 2, "{c:?}");
        assert_eq!(
            (c[0].y0, c[0].x0, c[0].window.dim(), c[0].area),
            (0, 0, (3, 3), 9)
        );
        // The car's first column was held out (farther side of the jump) and regrown.
        assert_eq!(
            (c[1].y0, c[1].x0, c[1].window.dim(), c[1].area),
            (0, 3, (3, 3), 9)
        );
        assert!(c[1].window.iter().all(|&v| v));
    }
}
