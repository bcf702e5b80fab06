//! Georeferenced CRS → scene frame: `p_scene = s · R · (p_geo − origin) + t` (`docs/design.md`),
//! evaluated in f64; `alignment.json` reading/writing; estimation of a similarity from ≥ 3
//! point pairs (Umeyama's least-squares similarity, rotation by Horn's quaternion method).
//!
//! An alignment is refused when its scale lies outside [`SCALE_RANGE`] or a value is not
//! finite. Estimation refuses collinear or coincident points (geo or scene side) and point
//! pairs that fit a mirror image much better than any rotation (a flipped axis), and warns,
//! in [`Estimate::warnings`], when the residuals are large against the spread of the points.
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};

use crate::numfmt::Num;

/// Errors of alignment reading and estimation.
#[derive(Debug, thiserror::Error)]
pub enum AlignError {
    #[error("cannot read {path}: {err}")]
    Read { path: PathBuf, err: std::io::Error },
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error("{path}:{line}: {why}")]
    Csv {
        path: PathBuf,
        line: usize,
        why: String,
    },
}

/// The accepted alignment scales (scene units per CRS unit).
pub const SCALE_RANGE: (f64, f64) = (1e-9, 1e9);

/// Estimation warns when the RMS residual exceeds this fraction of the RMS spread of the
/// scene points.
pub const RESIDUAL_WARN_FRACTION: f64 = 0.05;

/// A similarity transform with a georeferenced origin subtracted first.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Alignment {
    pub origin: DVec3,
    pub scale: f64,
    /// Rotation, applied after the origin is subtracted.
    pub rotation: DMat3,
    pub translation: DVec3,
}

#[derive(Serialize, Deserialize)]
struct AlignmentJson {
    origin: [f64; 3],
    scale: f64,
    rotation: serde_json::Value,
    translation: [f64; 3],
}

impl Alignment {
    /// Only a local origin: scene = geo − origin.
    pub fn local(origin: DVec3) -> Alignment {
        Alignment {
            origin,
            scale: 1.0,
            rotation: DMat3::IDENTITY,
            translation: DVec3::ZERO,
        }
    }

    /// Applies the transform in f64.
    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.scale * (self.rotation * (p - self.origin)) + self.translation
    }

    /// Rotation rows (row-major), as in `alignment.json`.
    pub fn rotation_rows(&self) -> [[f64; 3]; 3] {
        let t = self.rotation.transpose();
        [
            t.x_axis.to_array(),
            t.y_axis.to_array(),
            t.z_axis.to_array(),
        ]
    }

    /// The `alignment.json` value.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "origin": self.origin.to_array(),
            "scale": self.scale,
            "rotation": self.rotation_rows(),
            "translation": self.translation.to_array(),
        })
    }

    /// Parses and validates `alignment.json`: finite values, `scale > 0`, `R` a rotation
    /// (orthonormal within 1e-6, det +1). `rotation` may be 3 rows or 9 numbers, row-major.
    pub fn from_json_str(path: &Path, text: &str) -> Result<Alignment, AlignError> {
        let bad = |why: String| AlignError::Invalid {
            path: path.to_path_buf(),
            why,
        };
        let j: AlignmentJson = serde_json::from_str(text).map_err(|e| {
            bad(format!(
                "not an alignment (origin, scale, rotation, translation): {e}"
            ))
        })?;
        let flat: Vec<f64> = match &j.rotation {
            serde_json::Value::Array(rows)
                if rows.len() == 3 && rows.iter().all(|r| r.is_array()) =>
            {
                rows.iter()
                    .flat_map(|r| r.as_array().cloned().unwrap_or_default())
                    .map(|v| v.as_f64().unwrap_or(f64::NAN))
                    .collect()
            }
            serde_json::Value::Array(v) => {
                v.iter().map(|v| v.as_f64().unwrap_or(f64::NAN)).collect()
            }
            _ => Vec::new(),
        };
        if flat.len() != 9 {
            return Err(bad(
                "rotation must be 3×3 (3 rows of 3, or 9 numbers, row-major)".into(),
            ));
        }
        for (name, values) in [
            ("origin", &j.origin[..]),
            ("translation", &j.translation[..]),
            ("rotation", &flat[..]),
            ("scale", std::slice::from_ref(&j.scale)),
        ] {
            if values.iter().any(|v| !v.is_finite()) {
                return Err(bad(format!(
                    "\"{name}\" holds a value that is not a finite number"
                )));
            }
        }
        check_scale(j.scale).map_err(bad)?;
        let rotation = DMat3::from_cols_array(&[
            flat[0], flat[3], flat[6], flat[1], flat[4], flat[7], flat[2], flat[5], flat[8],
        ]);
        let err = (rotation.transpose() * rotation - DMat3::IDENTITY)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs()));
        if err > 1e-6 || rotation.determinant() < 0.0 {
            return Err(bad(format!(
                "rotation is not a proper rotation (|RᵀR − I| = {err:.2e}, det = {})",
                Num(rotation.determinant())
            )));
        }
        Ok(Alignment {
            origin: DVec3::from_array(j.origin),
            scale: j.scale,
            rotation,
            translation: DVec3::from_array(j.translation),
        })
    }

    /// Reads `alignment.json`.
    pub fn read(path: &Path) -> Result<Alignment, AlignError> {
        let text = std::fs::read_to_string(path).map_err(|err| AlignError::Read {
            path: path.to_path_buf(),
            err,
        })?;
        Alignment::from_json_str(path, &text)
    }
}

