//! `gs4city view --run R` / `gs4city view --scene S`: a local interactive viewer of a finished
//! run, or of a scene before any run (its own Gaussians in RGB, to collect ground-control
//! points) (docs/view.md). A small HTTP server ([`http`], bound to 127.0.0.1 only) serves the
//! page, its script and the splat renderer it draws with (Spark on three.js, vendored from npm;
//! all embedded in the binary, [`assets`]), the Gaussians in a compact binary
//! ([`splats_binary`]), a JSON API and the run folder's files ([`files`]):
//!
//! * `GET /api/meta`: Gaussian count, mode, scene up axis, centre and extent, the class legend
//!   (`run` is null for a scene);
//! * `GET /api/point?eye=X,Y,Z&target=X,Y,Z&up=X,Y,Z&fovy=DEG&width=W&height=H&x=U&y=V` (the
//!   page's camera and a position in its canvas, CSS pixels from the top left) or
//!   `GET /api/point?view=IMAGE&x=U&y=V` (a position in a COLMAP image, pixel (i, j) covering
//!   [i, i+1) × [j, j+1)): the point of the splat surface under that position
//!   ([`crate::splat::surface`]: the renderer's own blend list of that one pixel, the Gaussian
//!   where the transmittance falls to one half, the ray's peak of its density), in the scene
//!   frame and, where an alignment is known, in the city model's CRS (f64);
//! * `GET /api/splats.bin`: centres, scales, rotations, RGB / class / building colours and the
//!   Gaussian each splat stands for ([`splats_binary`]): every Gaussian, or, for a run of more
//!   than the splat budget (`--max-splats`), the coarse set the 3D Tiles export's level of
//!   detail merges ([`crate::tiles3d::lod::coarsen`]), each splat standing for its heaviest
//!   Gaussian (its class, building, pick and query bit);
//! * `GET /api/query?where=EXPR`: the selection of `gs4city query --where EXPR` — the same parser
//!   and evaluation ([`crate::selection`]) over the same per-Gaussian labels — as a count and a
//!   bitmask (base64, bit `i` of byte `i / 8` LSB first = Gaussian `i`); a bad expression is
//!   answered 400 with the parser's one-line message;
//! * `GET /api/pick?i=N` (a run): Gaussian `N`'s label, class and city hierarchy building →
//!   surface → part with gml:ids and attributes ([`crate::query::chain`], as `query --pick`);
//! * `GET /files/PATH`: a regular file inside the run folder, nothing outside it.
//!
//! A click on the page asks `/api/point` for the clicked point's coordinates; with a run it also
//! picks the splat on the client (every splat's index + 1 drawn as an RGBA colour into an
//! offscreen target with the renderer's camera, the clicked pixel read back) and asks
//! `/api/pick` for its hierarchy.
pub mod assets;
pub mod files;
pub mod http;

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::DVec3;

use crate::camera::{Camera, Distortion, Intrinsics, Pose, View};
use crate::mesh::FaceLabel;
use crate::render::{PreparedScene, RenderOptions};
use crate::selection::{SelectionError, SemanticRun, TextOptions};
use crate::splat::{self, Gaussians, ReadOptions};
use crate::{alignment, classes, query, semantics};
use http::{Body, Request, Response};

/// Magic and version of [`splats_binary`].
pub const SPLATS_MAGIC: &[u8; 4] = b"GS4V";
pub const SPLATS_VERSION: u32 = 3;
/// Bytes per splat in [`splats_binary`] (after the 16-byte head).
pub const SPLATS_STRIDE: usize = 60;
/// The default splat budget of the page: a run with more Gaussians is served as a coarse set of
/// at most this many splats.
pub const MAX_SPLATS: usize = 600_000;

