//! CPU rasterizer for 3D Gaussian Splatting: the INRIA `diff-gaussian-rasterization`
//! forward pass (its constants: near cull z ≤ 0.2, +0.3 on the 2D covariance's diagonal, radius
//! ⌈3√λ_max⌉, α = min(0.99, o·e^power), α < 1/255 skipped, stop once T·(1 − α) < 1e-4; the
//! `forward.cu` of the INRIA repository), deterministic and rayon-parallel
//! over 16×16 tiles. This module owns the render stage: [`PreparedScene`] (view-independent
//! activations), [`render_view`] (one camera → RGB, alpha, depths, features, contribution
//! lists) and [`render_to_dir`] (per-view files). Submodules: [`project`] (per-Gaussian
//! preprocessing), [`tile`] (binning and depth sort), [`blend`] (per-tile compositing).
//!
//! Conventions:
//! * Pixel `(i, j)` is evaluated at the projected mean in index coordinates
//!   `fx·x/z + cx − 0.5` (COLMAP puts pixel centres at integer + 0.5; this equals INRIA's
//!   `ndc2Pix` when `cx = W/2`). `tan_fovx = W/(2fx)`, `tan_fovy = H/(2fy)`.
//! * Lens distortion is ignored (pinhole only, like INRIA); [`render_to_dir`] counts such views.
//! * `depth_acc` is INRIA-style accumulated depth `Σ wᵢ·zᵢ` with `wᵢ = αᵢ·Tᵢ`; `depth` is the
//!   expected depth `Σ wᵢ·zᵢ / (1 − T)` (NaN where `1 − T < DEPTH_MIN_ALPHA`); `median_depth`
//!   is the z of the first Gaussian after which `T < 0.5` (NaN if never).
//! * Features are blended with the same weights and no background term.
//! * Results do not depend on the number of threads: tiles are independent and every
//!   tile list is ordered by `(depth, Gaussian index)`.
pub mod blend;
pub mod cache;
pub mod cull;
pub mod project;
pub mod select;
pub mod tile;

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DQuat};
use ndarray::Array3;
use rayon::prelude::*;

use blend::{BlendInput, TileOut};
pub use blend::{Contribution, ContributionMode};
use project::{Projected, ViewParams};

use crate::cache::{Contributions, DEPTH_MIN_ALPHA};
use crate::camera::{Camera, Distortion, View};
use crate::fsutil::{self, FsError};
use crate::imageio::{self, ImageError};
use crate::npy::{self, NpyError};
use crate::splat::Gaussians;

/// Errors of the render stage.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("invalid scene: {0}")]
    Scene(String),
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error("features: {found} values for {gaussians} Gaussians × {channels} channels")]
    Features {
        found: usize,
        gaussians: usize,
        channels: usize,
    },
    #[error("view `{view}`: {why}")]
    Camera { view: String, why: String },
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error(transparent)]
    Npy(#[from] NpyError),
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error(transparent)]
    Cache(#[from] crate::cache::CacheError),
}

/// Render settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RenderOptions {
    /// Background colour added with the final transmittance.
    pub background: [f32; 3],
    /// Mip-Splatting style opacity compensation `√(det Σ / det(Σ + 0.3 I))` (clamped at
    /// 0.000025 inside the root, as INRIA's antialiasing branch).
    pub antialiased: bool,
    /// Highest SH degree used (the scene's own degree caps it).
    pub max_sh_degree: u8,
    /// Blend the scene's feature channels.
    pub features: bool,
    /// Blend the colour and track the median depth (off where only alpha, expected depth and
    /// the lists are read: the contributions cache; the output's colour, accumulated depth
    /// and median depth are then empty).
    #[serde(default = "yes")]
    pub images: bool,
    /// Per-pixel contribution lists.
    pub contributions: ContributionMode,
    /// Early stop: a pixel stops once its transmittance falls below this after a
    /// contribution (0 = INRIA's rule alone: stop before a contribution that would take T
    /// below 10⁻⁴). What lies behind is at most `t_stop` of the pixel's mass.
    #[serde(default)]
    pub t_stop: f32,
    /// The smallest α a Gaussian contributes with at a pixel: INRIA's 1/255
    /// ([`project::ALPHA_MIN`]), or higher for the contributions cache, where the faint tails
    /// of Gaussians are left out of the lists and the blend (and each Gaussian's box shrinks).
    #[serde(default = "alpha_min")]
    pub alpha_min: f32,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            background: [0.0; 3],
            antialiased: false,
            max_sh_degree: 3,
            features: true,
            images: true,
            contributions: ContributionMode::None,
            t_stop: 0.0,
            alpha_min: project::ALPHA_MIN,
        }
    }
}

fn yes() -> bool {
    true
}

fn alpha_min() -> f32 {
    project::ALPHA_MIN
}

