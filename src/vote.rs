//! The closed-form weighted vote (FlashSplat) that lifts per-view label maps into the Gaussians
//! through the contributions cache — the algorithm of the `lift` stage, also the initialisation
//! of identity learning (`train`). A library module: it imports formats only.
//!
//! For every Gaussian `i` and label `n` (a label id, or background −1 for pixels no label
//! covers) the vote accumulates `A[i][n] = Σ_views Σ_pixels α_i·T_i · [M(p) = n]` (in `f64`) over
//! the pixels whose cached list holds the Gaussian. The votes are L1-normalised per Gaussian, a
//! bias `γ` is added to the background entry, and the argmax is taken (ties: the smaller id).
//! Views are processed in name order and pixels in raster order, so the result does not depend
//! on the thread count.
use std::path::Path;
use std::time::Instant;

use rayon::prelude::*;

use serde::{Deserialize, Serialize};

use crate::cache::{Cache, CacheError, ViewContrib};
use crate::camera::View;
use crate::idmap::{IdMapError, LabelMaps};
use crate::labels::LabelTable;
use crate::progress::Bar;
use crate::semantics::Entity;

/// Errors of the vote.
#[derive(Debug, thiserror::Error)]
pub enum VoteError {
    #[error(transparent)]
    Cache(#[from] CacheError),
    #[error(transparent)]
    IdMap(#[from] IdMapError),
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error("{path}: {n} Gaussians, but the contributions cache was built from {cache}")]
    Gaussians {
        path: std::path::PathBuf,
        n: usize,
        cache: usize,
    },
    #[error(transparent)]
    MeshRead(#[from] crate::mesh::MeshError),
    #[error("{path}: {why}")]
    Mesh {
        path: std::path::PathBuf,
        why: String,
    },
    #[error(transparent)]
    Embree(#[from] crate::embree::EmbreeError),
}

/// [`Cache::check_size`] of view `v`'s loaded lists `c` against its camera.
pub fn check_view_size(cache: &Cache, v: &View, c: &ViewContrib) -> Result<(), CacheError> {
    let k = &v.camera.intrinsics;
    cache.check_size(
        &v.stem(),
        (c.width, c.height),
        (k.width as usize, k.height as usize),
    )
}

/// Everything a vote-based stage reads (`lift`, and `train`, which starts from the vote).
pub struct VoteInputs<'a> {
    /// The pre-trained 3DGS PLY the cache was built from.
    pub ply: &'a Path,
    pub cache: &'a Cache,
    pub train: &'a [View],
    pub test: &'a [View],
    pub maps: &'a LabelMaps,
    pub labels: &'a LabelTable,
    pub entities: &'a [Entity],
    /// The raycast folder (its z-depth maps) and the alignment scale (scene units per metre)
    /// for the depth gate of city votes ([`CityGate`]); `None` leaves city votes ungated.
    pub city_depth: Option<(&'a Path, f64)>,
    /// The city model's `mesh.ply` whose face ids are `entities` (the citymodel stage's, or the
    /// openings stage's completed one) and the alignment scale (scene units per metre), for the
    /// city-model prior ([`ModelPrior`]); `None` leaves the prior out.
    pub city_mesh: Option<(&'a Path, f64)>,
}

/// The background label (a pixel no label covers).
pub const BACKGROUND: i32 = -1;

/// Options of the vote (the lift stage's options).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct VoteOptions {
    /// Background bias γ ∈ [−1, 1], added to the normalised background vote; `None`: by the
    /// label source ([`gamma_for`]).
    pub gamma: Option<f32>,
    /// Depth gate of city votes, in metres ([`CityGate`]); 0 turns it off (and the centre
    /// gate with it).
    pub city_gate_m: f32,
    /// The centre gate of city votes ([`CityGate`]).
    pub centre_gate: bool,
    /// Weight of the city-model prior ([`ModelPrior`]) as a share of the median Gaussian's
    /// vote weight; 0 turns it off.
    pub model_prior: f32,
    /// Reach of the city-model prior in metres: a Gaussian whose centre lies further from
    /// every city-model triangle gets no prior vote.
    pub model_prior_m: f32,
}

/// The default background bias γ of the vote: −1, so the background's biased score (its share
/// − 1) never exceeds 0 and a Gaussian that any view labels keeps its strongest label; only a
/// Gaussian no view labels stays background. A pixel no label covers is no evidence against a
/// label (masks are missed far more often than they are wrong: person recall is bounded by the
/// masks SAM misses). Measured in BENCHMARKS.md's git history ("Loss budget", "γ sweep"): −1 beats −0.7 and
/// −0.5 on `street`, on three harder simulated perceptions and on the oracle one, with the leak
/// onto non-fine classes unchanged on `street` and the oracle and +0.1 / +0.5 points at the two
/// hardest levels.
pub const GAMMA: f32 = -1.0;

/// The default γ with the city model alone as supervision (`M_city`): there a pixel whose ray
/// misses the model or hits no building *is* evidence of background (raycasting is exhaustive,
/// unlike SAM), and γ −1 would label every Gaussian some ray reaches through the model (the
/// demo's city-only coarse precision fell from 99.4 to 90.7 % with it; BENCHMARKS.md's git history, "γ sweep").
pub const GAMMA_CITY: f32 = -0.5;

/// The γ a vote over `maps` uses: `gamma` when given, else [`GAMMA_CITY`] for `M_city` and
/// [`GAMMA`] for fused (mask) labels.
pub fn gamma_for(gamma: Option<f32>, maps: &LabelMaps) -> f32 {
    gamma.unwrap_or(match maps {
        LabelMaps::City(_) => GAMMA_CITY,
        LabelMaps::Fused(_) => GAMMA,
    })
}

/// The default depth gate of city votes (metres): a Gaussian more than this in front of the
/// city model's surface takes no vote from the city label of that surface.
pub const CITY_GATE_M: f32 = 0.5;

/// The default weight of the city-model prior, a share of the median Gaussian's vote weight
/// ([`ModelPrior`]; measured in BENCHMARKS.md's git history, "The city-model prior in 3D").
pub const MODEL_PRIOR: f32 = 0.3;

/// The default reach of the city-model prior, in metres.
pub const MODEL_PRIOR_M: f32 = 0.2;

impl Default for VoteOptions {
    fn default() -> Self {
        VoteOptions {
            gamma: None,
            city_gate_m: CITY_GATE_M,
            centre_gate: true,
            model_prior: MODEL_PRIOR,
            model_prior_m: MODEL_PRIOR_M,
        }
    }
}

impl VoteOptions {
    /// Checks γ and the gate.
    pub fn validate(&self) -> Result<(), VoteError> {
        use crate::check::{End, non_negative, range};
        if let Some(g) = self.gamma {
            range("gamma", g, End::Closed(-1.0), End::Closed(1.0))?;
        }
        non_negative("city_gate_m", self.city_gate_m)?;
        non_negative("model_prior", self.model_prior)?;
        non_negative("model_prior_m", self.model_prior_m)?;
        Ok(())
    }
}

/// The depth gate of city votes. A city label (`M_city`, or a fused label below `Δ`) names
/// the city-model surface a pixel's ray hits at z-depth `d`; it says nothing of what stands in
/// front of that surface. So a city-labelled pixel votes only for the Gaussians of its list whose
/// centre lies no more than `tol` in front of the surface (z ≥ `d − tol`); the weight of the
/// Gaussians further in front (a person, a car or a tree whose mask is missing in this view) is
/// left out of their vote instead of counting for the wall behind them. Gaussians behind the
/// surface keep the vote (recessed windows, reflections modelled behind the glass). Image
/// labels and background pixels are not gated.
///
/// With the **centre gate** (on by default, [`VoteOptions::centre_gate`]) a city-labelled pixel
/// also gives no vote to a Gaussian whose centre projects, in the same view, onto a city label
/// of *another class*: a wall Gaussian that straddles a door's outline takes no door votes from
/// the door pixels it spills onto (and a door Gaussian no wall votes), so each Gaussian follows
/// the city-model surface its centre lies on. A centre outside the image, behind the camera or
/// on a pixel that is not city-labelled (background, an image label) gates nothing.
pub struct CityGate {
    centres: Vec<[f32; 3]>,
    raycast: std::path::PathBuf,
    /// Tolerance in scene units.
    tol: f64,
    /// Labels in `0..city_below` are city labels.
    city_below: i32,
    /// The class of each label, when the centre gate is on.
    classes: Option<LabelTable>,
}

/// The gate of one view: Gaussian z-depths and the raycast z-depth per pixel.
pub struct GateView {
    z: Vec<f32>,
    /// Per Gaussian, the class of the city label its centre projects onto (`i32::MIN`: none);
    /// empty when the centre gate is off.
    centre: Vec<i32>,
    /// Per pixel, the class of its label (empty when the centre gate is off).
    pclass: Vec<i32>,
    depth: Vec<f32>,
    tol: f32,
    city_below: i32,
}

impl CityGate {
    /// The gate of a vote's inputs: `None` when `gate_m` is 0 or the inputs name no raycast
    /// (the centre gate, `centre`, is part of it).
    pub fn for_inputs(
        inp: &VoteInputs<'_>,
        gate_m: f32,
        centre: bool,
    ) -> Result<Option<CityGate>, VoteError> {
        let Some((raycast, scene_per_metre)) = inp.city_depth else {
            return Ok(None);
        };
        if gate_m <= 0.0 {
            return Ok(None);
        }
        // The pipeline's reading: every Gaussian in file order, invalid ones kept in place (their
        // centres may be non-finite; a NaN depth never compares below the gate, and they are
        // never drawn, so no pixel lists them).
        let positions = read_centres(inp)?;
        let city_below = match inp.maps {
            LabelMaps::City(_) => i32::MAX,
            LabelMaps::Fused(_) => inp.labels.delta,
        };
        let mut gate = CityGate::new(
            positions,
            raycast,
            f64::from(gate_m) * scene_per_metre,
            city_below,
        );
        if centre {
            gate.classes = Some(inp.labels.clone());
        }
        Ok(Some(gate))
    }

    /// The Gaussian centres the gate projects (scene frame, cache order).
    pub fn centres(&self) -> &[[f32; 3]] {
        &self.centres
    }

    /// A gate from Gaussian centres (scene frame, cache order), the raycast folder, the
    /// tolerance in scene units and the first non-city label id.
    pub fn new(centres: Vec<[f32; 3]>, raycast: &Path, tol: f64, city_below: i32) -> CityGate {
        CityGate {
            centres,
            raycast: raycast.to_path_buf(),
            tol,
            city_below,
            classes: None,
        }
    }

    /// The gate of view `v` with its cached lists `c` and per-pixel labels `labels` (the
    /// centre gate reads them). Only the Gaussians that `c` lists at a pixel the gate applies to
    /// (a city label over a finite surface depth: the pixels [`Votes::accumulate_gated`] gates)
    /// are projected; no other Gaussian's depth or centre is ever looked up.
    pub fn view(&self, v: &View, c: &ViewContrib, labels: &[i32]) -> Result<GateView, IdMapError> {
        let (width, height) = (c.width, c.height);
        let depth = crate::idmap::read_depth(&self.raycast, &v.stem(), width, height)?;
        let tol = self.tol as f32;
        let n = self.centres.len();
        // One bit per Gaussian (ids the cache reader checked; any beyond `n` are left out).
        let mut bits = vec![0u64; n.div_ceil(64)];
        for (p, &label) in labels.iter().enumerate() {
            let gated = label >= 0
                && label < self.city_below
                && depth.get(p).is_some_and(|&d| (d - tol).is_finite());
            if gated {
                for &g in c.pixel(p).0 {
                    if let Some(w) = bits.get_mut(g as usize / 64) {
                        *w |= 1u64 << (g % 64);
                    }
                }
            }
        }
        let mut listed = Vec::new();
        for (w, &b) in bits.iter().enumerate() {
            let mut b = b;
            while b != 0 {
                let g = (w * 64) as u32 + b.trailing_zeros();
                if (g as usize) < n {
                    listed.push(g);
                }
                b &= b - 1;
            }
        }
        let pose = v.camera.pose;
        let cam = |g: u32| {
            let c = &self.centres[g as usize];
            pose.world_to_camera(glam::DVec3::new(
                f64::from(c[0]),
                f64::from(c[1]),
                f64::from(c[2]),
            ))
        };
        // Entries of Gaussians the view does not list at a gated pixel are never read.
        let mut z = vec![f32::NAN; n];
        let (centre, pclass) = match &self.classes {
            None => {
                let zs: Vec<f32> = listed.par_iter().map(|&g| cam(g).z as f32).collect();
                for (&g, zg) in listed.iter().zip(zs) {
                    z[g as usize] = zg;
                }
                (Vec::new(), Vec::new())
            }
            Some(t) => {
                let city = |l: i32| (0..self.city_below).contains(&l);
                let zc: Vec<(f32, i32)> = listed
                    .par_iter()
                    .map(|&g| {
                        let q = cam(g);
                        // The class of the city label under the centre (i32::MIN: none).
                        let class = v
                            .camera
                            .pixel_containing(q, width, height)
                            .and_then(|px| labels.get(px).copied())
                            .filter(|&l| city(l))
                            .map_or(i32::MIN, |l| t.class_of(l));
                        (q.z as f32, class)
                    })
                    .collect();
                let mut centre = vec![i32::MIN; n];
                for (&g, (zg, cg)) in listed.iter().zip(zc) {
                    z[g as usize] = zg;
                    centre[g as usize] = cg;
                }
                (centre, labels.iter().map(|&l| t.class_of(l)).collect())
            }
        };
        Ok(GateView {
            z,
            centre,
            pclass,
            depth,
            tol,
            city_below: self.city_below,
        })
    }
}

/// The Gaussian centres of a vote's PLY in the pipeline's reading: every Gaussian in file order,
/// invalid ones kept in place with a NaN centre (no pixel lists them, the depth gate never
/// compares a NaN below the surface, and the city-model prior skips them); the count must be
/// the cache's.
fn read_centres(inp: &VoteInputs<'_>) -> Result<Vec<[f32; 3]>, VoteError> {
    let (g, report) = crate::splat::read_ply(inp.ply, &crate::splat::ReadOptions::KEEP)?;
    let cache = inp.cache.summary.gaussians;
    if g.len() != cache {
        return Err(VoteError::Gaussians {
            path: inp.ply.to_path_buf(),
            n: g.len(),
            cache,
        });
    }
    let invalid: Vec<usize> = if report.kept_invalid > 0 {
        (0..g.len())
            .filter(|&i| !crate::splat::ply::is_valid(&g, i))
            .collect()
    } else {
        Vec::new()
    };
    let mut centres = g.positions;
    for i in invalid {
        centres[i] = [f32::NAN; 3];
    }
    Ok(centres)
}

/// City-model surfaces no Gaussian lies on (seen from outside a building): they give no prior.
const HIDDEN_SURFACES: [crate::citygml::Class; 2] = [
    crate::citygml::Class::GroundSurface,
    crate::citygml::Class::ClosureSurface,
];

/// The **city-model prior in 3D**. The views' votes decide a Gaussian's label where the
/// training views see it well; a Gaussian they hardly see (a door only the distant orbit views
/// show, a few pixels each, or one the training views never reach) collects almost no weight,
/// and a stray vote decides it. The aligned city model says directly what such a Gaussian lies
/// on: each Gaussian whose centre lies within `model_prior_m` of a city-model triangle gets one
/// extra vote, for that triangle's finest label (part, else surface, else building), of weight
/// `model_prior` × the median Gaussian's vote weight. A Gaussian seen well outweighs it; one
/// seen barely follows the model. Ground and closure surfaces give no prior; a person or car
/// against a wall gets the wall's prior vote too, which its own views' votes outweigh where they
/// see it; the background bias γ applies as before.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelPrior {
    /// Per Gaussian (cache order): the label of the nearest triangle, or [`BACKGROUND`] where
    /// no triangle lies within reach (or the centre is not finite).
    pub label: Vec<i32>,
    /// The prior's weight as a share of the median vote weight.
    pub share: f32,
}

impl ModelPrior {
    /// The prior of a vote's inputs: `None` when `opts.model_prior` is 0 or the inputs name no
    /// city mesh. `centres` are the Gaussian centres when already read (the gate's).
    pub fn for_inputs(
        inp: &VoteInputs<'_>,
        opts: &VoteOptions,
        centres: Option<&[[f32; 3]]>,
    ) -> Result<Option<ModelPrior>, VoteError> {
        let Some((mesh_path, per_metre)) = inp.city_mesh else {
            return Ok(None);
        };
        if opts.model_prior <= 0.0 {
            return Ok(None);
        }
        let mesh = crate::mesh::TriMesh::read_ply(mesh_path)?;
        mesh.validate()
            .and_then(|()| mesh.check_label_range(inp.entities.len()))
            .map_err(|why| VoteError::Mesh {
                path: mesh_path.to_path_buf(),
                why,
            })?;
        let read;
        let centres = match centres {
            Some(c) => c,
            None => {
                read = read_centres(inp)?;
                &read
            }
        };
        let reach = f64::from(opts.model_prior_m) * per_metre;
        Ok(Some(ModelPrior {
            label: nearest_labels(
                &mesh,
                inp.entities,
                inp.labels,
                centres,
                reach,
                PART_TOL_M * per_metre,
            )?,
            share: opts.model_prior,
        }))
    }
}

/// How much further (metres) than the nearest triangle a window or door of the same surface
/// may lie and still win it: an opening drawn in its wall's plane over an uncut wall (as the
/// openings stage adds them, and as some LoD3 models draw theirs) lies exactly as near as the
/// wall, and the nearer-by-index tie would otherwise give the wall. The raycast's part pass
/// settles the same tie along its rays.
const PART_TOL_M: f64 = 0.02;

/// Per centre, the label of the nearest visible city-model triangle within `reach` (scene
/// units), or [`BACKGROUND`]: a window or door of that triangle's surface within `part_tol`
/// further wins over it (the part pass, [`PART_TOL_M`]); else the triangle's finest id that the
/// label table holds (part, else surface, else building).
fn nearest_labels(
    mesh: &crate::mesh::TriMesh,
    entities: &[Entity],
    labels: &LabelTable,
    centres: &[[f32; 3]],
    reach: f64,
    part_tol: f64,
) -> Result<Vec<i32>, VoteError> {
    let in_table = |x: i32| x >= 0 && labels.get(x).is_some();
    // Visible faces with their label and surface; the part faces among them, for the part pass.
    let (mut faces, mut face_info) = (Vec::new(), Vec::new());
    let (mut parts, mut part_info) = (Vec::new(), Vec::new());
    for (f, l) in mesh.faces.iter().zip(&mesh.labels) {
        let hidden = usize::try_from(l.surface)
            .ok()
            .and_then(|s| entities.get(s))
            .is_some_and(|e| HIDDEN_SURFACES.contains(&e.class));
        let Some(id) = [l.part, l.surface, l.feature]
            .into_iter()
            .find(|&x| in_table(x))
        else {
            continue;
        };
        if hidden {
            continue;
        }
        faces.push(*f);
        face_info.push((id, l.surface));
        if in_table(l.part) {
            parts.push(*f);
            part_info.push((l.part, l.surface));
        }
    }
    if faces.is_empty() || reach.is_nan() || reach <= 0.0 {
        return Ok(vec![BACKGROUND; centres.len()]);
    }
    let device = crate::embree::Device::new()?;
    let commit = |faces: &[[u32; 3]]| -> Result<crate::embree::CommittedScene, VoteError> {
        let mut scene = crate::embree::Scene::new(&device)?;
        scene.add_triangles(&mesh.vertices, faces)?;
        Ok(scene.commit()?)
    };
    let scene = commit(&faces)?;
    let part_scene = if parts.is_empty() {
        None
    } else {
        Some(commit(&parts)?)
    };
    let mut out = Vec::new();
    centres
        .par_iter()
        .with_min_len(1024)
        .map(|c| {
            let p = c.map(f64::from);
            let Some(h) = scene.closest_point(p, reach) else {
                return BACKGROUND;
            };
            let (id, surface) = face_info[h.prim_id as usize];
            if surface >= 0
                && let Some(ps) = &part_scene
                && let Some(hp) = ps.closest_point(p, h.distance + part_tol)
                && part_info[hp.prim_id as usize].1 == surface
            {
                return part_info[hp.prim_id as usize].0;
            }
            id
        })
        .collect_into_vec(&mut out);
    Ok(out)
}

/// Per-Gaussian label votes: a few inline slots, and per Gaussian an overflow list for the
/// rare rest (looked up by Gaussian, so reading all votes stays linear). Weights are `f64`:
/// a Gaussian can collect millions of small terms.
pub struct Votes {
    slots: Vec<[(i32, f64); SLOTS]>,
    /// Keyed by Gaussian; Fx hashing (the map's order is never read: [`Votes::of`] sorts).
    overflow: rustc_hash::FxHashMap<u32, Vec<(i32, f64)>>,
}

const SLOTS: usize = 4;
const EMPTY: i32 = i32::MIN;

impl Votes {
    /// Empty votes for `n` Gaussians.
    pub fn new(n: usize) -> Votes {
        Votes {
            slots: vec![[(EMPTY, 0.0); SLOTS]; n],
            overflow: rustc_hash::FxHashMap::default(),
        }
    }

    /// Adds weight `w` for `label` to Gaussian `g`.
    #[inline]
    pub fn add(&mut self, g: u32, label: i32, w: f64) {
        let s = &mut self.slots[g as usize];
        for slot in s.iter_mut() {
            if slot.0 == label {
                slot.1 += w;
                return;
            }
            if slot.0 == EMPTY {
                *slot = (label, w);
                return;
            }
        }
        let list = self.overflow.entry(g).or_default();
        match list.iter_mut().find(|e| e.0 == label) {
            Some(e) => e.1 += w,
            None => list.push((label, w)),
        }
    }

    /// All `(label, weight)` votes of Gaussian `g`, in a deterministic order.
    pub fn of(&self, g: u32) -> Vec<(i32, f64)> {
        let mut v: Vec<(i32, f64)> = self.slots[g as usize]
            .iter()
            .copied()
            .filter(|s| s.0 != EMPTY)
            .collect();
        if v.len() == SLOTS
            && let Some(extra) = self.overflow.get(&g)
        {
            let mut extra = extra.clone();
            extra.sort_by_key(|e| e.0);
            v.extend(extra);
        }
        v
    }

    /// Gaussian `g`'s total vote weight (every label, background included).
    pub fn total(&self, g: u32) -> f64 {
        let inline: f64 = self.slots[g as usize]
            .iter()
            .filter(|s| s.0 != EMPTY)
            .map(|s| s.1)
            .sum();
        inline
            + self
                .overflow
                .get(&g)
                .map_or(0.0, |v| v.iter().map(|e| e.1).sum())
    }

    /// Adds the city-model prior: one vote of `share` × the median positive total weight for
    /// each Gaussian's prior label. Returns that weight and the number of Gaussians given one
    /// (none when no Gaussian has any vote: the prior scales the views' evidence, it does not
    /// replace it).
    pub fn add_prior(&mut self, prior: &ModelPrior) -> (f64, usize) {
        let mut totals: Vec<f64> = (0..self.slots.len() as u32)
            .map(|g| self.total(g))
            .filter(|&t| t > 0.0)
            .collect();
        if totals.is_empty() {
            return (0.0, 0);
        }
        let mid = totals.len() / 2;
        let median = *totals.select_nth_unstable_by(mid, f64::total_cmp).1;
        let w = f64::from(prior.share) * median;
        if !(w > 0.0 && w.is_finite()) {
            return (0.0, 0);
        }
        let mut n = 0;
        for (g, &l) in prior.label.iter().enumerate().take(self.slots.len()) {
            if l != BACKGROUND {
                self.add(g as u32, l, w);
                n += 1;
            }
        }
        (w, n)
    }

    /// Votes kept in overflow lists.
    pub fn overflow_votes(&self) -> usize {
        self.overflow.values().map(Vec::len).sum()
    }

    /// Accumulates one view: `labels[p]` is pixel `p`'s label (or background).
    pub fn accumulate(&mut self, c: &ViewContrib, labels: &[i32]) {
        self.accumulate_gated(c, labels, None);
    }

    /// [`Votes::accumulate`] with the depth gate of city votes ([`CityGate`]); returns the
    /// weight the gate left out and the weight of the gated (city-labelled) pixels' lists.
    pub fn accumulate_gated(
        &mut self,
        c: &ViewContrib,
        labels: &[i32],
        gate: Option<&GateView>,
    ) -> (f64, f64) {
        let (mut gated, mut city) = (0.0f64, 0.0f64);
        for (p, &label) in labels.iter().enumerate() {
            let (ids, ws) = c.pixel(p);
            // The nearest z a Gaussian may have and still take this pixel's city label.
            let near = gate
                .filter(|g| label >= 0 && label < g.city_below)
                .map(|g| (g, g.depth[p] - g.tol))
                .filter(|(_, d)| d.is_finite());
            for (&g, &w) in ids.iter().zip(ws) {
                if let Some((gv, near)) = near {
                    city += f64::from(w);
                    if gv.z[g as usize] < near {
                        gated += f64::from(w);
                        continue;
                    }
                    if let Some(&cc) = gv.centre.get(g as usize)
                        && cc != i32::MIN
                        && cc != gv.pclass[p]
                    {
                        gated += f64::from(w);
                        continue;
                    }
                }
                self.add(g, label, f64::from(w));
            }
        }
        (gated, city)
    }
}

/// The label chosen for one Gaussian.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Assignment {
    /// Label id, or −1 (background, or no vote at all).
    pub label: i32,
    /// Normalised vote of the winning label (0 when there was no vote).
    pub confidence: f32,
    /// Total vote weight.
    pub weight: f64,
}

/// Chooses, per Gaussian, the label with the largest normalised vote (+γ on background).
/// Ties go to the smaller label id.
pub fn assign(votes: &Votes, n: usize, gamma: f32) -> Vec<Assignment> {
    let gamma = f64::from(gamma);
    (0..n as u32)
        .map(|g| {
            let v = votes.of(g);
            let total: f64 = v.iter().map(|x| x.1).sum();
            if total <= 0.0 {
                return Assignment {
                    label: BACKGROUND,
                    confidence: 0.0,
                    weight: 0.0,
                };
            }
            let mut best = (BACKGROUND, f64::NEG_INFINITY);
            let mut bg_seen = false;
            let mut consider = |label: i32, score: f64| {
                if score > best.1 || (score == best.1 && label < best.0) {
                    best = (label, score);
                }
            };
            for &(label, w) in &v {
                let mut s = w / total;
                if label == BACKGROUND {
                    s += gamma;
                    bg_seen = true;
                }
                consider(label, s);
            }
            if !bg_seen {
                consider(BACKGROUND, gamma);
            }
            let conf = v
                .iter()
                .find(|x| x.0 == best.0)
                .map_or(0.0, |x| x.1 / total);
            Assignment {
                label: best.0,
                confidence: conf as f32,
                weight: total,
            }
        })
        .collect()
}

/// Timings and counts of a vote.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct VoteStats {
    pub views: usize,
    pub load_s: f64,
    pub accumulate_s: f64,
    pub assign_s: f64,
    pub contributions: u64,
    pub overflow_votes: usize,
    /// Weight of city votes the depth gate left out, and the total weight of city-labelled
    /// pixels' contributions (both summed over views).
    #[serde(default)]
    pub city_gated_weight: f64,
    #[serde(default)]
    pub city_weight: f64,
    /// The background bias the assignment used ([`gamma_for`]).
    #[serde(default)]
    pub gamma: f32,
    /// The city-model prior ([`ModelPrior`]): the weight of one prior vote and the number of
    /// Gaussians within its reach (0 and 0 when it is off).
    #[serde(default)]
    pub model_prior_weight: f64,
    #[serde(default)]
    pub model_prior_gaussians: usize,
}

