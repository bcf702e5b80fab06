//! Stage `segment`: SAM-family automatic mask generation on the CPU (`gs4city segment`).
//!
//! Per image of `S/images/` (sorted by name; an image whose `S/masks/<stem>.json` exists is
//! skipped, so a stopped run resumes): area-downscale by `scale` (the reference pipeline's
//! `default_scale` 0.25) → longest side to 1024 (bilinear) → SAM's normalisation, zero padding
//! → `encoder.onnx` → an `n × n` point grid decoded in batches by `decoder.onnx` (SAM's ONNX
//! export) → `amg`: predicted-IoU and stability filters, box NMS, optional small-region removal →
//! masks upscaled to the image size (nearest) → `S/masks/<stem>.json` (SAM format, `sam`).
//! ONNX Runtime is loaded at run time (`model`); docs/segment.md has the model folder layout.
pub mod amg;
pub mod bpe;
pub mod clip;
pub mod features;
pub mod model;
pub mod native;
pub mod semantic;

use std::path::{Path, PathBuf};
use std::time::Instant;

use ndarray::{Array2, Array3};
use ort::session::Session;

use crate::check;
use crate::fsutil::FsError;
use crate::imageio::{self, ImageError, Resample};
use crate::sam::{self, SamError, SamMask};

pub use clip::{CLIP_LAYOUT_HELP, Clip};
pub use features::{FeaturesOptions, FeaturesSummary};
pub use model::{LAYOUT_HELP, ModelInfo};

/// Errors of the segment stage; each names the file (model, image or mask file) at fault.
#[derive(Debug, thiserror::Error)]
pub enum SegmentError {
    #[error("{0}")]
    Runtime(String),
    #[error("no SAM-family model in {dir}: {missing} missing; {LAYOUT_HELP}")]
    NoModel { dir: PathBuf, missing: String },
    #[error(
        "no CLIP model in {dir}: {missing} missing; {}",
        clip::CLIP_LAYOUT_HELP
    )]
    NoClip { dir: PathBuf, missing: String },
    #[error(transparent)]
    Tokenizer(#[from] bpe::BpeError),
    #[error("model file {path}: {why}")]
    Model { path: PathBuf, why: String },
    #[error("{path}: {why}")]
    Image { path: PathBuf, why: String },
    #[error("{dir}: no images (png, jpg, jpeg)")]
    NoImages { dir: PathBuf },
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error("empty prompt {0:?}")]
    EmptyPrompt(String),
    /// An image too large for the network's buffers (the caller names the image).
    #[error("{0}")]
    TooLarge(String),
    #[error(transparent)]
    Cv(#[from] ImageError),
    #[error(transparent)]
    Sam(#[from] SamError),
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// SAM's pixel mean and standard deviation (RGB, 0..255).
const PIXEL_MEAN: [f64; 3] = [123.675, 116.28, 103.53];
const PIXEL_STD: [f64; 3] = [58.395, 57.12, 57.375];
/// The encoder's input side.
pub const IMAGE_SIDE: usize = 1024;
/// The most decoder workers `threads = 0` starts for a fixed-batch decoder.
const DEFAULT_MAX_WORKERS: usize = 8;

/// The side of the decoder's low-resolution masks.
const LOW_RES: usize = native::LOW;
/// Prompts a worker takes at a time from the native decoder.
const NATIVE_CHUNK: usize = 4;

/// The options of automatic mask generation (SAM's `SamAutomaticMaskGenerator` names).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SegmentOptions {
    /// Points per side of the prompt grid (SAM: 32).
    pub points_per_side: usize,
    /// Prompts decoded per decoder call (a decoder with a fixed batch of 1 is called per point).
    pub points_per_batch: usize,
    /// Masks whose predicted IoU is not above this are dropped.
    pub pred_iou_thresh: f32,
    /// Masks whose stability score is below this are dropped.
    pub stability_score_thresh: f64,
    /// The logit offset of the stability score (SAM: 1.0).
    pub stability_score_offset: f32,
    /// Box IoU above which NMS drops the lower-scored mask.
    pub box_nms_thresh: f64,
    /// Holes and islands smaller than this (pixels, at the segmentation scale) are removed; 0 = off.
    pub min_mask_region_area: usize,
    /// The image is downscaled by this factor before segmentation (reference: 0.25).
    pub scale: f64,
    /// ONNX Runtime intra-op threads of the encoder and of a dynamic-batch decoder, and the
    /// number of single-threaded workers of a fixed-batch decoder (SAM's own export); 0 = ONNX
    /// Runtime's default, and one worker per core (at most 8).
    pub threads: usize,
    /// Decode every prompt with ONNX Runtime, never natively ([`native`]).
    pub onnx_decoder: bool,
}

impl Default for SegmentOptions {
    fn default() -> Self {
        SegmentOptions {
            points_per_side: 32,
            points_per_batch: 64,
            pred_iou_thresh: 0.88,
            stability_score_thresh: 0.95,
            stability_score_offset: 1.0,
            box_nms_thresh: 0.7,
            min_mask_region_area: 0,
            scale: 0.25,
            threads: 0,
            onnx_decoder: false,
        }
    }
}

impl SegmentOptions {
    /// Checks every option's range.
    pub fn validate(&self) -> Result<(), SegmentError> {
        use check::End::{Closed, Open};
        let r = || -> Result<(), check::OutOfRange> {
            check::range(
                "points-per-side",
                self.points_per_side as f64,
                Closed(1.0),
                Closed(256.0),
            )?;
            check::range(
                "points-per-batch",
                self.points_per_batch as f64,
                Closed(1.0),
                Closed(4096.0),
            )?;
            check::unit("pred-iou-thresh", self.pred_iou_thresh)?;
            check::unit("stability-score-thresh", self.stability_score_thresh)?;
            check::range(
                "stability-score-offset",
                self.stability_score_offset,
                Closed(0.0),
                Open(1e6),
            )?;
            check::unit("box-nms-thresh", self.box_nms_thresh)?;
            check::range("scale", self.scale, Open(0.0), Closed(1.0))?;
            Ok(())
        };
        Ok(r()?)
    }
}

/// Seconds spent per part of one image.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct Timings {
    /// Resizing, normalisation and the encoder.
    pub encoder_s: f64,
    /// The decoder calls.
    pub decoder_s: f64,
    /// Filters, NMS, small regions, upscaling and RLE.
    pub post_s: f64,
}