/// View-independent, activated Gaussian data, reusable across views.
#[derive(Debug, Clone)]
pub struct PreparedScene {
    pub positions: Vec<[f32; 3]>,
    /// World covariance `Σ = R·S²·Rᵀ` as `xx xy xz yy yz zz`.
    pub cov3d: Vec<[f32; 6]>,
    /// `sigmoid(opacity)`; 0 for a Gaussian that cannot be rendered (zero quaternion).
    pub opacity: Vec<f32>,
    pub sh_degree: u8,
    /// SH coefficients per Gaussian (`coeffs` each, coefficient-major, RGB).
    pub sh: Vec<[f32; 3]>,
    pub coeffs: usize,
    /// Per-Gaussian features, `len × channels`.
    pub features: Vec<f32>,
    pub channels: usize,
    /// Gaussians that are never drawn: zero or non-finite quaternion, a non-finite
    /// position, scale, opacity or SH value (e.g. hidden by [`crate::splat::ply::hide_invalid`]),
    /// or a covariance that overflows `f32`.
    pub skipped: usize,
    /// The per-view cull's cells ([`cull::CellIndex`]), built by the first render; the
    /// fields above must not change after [`PreparedScene::new`].
    cells: std::sync::OnceLock<cull::CellIndex>,
}

impl PreparedScene {
    /// Activates `g`: `exp` scales, `sigmoid` opacity, normalised quaternion, covariance.
    /// A Gaussian that cannot be drawn (see [`PreparedScene::skipped`]) gets opacity 0 and
    /// is counted, so that in-memory scenes (which `read_ply` has not checked) never put
    /// NaN into an image.
    pub fn new(g: &Gaussians) -> Result<Self, RenderError> {
        g.check().map_err(|e| RenderError::Scene(e.to_string()))?;
        let n = g.len();
        let coeffs = (usize::from(g.sh_degree) + 1).pow(2);
        let kk = coeffs - 1;
        let rest = g.rest_per_gaussian();
        let mut sh = Vec::with_capacity(n * coeffs);
        for i in 0..n {
            sh.push(g.f_dc[i]);
            let r = &g.f_rest[i * rest..(i + 1) * rest];
            for k in 0..kk {
                sh.push([r[k], r[kk + k], r[2 * kk + k]]);
            }
        }
        let mut opacity = Vec::with_capacity(n);
        let mut skipped = 0;
        let cov3d = (0..n)
            .map(|i| {
                let finite = g.positions[i].iter().all(|v| v.is_finite())
                    && g.scale[i].iter().all(|v| v.is_finite())
                    && g.opacity[i].is_finite()
                    && sh[i * coeffs..(i + 1) * coeffs]
                        .iter()
                        .all(|c| c.iter().all(|v| v.is_finite()));
                let cov = g.normalized_rotation(i).map(|q| covariance(g.scale[i], q));
                match cov {
                    Some(cov) if finite && cov.iter().all(|v| v.is_finite()) => {
                        opacity.push(g.activated_opacity(i));
                        cov
                    }
                    _ => {
                        skipped += 1;
                        opacity.push(0.0);
                        [0.0; 6]
                    }
                }
            })
            .collect();
        Ok(PreparedScene {
            positions: g.positions.clone(),
            cov3d,
            opacity,
            sh_degree: g.sh_degree,
            sh,
            coeffs,
            features: Vec::new(),
            channels: 0,
            skipped,
            cells: std::sync::OnceLock::new(),
        })
    }

    /// Attaches per-Gaussian features (`len × channels`, Gaussian-major).
    pub fn with_features(mut self, channels: usize, data: Vec<f32>) -> Result<Self, RenderError> {
        if data.len() != self.len() * channels {
            return Err(RenderError::Features {
                found: data.len(),
                gaussians: self.len(),
                channels,
            });
        }
        self.features = data;
        self.channels = channels;
        Ok(self)
    }

    /// The cells of the per-view cull ([`cull::CellIndex`]), built on first use.
    pub fn cells(&self) -> &cull::CellIndex {
        self.cells.get_or_init(|| cull::CellIndex::new(self))
    }

    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}

/// `Σ = R·diag(exp(scale))²·Rᵀ` for a unit quaternion `(w, x, y, z)`, computed in `f64`.
pub fn covariance(scale: [f32; 3], q: [f32; 4]) -> [f32; 6] {
    let q = q.map(f64::from);
    let r = DMat3::from_quat(DQuat::from_xyzw(q[1], q[2], q[3], q[0]));
    let s = scale.map(|v| f64::from(v).exp());
    let m = r * DMat3::from_diagonal(glam::DVec3::from_array(s));
    let sig = m * m.transpose();
    [
        sig.x_axis.x,
        sig.y_axis.x,
        sig.z_axis.x,
        sig.y_axis.y,
        sig.z_axis.y,
        sig.z_axis.z,
    ]
    .map(|v| v as f32)
}

