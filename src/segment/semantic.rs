//! `gs4city segment --semantic MODEL.onnx`: a semantic segmentation network as the perception
//! source (docs/segment.md, "Semantic networks"). Per image of `S/images/`: the network's class
//! probabilities (tiles at the network's working size, softmax, averaged where tiles overlap)
//! → per-pixel argmax → per class of the card that maps to an evaluation class
//! ([`crate::classes::CITYSCAPES`], [`crate::classes::ADE20K`]), the 8-connected components,
//! those below the area threshold dropped → `S/masks/<stem>.json` (SAM format; predicted IoU =
//! the mean probability of the component's class over its pixels, stability = the share of its
//! pixels where that probability is at least 0.5) and `S/features/<stem>.npy` (one row per
//! mask: its mean class probabilities), with `S/features/prompts.json` holding each mapped
//! class as a one-hot prompt of its name and its evaluation class.
//!
//! The model card `MODEL.json` beside `MODEL.onnx` ([`ModelCard`]) says how the network wants
//! its input; without it, or when the network's class count differs from the card's, the
//! command stops with one line naming the file.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use ndarray::{Array2, Array3};
use ort::session::Session;

use super::{SegmentError, list_images, mask_path, model};
use crate::classes::{self, ClassTable};
use crate::sam::{self, Prompts, SamMask};

/// Most bytes the per-pixel class probabilities of one image may take (classes × pixels × 4).
pub const MAX_PROBABILITY_BYTES: u64 = 4 << 30;
/// Tiles overlap by at least this share of the tile along an axis with more than one tile.
pub const MIN_TILE_OVERLAP: f64 = 0.25;

/// The model card beside a semantic network (`MODEL.json` for `MODEL.onnx`).
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ModelCard {
    /// What the network is (informational).
    #[serde(default)]
    pub name: String,
    /// The input tensor (`[1, 3, H, W]` float); default the graph's first input.
    #[serde(default)]
    pub input: Option<String>,
    /// The output tensor (`[1, C, h, w]`, logits or probabilities); default the first output.
    #[serde(default)]
    pub output: Option<String>,
    /// Whether the output holds probabilities already (else logits: softmax here).
    #[serde(default)]
    pub output_probabilities: bool,
    /// The working size `[height, width]`: images larger along an axis run in tiles of it.
    pub tile: [usize; 2],
    /// The input's height and width must be multiples of this (e.g. 8, 32).
    #[serde(default = "one")]
    pub multiple_of: usize,
    /// `"RGB"` or `"BGR"`: the order of the input channels (and of `mean`, `std`).
    pub channel_order: String,
    /// Per channel, in `channel_order`.
    pub mean: [f64; 3],
    pub std: [f64; 3],
    /// The divisor of the `"scale"` step (usually 255).
    pub scale: f64,
    /// The order in which the byte value `v` (0–255) is normalised: each of `"mean"` (`v −
    /// mean`), `"std"` (`v / std`) and `"scale"` (`v / scale`) once.
    pub steps: Vec<String>,
    /// `"cityscapes"` or `"ade20k"`: the table that maps `classes` onto the evaluation classes.
    pub class_table: String,
    /// The output channels' class names, in order (each a name of the class table).
    pub classes: Vec<String>,
    /// Licence and source (informational).
    #[serde(default)]
    pub license: String,
    #[serde(default)]
    pub source: String,
}

fn one() -> usize {
    1
}

/// The card of `onnx`: `MODEL.json` beside `MODEL.onnx`.
pub fn card_path(onnx: &Path) -> PathBuf {
    onnx.with_extension("json")
}

