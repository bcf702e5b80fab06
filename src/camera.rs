//! Calibrated cameras in the COLMAP/OpenCV convention: world-to-camera pose
//! `x_cam = R · x_world + t`, camera +z forward, +x right, +y down, pixel centres at
//! integer coordinates + 0.5 in COLMAP (the principal point `cx, cy` is in that frame).
//!
//! ## The scene frame and the one camera check
//! Every stage stores scene coordinates (mesh vertices, Gaussian centres) as `f32` and traces
//! them with Embree in `f32`. [`SCENE_COORD_LIMIT`] is the largest coordinate magnitude the
//! scene frame accepts: at 10⁶ units the `f32` spacing is 0.0625 units, so a frame left in
//! georeferenced coordinates (UTM northing ≈ 5·10⁶ m, ECEF ≈ 6.4·10⁶ m, where `f32` resolves
//! only 0.5 m) is refused instead of silently losing the detail that separates a window from
//! its wall; far below it lie the limits of the arithmetic itself (Embree skips geometry
//! beyond 1.844·10¹⁸ and asserts on rays from ≥ 10²⁰; squared distances overflow `f32` at
//! 1.8·10¹⁹). `citymodel` recentres georeferenced input (its alignment) and checks the
//! aligned mesh against this limit.
//!
//! [`Camera::validate`] is the one sanity check every consumer of a camera calls (the COLMAP
//! reader, render, raycast): image size within [`MAX_IMAGE_SIDE`] and [`MAX_IMAGE_PIXELS`],
//! focal lengths finite with `f / max(w, h)` in [`FOCAL_RATIO_RANGE`], principal point finite
//! and within [`PRINCIPAL_POINT_RANGE`] image sizes of the image, distortion coefficients
//! finite with magnitude ≤ [`MAX_DISTORTION_COEFF`], a finite proper rotation, and a camera
//! centre within [`SCENE_COORD_LIMIT`].
use crate::numfmt::Num;
use glam::{DMat3, DQuat, DVec2, DVec3};

/// Largest accepted coordinate magnitude of the scene frame, in scene units (module docs).
pub const SCENE_COORD_LIMIT: f64 = 1.0e6;

/// Why a point in the scene frame cannot be used (not finite, or beyond
/// [`SCENE_COORD_LIMIT`]), or `None` when it can.
pub fn outside_scene_frame(s: DVec3) -> Option<String> {
    if s.is_finite() && s.abs().max_element() <= SCENE_COORD_LIMIT {
        return None;
    }
    Some(format!(
        "a vertex lands at ({}, {}, {}) in the scene frame, beyond ±{SCENE_COORD_LIMIT:e} (camera::SCENE_COORD_LIMIT, the f32 frame's limit): check the coordinates and the alignment's scale and translation",
        Num(s.x),
        Num(s.y),
        Num(s.z)
    ))
}

/// Largest accepted image side, in pixels.
pub const MAX_IMAGE_SIDE: u32 = 32_768;
/// Largest accepted image area: 160 megapixels (a 150 MP aerial camera fits; raycasting
/// holds ≈ 40 bytes per pixel, so this bounds one view at ≈ 6.4 GB).
pub const MAX_IMAGE_PIXELS: u64 = 160_000_000;
/// Accepted focal length relative to the larger image side, `f / max(w, h)`: from 10⁻³
/// (a field of view of 179.9°) to 10⁵ (0.0006°).
pub const FOCAL_RATIO_RANGE: (f64, f64) = (1e-3, 1e5);
/// The principal point may lie this many image widths (heights) outside the image.
pub const PRINCIPAL_POINT_RANGE: f64 = 10.0;
/// Largest accepted magnitude of a distortion coefficient.
pub const MAX_DISTORTION_COEFF: f64 = 1e6;

/// Why a camera cannot be used; the message is a sentence without the file or view name,
/// which the caller adds.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct CameraError(pub String);

