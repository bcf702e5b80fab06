//! The post-processing of SAM's automatic mask generation (`SamAutomaticMaskGenerator`, one
//! crop): the point grid, the stability score, mask boxes, greedy box NMS and the removal of
//! small holes and islands. Pure functions on binary masks; docs/segment.md states each rule.
use ndarray::Array2;

use crate::imageio::{self, ImageError};

/// SAM's point grid: `n × n` cell centres in `[0, 1]²`, `x` fastest (`build_point_grid`).
pub fn point_grid(n: usize) -> Vec<[f64; 2]> {
    let side = linspace(0.5 / n as f64, 1.0 - 0.5 / n as f64, n);
    let mut out = Vec::with_capacity(n * n);
    for &y in &side {
        for &x in &side {
            out.push([x, y]);
        }
    }
    out
}

/// `numpy.linspace(a, b, n)` (start + i·step, the last value exactly `b`).
fn linspace(a: f64, b: f64, n: usize) -> Vec<f64> {
    if n == 1 {
        return vec![a];
    }
    let step = (b - a) / (n - 1) as f64;
    let mut v: Vec<f64> = (0..n).map(|i| a + i as f64 * step).collect();
    v[n - 1] = b;
    v
}

/// The stability score of mask logits: `#(logit > offset) / #(logit > −offset)` (threshold 0),
/// 0 when no logit exceeds `−offset`.
pub fn stability_score(logits: &[f32], offset: f32) -> f64 {
    let (mut inter, mut union) = (0u64, 0u64);
    for &l in logits {
        inter += u64::from(l > offset);
        union += u64::from(l > -offset);
    }
    if union == 0 {
        0.0
    } else {
        inter as f64 / union as f64
    }
}

/// SAM's box of a row-major `h × w` mask: `[x0, y0, x1, y1]` with inclusive maxima; all zero
/// for an empty mask.
pub fn mask_box(mask: &[bool], h: usize, w: usize) -> [f64; 4] {
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for y in 0..h {
        let row = &mask[y * w..(y + 1) * w];
        if let Some(first) = row.iter().position(|&b| b) {
            let last = row.iter().rposition(|&b| b).unwrap_or(first);
            y0 = y0.min(y);
            y1 = y;
            x0 = x0.min(first);
            x1 = x1.max(last);
        }
    }
    if y0 == usize::MAX {
        return [0.0; 4];
    }
    [x0 as f64, y0 as f64, x1 as f64, y1 as f64]
}

/// Greedy non-maximum suppression: boxes in order of decreasing score (ties by index); a box
/// whose IoU with a kept box exceeds `thresh` is dropped. Box area is `(x1 − x0)·(y1 − y0)`
/// (torchvision's); a pair with an empty union never suppresses. Returns the kept indices in
/// the order kept.
pub fn nms(boxes: &[[f64; 4]], scores: &[f64], thresh: f64) -> Vec<usize> {
    let mut order: Vec<usize> = (0..boxes.len()).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    let area = |b: &[f64; 4]| (b[2] - b[0]) * (b[3] - b[1]);
    let mut dead = vec![false; boxes.len()];
    let mut keep = Vec::new();
    for (k, &i) in order.iter().enumerate() {
        if dead[i] {
            continue;
        }
        keep.push(i);
        let a = &boxes[i];
        for &j in &order[k + 1..] {
            if dead[j] {
                continue;
            }
            let b = &boxes[j];
            let iw = (a[2].min(b[2]) - a[0].max(b[0])).max(0.0);
            let ih = (a[3].min(b[3]) - a[1].max(b[1])).max(0.0);
            let inter = iw * ih;
            let union = area(a) + area(b) - inter;
            if union > 0.0 && inter / union > thresh {
                dead[j] = true;
            }
        }
    }
    keep
}

/// Removes the 8-connected regions smaller than `min_area` pixels: holes (`holes`: small
/// components of the background are filled) or islands (small components of the mask are
/// cleared; when every island is small, the largest stays). Returns the mask and whether it
/// changed.
pub fn remove_small_regions(
    mask: &Array2<bool>,
    min_area: usize,
    holes: bool,
) -> Result<(Array2<bool>, bool), ImageError> {
    let work = mask.mapv(|b| u8::from(b != holes));
    let (labels, areas) = imageio::connected_components(&work)?;
    let small: Vec<bool> = areas
        .iter()
        .enumerate()
        .map(|(i, &a)| i > 0 && a < min_area)
        .collect();
    if !small.iter().any(|&s| s) {
        return Ok((mask.clone(), false));
    }
    if holes {
        let out = ndarray::Zip::from(mask)
            .and(&labels)
            .map_collect(|&m, &l| m || small[l as usize]);
        return Ok((out, true));
    }
    let mut keep: Vec<bool> = small
        .iter()
        .enumerate()
        .map(|(i, &s)| i > 0 && !s)
        .collect();
    if !keep.iter().any(|&k| k) {
        // every island is small: keep the largest (the first of equal ones)
        let mut best = 1;
        for i in 1..areas.len() {
            if areas[i] > areas[best] {
                best = i;
            }
        }
        keep[best] = true;
    }
    Ok((labels.mapv(|l| keep[l as usize]), true))
}

