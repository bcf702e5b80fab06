//! Two-pass raycasting (GS4City §3.1, a stage): casts one ray per pixel centre of each
//! view into the labelled city mesh and produces per-pixel feature / surface / part ids,
//! the city id `M_city` and the z-depth.
//!
//! * Global pass over all faces: front-most face `f*`, its label `(feature, surface, part)`
//!   and depth `D_t`.
//! * Part pass over the part-level faces only (`label.part != −1`, a second Embree scene;
//!   its primitive ids map back to mesh faces through a `Vec<u32>`): part depth `D̃`, part
//!   id `p̃` and its parent surface `s̃` (that face's `label.surface`).
//! * Accept `γ = (s̃ = s_t) ∧ (D̃ − D_t ≤ τ)`, with `s_t ≠ −1` (a missing surface equals
//!   nothing). `p = p̃` where accepted; otherwise the global hit's own part id (a part face
//!   hit directly in the global pass keeps its part; else −1).
//! * `M_city = p` if `p ≠ −1`, else `s_t` if ≠ −1, else the feature id.
//!
//! Depth is z-depth along the camera axis (`t · dot(dir, forward)` for the unit ray
//! direction), NaN where nothing is hit. τ is in scene units (the caller converts metres
//! with the alignment scale). The part pass only needs hits with `D̃ ≤ D_t + τ`, so its
//! `tfar` is limited accordingly, and no part face (each is also a face of the global
//! scene) lies in front of the global hit, so its `tnear` starts just before that hit —
//! the result is identical, the work smaller.
//!
//! Rays are traced in Embree's coherent packets as wide as the CPU traces natively
//! ([`PacketWidth::native`]: 16 lanes on 4×4 pixel tiles with AVX-512, else 8 lanes on 4×2),
//! in 8×8-pixel blocks, strips of 8 rows in parallel (rayon); every pixel's result is
//! independent of the packet width and the thread count.
mod output;

use std::time::Instant;

use rayon::prelude::*;

use crate::camera::Camera;
use crate::embree::{
    CommittedScene, Device, EmbreeError, Packet8, Packet16, PacketWidth, RayPacket, Scene,
};
use crate::mesh::{FaceLabel, TriMesh};

pub use output::{Overlays, RaycastSummary, ViewSummary, run};

/// The default depth tolerance τ of the part pass, in metres (× the alignment scale).
pub const TAU_M: f64 = 0.5;