/// A similarity of the scene frame, `y ↦ s·R·y + t` (f64): a correction applied after an
/// [`Alignment`] (see [`Alignment::then`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    pub scale: f64,
    pub rotation: DMat3,
    pub translation: DVec3,
}

impl Similarity {
    pub const IDENTITY: Similarity = Similarity {
        scale: 1.0,
        rotation: DMat3::IDENTITY,
        translation: DVec3::ZERO,
    };

    /// `s·R·y + t`.
    pub fn apply(&self, y: DVec3) -> DVec3 {
        self.scale * (self.rotation * y) + self.translation
    }

    /// `next ∘ self` (first `self`, then `next`); the rotation is re-orthonormalised.
    pub fn then(&self, next: &Similarity) -> Similarity {
        Similarity {
            scale: next.scale * self.scale,
            rotation: orthonormalize(next.rotation * self.rotation),
            translation: next.apply(self.translation),
        }
    }

    /// The inverse similarity `y ↦ Rᵀ(y − t)/s`.
    pub fn inverse(&self) -> Similarity {
        let rt = self.rotation.transpose();
        Similarity {
            scale: 1.0 / self.scale,
            rotation: rt,
            translation: -(rt * self.translation) / self.scale,
        }
    }

    /// The rotation angle of `R`, degrees.
    pub fn rotation_deg(&self) -> f64 {
        rotation_angle_deg(&self.rotation)
    }
}

/// The angle of a rotation matrix, degrees (from its quaternion: accurate near 0 and 180°).
pub fn rotation_angle_deg(r: &DMat3) -> f64 {
    let q = glam::DQuat::from_mat3(r).normalize();
    (2.0 * q.xyz().length().atan2(q.w.abs())).to_degrees()
}

/// The nearest rotation to an almost-orthonormal matrix (through its quaternion).
fn orthonormalize(r: DMat3) -> DMat3 {
    DMat3::from_quat(glam::DQuat::from_mat3(&r).normalize())
}

impl Alignment {
    /// The alignment followed by a scene-frame similarity: `p ↦ S(A(p))`, same origin.
    pub fn then(&self, s: &Similarity) -> Alignment {
        Alignment {
            origin: self.origin,
            scale: s.scale * self.scale,
            rotation: orthonormalize(s.rotation * self.rotation),
            translation: s.apply(self.translation),
        }
    }

    /// The inverse transform, scene → georeferenced: `origin + Rᵀ(y − t)/s`.
    pub fn unapply(&self, y: DVec3) -> DVec3 {
        self.origin + self.rotation.transpose() * (y - self.translation) / self.scale
    }

    /// The scene-frame similarity `S` with `other = S ∘ self`, i.e. what moves a model
    /// aligned with `self` onto the same model aligned with `other`.
    pub fn relative(&self, other: &Alignment) -> Similarity {
        let k = other.scale / self.scale;
        let q = other.rotation * self.rotation.transpose();
        // other(p) = k·Q·(self(p) − t) + s'·R'·(o − o') + t'
        let shift = other.scale * (other.rotation * (self.origin - other.origin));
        Similarity {
            scale: k,
            rotation: q,
            translation: other.translation + shift - k * (q * self.translation),
        }
    }
}

/// `Ok` when `scale` lies in [`SCALE_RANGE`]; else the reason.
fn check_scale(scale: f64) -> Result<(), String> {
    let (lo, hi) = SCALE_RANGE;
    if !(lo..=hi).contains(&scale) {
        return Err(format!(
            "scale {} is outside {lo:e}..{hi:e} (scene units per CRS unit)",
            Num(scale)
        ));
    }
    Ok(())
}

/// An estimated alignment and its residuals (scene units) per point pair.
#[derive(Debug, Clone)]
pub struct Estimate {
    pub alignment: Alignment,
    pub residuals: Vec<f64>,
    pub rms: f64,
    pub max: f64,
    /// Sentences about a fit that is usable but suspicious (large residuals).
    pub warnings: Vec<String>,
}

/// Largest coordinate a point pair may hold: far beyond any coordinate reference system
/// (geocentric coordinates stay below 7·10⁶ m), and small enough that the fit's sums of
/// squares keep their precision.
pub const MAX_COORDINATE: f64 = 1e12;

/// Reads point pairs: 6 numbers per line `geo_x geo_y geo_z scene_x scene_y scene_z`
/// (comma- or whitespace-separated); `#` comments and a non-numeric header line are skipped.
pub fn read_pairs(path: &Path) -> Result<Vec<(DVec3, DVec3)>, AlignError> {
    let text = std::fs::read_to_string(path).map_err(|err| AlignError::Read {
        path: path.to_path_buf(),
        err,
    })?;
    parse_pairs(path, &text)
}

