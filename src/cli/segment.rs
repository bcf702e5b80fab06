//! `gs4city segment`: SAM-family automatic masks of a scene's images on the CPU → `S/masks/`,
//! or with `--semantic` a semantic segmentation network's masks and class features.
use std::path::PathBuf;

use clap::Args;

use crate::segment::{self, SegmentOptions};

#[derive(Debug, Args)]
pub struct SegmentArgs {
    /// Scene folder: reads images/, writes masks/<stem>.json (an image whose file exists is skipped).
    #[arg(long)]
    scene: PathBuf,
    /// Model folder: encoder.onnx, decoder.onnx, model.json (docs/segment.md).
    #[arg(
        long,
        required_unless_present = "semantic",
        conflicts_with = "semantic"
    )]
    model: Option<PathBuf>,
    /// A semantic segmentation network (MODEL.onnx with its card MODEL.json beside it):
    /// masks are its classes' connected components, features their mean class probabilities
    /// (docs/segment.md; e.g. models/espnet/espnet_p2_q8_cityscapes.onnx for street-level photos).
    #[arg(long, value_name = "MODEL.onnx")]
    semantic: Option<PathBuf>,
    /// With --semantic: components smaller than this many pixels are dropped (0 = 1/2000 of the image).
    #[arg(long, default_value_t = 0, requires = "semantic")]
    min_area: usize,
    /// Points per side of the prompt grid.
    #[arg(long, default_value_t = SegmentOptions::default().points_per_side)]
    points_per_side: usize,
    /// Prompts per decoder call.
    #[arg(long, default_value_t = SegmentOptions::default().points_per_batch)]
    points_per_batch: usize,
    /// Masks whose predicted IoU is not above this are dropped.
    #[arg(long, default_value_t = SegmentOptions::default().pred_iou_thresh)]
    pred_iou_thresh: f32,
    /// Masks whose stability score is below this are dropped.
    #[arg(long, default_value_t = SegmentOptions::default().stability_score_thresh)]
    stability_score_thresh: f64,
    /// Box IoU above which NMS drops the lower-scored mask.
    #[arg(long, default_value_t = SegmentOptions::default().box_nms_thresh)]
    box_nms_thresh: f64,
    /// Holes and islands smaller than this many pixels (at the segmentation scale) are removed; 0 = off.
    #[arg(long, default_value_t = SegmentOptions::default().min_mask_region_area)]
    min_mask_region_area: usize,
    /// Downscale factor of the images before segmentation (the reference pipeline's default_scale).
    #[arg(long, default_value_t = SegmentOptions::default().scale)]
    scale: f64,
    /// Encoder threads and decoder workers (0 = every core, at most 8 decoder workers).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Decode every prompt with ONNX Runtime; by default SAM's decoder is computed natively
    /// from the export's weights when they are found and agree with ONNX Runtime on a probe.
    #[arg(long)]
    onnx_decoder: bool,
}

impl SegmentArgs {
    /// Validated options.
    pub fn options(&self) -> anyhow::Result<SegmentOptions> {
        let o = SegmentOptions {
            points_per_side: self.points_per_side,
            points_per_batch: self.points_per_batch,
            pred_iou_thresh: self.pred_iou_thresh,
            stability_score_thresh: self.stability_score_thresh,
            box_nms_thresh: self.box_nms_thresh,
            min_mask_region_area: self.min_mask_region_area,
            scale: self.scale,
            threads: self.threads,
            onnx_decoder: self.onnx_decoder,
            ..SegmentOptions::default()
        };
        o.validate()?;
        Ok(o)
    }
}

pub fn run(args: &SegmentArgs) -> anyhow::Result<()> {
    let t = std::time::Instant::now();
    if let Some(net) = &args.semantic {
        let o = segment::semantic::SemanticOptions {
            min_area: args.min_area,
            threads: args.threads,
        };
        let s = segment::semantic::run(&args.scene, net, &o)?;
        crate::progress::done(
            "segment",
            &format!(
                "{} images segmented ({} masks), {} skipped (masks and features exist); network {:.1} s, masks {:.1} s",
                s.segmented, s.masks, s.skipped, s.network_s, s.post_s
            ),
            t.elapsed().as_secs_f64(),
        );
        return Ok(());
    }
    let o = args.options()?;
    let model = args
        .model
        .as_ref()
        .ok_or_else(|| anyhow::anyhow!("give --model DIR or --semantic MODEL.onnx"))?;
    let s = segment::run(&args.scene, model, &o)?;
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