/// Timings and counts of one render.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct RenderStats {
    pub gaussians: usize,
    /// Gaussians that survived preprocessing.
    pub projected: usize,
    /// (Gaussian, tile) pairs.
    pub tile_pairs: usize,
    pub project_s: f64,
    pub sort_s: f64,
    pub blend_s: f64,
    pub total_s: f64,
}

/// Everything one view renders. Images are row-major `H×W`; RGB is `H×W×3`.
#[derive(Debug, Clone)]
pub struct RenderOutput {
    pub width: usize,
    pub height: usize,
    /// RGB per pixel, `H × W × 3` (empty without [`RenderOptions::images`]).
    pub rgb: Vec<f32>,
    /// Accumulated alpha `1 − T`.
    pub alpha: Vec<f32>,
    /// INRIA-style accumulated depth `Σ w·z` (empty without [`RenderOptions::images`]).
    pub depth_acc: Vec<f32>,
    /// Expected depth `Σ w·z / (1 − T)`, NaN where `1 − T < DEPTH_MIN_ALPHA`.
    pub depth: Vec<f32>,
    /// Median depth (empty without [`RenderOptions::images`]).
    pub median_depth: Vec<f32>,
    /// `channels × H × W`.
    pub features: Vec<f32>,
    pub channels: usize,
    pub contributions: Option<Contributions>,
    pub stats: RenderStats,
}