/// Errors of opening a run for viewing or binding the server.
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error(transparent)]
    Selection(#[from] SelectionError),
    #[error(transparent)]
    Ply(#[from] splat::PlyError),
    #[error(transparent)]
    Alignment(#[from] alignment::AlignError),
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    #[error(transparent)]
    Colmap(#[from] crate::colmap::ColmapError),
    #[error(transparent)]
    Render(#[from] crate::render::RenderError),
    #[error("{0}")]
    Inputs(String),
    #[error("cannot listen on 127.0.0.1:{port}: {err}")]
    Bind { port: u16, err: std::io::Error },
    #[error("cannot serve on 127.0.0.1:{port}: {err}")]
    Serve { port: u16, err: std::io::Error },
}

/// A finished run's semantics, when one is viewed.
struct RunPart {
    sr: SemanticRun,
    /// The run folder, canonical (the root of `/files/`).
    root: PathBuf,
    chains: Vec<FaceLabel>,
    text: TextOptions,
}

/// A scene's Gaussians (and, with `--run`, a finished run of it), loaded for serving.
pub struct Viewer {
    run: Option<RunPart>,
    /// The Gaussians as the renderer draws them (invalid ones hidden) and as picked.
    gaussians: Gaussians,
    prepared: PreparedScene,
    /// The scene's COLMAP views (`/api/point?view=`).
    views: Vec<View>,
    /// Scene frame → the city model's CRS, where an alignment is known, and the CRS's name.
    alignment: Option<alignment::Alignment>,
    crs: Option<String>,
    splats: Arc<Vec<u8>>,
    meta: serde_json::Value,
}

/// The DC colour of a Gaussian as 8-bit RGB (`0.5 + C0·f_dc`, clamped).
fn dc_rgb(dc: [f32; 3]) -> [u8; 3] {
    const C0: f32 = 0.282_094_8;
    dc.map(|c| ((0.5 + C0 * c).clamp(0.0, 1.0) * 255.0).round() as u8)
}

/// The page's binary of `n` Gaussians (little endian, every block 4-byte aligned), 16 +
/// [`SPLATS_STRIDE`]·n bytes: `GS4V`, u32 version, u32 n, u32 0; f32 `x y z` × n; f32 size × n
/// (the largest activated scale, σ in scene units); f32 activated scales `sx sy sz` × n; f32
/// unit quaternion `x y z w` × n (identity for a zero or non-finite one); RGBA8 × n (DC colour,
/// activated opacity); RGBA8 × n (class colour, `classes::color`); RGBA8 × n (building colour,
/// `classes::building_color`); u32 × n (the Gaussian each splat stands for: its index in the
/// run). Non-finite scales are sent as 0.
pub fn splats_binary(
    g: &splat::Gaussians,
    class_of: &[i32],
    building_of: &[i32],
    gaussian: &[u32],
) -> Vec<u8> {
    let n = g.len();
    let mut out = Vec::with_capacity(16 + n * SPLATS_STRIDE);
    out.extend_from_slice(SPLATS_MAGIC);
    out.extend_from_slice(&SPLATS_VERSION.to_le_bytes());
    out.extend_from_slice(&(n as u32).to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    let f32s = |out: &mut Vec<u8>, v: &[f32]| {
        for x in v {
            out.extend_from_slice(&(if x.is_finite() { *x } else { 0.0 }).to_le_bytes());
        }
    };
    for p in &g.positions {
        f32s(&mut out, p);
    }
    for i in 0..n {
        let s = g.activated_scale(i);
        f32s(&mut out, &[s[0].max(s[1]).max(s[2])]);
    }
    for i in 0..n {
        f32s(&mut out, &g.activated_scale(i));
    }
    for i in 0..n {
        let [w, x, y, z] = g.normalized_rotation(i).unwrap_or([1.0, 0.0, 0.0, 0.0]);
        f32s(&mut out, &[x, y, z, w]);
    }
    for i in 0..n {
        let [r, gg, b] = dc_rgb(g.f_dc[i]);
        let a = (g.activated_opacity(i).clamp(0.0, 1.0) * 255.0).round() as u8;
        out.extend_from_slice(&[r, gg, b, a]);
    }
    for &c in class_of {
        let [r, gg, b] = classes::color(c);
        out.extend_from_slice(&[r, gg, b, 255]);
    }
    for &b in building_of {
        let [r, gg, bl] = classes::building_color(b);
        out.extend_from_slice(&[r, gg, bl, 255]);
    }
    for &i in gaussian {
        out.extend_from_slice(&i.to_le_bytes());
    }
    out
}

/// The splats the page draws for Gaussians `g` with their classes and buildings: all of them
/// when they are at most `max_splats`, else the coarse set of at most `max_splats` that
/// [`crate::tiles3d::lod::coarsen`] merges (moment matching in voxel cells), each splat standing
/// for its heaviest Gaussian. Returns the splats, their classes, buildings and Gaussians.
pub fn budget(
    g: splat::Gaussians,
    class_of: &[i32],
    building_of: &[i32],
    max_splats: usize,
) -> (splat::Gaussians, Vec<i32>, Vec<i32>, Vec<u32>) {
    let n = g.len();
    if n <= max_splats {
        return (
            g,
            class_of.to_vec(),
            building_of.to_vec(),
            (0..n as u32).collect(),
        );
    }
    let set = crate::tiles3d::lod::SplatSet {
        g,
        tags: (0..n)
            .map(|i| [i as i32, class_of[i], building_of[i], 0])
            .collect(),
        error: vec![0.0; n],
    };
    let c = crate::tiles3d::lod::coarsen(&set, max_splats.max(1));
    let class = c.tags.iter().map(|t| t[1]).collect();
    let building = c.tags.iter().map(|t| t[2]).collect();
    let index = c.tags.iter().map(|t| t[0] as u32).collect();
    (c.g, class, building, index)
}

/// Standard base64 (RFC 4648, with padding) of `bytes`.
pub fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let v = (u32::from(c[0]) << 16)
            | (u32::from(*c.get(1).unwrap_or(&0)) << 8)
            | u32::from(*c.get(2).unwrap_or(&0));
        for k in 0..4 {
            if k <= c.len() {
                s.push(A[(v >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

/// The selection bitmask: bit `i % 8` (LSB first) of byte `i / 8` is Gaussian `i`.
pub fn bitmask(selected: &[bool]) -> Vec<u8> {
    let mut m = vec![0u8; selected.len().div_ceil(8)];
    for (i, _) in selected.iter().enumerate().filter(|(_, s)| **s) {
        m[i / 8] |= 1 << (i % 8);
    }
    m
}

/// Robust centre and extent of the Gaussians: per axis the 2nd and 98th percentile.
fn bounds(g: &splat::Gaussians) -> (DVec3, f64) {
    if g.is_empty() {
        return (DVec3::ZERO, 1.0);
    }
    let mut lo = [0.0f64; 3];
    let mut hi = [0.0f64; 3];
    for a in 0..3 {
        let mut v: Vec<f32> = g
            .positions
            .iter()
            .map(|p| p[a])
            .filter(|x| x.is_finite())
            .collect();
        if v.is_empty() {
            continue;
        }
        v.sort_by(f32::total_cmp);
        lo[a] = f64::from(v[v.len() * 2 / 100]);
        hi[a] = f64::from(v[(v.len() * 98 / 100).min(v.len() - 1)]);
    }
    let (lo, hi) = (DVec3::from(lo), DVec3::from(hi));
    ((lo + hi) * 0.5, ((hi - lo).length() * 0.5).max(1e-3))
}

impl Viewer {
    /// Loads run folder `run` made from scene folder `scene` in `mode` (as `gs4city query`),
    /// and its Gaussians (the scene's `point_cloud.ply`, every Gaussian kept in file order as
    /// the pipeline reads it). `crs`: the city model's CRS name, when known.
    pub fn open(
        run: &Path,
        scene: &Path,
        mode: Option<crate::layout::Mode>,
        max_splats: usize,
        crs: Option<String>,
    ) -> Result<Viewer, ViewError> {
        let sr = SemanticRun::open(run, scene, mode)?;
        let (g, _) = splat::read_ply(&sr.scene.ply, &ReadOptions::KEEP)?;
        if g.len() != sr.label_of.len() {
            return Err(ViewError::Inputs(format!(
                "{}: {} Gaussians, but {}/gaussians.npy labels {}",
                sr.scene.ply.display(),
                g.len(),
                sr.mode.dir(),
                sr.label_of.len()
            )));
        }
        let root = run
            .canonicalize()
            .map_err(|e| ViewError::Inputs(format!("{}: {e}", run.display())))?;
        let cols = query::columns(&sr);
        let (bg, class, building, index) =
            budget(g.clone(), &sr.class_of, &cols.building, max_splats);
        let n_splats = bg.len();
        let splats = splats_binary(&bg, &class, &building, &index);
        drop(bg);
        // The run's alignment (its citymodel stage's: refined where the run refined it).
        let apath = crate::layout::Stage::Citymodel
            .path(run)
            .join("alignment.json");
        let alignment = if apath.is_file() {
            Some(alignment::Alignment::read(&apath)?)
        } else {
            None
        };
        let views = crate::colmap::read_model(&sr.scene.sparse)?;
        let mut v = Viewer::new(g, views, alignment, crs, splats, n_splats)?;
        v.meta["mode"] = sr.mode.name().into();
        v.meta["run"] = root.display().to_string().into();
        v.meta["labels_source"] = sr.labels_source.clone().into();
        v.meta["files"] =
            serde_json::json!(["report.html", format!("{}/semantic.ply", sr.mode.dir())]);
        v.run = Some(RunPart {
            chains: semantics::chains(&sr.entities),
            sr,
            root,
            text: TextOptions::default(),
        });
        Ok(v)
    }

    /// Loads scene folder `scene` before any run: its Gaussians in RGB, clicks giving the
    /// points' scene coordinates (and, once `citymodel/alignment.json` exists, their
    /// coordinates in the city model's CRS).
    pub fn open_scene(scene: &Path, crs: Option<String>) -> Result<Viewer, ViewError> {
        let s = crate::scene::Scene::open(scene)?;
        let (g, _) = splat::read_ply(&s.ply, &ReadOptions::KEEP)?;
        let none = vec![-1; g.len()];
        let index: Vec<u32> = (0..g.len() as u32).collect();
        let splats = splats_binary(&g, &none, &none, &index);
        let n_splats = g.len();
        let alignment = s
            .alignment
            .as_deref()
            .map(alignment::Alignment::read)
            .transpose()?;
        let views = crate::colmap::read_model(&s.sparse)?;
        let mut v = Viewer::new(g, views, alignment, crs, splats, n_splats)?;
        v.meta["scene"] = s.root.display().to_string().into();
        v.meta["simulated"] = s.simulated().into();
        Ok(v)
    }

    fn new(
        mut gaussians: Gaussians,
        views: Vec<View>,
        alignment: Option<alignment::Alignment>,
        crs: Option<String>,
        splats: Vec<u8>,
        n_splats: usize,
    ) -> Result<Viewer, ViewError> {
        // Up in the scene frame: p_scene = s·R·(p_geo − origin) + t, so geo z is R·ẑ.
        let up = alignment
            .as_ref()
            .map_or(DVec3::Z, |a| a.rotation * DVec3::Z);
        let (center, extent) = bounds(&gaussians);
        let legend: Vec<serde_json::Value> = (0..classes::NAMES.len() as i32)
            .map(|c| serde_json::json!({"id": c, "name": classes::name(c), "color": classes::color(c)}))
            .collect();
        let meta = serde_json::json!({
            "gaussians": gaussians.len(),
            "splats": n_splats,
            "mode": null,
            "run": null,
            "scene": null,
            "simulated": false,
            "labels_source": null,
            "up": up.normalize_or(DVec3::Z).to_array(),
            "center": center.to_array(),
            "extent": extent,
            "classes": legend,
            "files": [],
            "georeferenced": alignment.is_some(),
            "crs": crs,
        });
        splat::ply::hide_invalid(&mut gaussians);
        let prepared = PreparedScene::new(&gaussians)?;
        Ok(Viewer {
            run: None,
            gaussians,
            prepared,
            views,
            alignment,
            crs,
            splats: Arc::new(splats),
            meta,
        })
    }

    /// Number of Gaussians served.
    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    /// Whether the scene has no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

    /// `/api/query?where=EXPR`.
    pub fn query(&self, expr: &str) -> Response {
        let Some(run) = &self.run else {
            return Response::error(404, NO_RUN);
        };
        match run.sr.select_text("where", expr, run.text) {
            Ok((e, sel)) => {
                let selected = run.sr.gaussian_selection(&sel.labels);
                let count = selected.iter().filter(|s| **s).count();
                let gml = |id: &i32| {
                    run.sr
                        .entities
                        .get(*id as usize)
                        .map(|e| e.object_id.clone())
                };
                Response::json(
                    200,
                    &serde_json::json!({
                        "query": e.to_string(),
                        "count": count,
                        "labels": sel.labels.len(),
                        "entities": sel.entities.len(),
                        "roots": sel.roots.iter().filter_map(gml).take(100).collect::<Vec<_>>(),
                        "warnings": sel.warnings,
                        "mask": base64(&bitmask(&selected)),
                    }),
                )
            }
            Err(e @ (SelectionError::Parse { .. } | SelectionError::Select { .. })) => {
                Response::error(400, e.to_string())
            }
            Err(e) => Response::error(500, e.to_string()),
        }
    }

    /// `/api/pick?i=N`.
    pub fn pick(&self, i: &str) -> Response {
        let Some(run) = &self.run else {
            return Response::error(404, NO_RUN);
        };
        let Ok(i) = i.trim().parse::<usize>() else {
            return Response::error(400, format!("i `{i}`: expected a Gaussian index ≥ 0"));
        };
        if i >= self.len() {
            return Response::error(
                404,
                format!("Gaussian {i}: the run has {} Gaussians", self.len()),
            );
        }
        let sr = &run.sr;
        let label = sr.label_of[i];
        let l = sr.labels.get(label);
        Response::json(
            200,
            &serde_json::json!({
                "gaussian": i,
                "label": label,
                "class": sr.class_of[i],
                "category": classes::name(sr.class_of[i]),
                "source": l.map(|l| match l.source {
                    crate::labels::Source::City => "city",
                    crate::labels::Source::Image => "image",
                }),
                "group": l.and_then(|l| l.group),
                "chain": query::chain(sr, &run.chains, label),
            }),
        )
    }

    /// `/api/point?…` (module docs): the camera and the position, parsed.
    fn point_camera(
        &self,
        param: &dyn Fn(&str) -> Option<String>,
    ) -> Result<(Camera, f64, f64), String> {
        let num = |k: &str| -> Result<f64, String> {
            let v = param(k).ok_or_else(|| format!("give {k}="))?;
            v.trim()
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| format!("{k} `{v}`: expected a finite number"))
        };
        let vec3 = |k: &str| -> Result<DVec3, String> {
            let v = param(k).ok_or_else(|| format!("give {k}=X,Y,Z"))?;
            let xs: Vec<f64> = v
                .split(',')
                .map(|t| t.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|_| format!("{k} `{v}`: expected three numbers X,Y,Z"))?;
            match xs[..] {
                [x, y, z] if xs.iter().all(|v| v.is_finite()) => Ok(DVec3::new(x, y, z)),
                _ => Err(format!("{k} `{v}`: expected three finite numbers X,Y,Z")),
            }
        };
        let (x, y) = (num("x")?, num("y")?);
        if let Some(name) = param("view") {
            let v = self
                .views
                .iter()
                .find(|v| v.name == name || v.stem() == name)
                .ok_or_else(|| {
                    format!("view `{name}` is not an image of the scene's COLMAP model")
                })?;
            return Ok((v.camera, x, y));
        }
        let (eye, target, up) = (vec3("eye")?, vec3("target")?, vec3("up")?);
        let (fovy, w, h) = (num("fovy")?, num("width")?, num("height")?);
        if !(fovy > 0.0 && fovy < 180.0) {
            return Err(format!("fovy {fovy}: expected degrees in (0, 180)"));
        }
        if !(w >= 1.0 && h >= 1.0 && w <= 32768.0 && h <= 32768.0) {
            return Err(format!(
                "width × height {w} × {h}: expected 1 to 32768 pixels each"
            ));
        }
        let pose = Pose::look_at(eye, target, up)
            .ok_or_else(|| "eye equals target, or the view looks along up".to_string())?;
        let f = (h / 2.0) / (fovy.to_radians() / 2.0).tan();
        let intrinsics = Intrinsics {
            width: w.round() as u32,
            height: h.round() as u32,
            fx: f,
            fy: f,
            cx: w / 2.0,
            cy: h / 2.0,
            distortion: Distortion::None,
        };
        Ok((Camera { intrinsics, pose }, x, y))
    }

    /// `/api/point?…`: the point of the splat surface under position (x, y) of a camera
    /// (module docs), in the scene frame and the city model's CRS.
    pub fn point(&self, param: &dyn Fn(&str) -> Option<String>) -> Response {
        let (cam, x, y) = match self.point_camera(param) {
            Ok(c) => c,
            Err(e) => return Response::error(400, e),
        };
        let k = &cam.intrinsics;
        if !(x >= 0.0 && y >= 0.0 && x <= f64::from(k.width) && y <= f64::from(k.height)) {
            return Response::error(
                400,
                format!(
                    "position ({x}, {y}) lies outside the {}×{} image",
                    k.width, k.height
                ),
            );
        }
        // The renderer's blend list of one pixel centred on (x, y): the same camera, an image
        // of 1×1 pixels whose principal point is moved so that its pixel covers (x, y) ± ½.
        let one = Camera {
            intrinsics: Intrinsics {
                width: 1,
                height: 1,
                cx: k.cx - (x - 0.5),
                cy: k.cy - (y - 0.5),
                ..*k
            },
            pose: cam.pose,
        };
        let opts = RenderOptions {
            features: false,
            max_sh_degree: 0,
            images: false,
            contributions: crate::render::ContributionMode::All,
            t_stop: 0.0,
            ..Default::default()
        };
        let out = match crate::render::render_view(&self.prepared, &one, &opts) {
            Ok(o) => o,
            Err(e) => return Response::error(400, e.to_string()),
        };
        let c = out.contributions.unwrap_or_default();
        let (ids, ws) = if c.offsets.len() >= 2 {
            c.pixel(0)
        } else {
            (&[][..], &[][..])
        };
        let origin = cam.pose.center();
        let dir = cam.pose.rotation.transpose() * cam.pixel_ray(x, y);
        let list = ids.iter().copied().zip(ws.iter().copied());
        let alpha: f64 = ws.iter().map(|&w| f64::from(w)).sum();
        match splat::surface::surface_point(&self.gaussians, list, origin, dir) {
            None => Response::json(
                200,
                &serde_json::json!({
                    "hit": false,
                    "alpha": alpha,
                    "why": "the splats under this position are less than half opaque (sky, a gap)",
                }),
            ),
            Some(p) => {
                let geo = self
                    .alignment
                    .as_ref()
                    .map(|a| a.unapply(p.point).to_array());
                Response::json(
                    200,
                    &serde_json::json!({
                        "hit": true,
                        "scene": p.point.to_array(),
                        "geo": geo,
                        "crs": self.crs,
                        "gaussian": p.gaussian,
                        "distance": p.t,
                        "alpha": p.alpha,
                    }),
                )
            }
        }
    }

    /// Answers one request.
    pub fn handle(&self, req: &Request, port: u16) -> Response {
        if req.method != "GET" && req.method != "HEAD" {
            return Response::text(405, format!("{}: only GET and HEAD", req.method));
        }
        if let Some(h) = &req.host {
            let ok = [format!("127.0.0.1:{port}"), format!("localhost:{port}")];
            if !ok.iter().any(|o| o.eq_ignore_ascii_case(h)) {
                return Response::text(421, format!("Host `{h}`: this server is 127.0.0.1:{port}"));
            }
        }
        let params = parse_query(&req.query);
        let param = |k: &str| params.iter().find(|(n, _)| n == k).map(|(_, v)| v.as_str());
        let owned = |k: &str| param(k).map(str::to_string);
        if let Some(a) = assets::find(&req.path) {
            return Response {
                status: 200,
                content_type: a.content_type,
                body: Body::Static(a.bytes),
            };
        }
        match req.path.as_str() {
            "/api/meta" => Response::json(200, &self.meta),
            "/api/splats.bin" => Response {
                status: 200,
                content_type: "application/octet-stream",
                body: Body::Shared(Arc::clone(&self.splats)),
            },
            "/api/query" => match param("where") {
                Some(w) => self.query(w),
                None if params.iter().any(|(n, _)| n == "\u{fffd}") => {
                    Response::error(400, "the query string is not valid percent-encoded UTF-8")
                }
                None => Response::error(400, "give where=EXPR (the syntax of query --where)"),
            },
            "/api/pick" => match param("i") {
                Some(i) => self.pick(i),
                None => Response::error(400, "give i=N (a Gaussian index)"),
            },
            "/api/point" => self.point(&owned),
            p => match p.strip_prefix("/files/") {
                None => Response::text(404, format!("{p}: no such page")),
                Some(_) if self.run.is_none() => Response::text(404, NO_RUN),
                Some(rel) => match files::resolve(&self.run.as_ref().expect("a run").root, rel) {
                    Ok(f) => match std::fs::metadata(&f) {
                        Ok(m) => Response {
                            status: 200,
                            content_type: content_type(&f),
                            body: Body::File(f, m.len()),
                        },
                        Err(e) => Response::text(404, format!("{}: {e}", f.display())),
                    },
                    Err(files::Refusal::Outside(m)) => Response::text(403, m),
                    Err(files::Refusal::Missing(m)) => Response::text(404, m),
                },
            },
        }
    }
}

/// The answer of the run's routes when a scene is viewed before any run.
const NO_RUN: &str = "no run is loaded (gs4city view --scene S shows the scene before a run: \
                      colours and clicked points only; `gs4city view --run R` after \
                      `gs4city run --scene S --out R`)";

fn content_type(p: &Path) -> &'static str {
    match p.extension().and_then(|e| e.to_str()) {
        Some("html") => "text/html; charset=utf-8",
        Some("json") => "application/json",
        Some("png") => "image/png",
        Some("txt" | "md") => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    }
}

/// `a=1&b=x%20y` → pairs, `+` as space; a pair that does not decode becomes (`\u{fffd}`, ``).
pub fn parse_query(q: &str) -> Vec<(String, String)> {
    q.split('&')
        .filter(|p| !p.is_empty())
        .map(|p| {
            let (k, v) = p.split_once('=').unwrap_or((p, ""));
            let dec = |s: &str| files::percent_decode(&s.replace('+', " "));
            match (dec(k), dec(v)) {
                (Some(k), Some(v)) => (k, v),
                _ => ("\u{fffd}".to_string(), String::new()),
            }
        })
        .collect()
}

/// Binds 127.0.0.1:`port` (0: a free port).
pub fn bind(port: u16) -> Result<TcpListener, ViewError> {
    TcpListener::bind(("127.0.0.1", port)).map_err(|err| ViewError::Bind { port, err })
}

/// Serves `viewer` on `listener` until the process ends (returns only when the server cannot
/// start).
pub fn serve(viewer: Viewer, listener: TcpListener) -> Result<(), ViewError> {
    let port = listener.local_addr().map(|a| a.port()).unwrap_or(0);
    let viewer = Arc::new(viewer);
    http::serve(listener, move |req| {
        let r = viewer.handle(req, port);
        log::debug!("view: {} {} → {}", req.method, req.path, r.status);
        r
    })
    .map_err(|err| ViewError::Serve { port, err })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_of_rfc4648_vectors() {
        for (i, o) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(i.as_bytes()), o, "{i}");
        }
    }

    #[test]
    fn bitmask_is_lsb_first() {
        let s = [
            true, false, false, true, false, false, false, false, false, true,
        ];
        assert_eq!(bitmask(&s), vec![0b0000_1001, 0b0000_0010]);
    }

    #[test]
    fn query_strings() {
        assert_eq!(
            parse_query("where=class%3DWindow+and+x&i=3"),
            vec![
                ("where".to_string(), "class=Window and x".to_string()),
                ("i".to_string(), "3".to_string())
            ]
        );
        assert_eq!(parse_query("where=%zz")[0].0, "\u{fffd}");
    }
}
