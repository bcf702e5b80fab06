//! Per-view masks of a selection, through the contributions cache.
//!
//! **The rule** ([`MaskRule::Argmax`], the default) is the per-pixel rule of the class maps
//! ([`crate::cache::predict_map`] over the Gaussians' classes): the selected Gaussians count as
//! *one* class, every other Gaussian keeps its class, and a pixel is selected when the summed
//! weight `Σ α·T` of the selected Gaussians in its cached list exceeds the weight of every other
//! class and the weight of "nothing" (the transmittance `1 − α`, the truncated mass of the
//! top-k list and the unclassified Gaussians). A class selection (`query --class Window`)
//! therefore gives exactly the pixels of that class in the class maps of the same run, ties
//! included: the selection takes the place of the smallest class among its Gaussians.
//! [`MaskRule::Majority`] (FlashSplat's novel-view masks) instead needs the selected weight to
//! exceed half the pixel: `Σ_sel w > 1 − Σ_sel w`.

use ndarray::Array3;
use serde::{Deserialize, Serialize};

use crate::cache::ViewContrib;

/// How a pixel is decided (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MaskRule {
    /// The selection beats every other class and "nothing" (the class maps' rule).
    #[default]
    Argmax,
    /// The selection holds more than half of the pixel.
    Majority,
}

impl std::str::FromStr for MaskRule {
    type Err = String;
    fn from_str(s: &str) -> Result<MaskRule, String> {
        match s {
            "argmax" => Ok(MaskRule::Argmax),
            "majority" => Ok(MaskRule::Majority),
            _ => Err(format!("{s:?} is not one of argmax, majority")),
        }
    }
}

/// The per-Gaussian values of the argmax: class `c` of an unselected Gaussian becomes `2c + 1`
/// (−1 stays −1, "nothing"), every selected Gaussian becomes `2m`, where `m` is the smallest
/// class (≥ 0) among them. The order of the values is the order of the classes, so ties are
/// decided as in the class maps (to the smaller class). Returns the values and the selection's.
pub fn merged_values(class_of: &[i32], selected: &[bool]) -> (Vec<i32>, i32) {
    let m = class_of
        .iter()
        .zip(selected)
        .filter(|(c, s)| **s && **c >= 0)
        .map(|(&c, _)| c)
        .min()
        .unwrap_or(0);
    let values = class_of
        .iter()
        .zip(selected)
        .map(|(&c, &s)| match (s, c) {
            (true, _) => 2 * m,
            (false, c) if c < 0 => -1,
            (false, c) => 2 * c + 1,
        })
        .collect();
    (values, 2 * m)
}

/// The mask (1 = selected) of one cached view. `merged` comes from [`merged_values`] (argmax),
/// `selected` is the per-Gaussian selection (majority).
pub fn view_mask(
    c: &ViewContrib,
    merged: &(Vec<i32>, i32),
    selected: &[bool],
    rule: MaskRule,
) -> Vec<u8> {
    match rule {
        MaskRule::Argmax => crate::cache::predict_map(c, &merged.0)
            .iter()
            .map(|&l| u8::from(l == merged.1))
            .collect(),
        MaskRule::Majority => (0..c.pixels())
            .map(|p| {
                let (ids, ws) = c.pixel(p);
                let s: f64 = ids
                    .iter()
                    .zip(ws)
                    .filter(|(g, _)| selected[**g as usize])
                    .map(|(_, &w)| f64::from(w))
                    .sum();
                u8::from(s > 1.0 - s)
            })
            .collect(),
    }
}