/// A loaded model: encoder and decoder sessions.
pub struct Segmenter {
    pub info: ModelInfo,
    encoder: Session,
    /// The decoder sessions. A decoder with a fixed batch (SAM's own export: one prompt per
    /// call) gets one single-threaded session per worker, decoding side by side (faster than
    /// one session's intra-op threads on its small tensors, and each prompt's result is
    /// independent of the number of workers); a dynamic-batch decoder gets one session on
    /// `threads` intra-op threads.
    decoders: Vec<Session>,
    encoder_path: PathBuf,
    decoder_path: PathBuf,
    /// The decoder's fixed batch size, if it has one.
    fixed_batch: Option<usize>,
    /// Whether the decoder has `low_res_masks`: then only it and `iou_predictions` are asked
    /// for, and the masks that pass the IoU filter are upscaled here (`amg::upscale_logits`).
    low_res: bool,
    /// SAM's decoder computed natively from the export's weights ([`native`]), where they were
    /// found and agreed with ONNX Runtime on a probe; `None`: ONNX Runtime decodes.
    native: Option<native::SamDecoder>,
    /// Why the native decoder is not used (for the summary), when it is not.
    pub native_note: Option<String>,
    /// Workers decoding prompts side by side.
    workers: usize,
}

impl Segmenter {
    /// Opens `dir/encoder.onnx`, `dir/decoder.onnx` and `dir/model.json`: every missing file is
    /// named with the layout; a corrupt or mismatched file is named with what is wrong.
    pub fn open(dir: &Path, threads: usize) -> Result<Segmenter, SegmentError> {
        Segmenter::open_with(dir, threads, true)
    }