impl RenderOutput {
    /// RGB as 8-bit `H×W×3` (clamped to [0, 1], rounded); the render needs
    /// [`RenderOptions::images`].
    pub fn rgb8(&self) -> Array3<u8> {
        let v = self
            .rgb
            .iter()
            .map(|&c| (c.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        Array3::from_shape_vec((self.height, self.width, 3), v).expect("H×W×3 values")
    }
}

fn check_camera(camera: &Camera) -> Result<(), String> {
    let k = &camera.intrinsics;
    if k.width == 0 || k.height == 0 {
        return Err("image size is zero".into());
    }
    if (k.width as u64) * (k.height as u64) > (1 << 31) {
        return Err("image larger than 2^31 pixels".into());
    }
    let finite = [k.fx, k.fy, k.cx, k.cy].iter().all(|v| v.is_finite())
        && camera.pose.rotation.is_finite()
        && camera.pose.translation.is_finite();
    if !finite || k.fx <= 0.0 || k.fy <= 0.0 {
        return Err("non-finite pose or non-positive focal length".into());
    }
    Ok(())
}

thread_local! {
    /// Scratch of [`render_view`]: the projected Gaussians of the last view.
    static PROJECTED: std::cell::Cell<Vec<[Projected; project::LANES]>> = const { std::cell::Cell::new(Vec::new()) };
    /// Scratch of [`render_view`]: the Gaussians the cell cull left.
    static CANDIDATES: std::cell::Cell<Vec<u32>> = const { std::cell::Cell::new(Vec::new()) };
}

/// Renders one camera.
pub fn render_view(
    scene: &PreparedScene,
    camera: &Camera,
    options: &RenderOptions,
) -> Result<RenderOutput, RenderError> {
    render_view_with(scene, camera, options, true)
}

/// [`render_view`], with or without the cull of whole cells ([`cull`]; the output is the
/// same either way).
fn render_view_with(
    scene: &PreparedScene,
    camera: &Camera,
    options: &RenderOptions,
    cull_cells: bool,
) -> Result<RenderOutput, RenderError> {
    check_camera(camera).map_err(|why| RenderError::Camera {
        view: String::new(),
        why,
    })?;
    crate::check::range(
        "alpha_min",
        options.alpha_min,
        crate::check::End::Closed(f64::from(project::ALPHA_MIN)),
        crate::check::End::Open(0.99),
    )?;
    let t0 = Instant::now();
    let v = ViewParams {
        alpha_min: options.alpha_min,
        ..ViewParams::new(camera)
    };
    let n = scene.len();
    // The Gaussians left after the cell cull, in index order (so that depth ties keep
    // breaking by index in `tile::bin`).
    let mut candidates = CANDIDATES.take();
    candidates.clear();
    if cull_cells {
        let cells = scene.cells();
        let mut keep = vec![0u64; n.div_ceil(64)];
        candidates.reserve(cells.mark_visible(&v, &mut keep));
        for (w, &bits) in keep.iter().enumerate() {
            let mut b = bits;
            while b != 0 {
                candidates.push((w * 64) as u32 + b.trailing_zeros());
                b &= b - 1;
            }
        }
    } else {
        candidates.extend(0..n as u32);
    }
    // Indexed collect: rayon writes every slot in place (no concatenation copy); culled
    // Gaussians get an empty tile rectangle and are never binned.
    // The array is reused from the previous view on this thread (taken, so that a nested
    // render gets a fresh one): a new n × 80-byte allocation per view costs a page fault per
    // 4 KB (BENCHMARKS.md's git history, "Render: allocation").
    let mut batches = PROJECTED.take();
    // Resized, not refilled: every batch is written below.
    batches.resize(
        candidates.len().div_ceil(project::LANES),
        [Projected::CULLED; project::LANES],
    );
    const BATCHES: usize = 256;
    batches
        .par_chunks_mut(BATCHES)
        .zip(candidates.par_chunks(BATCHES * project::LANES))
        .for_each(|(out, ids)| {
            project::project_into(
                scene,
                ids,
                &v,
                options.antialiased,
                options.max_sh_degree,
                out,
            )
        });
    // The last batch's padding is culled; the array is the candidates', in order.
    let projected = &batches.as_flattened()[..candidates.len()];
    CANDIDATES.set(candidates);
    let t1 = Instant::now();
    let bins = tile::bin(projected, v.grid_x, v.grid_y);
    let t2 = Instant::now();
    let channels = if options.features { scene.channels } else { 0 };
    let input = BlendInput {
        projected,
        features: if channels > 0 { &scene.features } else { &[] },
        channels,
        width: v.width,
        height: v.height,
        grid_x: v.grid_x,
        background: options.background,
        images: options.images,
        mode: options.contributions,
        t_stop: options.t_stop,
        alpha_min: v.alpha_min,
    };
    let tiles: Vec<TileOut> = (0..v.grid_x * v.grid_y)
        .into_par_iter()
        .map(|t| blend::blend_tile(&input, t, bins.tile(t)))
        .collect();
    PROJECTED.set(batches);
    let mut out = assemble(
        &tiles,
        v.width,
        v.height,
        channels,
        options.contributions,
        options.images,
    );
    let t3 = Instant::now();
    out.stats = RenderStats {
        gaussians: n,
        projected: bins.visible,
        tile_pairs: bins.items.len(),
        project_s: (t1 - t0).as_secs_f64(),
        sort_s: (t2 - t1).as_secs_f64(),
        blend_s: (t3 - t2).as_secs_f64(),
        total_s: (t3 - t0).as_secs_f64(),
    };
    Ok(out)
}

/// The view's arrays from its tiles. Without `images`, the colour, the accumulated depth and
/// the median depth are left empty: the contributions cache reads none of them, and a view's
/// arrays are fresh memory (page faults) each time.
fn assemble(
    tiles: &[TileOut],
    width: usize,
    height: usize,
    channels: usize,
    mode: ContributionMode,
    images: bool,
) -> RenderOutput {
    let npx = width * height;
    let planes = if images { npx } else { 0 };
    let mut rgb = vec![0.0f32; planes * 3];
    let mut alpha = vec![0.0f32; npx];
    let mut depth_acc = vec![0.0f32; planes];
    let mut depth = vec![f32::NAN; npx];
    let mut median_depth = vec![f32::NAN; planes];
    let mut features = vec![0.0f32; channels * npx];
    let keep = mode != ContributionMode::None;
    // Pixel p's list length at offsets[p + 1], summed into the offsets below.
    let mut offsets = vec![0u64; if keep { npx + 1 } else { 0 }];
    let mut residual = vec![0.0f32; if keep { npx } else { 0 }];
    for t in tiles {
        for y in 0..t.h {
            for x in 0..t.w {
                let k = y * blend_tile_width() + x;
                let p = (t.y0 + y) * width + t.x0 + x;
                let a = 1.0 - t.trans[k];
                alpha[p] = a;
                if a >= DEPTH_MIN_ALPHA {
                    depth[p] = t.depth_acc[k] / a;
                }
                if images {
                    for c in 0..3 {
                        rgb[p * 3 + c] = t.rgb[c][k];
                    }
                    depth_acc[p] = t.depth_acc[k];
                    median_depth[p] = t.median[k];
                }
                for c in 0..channels {
                    features[c * npx + p] = t.features[k * channels + c];
                }
                if keep {
                    offsets[p + 1] = t.list(k).len() as u64;
                    if let Some(r) = t.residual.get(k) {
                        residual[p] = *r;
                    }
                }
            }
        }
    }
    let contributions = keep.then(|| {
        for p in 0..npx {
            offsets[p + 1] += offsets[p];
        }
        let total = offsets[npx] as usize;
        let mut ids = vec![0u32; total];
        let mut weights = vec![0.0f32; total];
        for t in tiles {
            for y in 0..t.h {
                for x in 0..t.w {
                    let k = y * blend_tile_width() + x;
                    let p = (t.y0 + y) * width + t.x0 + x;
                    let o = offsets[p] as usize;
                    for (j, c) in t.list(k).iter().enumerate() {
                        ids[o + j] = c.id;
                        weights[o + j] = c.weight;
                    }
                }
            }
        }
        Contributions {
            offsets,
            ids,
            weights,
            residual,
        }
    });
    RenderOutput {
        width,
        height,
        rgb,
        alpha,
        depth_acc,
        depth,
        median_depth,
        features,
        channels,
        contributions,
        stats: RenderStats::default(),
    }
}

const fn blend_tile_width() -> usize {
    project::TILE
}

/// One rendered view in a [`RenderSummary`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct ViewSummary {
    pub name: String,
    pub stem: String,
    pub width: usize,
    pub height: usize,
    pub projected: usize,
    pub tile_pairs: usize,
    pub render_s: f64,
    pub write_s: f64,
    /// Fraction of pixels with accumulated alpha ≥ `DEPTH_MIN_ALPHA`.
    pub coverage: f64,
}

/// What [`render_to_dir`] did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RenderSummary {
    pub gaussians: usize,
    /// Gaussians never drawn (see [`PreparedScene::skipped`]).
    pub skipped_gaussians: usize,
    pub views: Vec<ViewSummary>,
    pub feature_channels: usize,
    pub options: RenderOptions,
    pub render_s: f64,
    pub write_s: f64,
    /// Gaussians × views / render seconds.
    pub gaussians_per_s: f64,
    pub warnings: Vec<String>,
}