/// Nearest-neighbour upscaling of a row-major `h × w` mask to `big_h × big_w`: output pixel
/// `(y, x)` takes source pixel `(⌊y·h / big_h⌋, ⌊x·w / big_w⌋)`.
pub fn upscale_nearest(
    mask: &[bool],
    h: usize,
    w: usize,
    big_h: usize,
    big_w: usize,
) -> Array2<bool> {
    let xs: Vec<usize> = (0..big_w).map(|x| x * w / big_w).collect();
    Array2::from_shape_fn((big_h, big_w), |(y, x)| mask[(y * h / big_h) * w + xs[x]])
}

/// One axis of SAM's export post-processing as a linear map from the 256 low-resolution
/// logits: bilinear to 1024 (half-pixel centres, coordinates clamped to the edges), the first
/// `pre` of those, bilinear to `out`. Entry `o` lists `(low index, weight)`.
#[derive(Debug, Clone)]
pub struct AxisMap(Vec<Vec<(usize, f32)>>);

/// The two taps of a half-pixel bilinear resize from `n_in` to `n_out` at output `o`.
fn taps(n_in: usize, n_out: usize, o: usize) -> [(usize, f64); 2] {
    let src = ((o as f64 + 0.5) * n_in as f64 / n_out as f64 - 0.5).max(0.0);
    let i0 = (src.floor() as usize).min(n_in - 1);
    let i1 = (i0 + 1).min(n_in - 1);
    let w = if i0 == n_in - 1 { 0.0 } else { src - i0 as f64 };
    [(i0, 1.0 - w), (i1, w)]
}

impl AxisMap {
    /// The map of one axis: `low` logits → 1024 → the first `pre` → `out` values.
    pub fn new(low: usize, pre: usize, out: usize) -> AxisMap {
        const FRAME: usize = 1024;
        AxisMap(
            (0..out)
                .map(|o| {
                    let mut taps_out: Vec<(usize, f32)> = Vec::with_capacity(4);
                    for (m, wm) in taps(pre, out, o) {
                        for (l, wl) in taps(low, FRAME, m) {
                            let w = (wm * wl) as f32;
                            match taps_out.iter_mut().find(|(i, _)| *i == l) {
                                Some(t) => t.1 += w,
                                None => taps_out.push((l, w)),
                            }
                        }
                    }
                    taps_out
                })
                .collect(),
        )
    }
}

