//! Image files through OpenCV (the only module that imports `opencv`): 8-bit RGB images as
//! `ndarray` `H×W×3` arrays, PNG writing (the `png` crate's encoder), and OpenCV's connected
//! components on label masks.
use std::path::{Path, PathBuf};

use ndarray::Array3;
use opencv::core::{Mat, Vector};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};

use crate::fsutil::FsError;

/// Errors of image reading and writing.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("cannot read image {path}: {why}")]
    Read { path: PathBuf, why: String },
    #[error("cannot write image {path}: {why}")]
    Write { path: PathBuf, why: String },
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error("OpenCV {op} failed: {why}")]
    Cv { op: &'static str, why: String },
}

/// The width and height a PNG or JPEG header declares (`None` for other formats or a header
/// that cannot be parsed; OpenCV then reports what it finds).
pub fn declared_size(bytes: &[u8]) -> Option<(u32, u32)> {
    if bytes.starts_with(b"\x89PNG\r\n\x1a\n") && bytes.get(12..16) == Some(b"IHDR") {
        let be = |o: usize| Some(u32::from_be_bytes(bytes.get(o..o + 4)?.try_into().ok()?));
        return Some((be(16)?, be(20)?));
    }
    if !bytes.starts_with(&[0xFF, 0xD8]) {
        return None;
    }
    // JPEG: walk the marker segments to the first start-of-frame.
    let mut i = 2;
    while i + 4 <= bytes.len() {
        if bytes[i] != 0xFF {
            return None;
        }
        let marker = bytes[i + 1];
        match marker {
            0xFF => i += 1, // fill byte
            0x01 | 0xD0..=0xD7 => i += 2,
            0xC0..=0xC3 | 0xC5..=0xC7 | 0xC9..=0xCB | 0xCD..=0xCF => {
                let h = u16::from_be_bytes([*bytes.get(i + 5)?, *bytes.get(i + 6)?]);
                let w = u16::from_be_bytes([*bytes.get(i + 7)?, *bytes.get(i + 8)?]);
                return Some((u32::from(w), u32::from(h)));
            }
            _ => {
                let len = usize::from(u16::from_be_bytes([bytes[i + 2], bytes[i + 3]]));
                i += 2 + len;
            }
        }
    }
    None
}

/// Reads an image file (PNG, JPEG, …) as 8-bit RGB, `H×W×3`. A PNG or JPEG whose header
/// declares more than `camera::MAX_IMAGE_PIXELS` is refused before it is decoded.
pub fn read_rgb(path: &Path) -> Result<Array3<u8>, ImageError> {
    let err = |why: String| ImageError::Read {
        path: path.to_path_buf(),
        why: why.replace('\n', " "),
    };
    let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
    if let Some((w, h)) = declared_size(&bytes) {
        let px = u64::from(w) * u64::from(h);
        let side = crate::camera::MAX_IMAGE_SIDE;
        if px > crate::camera::MAX_IMAGE_PIXELS || w > side || h > side {
            return Err(err(format!(
                "its header declares {w}×{h} pixels ({:.1} megapixels), beyond the limit of {side} pixels per side and {} megapixels",
                px as f64 / 1e6,
                crate::camera::MAX_IMAGE_PIXELS / 1_000_000
            )));
        }
    }
    let buf = Vector::<u8>::from_slice(&bytes);
    let bgr = imgcodecs::imdecode(&buf, imgcodecs::IMREAD_COLOR).map_err(|e| err(e.to_string()))?;
    if bgr.empty() {
        return Err(err("OpenCV could not decode it".into()));
    }
    let (h, w) = (bgr.rows() as usize, bgr.cols() as usize);
    let mut rgb = Mat::default();
    imgproc::cvt_color_def(&bgr, &mut rgb, imgproc::COLOR_BGR2RGB)
        .map_err(|e| err(e.to_string()))?;
    let rgb = if rgb.is_continuous() {
        rgb
    } else {
        rgb.try_clone().map_err(|e| err(e.to_string()))?
    };
    let bytes = rgb.data_bytes().map_err(|e| err(e.to_string()))?;
    Array3::from_shape_vec((h, w, 3), bytes.to_vec()).map_err(|e| err(e.to_string()))
}