impl ModelCard {
    /// Reads and checks a card: its class table is known and names every class, the steps are
    /// `mean`, `std` and `scale` once each, sizes and divisors are positive.
    pub fn read(path: &Path) -> Result<(ModelCard, Vec<Option<i32>>), SegmentError> {
        let bad = |why: String| SegmentError::Model {
            path: path.to_path_buf(),
            why,
        };
        let card: ModelCard = crate::fsutil::read_json(path).map_err(|e| bad(e.to_string()))?;
        let table: ClassTable = classes::class_table(&card.class_table).ok_or_else(|| {
            bad(format!(
                "class_table {:?} is not a known table (cityscapes, ade20k)",
                card.class_table
            ))
        })?;
        let mut mapped = Vec::with_capacity(card.classes.len());
        for (k, name) in card.classes.iter().enumerate() {
            let c = table
                .iter()
                .find(|(n, _)| n.eq_ignore_ascii_case(name.trim()))
                .ok_or_else(|| {
                    bad(format!(
                        "class {k} {name:?} is not a class of the {} table",
                        card.class_table
                    ))
                })?;
            mapped.push(c.1);
        }
        if card.classes.len() < 2 {
            return Err(bad(format!("{} classes (at least 2)", card.classes.len())));
        }
        let mut steps = card.steps.clone();
        steps.sort();
        if steps != ["mean", "scale", "std"] {
            return Err(bad(format!(
                "steps {:?} must name \"mean\", \"std\" and \"scale\" once each, in their order of application",
                card.steps
            )));
        }
        if !matches!(card.channel_order.as_str(), "RGB" | "BGR") {
            return Err(bad(format!(
                "channel_order {:?} is neither \"RGB\" nor \"BGR\"",
                card.channel_order
            )));
        }
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !(card.std.iter().all(|&s| positive(s))
            && positive(card.scale)
            && card.mean.iter().all(|m| m.is_finite()))
        {
            return Err(bad("mean must be finite, std and scale positive".into()));
        }
        if card.multiple_of == 0
            || card
                .tile
                .iter()
                .any(|&t| t == 0 || t % card.multiple_of != 0)
        {
            return Err(bad(format!(
                "tile {:?} must be positive multiples of multiple_of {}",
                card.tile, card.multiple_of
            )));
        }
        if !mapped.iter().any(|c| c.is_some_and(classes::is_building))
            || !mapped
                .iter()
                .any(|c| c.is_some_and(|c| c > classes::INSTALLATION))
        {
            return Err(bad(
                "the classes map to no building class or no foreground class (the masks stage's features test needs both)".into(),
            ));
        }
        Ok((card, mapped))
    }

    /// The network input of byte `v` of channel `c` (in `channel_order`), in `f64` then `f32`.
    pub fn normalise(&self, v: u8, c: usize) -> f32 {
        let mut x = f64::from(v);
        for s in &self.steps {
            match s.as_str() {
                "mean" => x -= self.mean[c],
                "std" => x /= self.std[c],
                _ => x /= self.scale,
            }
        }
        x as f32
    }
}

/// The tile origins along an axis of `len` pixels for tiles of `tile` (module docs): one tile
/// when it fits, else evenly spaced tiles overlapping by at least [`MIN_TILE_OVERLAP`].
pub fn tile_starts(len: usize, tile: usize) -> Vec<usize> {
    if len <= tile {
        return vec![0];
    }
    let stride = (tile as f64 * (1.0 - MIN_TILE_OVERLAP)).max(1.0);
    let n = ((len - tile) as f64 / stride).ceil() as usize + 1;
    (0..n)
        .map(|k| ((k * (len - tile)) as f64 / (n - 1) as f64).round() as usize)
        .collect()
}

/// A semantic network and its card.
pub struct SemanticModel {
    pub path: PathBuf,
    pub card_path: PathBuf,
    pub card: ModelCard,
    /// Per output channel: its evaluation class (`None`: none).
    pub mapped: Vec<Option<i32>>,
    session: Session,
    input: String,
    output: String,
}

/// Per-pixel class probabilities of one image: `classes × h × w`, row-major per class.
pub struct Probabilities {
    pub classes: usize,
    pub h: usize,
    pub w: usize,
    pub data: Vec<f32>,
}

impl Probabilities {
    /// The argmax class of every pixel (ties: the lower class).
    pub fn argmax(&self) -> Array2<u16> {
        let plane = self.h * self.w;
        Array2::from_shape_fn((self.h, self.w), |(y, x)| {
            let i = y * self.w + x;
            let mut best = 0;
            for k in 1..self.classes {
                if self.data[k * plane + i] > self.data[best * plane + i] {
                    best = k;
                }
            }
            best as u16
        })
    }
}

