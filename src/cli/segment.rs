//! `gs4city segment`: SAM-family automatic masks of a scene's images on the CPU → `S/masks/`.
use std::path::PathBuf;

use clap::Args;

use crate::segment::{self, SegmentOptions};

#[derive(Debug, Args)]
pub struct SegmentArgs {
    /// Scene folder: reads images/, writes masks/<stem>.json (an image whose file exists is skipped).
    #[arg(long)]
    scene: PathBuf,
    /// Model folder: encoder.onnx, decoder.onnx, model.json (docs/segment.md).
    #[arg(long)]
    model: PathBuf,
    #[command(flatten)]
    config: super::groups::ConfigArg,
    #[command(flatten, next_help_heading = "Segmentation (config [segment])")]
    tuning: super::groups::SegmentTuning,
}

impl SegmentArgs {
    /// Validated options.
    pub fn options(&self) -> anyhow::Result<SegmentOptions> {
        super::groups::merged(&self.config.load()?.segment, &self.tuning).options()
    }
}

pub fn run(args: &SegmentArgs) -> anyhow::Result<()> {
    let o = args.options()?;
    let t = std::time::Instant::now();
    let s = segment::run(&args.scene, &args.model, &o)?;
    crate::progress::done(
        "segment",
        &format!(
            "{} images segmented ({} masks), {} skipped (masks exist); encoder {:.1} s, decoder {:.1} s ({}), post-processing {:.1} s",
            s.segmented,
            s.masks,
            s.skipped,
            s.timings.encoder_s,
            s.timings.decoder_s,
            if s.decoder.is_empty() {
                "-"
            } else {
                &s.decoder
            },
            s.timings.post_s
        ),
        t.elapsed().as_secs_f64(),
    );
    Ok(())
}