/// [`read_rgb`] for a view of `width × height` pixels: an image of that size as it is, one
/// of an integer multiple of it (a view worked at `1/s` of its resolution,
/// [`crate::camera::downscale_factor`]) averaged over each `s × s` block (clipped to the
/// image; rounded half up); any other size is an error naming the file and both sizes.
pub fn read_rgb_sized(path: &Path, width: usize, height: usize) -> Result<Array3<u8>, ImageError> {
    let img = read_rgb(path)?;
    let (h, w, _) = img.dim();
    match crate::camera::downscale_factor((w, h), (width, height)) {
        Some(1) => Ok(img),
        Some(s) => Ok(box_downscale(&img, s, width, height)),
        None => Err(ImageError::Read {
            path: path.to_path_buf(),
            why: format!("{w}×{h} pixels, the view's camera is {width}×{height}"),
        }),
    }
}

/// The mean of each `s × s` block of `img` (clipped at the image's edges), rounded half up:
/// an `height × width` image.
fn box_downscale(img: &Array3<u8>, s: usize, width: usize, height: usize) -> Array3<u8> {
    let (h, w, _) = img.dim();
    Array3::from_shape_fn((height, width, 3), |(y, x, c)| {
        let (y0, x0) = (y * s, x * s);
        let (y1, x1) = ((y0 + s).min(h), (x0 + s).min(w));
        let mut sum = 0u32;
        for yy in y0..y1 {
            for xx in x0..x1 {
                sum += u32::from(img[[yy, xx, c]]);
            }
        }
        let n = ((y1 - y0) * (x1 - x0)) as u32;
        ((sum + n / 2) / n) as u8
    })
}

/// Writes an 8-bit RGB `H×W×3` array as PNG, atomically (temporary file, then rename). The
/// encoder is the `png` crate's fast setting (adaptive row filters, `fdeflate`): about 4×
/// faster than OpenCV's encoder, with files no larger (BENCHMARKS.md's git history, "PNG writing").
pub fn write_png(path: &Path, rgb: &Array3<u8>) -> Result<(), ImageError> {
    let err = |why: String| ImageError::Write {
        path: path.to_path_buf(),
        why,
    };
    let (h, w, c) = rgb.dim();
    if c != 3 {
        return Err(err(format!("expected 3 channels, got {c}")));
    }
    let (Ok(w32), Ok(h32)) = (u32::try_from(w), u32::try_from(h)) else {
        return Err(err(format!("{w}×{h} pixels: too large for a PNG")));
    };
    if w32 == 0 || h32 == 0 {
        return Err(err(format!("{w}×{h} pixels: an empty image")));
    }
    let data = rgb.as_standard_layout();
    let pixels = data
        .as_slice()
        .expect("a standard-layout array is contiguous");
    let mut buf = Vec::with_capacity(pixels.len() / 2 + 1024);
    let mut encoder = png::Encoder::new(&mut buf, w32, h32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    let mut writer = encoder.write_header().map_err(|e| err(e.to_string()))?;
    writer
        .write_image_data(pixels)
        .map_err(|e| err(e.to_string()))?;
    writer.finish().map_err(|e| err(e.to_string()))?;
    crate::fsutil::write_bytes(path, &buf)?;
    Ok(())
}

/// The one overlay blend of the overlays (raycast, report, query masks): each pixel `p` with
/// a colour `colour_at(p)` becomes `(1 − alpha)·base + alpha·colour`, every other pixel
/// `dim·base`, rounded; the base is `image` (H×W×3) or, without one (or with one of another
/// size), the grey `background`.
pub fn blend_overlay(
    image: Option<&Array3<u8>>,
    height: usize,
    width: usize,
    background: f32,
    alpha: f32,
    dim: f32,
    colour_at: impl Fn(usize) -> Option<[u8; 3]>,
) -> Array3<u8> {
    let n = height * width;
    // The image's bytes in row-major order (a copy only for a non-standard layout); an image
    // of another size is not used (callers check sizes and warn).
    let image = image
        .filter(|im| im.dim() == (height, width, 3))
        .map(|im| im.as_standard_layout());
    let base_bytes = image.as_ref().and_then(|im| im.as_slice());
    let mut out = vec![0u8; n * 3];
    // `colour_at` once per pixel (not per channel).
    for (p, px) in out.chunks_exact_mut(3).enumerate() {
        let colour = colour_at(p);
        for (ch, o) in px.iter_mut().enumerate() {
            let base = base_bytes.map_or(background, |b| f32::from(b[p * 3 + ch]));
            let v = match colour {
                Some(c) => (1.0 - alpha) * base + alpha * f32::from(c[ch]),
                None => dim * base,
            };
            *o = crate::fastmath::round_u8(v);
        }
    }
    Array3::from_shape_vec((height, width, 3), out).expect("H·W·3 bytes")
}

/// 8-connected components of a binary mask (`H×W`, nonzero = foreground) by OpenCV.
/// Returns the label image (0 = background, 1..n) and the pixel count of each label.
pub fn connected_components(
    mask: &ndarray::Array2<u8>,
) -> Result<(ndarray::Array2<i32>, Vec<usize>), ImageError> {
    let err = |why: String| ImageError::Read {
        path: PathBuf::from("<mask>"),
        why,
    };
    let (h, w) = mask.dim();
    let data: Vec<u8> = mask.iter().map(|&v| u8::from(v != 0)).collect();
    let flat = Mat::from_slice(&data).map_err(|e| err(e.to_string()))?;
    let img = flat.reshape(1, h as i32).map_err(|e| err(e.to_string()))?;
    let (mut labels, mut stats, mut centroids) = (Mat::default(), Mat::default(), Mat::default());
    let n = imgproc::connected_components_with_stats(
        &img,
        &mut labels,
        &mut stats,
        &mut centroids,
        8,
        opencv::core::CV_32S,
    )
    .map_err(|e| err(e.to_string()))?;
    let lab: Vec<i32> = labels
        .data_typed::<i32>()
        .map_err(|e| err(e.to_string()))?
        .to_vec();
    let mut areas = Vec::with_capacity(n as usize);
    for i in 0..n {
        areas.push(
            *stats
                .at_2d::<i32>(i, imgproc::CC_STAT_AREA)
                .map_err(|e| err(e.to_string()))? as usize,
        );
    }
    let labels = ndarray::Array2::from_shape_vec((h, w), lab).map_err(|e| err(e.to_string()))?;
    Ok((labels, areas))
}

/// Which morphological operation [`morphology`] applies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Morph {
    /// Shrinks the foreground (`cv::erode`).
    Erode,
    /// Grows the foreground (`cv::dilate`).
    Dilate,
}