impl SemanticModel {
    /// Opens `onnx` and its card; checks the network's class count against the card's.
    pub fn open(onnx: &Path, threads: usize) -> Result<SemanticModel, SegmentError> {
        if !onnx.is_file() {
            return Err(SegmentError::Model {
                path: onnx.to_path_buf(),
                why: "no such file".into(),
            });
        }
        let card_path = card_path(onnx);
        if !card_path.is_file() {
            return Err(SegmentError::Model {
                path: onnx.to_path_buf(),
                why: format!(
                    "no model card {} beside it (input tile, channel order, mean/std/scale and their order, class names, class table: docs/segment.md)",
                    card_path.display()
                ),
            });
        }
        let (card, mapped) = ModelCard::read(&card_path)?;
        let session = model::open_session(onnx, threads)?;
        let input = match &card.input {
            Some(n) => {
                model::input_shape(&session, onnx, n)?;
                n.clone()
            }
            None => session
                .inputs()
                .first()
                .map(|o| o.name().to_string())
                .ok_or_else(|| SegmentError::Model {
                    path: onnx.to_path_buf(),
                    why: "has no input".into(),
                })?,
        };
        let output = match &card.output {
            Some(n) => {
                model::require_outputs(&session, onnx, &[n.as_str()])?;
                n.clone()
            }
            None => session
                .outputs()
                .first()
                .map(|o| o.name().to_string())
                .ok_or_else(|| SegmentError::Model {
                    path: onnx.to_path_buf(),
                    why: "has no output".into(),
                })?,
        };
        let mut m = SemanticModel {
            path: onnx.to_path_buf(),
            card_path,
            card,
            mapped,
            session,
            input,
            output,
        };
        // the class count: a probe of the smallest input the network takes
        let side = m.card.multiple_of.max(8) * 4;
        let (c, _, _, _) = m.infer(&vec![0f32; 3 * side * side], side, side)?;
        if c != m.card.classes.len() {
            return Err(SegmentError::Model {
                path: m.path.clone(),
                why: format!(
                    "gives {c} classes, its card {} names {}",
                    m.card_path.display(),
                    m.card.classes.len()
                ),
            });
        }
        Ok(m)
    }

    /// One network call on a normalised `3 × th × tw` tile → (classes, out h, out w, values).
    fn infer(
        &mut self,
        input: &[f32],
        th: usize,
        tw: usize,
    ) -> Result<(usize, usize, usize, Vec<f32>), SegmentError> {
        let t = model::tensor(&[1, 3, th, tw], input.to_vec(), &self.path)?;
        let out = self
            .session
            .run(ort::inputs![self.input.as_str() => t])
            .map_err(|e| super::run_err(&self.path, e))?;
        let (shape, data) = out[self.output.as_str()]
            .try_extract_tensor::<f32>()
            .map_err(|e| super::run_err(&self.path, e))?;
        let s: Vec<i64> = shape.iter().copied().collect();
        if s.len() != 4 || s[0] != 1 || s.iter().any(|&d| d <= 0) {
            return Err(SegmentError::Model {
                path: self.path.clone(),
                why: format!(
                    "output `{}` has shape {s:?} for a [1, 3, {th}, {tw}] input; [1, classes, h, w] expected",
                    self.output
                ),
            });
        }
        Ok((s[1] as usize, s[2] as usize, s[3] as usize, data.to_vec()))
    }

    /// The class probabilities of an RGB image (module docs): tiles of the card's working size
    /// (an axis shorter than the tile: the image's length rounded up to `multiple_of`, the
    /// last row or column repeated), each normalised, run, brought to the tile's size
    /// (bilinear, half-pixel centres, where the network's output is smaller), softmax (unless
    /// the card says probabilities), averaged where tiles overlap.
    pub fn probabilities(&mut self, rgb: &Array3<u8>) -> Result<Probabilities, SegmentError> {
        let (h, w, _) = rgb.dim();
        let c = self.card.classes.len();
        let bytes = (c as u64) * (h as u64) * (w as u64) * 4;
        if bytes > MAX_PROBABILITY_BYTES {
            return Err(SegmentError::Options(format!(
                "a {w}×{h} image needs {:.1} GiB of class probabilities for {c} classes (at most {} GiB): downscale the images",
                bytes as f64 / f64::from(1u32 << 30),
                MAX_PROBABILITY_BYTES >> 30
            )));
        }
        let m = self.card.multiple_of;
        let th = self.card.tile[0].min(h.div_ceil(m) * m);
        let tw = self.card.tile[1].min(w.div_ceil(m) * m);
        let bgr = self.card.channel_order == "BGR";
        let plane = h * w;
        let mut sum = vec![0f32; c * plane];
        let mut count = vec![0u16; plane];
        let mut input = vec![0f32; 3 * th * tw];
        let mut probs = vec![0f32; c * th * tw];
        for &y0 in &tile_starts(h, th) {
            for &x0 in &tile_starts(w, tw) {
                for ty in 0..th {
                    let y = (y0 + ty).min(h - 1);
                    for tx in 0..tw {
                        let x = (x0 + tx).min(w - 1);
                        for ch in 0..3 {
                            let src = if bgr { 2 - ch } else { ch };
                            input[ch * th * tw + ty * tw + tx] =
                                self.card.normalise(rgb[[y, x, src]], ch);
                        }
                    }
                }
                let (oc, oh, ow, out) = self.infer(&input, th, tw)?;
                if oc != c {
                    return Err(SegmentError::Model {
                        path: self.path.clone(),
                        why: format!(
                            "gives {oc} classes, its card {} names {c}",
                            self.card_path.display()
                        ),
                    });
                }
                resize_planes(&out, c, oh, ow, th, tw, &mut probs);
                if !self.card.output_probabilities {
                    softmax_in_place(&mut probs, c, th * tw);
                }
                for ty in 0..th.min(h - y0) {
                    for tx in 0..tw.min(w - x0) {
                        let i = (y0 + ty) * w + x0 + tx;
                        count[i] += 1;
                        for k in 0..c {
                            sum[k * plane + i] += probs[k * th * tw + ty * tw + tx];
                        }
                    }
                }
            }
        }
        for k in 0..c {
            for (v, &n) in sum[k * plane..(k + 1) * plane].iter_mut().zip(&count) {
                *v /= f32::from(n.max(1));
            }
        }
        if sum.iter().any(|v| !v.is_finite()) {
            return Err(SegmentError::Model {
                path: self.path.clone(),
                why: "gave a non-finite class score".into(),
            });
        }
        Ok(Probabilities {
            classes: c,
            h,
            w,
            data: sum,
        })
    }
}

