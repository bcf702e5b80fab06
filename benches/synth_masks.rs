//! Time of the mask and feature simulation (`gs4city::synth::masks`) on a 1920×1080 view with
//! 1 208 instances: 8 walls side by side, each with 10×15 windows (docs/sam.md).
//!
//! ```text
//! cargo bench --bench synth_masks
//! ```
use std::time::Instant;

use gs4city::classes;
use gs4city::synth::masks::{FeatureNoise, MaskNoise, simulate_features, simulate_masks};
use ndarray::{Array2, s};

fn main() {
    let (h, w) = (1080, 1920);
    let mut inst = Array2::from_elem((h, w), -1);
    let mut cls = Array2::from_elem((h, w), classes::NONE);
    let mut id = 0;
    for b in 0..8 {
        let x0 = b * 240;
        inst.slice_mut(s![100..1000, x0..x0 + 230]).fill(id);
        cls.slice_mut(s![100..1000, x0..x0 + 230])
            .fill(classes::WALL);
        id += 1;
        for r in 0..15 {
            for c in 0..10 {
                let (y, x) = (120 + r * 58, x0 + 8 + c * 22);
                inst.slice_mut(s![y..y + 40, x..x + 16]).fill(id);
                cls.slice_mut(s![y..y + 40, x..x + 16])
                    .fill(classes::WINDOW);
                id += 1;
            }
        }
    }
    let t = Instant::now();
    let out = simulate_masks(inst.view(), cls.view(), &MaskNoise::default(), 1);
    let dt = t.elapsed();
    let t = Instant::now();
    let (f, _) = simulate_features(
        &out.iter().map(|m| m.class).collect::<Vec<_>>(),
        &FeatureNoise::default(),
        1,
    );
    println!(
        "{id} instances → {} masks in {:.3} s; {} features in {:.3} s",
        out.len(),
        dt.as_secs_f64(),
        f.len(),
        t.elapsed().as_secs_f64()
    );
}