/// Erodes or dilates a binary mask (`H×W`, `true` = foreground) with an elliptical kernel of
/// size `(2·radius+1)²` (`cv::getStructuringElement(MORPH_ELLIPSE)`), one iteration, OpenCV's
/// default border (`BORDER_CONSTANT` with `morphologyDefaultBorderValue`, i.e. the outside
/// of the image never erodes the mask and never dilates into it). `radius = 0` is the identity.
pub fn morphology(
    mask: &ndarray::Array2<bool>,
    op: Morph,
    radius: usize,
) -> Result<ndarray::Array2<bool>, ImageError> {
    let name = match op {
        Morph::Erode => "erode",
        Morph::Dilate => "dilate",
    };
    let err = |why: String| ImageError::Cv { op: name, why };
    let (h, w) = mask.dim();
    if radius == 0 || h == 0 || w == 0 {
        return Ok(mask.clone());
    }
    let data: Vec<u8> = mask.iter().map(|&v| u8::from(v)).collect();
    let flat = Mat::from_slice(&data).map_err(|e| err(e.to_string()))?;
    let img = flat.reshape(1, h as i32).map_err(|e| err(e.to_string()))?;
    let k = 2 * radius as i32 + 1;
    let kernel = imgproc::get_structuring_element(
        imgproc::MORPH_ELLIPSE,
        opencv::core::Size::new(k, k),
        opencv::core::Point::new(-1, -1),
    )
    .map_err(|e| err(e.to_string()))?;
    let mut out = Mat::default();
    match op {
        Morph::Erode => imgproc::erode_def(&img, &mut out, &kernel),
        Morph::Dilate => imgproc::dilate_def(&img, &mut out, &kernel),
    }
    .map_err(|e| err(e.to_string()))?;
    let out = if out.is_continuous() {
        out
    } else {
        out.try_clone().map_err(|e| err(e.to_string()))?
    };
    let bytes = out.data_bytes().map_err(|e| err(e.to_string()))?;
    ndarray::Array2::from_shape_vec((h, w), bytes.iter().map(|&b| b != 0).collect())
        .map_err(|e| err(e.to_string()))
}

/// [`morphology`] with [`Morph::Erode`].
pub fn erode(
    mask: &ndarray::Array2<bool>,
    radius: usize,
) -> Result<ndarray::Array2<bool>, ImageError> {
    morphology(mask, Morph::Erode, radius)
}

