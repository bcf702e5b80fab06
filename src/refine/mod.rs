//! The `align --refine` stage: recovers a misaligned city model's alignment from the
//! pre-trained 3DGS scene. Robust 7-DoF (similarity) point-to-plane ICP of selected Gaussian
//! centres (opaque, flat, voxel-subsampled) to the city-model mesh: closest points through
//! Embree's `rtcPointQuery`, restricted to triangles whose normal matches the Gaussian's;
//! Tukey-biweight IRLS with a MAD scale and a shrinking search radius; f64 normal equations
//! solved in their well-conditioned eigen-subspace; refusal when the final fit leaves a
//! direction undetermined (eigenvalue ratio), does not converge or drifts implausibly far.
//!
//! Frames: the mesh stays where the initial alignment `A₀` put it; the Gaussians are moved by
//! the estimate `M` (scene → mesh frame). The refined alignment is `M⁻¹ ∘ A₀`.
//! Lengths in options and outputs are metres (scene units ÷ the initial alignment's scale).
mod solve;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DVec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::alignment::{Alignment, Similarity};
use crate::embree::{CommittedScene, Device, EmbreeError, Scene};
use crate::mesh::TriMesh;
use crate::semantics::{Class, Entity};
use crate::splat::{Gaussians, InvalidPolicy, PlyReport, ReadOptions};
use solve::{Normal7, Solution};

/// Errors (and refusals) of the refinement.
#[derive(Debug, thiserror::Error)]
pub enum RefineError {
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error("city model: {0}")]
    Mesh(String),
    #[error(transparent)]
    Embree(#[from] EmbreeError),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Fs(#[from] crate::fsutil::FsError),
    #[error(
        "only {selected} of {total} Gaussians are opaque (≥ {min_opacity}), flat and inside the cameras' range; need ≥ {needed}"
    )]
    TooFewGaussians {
        total: usize,
        selected: usize,
        min_opacity: f64,
        needed: usize,
    },
    #[error(
        "only {matched} selected Gaussians lie within {radius_m:.3} m of a city-model surface of matching orientation (iteration {iteration}); need ≥ {needed}: is the initial alignment that far off?"
    )]
    TooFewMatches {
        iteration: usize,
        matched: usize,
        radius_m: f64,
        needed: usize,
    },
    #[error(
        "ambiguous fit, refusing: the Gaussians near the model do not determine {weakest} (normal-equation eigenvalue ratio {ratio:.2e} < {min_ratio:.0e}; surfaces of too few orientations, e.g. a single façade)"
    )]
    Degenerate {
        ratio: f64,
        min_ratio: f64,
        weakest: String,
    },
    #[error(
        "did not converge in {iterations} iterations (last step moved points by up to {last_motion_m:.2e} m, tolerance {tolerance_m:.0e} m)"
    )]
    NotConverged {
        iterations: usize,
        last_motion_m: f64,
        tolerance_m: f64,
    },
    #[error(
        "refusing: the Gaussians do not settle on the model (robust residual σ {sigma_m:.3} m after refinement > {max_sigma_m} m): a wrong local minimum, or the scene and the model disagree"
    )]
    NoFit { sigma_m: f64, max_sigma_m: f64 },
    #[error(
        "refusing: the fit drifted implausibly far from the initial alignment ({what}); the initial alignment is outside the basin of convergence"
    )]
    Drift { what: String },
}

/// Knobs of the refinement. Lengths in metres (× the initial alignment's scale in the scene).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RefineOptions {
    /// Gaussians used: activated opacity at least this.
    pub min_opacity: f64,
    /// Gaussians used: smallest scale ≤ this × the middle scale (flat discs have a normal).
    pub max_flatness: f64,
    /// Voxel size of the spatial subsampling (one Gaussian per voxel).
    pub voxel_m: f64,
    /// At most this many Gaussians after the voxel subsampling (seeded random subset).
    pub max_points: usize,
    /// Refuse with fewer selected Gaussians than this.
    pub min_points: usize,
    /// With cameras (`--colmap`): only Gaussians within this distance of some camera centre.
    pub max_camera_distance_m: f64,
    /// First search radius for closest points: bounds the initial error that can be recovered.
    pub initial_radius_m: f64,
    /// The search radius never shrinks below this.
    pub final_radius_m: f64,
    /// Correspondences only between a Gaussian and a triangle whose normals differ by less.
    pub max_normal_angle_deg: f64,
    /// Tukey biweight cutoff in robust standard deviations (1.4826 × MAD).
    pub tukey_k: f64,
    /// The Tukey cutoff never goes below this (the expected surface noise).
    pub min_cutoff_m: f64,
    /// Converged when an iteration moves every selected point by less than this…
    pub tolerance_m: f64,
    /// …or after this many iterations (then: an error).
    pub max_iterations: usize,
    /// Refuse when the smallest / largest eigenvalue of the final normal equations is below.
    pub min_eigen_ratio: f64,
    /// Refuse when, at the refined alignment and the initial search radius, the robust
    /// residual σ (1.4826 × MAD) of all matches exceeds this.
    pub max_sigma_m: f64,
    /// Refuse when the correction rotates by more than this…
    pub max_rotation_deg: f64,
    /// …or changes the scale by more than this fraction.
    pub max_scale_change: f64,
    /// Estimate the scale (7 DoF); `false`: rigid (6 DoF).
    pub estimate_scale: bool,
    /// Seed of the subsampling.
    pub seed: u64,
}

