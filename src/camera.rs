//! Calibrated cameras in the COLMAP/OpenCV convention: world-to-camera pose
//! `x_cam = R · x_world + t`, camera +z forward, +x right, +y down, pixel centres at
//! integer coordinates + 0.5 in COLMAP (the principal point `cx, cy` is in that frame).
use glam::{DMat3, DQuat, DVec2, DVec3};

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
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
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
    /// Projects a camera-frame point with the pinhole part only (no distortion);
    /// `None` behind or on the camera plane.
    pub fn project_pinhole(&self, p_cam: DVec3) -> Option<DVec2> {
        if p_cam.z <= 0.0 {
            return None;
        }
        let k = &self.intrinsics;
        Some(DVec2::new(
            k.fx * p_cam.x / p_cam.z + k.cx,
            k.fy * p_cam.y / p_cam.z + k.cy,
        ))
    }

    /// The camera-frame direction (z = 1) of an undistorted pixel position.
    pub fn pinhole_direction(&self, pixel: DVec2) -> DVec3 {
        let k = &self.intrinsics;
        DVec3::new((pixel.x - k.cx) / k.fx, (pixel.y - k.cy) / k.fy, 1.0)
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
    /// The image name without directories and extension: the `<stem>` of every per-view file.
    pub fn stem(&self) -> String {
        let file = self.name.rsplit('/').next().unwrap_or(&self.name);
        match file.rfind('.') {
            Some(i) if i > 0 => file[..i].to_string(),
            _ => file.to_string(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