/// An overlay of `mask` on `image` (H×W×3; `None`: a grey background): selected pixels tinted
/// red at 50 %, the rest dimmed to 60 %.
pub fn overlay(mask: &[u8], width: usize, height: usize, image: Option<&Array3<u8>>) -> Array3<u8> {
    let colour = |p: usize| (mask[p] != 0).then_some([255, 40, 40]);
    crate::imageio::blend_overlay(image, height, width, 96.0, 0.5, 0.6, colour)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache::Contributions;

    /// Three pixels, Gaussians 0..4 with labels [1, 2, 3, −1].
    fn view() -> ViewContrib {
        ViewContrib {
            width: 3,
            height: 1,
            k: 4,
            gaussians: 4,
            lists: Contributions {
                // p0: g0 0.4, g1 0.35 (alpha 0.9 → nothing 0.1 + residual 0.05)
                // p1: g0 0.31, g1 0.3, g2 0.29 (alpha 0.95)
                // p2: g0 0.2, g3 0.5 (alpha 0.8)
                offsets: vec![0, 2, 5, 7],
                ids: vec![0, 1, 0, 1, 2, 0, 3],
                weights: vec![0.4, 0.35, 0.31, 0.3, 0.29, 0.2, 0.5],
                residual: vec![0.05, 0.05, 0.1],
            },
            alpha: vec![0.9, 0.95, 0.8],
            depth: vec![1.0; 3],
            median: Vec::new(),
        }
    }

    #[test]
    fn argmax_and_majority_rules_by_hand() {
        let c = view();
        let label = [1, 2, 3, -1];
        let sel = |s: [bool; 4]| {
            let m = merged_values(&label, &s);
            (
                view_mask(&c, &m, &s, MaskRule::Argmax),
                view_mask(&c, &m, &s, MaskRule::Majority),
            )
        };
        // Label 1 alone: p0 0.4 > 0.35, 0.15 → 1; p1 0.31 > 0.3, 0.29, 0.1 → 1; p2: 0.2 vs
        // nothing 0.2 + 0.1 + 0.5 (unlabelled g3) → 0. Majority: 0.4 < 0.6, 0.31 < 0.69 → 0.
        assert_eq!(
            sel([true, false, false, false]),
            (vec![1, 1, 0], vec![0, 0, 0])
        );
        // Labels 1 and 2: p0 0.75 → 1/1; p1 0.61 → 1, majority 0.61 > 0.39 → 1; p2 → 0.
        assert_eq!(
            sel([true, true, false, false]),
            (vec![1, 1, 0], vec![1, 1, 0])
        );
        // Nothing selected: empty masks.
        assert_eq!(sel([false; 4]), (vec![0, 0, 0], vec![0, 0, 0]));
        // A one-class selection equals "predicted class == that class".
        let (predicted, _) = crate::cache::predict(&c, &label, &label);
        for l in [1, 2, 3] {
            let s = [label[0] == l, label[1] == l, label[2] == l, false];
            let want: Vec<u8> = predicted.iter().map(|&p| u8::from(p == l)).collect();
            assert_eq!(sel(s).0, want, "class {l}");
        }
    }

    #[test]
    fn a_class_selection_is_the_class_map_ties_and_several_labels_included() {
        // Pixel 0: g0 (class 2) 0.3, g1 (class 1) 0.3 — a tie, the class map takes 1.
        // Pixel 1: g2 and g3, two labels of class 3, 0.45 each.
        let c = ViewContrib {
            width: 2,
            height: 1,
            k: 4,
            gaussians: 4,
            lists: Contributions {
                offsets: vec![0, 2, 4],
                ids: vec![0, 1, 2, 3],
                weights: vec![0.3, 0.3, 0.45, 0.45],
                residual: vec![0.0, 0.0],
            },
            alpha: vec![0.9, 0.95],
            depth: vec![1.0; 2],
            median: Vec::new(),
        };
        let class = [2, 1, 3, 3];
        let (map, _) = crate::cache::predict(&c, &[0, 1, 2, 3], &class);
        assert_eq!(map, vec![1, 3]);
        for k in [1, 2, 3] {
            let s: Vec<bool> = class.iter().map(|&x| x == k).collect();
            let got = view_mask(&c, &merged_values(&class, &s), &s, MaskRule::Argmax);
            let want: Vec<u8> = map.iter().map(|&p| u8::from(p == k)).collect();
            assert_eq!(got, want, "class {k}");
        }
    }
}
