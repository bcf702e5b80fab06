//! Foundation-model masks: the Segment-Anything (SAM) automatic-mask-generator JSON format
//! (`output_mode="coco_rle"`), read and written exactly as `pycocotools` encodes it.
//!
//! A file is a JSON list, one object per mask:
//! `{"segmentation": {"size": [h, w], "counts": "<COCO compressed RLE>"}, "area": int,
//! "bbox": [x, y, w, h], "predicted_iou": f, "stability_score": f, "point_coords": [[x, y]],
//! "crop_box": [x, y, w, h]}`. Uncompressed RLE (`"counts": [int, ...]`) is accepted too.
//!
//! Also the two feature files that travel with the masks (computed elsewhere, e.g. by CLIP):
//! `features/<stem>.npy` (float32 N×D, one row per SAM mask, [`read_features`]) and
//! `features/prompts.json` (`{"dim": D, "prompts": {text: [D floats]}}`, [`read_prompts_json`]).
//!
//! This module is a reader/writer: it depends on no pipeline stage. `synth::masks` builds
//! *simulated* SAM masks and *simulated* CLIP features from ground truth for the synthetic
//! benchmark; nothing here runs SAM or CLIP. The format, the checks and the noise model are
//! documented in `docs/sam.md`.
//!
//! ## RLE (as `pycocotools/common/maskApi.c`)
//! Pixels are visited in column-major (Fortran) order, index `y + h·x`. `counts` are the run
//! lengths, alternating and starting with a run of zeros (so a mask whose first pixel is set
//! starts with a 0). The compressed string (`rleToString`) stores each count, from index 3 on
//! as the difference to the count two places before, in 5-bit little-endian groups; each
//! character is `48 + group`, with `0x20` = more groups follow and `0x10` of the last group =
//! sign.
//!
//! ## Checks on reading ([`read_sam_json`])
//! Every mask is validated without decoding it to pixels: its RLE must decode (legal
//! characters, no truncated count, counts in `u32`, counts summing to `h·w`), all masks of a
//! file must share one `size` (and match the image size when one is expected), and `area`
//! must equal the RLE's pixel count. A wrong `area` is an **error**, not a warning: SAM
//! computes `area` from the very RLE it writes (`area_from_rle`), so a mismatch means the file
//! was damaged or written by a different tool, and downstream area filters would silently use
//! a wrong number. `bbox` and `point_coords` are not checked (they are informational).
//! Every error names the file and the 0-based index of the mask.
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use ndarray::{Array2, ArrayView2};
use serde::{Deserialize, Deserializer, Serialize};

use crate::fsutil::{self, FsError};
use crate::npy::{self, NpyError};

/// Errors of one RLE (independent of any file).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RleError {
    #[error(
        "compressed counts end inside count {index} (the last character has the continuation bit)"
    )]
    Truncated { index: usize },
    #[error("compressed counts hold byte {byte:#04x} at position {pos}, outside '0'..='o'")]
    BadChar { pos: usize, byte: u8 },
    #[error("compressed count {index} is longer than 7 characters")]
    TooLong { index: usize },
    #[error("count {index} is {value}, outside 0..=4294967295")]
    BadCount { index: usize, value: i64 },
    #[error("counts sum to {sum} pixels but size {h}×{w} holds {expected}")]
    Sum {
        sum: u64,
        h: usize,
        w: usize,
        expected: u64,
    },
}

/// Errors of SAM mask files. Each names the file and, where one is at fault, the mask index.
#[derive(Debug, thiserror::Error)]
pub enum SamError {
    #[error("cannot read {path}: {err}")]
    Read { path: PathBuf, err: std::io::Error },
    #[error("{path}: not a JSON list of SAM masks: {err}")]
    Json {
        path: PathBuf,
        err: serde_json::Error,
    },
    #[error("{path}: mask {index}: {err}")]
    Field {
        path: PathBuf,
        index: usize,
        err: serde_json::Error,
    },
    #[error("{path}: mask {index}: bad RLE: {err}")]
    Rle {
        path: PathBuf,
        index: usize,
        err: RleError,
    },
    #[error("{path}: mask {index}: size [h, w] = {found:?} differs from {expected:?} ({what})")]
    Size {
        path: PathBuf,
        index: usize,
        found: [usize; 2],
        expected: [usize; 2],
        what: &'static str,
    },
    #[error(
        "{path}: mask {index}: size {h}×{w} exceeds the image limit ({} pixels per side, {} megapixels)",
        crate::camera::MAX_IMAGE_SIDE,
        crate::camera::MAX_IMAGE_PIXELS / 1_000_000
    )]
    TooLarge {
        path: PathBuf,
        index: usize,
        h: usize,
        w: usize,
    },
    #[error("{path}: prompt {prompt:?}: {why}")]
    Prompt {
        path: PathBuf,
        prompt: String,
        why: String,
    },
    #[error("{path}: {why}")]
    Features { path: PathBuf, why: String },
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error("{path}: mask {index}: \"area\" is {stated} but its RLE holds {decoded} pixels")]
    Area {
        path: PathBuf,
        index: usize,
        stated: u64,
        decoded: u64,
    },
    #[error(
        "{path}: not a prompts file ({{\"dim\": D, \"prompts\": {{text: [D floats]}}}}): {err}"
    )]
    Prompts {
        path: PathBuf,
        err: serde_json::Error,
    },
    #[error("cannot serialise SAM masks for {path}: {err}")]
    Serialize {
        path: PathBuf,
        err: serde_json::Error,
    },
    #[error("{path}: mask {index}: \"{field}\" is {value:e}, outside {lo}..={hi}")]
    Score {
        path: PathBuf,
        index: usize,
        field: &'static str,
        value: f64,
        lo: f64,
        hi: f64,
    },
    #[error("{path}: mask {index}: {why}")]
    Mask {
        path: PathBuf,
        index: usize,
        why: &'static str,
    },
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// The `counts` of an RLE: COCO's compressed string or the plain list of run lengths.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(
    untagged,
    expecting = "\"counts\" must be COCO's compressed RLE string or a list of non-negative run lengths"
)]
pub enum RleCounts {
    /// `rleToString` text (what SAM's `coco_rle` output holds).
    Compressed(String),
    /// Run lengths, zeros first.
    Uncompressed(Vec<u64>),
}

