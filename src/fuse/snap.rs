//! City-part snapping (beyond the paper). A SAM mask that the masks stage dropped because it
//! lies on a building, and that is dominated by one city part (a window or a door), is the
//! image's own pixel-accurate outline of that part. Where the raycast outline of the part
//! disagrees with it (misalignment, recessed openings), the mask's pixels take the part's id
//! and the part's raycast pixels outside its snapped masks fall back to the parent surface.
//!
//! Limits ([`SnapLimits`], each a guard against a failure seen or expected):
//! * quality: `predicted_iou ≥ 0.7` (the masks stage's own threshold; sloppy masks would move
//!   outlines the wrong way);
//! * on the building: at least 80 % of the mask on the raycast building support (the
//!   filter's `ρ`), so masks of trees or cars are never snapped;
//! * one part: ≥ 30 % of the mask on its dominant part, ≤ 25 % on any other part (a mask
//!   spanning two windows, or a wall mask with windows, is not a part's outline);
//! * comparable size: mask area / the part's raycast area in the view within [1/3, 3];
//! * disagreement: only where the IoU of mask and raycast part is below 0.75 — where they agree
//!   closely the raycast outline is kept (it is exact under perfect alignment, while SAM outlines
//!   carry a pixel or two of boundary noise);
//! * pixels: only pixels on the part's own building (raycast feature channel) that no image
//!   group covers (image priority) are relabelled.
use std::collections::{BTreeMap, HashSet};

use serde::{Deserialize, Serialize};

use crate::classes;
use crate::sam::SamMask;

/// Limits of the snapping (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SnapLimits {
    pub min_quality: f64,
    pub min_building_share: f64,
    pub min_part_share: f64,
    pub max_other_part_share: f64,
    pub area_ratio: [f64; 2],
    pub max_iou: f64,
}

impl Default for SnapLimits {
    fn default() -> Self {
        SnapLimits {
            min_quality: 0.7,
            min_building_share: 0.8,
            min_part_share: 0.3,
            max_other_part_share: 0.25,
            area_ratio: [1.0 / 3.0, 3.0],
            max_iou: 0.75,
        }
    }
}

/// Counts of one view's (or a run's) snapping.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct SnapStats {
    /// Dropped masks on a building with a window/door as dominant part.
    pub considered: usize,
    /// Masks snapped.
    pub snapped: usize,
    /// Masks where raycast and mask agreed (IoU ≥ max_iou): nothing to fix.
    pub agreed: usize,
    /// Pixels relabelled to a part.
    pub pixels_to_part: u64,
    /// Part pixels outside every snapped mask of the part, relabelled to the parent surface.
    pub pixels_to_surface: u64,
}

impl SnapStats {
    /// Adds another's counts.
    pub fn add(&mut self, o: &SnapStats) {
        self.considered += o.considered;
        self.snapped += o.snapped;
        self.agreed += o.agreed;
        self.pixels_to_part += o.pixels_to_part;
        self.pixels_to_surface += o.pixels_to_surface;
    }
}

/// The raycast channels snapping reads (row-major H×W each).
pub struct RayChannels<'a> {
    pub feature: &'a [i32],
    pub surface: &'a [i32],
    pub part: &'a [i32],
}

/// Per entity (indexed by entity id): its class and its building.
pub struct Entities<'a> {
    pub class: &'a [i32],
    pub building: &'a [i32],
}