/// Lens distortion of a camera model (COLMAP parameter order).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Distortion {
    /// PINHOLE, SIMPLE_PINHOLE.
    None,
    /// SIMPLE_RADIAL (`k2 = 0`) and RADIAL: `r' = r (1 + k1 r² + k2 r⁴)`.
    Radial { k1: f64, k2: f64 },
    /// OPENCV: radial k1, k2 and tangential p1, p2.
    OpenCv { k1: f64, k2: f64, p1: f64, p2: f64 },
    /// FULL_OPENCV: rational radial k1..k6 and tangential p1, p2.
    FullOpenCv { k: [f64; 6], p1: f64, p2: f64 },
}

/// Newton iterations allowed in [`Distortion::undistort`].
const UNDISTORT_MAX_ITERS: usize = 100;
/// Convergence threshold of [`Distortion::undistort`] on the residual in normalised
/// image coordinates (≈ 1e-9 px at a focal length of 10⁴ px).
const UNDISTORT_TOL: f64 = 1e-13;

impl Distortion {
    /// Applies the lens model to an undistorted normalised point `(x/z, y/z)`, as COLMAP does.
    pub fn distort(&self, p: DVec2) -> DVec2 {
        let (u, v) = (p.x, p.y);
        let (u2, v2, uv) = (u * u, v * v, u * v);
        let r2 = u2 + v2;
        match *self {
            Distortion::None => p,
            Distortion::Radial { k1, k2 } => {
                let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
                p * radial
            }
            Distortion::OpenCv { k1, k2, p1, p2 } => {
                let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
                DVec2::new(
                    u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u2),
                    v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2),
                )
            }
            Distortion::FullOpenCv { k, p1, p2 } => {
                let (r4, r6) = (r2 * r2, r2 * r2 * r2);
                let radial = (1.0 + k[0] * r2 + k[1] * r4 + k[2] * r6)
                    / (1.0 + k[3] * r2 + k[4] * r4 + k[5] * r6);
                DVec2::new(
                    u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u2),
                    v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2),
                )
            }
        }
    }

    /// Inverts [`Distortion::distort`] by Newton's method (numerical Jacobian, as COLMAP),
    /// starting from the distorted point. Returns the best estimate and whether the
    /// residual `|distort(x) − p|` fell below 1e-13 (normalised units) within 100 iterations.
    pub fn undistort_checked(&self, p: DVec2) -> (DVec2, bool) {
        if matches!(self, Distortion::None) {
            return (p, true);
        }
        if !p.is_finite() {
            return (p, false);
        }
        let mut x = p;
        for _ in 0..UNDISTORT_MAX_ITERS {
            let r = self.distort(x) - p;
            let (dx, dy) = self.jacobian(x);
            let det = dx.x * dy.y - dy.x * dx.y;
            if r.abs().max_element() < UNDISTORT_TOL {
                // A root on a folded-over branch (negative Jacobian, or pointing away
                // from the distorted point) is not the physical preimage.
                return (x, det > 0.0 && x.dot(p) >= 0.0);
            }
            if !det.is_finite() || det.abs() < 1e-300 {
                return (x, false);
            }
            // Solve J · step = r with J = [dx dy] (columns).
            let step = DVec2::new(
                (r.x * dy.y - dy.x * r.y) / det,
                (dx.x * r.y - r.x * dx.y) / det,
            );
            let next = x - step;
            if !next.is_finite() {
                return (x, false);
            }
            x = next;
        }
        let (dx, dy) = self.jacobian(x);
        let ok = (self.distort(x) - p).abs().max_element() < UNDISTORT_TOL
            && dx.x * dy.y - dy.x * dx.y > 0.0
            && x.dot(p) >= 0.0;
        (x, ok)
    }

    /// Central-difference Jacobian columns `(∂d/∂x, ∂d/∂y)` of [`Distortion::distort`].
    fn jacobian(&self, x: DVec2) -> (DVec2, DVec2) {
        let h = 1e-7 * (1.0 + x.abs().max_element());
        let dx = (self.distort(x + DVec2::new(h, 0.0)) - self.distort(x - DVec2::new(h, 0.0)))
            / (2.0 * h);
        let dy = (self.distort(x + DVec2::new(0.0, h)) - self.distort(x - DVec2::new(0.0, h)))
            / (2.0 * h);
        (dx, dy)
    }

    /// Inverts [`Distortion::distort`]; `None` where Newton's method does not converge
    /// (outside the invertible region of a strongly distorting model).
    pub fn undistort(&self, p: DVec2) -> Option<DVec2> {
        match self.undistort_checked(p) {
            (x, true) => Some(x),
            _ => None,
        }
    }
}