/// A COCO run-length encoded binary mask (`{"size": [h, w], "counts": ...}`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(
    expecting = "an RLE {\"size\": [h, w], \"counts\": …} (polygon segmentations are not read: write SAM's coco_rle output)"
)]
pub struct Rle {
    /// `[h, w]`.
    pub size: [usize; 2],
    pub counts: RleCounts,
}

/// Builds run lengths, zeros first, from pixel values in column-major order.
struct Runs {
    counts: Vec<u32>,
    value: bool,
    run: u32,
}

impl Runs {
    fn new() -> Self {
        Runs {
            counts: Vec::new(),
            value: false,
            run: 0,
        }
    }
    fn push(&mut self, value: bool, n: usize) {
        if n == 0 {
            return;
        }
        if value != self.value {
            self.counts.push(self.run);
            self.run = 0;
            self.value = value;
        }
        self.run += u32::try_from(n).expect("RLE: more than u32::MAX pixels");
    }
    fn finish(mut self) -> Vec<u32> {
        self.counts.push(self.run);
        self.counts
    }
}

/// `rleToString`: compresses run lengths into COCO's ASCII form.
pub fn counts_to_string(counts: &[u32]) -> String {
    let mut s = Vec::with_capacity(counts.len() * 2);
    for (i, &c) in counts.iter().enumerate() {
        let mut x = i64::from(c);
        if i > 2 {
            x -= i64::from(counts[i - 2]);
        }
        loop {
            let mut c = (x & 0x1f) as u8;
            x >>= 5; // arithmetic shift, as C's `long >>`
            let more = if c & 0x10 != 0 { x != -1 } else { x != 0 };
            if more {
                c |= 0x20;
            }
            s.push(c + 48);
            if !more {
                break;
            }
        }
    }
    String::from_utf8(s).expect("RLE characters are ASCII 48..=111")
}

/// `rleFrString`: decompresses COCO's ASCII form into run lengths. Unlike pycocotools, a
/// truncated string, an illegal character or an out-of-range count is an error.
pub fn counts_from_string(s: &str) -> Result<Vec<u32>, RleError> {
    let b = s.as_bytes();
    let mut counts: Vec<u32> = Vec::with_capacity(b.len());
    let mut p = 0;
    while p < b.len() {
        let index = counts.len();
        let (mut x, mut k) = (0i64, 0u32);
        loop {
            let Some(&byte) = b.get(p) else {
                return Err(RleError::Truncated { index });
            };
            if !(48..=111).contains(&byte) {
                return Err(RleError::BadChar { pos: p, byte });
            }
            if k == 7 {
                return Err(RleError::TooLong { index });
            }
            let c = i64::from(byte - 48);
            x |= (c & 0x1f) << (5 * k);
            p += 1;
            k += 1;
            if c & 0x20 == 0 {
                if c & 0x10 != 0 {
                    x |= -1i64 << (5 * k);
                }
                break;
            }
        }
        if index > 2 {
            x += i64::from(counts[index - 2]);
        }
        let v = u32::try_from(x).map_err(|_| RleError::BadCount { index, value: x })?;
        counts.push(v);
    }
    Ok(counts)
}

impl Rle {
    /// Calls `f` with the row-major index of every set pixel (in RLE order: column-major).
    pub fn for_each_pixel(&self, mut f: impl FnMut(usize)) -> Result<(), RleError> {
        let counts = self.counts()?;
        let [h, w] = self.size;
        let mut k = 0usize;
        for (i, &c) in counts.iter().enumerate() {
            let c = c as usize;
            if i % 2 == 1 {
                for j in k..k + c {
                    // Column-major index j = y + h·x.
                    f((j % h) * w + j / h);
                }
            }
            k += c;
        }
        Ok(())
    }

    /// Encodes a mask (compressed counts), as `pycocotools.mask.encode` on a Fortran array.
    pub fn encode(mask: &Array2<bool>) -> Rle {
        let (h, w) = mask.dim();
        Rle::encode_region(h, w, 0, 0, mask.view())
    }

