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
/// Smallest contributing alpha (INRIA's).
pub const ALPHA_MIN: f32 = crate::cache::INRIA_ALPHA_MIN;

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
    /// The smallest α a Gaussian contributes with ([`ALPHA_MIN`], INRIA's 1/255, unless the
    /// render asks for a higher one: [`super::RenderOptions::alpha_min`]).
    pub alpha_min: f32,
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
            alpha_min: ALPHA_MIN,
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
    /// Half extents of the box outside which `alpha < 1/255` for sure (`alpha_extent`).
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
#[inline(always)]
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

/// Whether INRIA's tile rectangle is surely empty, decided before the 2D covariance is
/// computed: its radius `⌈3√λ₁⌉` is bounded through `λ₁ ≤ 2L + 0.32`, where
/// `L = ‖J‖²_F·‖Σ‖_F + 0.3` bounds the eigenvalues of the dilated `J·Σ·Jᵀ` (`‖Σ‖_F` bounds
/// `|λ(Σ)|` for any symmetric Σ, PSD or not) and INRIA's `λ₁ = mid + √max(0.1, mid² − det)`
/// adds at most 0.32 to the true one. A Gaussian whose mean lies further than that radius
/// (+ 1 px) outside the grid gets an empty rectangle in [`rect`]; NaN never culls here.
/// `jf` is `‖J‖²_F`.
#[inline(always)]
fn outside_grid(mean: [f64; 2], jf: f64, s: &[f64; 6], v: &ViewParams) -> bool {
    let r = radius_bound(jf * frobenius(s));
    let (wx, wy) = ((v.grid_x * TILE) as f64, (v.grid_y * TILE) as f64);
    mean[0] + r < 0.0 || mean[1] + r < 0.0 || mean[0] - r > wx || mean[1] - r > wy
}

/// `‖Σ‖_F` of a symmetric 3×3 matrix stored as `xx xy xz yy yz zz`.
#[inline(always)]
pub fn frobenius(s: &[f64; 6]) -> f64 {
    (s[0] * s[0] + s[3] * s[3] + s[5] * s[5] + 2.0 * (s[1] * s[1] + s[2] * s[2] + s[4] * s[4]))
        .sqrt()
}

/// The bound on INRIA's screen radius that the projection's grid cull uses (+ 1 px) given `‖J‖²_F·‖Σ‖_F`;
/// increasing in its argument.
#[inline(always)]
pub fn radius_bound(jf_sf: f64) -> f64 {
    let l = jf_sf + LOW_PASS;
    (3.0 * (2.0 * l + 0.32).sqrt() + 1.0) * (1.0 + 1e-9) + 1.0
}

/// Half extents `[ex, ey]` of the ellipse where `α ≥ α_min` is possible (`ln_ratio` =
/// `ln(o/α_min)`; INRIA's `α_min` = 1/255): the blend skips a pixel whose `power < −ln_ratio −
/// 1e-3`, i.e. whose `dᵀ·conic·d > q = 2(ln_ratio + 1e-3)`,
/// and that ellipse's half extents are `√(q·Σ_xx)`, `√(q·Σ_yy)` (`Σ = (a, b; b, c)`, the dilated
/// 2D covariance). The margin covers the `f32` rounding of `power` in the blend: its error
/// is a few ulp of `|a'dx²| + |c'dy²| + 2|b'dx·dy|`, which near the box's edge is at most
/// `4/(1 − ρ²)` times `dᵀ·conic·d` (`ρ²= b²/(a·c)`), so the relative margin grows with the
/// correlation; a pixel outside the box cannot pass the blend's test.
#[inline(always)]
fn alpha_extent(ln_ratio: f64, a: f64, c: f64, det: f64) -> [f32; 2] {
    let q = 2.0 * (ln_ratio.max(0.0) + 1e-3);
    let corr = (a * c / det).max(1.0);
    let grow = 1.0 + (1e-4 + 4e-6 * corr).min(1.0);
    [
        ((q * a).sqrt() * grow + 1e-3) as f32,
        ((q * c).sqrt() * grow + 1e-3) as f32,
    ]
}