    /// [`Segmenter::open`]; `native` false keeps every prompt on ONNX Runtime.
    pub fn open_with(dir: &Path, threads: usize, native: bool) -> Result<Segmenter, SegmentError> {
        let names = ["encoder.onnx", "decoder.onnx", "model.json"];
        let missing: Vec<&str> = names
            .iter()
            .copied()
            .filter(|n| !dir.join(n).is_file())
            .collect();
        if !missing.is_empty() {
            return Err(SegmentError::NoModel {
                dir: dir.to_path_buf(),
                missing: missing.join(", "),
            });
        }
        let json = dir.join("model.json");
        let info: ModelInfo = crate::fsutil::read_json(&json).map_err(|e| SegmentError::Model {
            path: json.clone(),
            why: e.to_string(),
        })?;
        let encoder_path = dir.join("encoder.onnx");
        let decoder_path = dir.join("decoder.onnx");
        let encoder = model::open_session(&encoder_path, threads)?;
        // SAM's export computes `masks` after `low_res_masks`; a graph without that tail gives
        // `iou_predictions` and `low_res_masks` bit for bit with less work. A model that cannot
        // be pruned (no such outputs, control flow, external data) is loaded as it is.
        let decoder_bytes = std::fs::read(&decoder_path).ok();
        let pruned = decoder_bytes.as_ref().and_then(|b| {
            crate::onnxproto::keep_outputs(b, &["iou_predictions", "low_res_masks"])
                .ok()
                .filter(|(_, dropped)| dropped.iter().any(|d| d == "masks"))
        });
        // Each extra worker holds its own session (≈ 100 MB with SAM's decoder): by default one
        // per core, at most `DEFAULT_MAX_WORKERS`; `--threads N` asks for exactly N.
        let workers = if threads > 0 {
            threads
        } else {
            std::thread::available_parallelism()
                .map_or(1, |n| n.get())
                .min(DEFAULT_MAX_WORKERS)
        };
        let decoder =
            model::open_session_from(&decoder_path, pruned.as_ref().map(|p| &p.0[..]), 1)?;
        let enc_in = encoder
            .inputs()
            .first()
            .map(|o| o.name().to_string())
            .ok_or_else(|| SegmentError::Model {
                path: encoder_path.clone(),
                why: "has no input".into(),
            })?;
        let shape = model::input_shape(&encoder, &encoder_path, &enc_in)?;
        let want = [1, 3, IMAGE_SIDE as i64, IMAGE_SIDE as i64];
        if shape.len() != 4 || shape.iter().zip(want).any(|(&d, w)| d >= 0 && d != w) {
            return Err(SegmentError::Model {
                path: encoder_path,
                why: format!(
                    "input `{enc_in}` has shape {shape:?}, expected [1, 3, 1024, 1024] (a SAM image encoder)"
                ),
            });
        }
        for name in [
            "image_embeddings",
            "point_coords",
            "point_labels",
            "mask_input",
            "has_mask_input",
            "orig_im_size",
        ] {
            model::input_shape(&decoder, &decoder_path, name)?;
        }
        if pruned.is_none() {
            model::require_outputs(&decoder, &decoder_path, &["masks", "iou_predictions"])?;
        }
        let pc = model::input_shape(&decoder, &decoder_path, "point_coords")?;
        let fixed_batch = pc.first().copied().filter(|&b| b > 0).map(|b| b as usize);
        let low_res = decoder
            .outputs()
            .iter()
            .any(|o| o.name() == "low_res_masks");
        let bytes = pruned.as_ref().map(|p| &p.0[..]);
        let decoders = if fixed_batch.is_some() {
            // SAM's own export (batch 1): single-threaded sessions side by side
            let mut d = vec![decoder];
            while d.len() < workers {
                d.push(model::open_session_from(&decoder_path, bytes, 1)?);
            }
            d
        } else {
            // A dynamic batch holds `--points-per-batch` prompts' tensors per call (≈ 4 GB at
            // 64 with SAM's decoder): one session, on ONNX Runtime's intra-op threads, keeps
            // that once (side-by-side sessions gained nothing measurable here and doubled it).
            drop(decoder);
            vec![model::open_session_from(&decoder_path, bytes, threads)?]
        };
        let mut seg = Segmenter {
            info,
            encoder,
            decoders,
            encoder_path,
            decoder_path,
            fixed_batch,
            low_res,
            native: None,
            native_note: None,
            workers,
        };
        if native {
            match seg.try_native(decoder_bytes.as_deref()) {
                Ok(d) => seg.native = Some(d),
                Err(why) => seg.native_note = Some(why),
            }
        } else {
            seg.native_note = Some("ONNX Runtime asked for (--onnx-decoder)".into());
        }
        Ok(seg)
    }

    /// Whether prompts are decoded natively ([`native`]) rather than by ONNX Runtime.
    pub fn native(&self) -> bool {
        self.native.is_some()
    }