impl Distortion {
    /// The coefficients in COLMAP order (empty for [`Distortion::None`]).
    pub fn coefficients(&self) -> Vec<f64> {
        match *self {
            Distortion::None => Vec::new(),
            Distortion::Radial { k1, k2 } => vec![k1, k2],
            Distortion::OpenCv { k1, k2, p1, p2 } => vec![k1, k2, p1, p2],
            Distortion::FullOpenCv { k, p1, p2 } => {
                vec![k[0], k[1], p1, p2, k[2], k[3], k[4], k[5]]
            }
        }
    }
}

/// Image size and projection parameters.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: Distortion,
}

impl Intrinsics {
    /// The intrinsics of the same camera at `1/s` of its resolution (`s ≥ 1`): pixel `(i, j)`
    /// of the result covers pixels `[s·i, s·i + s) × [s·j, s·j + s)` of the original (clipped
    /// to the image), so the image is `⌈W/s⌉ × ⌈H/s⌉` and every focal length and principal
    /// point coordinate is divided by `s` (COLMAP's pixel frame: pixel `i` spans `[i, i + 1)`);
    /// the lens model, in normalised coordinates, is unchanged. `s = 1` is the identity.
    pub fn downscaled(&self, s: u32) -> Intrinsics {
        let s = s.max(1);
        let f = f64::from(s);
        Intrinsics {
            width: self.width.div_ceil(s),
            height: self.height.div_ceil(s),
            fx: self.fx / f,
            fy: self.fy / f,
            cx: self.cx / f,
            cy: self.cy / f,
            distortion: self.distortion,
        }
    }

    /// Checks the image size, focal lengths, principal point and distortion (module docs).
    pub fn validate(&self) -> Result<(), CameraError> {
        let (w, h) = (self.width, self.height);
        let bad = |why: String| Err(CameraError(why));
        if w == 0 || h == 0 {
            return bad(format!("image size {w}×{h} is empty"));
        }
        let pixels = u64::from(w) * u64::from(h);
        if w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE || pixels > MAX_IMAGE_PIXELS {
            return bad(format!(
                "image size {w}×{h} ({:.1} megapixels) exceeds the limit of {MAX_IMAGE_SIDE} pixels per side and {} megapixels",
                pixels as f64 / 1e6,
                MAX_IMAGE_PIXELS / 1_000_000
            ));
        }
        let side = f64::from(w.max(h));
        let (lo, hi) = FOCAL_RATIO_RANGE;
        for (name, f) in [("fx", self.fx), ("fy", self.fy)] {
            if !f.is_finite() || f < lo * side || f > hi * side {
                return bad(format!(
                    "focal length {name} = {} px is outside {}..{} px ({lo:e}..{hi:e} times the larger image side {side} px)",
                    Num(f),
                    lo * side,
                    hi * side
                ));
            }
        }
        let r = PRINCIPAL_POINT_RANGE;
        for (name, c, n) in [("cx", self.cx, f64::from(w)), ("cy", self.cy, f64::from(h))] {
            if !c.is_finite() || c < -r * n || c > (r + 1.0) * n {
                return bad(format!(
                    "principal point {name} = {} px lies more than {r} image sizes outside the image",
                    Num(c)
                ));
            }
        }
        if let Some(k) = self
            .distortion
            .coefficients()
            .into_iter()
            .find(|k| !k.is_finite() || k.abs() > MAX_DISTORTION_COEFF)
        {
            return bad(format!(
                "distortion coefficient {} is not a finite number of magnitude ≤ {MAX_DISTORTION_COEFF:e}",
                Num(k)
            ));
        }
        Ok(())
    }
}