/// `r` cut to the tiles that the box `mean ± extent` reaches (pixel centres `x` with
/// `|x − mean| ≤ extent`).
#[inline(always)]
fn tight_rect(r: [u32; 4], mean: [f64; 2], extent: [f32; 2]) -> [u32; 4] {
    let t = TILE as f64;
    // Tile of the first pixel column/row ≥ m − e (conservative: the tile of m − e), and one
    // past the tile of the last ≤ m + e (0 when m + e < 0); `as u32` saturates.
    let lo = |m: f64, e: f32| ((m - f64::from(e)).max(0.0) / t) as u32;
    let hi = |m: f64, e: f32| {
        let v = m + f64::from(e);
        if v < 0.0 { 0 } else { (v / t) as u32 + 1 }
    };
    let x0 = r[0].max(lo(mean[0], extent[0]));
    let y0 = r[1].max(lo(mean[1], extent[1]));
    let x1 = r[2].min(hi(mean[0], extent[0])).max(x0);
    let y1 = r[3].min(hi(mean[1], extent[1])).max(y0);
    [x0, y0, x1, y1]
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
/// empty tile rectangle) or it cannot contribute anywhere (opacity < `v.alpha_min`, not
/// finite).
pub fn project(
    scene: &PreparedScene,
    i: usize,
    v: &ViewParams,
    antialiased: bool,
    max_degree: u8,
) -> Option<Projected> {
    let front = Front::<1>::new(scene, &[i as u32], v);
    finish(scene, i, &front, 0, v, antialiased, max_degree)
}

/// Gaussians per batch of [`project_into`].
pub const LANES: usize = 4;

/// [`project`] of the Gaussians `ids` into `out`, `LANES` at a time (`out` has
/// `ids.len().div_ceil(LANES)` batches; a short last batch is padded with culled entries, and
/// a culled Gaussian is [`Projected::CULLED`]). The arithmetic up to the 2D covariance runs lane
/// by lane in the same operations and order as for one Gaussian, so that it vectorises and
/// every lane's result is bit for bit [`project`]'s; runs under the widest instruction set
/// the CPU has (`pulp`'s dispatch).
pub fn project_into(
    scene: &PreparedScene,
    ids: &[u32],
    v: &ViewParams,
    antialiased: bool,
    max_degree: u8,
    out: &mut [[Projected; LANES]],
) {
    pulp::Arch::new().dispatch(BatchOp {
        scene,
        ids,
        v,
        antialiased,
        max_degree,
        out,
    })
}

/// [`project_into`]'s arguments as a `pulp` operation.
struct BatchOp<'a> {
    scene: &'a PreparedScene,
    ids: &'a [u32],
    v: &'a ViewParams,
    antialiased: bool,
    max_degree: u8,
    out: &'a mut [[Projected; LANES]],
}

impl pulp::WithSimd for BatchOp<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let (scene, v, aa, deg) = (self.scene, self.v, self.antialiased, self.max_degree);
        for (out, ids) in self.out.iter_mut().zip(self.ids.chunks(LANES)) {
            match <&[u32; LANES]>::try_from(ids) {
                Ok(ids) => {
                    let front = Front::<LANES>::new(scene, ids, v);
                    for (l, (o, &i)) in out.iter_mut().zip(ids).enumerate() {
                        *o = finish(scene, i as usize, &front, l, v, aa, deg)
                            .unwrap_or(Projected::CULLED);
                    }
                }
                Err(_) => {
                    *out = [Projected::CULLED; LANES];
                    for (o, &i) in out.iter_mut().zip(ids) {
                        *o = project(scene, i as usize, v, aa, deg).unwrap_or(Projected::CULLED);
                    }
                }
            }
        }
    }
}

/// The branch-free front of the projection for `L` Gaussians, one array per quantity: the
/// camera-frame depth, the projected mean, [`outside_grid`]'s verdict, the 2D covariance
/// `abc` and its determinant before the low-pass (`det0`) and after it (`det`). Lane `l`
/// performs exactly the scalar operations of one Gaussian (glam's order for `R·p + t`,
/// `(R·Σ)·Rᵀ` and `J·Σ'·Jᵀ`, zero entries of `J` included), so any `L` gives the same bits.
struct Front<const L: usize> {
    tz: [f64; L],
    mean: [[f64; 2]; L],
    outside: [bool; L],
    /// `(a, b, c)` before the low-pass.
    abc: [[f64; 3]; L],
    det0: [f64; L],
    det: [f64; L],
}

