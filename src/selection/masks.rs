//! Per-view masks of a selection, through the contributions cache.
//!
//! **The rule** ([`MaskRule::Argmax`], the default): the selected labels count as *one* label in
//! the same per-pixel argmax that makes the predicted maps ([`crate::cache::predict`]): a pixel is
//! selected when the summed weight `Σ α·T` of the selected Gaussians in its cached list exceeds
//! the weight of every other single label and the weight of "nothing" (the transmittance
//! `1 − α`, the truncated mass of the top-k list and the unlabelled Gaussians). A one-label
//! selection therefore gives the pixels whose predicted label is that label (up to exact ties,
//! which the predicted map gives to the smaller label id).
//! [`MaskRule::Majority`] (FlashSplat's novel-view masks) instead needs the selected weight to
//! exceed half the pixel: `Σ_sel w > 1 − Σ_sel w`.

use ndarray::Array3;
use serde::{Deserialize, Serialize};

use crate::cache::ViewContrib;

/// How a pixel is decided (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MaskRule {
    /// The selection beats every other label and "nothing" (the predicted-map rule).
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

/// The label id standing for the whole selection in the argmax (above every real id).
const SELECTED: i32 = i32::MAX;

/// The per-Gaussian labels with every selected Gaussian relabelled as one label.
pub fn merged_labels(label_of: &[i32], selected: &[bool]) -> Vec<i32> {
    label_of
        .iter()
        .zip(selected)
        .map(|(&l, &s)| if s { SELECTED } else { l })
        .collect()
}

/// The mask (1 = selected) of one cached view. `merged` comes from [`merged_labels`] (argmax),
/// `selected` is the per-Gaussian selection (majority).
pub fn view_mask(c: &ViewContrib, merged: &[i32], selected: &[bool], rule: MaskRule) -> Vec<u8> {
    match rule {
        MaskRule::Argmax => crate::cache::predict_map(c, merged)
            .iter()
            .map(|&l| u8::from(l == SELECTED))
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
        }
    }

    #[test]
    fn argmax_and_majority_rules_by_hand() {
        let c = view();
        let label = [1, 2, 3, -1];
        let sel = |s: [bool; 4]| {
            let m = merged_labels(&label, &s);
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
        // A one-label selection equals "predicted label == that label".
        let (_, predicted) = crate::cache::predict(&c, &label, &label);
        for l in [1, 2, 3] {
            let s = [label[0] == l, label[1] == l, label[2] == l, false];
            let want: Vec<u8> = predicted.iter().map(|&p| u8::from(p == l)).collect();
            assert_eq!(sel(s).0, want, "label {l}");
        }
    }
}