/// Snaps one view: `fused` is changed in place where `group` (the associate map) is −1.
/// `sam` is the view's SAM list, `kept` the source indices the masks stage kept.
pub fn snap_view(
    fused: &mut [i32],
    group: &[i32],
    ray: &RayChannels<'_>,
    sam: &[SamMask],
    kept: &HashSet<i64>,
    ents: &Entities<'_>,
    lim: &SnapLimits,
) -> SnapStats {
    let (class, building) = (ents.class, ents.building);
    let mut st = SnapStats::default();
    let ent = |id: i32, t: &[i32]| -> i32 {
        usize::try_from(id)
            .ok()
            .and_then(|i| t.get(i))
            .copied()
            .unwrap_or(-1)
    };
    let mut part_area: BTreeMap<i32, u64> = BTreeMap::new();
    for &p in ray.part {
        if p >= 0 {
            *part_area.entry(p).or_insert(0) += 1;
        }
    }
    // (part, pixels) of every accepted mask.
    let mut accepted: Vec<(i32, Vec<u32>)> = Vec::new();
    let mut px: Vec<u32> = Vec::new();
    for (i, m) in sam.iter().enumerate() {
        if kept.contains(&(i as i64)) || m.predicted_iou < lim.min_quality {
            continue;
        }
        px.clear();
        if m.segmentation
            .for_each_pixel(|p| px.push(p as u32))
            .is_err()
            || px.is_empty()
        {
            continue;
        }
        let n = px.len() as f64;
        let on_building = px.iter().filter(|&&p| ray.feature[p as usize] >= 0).count();
        if (on_building as f64) < lim.min_building_share * n {
            continue;
        }
        let mut hist: BTreeMap<i32, u64> = BTreeMap::new();
        for &p in &px {
            let q = ray.part[p as usize];
            if q >= 0 {
                *hist.entry(q).or_insert(0) += 1;
            }
        }
        // Dominant part (most pixels, ties: the smaller id) and the runner-up.
        let mut best = (-1i32, 0u64);
        let mut second = 0u64;
        for (&q, &c) in &hist {
            if c > best.1 {
                second = best.1;
                best = (q, c);
            } else if c > second {
                second = c;
            }
        }
        let (p, c) = best;
        if p < 0 || !matches!(ent(p, class), classes::WINDOW | classes::DOOR) {
            continue;
        }
        st.considered += 1;
        let area = part_area.get(&p).copied().unwrap_or(0) as f64;
        let ratio = n / area.max(1.0);
        let iou = c as f64 / (n + area - c as f64);
        if (c as f64) < lim.min_part_share * n
            || (second as f64) > lim.max_other_part_share * n
            || ratio < lim.area_ratio[0]
            || ratio > lim.area_ratio[1]
        {
            continue;
        }
        if iou >= lim.max_iou {
            st.agreed += 1;
            continue;
        }
        st.snapped += 1;
        accepted.push((p, px.clone()));
    }
    if accepted.is_empty() {
        return st;
    }
    // Larger masks first, smaller on top (as the association composites).
    accepted.sort_by(|a, b| b.1.len().cmp(&a.1.len()).then(a.0.cmp(&b.0)));
    let mut snapped_to: Vec<i32> = vec![-1; fused.len()];
    let parts: HashSet<i32> = accepted.iter().map(|a| a.0).collect();
    for (p, pixels) in &accepted {
        let b = ent(*p, building);
        for &q in pixels {
            let q = q as usize;
            if group[q] >= 0 || ent(ray.feature[q], building) != b {
                continue;
            }
            if fused[q] != *p {
                st.pixels_to_part += 1;
            }
            fused[q] = *p;
            snapped_to[q] = *p;
        }
    }
    for q in 0..fused.len() {
        let p = ray.part[q];
        if p >= 0 && parts.contains(&p) && snapped_to[q] != p && group[q] < 0 && fused[q] == p {
            let s = ray.surface[q];
            fused[q] = if s >= 0 { s } else { ray.feature[q] };
            st.pixels_to_surface += 1;
        }
    }
    st
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sam::SamMask;
    use ndarray::Array2;

    /// A 10×20 view: building 0 everywhere, wall surface 1, window part 2 raycast at columns
    /// 4..8 of rows 3..7; the image's window mask sits two columns to the right (6..10).
    fn view() -> (Vec<i32>, Vec<i32>, Vec<i32>, Vec<SamMask>) {
        let (h, w) = (10, 20);
        let feature = vec![0; h * w];
        let surface = vec![1; h * w];
        let mut part = vec![-1; h * w];
        let mut mask = Array2::from_elem((h, w), false);
        for y in 3..7 {
            for x in 4..8 {
                part[y * w + x] = 2;
            }
            for x in 6..10 {
                mask[[y, x]] = true;
            }
        }
        let sam = vec![SamMask::from_mask(&mask, 0.9, 0.95, vec![])];
        (feature, surface, part, sam)
    }

    #[test]
    fn a_shifted_window_mask_moves_the_window() {
        let (feature, surface, part, sam) = view();
        let (h, w) = (10, 20);
        let city: Vec<i32> = (0..h * w)
            .map(|q| if part[q] >= 0 { part[q] } else { surface[q] })
            .collect();
        let mut fused = city.clone();
        let group = vec![-1; h * w];
        // Entities: 0 building, 1 wall, 2 window.
        let class = [classes::WALL, classes::WALL, classes::WINDOW];
        let building = [0, 0, 0];
        let ray = RayChannels {
            feature: &feature,
            surface: &surface,
            part: &part,
        };
        let st = snap_view(
            &mut fused,
            &group,
            &ray,
            &sam,
            &HashSet::new(),
            &Entities {
                class: &class,
                building: &building,
            },
            &SnapLimits::default(),
        );
        // IoU = 8 / 24 = 0.33 < 0.6: snapped. 8 pixels become window, 8 fall back to wall.
        assert_eq!(st.snapped, 1);
        assert_eq!((st.pixels_to_part, st.pixels_to_surface), (8, 8));
        for y in 0..h {
            for x in 0..w {
                let expect = if (3..7).contains(&y) && (6..10).contains(&x) {
                    2
                } else {
                    1
                };
                assert_eq!(fused[y * w + x], expect, "pixel ({y}, {x})");
            }
        }
        // Kept by the filter, or covered by an image group: nothing moves.
        let mut f2 = city.clone();
        let kept: HashSet<i64> = [0].into_iter().collect();
        let st = snap_view(
            &mut f2,
            &group,
            &ray,
            &sam,
            &kept,
            &Entities {
                class: &class,
                building: &building,
            },
            &SnapLimits::default(),
        );
        assert_eq!((st.considered, f2 == city), (0, true));
        let mut f3 = city.clone();
        let covered = vec![0; h * w];
        snap_view(
            &mut f3,
            &covered,
            &ray,
            &sam,
            &HashSet::new(),
            &Entities {
                class: &class,
                building: &building,
            },
            &SnapLimits::default(),
        );
        assert_eq!(f3, city);
        // A window mask that agrees with the raycast (IoU 1) is left alone.
        let mut aligned = Array2::from_elem((h, w), false);
        for y in 3..7 {
            for x in 4..8 {
                aligned[[y, x]] = true;
            }
        }
        let sam2 = vec![SamMask::from_mask(&aligned, 0.9, 0.95, vec![])];
        let mut f4 = city.clone();
        let st = snap_view(
            &mut f4,
            &group,
            &ray,
            &sam2,
            &HashSet::new(),
            &Entities {
                class: &class,
                building: &building,
            },
            &SnapLimits::default(),
        );
        assert_eq!((st.agreed, st.snapped), (1, 0));
        assert_eq!(f4, city);
    }
}