    /// Encodes an `h×w` mask that is zero outside the window `region` placed at row `y0`,
    /// column `x0` (the window must fit inside the image). Costs `O(w + region area)`.
    pub fn encode_region(
        h: usize,
        w: usize,
        y0: usize,
        x0: usize,
        region: ArrayView2<bool>,
    ) -> Rle {
        let (rh, rw) = region.dim();
        assert!(
            y0 + rh <= h && x0 + rw <= w,
            "Rle::encode_region: window outside the image"
        );
        let mut runs = Runs::new();
        if rh == 0 || rw == 0 {
            runs.push(false, h * w);
        } else {
            runs.push(false, x0 * h);
            for x in 0..rw {
                runs.push(false, y0);
                for y in 0..rh {
                    runs.push(region[[y, x]], 1);
                }
                runs.push(false, h - y0 - rh);
            }
            runs.push(false, (w - x0 - rw) * h);
        }
        Rle::from_counts([h, w], &runs.finish())
    }

    /// An RLE with compressed counts from run lengths (zeros first).
    pub fn from_counts(size: [usize; 2], counts: &[u32]) -> Rle {
        Rle {
            size,
            counts: RleCounts::Compressed(counts_to_string(counts)),
        }
    }

    /// The run lengths, validated: they decode and sum to `h·w`.
    pub fn counts(&self) -> Result<Vec<u32>, RleError> {
        let counts = match &self.counts {
            RleCounts::Compressed(s) => counts_from_string(s)?,
            RleCounts::Uncompressed(v) => v
                .iter()
                .enumerate()
                .map(|(index, &c)| {
                    u32::try_from(c).map_err(|_| RleError::BadCount {
                        index,
                        value: i64::try_from(c).unwrap_or(i64::MAX),
                    })
                })
                .collect::<Result<Vec<u32>, _>>()?,
        };
        let [h, w] = self.size;
        let sum: u64 = counts.iter().map(|&c| u64::from(c)).sum();
        // u128: h·w of two usize values cannot overflow it; a product beyond u64 cannot
        // equal any sum of u32 counts and fails below.
        let expected = u64::try_from(h as u128 * w as u128).unwrap_or(u64::MAX);
        // pycocotools encodes an empty image as [0]; an empty list is accepted for it too.
        if sum != expected {
            return Err(RleError::Sum {
                sum,
                h,
                w,
                expected,
            });
        }
        Ok(counts)
    }

    /// Decodes to an `h×w` mask, as `pycocotools.mask.decode`.
    pub fn decode(&self) -> Result<Array2<bool>, RleError> {
        let counts = self.counts()?;
        let [h, w] = self.size;
        let mut out = Array2::from_elem((h, w), false);
        let mut j = 0usize;
        for (i, &c) in counts.iter().enumerate() {
            let c = c as usize;
            if i % 2 == 1 {
                for k in j..j + c {
                    out[[k % h, k / h]] = true;
                }
            }
            j += c;
        }
        Ok(out)
    }

    /// The number of set pixels (`pycocotools.mask.area`).
    pub fn area(&self) -> Result<u64, RleError> {
        Ok(self
            .counts()?
            .iter()
            .skip(1)
            .step_by(2)
            .map(|&c| u64::from(c))
            .sum())
    }

    /// The same mask with compressed counts.
    pub fn to_compressed(&self) -> Result<Rle, RleError> {
        Ok(Rle::from_counts(self.size, &self.counts()?))
    }

    /// The same mask with uncompressed counts.
    pub fn to_uncompressed(&self) -> Result<Rle, RleError> {
        Ok(Rle {
            size: self.size,
            counts: RleCounts::Uncompressed(self.counts()?.iter().map(|&c| u64::from(c)).collect()),
        })
    }

    /// The bounding box in SAM's convention (`batched_mask_to_box` then `box_xyxy_to_xywh`):
    /// `[x_min, y_min, x_max − x_min, y_max − y_min]` with inclusive maxima, so a one-pixel
    /// mask has width and height 0; `[0, 0, 0, 0]` for an empty mask.
    pub fn sam_bbox(&self) -> Result<[i64; 4], RleError> {
        let counts = self.counts()?;
        let h = self.size[0];
        let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0usize, 0usize);
        let mut j = 0usize;
        for (i, &c) in counts.iter().enumerate() {
            let c = c as usize;
            if i % 2 == 1 && c > 0 {
                let (s, e) = (j, j + c - 1);
                let (cs, ce) = (s / h, e / h);
                x0 = x0.min(cs);
                x1 = x1.max(ce);
                if cs == ce {
                    y0 = y0.min(s % h);
                    y1 = y1.max(e % h);
                } else {
                    y0 = 0;
                    y1 = h - 1;
                }
            }
            j += c;
        }
        if x0 == usize::MAX {
            return Ok([0; 4]);
        }
        Ok([x0 as i64, y0 as i64, (x1 - x0) as i64, (y1 - y0) as i64])
    }
}