/// World-to-camera rigid transform.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation world → camera.
    pub rotation: DMat3,
    /// Translation world → camera.
    pub translation: DVec3,
}

impl Pose {
    /// From a COLMAP quaternion `(qw, qx, qy, qz)` (normalised here) and translation.
    /// Returns `None` for a non-finite or zero quaternion or a non-finite translation.
    pub fn from_colmap(q: [f64; 4], t: [f64; 3]) -> Option<Pose> {
        let mut q = q;
        let mut norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm == f64::INFINITY && q.iter().all(|v| v.is_finite()) {
            // Finite components whose squares overflow (|q| > 1.3e154): scaled first, so that
            // the direction is kept (a finite quaternion of any size is a rotation).
            let m = q.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            q = q.map(|v| v / m);
            norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        }
        if !norm.is_finite() || norm < 1e-12 || t.iter().any(|v| !v.is_finite()) {
            return None;
        }
        let quat = DQuat::from_xyzw(q[1] / norm, q[2] / norm, q[3] / norm, q[0] / norm);
        Some(Pose {
            rotation: DMat3::from_quat(quat),
            translation: DVec3::from_array(t),
        })
    }

    /// A camera at `eye` looking at `target`, with image "up" as close to `up` as possible.
    /// Returns `None` when `eye == target` or the view direction is parallel to `up`.
    pub fn look_at(eye: DVec3, target: DVec3, up: DVec3) -> Option<Pose> {
        let z = (target - eye).try_normalize()?;
        let x = (-up).cross(z).try_normalize()?; // image +x right, image −y towards `up`
        let y = z.cross(x);
        // Rows of R are the camera axes in world coordinates.
        let rotation = DMat3::from_cols(x, y, z).transpose();
        Some(Pose {
            rotation,
            translation: -(rotation * eye),
        })
    }

    /// Camera centre in world coordinates, `−Rᵀ t`.
    pub fn center(&self) -> DVec3 {
        -(self.rotation.transpose() * self.translation)
    }

    /// Maps a world point into the camera frame.
    pub fn world_to_camera(&self, p: DVec3) -> DVec3 {
        self.rotation * p + self.translation
    }

    /// Checks a finite proper rotation (orthonormal within 1e-6, det +1), a finite
    /// translation and a camera centre within [`SCENE_COORD_LIMIT`].
    pub fn validate(&self) -> Result<(), CameraError> {
        if !self.rotation.is_finite() || !self.translation.is_finite() {
            return Err(CameraError(
                "the pose holds a value that is not a finite number".into(),
            ));
        }
        let err = (self.rotation.transpose() * self.rotation - DMat3::IDENTITY)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs()));
        let det = self.rotation.determinant();
        if err > 1e-6 || det < 0.0 {
            return Err(CameraError(format!(
                "the pose rotation is not a rotation (|RᵀR − I| = {err:.1e}, det = {det:.6})"
            )));
        }
        let c = self.center();
        if c.abs().max_element() > SCENE_COORD_LIMIT {
            return Err(CameraError(format!(
                "the camera centre ({:.6e}, {:.6e}, {:.6e}) lies beyond ±{SCENE_COORD_LIMIT:e}, the scene frame's limit (recentre the scene)",
                c.x, c.y, c.z
            )));
        }
        Ok(())
    }

    /// The unit quaternion `(qw, qx, qy, qz)` of the rotation (COLMAP order).
    pub fn colmap_qvec(&self) -> [f64; 4] {
        let q = DQuat::from_mat3(&self.rotation).normalize();
        let q = if q.w < 0.0 { -q } else { q };
        [q.w, q.x, q.y, q.z]
    }
}

