//! Ground truth per view from the Gaussians' truth: the label of the Gaussian with the
//! largest `α·T` weight at each pixel (top-1 contribution), −1 where the accumulated alpha is
//! below a threshold; and the contact sheet (image | GT class overlay).
use ndarray::Array3;

use super::gaussians::Truth;
use crate::camera::Camera;
use crate::classes;
use crate::render::{ContributionMode, PreparedScene, RenderError, RenderOptions, render_view};

/// One labelled view.
#[derive(Debug, Clone)]
pub struct ViewLabels {
    pub width: usize,
    pub height: usize,
    pub rgb: Array3<u8>,
    pub alpha: Vec<f32>,
    /// `H×W`.
    pub class: Vec<i32>,
    pub instance: Vec<i32>,
    /// `3×H×W`: feature, surface, part (−1 off buildings).
    pub hier: Vec<i32>,
}

/// Renders `camera` and labels every pixel with the truth of its top-1 Gaussian.
pub fn label_view(
    scene: &PreparedScene,
    truth: &[Truth],
    camera: &Camera,
    background: [f32; 3],
    min_alpha: f32,
) -> Result<ViewLabels, RenderError> {
    let opts = RenderOptions {
        background,
        antialiased: false,
        max_sh_degree: 3,
        features: false,
        images: true,
        contributions: ContributionMode::TopK(1),
        t_stop: 0.0,
        alpha_min: crate::render::project::ALPHA_MIN,
    };
    let r = render_view(scene, camera, &opts)?;
    let n = r.width * r.height;
    let mut class = vec![-1; n];
    let mut instance = vec![-1; n];
    let mut hier = vec![-1; 3 * n];
    if let Some(c) = &r.contributions {
        for p in 0..n {
            if r.alpha[p] < min_alpha {
                continue;
            }
            let (ids, _) = c.pixel(p);
            if let Some(&g) = ids.first()
                && let Some(t) = truth.get(g as usize)
            {
                class[p] = t[0];
                instance[p] = t[1];
                if classes::is_building(t[0]) {
                    for k in 0..3 {
                        hier[k * n + p] = t[2 + k];
                    }
                }
            }
        }
    }
    Ok(ViewLabels {
        width: r.width,
        height: r.height,
        rgb: r.rgb8(),
        alpha: r.alpha,
        class,
        instance,
        hier,
    })
}

/// Display colour of a class id (sky/none: black).
pub fn class_color(c: i32) -> [u8; 3] {
    match c {
        classes::WALL => [230, 200, 150],
        classes::ROOF => [200, 60, 40],
        classes::WINDOW => [40, 120, 255],
        classes::DOOR => [255, 160, 0],
        classes::GROUND_SURFACE => [120, 120, 120],
        classes::INSTALLATION => [180, 80, 200],
        classes::TREE => [30, 170, 40],
        classes::PERSON => [255, 0, 120],
        classes::CAR => [0, 230, 230],
        classes::ROAD => [90, 90, 90],
        classes::WATER => [20, 40, 160],
        classes::OTHER => [255, 255, 0],
        _ => [0, 0, 0],
    }
}

/// A grid: one row per view, image left, GT class overlay (60 % class colour) right;
/// halved in size when the views are wider than 400 px.
pub fn contact_sheet(views: &[(Array3<u8>, Vec<i32>)]) -> Option<Array3<u8>> {
    let (h, w, _) = views.first()?.0.dim();
    let f = if w > 400 { 2 } else { 1 };
    let (ho, wo) = (h / f, w / f);
    let gap = 4;
    let mut out = Array3::<u8>::from_elem((views.len() * (ho + gap), 2 * wo + gap, 3), 255);
    for (r, (img, cls)) in views.iter().enumerate() {
        if img.dim() != (h, w, 3) || cls.len() != h * w {
            continue;
        }
        for y in 0..ho {
            for x in 0..wo {
                let mut a = [0u32; 3];
                let mut b = [0u32; 3];
                for dy in 0..f {
                    for dx in 0..f {
                        let (sy, sx) = (y * f + dy, x * f + dx);
                        let c = class_color(cls[sy * w + sx]);
                        for k in 0..3 {
                            let v = u32::from(img[[sy, sx, k]]);
                            a[k] += v;
                            b[k] += if cls[sy * w + sx] < 0 {
                                v
                            } else {
                                (v * 4 + u32::from(c[k]) * 6) / 10
                            };
                        }
                    }
                }
                let oy = r * (ho + gap) + y;
                for k in 0..3 {
                    out[[oy, x, k]] = (a[k] / (f * f) as u32) as u8;
                    out[[oy, wo + gap + x, k]] = (b[k] / (f * f) as u32) as u8;
                }
            }
        }
    }
    Some(out)
}
