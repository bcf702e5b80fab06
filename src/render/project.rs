//! Per-view preprocessing of each Gaussian, as INRIA's `preprocessCUDA`: camera transform,
//! near cull (`z ≤ 0.2`), EWA projection of the 3D covariance with the clamped Jacobian,
//! the +0.3 low-pass on the 2D covariance, the conic, the 3σ screen radius, the tile
//! rectangle and the view-dependent SH colour. Computed in `f64`, stored in `f32` (the
//! mean in `f64`, so per-tile offsets stay exact on large images).
use glam::{DMat3, DVec3};

use super::PreparedScene;
use crate::camera::Camera;

/// INRIA's SH constants (`auxiliary.h`), owned by the splat format.
pub use crate::splat::transform::{SH_C0, SH_C1, SH_C2, SH_C3};

/// Near-plane cull distance along the camera axis.
pub const NEAR: f64 = 0.2;
/// Low-pass filter added to the 2D covariance diagonal.
pub const LOW_PASS: f64 = 0.3;
/// Tile edge in pixels.
pub const TILE: usize = 16;
/// Smallest contributing alpha.
pub const ALPHA_MIN: f32 = 1.0 / 255.0;

/// The view-independent inputs of the projection, per camera.
#[derive(Debug, Clone, Copy)]
pub struct ViewParams {
    pub rot: DMat3,
    pub trans: DVec3,
    pub center: DVec3,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub tan_fovx: f64,
    pub tan_fovy: f64,
    pub width: usize,
    pub height: usize,
    pub grid_x: usize,
    pub grid_y: usize,
}

impl ViewParams {
    pub fn new(camera: &Camera) -> Self {
        let k = &camera.intrinsics;
        let (width, height) = (k.width as usize, k.height as usize);
        ViewParams {
            rot: camera.pose.rotation,
            trans: camera.pose.translation,
            center: camera.pose.center(),
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            tan_fovx: width as f64 / (2.0 * k.fx),
            tan_fovy: height as f64 / (2.0 * k.fy),
            width,
            height,
            grid_x: width.div_ceil(TILE),
            grid_y: height.div_ceil(TILE),
        }
    }
}

/// One Gaussian as seen by one view.
#[derive(Debug, Clone, Copy)]
pub struct Projected {
    /// Mean in pixel-index coordinates (pixel `(i, j)` is evaluated at `(i, j)`).
    pub mean: [f64; 2],
    /// Inverse 2D covariance `(a, b, c)`.
    pub conic: [f32; 3],
    /// Activated opacity (× the antialiasing compensation when enabled).
    pub opacity: f32,
    /// Camera-frame z.
    pub depth: f32,
    pub color: [f32; 3],
    /// Half extents of the box outside which `alpha < 1/255` for sure (+1 px margin).
    pub extent: [f32; 2],
    /// Below this `power`, `α < 1/255` for sure (`−ln(255·o) − 1e-3`): lets the blend skip
    /// `exp` without changing any decision.
    pub power_min: f32,
    /// Tile rectangle `[x_min, y_min, x_max, y_max)`.
    pub rect: [u32; 4],
    /// Index of the Gaussian in the scene.
    pub id: u32,
}

impl Projected {
    /// Placeholder for a culled Gaussian: an empty tile rectangle.
    pub const CULLED: Projected = Projected {
        mean: [0.0; 2],
        conic: [0.0; 3],
        opacity: 0.0,
        depth: 0.0,
        color: [0.0; 3],
        extent: [0.0; 2],
        power_min: 0.0,
        rect: [0; 4],
        id: u32::MAX,
    };

    /// Whether this Gaussian touches any tile.
    pub fn is_visible(&self) -> bool {
        self.rect[0] < self.rect[2] && self.rect[1] < self.rect[3]
    }
}

/// INRIA's `getRect`, with float → int truncation toward zero, clamped to the grid.
fn rect(mean: [f64; 2], radius: f64, grid_x: usize, grid_y: usize) -> [u32; 4] {
    let t = TILE as f64;
    // `as i64` truncates toward zero (and saturates), like C's float → int conversion.
    let clamp = |v: f64, hi: usize| -> u32 { (v as i64).clamp(0, hi as i64) as u32 };
    [
        clamp((mean[0] - radius) / t, grid_x),
        clamp((mean[1] - radius) / t, grid_y),
        clamp((mean[0] + radius + t - 1.0) / t, grid_x),
        clamp((mean[1] + radius + t - 1.0) / t, grid_y),
    ]
}