/// One mask of SAM's automatic mask generator (`output_mode="coco_rle"`). Unknown extra
/// fields are ignored on reading.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SamMask {
    pub segmentation: Rle,
    /// Pixel count of the mask.
    pub area: u64,
    /// `[x, y, w, h]` in SAM's convention (see [`Rle::sam_bbox`]).
    #[serde(deserialize_with = "de_box")]
    pub bbox: [i64; 4],
    /// SAM's own estimate of the mask's IoU (the automatic generator keeps ≥ `pred_iou_thresh`).
    pub predicted_iou: f64,
    /// IoU of the mask thresholded at ±offset (kept ≥ `stability_score_thresh`).
    pub stability_score: f64,
    /// The prompt point(s) `[x, y]` that produced the mask.
    #[serde(default)]
    pub point_coords: Vec<[f64; 2]>,
    /// The crop `[x, y, w, h]` the mask was generated in (the whole image without crops).
    #[serde(
        default,
        deserialize_with = "de_opt_box",
        skip_serializing_if = "Option::is_none"
    )]
    pub crop_box: Option<[i64; 4]>,
}

fn int_box<E: serde::de::Error>(v: [f64; 4]) -> Result<[i64; 4], E> {
    let mut out = [0i64; 4];
    for (o, x) in out.iter_mut().zip(v) {
        if !x.is_finite() || x.fract() != 0.0 || x.abs() > 1e15 {
            return Err(E::custom(format!(
                "box value {} is not an integer of magnitude ≤ 1e15",
                crate::numfmt::Num(x)
            )));
        }
        *o = x as i64;
    }
    Ok(out)
}

fn de_box<'de, D: Deserializer<'de>>(d: D) -> Result<[i64; 4], D::Error> {
    int_box(<[f64; 4]>::deserialize(d)?)
}

fn de_opt_box<'de, D: Deserializer<'de>>(d: D) -> Result<Option<[i64; 4]>, D::Error> {
    Option::<[f64; 4]>::deserialize(d)?.map(int_box).transpose()
}

impl SamMask {
    /// A mask record from an RLE with SAM's derived fields (area, bbox, whole-image crop box).
    pub fn from_rle(
        segmentation: Rle,
        predicted_iou: f64,
        stability_score: f64,
        point_coords: Vec<[f64; 2]>,
    ) -> Result<SamMask, RleError> {
        let area = segmentation.area()?;
        let bbox = segmentation.sam_bbox()?;
        let [h, w] = segmentation.size;
        Ok(SamMask {
            segmentation,
            area,
            bbox,
            predicted_iou,
            stability_score,
            point_coords,
            crop_box: Some([0, 0, w as i64, h as i64]),
        })
    }

    /// A mask record from a binary mask (see [`SamMask::from_rle`]).
    pub fn from_mask(
        mask: &Array2<bool>,
        predicted_iou: f64,
        stability_score: f64,
        point_coords: Vec<[f64; 2]>,
    ) -> SamMask {
        SamMask::from_rle(
            Rle::encode(mask),
            predicted_iou,
            stability_score,
            point_coords,
        )
        .expect("a freshly encoded RLE is valid")
    }
}

/// Reads a SAM mask JSON file and validates every mask (module docs: RLE, common size, area).
pub fn read_sam_json(path: &Path) -> Result<Vec<SamMask>, SamError> {
    read_sam_json_sized(path, None)
}

/// [`read_sam_json`], additionally requiring every mask to be `[h, w]` = `image_size`, or an
/// integer multiple of it (a view worked at `1/s` of its resolution,
/// [`crate::camera::downscale_factor`]): such masks are validated at their own size and
/// then box-downscaled to `image_size` ([`downscale`]).
pub fn read_sam_json_sized(
    path: &Path,
    image_size: Option<[usize; 2]>,
) -> Result<Vec<SamMask>, SamError> {
    let bytes = std::fs::read(path).map_err(|err| SamError::Read {
        path: path.to_path_buf(),
        err,
    })?;
    parse_sam_json(path, &bytes, image_size)
}

