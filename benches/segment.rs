//! Seconds per 660×494 image of `gs4city segment` (SAM automatic mask generation through ONNX
//! Runtime): encoder, decoder and post-processing at 16×16 and 32×32 point grids, for
//! random-weight models of MobileSAM size and SAM ViT-B size (`scripts/make_test_models.py`:
//! the real layer counts, widths, token counts and windows; compute does not depend on the
//! weights' values). The models are generated into `target/bench-models/` on first use.
//!
//! ```text
//! cargo bench --bench segment [-- --image PATH.png] [--sizes mobilesam,vit_b] [--grids 16,32] [--threads N]
//! ```
use std::path::{Path, PathBuf};
use std::process::Command;

use gs4city::imageio;
use gs4city::segment::{SegmentOptions, Segmenter};

fn arg(name: &str) -> Option<String> {
    let a: Vec<String> = std::env::args().collect();
    a.iter()
        .position(|x| x == name)
        .and_then(|i| a.get(i + 1).cloned())
}

fn model(size: &str) -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = root.join("target/bench-models").join(size);
    if !dir.join("model.json").is_file() {
        eprintln!(
            "generating the random-weight {size} model in {}",
            dir.display()
        );
        let ok = Command::new("python3")
            .arg(root.join("scripts/make_test_models.py"))
            .args(["--size", size, "--out"])
            .arg(&dir)
            .status()
            .expect("python3");
        assert!(ok.success(), "make_test_models.py failed");
    }
    dir
}

/// CPU seconds (user + system, all threads) of this process so far, from /proc/self/stat.
fn cpu_s() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // fields 14 and 15 of stat (utime, stime) are items 11 and 12 after the command name
    (ticks(11) + ticks(12)) / 100.0
}

fn main() {
    let rgb = match arg("--image") {
        Some(p) => imageio::read_rgb(Path::new(&p)).expect("image"),
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
        let dir = model(size);
        let mut seg = Segmenter::open(&dir, threads).expect("model");
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
