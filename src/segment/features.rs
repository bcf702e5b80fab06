//! `gs4city features`: CLIP features of a scene's SAM masks on the CPU → `S/features/<stem>.npy`
//! (one unit row per mask of `S/masks/<stem>.json`, in mask order) and `S/features/prompts.json`
//! (the unit text embeddings of the class prompts, [`crate::classes::CLASS_PROMPTS`], and the
//! user's). Per image resumable: an image whose features file exists with one row per mask (of
//! the model's dimension) is skipped; `prompts.json` is written last, so a stopped run leaves
//! no file that says the features are complete.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;

use super::clip::{self, Clip};
use super::{SegmentError, list_images, mask_path};
use crate::check;
use crate::imageio;
use crate::sam::{self, Prompts};

/// The options of `gs4city features`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FeaturesOptions {
    /// Mask crops per image-encoder call (an encoder with a fixed batch uses its own).
    pub batch: usize,
    /// ONNX Runtime intra-op threads (0 = its default).
    pub threads: usize,
    /// Prompts beyond the class prompts.
    pub prompts: Vec<String>,
}

impl Default for FeaturesOptions {
    fn default() -> Self {
        FeaturesOptions {
            batch: 16,
            threads: 0,
            prompts: Vec::new(),
        }
    }
}

impl FeaturesOptions {
    /// Checks every option's range.
    pub fn validate(&self) -> Result<(), SegmentError> {
        use check::End::Closed;
        check::range("batch", self.batch, Closed(1.0), Closed(1024.0))?;
        if let Some(p) = self.prompts.iter().find(|p| p.trim().is_empty()) {
            return Err(SegmentError::EmptyPrompt(p.clone()));
        }
        Ok(())
    }

    /// The prompt texts: the class prompts, then the user's (each once, in that order).
    pub fn prompt_texts(&self) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        let class = crate::classes::CLASS_PROMPTS
            .iter()
            .map(|(t, _)| t.to_string());
        for t in class.chain(self.prompts.iter().map(|p| p.trim().to_string())) {
            if !out.contains(&t) {
                out.push(t);
            }
        }
        out
    }
}

/// Reads a prompts file: one prompt per line; empty lines and lines starting with `#` are
/// skipped.
pub fn read_prompt_lines(path: &Path) -> Result<Vec<String>, SegmentError> {
    let text = std::fs::read_to_string(path).map_err(|e| SegmentError::Image {
        path: path.to_path_buf(),
        why: format!("cannot read the prompts: {e}"),
    })?;
    Ok(text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(str::to_string)
        .collect())
}

/// What `features` did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct FeaturesSummary {
    /// Images whose features were computed now.
    pub computed: usize,
    /// Images skipped because their features file was complete.
    pub skipped: usize,
    /// Images without a mask file (no features).
    pub without_masks: usize,
    /// Mask crops embedded now.
    pub masks: usize,
    /// Prompts in `prompts.json`.
    pub prompts: usize,
    /// Whether `prompts.json` was written now.
    pub prompts_written: bool,
    /// Feature dimension.
    pub dim: usize,
    /// Seconds: crops and image encoder.
    pub image_s: f64,
    /// Seconds: tokenizer and text encoder.
    pub text_s: f64,
}

/// `features/<stem>.npy` of an image.
pub fn features_path(features_dir: &Path, image: &Path) -> PathBuf {
    let m = mask_path(features_dir, image);
    m.with_extension("npy")
}

/// The rows and dimension of an existing features file, if it is a complete one for `n` masks.
fn existing(path: &Path, n: usize) -> Option<usize> {
    if !path.is_file() {
        return None;
    }
    sam::read_features(path, Some(n)).ok().map(|(_, d, _)| d)
}