/// Parses the bytes of a SAM mask file (`path` only names it in errors).
pub fn parse_sam_json(
    path: &Path,
    bytes: &[u8],
    image_size: Option<[usize; 2]>,
) -> Result<Vec<SamMask>, SamError> {
    let p = || path.to_path_buf();
    let items: Vec<serde_json::Value> = serde_json::from_slice(crate::fsutil::strip_bom(bytes))
        .map_err(|err| SamError::Json { path: p(), err })?;
    let mut out = Vec::with_capacity(items.len());
    let mut expected = image_size.map(|s| (s, "the image size"));
    // The divisor to the expected image size of a file made at a multiple of it (1: as is).
    let mut factor = 1;
    for (index, item) in items.into_iter().enumerate() {
        if item.get("segmentation").is_some_and(|s| s.is_array()) {
            return Err(SamError::Mask {
                path: p(),
                index,
                why: "\"segmentation\" is a polygon list: only RLE masks ({\"size\": [h, w], \
                      \"counts\": …}) are read; write SAM's output with output_mode \"coco_rle\"",
            });
        }
        let m: SamMask = serde_json::from_value(item).map_err(|err| SamError::Field {
            path: p(),
            index,
            err,
        })?;
        let size = m.segmentation.size;
        let [h, w] = size;
        let side = crate::camera::MAX_IMAGE_SIDE as usize;
        if h > side || w > side || (h as u64) * (w as u64) > crate::camera::MAX_IMAGE_PIXELS {
            return Err(SamError::TooLarge {
                path: p(),
                index,
                h,
                w,
            });
        }
        if let (0, Some([eh, ew])) = (index, image_size)
            && [eh, ew] != size
            && let Some(f) = crate::camera::downscale_factor((w, h), (ew, eh))
        {
            factor = f;
            expected = Some((size, "the size of mask 0"));
        }
        match expected {
            Some((e, what)) if e != size => {
                return Err(SamError::Size {
                    path: p(),
                    index,
                    found: size,
                    expected: e,
                    what,
                });
            }
            Some(_) => {}
            None => expected = Some((size, "the size of mask 0")),
        }
        let decoded = m.segmentation.area().map_err(|err| SamError::Rle {
            path: p(),
            index,
            err,
        })?;
        if decoded != m.area {
            return Err(SamError::Area {
                path: p(),
                index,
                stated: m.area,
                decoded,
            });
        }
        // SAM's IoU head is a regression (a small excess over 1 occurs); the stability score
        // is a ratio of areas.
        for (field, value, lo, hi) in [
            ("predicted_iou", m.predicted_iou, -0.5, 1.5),
            ("stability_score", m.stability_score, 0.0, 1.0),
        ] {
            if !(lo..=hi).contains(&value) {
                return Err(SamError::Score {
                    path: p(),
                    index,
                    field,
                    value,
                    lo,
                    hi,
                });
            }
        }
        out.push(if factor > 1 {
            downscale(&m, factor).map_err(|err| SamError::Rle {
                path: p(),
                index,
                err,
            })?
        } else {
            m
        });
    }
    Ok(out)
}

/// The mask at `1/s` of its resolution (`s ≥ 1`): pixel `(i, j)` of the `⌈h/s⌉ × ⌈w/s⌉` result
/// is set when at least half of the pixels of its `s × s` block (clipped to the image) are; the
/// area and the box are recomputed, the prompt points and the crop box divided by `s`, the
/// scores kept. Works on the runs: `O(runs + area/s + the result's runs)`, never the whole
/// image.
pub fn downscale(m: &SamMask, s: usize) -> Result<SamMask, RleError> {
    let s = s.max(1);
    let [h, w] = m.segmentation.size;
    let (sh, sw) = (h.div_ceil(s), w.div_ceil(s));
    let block = |i: usize, n: usize| ((i + 1) * s).min(n) - i * s;
    // Set pixels per block of the low-resolution column being gathered (`touched`: its rows
    // with any), then written out as runs in column-major order.
    let mut col = vec![0u32; sh];
    let mut touched: Option<(usize, usize)> = None;
    let mut out = Runs::new();
    let mut written = 0usize;
    let mut flush = |xs: usize, col: &mut [u32], touched: &mut Option<(usize, usize)>| {
        let Some((lo, hi)) = touched.take() else {
            return;
        };
        out.push(false, xs * sh + lo - written);
        let bw = block(xs, w);
        for (r, c) in col.iter_mut().enumerate().take(hi + 1).skip(lo) {
            out.push(2 * *c as usize >= block(r, h) * bw, 1);
            *c = 0;
        }
        written = xs * sh + hi + 1;
    };
    let mut current = 0usize;
    let mut j = 0usize;
    for (i, c) in m.segmentation.counts()?.into_iter().enumerate() {
        let end = j + c as usize;
        if i % 2 == 1 {
            // A run of set pixels, column piece by column piece.
            while j < end {
                let (x, y0) = (j / h, j % h);
                let y1 = h.min(y0 + (end - j));
                if x / s != current {
                    flush(current, &mut col, &mut touched);
                    current = x / s;
                }
                for (r, c) in col
                    .iter_mut()
                    .enumerate()
                    .take((y1 - 1) / s + 1)
                    .skip(y0 / s)
                {
                    *c += (y1.min((r + 1) * s) - y0.max(r * s)) as u32;
                }
                touched = Some(touched.map_or((y0 / s, (y1 - 1) / s), |(lo, hi)| {
                    (lo.min(y0 / s), hi.max((y1 - 1) / s))
                }));
                j += y1 - y0;
            }
        }
        j = end;
    }
    flush(current, &mut col, &mut touched);
    out.push(false, sh * sw - written);
    let f = s as f64;
    let mut small = SamMask::from_rle(
        Rle::from_counts([sh, sw], &out.finish()),
        m.predicted_iou,
        m.stability_score,
        m.point_coords
            .iter()
            .map(|&[x, y]| [x / f, y / f])
            .collect(),
    )?;
    let si = s as i64;
    small.crop_box = m
        .crop_box
        .map(|[x, y, bw, bh]| [x / si, y / si, (bw + si - 1) / si, (bh + si - 1) / si]);
    Ok(small)
}