impl Default for RefineOptions {
    fn default() -> Self {
        RefineOptions {
            min_opacity: 0.5,
            max_flatness: 0.3,
            voxel_m: 0.25,
            max_points: 200_000,
            min_points: 200,
            max_camera_distance_m: 150.0,
            initial_radius_m: crate::alignment::REFINE_REACH_M,
            final_radius_m: 0.1,
            max_normal_angle_deg: 30.0,
            tukey_k: 4.685,
            min_cutoff_m: 0.03,
            tolerance_m: 1e-4,
            max_iterations: 100,
            min_eigen_ratio: 1e-3,
            max_sigma_m: 0.2,
            max_rotation_deg: 15.0,
            max_scale_change: 0.15,
            estimate_scale: true,
            seed: 0,
        }
    }
}

impl RefineOptions {
    /// Checks ranges (every length positive and finite, angles in range).
    pub fn validate(&self) -> Result<(), RefineError> {
        let pos = [
            ("voxel_m", self.voxel_m),
            ("max_camera_distance_m", self.max_camera_distance_m),
            ("initial_radius_m", self.initial_radius_m),
            ("tukey_k", self.tukey_k),
            ("min_cutoff_m", self.min_cutoff_m),
            ("tolerance_m", self.tolerance_m),
            ("max_sigma_m", self.max_sigma_m),
            ("max_rotation_deg", self.max_rotation_deg),
            ("max_scale_change", self.max_scale_change),
        ];
        use crate::check::{End, at_least, positive, range, unit};
        for (k, v) in pos {
            positive(k, v)?;
        }
        unit("min_opacity", self.min_opacity)?;
        range(
            "max_flatness",
            self.max_flatness,
            End::Open(0.0),
            End::Closed(1.0),
        )?;
        range(
            "max_normal_angle_deg",
            self.max_normal_angle_deg,
            End::Open(0.0),
            End::Closed(90.0),
        )?;
        range(
            "final_radius_m",
            self.final_radius_m,
            End::Open(0.0),
            End::Closed(self.initial_radius_m),
        )?;
        range(
            "min_points",
            self.min_points,
            End::Closed(7.0),
            End::Closed(self.max_points as f64),
        )?;
        at_least("max_iterations", self.max_iterations, 1)?;
        range(
            "min_eigen_ratio",
            self.min_eigen_ratio,
            End::Open(0.0),
            End::Open(1.0),
        )?;
        Ok(())
    }
}

/// What the refinement works on. The mesh is in the scene frame of `initial` (as the
/// `citymodel` stage writes it for that alignment); `entities` are its `semantics.json` rows.
#[derive(Clone, Copy)]
pub struct RefineInput<'a> {
    pub mesh: &'a TriMesh,
    pub entities: &'a [Entity],
    pub initial: &'a Alignment,
    pub gaussians: &'a Gaussians,
    /// Camera centres in the scene frame (from COLMAP), to drop far background Gaussians.
    pub camera_centres: Option<&'a [DVec3]>,
}

/// Distances of the selected Gaussian centres to the city-model surface (metres; only
/// triangles of matching orientation count, within the initial search radius).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ResidualStats {
    /// Selected Gaussians.
    pub points: usize,
    /// Those with a matching surface within `initial_radius_m`.
    pub matched: usize,
    pub median_m: f64,
    pub mean_m: f64,
    pub rms_m: f64,
    pub p90_m: f64,
    /// Fraction of the matched within 2 cm, 5 cm and 10 cm.
    pub within_2cm: f64,
    pub within_5cm: f64,
    pub within_10cm: f64,
}