/// Errors of the raycasting stage.
#[derive(Debug, thiserror::Error)]
pub enum RaycastError {
    #[error(transparent)]
    Embree(#[from] EmbreeError),
    #[error("invalid mesh: {0}")]
    Mesh(String),
    #[error(transparent)]
    Option(#[from] crate::check::OutOfRange),
    #[error("view {name}: {why}")]
    View { name: String, why: String },
    #[error(transparent)]
    Npy(#[from] crate::npy::NpyError),
    #[error(transparent)]
    IdMap(#[from] crate::idmap::IdMapError),
    #[error(transparent)]
    Image(#[from] crate::imageio::ImageError),
    #[error(transparent)]
    Fs(#[from] crate::fsutil::FsError),
}

/// Options of the raycasting stage.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RaycastOptions {
    /// Depth tolerance τ of the part pass, in scene units (≥ 0).
    pub tau: f64,
    /// Disables the part pass (single-pass labels, for comparison).
    pub single_pass: bool,
}

impl Default for RaycastOptions {
    fn default() -> Self {
        RaycastOptions {
            tau: 0.5,
            single_pass: false,
        }
    }
}

impl RaycastOptions {
    /// Checks τ (finite, ≥ 0).
    pub fn validate(&self) -> Result<(), RaycastError> {
        Ok(crate::check::non_negative("tau", self.tau)?)
    }
}

/// The largest entity id a mesh label may hold (2²⁴ − 1: a dense per-surface table of this
/// size takes 16 MB; the 30 real CityGML files the tests
/// read hold 3,193 entities together).
pub const MAX_LABEL_ID: i32 = (1 << 24) - 1;

/// The two committed Embree scenes of a mesh plus the face labels.
pub struct TwoPassScene {
    global: CommittedScene,
    part: CommittedScene,
    /// Part-scene primitive id → mesh face index.
    part_faces: Vec<u32>,
    labels: Vec<FaceLabel>,
    /// Indexed by surface id: whether any part face has that parent surface.
    surface_has_parts: Vec<bool>,
    /// Lanes per packet in [`raycast_view`].
    packet_width: PacketWidth,
    /// Seconds spent building both scenes.
    pub build_seconds: f64,
}

impl TwoPassScene {
    /// Validates the mesh ([`TriMesh::validate`]: finite vertices within the scene frame's
    /// `camera::SCENE_COORD_LIMIT`, which keeps every coordinate far inside what Embree
    /// accepts; label ids −1 or ≥ 0) and builds the global and part scenes. Label ids must
    /// also stay below [`MAX_LABEL_ID`] (the per-surface table is dense); checking them
    /// against the semantic table is `semantics::check_mesh_labels`.
    pub fn build(mesh: &TriMesh) -> Result<TwoPassScene, RaycastError> {
        TwoPassScene::build_with(mesh, false)
    }

    /// [`TwoPassScene::build`], optionally with Embree's high-quality BVH build
    /// ([`Scene::set_high_quality`]; measured in `benches/raycast.rs`).
    pub fn build_with(mesh: &TriMesh, high_quality: bool) -> Result<TwoPassScene, RaycastError> {
        mesh.validate().map_err(RaycastError::Mesh)?;
        if let Some((i, l)) = mesh
            .labels
            .iter()
            .enumerate()
            .find(|(_, l)| l.ids().iter().any(|&id| id > MAX_LABEL_ID))
        {
            return Err(RaycastError::Mesh(format!(
                "face {i} has label ids {}, {}, {}, beyond the largest supported id {MAX_LABEL_ID}",
                l.feature, l.surface, l.part
            )));
        }
        let t0 = Instant::now();
        let device = Device::new()?;
        let mut global = Scene::new(&device)?;
        if high_quality {
            global.set_high_quality()?;
        }
        global.add_triangles(&mesh.vertices, &mesh.faces)?;
        let part_faces: Vec<u32> = (0..mesh.faces.len() as u32)
            .filter(|&i| mesh.labels[i as usize].part != -1)
            .collect();
        let sub: Vec<[u32; 3]> = part_faces.iter().map(|&i| mesh.faces[i as usize]).collect();
        let mut part = Scene::new(&device)?;
        if high_quality {
            part.set_high_quality()?;
        }
        part.add_triangles(&mesh.vertices, &sub)?;
        let (global, part) = (global.commit()?, part.commit()?);
        let max_surface = mesh.labels.iter().map(|l| l.surface).max().unwrap_or(-1);
        let mut surface_has_parts = vec![false; (max_surface + 1).max(0) as usize];
        for &f in &part_faces {
            if let Ok(s) = usize::try_from(mesh.labels[f as usize].surface) {
                surface_has_parts[s] = true;
            }
        }
        Ok(TwoPassScene {
            global,
            part,
            part_faces,
            surface_has_parts,
            labels: mesh.labels.clone(),
            packet_width: PacketWidth::native(&device),
            build_seconds: t0.elapsed().as_secs_f64(),
        })
    }

    /// Whether a part face hangs under surface `s` (only then can the part pass change a pixel).
    fn has_parts(&self, s: i32) -> bool {
        usize::try_from(s)
            .ok()
            .and_then(|i| self.surface_has_parts.get(i))
            .copied()
            .unwrap_or(false)
    }

    /// The packet width [`raycast_view`] traces with (the CPU's native one).
    pub fn packet_width(&self) -> PacketWidth {
        self.packet_width
    }

    /// Number of faces in the global and in the part scene.
    pub fn face_counts(&self) -> (usize, usize) {
        (self.labels.len(), self.part_faces.len())
    }

    /// Global pass for one ray: mesh face index and hit distance `t`.
    pub fn trace_global(&self, org: [f32; 3], dir: [f32; 3]) -> Option<(u32, f32)> {
        self.global
            .intersect1(org, dir, f32::INFINITY)
            .map(|h| (h.prim_id, h.t))
    }
}

/// The per-pixel result of one view, row-major `H×W` each.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewIds {
    pub width: usize,
    pub height: usize,
    pub feature: Vec<i32>,
    pub surface: Vec<i32>,
    pub part: Vec<i32>,
    pub city: Vec<i32>,
    /// z-depth, NaN where nothing is hit.
    pub depth: Vec<f32>,
    /// Global-pass mesh face index, −1 where nothing is hit.
    pub face: Vec<i32>,
    /// Pixels whose part came from the part pass where the global face had none
    /// (single pass would have labelled them surface/feature).
    pub recovered: Vec<bool>,
    /// Pixels whose ray could not be undistorted (traced as misses).
    pub undistort_failures: usize,
    /// Lanes of the ray packets the view was traced with (8 or 16).
    pub lanes: usize,
}

impl ViewIds {
    /// Pixels with a part id.
    pub fn part_pixels(&self) -> usize {
        self.part.iter().filter(|&&p| p != -1).count()
    }
    /// Pixels recovered by the part pass.
    pub fn recovered_pixels(&self) -> usize {
        self.recovered.iter().filter(|&&r| r).count()
    }
    /// Distinct part ids among the recovered pixels.
    pub fn recovered_parts(&self) -> usize {
        let mut ids: Vec<i32> = self
            .part
            .iter()
            .zip(&self.recovered)
            .filter(|(_, r)| **r)
            .map(|(p, _)| *p)
            .collect();
        ids.sort_unstable();
        ids.dedup();
        ids.len()
    }
}

/// The world-space ray of pixel `(i, j)` (through its centre `(i + 0.5, j + 0.5)`):
/// origin, unit direction (f32 for Embree) and the z-depth factor `dot(dir, forward)`.
/// `None` where undistortion does not converge.
pub fn pixel_ray(camera: &Camera, i: usize, j: usize) -> Option<([f32; 3], [f32; 3], f64)> {
    let c = camera.try_pixel_ray(i as f64 + 0.5, j as f64 + 0.5)?;
    let rt = camera.pose.rotation.transpose();
    let dir = rt * c;
    let org = camera.pose.center();
    Some((org.as_vec3().to_array(), dir.as_vec3().to_array(), c.z))
}

/// Pixels per side of the blocks a strip is traced in (4×4 or 4×2 packet tiles inside).
const BLOCK: usize = 8;

/// The rays of one view: the camera centre and, per column and per row, the distorted
/// normalised coordinate (`(i + 0.5 − cx)/fx`, `(j + 0.5 − cy)/fy`, as
/// [`Camera::try_pixel_ray`] computes them: the same f64 operations, so the same rays).
struct ViewRays<'a> {
    camera: &'a Camera,
    org: [f32; 3],
    rt: glam::DMat3,
    xs: Vec<f64>,
    ys: Vec<f64>,
}

impl<'a> ViewRays<'a> {
    fn new(camera: &'a Camera, w: usize, h: usize) -> ViewRays<'a> {
        let k = &camera.intrinsics;
        ViewRays {
            camera,
            org: camera.pose.center().as_vec3().to_array(),
            rt: camera.pose.rotation.transpose(),
            xs: (0..w).map(|i| (i as f64 + 0.5 - k.cx) / k.fx).collect(),
            ys: (0..h).map(|j| (j as f64 + 0.5 - k.cy) / k.fy).collect(),
        }
    }

    /// Unit world direction and z-depth factor of pixel `(i, j)`, as [`pixel_ray`].
    #[inline]
    fn ray(&self, i: usize, j: usize) -> Option<([f32; 3], f64)> {
        let c = self
            .camera
            .try_normalized_ray(glam::DVec2::new(self.xs[i], self.ys[j]))?;
        Some(((self.rt * c).as_vec3().to_array(), c.z))
    }
}

/// One strip's share of the output arrays (rows `j0 .. j0 + rows`, row-major).
struct Strip<'a> {
    j0: usize,
    feature: &'a mut [i32],
    surface: &'a mut [i32],
    part: &'a mut [i32],
    city: &'a mut [i32],
    depth: &'a mut [f32],
    face: &'a mut [i32],
    recovered: &'a mut [bool],
}

/// Casts both passes for one view (see the module docs for the rules), with the scene's
/// native packet width ([`TwoPassScene::packet_width`]).
pub fn raycast_view(scene: &TwoPassScene, camera: &Camera, opts: &RaycastOptions) -> ViewIds {
    raycast_view_with(scene, camera, opts, scene.packet_width)
}

/// [`raycast_view`] with packets of the given width (4×2 tiles for 8 lanes, 4×4 for 16).
/// Every width gives the same result.
pub fn raycast_view_with(
    scene: &TwoPassScene,
    camera: &Camera,
    opts: &RaycastOptions,
    width: PacketWidth,
) -> ViewIds {
    match width {
        PacketWidth::W8 => trace_view::<Packet8>(scene, camera, opts),
        PacketWidth::W16 => trace_view::<Packet16>(scene, camera, opts),
    }
}

fn trace_view<P: RayPacket>(
    scene: &TwoPassScene,
    camera: &Camera,
    opts: &RaycastOptions,
) -> ViewIds {
    let (w, h) = (
        camera.intrinsics.width as usize,
        camera.intrinsics.height as usize,
    );
    let n = w * h;
    let mut out = ViewIds {
        width: w,
        height: h,
        feature: vec![-1; n],
        surface: vec![-1; n],
        part: vec![-1; n],
        city: vec![-1; n],
        depth: vec![f32::NAN; n],
        face: vec![-1; n],
        recovered: vec![false; n],
        undistort_failures: 0,
        lanes: P::LANES,
    };
    if n == 0 {
        return out;
    }
    let rays = ViewRays::new(camera, w, h);
    let rows = BLOCK * w;
    let failures: usize = out
        .feature
        .par_chunks_mut(rows)
        .zip(out.surface.par_chunks_mut(rows))
        .zip(out.part.par_chunks_mut(rows))
        .zip(out.city.par_chunks_mut(rows))
        .zip(out.depth.par_chunks_mut(rows))
        .zip(out.face.par_chunks_mut(rows))
        .zip(out.recovered.par_chunks_mut(rows))
        .enumerate()
        .map(
            |(sy, ((((((feature, surface), part), city), depth), face), recovered))| {
                let mut strip = Strip {
                    j0: sy * BLOCK,
                    feature,
                    surface,
                    part,
                    city,
                    depth,
                    face,
                    recovered,
                };
                trace_strip::<P>(scene, &rays, opts, &mut strip)
            },
        )
        .sum();
    out.undistort_failures = failures;
    out
}

/// Traces one strip of [`BLOCK`] rows in blocks of `BLOCK`×`BLOCK` pixels (coherent ray
/// order: the packets of a block share most of their BVH path); returns the pixels whose
/// ray could not be undistorted.
fn trace_strip<P: RayPacket>(
    scene: &TwoPassScene,
    rays: &ViewRays<'_>,
    opts: &RaycastOptions,
    strip: &mut Strip<'_>,
) -> usize {
    let w = rays.xs.len();
    let sh = strip.feature.len() / w;
    let th = P::LANES / 4;
    let mut failures = 0;
    for bx in (0..w).step_by(BLOCK) {
        for ty in (0..sh).step_by(th) {
            for tx in (bx..(bx + BLOCK).min(w)).step_by(4) {
                failures += trace_tile::<P>(scene, rays, opts, strip, tx, ty);
            }
        }
    }
    failures
}

/// Traces the 4-pixel-wide tile whose top-left pixel is `(tx, ty)` of the strip.
#[allow(clippy::needless_range_loop)] // packet lanes index several parallel arrays
fn trace_tile<P: RayPacket>(
    scene: &TwoPassScene,
    rays: &ViewRays<'_>,
    opts: &RaycastOptions,
    s: &mut Strip<'_>,
    tx: usize,
    ty: usize,
) -> usize {
    let w = rays.xs.len();
    let sh = s.feature.len() / w;
    let mut failures = 0;
    let mut packet = P::empty();
    let mut pixel = [0usize; 16];
    let mut zf = [0f64; 16];
    let mut dir = [[0f32; 3]; 16];
    for k in 0..P::LANES {
        let (i, jl) = (tx + k % 4, ty + k / 4);
        if i >= w || jl >= sh {
            continue;
        }
        match rays.ray(i, s.j0 + jl) {
            Some((d, z)) => {
                packet.set(k, rays.org, d, f32::INFINITY);
                (pixel[k], zf[k], dir[k]) = (jl * w + i, z, d);
            }
            None => failures += 1,
        }
    }
    packet.intersect(&scene.global);
    let mut part_packet = P::empty();
    let mut globals = [None; 16];
    for k in 0..P::LANES {
        let Some(hit) = packet.hit(k) else { continue };
        let face = hit.prim_id as usize;
        let Some(label) = scene.labels.get(face).copied() else {
            continue;
        };
        let p = pixel[k];
        let depth = f64::from(hit.t) * zf[k];
        s.feature[p] = label.feature;
        s.surface[p] = label.surface;
        s.part[p] = label.part;
        s.depth[p] = depth as f32;
        s.face[p] = face as i32;
        s.city[p] = city_id(label.part, label.surface, label.feature);
        // Only part hits with D̃ ≤ D_t + τ can be accepted; a missing surface can never
        // match. A part face hit directly keeps its part (the part pass could only find
        // that face again); a surface without openings has nothing to recover.
        if opts.single_pass || label.part != -1 || !scene.has_parts(label.surface) {
            continue;
        }
        let tmax = (depth + opts.tau) / zf[k];
        // Widen by a relative ulp margin so f32 rounding of tfar never drops a hit exactly
        // at the limit; the exact test is done below in f64. Every part face is also in
        // the global scene (same vertices), so none lies in front of the global hit: the
        // segment starts just before it (a relative 1e-5, far above f32 rounding of `t`,
        // for coplanar windows), which spares the traversal of everything in front.
        let tmin = (f64::from(hit.t) * (1.0 - 1e-5)) as f32;
        part_packet.set_segment(
            k,
            rays.org,
            dir[k],
            tmin,
            (tmax * (1.0 + 1e-6) + 1e-6) as f32,
        );
        globals[k] = Some((label, depth));
    }
    if !part_packet.any_active() {
        return failures;
    }
    part_packet.intersect(&scene.part);
    for k in 0..P::LANES {
        let (Some((label, depth)), Some(ph)) = (globals[k], part_packet.hit(k)) else {
            continue;
        };
        let Some(&face) = scene.part_faces.get(ph.prim_id as usize) else {
            continue;
        };
        let pl = scene.labels[face as usize];
        let pdepth = f64::from(ph.t) * zf[k];
        if pl.surface == label.surface && pdepth - depth <= opts.tau {
            let p = pixel[k];
            s.part[p] = pl.part;
            s.recovered[p] = label.part == -1;
            s.city[p] = city_id(pl.part, label.surface, label.feature);
        }
    }
    failures
}

/// `M_city`: the part id if ≠ −1, else the surface id if ≠ −1, else the feature id.
fn city_id(part: i32, surface: i32, feature: i32) -> i32 {
    if part != -1 {
        part
    } else if surface != -1 {
        surface
    } else {
        feature
    }
}