/// Softmax over `c` planes of `n` values each, in place (max subtracted, `f32`).
fn softmax_in_place(p: &mut [f32], c: usize, n: usize) {
    for i in 0..n {
        let m = (0..c)
            .map(|k| p[k * n + i])
            .fold(f32::NEG_INFINITY, f32::max);
        let mut s = 0f32;
        for k in 0..c {
            let e = (p[k * n + i] - m).exp();
            p[k * n + i] = e;
            s += e;
        }
        for k in 0..c {
            p[k * n + i] /= s;
        }
    }
}

/// Planes `c × ih × iw` brought to `c × oh × ow`: copied when equal, else bilinear with
/// half-pixel centres and clamped edges (PyTorch's `interpolate(align_corners=False)`).
fn resize_planes(
    src: &[f32],
    c: usize,
    ih: usize,
    iw: usize,
    oh: usize,
    ow: usize,
    out: &mut [f32],
) {
    if (ih, iw) == (oh, ow) {
        out.copy_from_slice(&src[..c * oh * ow]);
        return;
    }
    let axis = |o: usize, i: usize| -> Vec<(usize, usize, f32)> {
        (0..o)
            .map(|k| {
                let s = ((k as f64 + 0.5) * i as f64 / o as f64 - 0.5).max(0.0);
                let a = (s.floor() as usize).min(i - 1);
                let b = (a + 1).min(i - 1);
                (a, b, (s - a as f64) as f32)
            })
            .collect()
    };
    let (ys, xs) = (axis(oh, ih), axis(ow, iw));
    for k in 0..c {
        let p = &src[k * ih * iw..(k + 1) * ih * iw];
        for (oy, &(y0, y1, fy)) in ys.iter().enumerate() {
            for (ox, &(x0, x1, fx)) in xs.iter().enumerate() {
                let top = p[y0 * iw + x0] * (1.0 - fx) + p[y0 * iw + x1] * fx;
                let bot = p[y1 * iw + x0] * (1.0 - fx) + p[y1 * iw + x1] * fx;
                out[k * oh * ow + oy * ow + ox] = top * (1.0 - fy) + bot * fy;
            }
        }
    }
}