/// How one alignment moves the model relative to another (metres, degrees, percent).
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct Displacement {
    /// RMS / max / mean displacement of the mesh vertices.
    pub rms_m: f64,
    pub max_m: f64,
    pub mean_m: f64,
    /// Displacement of the vertex centroid.
    pub centroid_m: f64,
    /// Angle of the relative rotation.
    pub rotation_deg: f64,
    /// Relative scale change, percent.
    pub scale_pct: f64,
}

/// How the mesh vertices (in the frame of `frame`) move from alignment `from` to `to`;
/// lengths in metres of `from`'s scale. Used for the stage's own correction report and by
/// the tests against the truth.
pub fn compare(
    from: &Alignment,
    to: &Alignment,
    vertices: &[[f32; 3]],
    frame: &Alignment,
) -> Displacement {
    let n = vertices.len().max(1) as f64;
    let (mut sum2, mut sum, mut max) = (0.0f64, 0.0f64, 0.0f64);
    let (mut ca, mut cb) = (DVec3::ZERO, DVec3::ZERO);
    for v in vertices {
        let geo = frame.unapply(DVec3::from_array(v.map(f64::from)));
        let (a, b) = (from.apply(geo), to.apply(geo));
        let d = (b - a).length();
        sum2 += d * d;
        sum += d;
        max = max.max(d);
        ca += a;
        cb += b;
    }
    let rel = from.relative(to);
    Displacement {
        rms_m: (sum2 / n).sqrt() / from.scale,
        max_m: max / from.scale,
        mean_m: sum / n / from.scale,
        centroid_m: ((cb - ca) / n).length() / from.scale,
        rotation_deg: rel.rotation_deg(),
        scale_pct: (rel.scale - 1.0) * 100.0,
    }
}

/// Counts of the Gaussian selection.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SelectionStats {
    pub gaussians: usize,
    pub opaque: usize,
    pub opaque_flat: usize,
    pub in_camera_range: usize,
    /// After the voxel subsampling and the `max_points` cap.
    pub sampled: usize,
    /// Mesh triangles used as targets (ground and closure surfaces are not: never seen).
    pub target_triangles: usize,
    pub excluded_triangles: usize,
}

/// The conditioning of the final normal equations (normalised: O(1) columns).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Conditioning {
    /// Eigenvalues, ascending.
    pub eigenvalues: Vec<f64>,
    /// Smallest / largest.
    pub ratio: f64,
    /// The least determined direction, in words.
    pub weakest: String,
}

/// One ICP iteration.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Iteration {
    pub radius_m: f64,
    pub matched: usize,
    /// Robust σ (1.4826 × median |point-to-plane residual|).
    pub sigma_m: f64,
    pub cutoff_m: f64,
    /// Matches with weight > 0.
    pub inliers: usize,
    /// Largest displacement of a selected point by this iteration's step.
    pub motion_m: f64,
    /// Directions left out of the step as undetermined.
    pub dropped_directions: usize,
}

/// Wall-clock seconds per phase.
#[derive(Debug, Clone, Serialize, Deserialize, Default)]
pub struct Timings {
    /// Building the city model (set by the caller of [`run`]).
    #[serde(default)]
    pub load_citymodel_s: f64,
    /// Reading the PLY ([`run`]).
    #[serde(default)]
    pub read_ply_s: f64,
    pub select_s: f64,
    pub bvh_s: f64,
    pub icp_s: f64,
    pub stats_s: f64,
    pub total_s: f64,
}

fn ser_alignment<S: serde::Serializer>(a: &Alignment, s: S) -> Result<S::Ok, S::Error> {
    a.to_json().serialize(s)
}

fn de_alignment<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Alignment, D::Error> {
    let v = serde_json::Value::deserialize(d)?;
    Alignment::from_json_str(std::path::Path::new("summary.json"), &v.to_string())
        .map_err(serde::de::Error::custom)
}

/// The result (also the stage's `summary.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RefineOutput {
    /// `"align_refine"`: marks a summary.json written by this stage.
    pub stage: String,
    /// The refined alignment (alignment.json format).
    #[serde(serialize_with = "ser_alignment", deserialize_with = "de_alignment")]
    pub alignment: Alignment,
    #[serde(serialize_with = "ser_alignment", deserialize_with = "de_alignment")]
    pub initial: Alignment,
    /// How the refinement moved the model (initial → refined).
    pub correction: Displacement,
    /// Residuals at the initial and at the refined alignment.
    pub before: ResidualStats,
    pub after: ResidualStats,
    /// After: the residuals per surface orientation.
    pub orientation: Vec<OrientationStats>,
    pub iterations: usize,
    pub converged: bool,
    pub selection: SelectionStats,
    pub conditioning: Conditioning,
    pub history: Vec<Iteration>,
    pub timings: Timings,
    pub options: RefineOptions,
    pub warnings: Vec<String>,
}