/// One calibrated camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    pub pose: Pose,
}

impl Camera {
    /// The shared sanity check of a camera (module docs): [`Intrinsics::validate`] and
    /// [`Pose::validate`]. Every stage that uses a camera calls it before allocating per-pixel
    /// buffers or tracing rays.
    pub fn validate(&self) -> Result<(), CameraError> {
        self.intrinsics.validate()?;
        self.pose.validate()
    }

    /// Projects a camera-frame point through the full lens model to a (distorted) pixel
    /// position; `None` behind or on the camera plane.
    pub fn project(&self, p_cam: DVec3) -> Option<DVec2> {
        if p_cam.z <= 0.0 {
            return None;
        }
        let k = &self.intrinsics;
        let d = k
            .distortion
            .distort(DVec2::new(p_cam.x / p_cam.z, p_cam.y / p_cam.z));
        Some(DVec2::new(k.fx * d.x + k.cx, k.fy * d.y + k.cy))
    }

    /// The row-major index of the pixel of a `width × height` image that contains the
    /// projection of camera-frame point `p_cam` ([`Camera::project`]; pixel `(i, j)` covers
    /// `[i, i + 1) × [j, j + 1)`); `None` behind the camera or outside the image.
    pub fn pixel_containing(&self, p_cam: DVec3, width: usize, height: usize) -> Option<usize> {
        let uv = self.project(p_cam)?;
        (uv.x >= 0.0 && uv.y >= 0.0 && uv.x < width as f64 && uv.y < height as f64)
            .then(|| uv.y as usize * width + uv.x as usize)
    }

    /// The unit camera-frame ray through a position `(u, v)` of the *distorted* image, in
    /// COLMAP pixel coordinates (pixel index `(i, j)` has its centre at `(i + 0.5, j + 0.5)`).
    /// `None` where undistortion does not converge.
    pub fn try_pixel_ray(&self, u: f64, v: f64) -> Option<DVec3> {
        let k = &self.intrinsics;
        self.try_normalized_ray(DVec2::new((u - k.cx) / k.fx, (v - k.cy) / k.fy))
    }

    /// As [`Camera::try_pixel_ray`], from the distorted normalised position
    /// `((u − cx)/fx, (v − cy)/fy)` (callers tracing whole images compute the two terms
    /// once per column and row).
    pub fn try_normalized_ray(&self, d: DVec2) -> Option<DVec3> {
        let n = self.intrinsics.distortion.undistort(d)?;
        DVec3::new(n.x, n.y, 1.0).try_normalize()
    }

    /// As [`Camera::try_pixel_ray`], but always returns a direction: where undistortion
    /// does not converge, Newton's best estimate (or the distorted direction) is used.
    pub fn pixel_ray(&self, u: f64, v: f64) -> DVec3 {
        let k = &self.intrinsics;
        let d = DVec2::new((u - k.cx) / k.fx, (v - k.cy) / k.fy);
        let (n, _) = k.distortion.undistort_checked(d);
        DVec3::new(n.x, n.y, 1.0)
            .try_normalize()
            .unwrap_or(DVec3::Z)
    }

    /// The camera's viewing axis (+z of the camera frame) in world coordinates.
    pub fn forward(&self) -> DVec3 {
        self.pose.rotation.transpose() * DVec3::Z
    }
}

/// A registered image: its name (as in COLMAP, relative to `images/`) and its camera.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    pub image_id: u32,
    pub camera_id: u32,
    pub name: String,
    pub camera: Camera,
}