/// SAM's export post-processing of one low-resolution mask (`low × low` logits, row-major):
/// the `rows.len() × cols.len()` logits at the image size ([`AxisMap`] per axis).
pub fn upscale_logits(lowres: &[f32], low: usize, rows: &AxisMap, cols: &AxisMap) -> Vec<f32> {
    let w = cols.0.len();
    let mut tmp = vec![0f32; low * w];
    for (r, row) in lowres.chunks_exact(low).enumerate() {
        for (x, taps) in cols.0.iter().enumerate() {
            tmp[r * w + x] = taps.iter().map(|&(i, t)| row[i] * t).sum();
        }
    }
    let mut out = vec![0f32; rows.0.len() * w];
    for (y, taps) in rows.0.iter().enumerate() {
        let dst = &mut out[y * w..(y + 1) * w];
        for &(r, t) in taps {
            for (d, s) in dst.iter_mut().zip(&tmp[r * w..(r + 1) * w]) {
                *d += s * t;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_is_cell_centres_x_fastest() {
        let g = point_grid(2);
        assert_eq!(
            g,
            vec![[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]]
        );
        assert_eq!(point_grid(1), vec![[0.5, 0.5]]);
    }

    /// The per-axis maps equal the two resizes done one after the other on whole images
    /// (PyTorch's / ONNX Runtime's bilinear, half-pixel centres, source coordinates clamped).
    #[test]
    fn upscale_equals_two_full_resizes() {
        fn resize(src: &[f64], h: usize, w: usize, oh: usize, ow: usize) -> Vec<f64> {
            let coord = |o: usize, n_in: usize, n_out: usize| {
                let s = ((o as f64 + 0.5) * n_in as f64 / n_out as f64 - 0.5).max(0.0);
                let i0 = (s.floor() as usize).min(n_in - 1);
                (i0, (i0 + 1).min(n_in - 1), s - s.floor())
            };
            let mut out = vec![0.0; oh * ow];
            for y in 0..oh {
                let (y0, y1, fy) = coord(y, h, oh);
                for x in 0..ow {
                    let (x0, x1, fx) = coord(x, w, ow);
                    let top = src[y0 * w + x0] * (1.0 - fx) + src[y0 * w + x1] * fx;
                    let bot = src[y1 * w + x0] * (1.0 - fx) + src[y1 * w + x1] * fx;
                    out[y * ow + x] = top * (1.0 - fy) + bot * fy;
                }
            }
            out
        }
        let low = 8;
        let lowres: Vec<f32> = (0..low * low)
            .map(|i| ((i * 37 % 23) as f32 - 11.0) * 0.7)
            .collect();
        let big = resize(
            &lowres.iter().map(|&v| f64::from(v)).collect::<Vec<_>>(),
            low,
            low,
            1024,
            1024,
        );
        for (pre_h, pre_w, h, w) in [
            (700, 1024, 90, 130),
            (1024, 1024, 37, 37),
            (1024, 300, 400, 117),
        ] {
            let cropped: Vec<f64> = (0..pre_h)
                .flat_map(|y| big[y * 1024..y * 1024 + pre_w].to_vec())
                .collect();
            let want = resize(&cropped, pre_h, pre_w, h, w);
            let got = upscale_logits(
                &lowres,
                low,
                &AxisMap::new(low, pre_h, h),
                &AxisMap::new(low, pre_w, w),
            );
            assert_eq!(got.len(), h * w);
            for (k, (a, b)) in got.iter().zip(&want).enumerate() {
                assert!(
                    (f64::from(*a) - b).abs() < 1e-4,
                    "{pre_h}×{pre_w}→{h}×{w} at {k}: {a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn stability_by_hand() {
        // > 1: 2 values; > -1: 4 values
        assert_eq!(stability_score(&[3.0, 1.5, 0.0, -0.5, -2.0], 1.0), 0.5);
        assert_eq!(stability_score(&[-3.0], 1.0), 0.0);
    }

    #[test]
    fn nms_by_hand() {
        // boxes 0 and 1 overlap with IoU 81/100 (> 0.7), box 2 is apart
        let b = [
            [0.0, 0.0, 10.0, 10.0],
            [1.0, 1.0, 10.0, 10.0],
            [20.0, 20.0, 30.0, 30.0],
        ];
        assert_eq!(nms(&b, &[0.5, 0.9, 0.7], 0.7), vec![1, 2]);
        assert_eq!(nms(&b, &[0.5, 0.9, 0.7], 0.9), vec![1, 2, 0]);
    }

    #[test]
    fn small_regions_by_hand() {
        // a 5×5 block with a one-pixel hole, and a one-pixel island far away
        let mut m = Array2::from_elem((8, 8), false);
        for y in 0..5 {
            for x in 0..5 {
                m[[y, x]] = true;
            }
        }
        m[[2, 2]] = false;
        m[[7, 7]] = true;
        let (filled, changed) = remove_small_regions(&m, 2, true).unwrap();
        assert!(changed && filled[[2, 2]] && filled[[7, 7]]);
        let (clean, changed) = remove_small_regions(&filled, 2, false).unwrap();
        assert!(changed && !clean[[7, 7]] && clean[[0, 0]]);
        assert_eq!(clean.iter().filter(|&&b| b).count(), 25);
        let (same, changed) = remove_small_regions(&clean, 2, false).unwrap();
        assert!(!changed && same == clean);
    }

    #[test]
    fn nearest_upscale_by_hand() {
        let m = [true, false, false, true];
        let big = upscale_nearest(&m, 2, 2, 3, 4);
        assert_eq!(big.row(0).to_vec(), vec![true, true, false, false]);
        assert_eq!(big.row(1).to_vec(), vec![true, true, false, false]);
        assert_eq!(big.row(2).to_vec(), vec![false, false, true, true]);
        assert_eq!(
            mask_box(&[false, true, false, true], 2, 2),
            [1.0, 0.0, 1.0, 1.0]
        );
    }
}
