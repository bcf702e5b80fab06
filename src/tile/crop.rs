//! A view cropped to the window of its image where a tile shows (docs/tile.md, "Views"): a
//! view that glimpses a tile — a neighbouring block seen beyond the one it looks at — joins
//! that tile only with the pixels that show it, so each stage of the tile's run (the
//! contributions cache, the raycast, the masks, the association, the vote) works on those
//! pixels alone and a view's cost over all its tiles stays about one image.
//!
//! The crop is exact: pixel `(i, j)` of the window `[x0, x0 + w) × [y0, y0 + h)` is pixel
//! `(x0 + i, y0 + j)` of the image, so the camera keeps its focal lengths and lens model and
//! moves its principal point by `(−x0, −y0)` (COLMAP's pixel frame; the distortion acts on
//! normalised coordinates, which do not change). The tile's scene gets the cropped image
//! (`images/<stem>.png`), its SAM list cut to the window (masks with no pixel there dropped;
//! area, box and prompt points recomputed, scores kept) and the rows of its per-mask features
//! for the masks kept.
use std::path::Path;

use ndarray::{Array2, s};

use super::TileError;
use crate::camera::View;
use crate::scene::Scene;

/// A pixel window `[x0, x1) × [y0, y1)` of a view's image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Window {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl Window {
    /// Pixels in the window.
    pub fn area(&self) -> u64 {
        u64::from(self.x1 - self.x0) * u64::from(self.y1 - self.y0)
    }
}

/// The view seen through `w`: the same pose and lens, the window's size, the principal point
/// moved to the window's frame, camera id `camera_id`, and the image name `<stem>.png` (the
/// cropped image is written as PNG; the stem, which names the view's masks and features, is
/// kept).
pub fn cropped_view(v: &View, w: Window, camera_id: u32) -> View {
    let mut c = v.clone();
    let k = &mut c.camera.intrinsics;
    k.width = w.x1 - w.x0;
    k.height = w.y1 - w.y0;
    k.cx -= f64::from(w.x0);
    k.cy -= f64::from(w.y0);
    c.camera_id = camera_id;
    let dir = match v.name.rfind('/') {
        Some(i) => &v.name[..=i],
        None => "",
    };
    c.name = format!("{dir}{}.png", v.stem());
    c
}

/// Writes into the tile scene `sdir` the image, SAM list and per-mask features of view `v`
/// (full size) cut to `w`, under the names of `cropped` ([`cropped_view`]). What the scene
/// lacks for the view (no image, no SAM list) is left out, as the links of an uncropped view.
pub fn write_cropped(
    scene: &Scene,
    sdir: &Path,
    v: &View,
    cropped: &View,
    w: Window,
) -> Result<(), TileError> {
    let (fw, fh) = (
        v.camera.intrinsics.width as usize,
        v.camera.intrinsics.height as usize,
    );
    let (x0, y0, x1, y1) = (w.x0 as usize, w.y0 as usize, w.x1 as usize, w.y1 as usize);
    let stem = v.stem();
    if let Some(images) = &scene.images {
        let src = images.join(&v.name);
        if src.is_file() {
            let rgb = crate::imageio::read_rgb_sized(&src, fw, fh)?;
            let part = rgb.slice(s![y0..y1, x0..x1, ..]).to_owned();
            let dst = sdir.join("images").join(&cropped.name);
            if let Some(parent) = dst.parent() {
                crate::fsutil::create_dir(parent)?;
            }
            crate::imageio::write_png(&dst, &part)?;
        }
    }
    let Some(sam_path) = scene.sam_file(&stem) else {
        return Ok(());
    };
    let masks = crate::sam::read_sam_json_sized(&sam_path, Some([fh, fw]))?;
    let (out, kept) = crop_masks(&masks, w).map_err(|(i, err)| {
        TileError::Invalid(format!("{}: mask {i}: {err}", sam_path.display()))
    })?;
    crate::fsutil::create_dir(&sdir.join("masks"))?;
    crate::sam::write_sam_json(&sdir.join("masks").join(format!("{stem}.json")), &out)?;
    if let Some(f) = scene.feature_file(&stem) {
        let (n, d, data) = crate::sam::read_features(&f, Some(masks.len()))?;
        debug_assert_eq!(n, masks.len());
        let rows: Vec<Vec<f32>> = kept
            .iter()
            .map(|&i| data[i * d..(i + 1) * d].to_vec())
            .collect();
        crate::fsutil::create_dir(&sdir.join("features"))?;
        crate::sam::write_features_npy(
            &sdir.join("features").join(format!("{stem}.npy")),
            d,
            &rows,
        )?;
    }
    Ok(())
}