/// [`morphology`] with [`Morph::Dilate`].
pub fn dilate(
    mask: &ndarray::Array2<bool>,
    radius: usize,
) -> Result<ndarray::Array2<bool>, ImageError> {
    morphology(mask, Morph::Dilate, radius)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_image_at_a_multiple_of_the_view_is_averaged_over_its_blocks() {
        let dir = crate::fsutil::test_temp_dir()
            .join(format!("gs4city-imageio-box-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // 3×5 → 2×3 at 1/2: blocks clipped at the right and bottom edges.
        let img = Array3::from_shape_fn((3, 5, 3), |(y, x, c)| (10 * y + x + 100 * c) as u8);
        let p = dir.join("b.png");
        write_png(&p, &img).unwrap();
        let got = read_rgb_sized(&p, 3, 2).unwrap();
        // Channel 0 by hand: [[0 1; 10 11] → 5.5 → 6, [2 3; 12 13] → 7.5 → 8, [4; 14] → 9],
        // [[20 21] → 20.5 → 21, [22 23] → 22.5 → 23, [24] → 24].
        let c0: Vec<u8> = got.slice(ndarray::s![.., .., 0]).iter().copied().collect();
        assert_eq!(c0, vec![6, 8, 9, 21, 23, 24]);
        assert_eq!(got[[1, 2, 2]], 224);
        assert_eq!(read_rgb_sized(&p, 5, 3).unwrap(), img);
        let e = read_rgb_sized(&p, 4, 2).unwrap_err().to_string();
        assert!(
            e.contains("b.png") && e.contains("5×3") && e.contains("4×2"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn png_round_trip_is_lossless() {
        let dir =
            crate::fsutil::test_temp_dir().join(format!("gs4city-imageio-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let img = Array3::from_shape_fn((5, 7, 3), |(y, x, c)| (y * 40 + x * 7 + c * 90) as u8);
        let p = dir.join("a.png");
        write_png(&p, &img).unwrap();
        assert_eq!(read_rgb(&p).unwrap(), img);
        // Noise (incompressible), flat runs and gradients, wider than tall, read back by
        // OpenCV's decoder; then a transposed view (not in standard layout).
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let big = Array3::from_shape_fn((257, 300, 3), |(y, x, c)| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            match (y / 64) % 3 {
                0 => state as u8,
                1 => (x / 50 * 40 + c * 7) as u8,
                _ => (x + y + c) as u8,
            }
        });
        write_png(&p, &big).unwrap();
        assert_eq!(read_rgb(&p).unwrap(), big);
        let t = big.clone().permuted_axes([1, 0, 2]);
        write_png(&p, &t).unwrap();
        assert_eq!(read_rgb(&p).unwrap(), t);
        // An empty image is refused, naming the file; nothing is left behind.
        let q = dir.join("empty.png");
        let e = write_png(&q, &Array3::zeros((0, 4, 3))).unwrap_err();
        assert!(e.to_string().contains("empty.png"), "{e}");
        assert!(!q.exists());
        let e = read_rgb(&dir.join("missing.png")).unwrap_err();
        assert!(e.to_string().contains("missing.png"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_overlay_blends_each_pixel_and_rounds_half_away_from_zero() {
        // A transposed image (not in standard layout) and colours on every third pixel.
        let (h, w) = (5, 7);
        let stored = Array3::from_shape_fn((w, h, 3), |(x, y, c)| (y * 53 + x * 31 + c * 77) as u8);
        let image = stored.clone().permuted_axes([1, 0, 2]);
        assert!(!image.is_standard_layout());
        let colour = |p: usize| (p % 3 == 0).then_some([255u8, (p * 9) as u8, 1]);
        let (alpha, dim) = (0.5f32, 0.6f32);
        let out = blend_overlay(Some(&image), h, w, 96.0, alpha, dim, colour);
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                for c in 0..3 {
                    // The pixel's own bytes, read by (x, y) from the stored array.
                    let base = f64::from(stored[[x, y, c]]);
                    let v = match colour(p) {
                        Some(col) => 0.5 * base + 0.5 * f64::from(col[c]),
                        None => 0.6 * base,
                    };
                    // Halves (x.5 from the 50 % blend of an odd sum) round up.
                    let want = (v + 0.5).floor().min(255.0) as u8;
                    assert_eq!(out[[y, x, c]], want, "pixel ({x}, {y}) channel {c}, {v}");
                }
            }
        }
        // Without an image, or with one of another size: the grey background.
        let small = Array3::<u8>::zeros((2, 2, 3));
        for im in [None, Some(&small)] {
            let out = blend_overlay(im, h, w, 96.0, alpha, dim, colour);
            assert_eq!(out[[0, 0, 0]], 176); // 0.5·96 + 0.5·255 = 175.5
            assert_eq!(out[[0, 1, 0]], 58); // 0.6·96 = 57.6
        }
    }

    #[test]
    fn components_count_blobs() {
        let mut m = ndarray::Array2::<u8>::zeros((6, 6));
        m[[0, 0]] = 1;
        m[[1, 1]] = 1; // diagonal neighbour: same 8-connected component
        m[[4, 4]] = 1;
        m[[4, 5]] = 1;
        let (labels, areas) = connected_components(&m).unwrap();
        assert_eq!(areas.len(), 3);
        assert_eq!(labels[[0, 0]], labels[[1, 1]]);
        assert_ne!(labels[[0, 0]], labels[[4, 4]]);
        assert_eq!(areas[labels[[4, 4]] as usize], 2);
    }

    #[test]
    fn morphology_with_elliptical_kernel() {
        let mut m = ndarray::Array2::from_elem((9, 9), false);
        m[[4, 4]] = true;
        let d = dilate(&m, 1).unwrap();
        assert!(d.iter().filter(|&&v| v).count() >= 5);
        assert!(d[[3, 4]] && d[[5, 4]] && d[[4, 3]] && d[[4, 5]]);
        assert!(!d[[2, 4]]);
        let d2 = dilate(&m, 2).unwrap();
        assert!(
            d2[[2, 4]] && !d2[[2, 2]],
            "radius 2 ellipse excludes the corners"
        );
        assert_eq!(erode(&d2, 2).unwrap(), m);
        // The image border does not erode a mask that touches it.
        let full = ndarray::Array2::from_elem((5, 6), true);
        assert_eq!(erode(&full, 2).unwrap(), full);
        assert_eq!(dilate(&m, 0).unwrap(), m);
    }
}

/// How [`resize`] resamples.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Resample {
    /// `INTER_AREA` on the 8-bit image: each output pixel is the overlap-weighted mean of the
    /// input pixels its box covers (downscaling).
    Area,
    /// `INTER_LINEAR` in `f32` (half-pixel centres, edge pixels repeated), rounded to 8 bits.
    Linear,
}

/// Resizes an 8-bit RGB `H×W×3` image to `w × h` by OpenCV.
pub fn resize(
    rgb: &Array3<u8>,
    w: usize,
    h: usize,
    how: Resample,
) -> Result<Array3<u8>, ImageError> {
    let err = |why: String| ImageError::Cv { op: "resize", why };
    let (ih, iw, c) = rgb.dim();
    if c != 3 || ih == 0 || iw == 0 || w == 0 || h == 0 {
        return Err(err(format!("cannot resize {iw}×{ih}×{c} to {w}×{h}")));
    }
    let data: Vec<u8> = rgb.iter().copied().collect();
    let flat = Mat::from_slice(&data).map_err(|e| err(e.to_string()))?;
    let img = flat.reshape(3, ih as i32).map_err(|e| err(e.to_string()))?;
    let size = opencv::core::Size::new(w as i32, h as i32);
    let mut out = Mat::default();
    let bytes: Vec<u8> = match how {
        Resample::Area => {
            imgproc::resize(&img, &mut out, size, 0.0, 0.0, imgproc::INTER_AREA)
                .map_err(|e| err(e.to_string()))?;
            out.data_bytes().map_err(|e| err(e.to_string()))?.to_vec()
        }
        Resample::Linear => {
            let mut f = Mat::default();
            img.convert_to(&mut f, opencv::core::CV_32FC3, 1.0, 0.0)
                .map_err(|e| err(e.to_string()))?;
            imgproc::resize(&f, &mut out, size, 0.0, 0.0, imgproc::INTER_LINEAR)
                .map_err(|e| err(e.to_string()))?;
            out.data_typed::<opencv::core::Vec3f>()
                .map_err(|e| err(e.to_string()))?
                .iter()
                .flat_map(|p| p.0)
                .map(|v| v.round_ties_even().clamp(0.0, 255.0) as u8)
                .collect()
        }
    };
    Array3::from_shape_vec((h, w, 3), bytes).map_err(|e| err(e.to_string()))
}