/// [`read_pairs`] on text (`path` names the source in errors).
pub fn parse_pairs(path: &Path, text: &str) -> Result<Vec<(DVec3, DVec3)>, AlignError> {
    const NAMES: [&str; 6] = ["geo_x", "geo_y", "geo_z", "scene_x", "scene_y", "scene_z"];
    let mut pairs = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let csv = |why: String| AlignError::Csv {
            path: path.to_path_buf(),
            line: i + 1,
            why,
        };
        let toks: Vec<&str> = line
            .split(|c: char| c == ',' || c == ';' || c.is_whitespace())
            .filter(|t| !t.is_empty())
            .collect();
        let vals: Result<Vec<f64>, _> = toks.iter().map(|t| t.parse::<f64>()).collect();
        let Ok(vals) = vals else {
            if pairs.is_empty() && i == 0 {
                continue; // header
            }
            let bad = toks
                .iter()
                .find(|t| t.parse::<f64>().is_err())
                .map(|t| t.chars().take(40).collect::<String>())
                .unwrap_or_default();
            return Err(csv(format!("\"{bad}\" is not a number")));
        };
        if vals.len() != 6 {
            return Err(csv(format!(
                "expected 6 numbers (geo_x geo_y geo_z scene_x scene_y scene_z), found {}",
                vals.len()
            )));
        }
        if let Some(k) = vals.iter().position(|v| !v.is_finite()) {
            return Err(csv(format!(
                "{} is {}, not a finite number",
                NAMES[k], vals[k]
            )));
        }
        if let Some(k) = vals.iter().position(|v| v.abs() > MAX_COORDINATE) {
            return Err(csv(format!(
                "{} is {:e}: beyond {MAX_COORDINATE:e}, which no coordinate reference system \
                 reaches (a unit or a column slip?)",
                NAMES[k], vals[k]
            )));
        }
        pairs.push((
            DVec3::new(vals[0], vals[1], vals[2]),
            DVec3::new(vals[3], vals[4], vals[5]),
        ));
    }
    Ok(pairs)
}

/// Eigenvalues (descending) of the scatter matrix of centred points.
fn spread(points: &[DVec3]) -> [f64; 3] {
    let cov = points.iter().fold(DMat3::ZERO, |m, p| m + outer(*p, *p));
    let mut ev = jacobi_eigen::<3>(mat3_to_arr(&cov)).0;
    ev.sort_by(|x, y| y.total_cmp(x));
    ev
}

/// The least-squares rotation (Horn) and scale mapping centred `a` onto centred `b`.
fn fit_rotation_scale(a: &[DVec3], b: &[DVec3]) -> (DMat3, f64) {
    // Horn: S = Σ a bᵀ, N (4×4) whose top eigenvector is the rotation quaternion.
    let s = a
        .iter()
        .zip(b)
        .fold(DMat3::ZERO, |m, (p, q)| m + outer(*p, *q));
    let s = mat3_to_arr(&s); // s[i][j] = Σ a_i b_j
    let (sxx, sxy, sxz, syx, syy, syz, szx, szy, szz) = (
        s[0][0], s[0][1], s[0][2], s[1][0], s[1][1], s[1][2], s[2][0], s[2][1], s[2][2],
    );
    let nmat = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (vals, vecs) = jacobi_eigen::<4>(nmat);
    let k = (0..4)
        .max_by(|&i, &j| vals[i].total_cmp(&vals[j]))
        .unwrap_or(0);
    let q = [vecs[0][k], vecs[1][k], vecs[2][k], vecs[3][k]];
    let rotation = DMat3::from_quat(glam::DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize());
    let var_a: f64 = a.iter().map(|p| p.length_squared()).sum();
    let scale = a
        .iter()
        .zip(b)
        .map(|(p, q)| q.dot(rotation * *p))
        .sum::<f64>()
        / var_a;
    (rotation, scale)
}

/// RMS of `|s·R·a − b|` over centred point sets.
fn rms_residual(a: &[DVec3], b: &[DVec3], rotation: DMat3, scale: f64) -> f64 {
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(p, q)| (scale * (rotation * *p) - *q).length_squared())
        .sum();
    (sum / a.len() as f64).sqrt()
}

