//! `gs4city features`: CLIP features of a scene's SAM masks on the CPU → `S/features/`.
use std::path::PathBuf;

use clap::Args;

use crate::segment::{FeaturesOptions, features};

#[derive(Debug, Args)]
pub struct FeaturesArgs {
    /// Scene folder: reads images/ and masks/<stem>.json, writes features/<stem>.npy (an image
    /// whose complete file exists is skipped) and, last, features/prompts.json.
    #[arg(long)]
    scene: PathBuf,
    /// Model folder: clip_image.onnx, clip_text.onnx, vocab.json + merges.txt (docs/features.md).
    #[arg(long)]
    model: PathBuf,
    /// A text file of prompts to embed besides the class prompts: one per line (`#` comments).
    #[arg(long, value_name = "FILE")]
    prompts: Option<PathBuf>,
    /// Mask crops per image-encoder call.
    #[arg(long, default_value_t = FeaturesOptions::default().batch)]
    batch: usize,
    /// ONNX Runtime threads (0 = its default).
    #[arg(long, default_value_t = 0)]
    threads: usize,
}

impl FeaturesArgs {
    /// Validated options.
    pub fn options(&self) -> anyhow::Result<FeaturesOptions> {
        let prompts = match &self.prompts {
            Some(p) => features::read_prompt_lines(p)?,
            None => Vec::new(),
        };
        let o = FeaturesOptions {
            batch: self.batch,
            threads: self.threads,
            prompts,
        };
        o.validate()?;
        Ok(o)
    }
}

/// The end-of-stage line of a features summary.
pub fn report(s: &crate::segment::FeaturesSummary, seconds: f64) {
    crate::progress::done(
        "features",
        &format!(
            "{} images embedded ({} masks), {} skipped (features exist), {} without masks; {} prompts{}; dimension {}; images {:.1} s, text {:.1} s",
            s.computed,
            s.masks,
            s.skipped,
            s.without_masks,
            s.prompts,
            if s.prompts_written { " written" } else { "" },
            s.dim,
            s.image_s,
            s.text_s
        ),
        seconds,
    );
}

pub fn run(args: &FeaturesArgs) -> anyhow::Result<()> {
    let o = args.options()?;
    let t = std::time::Instant::now();
    let s = features::run(&args.scene, &args.model, &o)?;
    report(&s, t.elapsed().as_secs_f64());
    Ok(())
}