/// Runs the vote over `views` (their cached lists and label maps); one assignment per Gaussian.
pub fn vote(
    cache: &Cache,
    views: &[View],
    maps: &LabelMaps,
    gate: Option<&CityGate>,
    prior: Option<&ModelPrior>,
    opts: &VoteOptions,
) -> Result<(Vec<Assignment>, VoteStats), VoteError> {
    opts.validate()?;
    let n = cache.summary.gaussians;
    let mut votes = Votes::new(n);
    let mut stats = VoteStats {
        views: views.len(),
        ..Default::default()
    };
    let bar = Bar::new("lift", views.len() as u64, "views");
    // Two slots, reused: view i is accumulated from one while view i + 1 is loaded into the
    // other (the accumulation order stays fixed; the memory is allocated once).
    type Slot = (ViewContrib, Vec<u8>, Vec<i32>, Option<GateView>);
    let load = |v: &View, s: &mut Slot| -> Result<(), VoteError> {
        cache.load_into(&v.stem(), &mut s.0, &mut s.1)?;
        check_view_size(cache, v, &s.0)?;
        s.2 = maps.read(&v.stem(), s.0.width, s.0.height)?;
        s.3 = gate.map(|g| g.view(v, &s.0, &s.2)).transpose()?;
        Ok(())
    };
    let mut slots: [Slot; 2] =
        std::array::from_fn(|_| (ViewContrib::empty(), Vec::new(), Vec::new(), None));
    let t = Instant::now();
    if let Some(v) = views.first() {
        load(v, &mut slots[0])?;
    }
    stats.load_s += t.elapsed().as_secs_f64();
    for i in 0..views.len() {
        let [a, b] = &mut slots;
        let (cur, next) = if i % 2 == 0 { (a, b) } else { (b, a) };
        let (loaded, acc_s) = rayon::join(
            || views.get(i + 1).map(|v| load(v, next)).transpose(),
            || {
                let t = Instant::now();
                let w = votes.accumulate_gated(&cur.0, &cur.2, cur.3.as_ref());
                (t.elapsed().as_secs_f64(), w)
            },
        );
        let (acc_s, (gated, city)) = acc_s;
        stats.city_gated_weight += gated;
        stats.city_weight += city;
        stats.accumulate_s += acc_s;
        stats.contributions += cur.0.entries() as u64;
        loaded?;
        bar.inc(1);
    }
    bar.finish();
    let t = Instant::now();
    if let Some(p) = prior {
        (stats.model_prior_weight, stats.model_prior_gaussians) = votes.add_prior(p);
    }
    stats.gamma = gamma_for(opts.gamma, maps);
    let a = assign(&votes, n, stats.gamma);
    stats.assign_s = t.elapsed().as_secs_f64();
    stats.overflow_votes = votes.overflow_votes();
    Ok((a, stats))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache::Contributions;

    fn entity(id: i32, class: &str, level: crate::citygml::Level, parent: Option<i32>) -> Entity {
        Entity {
            id,
            object_id: format!("e{id}"),
            class: crate::citygml::Class::from_local_name(class).unwrap(),
            level,
            parent,
            building: 0,
            source: String::new(),
            lod: Some(3),
            attributes: Default::default(),
        }
    }

    /// Building 0; wall 1 (the x = 0 plane, y 0..4, z 0..4); door 2 of wall 1 (y 1..2, z 0..2);
    /// ground surface 3 (z = 0, x 0..4, y 0..4). `cut`: the wall leaves the door's rectangle out;
    /// else the door's faces lie over the uncut wall in its plane, as the openings stage draws
    /// them. The ground's faces come first (they are left out, so the scene's primitive ids are
    /// not the mesh's face indices).
    fn wall_with_a_door(cut: bool) -> (Vec<Entity>, crate::mesh::TriMesh) {
        use crate::citygml::Level;
        use crate::mesh::{FaceLabel, TriMesh};
        let entities = vec![
            entity(0, "Building", Level::Feature, None),
            entity(1, "WallSurface", Level::Surface, Some(0)),
            entity(2, "Door", Level::Part, Some(1)),
            entity(3, "GroundSurface", Level::Surface, Some(0)),
        ];
        let v = |x: f32, y: f32, z: f32| [x, y, z];
        let vertices = vec![
            // ground: 0..3
            v(0.0, 0.0, 0.0),
            v(4.0, 0.0, 0.0),
            v(4.0, 4.0, 0.0),
            v(0.0, 4.0, 0.0),
            // wall corners: 4..7
            v(0.0, 0.0, 0.0),
            v(0.0, 4.0, 0.0),
            v(0.0, 4.0, 4.0),
            v(0.0, 0.0, 4.0),
            // door corners: 8..11
            v(0.0, 1.0, 0.0),
            v(0.0, 2.0, 0.0),
            v(0.0, 2.0, 2.0),
            v(0.0, 1.0, 2.0),
        ];
        let label = |surface: i32, part: i32| FaceLabel {
            feature: 0,
            surface,
            part,
        };
        let mut faces = vec![[0, 1, 2], [0, 2, 3]];
        let mut labels = vec![label(3, -1), label(3, -1)];
        if cut {
            // The wall around the door's rectangle.
            faces.extend([
                [4, 8, 11],
                [4, 11, 7],
                [11, 10, 7],
                [10, 6, 7],
                [9, 5, 6],
                [9, 6, 10],
            ]);
            labels.extend([label(1, -1); 6]);
        } else {
            faces.extend([[4, 5, 6], [4, 6, 7]]);
            labels.extend([label(1, -1); 2]);
        }
        faces.extend([[8, 9, 10], [8, 10, 11]]);
        labels.extend([label(1, 2); 2]);
        let mesh = TriMesh {
            vertices,
            faces,
            labels,
        };
        mesh.validate().unwrap();
        (entities, mesh)
    }

    #[test]
    fn the_model_prior_takes_the_finest_label_of_the_nearest_visible_triangle_within_reach() {
        let centres = [
            // 0.1 in front of the door's middle: the door (part 2), not the wall around it.
            [0.1, 1.5, 1.0],
            // 0.15 behind the wall, high up: the wall (surface 1).
            [-0.15, 3.0, 3.5],
            // 0.1 above the ground, 3 m from the wall: the ground is hidden, nothing else in reach.
            [3.0, 2.0, 0.1],
            // 0.3 in front of the door: beyond a reach of 0.2.
            [0.3, 1.5, 1.0],
            // Not finite.
            [f32::NAN, 1.5, 1.0],
            // In the wall's plane 0.15 beside the door's edge: the wall, although the door is
            // within reach (it is 0.15 further than the wall, more than the part tolerance).
            [0.0, 2.15, 1.0],
        ];
        for cut in [true, false] {
            let (entities, mesh) = wall_with_a_door(cut);
            let labels = LabelTable::city(&entities, &crate::classes::table(&entities)).unwrap();
            let got = nearest_labels(&mesh, &entities, &labels, &centres, 0.2, 0.02).unwrap();
            assert_eq!(
                got,
                vec![2, 1, BACKGROUND, BACKGROUND, BACKGROUND, 1],
                "cut {cut}"
            );
            // A reach of 0.5 finds the door for the fourth centre too.
            let got = nearest_labels(&mesh, &entities, &labels, &centres, 0.5, 0.02).unwrap();
            assert_eq!(got[3], 2, "cut {cut}");
            // No reach: no prior.
            let got = nearest_labels(&mesh, &entities, &labels, &centres, 0.0, 0.02).unwrap();
            assert!(got.iter().all(|&l| l == BACKGROUND), "cut {cut}");
        }
        // A door that the label table lacks gives its faces' surface instead.
        let (entities, mesh) = wall_with_a_door(false);
        let all = LabelTable::city(&entities, &crate::classes::table(&entities)).unwrap();
        let without_door = LabelTable::new(
            all.delta,
            all.labels.iter().filter(|l| l.id != 2).cloned().collect(),
        )
        .unwrap();
        let got = nearest_labels(&mesh, &entities, &without_door, &centres, 0.2, 0.02).unwrap();
        assert_eq!(got, vec![1, 1, BACKGROUND, BACKGROUND, BACKGROUND, 1]);
    }

    #[test]
    fn the_model_prior_outweighs_weak_votes_and_not_strong_ones() {
        // Gaussian totals 1, 10 and 100 (median of the positive totals: 10); the fourth has no
        // vote. Each has wall (1) votes only, except Gaussian 1 (wall 6, background 4).
        let mut v = Votes::new(4);
        v.add(0, 1, 1.0);
        v.add(1, 1, 6.0);
        v.add(1, BACKGROUND, 4.0);
        v.add(2, 1, 100.0);
        assert_eq!(v.total(1), 10.0);
        // The prior says door (2) for Gaussians 0, 2 and 3, nothing for 1.
        let prior = ModelPrior {
            label: vec![2, BACKGROUND, 2, 2],
            share: 0.3,
        };
        let (w, n) = v.add_prior(&prior);
        // 0.3 as the f32 option is, times the median 10.
        assert_eq!((w, n), (f64::from(0.3f32) * 10.0, 3));
        let a = assign(&v, 4, GAMMA);
        // 0: door 3 against wall 1; 1: untouched; 2: wall 100 against door 3; 3: door alone.
        let got: Vec<i32> = a.iter().map(|x| x.label).collect();
        assert_eq!(got, vec![2, 1, 1, 2]);
        assert!((a[0].confidence - 0.75).abs() < 1e-6, "{:?}", a[0]);
        // Without any vote there is no median to scale by: no prior.
        let mut empty = Votes::new(2);
        let prior = ModelPrior {
            label: vec![2, 2],
            share: 0.3,
        };
        assert_eq!(empty.add_prior(&prior), (0.0, 0));
        assert!(
            assign(&empty, 2, GAMMA)
                .iter()
                .all(|x| x.label == BACKGROUND)
        );
    }

    #[test]
    fn the_depth_gate_drops_city_votes_of_gaussians_in_front_of_the_surface_only() {
        // Three pixels, each listing Gaussians 0 (z 2, far in front), 1 (z 4.8, on the surface
        // within the 0.5 tolerance) and 2 (z 7, behind it) with weights 0.5, 0.3, 0.2.
        let lists = Contributions {
            offsets: vec![0, 3, 6, 9],
            ids: vec![0, 1, 2, 0, 1, 2, 0, 1, 2],
            weights: vec![0.5, 0.3, 0.2, 0.5, 0.3, 0.2, 0.5, 0.3, 0.2],
            residual: vec![0.0; 3],
        };
        let c = ViewContrib {
            width: 3,
            height: 1,
            k: 0,
            gaussians: 3,
            lists,
            alpha: vec![1.0; 3],
            depth: vec![f32::NAN; 3],
            median: Vec::new(),
        };
        let gate = GateView {
            z: vec![2.0, 4.8, 7.0],
            centre: Vec::new(),
            pclass: Vec::new(),
            // Pixel 2: no city hit (NaN), so nothing to gate against.
            depth: vec![5.0, 5.0, f32::NAN],
            tol: 0.5,
            city_below: 10,
        };
        // Pixel 0: city label 3; pixel 1: image label 12 (not gated); pixel 2: city label 3.
        let labels = [3, 12, 3];
        let mut v = Votes::new(3);
        let (gated, city) = v.accumulate_gated(&c, &labels, Some(&gate));
        // Only Gaussian 0's weight in pixel 0 is dropped; city mass = pixel 0's list (pixel 2 has
        // no finite depth, so it is not a gated pixel).
        assert!(
            (gated - 0.5).abs() < 1e-9 && (city - 1.0).abs() < 1e-6,
            "{gated} {city}"
        );
        assert_eq!(v.of(0), vec![(12, 0.5), (3, 0.5)]);
        let one = v.of(1);
        assert_eq!(one.len(), 2);
        assert!((one[0].1 - 0.6).abs() < 1e-6 && one[0].0 == 3 && one[1].0 == 12);
        let two = v.of(2);
        assert!((two[0].1 - 0.4).abs() < 1e-6 && two[0].0 == 3);
        // Without the gate Gaussian 0 takes the city label from pixels 0 and 2.
        let mut u = Votes::new(3);
        u.accumulate(&c, &labels);
        assert!((u.of(0)[0].1 - 1.0).abs() < 1e-6 && u.of(0)[0].0 == 3);
        // The M_city maps: every label ≥ 0 is a city label.
        let all = GateView {
            city_below: i32::MAX,
            ..gate
        };
        let mut w = Votes::new(3);
        w.accumulate_gated(&c, &labels, Some(&all));
        assert_eq!(
            w.of(0),
            vec![(3, 0.5)],
            "pixel 1's label 12 is a city label now"
        );
    }

    /// The centre gate through [`CityGate::view`]: a 4 × 1 view (identity pose, fx = 1, cx = 0,
    /// cy = ½: a centre (x, 0, 1) lands in pixel ⌊x⌋) whose pixels 0–1 are wall (city label 0),
    /// pixel 2 a door (city label 1), pixel 3 a person (image label Δ). Gaussian 0's centre lies
    /// on the wall, 1's on the door, 2's on the person, 3's outside the image.
    #[test]
    fn the_centre_gate_keeps_a_gaussian_to_the_city_class_its_centre_lies_on() {
        use crate::camera::{Camera, Distortion, Intrinsics, Pose};
        use crate::labels::{Label, Source};
        let delta = 10;
        let city = |id: i32, class: i32| Label {
            id,
            source: Source::City,
            entity: Some(id),
            group: None,
            class,
            level: None,
        };
        let person = Label {
            id: delta,
            source: Source::Image,
            entity: None,
            group: Some(0),
            class: crate::classes::PERSON,
            level: None,
        };
        let table = LabelTable::new(
            delta,
            vec![
                city(0, crate::classes::WALL),
                city(1, crate::classes::DOOR),
                person,
            ],
        )
        .unwrap();
        let labels = [0, 0, 1, delta];
        let dir = crate::fsutil::test_temp_dir().join("vote_centre_gate");
        crate::fsutil::create_dir(&dir).unwrap();
        crate::idmap::write_depth(&dir, "v", 4, 1, &[1.0; 4]).unwrap();
        let view = View {
            image_id: 1,
            camera_id: 1,
            name: "v.png".into(),
            camera: Camera {
                intrinsics: Intrinsics {
                    width: 4,
                    height: 1,
                    fx: 1.0,
                    fy: 1.0,
                    cx: 0.0,
                    cy: 0.5,
                    distortion: Distortion::None,
                },
                pose: Pose {
                    rotation: glam::DMat3::IDENTITY,
                    translation: glam::DVec3::ZERO,
                },
            },
        };
        let centres = vec![
            [0.5, 0.0, 1.0],
            [2.5, 0.0, 1.0],
            [3.5, 0.0, 1.0],
            [9.5, 0.0, 1.0],
        ];
        // Pixel 0 (wall) lists Gaussians 1 and 0; pixel 2 (door) lists 0, 1, 2, 3.
        let c = ViewContrib {
            width: 4,
            height: 1,
            k: 0,
            gaussians: 4,
            lists: Contributions {
                offsets: vec![0, 2, 2, 6, 6],
                ids: vec![1, 0, 0, 1, 2, 3],
                weights: vec![0.5, 0.5, 0.1, 0.2, 0.3, 0.4],
                residual: vec![0.0; 4],
            },
            alpha: vec![1.0; 4],
            depth: vec![1.0; 4],
            median: Vec::new(),
        };
        let mut gate = CityGate::new(centres, &dir, 0.5, delta);
        let off = gate.view(&view, &c, &labels).unwrap();
        gate.classes = Some(table);
        let on = gate.view(&view, &c, &labels).unwrap();
        let mut v = Votes::new(4);
        let (gated, total) = v.accumulate_gated(&c, &labels, Some(&on));
        // Gaussian 0 (centre on the wall) loses its door vote, 1 (centre on the door) its wall
        // vote; 2 (centre on a non-city label) and 3 (centre outside) keep theirs.
        assert_eq!(v.of(0), vec![(0, 0.5)]);
        assert!(v.of(1).len() == 1 && v.of(1)[0].0 == 1 && (v.of(1)[0].1 - 0.2).abs() < 1e-6);
        assert!(v.of(2).len() == 1 && v.of(2)[0].0 == 1 && (v.of(2)[0].1 - 0.3).abs() < 1e-6);
        assert!(v.of(3).len() == 1 && v.of(3)[0].0 == 1 && (v.of(3)[0].1 - 0.4).abs() < 1e-6);
        assert!(
            (gated - 0.6).abs() < 1e-6 && (total - 2.0).abs() < 1e-6,
            "{gated} {total}"
        );
        // Without the centre gate both straddling Gaussians vote for both labels.
        let mut u = Votes::new(4);
        u.accumulate_gated(&c, &labels, Some(&off));
        assert_eq!(u.of(0).len(), 2);
        assert_eq!(u.of(1).len(), 2);
    }

    #[test]
    fn vote_argmax_normalisation_and_gamma() {
        let mut v = Votes::new(3);
        v.add(0, 7, 0.6);
        v.add(0, BACKGROUND, 0.4);
        v.add(1, 7, 0.3);
        v.add(1, BACKGROUND, 0.5);
        for l in 10..20 {
            v.add(2, l, 0.01 * f64::from(l)); // overflows the inline slots
        }
        let a = assign(&v, 3, 0.0);
        assert_eq!(a[0].label, 7);
        assert!((a[0].confidence - 0.6).abs() < 1e-6);
        assert_eq!(a[1].label, BACKGROUND);
        assert_eq!(a[2].label, 19, "overflow votes count");
        // γ = 0.3 moves Gaussian 0 (0.6 vs 0.4 + 0.3) to background; γ = −0.3 moves Gaussian 1 to 7.
        assert_eq!(assign(&v, 3, 0.3)[0].label, BACKGROUND);
        assert_eq!(assign(&v, 3, -0.3)[1].label, 7);
        // No vote at all: background with zero confidence.
        let empty = assign(&Votes::new(1), 1, 0.0);
        assert_eq!(
            empty[0],
            Assignment {
                label: BACKGROUND,
                confidence: 0.0,
                weight: 0.0
            }
        );
    }

    #[test]
    fn long_sums_stay_exact_in_f64() {
        // 30 million votes of 1e-7 (= 3.0) for one label and one vote of 2.5 for another: a
        // sequential f32 sum stalls at 2.0 (NumPy `cumsum(dtype=float32)` gives 2.0), which
        // would hand the Gaussian to the wrong label.
        let mut v = Votes::new(1);
        for _ in 0..30_000_000 {
            v.add(0, 1, 1e-7);
        }
        v.add(0, 2, 2.5);
        let votes = v.of(0);
        let w1 = votes.iter().find(|x| x.0 == 1).unwrap().1;
        assert!((w1 - 3.0).abs() < 1e-6, "{w1}");
        assert_eq!(assign(&v, 1, 0.0)[0].label, 1);
    }
}