/// Writes masks as a SAM JSON list (compact, one trailing newline), atomically.
pub fn write_sam_json(path: &Path, masks: &[SamMask]) -> Result<(), SamError> {
    let mut text = serde_json::to_vec(masks).map_err(|err| SamError::Serialize {
        path: path.to_path_buf(),
        err,
    })?;
    text.write_all(b"\n").expect("writing to a Vec cannot fail");
    fsutil::write_bytes(path, &text)?;
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Feature files: per-mask image features and text-prompt features.

/// Text-prompt features: prompt text → vector of dimension `dim` (e.g. CLIP text embeddings
/// computed elsewhere). `simulated` is `true` in files written by the synthetic benchmark.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Prompts {
    /// `true` when these vectors are simulations, not real text embeddings.
    #[serde(default)]
    pub simulated: bool,
    /// Feature dimension.
    pub dim: usize,
    /// Prompt text → vector.
    pub prompts: BTreeMap<String, Vec<f32>>,
    /// Optional prompt text → class id (`docs/design.md` class table, −1 = none). Prompts not listed
    /// get their class from their text (`classes::class_from_text`, [`Prompts::class_of`]).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub classes: BTreeMap<String, i32>,
}

impl Prompts {
    /// The class of prompt `text`: the file's `classes` entry, else from its words
    /// ([`crate::classes::class_from_text`]).
    pub fn class_of(&self, text: &str) -> i32 {
        self.classes
            .get(text)
            .copied()
            .unwrap_or_else(|| crate::classes::class_from_text(text))
    }
}

/// Writes per-mask features as a float32 `N×dim` `.npy` (N = 0 gives shape `(0, dim)`).
///
/// # Panics
/// If a row is not `dim` long.
pub fn write_features_npy(path: &Path, dim: usize, features: &[Vec<f32>]) -> Result<(), NpyError> {
    assert!(
        features.iter().all(|f| f.len() == dim),
        "write_features_npy: every feature must have {dim} values"
    );
    let flat: Vec<f32> = features.iter().flatten().copied().collect();
    npy::write(path, &[features.len(), dim], &flat)
}

/// Writes prompts as JSON, atomically.
pub fn write_prompts_json(path: &Path, prompts: &Prompts) -> Result<(), SamError> {
    fsutil::write_json(path, prompts)?;
    Ok(())
}

/// Reads a prompts file (`{"dim": D, "prompts": {text: [D floats]}}`) and checks it
/// ([`parse_prompts_json`]).
pub fn read_prompts_json(path: &Path) -> Result<Prompts, SamError> {
    let bytes = std::fs::read(path).map_err(|err| SamError::Read {
        path: path.to_path_buf(),
        err,
    })?;
    parse_prompts_json(path, &bytes)
}

/// Parses a prompts file: `dim ≥ 1`, every vector has `dim` finite values.
pub fn parse_prompts_json(path: &Path, bytes: &[u8]) -> Result<Prompts, SamError> {
    let p: Prompts = serde_json::from_slice(crate::fsutil::strip_bom(bytes)).map_err(|err| {
        SamError::Prompts {
            path: path.to_path_buf(),
            err,
        }
    })?;
    let bad = |prompt: &str, why: String| SamError::Prompt {
        path: path.to_path_buf(),
        prompt: prompt.to_string(),
        why,
    };
    if p.dim == 0 && !p.prompts.is_empty() {
        return Err(SamError::Features {
            path: path.to_path_buf(),
            why: "\"dim\" is 0".into(),
        });
    }
    for (text, v) in &p.prompts {
        if v.len() != p.dim {
            return Err(bad(
                text,
                format!("has {} values, \"dim\" is {}", v.len(), p.dim),
            ));
        }
        if let Some(k) = v.iter().position(|x| !x.is_finite()) {
            return Err(bad(
                text,
                format!("value {k} is {}, not a finite number", v[k]),
            ));
        }
    }
    Ok(p)
}

/// Reads per-mask features (`features/<stem>.npy`, float32 `N×D`): returns `(N, D, values
/// row-major)`. Every value must be finite and no row all zero; `masks`, when given, must
/// equal `N`.
pub fn read_features(
    path: &Path,
    masks: Option<usize>,
) -> Result<(usize, usize, Vec<f32>), SamError> {
    let (shape, data) = npy::read::<f32>(path)?;
    let bad = |why: String| SamError::Features {
        path: path.to_path_buf(),
        why,
    };
    let [n, d] = shape[..] else {
        return Err(bad(format!(
            "shape {} is not 2-D (one row of features per mask)",
            npy::shape_text(&shape)
        )));
    };
    if let Some(m) = masks
        && m != n
    {
        return Err(bad(format!("{n} feature rows for {m} masks")));
    }
    if let Some(k) = data.iter().position(|x| !x.is_finite()) {
        return Err(bad(format!(
            "row {}, column {}: {} is not a finite number",
            k / d.max(1),
            k % d.max(1),
            data[k]
        )));
    }
    if d == 0 && n > 0 {
        return Err(bad(format!("{n} rows of 0 values (no feature dimension)")));
    }
    if let Some(r) = (0..n).find(|&r| data[r * d..(r + 1) * d].iter().all(|&x| x == 0.0)) {
        return Err(bad(format!(
            "row {r} is all zero: a mask's feature must be a non-zero vector"
        )));
    }
    Ok((n, d, data))
}