/// The Gaussians the fit uses: centres and unit normals (scene frame).
struct Selection {
    points: Vec<DVec3>,
    normals: Vec<DVec3>,
    stats: SelectionStats,
}

/// A well-mixed hash of an index and the seed (SplitMix64 at state `i + seed·γ`).
fn mix(i: u64, seed: u64) -> u64 {
    use crate::hash::{GAMMA, splitmix64};
    splitmix64(i.wrapping_add(seed.wrapping_mul(GAMMA)))
}

/// Opaque, flat Gaussians (normal = the axis of the smallest scale), in camera range, one per
/// voxel (the one with the smallest seeded hash: independent of order and thread count),
/// capped at `max_points` by the same hash.
fn select(input: &RefineInput, opts: &RefineOptions, unit: f64) -> Selection {
    let g = input.gaussians;
    let n = g.len();
    // Per Gaussian: 0 = not opaque, 1 = opaque not flat, 2 = flat but out of range, 3 = kept.
    let far2 = (opts.max_camera_distance_m * unit).powi(2);
    let judged: Vec<(u8, DVec3)> = (0..n)
        .into_par_iter()
        .map(|i| {
            let p = DVec3::from_array(g.positions[i].map(f64::from));
            if !p.is_finite() || f64::from(g.activated_opacity(i)) < opts.min_opacity {
                return (0, DVec3::ZERO);
            }
            let s = g.activated_scale(i).map(f64::from);
            let Some(q) = g.normalized_rotation(i) else {
                return (1, DVec3::ZERO);
            };
            let mut order = [0usize, 1, 2];
            order.sort_by(|&a, &b| s[a].total_cmp(&s[b]));
            let (smin, smid) = (s[order[0]], s[order[1]]);
            if !smin.is_finite() || !smid.is_finite() || smin > opts.max_flatness * smid {
                return (1, DVec3::ZERO);
            }
            let rot = DMat3::from_quat(
                glam::DQuat::from_xyzw(q[1] as f64, q[2] as f64, q[3] as f64, q[0] as f64)
                    .normalize(),
            );
            let normal = rot.col(order[0]);
            if let Some(cams) = input.camera_centres {
                if !cams.iter().any(|c| (*c - p).length_squared() <= far2) {
                    return (2, normal);
                }
            }
            (3, normal)
        })
        .collect();
    let opaque = judged.iter().filter(|j| j.0 >= 1).count();
    let opaque_flat = judged.iter().filter(|j| j.0 >= 2).count();
    let in_range = judged.iter().filter(|j| j.0 >= 3).count();
    let voxel = opts.voxel_m * unit;
    let mut best: HashMap<[i64; 3], (u64, u32)> = HashMap::new();
    for (i, j) in judged.iter().enumerate() {
        if j.0 != 3 {
            continue;
        }
        let p = g.positions[i];
        let key = p.map(|c| (f64::from(c) / voxel).floor() as i64);
        let h = mix(i as u64, opts.seed);
        let e = best.entry(key).or_insert((h, i as u32));
        if (h, i as u32) < *e {
            *e = (h, i as u32);
        }
    }
    let mut kept: Vec<(u64, u32)> = best.into_values().collect();
    if kept.len() > opts.max_points {
        kept.sort_unstable();
        kept.truncate(opts.max_points);
    }
    let mut idx: Vec<u32> = kept.into_iter().map(|k| k.1).collect();
    idx.sort_unstable();
    let points = idx
        .iter()
        .map(|&i| DVec3::from_array(g.positions[i as usize].map(f64::from)))
        .collect();
    let normals = idx.iter().map(|&i| judged[i as usize].1).collect();
    Selection {
        points,
        normals,
        stats: SelectionStats {
            gaussians: n,
            opaque,
            opaque_flat,
            in_camera_range: in_range,
            sampled: idx.len(),
            target_triangles: 0,
            excluded_triangles: 0,
        },
    }
}

/// The target surfaces: an Embree scene of the visible triangles with their unit normals.
struct Target {
    scene: CommittedScene,
    normals: Vec<DVec3>,
}

/// Surfaces never seen from outside a building: no Gaussian lies on them.
const HIDDEN_SURFACES: [Class; 2] = [Class::GroundSurface, Class::ClosureSurface];