/// The masks of one view cut to window `w`, and the indices of those kept (the masks with a
/// pixel in the window): area and box recomputed, prompt points moved to the window's frame,
/// scores kept. `Err`: the index of a mask whose RLE does not decode.
fn crop_masks(
    masks: &[crate::sam::SamMask],
    w: Window,
) -> Result<(Vec<crate::sam::SamMask>, Vec<usize>), (usize, crate::sam::RleError)> {
    let (x0, y0, x1, y1) = (w.x0 as usize, w.y0 as usize, w.x1 as usize, w.y1 as usize);
    let mut kept = Vec::new();
    let mut out = Vec::new();
    for (i, m) in masks.iter().enumerate() {
        let fw = m.segmentation.size[1];
        let mut region = Array2::from_elem((y1 - y0, x1 - x0), false);
        let mut any = false;
        // Row-major pixel index y · w + x.
        m.segmentation
            .for_each_pixel(|p| {
                let (x, y) = (p % fw, p / fw);
                if (x0..x1).contains(&x) && (y0..y1).contains(&y) {
                    region[[y - y0, x - x0]] = true;
                    any = true;
                }
            })
            .map_err(|err| (i, err))?;
        if !any {
            continue;
        }
        let points = m
            .point_coords
            .iter()
            .map(|&[px, py]| [px - x0 as f64, py - y0 as f64])
            .collect();
        out.push(crate::sam::SamMask::from_mask(
            &region,
            m.predicted_iou,
            m.stability_score,
            points,
        ));
        kept.push(i);
    }
    Ok((out, kept))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Distortion, Intrinsics, Pose};
    use glam::DVec3;

    #[test]
    fn a_cropped_view_projects_a_point_to_the_same_pixel_less_the_window_corner() {
        let v = View {
            image_id: 3,
            camera_id: 1,
            name: "cams/a.jpg".into(),
            camera: Camera {
                intrinsics: Intrinsics {
                    width: 640,
                    height: 480,
                    fx: 500.0,
                    fy: 510.0,
                    cx: 321.5,
                    cy: 239.0,
                    distortion: Distortion::OpenCv {
                        k1: -0.1,
                        k2: 0.02,
                        p1: 0.001,
                        p2: -0.002,
                    },
                },
                pose: Pose {
                    rotation: glam::DMat3::IDENTITY,
                    translation: DVec3::ZERO,
                },
            },
        };
        let w = Window {
            x0: 100,
            y0: 40,
            x1: 300,
            y1: 200,
        };
        let c = cropped_view(&v, w, 9);
        assert_eq!((c.name.as_str(), c.camera_id), ("cams/a.png", 9));
        assert_eq!(
            (c.camera.intrinsics.width, c.camera.intrinsics.height),
            (200, 160)
        );
        for p in [
            DVec3::new(-0.3, -0.2, 2.0),
            DVec3::new(0.1, 0.05, 5.0),
            DVec3::new(-1.0, 0.3, 7.0),
        ] {
            let a = v.camera.project(p).unwrap();
            let b = c.camera.project(p).unwrap();
            assert!((a.x - 100.0 - b.x).abs() < 1e-9 && (a.y - 40.0 - b.y).abs() < 1e-9);
            // And back: the pixel's ray is the same ray.
            let ra = v.camera.pixel_ray(a.x, a.y);
            let rb = c.camera.pixel_ray(b.x, b.y);
            assert!((ra - rb).length() < 1e-9, "{ra} {rb}");
        }
        assert_eq!(w.area(), 200 * 160);
    }

    #[test]
    fn masks_are_cut_to_the_window_as_the_decoded_pixels_are() {
        use crate::sam::SamMask;
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (h, wd) = (23, 37);
        let w = Window {
            x0: 6,
            y0: 4,
            x1: 30,
            y1: 15,
        };
        let mut masks = Vec::new();
        for _ in 0..40 {
            let (cx, cy, r) = (
                rng.random_range(0..wd) as f64,
                rng.random_range(0..h) as f64,
                rng.random_range(1.0..9.0),
            );
            let m =
                Array2::from_shape_fn((h, wd), |(y, x)| (x as f64 - cx).hypot(y as f64 - cy) < r);
            masks.push(SamMask::from_mask(&m, 0.9, 0.8, vec![[cx, cy]]));
        }
        let (out, kept) = crop_masks(&masks, w).unwrap();
        // Independently: decode the whole mask, slice the window (rows y, columns x).
        let mut want_kept = Vec::new();
        for (i, m) in masks.iter().enumerate() {
            let full = m.segmentation.decode().unwrap();
            let part = full.slice(s![4..15, 6..30]).to_owned();
            if part.iter().any(|&b| b) {
                let k = want_kept.len();
                want_kept.push(i);
                assert_eq!(out[k].segmentation.decode().unwrap(), part, "mask {i}");
                assert_eq!(out[k].area, part.iter().filter(|&&b| b).count() as u64);
                let [px, py] = m.point_coords[0];
                assert_eq!(out[k].point_coords, vec![[px - 6.0, py - 4.0]]);
                assert_eq!(out[k].segmentation.size, [11, 24]);
            }
        }
        assert_eq!(kept, want_kept);
        assert!(kept.len() > 5 && kept.len() < 40, "{}", kept.len());
    }
}