    /// SAM's decoder read from the export's weights, if it reproduces the export on a probe
    /// (two prompts on a fixed pseudo-random embedding: every IoU and low-resolution logit
    /// within 10⁻³ of the largest magnitude); else why not.
    fn try_native(&mut self, bytes: Option<&[u8]>) -> Result<native::SamDecoder, String> {
        if !self.low_res {
            return Err("the decoder has no low_res_masks output".into());
        }
        let bytes = bytes.ok_or("the decoder file could not be read")?;
        let graph = crate::onnxproto::read_graph(bytes).map_err(|e| e.to_string())?;
        let dec = native::SamDecoder::from_graph(&graph).map_err(|e| e.to_string())?;
        // a fixed pseudo-random embedding (xorshift), values in [−2, 2)
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let emb: Vec<f32> = (0..256 * 64 * 64)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                ((x >> 40) as f32 / (1u64 << 24) as f32) * 4.0 - 2.0
            })
            .collect();
        let o = SegmentOptions::default();
        let ctx = ChunkContext {
            path: &self.decoder_path,
            low_res: true,
            embeddings: &emb,
            scale: (1.0, 1.0),
            size: (IMAGE_SIDE, IMAGE_SIDE),
            axes: (
                amg::AxisMap::new(LOW_RES, IMAGE_SIDE, IMAGE_SIDE),
                amg::AxisMap::new(LOW_RES, IMAGE_SIDE, IMAGE_SIDE),
            ),
            options: &o,
        };
        let shared = SharedInputs::new(&ctx).map_err(|e| e.to_string())?;
        let prep = dec.prepare(&emb);
        for p in [[301.25f64, 199.5], [911.0, 37.75]] {
            let raw =
                ort_raw(&mut self.decoders[0], &ctx, &shared, &[p]).map_err(|e| e.to_string())?;
            let pts = [[p[0] as f32, p[1] as f32], [0.0, 0.0]];
            let d = dec.decode(&prep, &pts, &[1.0, -1.0]);
            if raw.k != dec.masks() {
                return Err(format!("{} masks per prompt, not {}", raw.k, dec.masks()));
            }
            let all: Vec<usize> = (0..raw.k).collect();
            let lows = dec.low_res(&prep, &d, &all);
            let scale = raw
                .masks
                .iter()
                .chain(&raw.ious)
                .fold(1f32, |m, v| m.max(v.abs()));
            // a NaN on either side counts as a difference
            let worst = d
                .iou
                .iter()
                .zip(&raw.ious)
                .chain(lows.iter().flatten().zip(&raw.masks))
                .fold(0f32, |m, (a, b)| {
                    let e = (a - b).abs();
                    if e.is_nan() { f32::INFINITY } else { m.max(e) }
                });
            if worst > 1e-3 * scale {
                return Err(format!(
                    "the native decoder differs from the export by {worst:.3e} (scale {scale:.3e})"
                ));
            }
        }
        Ok(dec)
    }

    /// Automatic masks of one RGB image (`H×W×3`), at the image's full size.
    pub fn segment(
        &mut self,
        rgb: &Array3<u8>,
        o: &SegmentOptions,
    ) -> Result<(Vec<SamMask>, Timings), SegmentError> {
        let mut t = Timings::default();
        let t0 = Instant::now();
        let (big_h, big_w, _) = rgb.dim();
        let w = ((big_w as f64) * o.scale).round_ties_even().max(1.0) as usize;
        let h = ((big_h as f64) * o.scale).round_ties_even().max(1.0) as usize;
        let small = if (w, h) == (big_w, big_h) {
            rgb.clone()
        } else {
            imageio::resize(rgb, w, h, Resample::Area)?
        };
        let s = IMAGE_SIDE as f64 / h.max(w) as f64;
        let nh = (h as f64 * s + 0.5) as usize;
        let nw = (w as f64 * s + 0.5) as usize;
        let resized = imageio::resize(&small, nw, nh, Resample::Linear)?;
        let side = IMAGE_SIDE;
        let mut input = vec![0f32; 3 * side * side];
        for ((y, x, c), &v) in resized.indexed_iter() {
            input[c * side * side + y * side + x] =
                ((f64::from(v) - PIXEL_MEAN[c]) / PIXEL_STD[c]) as f32;
        }
        let enc_in = self.encoder.inputs()[0].name().to_string();
        let image = model::tensor(&[1, 3, side, side], input, &self.encoder_path)?;
        let embeddings: Vec<f32> = {
            let out = self
                .encoder
                .run(ort::inputs![enc_in.as_str() => image])
                .map_err(|e| run_err(&self.encoder_path, e))?;
            let (shape, data) = out[0]
                .try_extract_tensor::<f32>()
                .map_err(|e| run_err(&self.encoder_path, e))?;
            if shape.iter().copied().collect::<Vec<i64>>() != [1, 256, 64, 64] {
                return Err(SegmentError::Model {
                    path: self.encoder_path.clone(),
                    why: format!("output has shape {shape:?}, expected [1, 256, 64, 64]"),
                });
            }
            data.to_vec()
        };
        t.encoder_s = t0.elapsed().as_secs_f64();

        let points: Vec<[f64; 2]> = amg::point_grid(o.points_per_side)
            .into_iter()
            .map(|[x, y]| [x * w as f64, y * h as f64])
            .collect();
        // the native decoder's per-image work (once), then prompts one by one per worker
        let prep = self.native.as_ref().map(|n| n.prepare(&embeddings));
        let batch = match (&self.native, self.fixed_batch) {
            (Some(_), _) => NATIVE_CHUNK,
            (None, Some(b)) => b,
            (None, None) => o.points_per_batch,
        };
        let (sx, sy) = (nw as f64 / w as f64, nh as f64 / h as f64);
        // SAM's export post-processing per axis: 256 → 1024 → the resized image → h × w
        let ctx = ChunkContext {
            path: &self.decoder_path,
            low_res: self.low_res,
            embeddings: &embeddings,
            scale: (sx, sy),
            size: (h, w),
            axes: (
                amg::AxisMap::new(LOW_RES, nh, h),
                amg::AxisMap::new(LOW_RES, nw, w),
            ),
            options: o,
        };
        // The batches are decoded by the workers side by side, each taking the next batch not
        // yet taken; the candidates are put back in batch order, so the result is the same
        // for any number of workers.
        let chunks: Vec<&[[f64; 2]]> = points.chunks(batch).collect();
        let next = std::sync::atomic::AtomicUsize::new(0);
        let t1 = Instant::now();
        let native = self.native.as_ref().zip(prep.as_ref());
        let sessions: Vec<Option<&mut Session>> = if native.is_some() {
            (0..self.workers).map(|_| None).collect()
        } else {
            self.decoders.iter_mut().map(Some).collect()
        };
        type Decoded = Result<(usize, Vec<Cand>, f64, f64), SegmentError>;
        let mut decoded: Vec<Decoded> = std::thread::scope(|sc| {
            let handles: Vec<_> = sessions
                .into_iter()
                .map(|session| {
                    let (ctx, chunks, next) = (&ctx, &chunks, &next);
                    sc.spawn(move || -> Vec<Decoded> {
                        let mut out = Vec::new();
                        // the inputs every call of this image shares, built once per worker
                        let shared = match session.as_ref().map(|_| SharedInputs::new(ctx)) {
                            Some(Err(e)) => {
                                next.store(chunks.len(), std::sync::atomic::Ordering::Relaxed);
                                out.push(Err(e));
                                return out;
                            }
                            Some(Ok(s)) => Some(s),
                            None => None,
                        };
                        let mut session = session;
                        loop {
                            let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            let Some(chunk) = chunks.get(i) else { break };
                            let r = match (session.as_deref_mut(), &shared, native) {
                                (Some(s), Some(sh), _) => decode_chunk(s, ctx, sh, chunk),
                                (_, _, Some((dec, prep))) => {
                                    Ok(decode_chunk_native(dec, prep, ctx, chunk))
                                }
                                _ => unreachable!("a worker has a session or the native decoder"),
                            };
                            let failed = r.is_err();
                            out.push(r.map(|(c, d, p)| (i, c, d, p)));
                            if failed {
                                // stop taking batches; the others finish theirs
                                next.store(chunks.len(), std::sync::atomic::Ordering::Relaxed);
                                break;
                            }
                        }
                        out
                    })
                })
                .collect();
            handles
                .into_iter()
                .flat_map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
                .collect()
        });
        let wall = t1.elapsed().as_secs_f64();
        if let Some(pos) = decoded.iter().position(Result::is_err) {
            return Err(decoded.swap_remove(pos).err().expect("an error"));
        }
        let mut parts: Vec<(usize, Vec<Cand>, f64, f64)> =
            decoded.into_iter().filter_map(Result::ok).collect();
        parts.sort_by_key(|p| p.0);
        // the phase's wall time, split between decoding and filtering as the workers spent it
        let (dec, post): (f64, f64) = parts
            .iter()
            .map(|p| (p.2, p.3))
            .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
        let busy = dec + post;
        if busy > 0.0 {
            t.decoder_s += wall * dec / busy;
            t.post_s += wall * post / busy;
        }
        let cands: Vec<Cand> = parts.into_iter().flat_map(|p| p.1).collect();
        let t3 = Instant::now();
        let boxes: Vec<[f64; 4]> = cands.iter().map(|c| amg::mask_box(&c.mask, h, w)).collect();
        let scores: Vec<f64> = cands.iter().map(|c| f64::from(c.iou)).collect();
        let keep = amg::nms(&boxes, &scores, o.box_nms_thresh);
        let mut cands: Vec<Option<Cand>> = cands.into_iter().map(Some).collect();
        let mut kept: Vec<Cand> = keep.iter().filter_map(|&i| cands[i].take()).collect();
        if o.min_mask_region_area > 0 && !kept.is_empty() {
            let mut scores = Vec::with_capacity(kept.len());
            for c in kept.iter_mut() {
                let m = Array2::from_shape_vec((h, w), std::mem::take(&mut c.mask))
                    .expect("h·w values");
                let (m, c1) = amg::remove_small_regions(&m, o.min_mask_region_area, true)?;
                let (m, c2) = amg::remove_small_regions(&m, o.min_mask_region_area, false)?;
                scores.push(if c1 || c2 { 0.0 } else { 1.0 });
                c.mask = m.iter().copied().collect();
            }
            let boxes: Vec<[f64; 4]> = kept.iter().map(|c| amg::mask_box(&c.mask, h, w)).collect();
            let keep = amg::nms(&boxes, &scores, o.box_nms_thresh);
            let mut all: Vec<Option<Cand>> = kept.into_iter().map(Some).collect();
            kept = keep.iter().filter_map(|&i| all[i].take()).collect();
        }
        let out = kept
            .iter()
            .map(|c| {
                let big = amg::upscale_nearest(&c.mask, h, w, big_h, big_w);
                SamMask::from_mask(
                    &big,
                    f64::from(c.iou),
                    c.stability,
                    vec![[
                        c.point[0] * big_w as f64 / w as f64,
                        c.point[1] * big_h as f64 / h as f64,
                    ]],
                )
            })
            .collect();
        t.post_s += t3.elapsed().as_secs_f64();
        Ok((out, t))
    }
}