impl View {
    /// The view with its camera at `1/s` of the resolution ([`Intrinsics::downscaled`]).
    pub fn downscaled(&self, s: u32) -> View {
        let mut v = self.clone();
        v.camera.intrinsics = v.camera.intrinsics.downscaled(s);
        v
    }

    /// The image name without directories and extension: the `<stem>` of every per-view file.
    pub fn stem(&self) -> String {
        let file = self.name.rsplit('/').next().unwrap_or(&self.name);
        match file.rfind('.') {
            Some(i) if i > 0 => file[..i].to_string(),
            _ => file.to_string(),
        }
    }
}

/// Largest resolution divisor [`downscale_factor`] recognises.
pub const MAX_DOWNSCALE: usize = 16;

/// The divisor `s` (1 ≤ s ≤ [`MAX_DOWNSCALE`], the smallest that fits) for which an image of
/// `full = (width, height)` pixels at `1/s` of its resolution ([`Intrinsics::downscaled`]) is
/// `small = (width, height)`; `None` when no such `s` exists. A per-view file made at a
/// view's full resolution (a SAM list, an image) is box-averaged to a view that works at a
/// lower one ([`crate::sam::downscale`], `imageio::read_rgb_sized`).
pub fn downscale_factor(full: (usize, usize), small: (usize, usize)) -> Option<usize> {
    if small.0 == 0 || small.1 == 0 {
        return None;
    }
    (1..=MAX_DOWNSCALE).find(|&s| full.0.div_ceil(s) == small.0 && full.1.div_ceil(s) == small.1)
}

/// A view traced at a size that is no downscale of its camera's: its stem, that size, the
/// camera's size.
pub type SizeMismatch = (String, (usize, usize), (usize, usize));

/// `views` as a stage made them: each view `size_of` knows, with its camera at that size (a
/// view worked at `1/s` of its camera's resolution, [`Intrinsics::downscaled`]); views it does
/// not know are left out. A size that is no such downscale of the camera's is returned as
/// `Err((stem, size, camera's size))`.
pub fn views_at_sizes(
    views: &[View],
    size_of: impl Fn(&View) -> Option<(usize, usize)>,
) -> Result<Vec<View>, SizeMismatch> {
    let mut out = Vec::with_capacity(views.len());
    for v in views {
        let Some(size) = size_of(v) else {
            continue;
        };
        let k = &v.camera.intrinsics;
        let full = (k.width as usize, k.height as usize);
        match downscale_factor(full, size) {
            Some(s) => out.push(v.downscaled(s as u32)),
            None => return Err((v.stem(), size, full)),
        }
    }
    Ok(out)
}

