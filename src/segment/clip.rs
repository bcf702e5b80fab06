//! The CLIP model folder (`gs4city features`): image and text encoders as ONNX, CLIP's BPE
//! files, the mask crop of the reference pipeline and the embeddings (L2-normalised).
//!
//! A mask's crop follows LangSplat's preprocessing (`get_seg_img` + `pad_img`): the mask's
//! bounding box, padded to a square (the box centred, the padding split as `(L − w) / 2`
//! before), every pixel outside the mask — padding included — filled with grey (CLIP's pixel
//! mean, which normalises to ≈ 0), resized to the encoder's side (bilinear), CLIP's mean/std.
use std::path::{Path, PathBuf};

use ndarray::{Array2, Array3};
use ort::session::Session;
use ort::value::TensorElementType;
use ort::value::{DynTensor, Tensor};

use super::bpe::{Bpe, CONTEXT};
use super::{SegmentError, model, run_err};
use crate::imageio::{self, Resample};

/// Where the published weights are and how a CLIP model folder is laid out (part of the
/// no-weights error).
pub const CLIP_LAYOUT_HELP: &str = "a CLIP model folder holds clip_image.onnx (pixel_values [B,3,224,224], CLIP-normalised → image_embeds [B,D]), clip_text.onnx (input_ids [B,77] int64, optional attention_mask → text_embeds [B,D]) and CLIP's BPE files vocab.json + merges.txt (or OpenAI's bpe_simple_vocab_16e6.txt, gunzipped); the published weights are OpenAI's CLIP ViT-B/32 (github.com/openai/CLIP; as ONNX: the vision and text models with projection of openai/clip-vit-base-patch32 on the Hugging Face hub, e.g. exported with `optimum-cli export onnx`, whose folder also has vocab.json and merges.txt); or lay the folder out with the gs4city repository's scripts/export_clip_model.py --checkpoint DIR --out DIR (needs torch and transformers; docs/features.md)";

/// CLIP's pixel mean and standard deviation (RGB, 0..1).
pub const CLIP_MEAN: [f64; 3] = [0.481_454_66, 0.457_827_5, 0.408_210_73];
pub const CLIP_STD: [f64; 3] = [0.268_629_54, 0.261_302_58, 0.275_777_11];
/// The fill colour outside the mask: CLIP's mean, 8-bit.
pub const GREY: [u8; 3] = [123, 117, 104];
/// The image side when the encoder does not fix it.
pub const DEFAULT_SIDE: usize = 224;

/// One encoder file and what was read of its signature.
struct Encoder {
    session: Session,
    path: PathBuf,
    input: String,
    output: String,
    /// The fixed batch size, if the graph has one.
    fixed_batch: Option<usize>,
}

/// A loaded CLIP model: image encoder, text encoder, tokenizer.
pub struct Clip {
    image: Encoder,
    text: Encoder,
    /// `attention_mask` input of the text encoder, if it has one.
    text_mask: bool,
    text_ids_i32: bool,
    /// The text encoder's sequence length.
    context: usize,
    /// The image encoder's input side.
    pub side: usize,
    pub tokenizer: Bpe,
}

/// The model folder's files: `(image, text, tokenizer files)`; a missing one is named with the
/// layout.
pub fn files(dir: &Path) -> Result<(PathBuf, PathBuf, Vec<PathBuf>), SegmentError> {
    let mut missing: Vec<&str> = ["clip_image.onnx", "clip_text.onnx"]
        .into_iter()
        .filter(|n| !dir.join(n).is_file())
        .collect();
    let hf = [dir.join("vocab.json"), dir.join("merges.txt")];
    let openai = dir.join("bpe_simple_vocab_16e6.txt");
    let tok = if hf.iter().all(|p| p.is_file()) {
        hf.to_vec()
    } else if openai.is_file() {
        vec![openai]
    } else {
        if dir.join("bpe_simple_vocab_16e6.txt.gz").is_file() {
            return Err(SegmentError::Model {
                path: dir.join("bpe_simple_vocab_16e6.txt.gz"),
                why: "is compressed: `gunzip -k` it (gs4city reads bpe_simple_vocab_16e6.txt)"
                    .into(),
            });
        }
        missing.push("vocab.json + merges.txt (or bpe_simple_vocab_16e6.txt)");
        vec![]
    };
    if !missing.is_empty() {
        return Err(SegmentError::NoClip {
            dir: dir.to_path_buf(),
            missing: missing.join(", "),
        });
    }
    Ok((dir.join("clip_image.onnx"), dir.join("clip_text.onnx"), tok))
}

/// Whether `dir` holds any file of a CLIP model folder (so `run --model-dir` computes features).
pub fn has_any(dir: &Path) -> bool {
    ["clip_image.onnx", "clip_text.onnx"]
        .iter()
        .any(|n| dir.join(n).is_file())
}

