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
use rayon::prelude::*;
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

/// The smallest class (≥ 0) among the selected Gaussians, 0 when there is none: the class
/// whose place the selection takes in the argmax (module docs).
fn smallest_class(class_of: &[i32], selected: &[bool]) -> i32 {
    class_of
        .iter()
        .zip(selected)
        .filter(|(c, s)| **s && **c >= 0)
        .map(|(&c, _)| c)
        .min()
        .unwrap_or(0)
}

/// Selections decided side by side per list entry (one lane each), and per packed key.
const LANES: usize = 16;

/// Selections whose per-view masks are computed together (either rule, module docs): per
/// Gaussian its class and one bit per selection, packed once, so that [`Selections::masks`]
/// reads each list entry's key once for all the masks.
pub struct Selections {
    /// Per group of [`LANES`] selections, per Gaussian: the class in the high 32 bits, bit `k`
    /// set when the group's selection `k` holds the Gaussian.
    keys: Vec<Vec<u64>>,
    /// Each selection's smallest class ([`smallest_class`]).
    smallest: Vec<i32>,
}

impl Selections {
    /// The selections `selected` (each as long as `class_of`).
    pub fn new(class_of: &[i32], selected: &[&[bool]]) -> Selections {
        let keys = selected
            .chunks(LANES)
            .map(|group| {
                (0..class_of.len())
                    .map(|g| {
                        let bits = group
                            .iter()
                            .enumerate()
                            .filter(|(_, s)| s[g])
                            .fold(0u64, |b, (k, _)| b | 1 << k);
                        (u64::from(class_of[g] as u32) << 32) | bits
                    })
                    .collect()
            })
            .collect();
        let smallest = selected
            .iter()
            .map(|s| smallest_class(class_of, s))
            .collect();
        Selections { keys, smallest }
    }

    /// The masks (1 = selected) of one cached view under `rule`, in the order of the
    /// selections.
    ///
    /// [`MaskRule::Argmax`]: a pixel is selected when its selected weight `T` (summed in list
    /// order, as the class maps sum a class, [`crate::cache::predict`]) exists, exceeds
    /// "nothing" (`1 − α`, the residual and the unclassified unselected Gaussians) and beats
    /// the unselected weight of every other class `c` present, a tie going to the selection
    /// when its smallest class `m ≤ c`: exactly the class maps' rule with the selection as one
    /// class in the place of `m`. [`MaskRule::Majority`]: `T > 1 − T` (summed in `f64`).
    pub fn masks(&self, c: &ViewContrib, rule: MaskRule) -> Vec<Vec<u8>> {
        const CHUNK: usize = 4096;
        let count = self.smallest.len();
        let npx = c.pixels();
        let mut out = vec![vec![0u8; npx]; count];
        if count == 0 {
            return out;
        }
        // Per task, CHUNK pixels of every mask, pixel-major (`p·count + k`).
        let mut flat = vec![0u8; npx * count];
        flat.par_chunks_mut(CHUNK * count)
            .enumerate()
            .for_each(|(i, chunk)| {
                let mut pixel = PixelScratch::default();
                for (j, px) in chunk.chunks_mut(count).enumerate() {
                    let p = i * CHUNK + j;
                    let (ids, ws) = c.pixel(p);
                    let rest = 1.0 - c.alpha[p] + c.lists.residual[p];
                    pixel.classes.clear();
                    pixel.entries.clear();
                    for &g in ids {
                        let class = (self.keys[0][g as usize] >> 32) as u32 as i32;
                        let slot = match pixel.classes.iter().position(|&x| x == class) {
                            Some(s) => s,
                            None => {
                                pixel.classes.push(class);
                                pixel.classes.len() - 1
                            }
                        };
                        pixel.entries.push((g, class, slot));
                    }
                    for ((o, m), keys) in px
                        .chunks_mut(LANES)
                        .zip(self.smallest.chunks(LANES))
                        .zip(&self.keys)
                    {
                        match rule {
                            MaskRule::Argmax => pixel.argmax(keys, ws, rest, m, o),
                            MaskRule::Majority => pixel.majority(keys, ws, o),
                        }
                    }
                }
            });
        for (p, px) in flat.chunks(count).enumerate() {
            for (mask, &x) in out.iter_mut().zip(px) {
                mask[p] = x;
            }
        }
        out
    }
}