impl<const L: usize> Front<L> {
    // Lane loops index several arrays at once; plain loops over `0..L` vectorise.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn new(scene: &PreparedScene, ids: &[u32; L], v: &ViewParams) -> Self {
        let (mut px, mut py, mut pz) = ([0.0f64; L], [0.0f64; L], [0.0f64; L]);
        let mut s = [[0.0f64; L]; 6];
        for l in 0..L {
            let i = ids[l] as usize;
            let p = scene.positions[i];
            (px[l], py[l], pz[l]) = (p[0].into(), p[1].into(), p[2].into());
            let c = scene.cov3d[i];
            for k in 0..6 {
                s[k][l] = c[k].into();
            }
        }
        let r = v.rot.to_cols_array_2d();
        let tr = v.trans.to_array();
        // t = R·p + trans (glam: x_axis·p.x + y_axis·p.y + z_axis·p.z, then + trans).
        let mut t = [[0.0f64; L]; 3];
        for k in 0..3 {
            for l in 0..L {
                t[k][l] = ((r[0][k] * px[l] + r[1][k] * py[l]) + r[2][k] * pz[l]) + tr[k];
            }
        }
        let [tx, ty, tz] = t;
        let limx = 1.3 * v.tan_fovx;
        let limy = 1.3 * v.tan_fovy;
        // `f64::clamp` as selects (NaN passes through, as there).
        let clamp = |x: f64, lim: f64| {
            if x < -lim {
                -lim
            } else if x > lim {
                lim
            } else {
                x
            }
        };
        let (mut j0x, mut j0z, mut j1y, mut j1z) =
            ([0.0f64; L], [0.0f64; L], [0.0f64; L], [0.0f64; L]);
        let mut mean = [[0.0f64; 2]; L];
        let mut outside = [false; L];
        for l in 0..L {
            let z = tz[l];
            let txc = clamp(tx[l] / z, limx) * z;
            let tyc = clamp(ty[l] / z, limy) * z;
            j0x[l] = v.fx / z;
            j0z[l] = -(v.fx * txc) / (z * z);
            j1y[l] = v.fy / z;
            j1z[l] = -(v.fy * tyc) / (z * z);
            let m = [v.fx * tx[l] / z + v.cx - 0.5, v.fy * ty[l] / z + v.cy - 0.5];
            mean[l] = m;
            // outside_grid: ‖J‖²_F (J's zero entries as glam's dot products see them) · ‖Σ‖_F.
            let jf = ((j0x[l] * j0x[l] + 0.0 * 0.0) + j0z[l] * j0z[l])
                + ((0.0 * 0.0 + j1y[l] * j1y[l]) + j1z[l] * j1z[l]);
            let sl = [s[0][l], s[1][l], s[2][l], s[3][l], s[4][l], s[5][l]];
            outside[l] = outside_grid(m, jf, &sl, v);
        }
        // Σ's columns (xx xy xz yy yz zz): column c, row k is s[SIG[c][k]].
        const SIG: [[usize; 3]; 3] = [[0, 1, 2], [1, 3, 4], [2, 4, 5]];
        // M = R·Σ, column c = R·Σ_c; then C = M·Rᵀ, column c = M·(row c of R).
        let mut m = [[[0.0f64; L]; 3]; 3];
        for c in 0..3 {
            let u = SIG[c];
            for k in 0..3 {
                for l in 0..L {
                    m[c][k][l] =
                        (r[0][k] * s[u[0]][l] + r[1][k] * s[u[1]][l]) + r[2][k] * s[u[2]][l];
                }
            }
        }
        let mut cc = [[[0.0f64; L]; 3]; 3];
        for c in 0..3 {
            for k in 0..3 {
                for l in 0..L {
                    cc[c][k][l] =
                        (m[0][k][l] * r[0][c] + m[1][k][l] * r[1][c]) + m[2][k][l] * r[2][c];
                }
            }
        }
        // C·j0 and C·j1 (j0 = (j0x, 0, j0z), j1 = (0, j1y, j1z)), then the dot products.
        let mut abc = [[0.0f64; 3]; L];
        let (mut det0, mut det) = ([0.0f64; L], [0.0f64; L]);
        for l in 0..L {
            let cj0: [f64; 3] = std::array::from_fn(|k| {
                (cc[0][k][l] * j0x[l] + cc[1][k][l] * 0.0) + cc[2][k][l] * j0z[l]
            });
            let cj1: [f64; 3] = std::array::from_fn(|k| {
                (cc[0][k][l] * 0.0 + cc[1][k][l] * j1y[l]) + cc[2][k][l] * j1z[l]
            });
            let a = (j0x[l] * cj0[0] + 0.0 * cj0[1]) + j0z[l] * cj0[2];
            let b = (j0x[l] * cj1[0] + 0.0 * cj1[1]) + j0z[l] * cj1[2];
            let c = (0.0 * cj1[0] + j1y[l] * cj1[1]) + j1z[l] * cj1[2];
            abc[l] = [a, b, c];
            det0[l] = a * c - b * b;
            det[l] = (a + LOW_PASS) * (c + LOW_PASS) - b * b;
        }
        Front {
            tz,
            mean,
            outside,
            abc,
            det0,
            det,
        }
    }
}