/// Evaluates the SH colour of Gaussian `i` for unit direction `d` (INRIA's
/// `computeColorFromSH`: `+0.5`, clamped at 0).
pub fn sh_color(coeffs: &[[f32; 3]], degree: u8, d: DVec3) -> [f32; 3] {
    let c = |k: usize| -> DVec3 { DVec3::from_array(coeffs[k].map(f64::from)) };
    let mut r = SH_C0 * c(0);
    if degree > 0 {
        let (x, y, z) = (d.x, d.y, d.z);
        r = r - SH_C1 * y * c(1) + SH_C1 * z * c(2) - SH_C1 * x * c(3);
        if degree > 1 {
            let (xx, yy, zz) = (x * x, y * y, z * z);
            let (xy, yz, xz) = (x * y, y * z, x * z);
            r = r
                + SH_C2[0] * xy * c(4)
                + SH_C2[1] * yz * c(5)
                + SH_C2[2] * (2.0 * zz - xx - yy) * c(6)
                + SH_C2[3] * xz * c(7)
                + SH_C2[4] * (xx - yy) * c(8);
            if degree > 2 {
                r = r
                    + SH_C3[0] * y * (3.0 * xx - yy) * c(9)
                    + SH_C3[1] * xy * z * c(10)
                    + SH_C3[2] * y * (4.0 * zz - xx - yy) * c(11)
                    + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * c(12)
                    + SH_C3[4] * x * (4.0 * zz - xx - yy) * c(13)
                    + SH_C3[5] * z * (xx - yy) * c(14)
                    + SH_C3[6] * x * (xx - 3.0 * yy) * c(15);
            }
        }
    }
    (r + DVec3::splat(0.5))
        .max(DVec3::ZERO)
        .as_vec3()
        .to_array()
}

/// Projects Gaussian `i`; `None` when INRIA's preprocess culls it (near plane, det = 0,
/// empty tile rectangle) or it cannot contribute anywhere (opacity < 1/255, not finite).
pub fn project(
    scene: &PreparedScene,
    i: usize,
    v: &ViewParams,
    antialiased: bool,
    max_degree: u8,
) -> Option<Projected> {
    let pw = DVec3::from_array(scene.positions[i].map(f64::from));
    let t = v.rot * pw + v.trans;
    if t.z.is_nan() || t.z <= NEAR {
        return None;
    }
    let s = scene.cov3d[i].map(f64::from);
    let sigma = DMat3::from_cols_array(&[s[0], s[1], s[2], s[1], s[3], s[4], s[2], s[4], s[5]]);
    let cov_cam = v.rot * sigma * v.rot.transpose();
    let limx = 1.3 * v.tan_fovx;
    let limy = 1.3 * v.tan_fovy;
    let tx = (t.x / t.z).clamp(-limx, limx) * t.z;
    let ty = (t.y / t.z).clamp(-limy, limy) * t.z;
    // J rows (2×3).
    let j0 = DVec3::new(v.fx / t.z, 0.0, -(v.fx * tx) / (t.z * t.z));
    let j1 = DVec3::new(0.0, v.fy / t.z, -(v.fy * ty) / (t.z * t.z));
    let cj0 = cov_cam * j0;
    let cj1 = cov_cam * j1;
    let mut a = j0.dot(cj0);
    let b = j0.dot(cj1);
    let mut c = j1.dot(cj1);
    let det0 = a * c - b * b;
    a += LOW_PASS;
    c += LOW_PASS;
    let det = a * c - b * b;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    let conic = [c * inv, -b * inv, a * inv];
    let mid = 0.5 * (a + c);
    let lambda1 = mid + (mid * mid - det).max(0.1).sqrt();
    let radius = (3.0 * lambda1.sqrt()).ceil();
    let mean = [v.fx * t.x / t.z + v.cx - 0.5, v.fy * t.y / t.z + v.cy - 0.5];
    let r = rect(mean, radius, v.grid_x, v.grid_y);
    if (r[2] - r[0]) * (r[3] - r[1]) == 0 {
        return None;
    }
    let mut opacity = f64::from(scene.opacity[i]);
    if antialiased {
        opacity *= (det0 / det).max(0.000_025).sqrt();
    }
    let opacity = opacity as f32;
    if opacity.is_nan() || opacity < ALPHA_MIN {
        return None;
    }
    // alpha ≥ 1/255 needs dᵀ·conic·d ≤ 2 ln(255·o); that ellipse's half extents are
    // sqrt(q·Σ_xx), sqrt(q·Σ_yy). One pixel of margin keeps the box conservative.
    let ln255o = (255.0 * f64::from(opacity)).ln();
    let q = 2.0 * ln255o.max(0.0);
    let extent = [(q * a).sqrt() as f32 + 1.0, (q * c).sqrt() as f32 + 1.0];
    let dir = (pw - v.center).normalize_or_zero();
    let k = scene.coeffs;
    let degree = scene.sh_degree.min(max_degree);
    let color = sh_color(&scene.sh[i * k..(i + 1) * k], degree, dir);
    Some(Projected {
        mean,
        conic: conic.map(|x| x as f32),
        opacity,
        depth: t.z as f32,
        color,
        extent,
        power_min: (-ln255o - 1e-3) as f32,
        rect: r,
        id: i as u32,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rect_truncates_toward_zero_and_clamps() {
        assert_eq!(rect([-5.0, 20.0], 3.0, 4, 4), [0, 1, 0, 2]);
        assert_eq!(rect([8.0, 8.0], 3.0, 4, 4), [0, 0, 1, 1]);
        assert_eq!(rect([8.0, 8.0], 1e30, 4, 4), [0, 0, 4, 4]);
    }

    #[test]
    fn sh_degree_zero_is_dc_plus_half() {
        let col = sh_color(&[[1.0, 0.0, -10.0]], 0, DVec3::Z);
        assert!((f64::from(col[0]) - (SH_C0 + 0.5)).abs() < 1e-6);
        assert_eq!(col[1], 0.5);
        assert_eq!(col[2], 0.0);
    }
}
