//! Seconds per mask crop of `gs4city features` (CLIP through ONNX Runtime): the crop (box,
//! square, grey fill, resize, normalisation) and the image encoder at batches of 16 and 1, and
//! seconds per prompt of the text encoder, for a random-weight model of OpenAI CLIP ViT-B/32's
//! size (`scripts/make_test_models.py --clip vit_b32`: the real layer counts, widths, patch
//! size, token counts and vocabulary; compute does not depend on the weights' values). The
//! model is generated into `target/bench-models/clip_vit_b32/` on first use.
//!
//! ```text
//! cargo bench --bench features [-- --masks 32] [--threads N] [--size vit_b32|tiny]
//! ```
use std::time::Instant;

mod common;

use common::{arg, cpu_s};

use gs4city::segment::Clip;
use gs4city::segment::clip;
use ndarray::{Array2, Array3};

fn main() {
    let (h, w) = (494usize, 660usize);
    let rgb = Array3::from_shape_fn((h, w, 3), |(y, x, c)| {
        ((x * 7 + y * 3 + c * 50) % 256) as u8
    });
    let n: usize = arg("--masks").map_or(32, |v| v.parse().expect("--masks N"));
    let threads: usize = arg("--threads").map_or(0, |t| t.parse().expect("--threads N"));
    let size = arg("--size").unwrap_or_else(|| "vit_b32".into());
    // masks from 20×20 to most of the image: rectangles of growing size
    let masks: Vec<Array2<bool>> = (0..n)
        .map(|i| {
            let s = 20 + i * (h - 40) / n.max(1);
            let (y0, x0) = ((i * 37) % (h - s).max(1), (i * 53) % (w - s).max(1));
            Array2::from_shape_fn((h, w), |(y, x)| {
                (y0..y0 + s).contains(&y) && (x0..x0 + s * 4 / 3).contains(&x)
            })
        })
        .collect();
    let dir = common::model(
        &format!("clip_{size}"),
        &["--clip", &size],
        "clip_text.onnx",
    );
    let mut m = Clip::open(&dir, threads).expect("model");
    println!(
        "CLIP {size} (random weights), {n} masks on a {w}×{h} image, input {0}×{0}, ONNX Runtime threads {threads} (0 = its default)",
        m.side
    );
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("load average at start: {}", load.trim());
    let side = m.side;
    let t = Instant::now();
    let crops: Vec<Vec<f32>> = masks
        .iter()
        .map(|k| clip::crop(&rgb, k, side).expect("crop"))
        .collect();
    let crop_s = t.elapsed().as_secs_f64() / n as f64;
    // warm-up (first call allocates)
    m.embed_crops(crops[0].clone(), 1).expect("encoder");
    println!("| part | batch | s per mask crop (wall) | CPU s per crop |");
    println!("|---|---|---|---|");
    println!("| crop + resize + normalise (1 thread) | – | {crop_s:.4} | – |");
    for batch in [16usize, 1] {
        let b = m.image_batch(batch);
        let (t, c) = (Instant::now(), cpu_s());
        for chunk in crops.chunks(b) {
            let flat: Vec<f32> = chunk.iter().flatten().copied().collect();
            m.embed_crops(flat, chunk.len()).expect("encoder");
        }
        let (wall, cpu) = (t.elapsed().as_secs_f64(), cpu_s() - c);
        println!(
            "| image encoder | {b} | {:.4} | {:.3} |",
            wall / n as f64,
            cpu / n as f64
        );
    }
    let prompts = gs4city::classes::CLASS_PROMPTS;
    let (t, c) = (Instant::now(), cpu_s());
    for (p, _) in prompts {
        m.embed_text(p).expect("text encoder");
    }
    let (wall, cpu) = (t.elapsed().as_secs_f64(), cpu_s() - c);
    println!(
        "| text encoder (s per prompt, {} class prompts) | 1 | {:.4} | {:.3} |",
        prompts.len(),
        wall / prompts.len() as f64,
        cpu / prompts.len() as f64
    );
}
