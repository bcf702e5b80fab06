//! SIMULATED CLIP-like features of the simulated SAM masks and the prompts (not CLIP): a
//! prototype per class on the unit sphere, building classes mixed towards a common building
//! direction, per-mask noise; deterministic per seed and mask. See `docs/synth.md`.
use std::collections::BTreeMap;

use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::masks::{
    FEATURE_DIM, TAG_BUILDING, TAG_FEATURE, TAG_PROMPT, TAG_PROTO, gauss, id_key, rng_for,
};
use crate::classes;
use crate::sam::Prompts;

/// The noise model of [`simulate_features`] (simulated CLIP, not CLIP).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FeatureNoise {
    /// Seed of the class prototypes and prompt vectors; keep it fixed across views so
    /// every view (and every query) shares one embedding space.
    pub prototype_seed: u64,
    /// Strength σ of a mask feature's noise: feature = normalise(prototype + σ·g/√D),
    /// g ~ N(0, I); its cosine to the prototype is then ≈ 1/√(1+σ²).
    pub noise: f64,
    /// Strength of a prompt vector's noise around its target direction (same form).
    pub prompt_noise: f64,
    /// β ∈ [0, 1]: the building classes (wall … installation) share a common "building"
    /// direction with weight √β, so their prototypes have cosine ≈ β with each other and
    /// ≈ √β with the prompt "a building"; other classes are independent random directions.
    pub building_affinity: f64,
}

impl Default for FeatureNoise {
    fn default() -> Self {
        FeatureNoise {
            prototype_seed: 0x00c1_1b5e_ed00,
            noise: 0.6,
            prompt_noise: 0.3,
            building_affinity: 0.3,
        }
    }
}

/// The prompts and the class each one targets (`None` = the shared building direction): the
/// class prompts of the pipeline ([`classes::CLASS_PROMPTS`]).
pub const PROMPTS: [(&str, Option<i32>); 14] = classes::CLASS_PROMPTS;

fn unit(v: &mut [f64]) {
    let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    if n > 0.0 {
        v.iter_mut().for_each(|x| *x /= n);
    }
}

fn random_unit(rng: &mut ChaCha8Rng) -> Vec<f64> {
    let mut v: Vec<f64> = (0..FEATURE_DIM).map(|_| gauss(rng)).collect();
    unit(&mut v);
    v
}

fn building_direction(cfg: &FeatureNoise) -> Vec<f64> {
    random_unit(&mut rng_for(cfg.prototype_seed, TAG_BUILDING, &[]))
}

/// The unit prototype of a class id (ids outside 0..=11 share the prototype of −1, "none").
pub fn class_prototype(cfg: &FeatureNoise, class: i32) -> Vec<f32> {
    to_f32(&prototype(cfg, class))
}

fn prototype(cfg: &FeatureNoise, class: i32) -> Vec<f64> {
    let c = if (0..classes::NAMES.len() as i32).contains(&class) {
        class
    } else {
        classes::NONE
    };
    let mut v = random_unit(&mut rng_for(cfg.prototype_seed, TAG_PROTO, &[id_key(c)]));
    if classes::is_building(c) {
        let beta = cfg.building_affinity.clamp(0.0, 1.0);
        let b = building_direction(cfg);
        v.iter_mut()
            .zip(&b)
            .for_each(|(x, y)| *x = (1.0 - beta).sqrt() * *x + beta.sqrt() * y);
        unit(&mut v);
    }
    v
}

fn noisy(target: &[f64], sigma: f64, rng: &mut ChaCha8Rng) -> Vec<f64> {
    let k = sigma / (FEATURE_DIM as f64).sqrt();
    let mut v: Vec<f64> = target.iter().map(|&t| t + k * gauss(rng)).collect();
    unit(&mut v);
    v
}

fn to_f32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

fn text_key(s: &str) -> u64 {
    // FNV-1a, stable across platforms and Rust versions.
    s.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Simulates CLIP image features (not CLIP): one unit vector of dimension 512 per mask,
/// `normalise(prototype[class] + noise·g/√D)`, with the mask's RNG keyed by `seed` and its
/// index; and the prompt vectors ([`PROMPTS`]), each near its class prototype (keyed by
/// `prototype_seed` and the text, so they are the same for every view).
pub fn simulate_features(
    classes: &[i32],
    cfg: &FeatureNoise,
    seed: u64,
) -> (Vec<Vec<f32>>, Prompts) {
    let mut protos: BTreeMap<i32, Vec<f64>> = BTreeMap::new();
    for &c in classes {
        protos.entry(c).or_insert_with(|| prototype(cfg, c));
    }
    let feats = classes
        .par_iter()
        .enumerate()
        .map(|(i, c)| {
            let mut rng = rng_for(seed, TAG_FEATURE, &[i as u64]);
            to_f32(&noisy(&protos[c], cfg.noise, &mut rng))
        })
        .collect();
    (feats, simulate_prompts(cfg))
}

/// The simulated prompt vectors alone (see [`simulate_features`]).
pub fn simulate_prompts(cfg: &FeatureNoise) -> Prompts {
    let prompts = PROMPTS
        .iter()
        .map(|&(text, class)| {
            let target = match class {
                Some(c) => prototype(cfg, c),
                None => building_direction(cfg),
            };
            let mut rng = rng_for(cfg.prototype_seed, TAG_PROMPT, &[text_key(text)]);
            (
                text.to_string(),
                to_f32(&noisy(&target, cfg.prompt_noise, &mut rng)),
            )
        })
        .collect();
    // Each prompt's class as the simulation knows it ("a building", the shared building
    // direction, counts as a wall: a building prompt).
    let prompt_classes = PROMPTS
        .iter()
        .map(|&(text, class)| (text.to_string(), class.unwrap_or(classes::WALL)))
        .collect();
    Prompts {
        simulated: true,
        dim: FEATURE_DIM,
        prompts,
        classes: prompt_classes,
    }
}