/// A mask that passed the predicted-IoU and stability filters, before NMS.
struct Cand {
    mask: Vec<bool>,
    iou: f32,
    stability: f64,
    point: [f64; 2],
}

/// What every batch of prompts of one image shares.
struct ChunkContext<'a> {
    path: &'a Path,
    low_res: bool,
    embeddings: &'a [f32],
    /// Downscaled image → 1024 frame, per axis.
    scale: (f64, f64),
    /// The downscaled image's `(h, w)`.
    size: (usize, usize),
    /// SAM's export post-processing per axis: 256 → 1024 → the resized image → h × w.
    axes: (amg::AxisMap, amg::AxisMap),
    options: &'a SegmentOptions,
}

/// The decoder inputs that every call of one image shares (the image's embeddings, no mask
/// prompt, `orig_im_size`) and the run options, built once per worker and image instead of
/// once per call (the embeddings are 4 MB).
struct SharedInputs {
    embeddings: ort::value::Tensor<f32>,
    mask_input: ort::value::Tensor<f32>,
    has_mask_input: ort::value::Tensor<f32>,
    orig_im_size: ort::value::Tensor<f32>,
    low_res_only: ort::session::RunOptions<ort::session::HasSelectedOutputs>,
}

impl SharedInputs {
    fn new(ctx: &ChunkContext<'_>) -> Result<SharedInputs, SegmentError> {
        let dp = ctx.path;
        let (h, w) = ctx.size;
        // With the low-resolution outputs only, the export's post-processing (upsampling to
        // 1024², the crop to the resized image, the upsampling to `orig_im_size`) produces
        // `masks`, which is not read. It is normally pruned from the graph (`open`); where it
        // could not be, ONNX Runtime still computes it (it runs the whole graph), and a
        // 1 × 1024 "original" makes the crop one row and the last upsampling trivial. Neither
        // `low_res_masks` nor `iou_predictions` depends on it (SAM's export applies it after
        // the decoder).
        let orig_im_size: [f32; 2] = if ctx.low_res {
            [1.0, 1024.0]
        } else {
            [h as f32, w as f32]
        };
        Ok(SharedInputs {
            embeddings: model::tensor(&[1, 256, 64, 64], ctx.embeddings.to_vec(), dp)?,
            mask_input: model::tensor(&[1, 1, 256, 256], vec![0.0; 256 * 256], dp)?,
            has_mask_input: model::tensor(&[1], vec![0.0], dp)?,
            orig_im_size: model::tensor(&[2], orig_im_size.to_vec(), dp)?,
            low_res_only: ort::session::RunOptions::new()
                .map_err(|e| run_err(dp, e))?
                .with_outputs(
                    ort::session::OutputSelector::no_default()
                        .with("iou_predictions")
                        .with("low_res_masks"),
                ),
        })
    }
}