/// The masks and their features of one image's probabilities (module docs): per class of the
/// card that maps to an evaluation class, in card order, its 8-connected components of at least
/// `min_area` pixels in label order (OpenCV's raster order).
pub fn masks(
    p: &Probabilities,
    mapped: &[Option<i32>],
    min_area: usize,
) -> Result<(Vec<SamMask>, Vec<Vec<f32>>), SegmentError> {
    let labels = p.argmax();
    let plane = p.h * p.w;
    let mut out = Vec::new();
    let mut feats = Vec::new();
    for (k, m) in mapped.iter().enumerate() {
        if m.is_none() {
            continue;
        }
        let bin = labels.mapv(|l| u8::from(usize::from(l) == k));
        if !bin.iter().any(|&b| b != 0) {
            continue;
        }
        let (lab, areas) = crate::imageio::connected_components(&bin)?;
        // per component: pixel sum of each class's probability, pixels at p_k ≥ 0.5, centroid
        let n = areas.len();
        let mut sums = vec![0f64; n * p.classes];
        let mut sure = vec![0usize; n];
        let mut centre = vec![(0f64, 0f64); n];
        for ((y, x), &l) in lab.indexed_iter() {
            let l = l as usize;
            if l == 0 || areas[l] < min_area {
                continue;
            }
            let i = y * p.w + x;
            for c in 0..p.classes {
                sums[l * p.classes + c] += f64::from(p.data[c * plane + i]);
            }
            if p.data[k * plane + i] >= 0.5 {
                sure[l] += 1;
            }
            centre[l].0 += x as f64;
            centre[l].1 += y as f64;
        }
        for l in 1..n {
            if areas[l] < min_area {
                continue;
            }
            let a = areas[l] as f64;
            let mask = lab.mapv(|v| v as usize == l);
            let (cx, cy) = (centre[l].0 / a, centre[l].1 / a);
            // the component's pixel nearest its centroid
            let point = lab
                .indexed_iter()
                .filter(|(_, v)| **v as usize == l)
                .map(|((y, x), _)| (x as f64, y as f64))
                .min_by(|p1, p2| {
                    let d = |q: &(f64, f64)| (q.0 - cx).powi(2) + (q.1 - cy).powi(2);
                    d(p1).total_cmp(&d(p2))
                })
                .unwrap_or((cx, cy));
            let mean: Vec<f32> = (0..p.classes)
                .map(|c| (sums[l * p.classes + c] / a) as f32)
                .collect();
            out.push(SamMask::from_mask(
                &mask,
                f64::from(mean[k]),
                sure[l] as f64 / a,
                vec![[point.0, point.1]],
            ));
            feats.push(mean);
        }
    }
    Ok((out, feats))
}

/// The one-hot prompts of a card: each class that maps to an evaluation class, by its name.
pub fn prompts(card: &ModelCard, mapped: &[Option<i32>]) -> Prompts {
    let dim = card.classes.len();
    let mut p = BTreeMap::new();
    let mut c = BTreeMap::new();
    for (k, (name, m)) in card.classes.iter().zip(mapped).enumerate() {
        if let Some(class) = m {
            let mut v = vec![0f32; dim];
            v[k] = 1.0;
            p.insert(name.clone(), v);
            c.insert(name.clone(), *class);
        }
    }
    Prompts {
        simulated: false,
        dim,
        prompts: p,
        classes: c,
    }
}

/// The options of `segment --semantic`.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct SemanticOptions {
    /// Components smaller than this many pixels are dropped; 0 = 1/2000 of the image's pixels.
    pub min_area: usize,
    /// ONNX Runtime intra-op threads (0 = its default).
    pub threads: usize,
}

/// The area threshold of an `h × w` image.
pub fn min_area(o: &SemanticOptions, h: usize, w: usize) -> usize {
    if o.min_area > 0 {
        o.min_area
    } else {
        (h * w).div_ceil(2000)
    }
}

/// What `segment --semantic` did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct SemanticSummary {
    pub segmented: usize,
    pub skipped: usize,
    pub masks: usize,
    /// Seconds in the network (normalisation, tiles, softmax).
    pub network_s: f64,
    /// Seconds for components, masks, features and files.
    pub post_s: f64,
}