fn open_encoder(path: &Path, threads: usize, out: &str) -> Result<Encoder, SegmentError> {
    let session = model::open_session(path, threads)?;
    let input = session
        .inputs()
        .first()
        .map(|o| o.name().to_string())
        .ok_or_else(|| SegmentError::Model {
            path: path.to_path_buf(),
            why: "has no input".into(),
        })?;
    let output = session
        .outputs()
        .iter()
        .find(|o| o.name() == out)
        .or_else(|| session.outputs().first())
        .map(|o| o.name().to_string())
        .ok_or_else(|| SegmentError::Model {
            path: path.to_path_buf(),
            why: "has no output".into(),
        })?;
    let shape = model::input_shape(&session, path, &input)?;
    let fixed_batch = shape
        .first()
        .copied()
        .filter(|&b| b > 0)
        .map(|b| b as usize);
    Ok(Encoder {
        session,
        path: path.to_path_buf(),
        input,
        output,
        fixed_batch,
    })
}

impl Encoder {
    /// Runs the encoder on `b` rows; returns the `b × D` output.
    fn run(
        &mut self,
        inputs: Vec<(String, DynTensor)>,
        b: usize,
    ) -> Result<Vec<Vec<f32>>, SegmentError> {
        let out = self
            .session
            .run(inputs)
            .map_err(|e| run_err(&self.path, e))?;
        let (shape, data) = out[self.output.as_str()]
            .try_extract_tensor::<f32>()
            .map_err(|e| run_err(&self.path, e))?;
        let s: Vec<i64> = shape.iter().copied().collect();
        if s.len() != 2 || s[0] != b as i64 || s[1] < 1 {
            return Err(SegmentError::Model {
                path: self.path.clone(),
                why: format!(
                    "output `{}` has shape {s:?} for {b} inputs, expected [{b}, D] (the projected embeddings)",
                    self.output
                ),
            });
        }
        let d = s[1] as usize;
        Ok(data.chunks(d).map(unit).collect())
    }
}

/// `v / |v|` (f64 sum); a zero or non-finite vector stays as it is and is caught by the writer.
fn unit(v: &[f32]) -> Vec<f32> {
    let n = v
        .iter()
        .map(|&x| f64::from(x) * f64::from(x))
        .sum::<f64>()
        .sqrt();
    if n > 0.0 && n.is_finite() {
        v.iter().map(|&x| (f64::from(x) / n) as f32).collect()
    } else {
        v.to_vec()
    }
}

impl Clip {
    /// Opens the model folder: every missing file is named with the layout; a corrupt file or
    /// one with the wrong inputs/outputs is named with what is wrong.
    pub fn open(dir: &Path, threads: usize) -> Result<Clip, SegmentError> {
        let (image_path, text_path, tok) = files(dir)?;
        let tokenizer = match &tok[..] {
            [vocab, merges] => Bpe::from_vocab_merges(vocab, merges)?,
            [openai] => Bpe::from_openai_merges(openai)?,
            _ => unreachable!("files() gives one or two tokenizer files"),
        };
        let image = open_encoder(&image_path, threads, "image_embeds")?;
        let shape = model::input_shape(&image.session, &image.path, &image.input)?;
        let bad_shape = shape.len() != 4
            || (shape[1] >= 0 && shape[1] != 3)
            || (shape[2] >= 0 && shape[3] >= 0 && shape[2] != shape[3]);
        if bad_shape {
            return Err(SegmentError::Model {
                path: image_path,
                why: format!(
                    "input `{}` has shape {shape:?}, expected [B, 3, S, S] (a CLIP image encoder)",
                    image.input
                ),
            });
        }
        let side = if shape[2] > 0 {
            shape[2] as usize
        } else {
            DEFAULT_SIDE
        };
        let mut text = open_encoder(&text_path, threads, "text_embeds")?;
        if let Some(i) = text
            .session
            .inputs()
            .iter()
            .position(|o| o.name() == "input_ids")
        {
            text.input = text.session.inputs()[i].name().to_string();
        }
        let outlet = text
            .session
            .inputs()
            .iter()
            .find(|o| o.name() == text.input)
            .expect("the input exists");
        let ty = outlet.dtype().tensor_type();
        let tshape = model::input_shape(&text.session, &text.path, &text.input)?;
        if tshape.len() != 2
            || !matches!(
                ty,
                Some(TensorElementType::Int64 | TensorElementType::Int32)
            )
        {
            return Err(SegmentError::Model {
                path: text_path,
                why: format!(
                    "input `{}` is {ty:?} of shape {tshape:?}, expected int64 token ids [B, 77] (a CLIP text encoder)",
                    text.input
                ),
            });
        }
        let context = if tshape[1] > 0 {
            tshape[1] as usize
        } else {
            CONTEXT
        };
        let text_mask = text
            .session
            .inputs()
            .iter()
            .any(|o| o.name() == "attention_mask");
        let known = text
            .session
            .inputs()
            .iter()
            .map(|o| o.name())
            .find(|n| *n != text.input && *n != "attention_mask");
        if let Some(other) = known {
            return Err(SegmentError::Model {
                path: text_path,
                why: format!(
                    "has an input `{other}` besides `{}` and `attention_mask` (a CLIP text encoder takes token ids)",
                    text.input
                ),
            });
        }
        Ok(Clip {
            image,
            text,
            text_mask,
            text_ids_i32: ty == Some(TensorElementType::Int32),
            context,
            side,
            tokenizer,
        })
    }