/// Least-squares similarity (Umeyama 1991) mapping `geo` onto `scene`; the origin is the
/// centroid of the geo points, so all arithmetic runs on small centred f64 numbers. Refuses
/// degenerate and mirrored pairs and warns about large residuals (module docs).
pub fn estimate(path: &Path, pairs: &[(DVec3, DVec3)]) -> Result<Estimate, AlignError> {
    let bad = |why: String| AlignError::Invalid {
        path: path.to_path_buf(),
        why,
    };
    if pairs.len() < 3 {
        return Err(bad(format!(
            "need at least 3 point pairs, got {}",
            pairs.len()
        )));
    }
    let n = pairs.len() as f64;
    let mu_a = pairs.iter().map(|p| p.0).sum::<DVec3>() / n;
    let mu_b = pairs.iter().map(|p| p.1).sum::<DVec3>() / n;
    let a: Vec<DVec3> = pairs.iter().map(|p| p.0 - mu_a).collect();
    let b: Vec<DVec3> = pairs.iter().map(|p| p.1 - mu_b).collect();
    // Degeneracy: each side must span a plane (not a line or a point).
    for (side, pts) in [("geo", &a), ("scene", &b)] {
        let ev = spread(pts);
        if !ev[1].is_finite() || ev[1] <= 1e-10 * ev[0].max(1e-300) {
            return Err(bad(format!(
                "the {side} points are (nearly) collinear or coincident: the rotation is not determined"
            )));
        }
    }
    let (rotation, scale) = fit_rotation_scale(&a, &b);
    if !scale.is_finite() || scale <= 0.0 {
        return Err(bad(format!(
            "the estimated scale {} is not positive: the point pairs do not correspond",
            Num(scale)
        )));
    }
    check_scale(scale).map_err(|why| bad(format!("the estimated {why}")))?;
    let rms_proper = rms_residual(&a, &b, rotation, scale);
    // A flipped axis: the mirrored geo points (x → −x) fit far better than any rotation.
    // (For coplanar points a mirror is also a rotation, so both fits agree.)
    let flip = DVec3::new(-1.0, 1.0, 1.0);
    let a_m: Vec<DVec3> = a.iter().map(|p| *p * flip).collect();
    let (rot_m, scale_m) = fit_rotation_scale(&a_m, &b);
    let rms_mirror = if scale_m > 0.0 {
        rms_residual(&a_m, &b, rot_m, scale_m)
    } else {
        f64::INFINITY
    };
    let spread_b = (b.iter().map(|q| q.length_squared()).sum::<f64>() / n).sqrt();
    if rms_mirror < 0.5 * rms_proper && rms_proper > 1e-9 * spread_b {
        return Err(bad(format!(
            "the point pairs fit a mirror image far better than any rotation (RMS {rms_mirror:.4} against {rms_proper:.4} scene units): one axis is flipped between the geo and scene coordinates (a left-handed frame or swapped columns?)"
        )));
    }
    let alignment = Alignment {
        origin: mu_a,
        scale,
        rotation,
        translation: mu_b,
    };
    let residuals: Vec<f64> = pairs
        .iter()
        .map(|(g, sc)| (alignment.apply(*g) - *sc).length())
        .collect();
    let rms = (residuals.iter().map(|r| r * r).sum::<f64>() / n).sqrt();
    let max = residuals.iter().copied().fold(0.0, f64::max);
    let mut warnings = Vec::new();
    if rms > RESIDUAL_WARN_FRACTION * spread_b {
        let worst = residuals
            .iter()
            .enumerate()
            .max_by(|x, y| x.1.total_cmp(y.1))
            .map(|(i, _)| i + 1)
            .unwrap_or(1);
        warnings.push(format!(
            "the alignment fits poorly: the RMS residual {rms:.4} is {:.0} % of the spread of the scene points ({spread_b:.4}); the worst is pair {worst} ({max:.4}); check that each pair names the same point in both frames",
            100.0 * rms / spread_b
        ));
    }
    Ok(Estimate {
        alignment,
        residuals,
        rms,
        max,
        warnings,
    })
}

/// How [`estimate_robust`] fixes the vertical.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Vertical {
    /// The scene's up (unit, scene frame) is known: the geo frame's `+z` maps onto it; the
    /// fit is a horizontal similarity and one vertical offset (the median of the height
    /// residuals), so the geo heights never tilt it.
    Level(DVec3),
    /// The full 3D similarity, from every coordinate.
    Free,
}

/// A robust similarity ([`estimate_robust`]).
#[derive(Debug, Clone)]
pub struct RobustFit {
    pub alignment: Alignment,
    pub vertical: Vertical,
    /// Per pair, the scene point mapped back to the geo frame minus the geo point (CRS units).
    pub residuals: Vec<DVec3>,
    /// Whether each pair is an inlier (the refit uses the inliers only).
    pub inliers: Vec<bool>,
    /// The inlier bound on a residual (horizontal for [`Vertical::Level`], CRS units).
    pub threshold: f64,
    /// RMS of the inliers' residuals (horizontal, vertical, 3D; CRS units).
    pub rms: [f64; 3],
    pub warnings: Vec<String>,
}