fn build_target(mesh: &TriMesh, entities: &[Entity]) -> Result<(Target, usize), RefineError> {
    mesh.validate().map_err(RefineError::Mesh)?;
    let mut faces = Vec::with_capacity(mesh.faces.len());
    let mut normals = Vec::with_capacity(mesh.faces.len());
    let mut excluded = 0usize;
    for (i, f) in mesh.faces.iter().enumerate() {
        if let Some(l) = mesh.labels.get(i) {
            if l.surface >= 0 {
                let e = entities.get(l.surface as usize).ok_or_else(|| {
                    RefineError::Mesh(format!(
                        "face {i}: surface id {} has no entity ({} entities)",
                        l.surface,
                        entities.len()
                    ))
                })?;
                if HIDDEN_SURFACES.contains(&e.class) {
                    excluded += 1;
                    continue;
                }
            }
        }
        let v = |k: usize| DVec3::from_array(mesh.vertices[f[k] as usize].map(f64::from));
        let nrm = (v(1) - v(0)).cross(v(2) - v(0));
        let len = nrm.length();
        if len == 0.0 || !len.is_finite() {
            excluded += 1; // degenerate: no orientation
            continue;
        }
        faces.push(*f);
        normals.push(nrm / len);
    }
    if faces.is_empty() {
        return Err(RefineError::Mesh(
            "no visible, non-degenerate triangle to align to".into(),
        ));
    }
    let device = Device::new()?;
    let mut scene = Scene::new(&device)?;
    scene.add_triangles(&mesh.vertices, &faces)?;
    Ok((
        Target {
            scene: scene.commit()?,
            normals,
        },
        excluded,
    ))
}

/// A correspondence: the moved Gaussian centre, the triangle's normal, the residuals.
#[derive(Clone, Copy)]
struct Match {
    x: DVec3,
    n: DVec3,
    /// Orientation bin of `n` (see [`bin_of`]).
    bin: u8,
    /// Signed point-to-plane residual `n·(x − q)`.
    r: f64,
    /// Point-to-surface distance.
    d: f64,
}

/// Closest matching-orientation surface point for every selected Gaussian moved by `m`.
fn correspond(
    sel: &Selection,
    target: &Target,
    m: &Similarity,
    radius: f64,
    cos_max: f64,
) -> Vec<Option<Match>> {
    sel.points
        .par_iter()
        .zip(&sel.normals)
        .with_min_len(256)
        .map(|(p, gn)| {
            let x = m.apply(*p);
            let gn = m.rotation * *gn;
            let hit =
                target
                    .scene
                    .closest_point_filtered(x.to_array(), radius, &mut |_, prim| {
                        target.normals[prim as usize].dot(gn).abs() >= cos_max
                    })?;
            let n = target.normals[hit.prim_id as usize];
            let q = DVec3::from_array(hit.point);
            Some(Match {
                x,
                n,
                bin: bin_of(n),
                r: n.dot(x - q),
                d: hit.distance,
            })
        })
        .collect()
}

/// A level of the cutoff schedule is done when a step moves points by less than this
/// fraction of its cutoff, or after this many iterations.
const LEVEL_STEP: f64 = 0.05;
const LEVEL_ITERATIONS: usize = 8;

/// Orientation bins: the 13 unsigned symmetry axes of a cube (3 axes, 6 face diagonals,
/// 4 body diagonals), so that walls of every azimuth, roofs and slopes fall in separate bins.
const BINS: usize = 13;
const BIN_DIRS: [[f64; 3]; BINS] = [
    [1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [1.0, 1.0, 0.0],
    [1.0, -1.0, 0.0],
    [1.0, 0.0, 1.0],
    [1.0, 0.0, -1.0],
    [0.0, 1.0, 1.0],
    [0.0, 1.0, -1.0],
    [1.0, 1.0, 1.0],
    [1.0, 1.0, -1.0],
    [1.0, -1.0, 1.0],
    [-1.0, 1.0, 1.0],
];
/// A bin's own robust scale is used from this many matches on (else the global one).
const MIN_BIN: usize = 50;

/// The orientation bin of a unit normal (sign-free).
fn bin_of(n: DVec3) -> u8 {
    let mut best = (0usize, -1.0f64);
    for (k, d) in BIN_DIRS.iter().enumerate() {
        let c = n.dot(DVec3::from_array(*d).normalize()).abs();
        if c > best.1 {
            best = (k, c);
        }
    }
    best.0 as u8
}

/// Robust scales (1.4826 × median |r|): global, and per orientation bin (a bin with fewer
/// than [`MIN_BIN`] matches gets the global one), with the bins' match counts.
fn robust_scales(matched: &[Match]) -> (f64, [f64; BINS], [usize; BINS]) {
    let mut per: Vec<Vec<f64>> = vec![Vec::new(); BINS];
    for m in matched {
        per[m.bin as usize].push(m.r.abs());
    }
    let mut all: Vec<f64> = matched.iter().map(|m| m.r.abs()).collect();
    let global = 1.4826 * quantile(&mut all, 0.5);
    let mut sigma = [global; BINS];
    let mut count = [0usize; BINS];
    for (k, v) in per.iter_mut().enumerate() {
        count[k] = v.len();
        if v.len() >= MIN_BIN {
            sigma[k] = 1.4826 * quantile(v, 0.5);
        }
    }
    (global, sigma, count)
}

/// Residuals per orientation bin at the refined alignment.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct OrientationStats {
    /// The bin's (unsigned) normal direction, in the scene frame of the initial alignment.
    pub normal: [f64; 3],
    pub matched: usize,
    /// Robust σ of the point-to-plane residuals, metres.
    pub sigma_m: f64,
}