/// The decoder's outputs for a batch of prompts: the predicted IoUs (`b × k`) and the masks
/// (`b × k × plane`, low-resolution or at the image's size).
struct RawOut {
    ious: Vec<f32>,
    masks: Vec<f32>,
    k: usize,
    plane: usize,
}

/// Runs ONNX Runtime's decoder on one batch of prompts (each a point and the padding point).
fn ort_raw(
    session: &mut Session,
    ctx: &ChunkContext<'_>,
    shared: &SharedInputs,
    chunk: &[[f64; 2]],
) -> Result<RawOut, SegmentError> {
    let dp = ctx.path;
    let ((sx, sy), (h, w)) = (ctx.scale, ctx.size);
    let b = chunk.len();
    let mut coords = vec![0f32; b * 4];
    let mut labels = vec![0f32; b * 2];
    for (i, p) in chunk.iter().enumerate() {
        coords[i * 4] = (p[0] * sx) as f32;
        coords[i * 4 + 1] = (p[1] * sy) as f32;
        labels[i * 2] = 1.0;
        labels[i * 2 + 1] = -1.0;
    }
    let inputs = ort::inputs![
        "image_embeddings" => &shared.embeddings,
        "point_coords" => model::tensor(&[b, 2, 2], coords, dp)?,
        "point_labels" => model::tensor(&[b, 2], labels, dp)?,
        "mask_input" => &shared.mask_input,
        "has_mask_input" => &shared.has_mask_input,
        "orig_im_size" => &shared.orig_im_size,
    ];
    let out = if ctx.low_res {
        session
            .run_with_options(inputs, &shared.low_res_only)
            .map_err(|e| run_err(dp, e))?
    } else {
        session.run(inputs).map_err(|e| run_err(dp, e))?
    };
    let mask_name = if ctx.low_res {
        "low_res_masks"
    } else {
        "masks"
    };
    let (mshape, masks) = out[mask_name]
        .try_extract_tensor::<f32>()
        .map_err(|e| run_err(dp, e))?;
    let (ishape, ious) = out["iou_predictions"]
        .try_extract_tensor::<f32>()
        .map_err(|e| run_err(dp, e))?;
    let ms: Vec<i64> = mshape.iter().copied().collect();
    let is: Vec<i64> = ishape.iter().copied().collect();
    let (mh, mw) = if ctx.low_res {
        (LOW_RES as i64, LOW_RES as i64)
    } else {
        (h as i64, w as i64)
    };
    if ms.len() != 4
        || ms[0] != b as i64
        || ms[2] != mh
        || ms[3] != mw
        || is.len() != 2
        || is[0] != b as i64
        || is[1] != ms[1]
        || !matches!(ms[1], 1 | 3 | 4)
    {
        return Err(SegmentError::Model {
            path: dp.to_path_buf(),
            why: format!(
                "outputs {mask_name} {ms:?} and iou_predictions {is:?} for {b} prompts on a {w}×{h} image; expected [{b}, 4, {mh}, {mw}] and [{b}, 4]"
            ),
        });
    }
    Ok(RawOut {
        ious: ious.to_vec(),
        masks: masks.to_vec(),
        k: ms[1] as usize,
        plane: (mh * mw) as usize,
    })
}