/// LMedS' scale of the residuals: `1.4826 · (1 + 5/(n − p)) · √median(r²)` (Rousseeuw & Leroy).
fn lmeds_sigma(median_sq: f64, n: usize, p: usize) -> f64 {
    1.4826 * (1.0 + 5.0 / (n.saturating_sub(p).max(1)) as f64) * median_sq.sqrt()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The index sets LMedS tries: every `k`-subset of `0..n` when there are at most `cap`, else
/// `cap` subsets drawn by SplitMix64 (deterministic), without repeated indices.
fn subsets(n: usize, k: usize, cap: usize) -> Vec<Vec<usize>> {
    let mut all = Vec::new();
    let mut idx: Vec<usize> = (0..k).collect();
    let total = (0..k).fold(1f64, |c, i| c * (n - i) as f64 / (i + 1) as f64);
    if total <= cap as f64 {
        loop {
            all.push(idx.clone());
            let mut i = k;
            while i > 0 && idx[i - 1] == n - k + i - 1 {
                i -= 1;
            }
            if i == 0 {
                break;
            }
            idx[i - 1] += 1;
            for j in i..k {
                idx[j] = idx[j - 1] + 1;
            }
        }
        return all;
    }
    let mut x = 0x5eed_a11e_u64;
    while all.len() < cap {
        let mut s: Vec<usize> = Vec::with_capacity(k);
        while s.len() < k {
            x = crate::hash::splitmix64(x);
            let i = (x % n as u64) as usize;
            if !s.contains(&i) {
                s.push(i);
            }
        }
        all.push(s);
    }
    all
}

/// Subsets LMedS tries at most.
const LMEDS_SUBSETS: usize = 3000;
/// Inliers lie within this many LMedS sigmas.
const INLIER_SIGMAS: f64 = 2.5;
/// Fewer pairs than this: every pair counts (LMedS needs redundancy to tell an outlier).
const MIN_ROBUST_PAIRS: usize = 5;

/// A similarity from geo ↔ scene point pairs that a few gross outliers do not spoil: least
/// median of squares over minimal subsets (2 pairs for [`Vertical::Level`], 3 for
/// [`Vertical::Free`]; every subset up to 3000, else 3000 drawn), the inliers within 2.5 LMedS
/// sigmas of the best, a least-squares refit on them (Umeyama for the free model), inliers
/// again from the refit and a last refit. Residuals are in the geo frame. Fewer than 5 pairs:
/// a plain least-squares fit of all.
pub fn estimate_robust(
    path: &Path,
    pairs: &[(DVec3, DVec3)],
    vertical: Vertical,
) -> Result<RobustFit, AlignError> {
    let bad = |why: String| AlignError::Invalid {
        path: path.to_path_buf(),
        why,
    };
    let n = pairs.len();
    if n < 3 {
        return Err(bad(format!("need at least 3 point pairs, got {n}")));
    }
    let origin = pairs.iter().map(|p| p.0).sum::<DVec3>() / n as f64;
    let mut warnings = Vec::new();
    // a model from a subset, and the residuals (geo frame) of every pair under it
    let fit_on = |set: &[usize]| -> Option<Alignment> {
        match vertical {
            Vertical::Level(up) => level_fit(pairs, set, origin, up),
            Vertical::Free => {
                let sub: Vec<(DVec3, DVec3)> = set.iter().map(|&i| pairs[i]).collect();
                estimate(path, &sub).ok().map(|e| e.alignment)
            }
        }
    };
    let residual = |a: &Alignment, i: usize| -> DVec3 { a.unapply(pairs[i].1) - pairs[i].0 };
    let size = |r: DVec3| -> f64 {
        match vertical {
            Vertical::Level(_) => r.truncate().length(),
            Vertical::Free => r.length(),
        }
    };
    let (k, robust) = match vertical {
        Vertical::Level(_) => (2, n >= MIN_ROBUST_PAIRS),
        Vertical::Free => (3, n >= MIN_ROBUST_PAIRS),
    };
    let all: Vec<usize> = (0..n).collect();
    let mut inliers = vec![true; n];
    let mut threshold = f64::INFINITY;
    let mut best: Option<Alignment> = None;
    if robust {
        let mut best_med = f64::INFINITY;
        for set in subsets(n, k, LMEDS_SUBSETS) {
            let Some(a) = fit_on(&set) else { continue };
            let med = median((0..n).map(|i| size(residual(&a, i)).powi(2)).collect());
            if med < best_med {
                best_med = med;
                best = Some(a);
            }
        }
        let Some(a) = best else {
            return Err(bad(
                "no subset of the point pairs determines a similarity (coincident or collinear points)".into(),
            ));
        };
        let spread = (pairs
            .iter()
            .map(|p| (p.0 - origin).length_squared())
            .sum::<f64>()
            / n as f64)
            .sqrt();
        threshold = (INLIER_SIGMAS * lmeds_sigma(best_med, n, k)).max(1e-9 * spread.max(1e-300));
        let mut current = a;
        for _ in 0..2 {
            inliers = (0..n)
                .map(|i| size(residual(&current, i)) <= threshold)
                .collect();
            let set: Vec<usize> = all.iter().copied().filter(|&i| inliers[i]).collect();
            if set.len() < k + 1 {
                break;
            }
            match fit_on(&set) {
                Some(a) => current = a,
                None => break,
            }
        }
        best = Some(current);
        let out = inliers.iter().filter(|b| !**b).count();
        if out * 2 > n {
            warnings.push(format!(
                "{out} of {n} pairs are outliers: the fit rests on a minority, check the inputs"
            ));
        }
    } else {
        warnings.push(format!(
            "only {n} pairs: every pair is used (outliers can be told apart from {MIN_ROBUST_PAIRS} on)"
        ));
    }
    let alignment = match best {
        Some(a) => a,
        None => fit_on(&all).ok_or_else(|| {
            bad(
                "the point pairs do not determine a similarity (coincident or collinear points)"
                    .into(),
            )
        })?,
    };
    check_scale(alignment.scale).map_err(|why| bad(format!("the estimated {why}")))?;
    let residuals: Vec<DVec3> = (0..n).map(|i| residual(&alignment, i)).collect();
    let m = inliers.iter().filter(|b| **b).count().max(1) as f64;
    let rms_of = |f: &dyn Fn(DVec3) -> f64| {
        (residuals
            .iter()
            .zip(&inliers)
            .filter(|(_, b)| **b)
            .map(|(r, _)| f(*r).powi(2))
            .sum::<f64>()
            / m)
            .sqrt()
    };
    let rms = [
        rms_of(&|r| r.truncate().length()),
        rms_of(&|r| r.z),
        rms_of(&|r| r.length()),
    ];
    Ok(RobustFit {
        alignment,
        vertical,
        residuals,
        inliers,
        threshold,
        rms,
        warnings,
    })
}

/// The level model on the pairs `set` (module [`Vertical::Level`]): `L` turns the geo `+z`
/// onto the scene's `up`; in `L`'s frame the scene points are `s·Rz(θ)·(g − o) + t`, the
/// horizontal part a 2D least-squares similarity (complex numbers: `w = a·z + b`), the
/// vertical offset the median of `q_z − s·(g − o)_z`. `None` when the geo points of `set`
/// coincide horizontally.
fn level_fit(
    pairs: &[(DVec3, DVec3)],
    set: &[usize],
    origin: DVec3,
    up: DVec3,
) -> Option<Alignment> {
    let l = DMat3::from_quat(glam::DQuat::from_rotation_arc(DVec3::Z, up.normalize()));
    let lt = l.transpose();
    let g: Vec<DVec3> = set.iter().map(|&i| pairs[i].0 - origin).collect();
    let q: Vec<DVec3> = set.iter().map(|&i| lt * pairs[i].1).collect();
    let m = set.len() as f64;
    let (gz, qz) = (
        g.iter().map(|p| p.truncate()).sum::<glam::DVec2>() / m,
        q.iter().map(|p| p.truncate()).sum::<glam::DVec2>() / m,
    );
    // a = Σ conj(z)·w / Σ |z|² over the centred points
    let (mut re, mut im, mut den) = (0.0, 0.0, 0.0);
    for (p, r) in g.iter().zip(&q) {
        let (z, w) = (p.truncate() - gz, r.truncate() - qz);
        re += z.x * w.x + z.y * w.y;
        im += z.x * w.y - z.y * w.x;
        den += z.length_squared();
    }
    if den.is_nan() || den <= 0.0 {
        return None;
    }
    let (ar, ai) = (re / den, im / den);
    let scale = (ar * ar + ai * ai).sqrt();
    if !scale.is_finite() || scale <= 0.0 {
        return None;
    }
    let (c, s) = (ar / scale, ai / scale);
    let rz = DMat3::from_cols(DVec3::new(c, s, 0.0), DVec3::new(-s, c, 0.0), DVec3::Z);
    let b = qz - glam::DVec2::new(ar * gz.x - ai * gz.y, ar * gz.y + ai * gz.x);
    let tz = median(g.iter().zip(&q).map(|(p, r)| r.z - scale * p.z).collect());
    Some(Alignment {
        origin,
        scale,
        rotation: l * rz,
        translation: l * DVec3::new(b.x, b.y, tz),
    })
}

/// Eigenvalues (descending) and unit eigenvectors of a symmetric 3×3 matrix.
pub fn symmetric_eigen3(m: &DMat3) -> ([f64; 3], [DVec3; 3]) {
    let (vals, vecs) = jacobi_eigen::<3>(mat3_to_arr(m));
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| vals[b].total_cmp(&vals[a]));
    let col = |k: usize| DVec3::new(vecs[0][k], vecs[1][k], vecs[2][k]).normalize();
    (order.map(|k| vals[k]), order.map(col))
}