/// The per-mask features of one view when the scene has prompts (`prompts`, of dimension
/// `dim`): the file must exist, hold one row per mask of the view's SAM list (`masks`) and
/// have the prompts' dimension ([`read_features`]'s checks besides). Row-major values.
pub fn read_view_features(
    path: &Path,
    masks: usize,
    dim: usize,
    prompts: &Path,
) -> Result<Vec<f32>, SamError> {
    let bad = |why: String| SamError::Features {
        path: path.to_path_buf(),
        why,
    };
    if !path.is_file() {
        return Err(bad(format!(
            "missing: {} exists, so every view with SAM masks needs its per-mask features",
            prompts.display()
        )));
    }
    let (_, d, data) = read_features(path, Some(masks))?;
    if d != dim {
        return Err(bad(format!(
            "feature dimension {d}, but {} has dimension {dim}",
            prompts.display()
        )));
    }
    Ok(data)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_mask(rng: &mut ChaCha8Rng, h: usize, w: usize) -> Array2<bool> {
        let p: f64 = rng.random();
        let blocky = rng.random_bool(0.5);
        let (cy, cx, r) = (
            rng.random_range(0..=h) as f64,
            rng.random_range(0..=w) as f64,
            rng.random_range(0.0..(h + w) as f64),
        );
        Array2::from_shape_fn((h, w), |(y, x)| {
            if blocky {
                ((y as f64 - cy).powi(2) + (x as f64 - cx).powi(2)).sqrt() < r
            } else {
                rng.random::<f64>() < p
            }
        })
    }

    #[test]
    fn downscaled_masks_keep_the_blocks_at_least_half_set() {
        // A hand case: 3×5 at 1/2 → 2×3; blocks (clipped at the edges) with at least half of
        // their pixels set.
        let m = ndarray::array![
            [true, false, true, true, false],
            [false, false, true, false, true],
            [true, true, false, false, true],
        ];
        let small = downscale(&SamMask::from_mask(&m, 0.9, 0.8, vec![[4.0, 2.0]]), 2).unwrap();
        let want = ndarray::array![[false, true, true], [true, false, true]];
        assert_eq!(small.segmentation.decode().unwrap(), want);
        assert_eq!((small.area, small.bbox), (4, [0, 0, 2, 1]));
        assert_eq!(small.point_coords, vec![[2.0, 1.0]]);
        assert_eq!(small.crop_box, Some([0, 0, 3, 2]));
        assert_eq!((small.predicted_iou, small.stability_score), (0.9, 0.8));
        // Random masks against a count over the decoded pixels, block by block.
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for _ in 0..60 {
            let (h, w) = (rng.random_range(1..40), rng.random_range(1..40));
            let m = random_mask(&mut rng, h, w);
            for f in [1usize, 2, 3, 4] {
                let got = downscale(&SamMask::from_mask(&m, 0.5, 0.5, vec![]), f).unwrap();
                let want = Array2::from_shape_fn((h.div_ceil(f), w.div_ceil(f)), |(y, x)| {
                    let b = m.slice(ndarray::s![
                        y * f..((y + 1) * f).min(h),
                        x * f..((x + 1) * f).min(w)
                    ]);
                    2 * b.iter().filter(|&&v| v).count() >= b.len()
                });
                assert_eq!(got.segmentation.decode().unwrap(), want, "{h}×{w} / {f}");
                assert_eq!(got.area, want.iter().filter(|&&v| v).count() as u64);
            }
        }
    }

    #[test]
    fn a_list_at_a_multiple_of_the_image_size_is_read_downscaled() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let masks: Vec<SamMask> = (0..4)
            .map(|_| SamMask::from_mask(&random_mask(&mut rng, 21, 30), 0.8, 0.9, vec![]))
            .collect();
        let bytes = serde_json::to_vec(&masks).unwrap();
        let p = Path::new("v.json");
        let same = parse_sam_json(p, &bytes, Some([21, 30])).unwrap();
        assert_eq!(same, masks);
        let half = parse_sam_json(p, &bytes, Some([11, 15])).unwrap();
        for (a, b) in half.iter().zip(&masks) {
            assert_eq!(*a, downscale(b, 2).unwrap());
        }
        let third = parse_sam_json(p, &bytes, Some([7, 10])).unwrap();
        assert_eq!(third[3], downscale(&masks[3], 3).unwrap());
        // No divisor makes 21×30 into 10×15: one line naming the file, the mask and both sizes.
        let e = parse_sam_json(p, &bytes, Some([10, 15]))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("v.json") && e.contains("[21, 30]") && e.contains("[10, 15]"),
            "{e}"
        );
    }

    fn check_round_trip(m: &Array2<bool>) {
        let r = Rle::encode(m);
        assert_eq!(r.decode().unwrap(), *m, "{r:?}");
        let area = m.iter().filter(|&&v| v).count() as u64;
        assert_eq!(r.area().unwrap(), area);
        let u = r.to_uncompressed().unwrap();
        assert_eq!(u.decode().unwrap(), *m);
        assert_eq!(u.to_compressed().unwrap(), r);
        // The bbox from runs equals the bbox from pixels.
        let set: Vec<(usize, usize)> = m
            .indexed_iter()
            .filter(|(_, v)| **v)
            .map(|(i, _)| i)
            .collect();
        let expect = if set.is_empty() {
            [0; 4]
        } else {
            let y0 = set.iter().map(|p| p.0).min().unwrap();
            let y1 = set.iter().map(|p| p.0).max().unwrap();
            let x0 = set.iter().map(|p| p.1).min().unwrap();
            let x1 = set.iter().map(|p| p.1).max().unwrap();
            [x0 as i64, y0 as i64, (x1 - x0) as i64, (y1 - y0) as i64]
        };
        assert_eq!(r.sam_bbox().unwrap(), expect);
    }

    #[test]
    fn known_strings() {
        // 2×3, column-major 0 1 | 1 0 | 0 0 → counts [1, 2, 3].
        let m = ndarray::arr2(&[[false, true, false], [true, false, false]]);
        let r = Rle::encode(&m);
        assert_eq!(r.counts, RleCounts::Compressed("123".into()));
        assert_eq!(r.decode().unwrap(), m);
        // First pixel set: counts start with 0.
        let full = Array2::from_elem((2, 2), true);
        assert_eq!(Rle::encode(&full).counts().unwrap(), vec![0, 4]);
        // Delta coding from index 3 and negative deltas (sign bit) survive.
        for counts in [
            vec![5, 100, 3, 2, 1000, 1, 70000, 0, 7],
            vec![0, 1, 0, 1],
            vec![4294967295],
            vec![0, 4294967295],
        ] {
            let s = counts_to_string(&counts);
            assert_eq!(counts_from_string(&s).unwrap(), counts, "{s}");
        }
        assert_eq!(counts_to_string(&[]), "");
        assert_eq!(counts_to_string(&[0]), "0");
        assert_eq!(counts_to_string(&[31]), "o0"); // 31 has the sign bit: needs two groups
        assert_eq!(counts_to_string(&[15]), "?");
    }

    #[test]
    fn round_trip_random_and_edge_masks() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for (h, w) in [(1, 1), (1, 9), (9, 1), (3, 3), (17, 5), (40, 64)] {
            check_round_trip(&Array2::from_elem((h, w), false));
            check_round_trip(&Array2::from_elem((h, w), true));
            for _ in 0..3 {
                let mut one = Array2::from_elem((h, w), false);
                one[[rng.random_range(0..h), rng.random_range(0..w)]] = true;
                check_round_trip(&one);
                let mut row = Array2::from_elem((h, w), false);
                row.row_mut(rng.random_range(0..h)).fill(true);
                check_round_trip(&row);
                let mut col = Array2::from_elem((h, w), false);
                col.column_mut(rng.random_range(0..w)).fill(true);
                check_round_trip(&col);
            }
            for _ in 0..20 {
                check_round_trip(&random_mask(&mut rng, h, w));
            }
        }
        // Empty image.
        let e = Array2::from_elem((0, 4), false);
        let r = Rle::encode(&e);
        assert_eq!(r.counts().unwrap(), vec![0]);
        assert_eq!(r.decode().unwrap().dim(), (0, 4));
    }

    #[test]
    fn region_encoding_equals_full_encoding() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..50 {
            let (h, w) = (rng.random_range(1..20), rng.random_range(1..20));
            let (rh, rw) = (rng.random_range(0..=h), rng.random_range(0..=w));
            let (y0, x0) = (rng.random_range(0..=h - rh), rng.random_range(0..=w - rw));
            let region = random_mask(&mut rng, rh, rw);
            let mut full = Array2::from_elem((h, w), false);
            full.slice_mut(ndarray::s![y0..y0 + rh, x0..x0 + rw])
                .assign(&region);
            assert_eq!(
                Rle::encode_region(h, w, y0, x0, region.view()),
                Rle::encode(&full)
            );
        }
    }

    #[test]
    fn bad_strings_are_errors() {
        let ok = counts_to_string(&[3, 70000, 2]);
        // The middle count needs several characters; cut inside it.
        let cut = &ok[..2];
        assert_eq!(
            counts_from_string(cut),
            Err(RleError::Truncated { index: 1 })
        );
        assert_eq!(
            counts_from_string("1 2"),
            Err(RleError::BadChar { pos: 1, byte: b' ' })
        );
        assert!(matches!(
            counts_from_string("oooooooo0"),
            Err(RleError::TooLong { index: 0 })
        ));
        // A negative first count.
        assert!(matches!(
            counts_from_string("O"),
            Err(RleError::BadCount { index: 0, .. })
        ));
        let r = Rle {
            size: [2, 2],
            counts: RleCounts::Uncompressed(vec![1, 2]),
        };
        assert!(matches!(r.decode(), Err(RleError::Sum { sum: 3, .. })));
    }
}
