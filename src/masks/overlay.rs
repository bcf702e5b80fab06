//! Overlay PNGs of the masks stage: the view's image in darkened grey, with every kept mask
//! filled in the colour of the rule that kept it and outlined in white (blue `low_overlap`,
//! orange `features_foreground`, red `occluder`, magenta `occluder_and_features`, green
//! `depth_component`).
use std::path::Path;

use ndarray::Array3;

use super::MasksError;
use crate::imageio;
use crate::maskfile::{KeptMask, Rule};

/// Colour of a keep rule (grey for a dropping rule).
pub fn rule_color(rule: Rule) -> [u8; 3] {
    match rule {
        Rule::LowOverlap => [60, 140, 230],
        Rule::FeaturesForeground => [240, 160, 40],
        Rule::Occluder => [230, 40, 40],
        Rule::OccluderAndFeatures => [220, 60, 220],
        Rule::DepthComponent => [40, 200, 80],
        _ => [160, 160, 160],
    }
}

/// Draws `kept` over `image` (or black when there is none) and writes the PNG.
pub fn write(
    path: &Path,
    image: Option<Array3<u8>>,
    h: usize,
    w: usize,
    kept: &[KeptMask],
) -> Result<(), MasksError> {
    // The image in darkened grey, so that the rule colours stand out.
    let mut out = Array3::<u8>::zeros((h, w, 3));
    if let Some(img) = image.filter(|i| i.dim() == (h, w, 3)) {
        for y in 0..h {
            for x in 0..w {
                let l = 0.299 * img[[y, x, 0]] as f32
                    + 0.587 * img[[y, x, 1]] as f32
                    + 0.114 * img[[y, x, 2]] as f32;
                let g = (l * 0.55) as u8;
                for c in 0..3 {
                    out[[y, x, c]] = g;
                }
            }
        }
    }
    // Large masks first, so small ones stay visible on top.
    let mut order: Vec<usize> = (0..kept.len()).collect();
    order.sort_by_key(|&i| (std::cmp::Reverse(kept[i].sam.area), i));
    for i in order {
        let k = &kept[i];
        let m = k
            .sam
            .segmentation
            .decode()
            .map_err(|e| MasksError::Invalid {
                path: path.to_path_buf(),
                why: format!("kept mask {i}: {e}"),
            })?;
        let c = rule_color(k.rule);
        for ((y, x), &on) in m.indexed_iter() {
            if !on {
                continue;
            }
            let edge = y == 0
                || x == 0
                || y + 1 == h
                || x + 1 == w
                || !m[[y - 1, x]]
                || !m[[y + 1, x]]
                || !m[[y, x - 1]]
                || !m[[y, x + 1]];
            for ch in 0..3 {
                out[[y, x, ch]] = if edge {
                    255
                } else {
                    (out[[y, x, ch]] as f32 * 0.35 + c[ch] as f32 * 0.65) as u8
                };
            }
        }
    }
    imageio::write_png(path, &out).map_err(|e| MasksError::Invalid {
        path: path.to_path_buf(),
        why: e.to_string(),
    })
}