/// The masks of a prompt whose IoU the filter passes: SAM's multimask outputs are tokens
/// 1..4 of 4 (token 0 is the single-mask output); NaN scores fail too.
fn passing(ious: &[f32], o: &SegmentOptions) -> Vec<usize> {
    let first = usize::from(ious.len() == 4);
    (first..ious.len())
        .filter(|&k| ious[k].partial_cmp(&o.pred_iou_thresh) == Some(std::cmp::Ordering::Greater))
        .collect()
}

/// A mask that passed the IoU filter, upscaled (low-resolution logits) and kept if stable.
fn candidate(ctx: &ChunkContext<'_>, raw: &[f32], iou: f32, point: [f64; 2]) -> Option<Cand> {
    let o = ctx.options;
    let up;
    let lg = if ctx.low_res {
        up = amg::upscale_logits(raw, LOW_RES, &ctx.axes.0, &ctx.axes.1);
        &up[..]
    } else {
        raw
    };
    let stability = amg::stability_score(lg, o.stability_score_offset);
    (stability >= o.stability_score_thresh).then(|| Cand {
        mask: lg.iter().map(|&v| v > 0.0).collect(),
        iou,
        stability,
        point,
    })
}

/// Decodes one batch of prompts and keeps the masks that pass the filters; returns them with
/// the seconds spent decoding and filtering.
fn decode_chunk(
    session: &mut Session,
    ctx: &ChunkContext<'_>,
    shared: &SharedInputs,
    chunk: &[[f64; 2]],
) -> Result<(Vec<Cand>, f64, f64), SegmentError> {
    let t1 = Instant::now();
    let raw = ort_raw(session, ctx, shared, chunk)?;
    let decode_s = t1.elapsed().as_secs_f64();
    let t2 = Instant::now();
    let mut cands = Vec::new();
    for (i, p) in chunk.iter().enumerate() {
        let ious = &raw.ious[i * raw.k..(i + 1) * raw.k];
        for k in passing(ious, ctx.options) {
            let m = &raw.masks[(i * raw.k + k) * raw.plane..(i * raw.k + k + 1) * raw.plane];
            cands.extend(candidate(ctx, m, ious[k], *p));
        }
    }
    Ok((cands, decode_s, t2.elapsed().as_secs_f64()))
}