/// What a render to disk needs before it writes anything: views, each with its own non-empty
/// output stem, and at least one Gaussian that can be drawn.
pub fn check_inputs(scene: &PreparedScene, views: &[View]) -> Result<(), RenderError> {
    if views.is_empty() {
        return Err(RenderError::Scene(
            "no views to render: the COLMAP model lists no images (or --views chose none)".into(),
        ));
    }
    if scene.is_empty() {
        return Err(RenderError::Scene(
            "the PLY holds no Gaussians (vertex count 0)".into(),
        ));
    }
    if scene.skipped == scene.len() {
        return Err(RenderError::Scene(format!(
            "none of the {} Gaussians can be drawn (each has a zero quaternion or a non-finite \
             position, scale, opacity or colour): nothing to render",
            scene.len()
        )));
    }
    match crate::camera::stem_problems(views).into_iter().next() {
        Some((view, why)) => Err(RenderError::Camera { view, why }),
        None => Ok(()),
    }
}

/// Renders every view into `out_dir`: `<stem>.png` (8-bit RGB), `<stem>.depth.npy`
/// (`float32` H×W expected depth, NaN where alpha < `DEPTH_MIN_ALPHA`) and, when the scene
/// has feature channels and `options.features` is set, `<stem>.features.npy`
/// (`float32` C×H×W). Contribution lists are not written.
pub fn render_to_dir(
    scene: &PreparedScene,
    views: &[View],
    out_dir: &Path,
    options: &RenderOptions,
) -> Result<RenderSummary, RenderError> {
    check_inputs(scene, views)?;
    fsutil::create_dir(out_dir)?;
    let opts = RenderOptions {
        contributions: ContributionMode::None,
        ..*options
    };
    let mut summary = RenderSummary {
        gaussians: scene.len(),
        skipped_gaussians: scene.skipped,
        views: Vec::new(),
        feature_channels: if opts.features { scene.channels } else { 0 },
        options: opts,
        render_s: 0.0,
        write_s: 0.0,
        gaussians_per_s: 0.0,
        warnings: Vec::new(),
    };
    let _ = std::fs::remove_file(out_dir.join("summary.json"));
    let bar = crate::progress::Bar::new("render", views.len() as u64, "views");
    for view in views {
        bar.inc(1);
        let stem = view.stem();
        if view.camera.intrinsics.distortion != Distortion::None {
            summary.warnings.push(format!(
                "{}: lens distortion ignored (pinhole render)",
                view.name
            ));
        }
        let out = render_view(scene, &view.camera, &opts).map_err(|e| match e {
            RenderError::Camera { why, .. } => RenderError::Camera {
                view: view.name.clone(),
                why,
            },
            e => e,
        })?;
        let tw = Instant::now();
        let file = |ext: &str| -> PathBuf { out_dir.join(format!("{stem}.{ext}")) };
        imageio::write_png(&file("png"), &out.rgb8())?;
        npy::write(&file("depth.npy"), &[out.height, out.width], &out.depth)?;
        if out.channels > 0 {
            npy::write(
                &file("features.npy"),
                &[out.channels, out.height, out.width],
                &out.features,
            )?;
        }
        let write_s = tw.elapsed().as_secs_f64();
        let covered = out.alpha.iter().filter(|&&a| a >= DEPTH_MIN_ALPHA).count();
        summary.render_s += out.stats.total_s;
        summary.write_s += write_s;
        summary.views.push(ViewSummary {
            name: view.name.clone(),
            stem,
            width: out.width,
            height: out.height,
            projected: out.stats.projected,
            tile_pairs: out.stats.tile_pairs,
            render_s: out.stats.total_s,
            write_s,
            coverage: covered as f64 / (out.width * out.height) as f64,
        });
    }
    bar.finish();
    if let Some(first) = summary.warnings.first() {
        log::warn!(
            "render: {} of {} views have lens distortion, which this pinhole render ignores \
             (first: {first}; summary.json lists them)",
            summary.warnings.len(),
            views.len()
        );
    }
    if summary.render_s > 0.0 {
        summary.gaussians_per_s = (scene.len() * summary.views.len()) as f64 / summary.render_s;
    }
    crate::progress::done(
        "render",
        &format!("{} views of {} Gaussians", summary.views.len(), scene.len()),
        summary.render_s + summary.write_s,
    );
    Ok(summary)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::camera::{Intrinsics, Pose};
    use glam::{DMat3, DVec3};
    use rand::{Rng, SeedableRng};

    /// A random scene around the origin: centres within ±`extent` m, scales from 2 mm to
    /// 7 m (needles and blobs), random rotations and opacities, a few NaN centres and zero
    /// quaternions (never drawn).
    pub(crate) fn random_scene(n: usize, extent: f32, seed: u64) -> PreparedScene {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut r = |lo: f32, hi: f32| lo + (hi - lo) * rng.random::<f32>();
        let mut g = Gaussians::default();
        for i in 0..n {
            let mut p = [r(-extent, extent), r(-extent, extent), r(-extent, extent)];
            if i % 997 == 5 {
                p[1] = f32::NAN;
            }
            g.positions.push(p);
            g.f_dc.push([r(-1.0, 1.0), r(-1.0, 1.0), r(-1.0, 1.0)]);
            g.opacity.push(r(-7.0, 6.0));
            let s = r(-6.0, 2.0);
            g.scale.push([s, s + r(-3.0, 0.5), s + r(-3.0, 0.5)]);
            g.rotation.push(if i % 1009 == 7 {
                [0.0; 4]
            } else {
                [r(-1.0, 1.0), r(-1.0, 1.0), r(-1.0, 1.0), r(-1.0, 1.0)]
            });
        }
        PreparedScene::new(&g).expect("valid scene")
    }

    /// A point drawn uniformly from the cube `[−half, half]³` (a test camera's centre).
    pub(crate) fn random_centre(rng: &mut impl Rng, half: f64) -> DVec3 {
        DVec3::new(
            rng.random_range(-half..half),
            rng.random_range(-half..half),
            rng.random_range(-half..half),
        )
    }

    /// A 96 × 72 test camera (focal 80) at a random centre of the cube `[−20, 20]³`, with a
    /// random yaw and the given pitch.
    fn random_camera(rng: &mut impl Rng, pitch: f64) -> Camera {
        let c = random_centre(rng, 20.0);
        camera_at(c, rng.random_range(-3.1..3.1), pitch, 96, 72, 80.0)
    }

    /// A camera at `centre` looking along yaw/pitch, `w × h`, focal `f`.
    pub(crate) fn camera_at(centre: DVec3, yaw: f64, pitch: f64, w: u32, h: u32, f: f64) -> Camera {
        let rot = DMat3::from_rotation_x(pitch) * DMat3::from_rotation_y(yaw);
        Camera {
            intrinsics: Intrinsics {
                width: w,
                height: h,
                fx: f,
                fy: f * 1.1,
                cx: f64::from(w) / 2.0 + 3.0,
                cy: f64::from(h) / 2.0 - 2.0,
                distortion: Distortion::None,
            },
            pose: Pose {
                rotation: rot,
                translation: -(rot * centre),
            },
        }
    }

    #[test]
    fn an_early_stop_keeps_each_list_up_to_the_entry_that_takes_t_below_it() {
        let scene = random_scene(20_000, 30.0, 23);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let (mut cut, mut unsure) = (0usize, 0usize);
        for k in 0..4 {
            let cam = random_camera(&mut rng, 0.3);
            let opts = |t_stop| RenderOptions {
                contributions: ContributionMode::All,
                images: false,
                t_stop,
                ..RenderOptions::default()
            };
            let full = render_view(&scene, &cam, &opts(0.0)).unwrap();
            let lf = full.contributions.as_ref().unwrap();
            for t_stop in [0.01f32, 0.05, 0.3] {
                let stopped = render_view(&scene, &cam, &opts(t_stop)).unwrap();
                let ls = stopped.contributions.as_ref().unwrap();
                for p in 0..full.alpha.len() {
                    let ((fi, fw), (si, sw)) = (lf.pixel(p), ls.pixel(p));
                    // The stopped list is the complete list's prefix, bit for bit.
                    assert_eq!(&fi[..si.len()], si, "view {k}, pixel {p}");
                    let bits = |w: &[f32]| w.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&fw[..sw.len()]), bits(sw));
                    // Its length: up to the first entry after which T = 1 − Σw < t_stop,
                    // computed in f64 from the complete list (ties within 1e-5 not judged).
                    let mut t = 1.0f64;
                    let mut want = fw.len();
                    let mut near = false;
                    for (j, &w) in fw.iter().enumerate() {
                        t -= f64::from(w);
                        near |= (t - f64::from(t_stop)).abs() < 1e-5;
                        if t < f64::from(t_stop) {
                            want = j + 1;
                            break;
                        }
                    }
                    if near {
                        unsure += 1;
                        continue;
                    }
                    assert_eq!(sw.len(), want, "view {k}, pixel {p}, t_stop {t_stop}");
                    cut += usize::from(want < fw.len());
                    // What is left out is less than t_stop of the pixel's mass.
                    let tail: f64 = fw[want..].iter().map(|&w| f64::from(w)).sum();
                    assert!(tail < f64::from(t_stop) + 1e-6, "{tail}");
                    assert!(stopped.alpha[p] >= full.alpha[p] - t_stop - 1e-6);
                }
            }
        }
        assert!(
            cut > 1000,
            "only {cut} lists were cut: the test would be empty"
        );
        assert!(unsure < cut / 100, "{unsure} undecided of {cut}");
    }

    /// A higher `alpha_min` gives, at every pixel, the complete list's Gaussians whose α
    /// (recovered from the complete list: `α = w/T`, `T` decreasing by each `w`) is at least
    /// `alpha_min`, blended again on their own: `w' = α·T'`. Judged where the complete
    /// render never reached INRIA's stop (final T ≥ 0.011 > 10⁻⁴/(1 − 0.99)), and not where an
    /// α lies within 10⁻⁴ of the threshold.
    #[test]
    fn a_higher_alpha_min_keeps_the_contributions_above_it_blended_again() {
        let scene = random_scene(3_000, 30.0, 37);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(13);
        let (mut judged, mut dropped, mut unsure) = (0usize, 0usize, 0usize);
        for k in 0..4 {
            let cam = random_camera(&mut rng, 0.3);
            let opts = |alpha_min| RenderOptions {
                contributions: ContributionMode::All,
                images: false,
                alpha_min,
                ..RenderOptions::default()
            };
            let full = render_view(&scene, &cam, &opts(project::ALPHA_MIN)).unwrap();
            let lf = full.contributions.as_ref().unwrap();
            for a in [1.0f32 / 64.0, 1.0 / 8.0, 0.3] {
                let cut = render_view(&scene, &cam, &opts(a)).unwrap();
                let lc = cut.contributions.as_ref().unwrap();
                for p in 0..full.alpha.len() {
                    if 1.0 - f64::from(full.alpha[p]) < 0.011 {
                        continue;
                    }
                    let ((fi, fw), (ci, cw)) = (lf.pixel(p), lc.pixel(p));
                    let (mut t, mut t_cut) = (1.0f64, 1.0f64);
                    let (mut want_ids, mut want_w) = (Vec::new(), Vec::new());
                    let mut near = false;
                    for (&id, &w) in fi.iter().zip(fw) {
                        let alpha = f64::from(w) / t;
                        t -= f64::from(w);
                        near |= (alpha - f64::from(a)).abs() < 1e-4;
                        if alpha >= f64::from(a) {
                            want_ids.push(id);
                            want_w.push(alpha * t_cut);
                            t_cut *= 1.0 - alpha;
                        }
                    }
                    if near {
                        unsure += 1;
                        continue;
                    }
                    judged += 1;
                    dropped += usize::from(want_ids.len() < fi.len());
                    assert_eq!(ci, &want_ids[..], "view {k}, pixel {p}, alpha_min {a}");
                    for (&w, &want) in cw.iter().zip(&want_w) {
                        assert!((f64::from(w) - want).abs() < 1e-5, "{w} vs {want}");
                    }
                    assert!((f64::from(cut.alpha[p]) - (1.0 - t_cut)).abs() < 1e-5);
                }
            }
        }
        assert!(
            dropped > 1000,
            "only {dropped} of {judged} lists lost an entry"
        );
        // Large flat blobs give many pixels the same α: a few % fall in the window.
        assert!(unsure < judged / 20, "{unsure} undecided of {judged}");
    }

    #[test]
    fn without_images_the_alpha_depth_and_lists_are_the_same() {
        let scene = random_scene(20_000, 30.0, 29);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for k in 0..3 {
            let cam = random_camera(&mut rng, 0.2);
            let opts = |images| RenderOptions {
                contributions: ContributionMode::Mass {
                    epsilon: 0.05,
                    cap: 32,
                },
                images,
                t_stop: 0.02,
                ..RenderOptions::default()
            };
            let with = render_view(&scene, &cam, &opts(true)).unwrap();
            let without = render_view(&scene, &cam, &opts(false)).unwrap();
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&with.alpha), bits(&without.alpha), "view {k}");
            assert_eq!(bits(&with.depth), bits(&without.depth));
            assert_eq!(with.contributions, without.contributions);
            assert!(with.contributions.as_ref().unwrap().ids.len() > 1000);
            assert_eq!(with.rgb.len(), 3 * 96 * 72);
            assert!(without.rgb.is_empty() && without.depth_acc.is_empty());
            assert!(without.median_depth.is_empty());
        }
    }

    /// The blend keeps each pixel's first `blend::SLOTS` contributions in the pixel's own slots
    /// and spills the rest: the complete lists must equal those of the top-k path (its own
    /// per-pixel storage, back in depth order) with a k no list reaches, bit for bit, long
    /// lists included; the mass rule's lists must be `keep_mass` of the complete ones.
    #[test]
    fn lists_longer_than_the_pixel_slots_are_whole_in_depth_order() {
        let scene = random_scene(20_000, 30.0, 31);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(13);
        let (mut long, mut cut) = (0usize, 0usize);
        for k in 0..3 {
            let cam = random_camera(&mut rng, 0.3);
            let render = |mode| {
                let opts = RenderOptions {
                    contributions: mode,
                    images: false,
                    ..RenderOptions::default()
                };
                render_view(&scene, &cam, &opts)
                    .unwrap()
                    .contributions
                    .unwrap()
            };
            let all = render(ContributionMode::All);
            let every = render(ContributionMode::TopK(1 << 20));
            let mass = render(ContributionMode::Mass {
                epsilon: 0.05,
                cap: 0,
            });
            let bits = |w: &[f32]| w.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            let (mut keys, mut kept) = (Vec::new(), Vec::new());
            for p in 0..all.residual.len() {
                let (ids, ws) = all.pixel(p);
                let (ei, ew) = every.pixel(p);
                assert_eq!(ids, ei, "view {k}, pixel {p}");
                assert_eq!(bits(ws), bits(ew), "view {k}, pixel {p}");
                long += usize::from(ids.len() > blend::SLOTS);
                let list: Vec<blend::Contribution> = ids
                    .iter()
                    .zip(ws)
                    .map(|(&id, &weight)| blend::Contribution { id, weight })
                    .collect();
                kept.clear();
                let dropped = blend::keep_mass(&list, 0.05, 0, &mut keys, &mut kept);
                let (mi, mw) = mass.pixel(p);
                assert_eq!(mi, kept.iter().map(|c| c.id).collect::<Vec<_>>());
                assert_eq!(
                    bits(mw),
                    kept.iter().map(|c| c.weight.to_bits()).collect::<Vec<_>>()
                );
                assert_eq!(mass.residual[p].to_bits(), dropped.to_bits());
                cut += usize::from(mi.len() < ids.len());
            }
        }
        assert!(
            long > 200 && cut > 1000,
            "{long} long lists, {cut} cut by the mass rule"
        );
    }

    #[test]
    fn the_cell_cull_changes_no_output() {
        let scene = random_scene(20_000, 30.0, 17);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for k in 0..6 {
            let c = random_centre(&mut rng, 20.0);
            // Narrow to very wide fields of view (focal 25 px at 96 px: the Jacobian clamp).
            let f = [25.0, 60.0, 120.0, 400.0, 80.0, 1500.0][k];
            let cam = camera_at(
                c,
                rng.random_range(-3.1..3.1),
                rng.random_range(-1.5..1.5),
                96,
                72,
                f,
            );
            for mode in [
                ContributionMode::All,
                ContributionMode::Mass {
                    epsilon: 0.05,
                    cap: 32,
                },
            ] {
                let opts = RenderOptions {
                    antialiased: k % 2 == 0,
                    contributions: mode,
                    ..RenderOptions::default()
                };
                let a = render_view_with(&scene, &cam, &opts, true).unwrap();
                let b = render_view_with(&scene, &cam, &opts, false).unwrap();
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&a.rgb), bits(&b.rgb), "view {k}");
                assert_eq!(bits(&a.alpha), bits(&b.alpha));
                assert_eq!(bits(&a.depth_acc), bits(&b.depth_acc));
                assert_eq!(bits(&a.median_depth), bits(&b.median_depth));
                assert_eq!(a.contributions, b.contributions);
                assert_eq!(a.stats.projected, b.stats.projected);
                assert_eq!(a.stats.tile_pairs, b.stats.tile_pairs);
                assert!(
                    b.stats.projected > 0,
                    "view {k} sees nothing: the test would be empty"
                );
            }
        }
    }
}