/// Segments every image of `scene/images/` whose masks and features are not complete.
pub fn run(
    scene: &Path,
    onnx: &Path,
    o: &SemanticOptions,
) -> Result<SemanticSummary, SegmentError> {
    let images = list_images(&scene.join("images"))?;
    let masks_dir = scene.join("masks");
    let feat_dir = scene.join("features");
    let prompts_path = feat_dir.join("prompts.json");
    // the card first: a missing or wrong card stops before anything is read or written
    let cp = card_path(onnx);
    if !cp.is_file() {
        // the same one line the model gives
        SemanticModel::open(onnx, o.threads)?;
    }
    let (card, mapped) = ModelCard::read(&cp)?;
    let ours = prompts(&card, &mapped);
    let theirs = if prompts_path.is_file() {
        Some(sam::read_prompts_json(&prompts_path)?)
    } else {
        None
    };
    let same = theirs.as_ref().is_some_and(|p| {
        !p.simulated && p.dim == ours.dim && p.prompts == ours.prompts && p.classes == ours.classes
    });
    let any_masks = images.iter().any(|i| mask_path(&masks_dir, i).is_file());
    if any_masks && !same {
        return Err(SegmentError::Image {
            path: masks_dir,
            why: format!(
                "holds masks that {} did not make (its features/prompts.json is missing or another model's): move masks/ and features/ away to segment with it",
                onnx.display()
            ),
        });
    }
    let todo: Vec<&PathBuf> = images
        .iter()
        .filter(|i| {
            let mp = mask_path(&masks_dir, i);
            let fp = super::features::features_path(&feat_dir, i);
            let done = mp.is_file()
                && fp.is_file()
                && sam::read_sam_json(&mp)
                    .ok()
                    .and_then(|m| sam::read_features(&fp, Some(m.len())).ok())
                    .is_some_and(|(_, d, _)| d == ours.dim);
            !done
        })
        .collect();
    let mut summary = SemanticSummary {
        skipped: images.len() - todo.len(),
        ..Default::default()
    };
    if todo.is_empty() {
        return Ok(summary);
    }
    let mut model = SemanticModel::open(onnx, o.threads)?;
    crate::fsutil::create_dir(&masks_dir)?;
    crate::fsutil::create_dir(&feat_dir)?;
    // the prompts first: every mask file written after them has its features beside it
    if !same {
        sam::write_prompts_json(&prompts_path, &ours)?;
    }
    let bar = crate::progress::Bar::new("segment", todo.len() as u64, "images");
    for path in todo {
        bar.message(
            path.file_name()
                .map(|n| n.to_string_lossy().to_string())
                .unwrap_or_default(),
        );
        let rgb = crate::imageio::read_rgb(path)?;
        let t = Instant::now();
        let p = model.probabilities(&rgb).map_err(|e| match e {
            SegmentError::Options(why) => SegmentError::Image {
                path: path.clone(),
                why,
            },
            e => e,
        })?;
        summary.network_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (h, w, _) = rgb.dim();
        let (ms, feats) = masks(&p, &model.mapped, min_area(o, h, w))?;
        // features before masks: a mask file never lacks its features
        sam::write_features_npy(
            &super::features::features_path(&feat_dir, path),
            ours.dim,
            &feats,
        )
        .map_err(sam::SamError::from)?;
        sam::write_sam_json(&mask_path(&masks_dir, path), &ms)?;
        summary.post_s += t.elapsed().as_secs_f64();
        summary.segmented += 1;
        summary.masks += ms.len();
        bar.inc(1);
    }
    bar.finish();
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_cover_the_axis_with_overlap() {
        assert_eq!(tile_starts(500, 512), vec![0]);
        assert_eq!(tile_starts(768, 512), vec![0, 256]);
        assert_eq!(tile_starts(2048, 1024), vec![0, 512, 1024]);
        for (len, t) in [(1000, 300), (4032, 1024), (513, 512)] {
            let s = tile_starts(len, t);
            assert_eq!(s[0], 0);
            assert_eq!(*s.last().unwrap() + t, len);
            for w in s.windows(2) {
                assert!(w[1] > w[0] && w[1] - w[0] <= (t as f64 * 0.75).ceil() as usize);
            }
        }
    }

    #[test]
    fn bilinear_upsampling_has_half_pixel_centres() {
        // one plane 1×2 → 1×4: centres at −0.25, 0.25, 0.75, 1.25 of the input → clamped
        let mut out = vec![0f32; 4];
        resize_planes(&[0.0, 4.0], 1, 1, 2, 1, 4, &mut out);
        assert_eq!(out, vec![0.0, 1.0, 3.0, 4.0]);
    }

    #[test]
    fn one_hot_prompts_name_the_mapped_classes() {
        let card: ModelCard = serde_json::from_value(serde_json::json!({
            "tile": [8, 8], "channel_order": "RGB", "mean": [0.0, 0.0, 0.0],
            "std": [1.0, 1.0, 1.0], "scale": 1.0, "steps": ["scale", "mean", "std"],
            "class_table": "cityscapes", "classes": ["building", "vegetation", "void"]
        }))
        .unwrap();
        let p = prompts(&card, &[Some(0), Some(6), None]);
        assert_eq!(p.dim, 3);
        assert_eq!(p.prompts["vegetation"], vec![0.0, 1.0, 0.0]);
        assert_eq!(p.classes["building"], 0);
        assert!(!p.prompts.contains_key("void"));
    }
}