fn outer(p: DVec3, q: DVec3) -> DMat3 {
    // Column j is p * q_j, so entry (i, j) = p_i q_j.
    DMat3::from_cols(p * q.x, p * q.y, p * q.z)
}

fn mat3_to_arr(m: &DMat3) -> [[f64; 3]; 3] {
    let c = m.to_cols_array_2d();
    [
        [c[0][0], c[1][0], c[2][0]],
        [c[0][1], c[1][1], c[2][1]],
        [c[0][2], c[1][2], c[2][2]],
    ]
}

/// Eigen-decomposition of a symmetric matrix by cyclic Jacobi rotations: (values, vectors as columns).
pub(crate) fn jacobi_eigen<const N: usize>(mut a: [[f64; N]; N]) -> ([f64; N], [[f64; N]; N]) {
    let mut v = [[0.0; N]; N];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _sweep in 0..100 {
        let off: f64 = (0..N)
            .flat_map(|i| (0..N).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        if off < 1e-30 {
            break;
        }
        for p in 0..N {
            for q in p + 1..N {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for row in a.iter_mut() {
                    let (akp, akq) = (row[p], row[q]);
                    row[p] = c * akp - s * akq;
                    row[q] = s * akp + c * akq;
                }
                let (rp, rq) = (a[p], a[q]);
                for k in 0..N {
                    a[p][k] = c * rp[k] - s * rq[k];
                    a[q][k] = s * rp[k] + c * rq[k];
                }
                for row in v.iter_mut() {
                    let (vkp, vkq) = (row[p], row[q]);
                    row[p] = c * vkp - s * vkq;
                    row[q] = s * vkp + c * vkq;
                }
            }
        }
    }
    let mut vals = [0.0; N];
    for (i, val) in vals.iter_mut().enumerate() {
        *val = a[i][i];
    }
    (vals, v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Geo points from a known similarity plus noise and two gross outliers: the robust fit
    /// recovers the similarity and names the outliers, in both vertical models; plain
    /// least squares on the same points does not.
    #[test]
    fn robust_fits_recover_a_known_similarity_despite_two_gross_outliers() {
        let truth = Alignment {
            origin: DVec3::new(374_200.0, 6_176_500.0, 35.0),
            scale: 0.137,
            rotation: DMat3::from_euler(glam::EulerRot::XYZ, 1.9, -0.3, 2.4),
            translation: DVec3::new(0.4, -1.1, 3.2),
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(59);
        let mut gauss = |s: f64| -> f64 {
            // Box–Muller
            let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
            s * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let angle = |a: &DMat3, b: &DMat3| rotation_angle_deg(&(a.transpose() * *b));
        for level in [true, false] {
            // a street of 30 cameras (level) or a drone block (free)
            let truth_geo: Vec<DVec3> = (0..30)
                .map(|k| {
                    let t = k as f64 / 29.0;
                    if level {
                        truth.origin + DVec3::new(170.0 * t - 85.0, 25.0 * (3.0 * t).sin(), 0.5 * t)
                    } else {
                        truth.origin
                            + DVec3::new(
                                (k % 6) as f64 * 20.0 - 50.0,
                                (k / 6) as f64 * 20.0 - 40.0,
                                20.0 + (k % 4) as f64 * 10.0,
                            )
                    }
                })
                .collect();
            let mut pairs: Vec<(DVec3, DVec3)> = truth_geo
                .iter()
                .map(|g| {
                    // GPS: 2 m horizontal; altitude 4 m (phone) or 0.5 m (drone)
                    let zs = if level { 4.0 } else { 0.5 };
                    let noisy = *g + DVec3::new(gauss(2.0), gauss(2.0), gauss(zs));
                    (noisy, truth.apply(*g))
                })
                .collect();
            pairs[4].0 += DVec3::new(70.0, -40.0, 0.0);
            pairs[17].0 += DVec3::new(-55.0, 0.0, 30.0);
            let up = truth.rotation * DVec3::Z;
            let vertical = if level {
                Vertical::Level(up)
            } else {
                Vertical::Free
            };
            let fit = estimate_robust(Path::new("gps"), &pairs, vertical).unwrap();
            let a = fit.alignment;
            let what = if level { "level" } else { "free" };
            assert!(!fit.inliers[4] && !fit.inliers[17], "{what}: outliers kept");
            assert!(
                fit.inliers.iter().filter(|b| !**b).count() <= 4,
                "{what}: too many outliers {:?}",
                fit.inliers
            );
            assert!(
                (a.scale / truth.scale - 1.0).abs() < 0.02,
                "{what}: scale {}",
                a.scale
            );
            assert!(
                angle(&a.rotation, &truth.rotation) < 1.5,
                "{what}: rotation"
            );
            // the true camera positions map to their scene points within a few metres
            for (g, (_, sc)) in truth_geo.iter().zip(&pairs) {
                let err = (a.apply(*g) - *sc).length() / truth.scale;
                assert!(err < 3.5, "{what}: {err} m");
            }
            assert!(
                fit.rms[0] < 3.5 && fit.rms[0] > 1.0,
                "{what}: rms {:?}",
                fit.rms
            );
            if level {
                // the vertical is the cameras' up exactly, however noisy the altitudes
                assert!((a.rotation * DVec3::Z - up).length() < 1e-9);
            }
            // least squares over every pair is pulled away by the outliers
            let ls = estimate(Path::new("gps"), &pairs).unwrap().alignment;
            assert!(
                angle(&ls.rotation, &truth.rotation) > 2.0
                    || (ls.scale / truth.scale - 1.0).abs() > 0.05,
                "{what}: the outliers should spoil least squares"
            );
        }
    }

    #[test]
    fn lmeds_subsets_are_every_subset_or_a_deterministic_draw() {
        let s = subsets(5, 2, 100);
        assert_eq!(s.len(), 10);
        assert_eq!(s[0], vec![0, 1]);
        assert_eq!(s[9], vec![3, 4]);
        assert_eq!(subsets(6, 3, 100).len(), 20);
        let d = subsets(100, 3, 50);
        assert_eq!(d.len(), 50);
        assert_eq!(d, subsets(100, 3, 50));
        assert!(
            d.iter()
                .all(|v| v[0] != v[1] && v[1] != v[2] && v[0] != v[2])
        );
    }

    #[test]
    fn estimate_recovers_a_utm_similarity() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let truth = Alignment {
            origin: DVec3::new(678_100.0, 5_403_800.0, 400.0),
            scale: 0.37,
            rotation: DMat3::from_quat(glam::DQuat::from_euler(
                glam::EulerRot::ZYX,
                0.7,
                -0.2,
                0.1,
            )),
            translation: DVec3::new(3.0, -1.0, 0.5),
        };
        let pairs: Vec<(DVec3, DVec3)> = (0..12)
            .map(|_| {
                let g = truth.origin
                    + DVec3::new(
                        rng.random_range(-80.0..80.0),
                        rng.random_range(-80.0..80.0),
                        rng.random_range(0.0..30.0),
                    );
                (g, truth.apply(g))
            })
            .collect();
        let est = estimate(Path::new("pairs.csv"), &pairs).unwrap();
        assert!(est.max < 1e-9, "max residual {}", est.max);
        assert!((est.alignment.scale - 0.37).abs() < 1e-12);
        // With noise, residuals are reported and the fit stays close.
        let noisy: Vec<_> = pairs
            .iter()
            .map(|(g, s)| (*g, *s + DVec3::new(rng.random_range(-0.01..0.01), 0.0, 0.0)))
            .collect();
        let est = estimate(Path::new("pairs.csv"), &noisy).unwrap();
        assert!(est.rms > 0.0 && est.rms < 0.01);
    }

    #[test]
    fn composition_inverse_and_relative_agree_with_direct_evaluation() {
        let a = Alignment {
            origin: DVec3::new(678_039.0, 5_403_766.0, 412.0),
            scale: 0.8,
            rotation: DMat3::from_rotation_z(37f64.to_radians()),
            translation: DVec3::new(1.0, -2.0, 0.5),
        };
        let s = Similarity {
            scale: 1.01,
            rotation: DMat3::from_axis_angle(DVec3::new(1.0, 2.0, 3.0).normalize(), 0.02),
            translation: DVec3::new(0.3, -0.1, 0.2),
        };
        let b = a.then(&s);
        let geo = [
            DVec3::new(678_100.0, 5_403_800.0, 430.0),
            DVec3::new(678_000.0, 5_403_700.0, 400.0),
            DVec3::new(678_050.5, 5_403_766.25, 412.125),
        ];
        for g in geo {
            let direct = s.apply(a.apply(g));
            assert!((b.apply(g) - direct).length() < 1e-9);
            assert!((a.unapply(a.apply(g)) - g).length() < 1e-9);
            let y = a.apply(g);
            assert!((s.inverse().apply(s.apply(y)) - y).length() < 1e-12);
            assert!((s.then(&s.inverse()).apply(y) - y).length() < 1e-12);
        }
        // relative() recovers S, also across different origins.
        let r = a.relative(&b);
        assert!((r.scale - s.scale).abs() < 1e-15);
        assert!((r.translation - s.translation).length() < 1e-9);
        assert!((r.rotation - s.rotation).abs_diff_eq(DMat3::ZERO, 1e-12));
        let mut c = b;
        c.origin += DVec3::new(10.0, -5.0, 1.0);
        c.translation = b.apply(c.origin);
        for g in geo {
            assert!((c.apply(g) - b.apply(g)).length() < 1e-9);
            assert!((a.relative(&c).apply(a.apply(g)) - c.apply(g)).length() < 1e-9);
        }
        assert!((s.rotation_deg() - 0.02f64.to_degrees()).abs() < 1e-9);
        assert!(
            (rotation_angle_deg(&DMat3::from_rotation_z(3.0)) - 3f64.to_degrees()).abs() < 1e-9
        );
    }

    #[test]
    fn degenerate_and_bad_inputs_are_errors() {
        let line: Vec<(DVec3, DVec3)> = (0..5)
            .map(|i| (DVec3::X * i as f64, DVec3::Y * i as f64))
            .collect();
        assert!(
            estimate(Path::new("p.csv"), &line)
                .unwrap_err()
                .to_string()
                .contains("collinear")
        );
        assert!(estimate(Path::new("p.csv"), &line[..2]).is_err());
        let p = Path::new("alignment.json");
        let ok = r#"{"origin":[1,2,3],"scale":2,"rotation":[[0,-1,0],[1,0,0],[0,0,1]],"translation":[0,0,0]}"#;
        let a = Alignment::from_json_str(p, ok).unwrap();
        assert!((a.apply(DVec3::new(2.0, 2.0, 3.0)) - DVec3::new(0.0, 2.0, 0.0)).length() < 1e-12);
        let mirror = ok.replace("[0,0,1]]", "[0,0,-1]]");
        assert!(
            Alignment::from_json_str(p, &mirror)
                .unwrap_err()
                .to_string()
                .contains("alignment.json")
        );
        assert!(Alignment::from_json_str(p, &ok.replace("\"scale\":2", "\"scale\":0")).is_err());
        let flat =
            r#"{"origin":[0,0,0],"scale":1,"rotation":[1,0,0,0,1,0,0,0,1],"translation":[0,0,0]}"#;
        assert!(Alignment::from_json_str(p, flat).is_ok());
    }
}