/// One pixel's entries and sums in [`Selections::masks`].
#[derive(Default)]
struct PixelScratch {
    /// The pixel's distinct classes, in order of first appearance.
    classes: Vec<i32>,
    /// Per entry: Gaussian, class, slot of the class in `classes`.
    entries: Vec<(u32, i32, usize)>,
    /// Per class slot and lane: the unselected weight of the class, and whether any.
    sums: Vec<([f32; LANES], u32)>,
}

impl PixelScratch {
    /// The argmax masks of one key group's selections at this pixel (`m`: their smallest
    /// classes): per lane (one selection each) the selected weight `t`, the unclassified
    /// unselected weight and each class's unselected weight, each summed in list order (a
    /// lane adds only its own entries); then the rule of [`Selections::masks`].
    fn argmax(&mut self, keys: &[u64], ws: &[f32], rest: f32, m: &[i32], out: &mut [u8]) {
        let (mut t, mut background) = ([0.0f32; LANES], [-0.0f32; LANES]);
        let mut has_t = 0u32;
        self.sums.clear();
        self.sums.resize(self.classes.len(), ([0.0; LANES], 0));
        for (&(g, class, slot), &w) in self.entries.iter().zip(ws) {
            let bits = keys[g as usize] as u32;
            has_t |= bits;
            for (lane, x) in t.iter_mut().enumerate() {
                *x = if bits >> lane & 1 == 1 { *x + w } else { *x };
            }
            let other = if class < 0 {
                &mut background
            } else {
                self.sums[slot].1 |= !bits;
                &mut self.sums[slot].0
            };
            for (lane, x) in other.iter_mut().enumerate() {
                *x = if bits >> lane & 1 == 0 { *x + w } else { *x };
            }
        }
        for (lane, (o, &m)) in out.iter_mut().zip(m).enumerate() {
            let t = t[lane];
            let beats = |(&(ref u, present), &class): (&([f32; LANES], u32), &i32)| {
                let u = u[lane];
                present >> lane & 1 == 0 || u < t || (u == t && m <= class)
            };
            let wins = has_t >> lane & 1 == 1
                && t > rest + background[lane]
                && self.sums.iter().zip(&self.classes).all(beats);
            *o = u8::from(wins);
        }
    }