/// The `q`-quantile (0..1) of `v` (nearest rank; `v` is reordered).
fn quantile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let k = ((v.len() - 1) as f64 * q).round() as usize;
    *v.select_nth_unstable_by(k, |a, b| a.total_cmp(b)).1
}

fn residual_stats(matches: &[Option<Match>], unit: f64) -> ResidualStats {
    let mut d: Vec<f64> = matches.iter().flatten().map(|m| m.d / unit).collect();
    let n = d.len();
    let nf = n.max(1) as f64;
    let frac = |t: f64, d: &[f64]| d.iter().filter(|x| **x <= t).count() as f64 / nf;
    let mean = d.iter().sum::<f64>() / nf;
    let rms = (d.iter().map(|x| x * x).sum::<f64>() / nf).sqrt();
    let (w2, w5, w10) = (frac(0.02, &d), frac(0.05, &d), frac(0.10, &d));
    let median = quantile(&mut d, 0.5);
    let p90 = quantile(&mut d, 0.9);
    ResidualStats {
        points: matches.len(),
        matched: n,
        median_m: median,
        mean_m: mean,
        rms_m: rms,
        p90_m: p90,
        within_2cm: w2,
        within_5cm: w5,
        within_10cm: w10,
    }
}

/// Where the city model and the Gaussians of a refinement came from (its summary's `inputs`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RefineSources {
    /// The CityGML folder or `citymodel` stage folder.
    pub citymodel: PathBuf,
    /// `"CityGML"` (built in memory) or `"mesh.ply"` (a citymodel stage output).
    pub city_source: String,
    pub initial_alignment: Option<PathBuf>,
    pub ply: PathBuf,
    /// What reading the PLY dropped (invalid Gaussians are dropped and counted, never fatal:
    /// the refinement uses a subset of opaque flat Gaussians anyway).
    pub ply_report: Option<PlyReport>,
    pub colmap: Option<PathBuf>,
    /// Camera centres used to drop far background Gaussians.
    pub cameras: Option<usize>,
}

/// The stage's `summary.json`: the refinement and its inputs.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RefineSummary {
    #[serde(flatten)]
    pub refine: RefineOutput,
    pub inputs: RefineSources,
}

impl crate::layout::Summary for RefineSummary {}

/// The city model a refinement starts from: the mesh in the scene frame of `initial` and its
/// semantic table (built by the `citymodel` stage; the caller brings it).
pub struct CityFrame<'a> {
    pub mesh: &'a TriMesh,
    pub entities: &'a [Entity],
    pub initial: &'a Alignment,
    /// Seconds the caller spent building it (recorded in the timings).
    pub load_s: f64,
}