/// The rest of [`project`] for lane `l` of `front` (Gaussian `i`): the culls, the conic, the
/// screen radius, the opacity, the tile rectangle and the colour.
#[inline(always)]
fn finish<const L: usize>(
    scene: &PreparedScene,
    i: usize,
    front: &Front<L>,
    l: usize,
    v: &ViewParams,
    antialiased: bool,
    max_degree: u8,
) -> Option<Projected> {
    let tz = front.tz[l];
    if tz.is_nan() || tz <= NEAR || front.outside[l] {
        return None;
    }
    let mean = front.mean[l];
    let [a, b, c] = front.abc[l];
    let (a, c) = (a + LOW_PASS, c + LOW_PASS);
    let (det0, det) = (front.det0[l], front.det[l]);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    let conic = [c * inv, -b * inv, a * inv];
    let mid = 0.5 * (a + c);
    let lambda1 = mid + (mid * mid - det).max(0.1).sqrt();
    let radius = (3.0 * lambda1.sqrt()).ceil();
    let mut opacity = f64::from(scene.opacity[i]);
    if antialiased {
        opacity *= (det0 / det).max(0.000_025).sqrt();
    }
    let opacity = opacity as f32;
    if opacity.is_nan() || opacity < v.alpha_min {
        return None;
    }
    // ln(o/α_min): α = o·e^power ≥ α_min where power ≥ −ln(o/α_min).
    let ln_ratio = (f64::from(opacity) / f64::from(v.alpha_min)).ln();
    let extent = alpha_extent(ln_ratio, a, c, det);
    // INRIA's rectangle (3·√λ₁), cut to the tiles the α ≥ α_min box reaches: a tile outside
    // that box gets nothing from this Gaussian, so leaving it out changes no pixel.
    let r = rect(mean, radius, v.grid_x, v.grid_y);
    let r = tight_rect(r, mean, extent);
    if (r[2] - r[0]) * (r[3] - r[1]) == 0 {
        return None;
    }
    let k = scene.coeffs;
    let degree = scene.sh_degree.min(max_degree);
    // Degree 0 is view-independent: no viewing direction needed.
    let dir = if degree > 0 {
        let pw = DVec3::from_array(scene.positions[i].map(f64::from));
        (pw - v.center).normalize_or_zero()
    } else {
        DVec3::ZERO
    };
    let color = sh_color(&scene.sh[i * k..(i + 1) * k], degree, dir);
    Some(Projected {
        mean,
        conic: conic.map(|x| x as f32),
        opacity,
        depth: tz as f32,
        color,
        extent,
        power_min: (-ln_ratio - 1e-3) as f32,
        rect: r,
        id: i as u32,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rows of INRIA's projection Jacobian `J` at camera-frame point `t` (its x/y clamped
    /// to 1.3× the field of view) and the projected mean in pixel-index coordinates, written
    /// out with glam's types (the reference for [`Front`]).
    fn jacobian_and_mean(v: &ViewParams, t: DVec3) -> (DVec3, DVec3, [f64; 2]) {
        let limx = 1.3 * v.tan_fovx;
        let limy = 1.3 * v.tan_fovy;
        let tx = (t.x / t.z).clamp(-limx, limx) * t.z;
        let ty = (t.y / t.z).clamp(-limy, limy) * t.z;
        let j0 = DVec3::new(v.fx / t.z, 0.0, -(v.fx * tx) / (t.z * t.z));
        let j1 = DVec3::new(0.0, v.fy / t.z, -(v.fy * ty) / (t.z * t.z));
        let mean = [v.fx * t.x / t.z + v.cx - 0.5, v.fy * t.y / t.z + v.cy - 0.5];
        (j0, j1, mean)
    }

    /// The front of the projection written with glam's types, as it was before the lanes:
    /// `(t.z, mean, outside_grid, (a, b, c), det0, det)`, the reference of [`Front`]'s bits.
    #[allow(clippy::type_complexity)]
    fn reference_front(
        scene: &PreparedScene,
        i: usize,
        v: &ViewParams,
    ) -> (f64, [f64; 2], bool, [f64; 3], f64, f64) {
        let pw = DVec3::from_array(scene.positions[i].map(f64::from));
        let t = v.rot * pw + v.trans;
        let (j0, j1, mean) = jacobian_and_mean(v, t);
        let s = scene.cov3d[i].map(f64::from);
        let outside = outside_grid(mean, j0.length_squared() + j1.length_squared(), &s, v);
        let sigma = DMat3::from_cols_array(&[s[0], s[1], s[2], s[1], s[3], s[4], s[2], s[4], s[5]]);
        let cov_cam = v.rot * sigma * v.rot.transpose();
        let (cj0, cj1) = (cov_cam * j0, cov_cam * j1);
        let (a, b, c) = (j0.dot(cj0), j0.dot(cj1), j1.dot(cj1));
        let det = (a + LOW_PASS) * (c + LOW_PASS) - b * b;
        (t.z, mean, outside, [a, b, c], a * c - b * b, det)
    }

    /// Every field's bits (a culled Gaussian is `None`).
    fn bits(p: &Projected) -> Option<Vec<u64>> {
        if p.id == u32::MAX {
            return None;
        }
        let f = |x: f32| u64::from(x.to_bits());
        let mut b = vec![p.mean[0].to_bits(), p.mean[1].to_bits()];
        b.extend(p.conic.map(f));
        b.extend([f(p.opacity), f(p.depth), f(p.power_min)]);
        b.extend(p.color.map(f));
        b.extend(p.extent.map(f));
        b.extend(p.rect.map(u64::from));
        b.push(u64::from(p.id));
        Some(b)
    }

    /// The lanes give the glam-written front's bits in every lane (NaN where it has NaN), and
    /// the batched projection gives the one-Gaussian projection's result for every Gaussian,
    /// in full batches and a short last one, over cameras near, far, tilted and inside the
    /// cloud, with NaN centres, zero quaternions, needles and Gaussians behind or at the near
    /// plane.
    #[test]
    fn the_lanes_give_the_reference_projection_bit_for_bit() {
        use rand::{Rng, SeedableRng};
        let scene = crate::render::tests::random_scene(4_001, 30.0, 41);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let same = |x: f64, y: f64| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan());
        let (mut seen, mut culled) = (0usize, 0usize);
        for k in 0..24 {
            let c =
                crate::render::tests::random_centre(&mut rng, if k % 3 == 0 { 5.0 } else { 25.0 });
            let f = rng.random_range(if k % 4 == 0 {
                300.0..3000.0
            } else {
                20.0..200.0
            });
            let cam = crate::render::tests::camera_at(
                c,
                rng.random_range(-3.1..3.1),
                rng.random_range(-1.5..1.5),
                200,
                150,
                f,
            );
            let v = ViewParams::new(&cam);
            let all: Vec<u32> = (0..scene.len() as u32).collect();
            for ids in all.chunks_exact(LANES) {
                let front = Front::<LANES>::new(&scene, ids.try_into().unwrap(), &v);
                for (l, &i) in ids.iter().enumerate() {
                    let (tz, mean, outside, abc, det0, det) =
                        reference_front(&scene, i as usize, &v);
                    let at = format!("view {k}, Gaussian {i}");
                    assert!(same(front.tz[l], tz), "{at}: z");
                    assert!(
                        (0..2).all(|q| same(front.mean[l][q], mean[q])),
                        "{at}: mean"
                    );
                    assert_eq!(front.outside[l], outside, "{at}: grid cull");
                    assert!(
                        (0..3).all(|q| same(front.abc[l][q], abc[q])),
                        "{at}: covariance"
                    );
                    assert!(
                        same(front.det0[l], det0) && same(front.det[l], det),
                        "{at}: det"
                    );
                }
            }
            // Every Gaussian, then an odd subset (a short last batch).
            let odd: Vec<u32> = (0..scene.len() as u32)
                .filter(|i| i % 7 != 3)
                .take(1_003)
                .collect();
            for ids in [&all, &odd] {
                for aa in [false, true] {
                    let mut out = vec![[Projected::CULLED; LANES]; ids.len().div_ceil(LANES)];
                    project_into(&scene, ids, &v, aa, 0, &mut out);
                    let flat = out.as_flattened();
                    assert!(flat[ids.len()..].iter().all(|p| !p.is_visible()));
                    for (p, &i) in flat.iter().zip(ids.iter()) {
                        let want = project(&scene, i as usize, &v, aa, 0);
                        assert_eq!(
                            bits(p),
                            want.as_ref().and_then(bits),
                            "view {k}, Gaussian {i}, antialiased {aa}"
                        );
                        if want.is_some() {
                            seen += 1;
                        } else {
                            culled += 1;
                        }
                    }
                }
            }
        }
        assert!(
            seen > 20_000 && culled > 20_000,
            "{seen} projected, {culled} culled"
        );
    }

    #[test]
    fn rect_truncates_toward_zero_and_clamps() {
        assert_eq!(rect([-5.0, 20.0], 3.0, 4, 4), [0, 1, 0, 2]);
        assert_eq!(rect([8.0, 8.0], 3.0, 4, 4), [0, 0, 1, 1]);
        assert_eq!(rect([8.0, 8.0], 1e30, 4, 4), [0, 0, 4, 4]);
    }

    /// A 2D covariance with eigenvalues `l1 ≥ l2` rotated by `theta`: `(a, b, c)`.
    fn cov2(l1: f64, l2: f64, theta: f64) -> (f64, f64, f64) {
        let (s, c) = theta.sin_cos();
        (
            l1 * c * c + l2 * s * s,
            (l1 - l2) * s * c,
            l1 * s * s + l2 * c * c,
        )
    }

    #[test]
    fn alpha_extent_box_holds_every_pixel_the_blend_can_take() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(29);
        let mut inside_hits = 0usize;
        for case in 0..400 {
            // Dilated covariances from round to needle-thin and strongly correlated.
            let l2 = 0.3 + rng.random::<f64>() * if case % 2 == 0 { 0.2 } else { 5.0 };
            let l1 = l2 * 10f64.powf(rng.random::<f64>() * 3.5);
            let theta = if case % 3 == 0 {
                std::f64::consts::FRAC_PI_4 + rng.random::<f64>() * 1e-3
            } else {
                rng.random::<f64>() * std::f64::consts::PI
            };
            let (a, b, c) = cov2(l1, l2, theta);
            let det = a * c - b * b;
            let conic = [(c / det) as f32, (-b / det) as f32, (a / det) as f32];
            let o = (ALPHA_MIN + rng.random::<f32>() * (1.0 - ALPHA_MIN)).min(1.0);
            let ln255o = (255.0 * f64::from(o)).ln();
            let pmin = (-ln255o - 1e-3) as f32;
            let [ex, ey] = alpha_extent(ln255o, a, c, det);
            let (mx, my) = (rng.random::<f32>() * 16.0, rng.random::<f32>() * 16.0);
            // The blend's test, as `blend_tile` computes it.
            let takes = |x: f32, y: f32| {
                let (dx, dy) = (mx - x, my - y);
                let power = -0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) - conic[1] * dx * dy;
                let alpha = super::super::blend::ALPHA_MAX.min(o * crate::fastmath::exp_neg(power));
                !(power > 0.0 || power < pmin || alpha < ALPHA_MIN)
            };
            let (x0, x1) = ((mx - ex).ceil(), (mx + ex).floor());
            let (y0, y1) = ((my - ey).ceil(), (my + ey).floor());
            // The two pixel columns and rows just outside the box, along the whole box
            // (+3): there the ellipse comes closest to the outside.
            let span = |a: f32, b: f32| (0..=(b - a) as i32 + 6).map(move |i| a - 3.0 + i as f32);
            for k in [1.0f32, 2.0] {
                let cols = [x0 - k, x1 + k]
                    .into_iter()
                    .flat_map(|x| span(y0, y1).map(move |y| (x, y)));
                let rows = [y0 - k, y1 + k]
                    .into_iter()
                    .flat_map(|y| span(x0, x1).map(move |x| (x, y)));
                for (x, y) in cols.chain(rows) {
                    assert!(
                        !takes(x, y),
                        "case {case}: pixel ({x}, {y}) outside the box is taken"
                    );
                }
            }
            inside_hits += usize::from(takes(mx.round(), my.round()));
        }
        // The pixel nearest the mean is taken in most cases: the test is not vacuous.
        assert!(inside_hits > 300, "{inside_hits}");
    }

    #[test]
    fn outside_grid_only_culls_gaussians_with_an_empty_rectangle() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let (width, height, f) = (640usize, 480usize, 500.0);
        let v = ViewParams {
            rot: DMat3::IDENTITY,
            trans: DVec3::ZERO,
            center: DVec3::ZERO,
            fx: f,
            fy: f,
            cx: 320.0,
            cy: 240.0,
            tan_fovx: width as f64 / (2.0 * f),
            tan_fovy: height as f64 / (2.0 * f),
            width,
            height,
            grid_x: width.div_ceil(TILE),
            grid_y: height.div_ceil(TILE),
            alpha_min: ALPHA_MIN,
        };
        let (mut culled, mut kept_nonempty) = (0, 0);
        for _ in 0..20_000 {
            let t = DVec3::new(
                rng.random_range(-60.0..60.0),
                rng.random_range(-60.0..60.0),
                rng.random_range(0.25..60.0),
            );
            // Σ = R·diag(s²)·Rᵀ from a random rotation and log-uniform scales.
            let q = glam::DQuat::from_xyzw(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            let sc = DVec3::new(
                10f64.powf(rng.random_range(-3.0..1.0)),
                10f64.powf(rng.random_range(-3.0..1.0)),
                10f64.powf(rng.random_range(-3.0..1.0)),
            );
            let r = DMat3::from_quat(q);
            let sigma = r * DMat3::from_diagonal(sc * sc) * r.transpose();
            let s = [
                sigma.x_axis.x,
                sigma.y_axis.x,
                sigma.z_axis.x,
                sigma.y_axis.y,
                sigma.z_axis.y,
                sigma.z_axis.z,
            ];
            let (j0, j1, mean) = jacobian_and_mean(&v, t);
            // INRIA's rectangle, computed the long way.
            let a = j0.dot(sigma * j0) + LOW_PASS;
            let b = j0.dot(sigma * j1);
            let c = j1.dot(sigma * j1) + LOW_PASS;
            let det = a * c - b * b;
            let mid = 0.5 * (a + c);
            let lambda1 = mid + (mid * mid - det).max(0.1).sqrt();
            let rc = rect(mean, (3.0 * lambda1.sqrt()).ceil(), v.grid_x, v.grid_y);
            let empty = (rc[2] - rc[0]) * (rc[3] - rc[1]) == 0;
            if outside_grid(mean, j0.length_squared() + j1.length_squared(), &s, &v) {
                assert!(
                    empty,
                    "culled but INRIA's rectangle is {rc:?} (mean {mean:?})"
                );
                culled += 1;
            } else if !empty {
                kept_nonempty += 1;
            }
        }
        assert!(
            culled > 5_000 && kept_nonempty > 1_000,
            "{culled} {kept_nonempty}"
        );
    }

    #[test]
    fn sh_degree_zero_is_dc_plus_half() {
        let col = sh_color(&[[1.0, 0.0, -10.0]], 0, DVec3::Z);
        assert!((f64::from(col[0]) - (SH_C0 + 0.5)).abs() < 1e-6);
        assert_eq!(col[1], 0.5);
        assert_eq!(col[2], 0.0);
    }
}
