//! Seconds per 660×494 image of `gs4city segment` (SAM automatic mask generation through ONNX
//! Runtime): encoder, decoder and post-processing at 16×16 and 32×32 point grids, for
//! random-weight models of MobileSAM size and SAM ViT-B size (`scripts/make_test_models.py`:
//! the real layer counts, widths, token counts and windows; compute does not depend on the
//! weights' values). The models are generated into `target/bench-models/` on first use.
//!
//! ```text
//! cargo bench --bench segment [-- --image PATH.png] [--sizes mobilesam,vit_b,mobilesam-b1] [--grids 16,32] [--threads N]
//! ```

mod common;

use common::{arg, cpu_s};
use gs4city::imageio;
use gs4city::segment::{SegmentOptions, Segmenter};

fn main() {
    let rgb = match arg("--image") {
        Some(p) => imageio::read_rgb(std::path::Path::new(&p)).expect("image"),
        None => ndarray::Array3::from_shape_fn((494, 660, 3), |(y, x, c)| {
            ((x * 7 + y * 3 + c * 50) % 256) as u8
        }),
    };
    let (h, w, _) = rgb.dim();
    let sizes = arg("--sizes").unwrap_or_else(|| "mobilesam,vit_b".into());
    let grids = arg("--grids").unwrap_or_else(|| "16,32".into());
    let threads: usize = arg("--threads").map_or(0, |t| t.parse().expect("--threads N"));
    println!("image {w}×{h}, scale 0.25, ONNX Runtime threads {threads} (0 = its default)");
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("load average at start: {}", load.trim());
    println!(
        "| model | grid | encoder s | decoder s | post-processing s | total s (wall) | CPU s | masks |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for size in sizes.split(',') {
        // `NAME-b1`: the same network with SAM's own export's fixed batch of 1 (one prompt per
        // decoder call, decoded by single-threaded workers side by side)
        let (net, fixed) = match size.strip_suffix("-b1") {
            Some(n) => (n, true),
            None => (size, false),
        };
        let mut gen_args = vec!["--size", net];
        if fixed {
            gen_args.push("--fixed-batch");
        }
        let dir = common::model(size, &gen_args, "model.json");
        let mut seg = Segmenter::open(&dir, threads).expect("model");
        // which decoder runs (a fallback to ONNX Runtime changes the timings by 2–3×)
        match &seg.native_note {
            None => eprintln!("{size}: decoder native"),
            Some(why) => eprintln!("{size}: decoder onnxruntime ({why})"),
        }
        for grid in grids.split(',') {
            let o = SegmentOptions {
                points_per_side: grid.parse().expect("grid"),
                threads,
                ..SegmentOptions::default()
            };
            let (t, c) = (std::time::Instant::now(), cpu_s());
            let (masks, tm) = seg.segment(&rgb, &o).expect("segment");
            let (total, cpu) = (t.elapsed().as_secs_f64(), cpu_s() - c);
            println!(
                "| {size} (random weights) | {grid}×{grid} | {:.2} | {:.2} | {:.2} | {total:.2} | {cpu:.1} | {} |",
                tm.encoder_s,
                tm.decoder_s,
                tm.post_s,
                masks.len()
            );
        }
    }
}
