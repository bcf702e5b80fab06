//! The point of the splat surface a ray meets: what a click on a rendered 3DGS scene points
//! at, exact enough for ground-control points (`gs4city view`'s pick, `gs4city query --pick`).
//!
//! A pixel's blend list (Gaussian, weight `α·T`) in depth order is what the renderer
//! composites. The surface is where the ray's transmittance falls to one half: the Gaussian at
//! which the accumulated weight `Σ α·T = 1 − T` first reaches 0.5 (3DGS's *median depth*). The
//! point is taken on that Gaussian itself, where the ray passes its centre most closely in the
//! Gaussian's own metric: `t* = dᵀΣ⁻¹(μ − o) / dᵀΣ⁻¹d`, the maximum of the 3D density along
//! the ray. For the flat discs that make a 3DGS surface this is the ray's intersection with the
//! disc's plane — the surface itself, not the disc centre's depth, which lies off the ray by up
//! to the disc's radius times the slope of an oblique view.
use glam::{DMat3, DQuat, DVec3};

use super::Gaussians;

/// The transmittance at which the ray is taken to meet the surface.
pub const MEDIAN_TRANSMITTANCE: f64 = 0.5;

/// Where a ray meets the splat surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePoint {
    /// The point (scene frame).
    pub point: DVec3,
    /// The Gaussian whose weight brings the transmittance to one half.
    pub gaussian: u32,
    /// Distance along the (unit) ray.
    pub t: f64,
    /// Accumulated alpha of the whole list (`Σ α·T`).
    pub alpha: f64,
}

/// The point of the splat surface that the unit ray `origin + t·dir` meets, given its blend list
/// `(Gaussian, α·T)` in depth order (module docs); `None` when the list's accumulated alpha
/// stays below one half (sky, a gap between splats) or a Gaussian index is out of range.
pub fn surface_point(
    g: &Gaussians,
    list: impl IntoIterator<Item = (u32, f32)>,
    origin: DVec3,
    dir: DVec3,
) -> Option<SurfacePoint> {
    let dir = dir.try_normalize()?;
    let mut acc = 0.0f64;
    let mut hit: Option<u32> = None;
    for (id, w) in list {
        if id as usize >= g.len() {
            return None;
        }
        acc += f64::from(w);
        if hit.is_none() && acc >= 1.0 - MEDIAN_TRANSMITTANCE {
            hit = Some(id);
        }
    }
    let id = hit?;
    let t = ray_peak(g, id as usize, origin, dir);
    Some(SurfacePoint {
        point: origin + t * dir,
        gaussian: id,
        t,
        alpha: acc,
    })
}

/// `t*` of Gaussian `i` along the unit ray (module docs); the closest approach to its centre
/// when its covariance is degenerate.
pub fn ray_peak(g: &Gaussians, i: usize, origin: DVec3, dir: DVec3) -> f64 {
    let mu = DVec3::from(g.positions[i].map(f64::from));
    let along = (mu - origin).dot(dir);
    let Some([w, x, y, z]) = g.normalized_rotation(i) else {
        return along;
    };
    let r = DMat3::from_quat(DQuat::from_xyzw(
        f64::from(x),
        f64::from(y),
        f64::from(z),
        f64::from(w),
    ));
    let s = g.activated_scale(i).map(f64::from);
    let largest = s[0].max(s[1]).max(s[2]);
    if !(largest.is_finite() && largest > 0.0) {
        return along;
    }
    // Σ⁻¹ = R diag(1/s²) Rᵀ; a scale below 10⁻⁶ of the largest is held there (a disc of zero
    // thickness is still a plane).
    let inv = s.map(|v| 1.0 / v.max(largest * 1e-6).powi(2));
    let local_d = r.transpose() * dir;
    let local_m = r.transpose() * (mu - origin);
    let num = local_d.x * inv[0] * local_m.x
        + local_d.y * inv[1] * local_m.y
        + local_d.z * inv[2] * local_m.z;
    let den = local_d.x * local_d.x * inv[0]
        + local_d.y * local_d.y * inv[1]
        + local_d.z * local_d.z * inv[2];
    let t = num / den;
    if t.is_finite() { t } else { along }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One flat disc in the plane z = 2 (normal +z), centred off the ray: the ray from the
    /// origin along (0.3, 0, 1)/|·| meets the plane at t = 2·|(0.3, 0, 1)|, i.e. at (0.6, 0, 2),
    /// whatever the disc's centre within the plane.
    #[test]
    fn a_flat_disc_is_met_in_its_plane_not_at_its_centre_depth() {
        let mut g = Gaussians::default();
        g.positions.push([1.0, 0.5, 2.0]);
        g.scale.push([0.5f32.ln(), 0.5f32.ln(), 1e-5f32.ln()]);
        g.rotation.push([1.0, 0.0, 0.0, 0.0]);
        g.opacity.push(5.0);
        g.f_dc.push([0.0; 3]);
        let d = DVec3::new(0.3, 0.0, 1.0);
        let p = surface_point(&g, [(0u32, 0.9f32)], DVec3::ZERO, d).unwrap();
        assert!(
            (p.point - DVec3::new(0.6, 0.0, 2.0)).length() < 1e-6,
            "{p:?}"
        );
        assert!((p.t - 2.0 * d.length()).abs() < 1e-6);
        // The closest approach to the disc's centre lies 0.115 further along the ray.
        let along = DVec3::new(1.0, 0.5, 2.0).dot(d.normalize());
        assert!((along - p.t).abs() > 0.1);
        // Too little alpha: no surface.
        assert!(surface_point(&g, [(0u32, 0.4f32)], DVec3::ZERO, d).is_none());
        // The Gaussian that crosses one half, not the first of the list.
        g.positions.push([0.0, 0.0, 5.0]);
        g.scale.push([0.1f32.ln(); 3]);
        g.rotation.push([1.0, 0.0, 0.0, 0.0]);
        g.opacity.push(5.0);
        g.f_dc.push([0.0; 3]);
        let p = surface_point(&g, [(1u32, 0.3f32), (0, 0.3)], DVec3::ZERO, d).unwrap();
        assert_eq!(p.gaussian, 0);
        assert!((p.alpha - 0.6).abs() < 1e-6);
        // An id beyond the Gaussians: none.
        assert!(surface_point(&g, [(7u32, 0.9f32)], DVec3::ZERO, d).is_none());
    }

    /// A rotated disc: its normal along (0, 1, 1)/√2 through (0, 0, 4); the ray along z meets
    /// its plane y + z = 4 at (0, 0, 4) — and a ray along (0, 0.5, 1) at z = 4/1.5.
    #[test]
    fn a_rotated_disc() {
        let mut g = Gaussians::default();
        g.positions.push([0.0, 0.0, 4.0]);
        g.scale.push([1.0f32.ln(), 1.0f32.ln(), 1e-4f32.ln()]);
        // Rotation about x by −45°: local z → (0, 1, 1)/√2.
        let h = (std::f64::consts::FRAC_PI_8).cos() as f32;
        let s = (-std::f64::consts::FRAC_PI_8).sin() as f32;
        g.rotation.push([h, s, 0.0, 0.0]);
        g.opacity.push(5.0);
        g.f_dc.push([0.0; 3]);
        let d = DVec3::new(0.0, 0.5, 1.0);
        let p = surface_point(&g, [(0u32, 1.0f32)], DVec3::ZERO, d).unwrap();
        let want = d * (4.0 / 1.5);
        assert!((p.point - want).length() < 1e-3, "{p:?} vs {want}");
    }
}