    /// The majority masks of one key group's selections at this pixel: the selected weight
    /// summed in `f64` in list order, selected when it exceeds the rest of the pixel.
    fn majority(&self, keys: &[u64], ws: &[f32], out: &mut [u8]) {
        let mut t = [0.0f64; LANES];
        for (&(g, _, _), &w) in self.entries.iter().zip(ws) {
            let bits = keys[g as usize] as u32;
            for (lane, x) in t.iter_mut().enumerate() {
                *x = if bits >> lane & 1 == 1 {
                    *x + f64::from(w)
                } else {
                    *x
                };
            }
        }
        for (o, &t) in out.iter_mut().zip(&t) {
            *o = u8::from(t > 1.0 - t);
        }
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

    /// One selection's mask through [`Selections`].
    fn mask(c: &ViewContrib, class_of: &[i32], s: &[bool], rule: MaskRule) -> Vec<u8> {
        Selections::new(class_of, &[s]).masks(c, rule).remove(0)
    }

    /// The argmax rule's reference: the class maps' own rule ([`crate::cache::predict_map`])
    /// over merged values (an unselected Gaussian of class `c` is `2c + 1`, an unclassified one
    /// −1, a selected one `2m` with `m` the selection's smallest class); a pixel is selected
    /// when its value is `2m`.
    fn argmax_by_class_maps(c: &ViewContrib, class_of: &[i32], s: &[bool]) -> Vec<u8> {
        let m = class_of
            .iter()
            .zip(s)
            .filter(|(c, s)| **s && **c >= 0)
            .map(|(&c, _)| c)
            .min()
            .unwrap_or(0);
        let merged: Vec<i32> = class_of
            .iter()
            .zip(s)
            .map(|(&c, &s)| match (s, c) {
                (true, _) => 2 * m,
                (false, c) if c < 0 => -1,
                (false, c) => 2 * c + 1,
            })
            .collect();
        let map = crate::cache::predict_map(c, &merged);
        map.iter().map(|&l| u8::from(l == 2 * m)).collect()
    }

    /// The majority rule's reference, pixel by pixel.
    fn majority_by_pixels(c: &ViewContrib, s: &[bool]) -> Vec<u8> {
        (0..c.pixels())
            .map(|p| {
                let (ids, ws) = c.pixel(p);
                let t: f64 = ids
                    .iter()
                    .zip(ws)
                    .filter(|(g, _)| s[**g as usize])
                    .map(|(_, &w)| f64::from(w))
                    .sum();
                u8::from(t > 1.0 - t)
            })
            .collect()
    }

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

    /// A random view: `w × h` pixels, lists of 0–40 distinct Gaussians of `n`, weights from a
    /// small set (many exact ties), α and residuals from small sets.
    fn random_view(w: usize, h: usize, n: usize, rng: &mut impl rand::Rng) -> ViewContrib {
        let (mut offsets, mut ids, mut weights, mut residual, mut alpha) =
            (vec![0u64], Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for _ in 0..w * h {
            let len = rng.random_range(0..=40.min(n));
            let mut seen = std::collections::BTreeSet::new();
            while seen.len() < len {
                let g = rng.random_range(0..n as u32);
                if seen.insert(g) {
                    ids.push(g);
                    weights.push([0.125f32, 0.25, 0.1, 0.3, 0.05, 0.0][rng.random_range(0..6)]);
                }
            }
            offsets.push(ids.len() as u64);
            residual.push([0.0f32, 0.05, 0.25][rng.random_range(0..3)]);
            alpha.push([1.0f32, 0.9, 0.5, 0.0][rng.random_range(0..4)]);
        }
        ViewContrib {
            width: w,
            height: h,
            k: 0,
            gaussians: n,
            lists: Contributions {
                offsets,
                ids,
                weights,
                residual,
            },
            alpha,
            depth: vec![1.0; w * h],
            median: Vec::new(),
        }
    }

    #[test]
    fn masks_together_follow_the_class_maps_and_the_majority_pixel_by_pixel() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for (n, count) in [(7usize, 3usize), (60, 9), (300, 40), (50, 0)] {
            // 77 × 61 pixels: more than one task of `masks`, the last one partial; 40 selections
            // fill three key groups, the last one partly.
            let c = random_view(77, 61, n, &mut rng);
            // Classes −1..=11 (a few unclassified Gaussians).
            let class_of: Vec<i32> = (0..n).map(|_| rng.random_range(-1..12)).collect();
            // Selections: a random share each, one empty, one of everything, one of a class.
            let selected: Vec<Vec<bool>> = (0..count)
                .map(|k| match k % 5 {
                    0 => vec![false; n],
                    1 => vec![true; n],
                    2 => class_of.iter().map(|&x| x == 3).collect(),
                    _ => {
                        let p = rng.random_range(0.05..0.6);
                        (0..n).map(|_| rng.random_bool(p)).collect()
                    }
                })
                .collect();
            let refs: Vec<&[bool]> = selected.iter().map(Vec::as_slice).collect();
            let set_of = Selections::new(&class_of, &refs);
            let argmax = set_of.masks(&c, MaskRule::Argmax);
            let majority = set_of.masks(&c, MaskRule::Majority);
            assert_eq!((argmax.len(), majority.len()), (count, count));
            let mut set = 0;
            for (k, s) in selected.iter().enumerate() {
                let want = argmax_by_class_maps(&c, &class_of, s);
                assert_eq!(argmax[k], want, "argmax, n {n}, selection {k}");
                assert_eq!(
                    majority[k],
                    majority_by_pixels(&c, s),
                    "majority, n {n}, selection {k}"
                );
                set += want.iter().filter(|&&x| x == 1).count();
            }
            assert!(
                count == 0 || set > 0,
                "no pixel selected at all: a weak test"
            );
        }
    }

    #[test]
    fn argmax_and_majority_rules_by_hand() {
        let c = view();
        let label = [1, 2, 3, -1];
        let sel = |s: [bool; 4]| {
            (
                mask(&c, &label, &s, MaskRule::Argmax),
                mask(&c, &label, &s, MaskRule::Majority),
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
            let got = mask(&c, &class, &s, MaskRule::Argmax);
            let want: Vec<u8> = map.iter().map(|&p| u8::from(p == k)).collect();
            assert_eq!(got, want, "class {k}");
        }
    }
}