/// The stage, as `gs4city align --refine` and `gs4city run --refine-alignment` both run it:
/// reads the PLY (invalid Gaussians dropped and counted), refines, writes the refined alignment
/// to `alignment_out` and then `summary.json` into `dir` (last, the completion marker).
pub fn run(
    city: &CityFrame<'_>,
    mut sources: RefineSources,
    camera_centres: Option<&[DVec3]>,
    opts: &RefineOptions,
    alignment_out: &Path,
    dir: &Path,
) -> Result<RefineSummary, RefineError> {
    opts.validate()?;
    let t = Instant::now();
    let (gaussians, report) = crate::splat::read_ply(
        &sources.ply,
        &ReadOptions {
            invalid: InvalidPolicy::Drop,
            ..Default::default()
        },
    )?;
    let read_ply_s = t.elapsed().as_secs_f64();
    sources.ply_report = Some(report);
    sources.cameras = camera_centres.map(|c| c.len());
    let mut out = refine(
        &RefineInput {
            mesh: city.mesh,
            entities: city.entities,
            initial: city.initial,
            gaussians: &gaussians,
            camera_centres,
        },
        opts,
    )?;
    out.timings.read_ply_s = read_ply_s;
    out.timings.load_citymodel_s = city.load_s;
    crate::fsutil::create_dir(dir)?;
    crate::fsutil::write_json(alignment_out, &out.alignment.to_json())?;
    let summary = RefineSummary {
        refine: out,
        inputs: sources,
    };
    crate::layout::Summary::write(&summary, dir)?;
    Ok(summary)
}