/// Computes the features of every image of `scene/images/` that has a SAM mask file and no
/// complete features file, then `prompts.json`.
pub fn run(
    scene: &Path,
    model_dir: &Path,
    o: &FeaturesOptions,
) -> Result<FeaturesSummary, SegmentError> {
    o.validate()?;
    let images = list_images(&scene.join("images"))?;
    let masks_dir = scene.join("masks");
    let feat_dir = scene.join("features");
    let prompts_path = feat_dir.join("prompts.json");
    let texts = o.prompt_texts();
    let old_prompts = if prompts_path.is_file() {
        let p = sam::read_prompts_json(&prompts_path)?;
        if p.simulated {
            return Err(SegmentError::Image {
                path: prompts_path,
                why: "holds SIMULATED features (gs4city synth): move the scene's features/ folder away to compute CLIP features".into(),
            });
        }
        Some(p)
    } else {
        None
    };
    let mut summary = FeaturesSummary::default();
    // (image, mask file, mask count, existing dimension)
    let mut work = Vec::new();
    for img in &images {
        let mp = mask_path(&masks_dir, img);
        if !mp.is_file() {
            summary.without_masks += 1;
            continue;
        }
        let masks = sam::read_sam_json(&mp)?;
        let fp = features_path(&feat_dir, img);
        let d = existing(&fp, masks.len());
        work.push((img, masks, fp, d));
    }
    if work.is_empty() {
        return Err(SegmentError::Image {
            path: masks_dir,
            why: "no SAM mask file (<stem>.json) for any image of images/: run `gs4city segment` first".into(),
        });
    }
    let prompts_done = old_prompts.as_ref().is_some_and(|p| {
        p.prompts.len() == texts.len()
            && texts.iter().all(|t| p.prompts.contains_key(t))
            && work.iter().all(|(_, _, _, d)| *d == Some(p.dim))
    });
    if prompts_done {
        summary.skipped = work.len();
        summary.prompts = texts.len();
        summary.dim = old_prompts.map_or(0, |p| p.dim);
        return Ok(summary);
    }
    let mut model = Clip::open(model_dir, o.threads)?;
    let t = Instant::now();
    let mut vectors = BTreeMap::new();
    for text in &texts {
        vectors.insert(text.clone(), model.embed_text(text)?);
    }
    summary.text_s = t.elapsed().as_secs_f64();
    let dim = vectors.values().next().map_or(0, Vec::len);
    summary.dim = dim;
    crate::fsutil::create_dir(&feat_dir)?;
    let todo: Vec<_> = work
        .into_iter()
        .filter(|(_, _, _, d)| {
            let done = *d == Some(dim);
            if done {
                summary.skipped += 1;
            }
            !done
        })
        .collect();
    let bar = crate::progress::Bar::new("features", todo.len() as u64, "images");
    let batch = model.image_batch(o.batch);
    let side = model.side;
    for (img, masks, fp, _) in todo {
        let name = img
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        bar.message(name);
        let t = Instant::now();
        let rgb = imageio::read_rgb(img)?;
        let (h, w, _) = rgb.dim();
        let mp = mask_path(&masks_dir, img);
        if let Some(m) = masks.first()
            && m.segmentation.size != [h, w]
        {
            return Err(SegmentError::Image {
                path: mp,
                why: format!(
                    "masks are {}×{} pixels, the image {} is {h}×{w}",
                    m.segmentation.size[0],
                    m.segmentation.size[1],
                    img.display()
                ),
            });
        }
        let mut rows: Vec<Vec<f32>> = Vec::with_capacity(masks.len());
        for chunk in masks.chunks(batch) {
            let crops: Vec<Vec<f32>> = chunk
                .par_iter()
                .map(|m| {
                    let mask = m.segmentation.decode().map_err(|e| SegmentError::Image {
                        path: img.clone(),
                        why: format!("a mask's RLE: {e}"),
                    })?;
                    clip::crop(&rgb, &mask, side)
                })
                .collect::<Result<_, _>>()?;
            let flat: Vec<f32> = crops.into_iter().flatten().collect();
            let out = model.embed_crops(flat, chunk.len())?;
            if let Some(r) = out.iter().find(|r| r.len() != dim) {
                return Err(SegmentError::Model {
                    path: model_dir.join("clip_image.onnx"),
                    why: format!(
                        "image embeddings have {} values, the text embeddings {dim}: the two encoders are not one CLIP model",
                        r.len()
                    ),
                });
            }
            rows.extend(out);
        }
        if let Some((k, _)) = rows
            .iter()
            .enumerate()
            .find(|(_, r)| r.iter().any(|x| !x.is_finite()))
        {
            return Err(SegmentError::Model {
                path: model_dir.join("clip_image.onnx"),
                why: format!(
                    "gave a non-finite embedding for mask {k} of {}",
                    img.display()
                ),
            });
        }
        sam::write_features_npy(&fp, dim, &rows).map_err(sam::SamError::from)?;
        summary.image_s += t.elapsed().as_secs_f64();
        summary.computed += 1;
        summary.masks += rows.len();
        bar.inc(1);
    }
    bar.finish();
    let classes = crate::classes::CLASS_PROMPTS
        .iter()
        .map(|&(t, c)| (t.to_string(), c.unwrap_or(crate::classes::WALL)))
        .collect();
    let prompts = Prompts {
        simulated: false,
        dim,
        prompts: vectors,
        classes,
    };
    sam::write_prompts_json(&prompts_path, &prompts)?;
    summary.prompts = texts.len();
    summary.prompts_written = true;
    Ok(summary)
}