/// The views whose per-view files cannot be named: `(image name, why)` for each view whose
/// [`View::stem`] is empty or is an earlier view's (a rig's `camA/x.png` and `camB/x.png`),
/// in the views' order. Every stage that writes per-view files checks this first.
pub fn stem_problems(views: &[View]) -> Vec<(String, String)> {
    let mut first: std::collections::HashMap<String, &str> = std::collections::HashMap::new();
    let mut out = Vec::new();
    for v in views {
        let stem = v.stem();
        if stem.is_empty() {
            out.push((v.name.clone(), "the image name has no file stem".into()));
        } else if let Some(other) = first.get(&stem) {
            out.push((
                v.name.clone(),
                format!(
                    "shares the file stem `{stem}` with {other}: every per-view output is named \
                     by the stem, so their files would collide"
                ),
            ));
        } else {
            first.insert(stem, &v.name);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_downscaled_camera_puts_a_point_in_the_block_of_its_full_resolution_pixel() {
        // 661×495 (odd: the last block is clipped), a radial lens; every camera-frame point
        // on a grid over the image: its pixel at 1/s is its full-resolution pixel's block,
        // ⌊i/s⌋, ⌊j/s⌋, and the projection is the full one divided by s.
        let k = Intrinsics {
            width: 661,
            height: 495,
            fx: 440.3,
            fy: 439.0,
            cx: 331.2,
            cy: 246.7,
            distortion: Distortion::Radial {
                k1: -0.08,
                k2: 0.01,
            },
        };
        let pose = Pose::look_at(DVec3::ZERO, DVec3::Z, -DVec3::Y).unwrap();
        let full = Camera {
            intrinsics: k,
            pose,
        };
        for s in [1u32, 2, 3, 4] {
            let small = Camera {
                intrinsics: k.downscaled(s),
                pose,
            };
            let (w, h) = (661usize.div_ceil(s as usize), 495usize.div_ceil(s as usize));
            assert_eq!(
                (small.intrinsics.width, small.intrinsics.height),
                (w as u32, h as u32)
            );
            let mut checked = 0;
            for a in -40..=40 {
                for b in -30..=30 {
                    let q = DVec3::new(a as f64 * 0.0213, b as f64 * 0.0177, 1.0);
                    let (Some(uv), Some(uv_s)) = (full.project(q), small.project(q)) else {
                        continue;
                    };
                    assert!(
                        (uv / s as f64 - uv_s).abs().max_element() < 1e-9,
                        "{uv} {uv_s}"
                    );
                    let Some(p) = full.pixel_containing(q, 661, 495) else {
                        continue;
                    };
                    let (i, j) = (p % 661, p / 661);
                    let ps = small.pixel_containing(q, w, h).unwrap();
                    assert_eq!((ps % w, ps / w), (i / s as usize, j / s as usize));
                    checked += 1;
                }
            }
            assert!(checked > 3000, "{checked}");
        }
    }

    #[test]
    fn the_downscale_factor_is_the_divisor_of_both_sides() {
        assert_eq!(downscale_factor((660, 494), (660, 494)), Some(1));
        assert_eq!(downscale_factor((660, 494), (330, 247)), Some(2));
        assert_eq!(downscale_factor((660, 494), (165, 124)), Some(4));
        assert_eq!(downscale_factor((661, 495), (331, 248)), Some(2));
        assert_eq!(downscale_factor((660, 494), (330, 248)), None);
        assert_eq!(downscale_factor((660, 494), (0, 0)), None);
        assert_eq!(downscale_factor((660, 494), (1320, 988)), None);
        // 1/17 would fit, but the divisor is bounded.
        assert_eq!(downscale_factor((170, 170), (10, 10)), None);
    }

    #[test]
    fn look_at_points_z_at_target_and_y_down() {
        let eye = DVec3::new(10.0, -5.0, 3.0);
        let target = DVec3::new(0.0, 0.0, 1.0);
        let pose = Pose::look_at(eye, target, DVec3::Z).unwrap();
        assert!((pose.center() - eye).length() < 1e-12);
        let pc = pose.world_to_camera(target);
        assert!(pc.x.abs() < 1e-12 && pc.y.abs() < 1e-12 && pc.z > 0.0);
        // A point above the target appears higher in the image (smaller y).
        let up = pose.world_to_camera(target + DVec3::Z);
        assert!(up.y < 0.0);
        assert!(Pose::look_at(eye, eye, DVec3::Z).is_none());
        assert!(Pose::look_at(DVec3::ZERO, DVec3::Z, DVec3::Z).is_none());
    }

    #[test]
    fn colmap_quaternion_round_trip_and_bad_poses() {
        let pose = Pose::look_at(DVec3::new(3.0, 4.0, 5.0), DVec3::ZERO, DVec3::Z).unwrap();
        let q = pose.colmap_qvec();
        let back = Pose::from_colmap(q, pose.translation.to_array()).unwrap();
        assert!(
            (back.rotation - pose.rotation)
                .to_cols_array()
                .iter()
                .all(|d| d.abs() < 1e-12)
        );
        assert!(Pose::from_colmap([0.0; 4], [0.0; 3]).is_none());
        assert!(Pose::from_colmap([f64::NAN, 0.0, 0.0, 0.0], [0.0; 3]).is_none());
        assert!(Pose::from_colmap([1.0, 0.0, 0.0, 0.0], [f64::INFINITY, 0.0, 0.0]).is_none());
    }

    #[test]
    fn stem_drops_directories_and_extension() {
        let cam = Camera {
            intrinsics: Intrinsics {
                width: 2,
                height: 2,
                fx: 1.0,
                fy: 1.0,
                cx: 1.0,
                cy: 1.0,
                distortion: Distortion::None,
            },
            pose: Pose::look_at(DVec3::ZERO, DVec3::X, DVec3::Z).unwrap(),
        };
        let v = View {
            image_id: 1,
            camera_id: 1,
            name: "a/b/DJI_0001.JPG".into(),
            camera: cam,
        };
        assert_eq!(v.stem(), "DJI_0001");
    }
    fn camera_with(distortion: Distortion) -> Camera {
        Camera {
            intrinsics: Intrinsics {
                width: 640,
                height: 480,
                fx: 500.0,
                fy: 510.0,
                cx: 321.5,
                cy: 238.25,
                distortion,
            },
            pose: Pose::look_at(DVec3::ZERO, DVec3::X, DVec3::Z).unwrap(),
        }
    }

    /// distort ∘ undistort is the identity within 1e-6 px on a grid covering the whole
    /// image (every 4th pixel centre plus the corners), for each lens model.
    #[test]
    fn undistort_inverts_distort_over_the_whole_image() {
        let models = [
            Distortion::None,
            Distortion::Radial { k1: -0.12, k2: 0.0 },
            Distortion::Radial {
                k1: 0.08,
                k2: -0.02,
            },
            Distortion::OpenCv {
                k1: -0.2,
                k2: 0.05,
                p1: 1e-3,
                p2: -5e-4,
            },
            Distortion::FullOpenCv {
                k: [-0.25, 0.08, -0.01, 0.02, 0.01, 0.002],
                p1: 8e-4,
                p2: -3e-4,
            },
        ];
        for model in models {
            let cam = camera_with(model);
            let k = cam.intrinsics;
            let mut worst = 0.0f64;
            let mut pts: Vec<(f64, f64)> = Vec::new();
            for j in (0..k.height).step_by(4) {
                for i in (0..k.width).step_by(4) {
                    pts.push((i as f64 + 0.5, j as f64 + 0.5));
                }
            }
            pts.extend([(0.0, 0.0), (640.0, 0.0), (0.0, 480.0), (640.0, 480.0)]);
            for (u, v) in pts {
                let ray = cam.try_pixel_ray(u, v).expect("converges inside the image");
                let back = cam.project(ray).unwrap();
                worst = worst.max((back - DVec2::new(u, v)).length());
            }
            assert!(worst < 1e-6, "{model:?}: worst round trip {worst} px");
        }
    }

    #[test]
    fn pinhole_pixel_ray_goes_through_pixel_centres() {
        let cam = camera_with(Distortion::None);
        let r = cam.pixel_ray(321.5, 238.25);
        assert!((r - DVec3::Z).length() < 1e-15);
        let r = cam.pixel_ray(821.5, 238.25);
        assert!((r - DVec3::new(1.0, 0.0, 1.0).normalize()).length() < 1e-15);
        // Camera looks along world +x.
        assert!((cam.forward() - DVec3::X).length() < 1e-12);
    }

    #[test]
    fn undistort_reports_non_convergence_instead_of_panicking() {
        // Strong barrel distortion folds over beyond r ≈ 1.3: no preimage for large radii.
        let d = Distortion::Radial { k1: -0.2, k2: 0.0 };
        assert!(d.undistort(DVec2::new(5.0, 5.0)).is_none());
        assert!(d.undistort(DVec2::new(f64::NAN, 0.0)).is_none());
        let cam = camera_with(d);
        let r = cam.pixel_ray(1e7, 1e7);
        assert!(r.is_finite());
    }
}