/// Runs the refinement (see the module docs). Deterministic for given inputs and options,
/// whatever the thread count (correspondences are collected in order, sums are sequential).
pub fn refine(input: &RefineInput, opts: &RefineOptions) -> Result<RefineOutput, RefineError> {
    opts.validate()?;
    let t0 = Instant::now();
    let initial = *input.initial;
    let unit = initial.scale; // scene units per metre
    let mut warnings = Vec::new();

    // progress: selection, then one step per ICP iteration
    let mut sel = select(input, opts, unit);
    let t_select = t0.elapsed().as_secs_f64();
    if sel.points.len() < opts.min_points {
        return Err(RefineError::TooFewGaussians {
            total: sel.stats.gaussians,
            selected: sel.points.len(),
            min_opacity: opts.min_opacity,
            needed: opts.min_points,
        });
    }
    let t1 = Instant::now();
    let (target, excluded) = build_target(input.mesh, input.entities)?;
    sel.stats.target_triangles = target.normals.len();
    sel.stats.excluded_triangles = excluded;
    let t_bvh = t1.elapsed().as_secs_f64();

    let cos_max = opts.max_normal_angle_deg.to_radians().cos();
    let t2 = Instant::now();
    let mut m = Similarity::IDENTITY;
    let initial_radius = opts.initial_radius_m * unit;
    let final_radius = opts.final_radius_m * unit;
    let min_cutoff = opts.min_cutoff_m * unit;
    let tol = opts.tolerance_m * unit;
    let mut history = Vec::new();
    let mut converged = false;
    let mut first_matches = None;
    let mut last: Option<Normal7> = None;
    let mut last_motion = f64::INFINITY;
    // Graduated robustness: the Tukey cutoff starts at the search radius (every match
    // counts: the coarse pose) and halves whenever a level has converged, down to the
    // noise level (tukey_k × the robust σ, at least min_cutoff). A global, data-driven
    // cutoff from the start would let the majority that fits first (walls) turn the
    // minority that alone fixes a direction (roofs: the height) into outliers; a per-
    // orientation one would let junk-dominated orientations (ground Gaussians near low
    // roofs) pull. The search radius follows the level: 3 × cutoff.
    let mut level = initial_radius;
    let mut level_iterations = 0usize;
    for it in 0..opts.max_iterations {
        let radius = (3.0 * level).clamp(final_radius, initial_radius);
        let matches = correspond(&sel, &target, &m, radius, cos_max);
        if it == 0 {
            first_matches = Some(matches.clone());
        }
        let matched: Vec<Match> = matches.into_iter().flatten().collect();
        if matched.len() < opts.min_points {
            return Err(RefineError::TooFewMatches {
                iteration: it + 1,
                matched: matched.len(),
                radius_m: radius / unit,
                needed: opts.min_points,
            });
        }
        let mut abs: Vec<f64> = matched.iter().map(|m| m.r.abs()).collect();
        let sigma = 1.4826 * quantile(&mut abs, 0.5);
        let floor = (opts.tukey_k * sigma).max(min_cutoff);
        let last_level = level <= floor;
        let base = if last_level { floor } else { level };
        // Where the weights leave a direction undetermined, the cutoff doubles (up to the
        // search radius) for this iteration.
        let mut cutoff = base;
        let (system, solution, inliers) = loop {
            let weights: Vec<f64> = matched
                .iter()
                .map(|m| {
                    let u = m.r / cutoff;
                    if u.abs() < 1.0 {
                        (1.0 - u * u).powi(2)
                    } else {
                        0.0
                    }
                })
                .collect();
            let inliers = weights.iter().filter(|w| **w > 0.0).count();
            let can_widen = cutoff < radius;
            match Normal7::accumulate(&matched, &weights, opts.estimate_scale) {
                None if !can_widen => {
                    return Err(RefineError::TooFewMatches {
                        iteration: it + 1,
                        matched: inliers,
                        radius_m: radius / unit,
                        needed: opts.min_points,
                    });
                }
                Some(system) => {
                    let solution = system.solve(opts.min_eigen_ratio);
                    if solution.dropped == 0 || !can_widen {
                        break (system, solution, inliers);
                    }
                }
                None => {}
            }
            cutoff = (2.0 * cutoff).min(radius);
        };
        let Solution {
            step,
            motion,
            dropped,
        } = solution;
        m = m.then(&step);
        last_motion = motion;
        last = Some(system);
        history.push(Iteration {
            radius_m: radius / unit,
            matched: matched.len(),
            sigma_m: sigma / unit,
            cutoff_m: cutoff / unit,
            inliers,
            motion_m: motion / unit,
            dropped_directions: dropped,
        });
        level_iterations += 1;
        if last_level {
            if motion < tol && dropped == 0 {
                converged = true;
                break;
            }
        } else if motion < LEVEL_STEP * level || level_iterations >= LEVEL_ITERATIONS {
            level = (level / 2.0).max(floor);
            level_iterations = 0;
        }
    }
    let t_icp = t2.elapsed().as_secs_f64();
    let system = last.expect("max_iterations ≥ 1");
    let conditioning = system.conditioning();
    if conditioning.ratio < opts.min_eigen_ratio {
        return Err(RefineError::Degenerate {
            ratio: conditioning.ratio,
            min_ratio: opts.min_eigen_ratio,
            weakest: conditioning.weakest,
        });
    }
    if !converged {
        return Err(RefineError::NotConverged {
            iterations: history.len(),
            last_motion_m: last_motion / unit,
            tolerance_m: opts.tolerance_m,
        });
    }
    let alignment = initial.then(&m.inverse());
    let correction = compare(&initial, &alignment, &input.mesh.vertices, &initial);
    if correction.rotation_deg > opts.max_rotation_deg {
        return Err(RefineError::Drift {
            what: format!("rotation by {:.2}°", correction.rotation_deg),
        });
    }
    if correction.scale_pct.abs() > opts.max_scale_change * 100.0 {
        return Err(RefineError::Drift {
            what: format!("scale change {:+.2} %", correction.scale_pct),
        });
    }

    let t3 = Instant::now();
    let eval_radius = opts.initial_radius_m * unit;
    let before = residual_stats(&first_matches.expect("at least one iteration"), unit);
    let after_matches = correspond(&sel, &target, &m, eval_radius, cos_max);
    let after = residual_stats(&after_matches, unit);
    let after_matched: Vec<Match> = after_matches.into_iter().flatten().collect();
    let (sigma, sigmas, counts) = robust_scales(&after_matched);
    let orientation: Vec<OrientationStats> = (0..BINS)
        .filter(|&k| counts[k] > 0)
        .map(|k| OrientationStats {
            normal: DVec3::from_array(BIN_DIRS[k]).normalize().to_array(),
            matched: counts[k],
            sigma_m: if counts[k] >= MIN_BIN {
                sigmas[k] / unit
            } else {
                f64::NAN
            },
        })
        .collect();
    // At the initial search radius, the Gaussians must settle on the refined model: a
    // wrong local minimum leaves a large robust σ of all the matches. (Per orientation, σ
    // is reported but not judged: an orientation can be dominated by junk, e.g. ground
    // Gaussians near low flat roofs, whatever the alignment.)
    let worst = sigma;
    if worst > opts.max_sigma_m * unit {
        return Err(RefineError::NoFit {
            sigma_m: worst / unit,
            max_sigma_m: opts.max_sigma_m,
        });
    }
    let t_stats = t3.elapsed().as_secs_f64();
    if after.within_5cm < 0.3 {
        warnings.push(format!(
            "only {:.0} % of the matched Gaussians lie within 5 cm of the model after refinement",
            after.within_5cm * 100.0
        ));
    }
    Ok(RefineOutput {
        stage: "align_refine".into(),
        alignment,
        initial,
        correction,
        before,
        after,
        orientation,
        iterations: history.len(),
        converged,
        selection: sel.stats,
        conditioning,
        history,
        timings: Timings {
            select_s: t_select,
            bvh_s: t_bvh,
            icp_s: t_icp,
            stats_s: t_stats,
            total_s: t0.elapsed().as_secs_f64(),
            ..Default::default()
        },
        options: opts.clone(),
        warnings,
    })
}