    /// The image encoder's batch: `want`, or its fixed batch size.
    pub fn image_batch(&self, want: usize) -> usize {
        self.image.fixed_batch.unwrap_or(want).max(1)
    }

    /// Unit embeddings of `b` crops (`b × 3 × side × side` values, [`crop`]'s layout).
    pub fn embed_crops(
        &mut self,
        crops: Vec<f32>,
        b: usize,
    ) -> Result<Vec<Vec<f32>>, SegmentError> {
        let s = self.side;
        let t = model::tensor(&[b, 3, s, s], crops, &self.image.path)?;
        let name = self.image.input.clone();
        self.image.run(vec![(name, t.upcast())], b)
    }

    /// The unit embedding of one text.
    pub fn embed_text(&mut self, text: &str) -> Result<Vec<f32>, SegmentError> {
        let ids = self.tokenizer.tokenize(text, self.context);
        let p = self.text.path.clone();
        let bad = |e: ort::Error| run_err(&p, e);
        let shape = vec![1i64, self.context as i64];
        let mut inputs: Vec<(String, DynTensor)> = Vec::new();
        let ids_t: DynTensor = if self.text_ids_i32 {
            let v: Vec<i32> = ids.iter().map(|&x| x as i32).collect();
            Tensor::from_array((shape.clone(), v))
                .map_err(bad)?
                .upcast()
        } else {
            Tensor::from_array((shape.clone(), ids.clone()))
                .map_err(bad)?
                .upcast()
        };
        inputs.push((self.text.input.clone(), ids_t));
        if self.text_mask {
            // ones up to and including <|endoftext|> (the first id at which padding starts)
            let len = ids.iter().rposition(|&x| x != 0).map_or(0, |i| i + 1);
            let m: Vec<i64> = (0..self.context).map(|i| i64::from(i < len)).collect();
            inputs.push((
                "attention_mask".into(),
                Tensor::from_array((shape, m)).map_err(bad)?.upcast(),
            ));
        }
        Ok(self.text.run(inputs, 1)?.remove(0))
    }
}

/// The crop of one mask (`h × w`, the image's size) as the image encoder's input: `3 × side ×
/// side` values, channel-major, CLIP-normalised (module docs).
pub fn crop(rgb: &Array3<u8>, mask: &Array2<bool>, side: usize) -> Result<Vec<f32>, SegmentError> {
    let (h, w, _) = rgb.dim();
    debug_assert_eq!(mask.dim(), (h, w));
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for ((y, x), &m) in mask.indexed_iter() {
        if m {
            x0 = x0.min(x);
            y0 = y0.min(y);
            x1 = x1.max(x);
            y1 = y1.max(y);
        }
    }
    let square = if x0 == usize::MAX {
        // an empty mask: a grey square
        Array3::from_shape_fn((1, 1, 3), |(_, _, c)| GREY[c])
    } else {
        let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
        let l = bw.max(bh);
        let (ox, oy) = ((l - bw) / 2, (l - bh) / 2);
        let mut sq = Array3::from_shape_fn((l, l, 3), |(_, _, c)| GREY[c]);
        for y in 0..bh {
            for x in 0..bw {
                if mask[[y0 + y, x0 + x]] {
                    for c in 0..3 {
                        sq[[oy + y, ox + x, c]] = rgb[[y0 + y, x0 + x, c]];
                    }
                }
            }
        }
        sq
    };
    let resized = if square.dim().0 == side {
        square
    } else {
        imageio::resize(&square, side, side, Resample::Linear)?
    };
    let mut out = vec![0f32; 3 * side * side];
    for ((y, x, c), &v) in resized.indexed_iter() {
        out[c * side * side + y * side + x] =
            ((f64::from(v) / 255.0 - CLIP_MEAN[c]) / CLIP_STD[c]) as f32;
    }
    Ok(out)
}