/// [`decode_chunk`] on the native decoder: the upscaling runs only for the masks that pass
/// the IoU filter.
fn decode_chunk_native(
    dec: &native::SamDecoder,
    prep: &native::ImagePrep,
    ctx: &ChunkContext<'_>,
    chunk: &[[f64; 2]],
) -> (Vec<Cand>, f64, f64) {
    let (mut decode_s, mut post_s) = (0.0, 0.0);
    let (sx, sy) = ctx.scale;
    let mut cands = Vec::new();
    for p in chunk {
        let t1 = Instant::now();
        let pts = [[(p[0] * sx) as f32, (p[1] * sy) as f32], [0.0, 0.0]];
        let d = dec.decode(prep, &pts, &[1.0, -1.0]);
        let keep = passing(&d.iou, ctx.options);
        let lows = dec.low_res(prep, &d, &keep);
        decode_s += t1.elapsed().as_secs_f64();
        let t2 = Instant::now();
        for (k, m) in keep.iter().zip(&lows) {
            cands.extend(candidate(ctx, m, d.iou[*k], *p));
        }
        post_s += t2.elapsed().as_secs_f64();
    }
    (cands, decode_s, post_s)
}

fn run_err(path: &Path, e: ort::Error) -> SegmentError {
    SegmentError::Model {
        path: path.to_path_buf(),
        why: format!("inference failed: {}", e.to_string().replace('\n', " ")),
    }
}

/// What `segment` did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct SegmentSummary {
    /// Images segmented now.
    pub segmented: usize,
    /// Images skipped because their mask file existed.
    pub skipped: usize,
    /// Masks written now.
    pub masks: usize,
    /// Seconds per part, summed over the images segmented now.
    pub timings: Timings,
    /// Which decoder ran: `native` (SAM's decoder computed here from the export's weights) or
    /// `onnxruntime` with the reason; empty when nothing was segmented.
    pub decoder: String,
}

/// The images of `dir` (png, jpg, jpeg; sorted by name).
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>, SegmentError> {
    let rd = std::fs::read_dir(dir).map_err(|e| SegmentError::Image {
        path: dir.to_path_buf(),
        why: e.to_string(),
    })?;
    let mut out: Vec<PathBuf> = rd
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension().and_then(|x| x.to_str()).is_some_and(|x| {
                    ["png", "jpg", "jpeg"]
                        .iter()
                        .any(|e| x.eq_ignore_ascii_case(e))
                })
        })
        .collect();
    out.sort();
    if out.is_empty() {
        return Err(SegmentError::NoImages {
            dir: dir.to_path_buf(),
        });
    }
    Ok(out)
}

/// Segments every image of `scene/images/` that has no `scene/masks/<stem>.json` yet.
pub fn run(
    scene: &Path,
    model_dir: &Path,
    o: &SegmentOptions,
) -> Result<SegmentSummary, SegmentError> {
    o.validate()?;
    let images = list_images(&scene.join("images"))?;
    let masks_dir = scene.join("masks");
    let todo: Vec<&PathBuf> = images
        .iter()
        .filter(|p| !mask_path(&masks_dir, p).is_file())
        .collect();
    let mut summary = SegmentSummary {
        skipped: images.len() - todo.len(),
        ..Default::default()
    };
    if todo.is_empty() {
        return Ok(summary);
    }
    let mut seg = Segmenter::open_with(model_dir, o.threads, !o.onnx_decoder)?;
    summary.decoder = match &seg.native_note {
        None => "native".into(),
        Some(why) => format!("onnxruntime ({why})"),
    };
    crate::fsutil::create_dir(&masks_dir)?;
    let bar = crate::progress::Bar::new("segment", todo.len() as u64, "images");
    for path in todo {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        bar.message(name);
        let rgb = imageio::read_rgb(path)?;
        let (masks, t) = seg.segment(&rgb, o).map_err(|e| match e {
            SegmentError::Cv(err) => SegmentError::Image {
                path: path.clone(),
                why: err.to_string(),
            },
            e => e,
        })?;
        sam::write_sam_json(&mask_path(&masks_dir, path), &masks)?;
        summary.segmented += 1;
        summary.masks += masks.len();
        summary.timings.encoder_s += t.encoder_s;
        summary.timings.decoder_s += t.decoder_s;
        summary.timings.post_s += t.post_s;
        bar.inc(1);
    }
    bar.finish();
    Ok(summary)
}

/// `masks/<stem>.json` of an image.
pub fn mask_path(masks_dir: &Path, image: &Path) -> PathBuf {
    let stem = image
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_default();
    masks_dir.join(format!("{stem}.json"))
}
