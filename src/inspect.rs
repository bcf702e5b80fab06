//! The scene check (`gs4city check --scene S`, and the first thing `gs4city run` does): the whole
//! scene folder (`docs/design.md`) is read once, before any stage runs, and **every** problem is
//! listed at once, each as one line naming its file:
//!
//! * missing parts: `citymodel/*.gml`, `citymodel/alignment.json` (unless a local origin is
//!   asked for), the COLMAP model `sparse/0/`, `point_cloud.ply`; `images/` missing is a
//!   warning (the pipeline does not need the pixels; overlays and the report show grey panels);
//! * images against the COLMAP model: an image the model names that is not in `images/`, a file
//!   of `images/` the model does not name, an image whose size is not its camera's;
//! * the COLMAP model itself (its reader's checks) and every camera (`Camera::validate`);
//! * the PLY: its header, the payload size (a truncated file), and per-Gaussian values — a
//!   non-finite position is an error, other invalid Gaussians are a warning (the pipeline keeps
//!   them in place and labels them −1);
//! * every CityGML file: parse errors, and the reader's warnings with their gml:ids; a city
//!   object's gml:id used in two files; a vertex the alignment puts beyond the scene frame
//!   (`camera::outside_scene_frame`, which `citymodel` refuses);
//! * `masks/` and `features/`: every SAM list, per-mask feature array and `prompts.json`, read
//!   and checked as the masks stage reads them (RLE, sizes, scores, row counts, dimensions,
//!   finite non-zero features); a view without a SAM list is a warning (test views need none);
//! * the alignment's plausibility: in how many views the aligned city model projects inside the
//!   image, and the distances between opaque Gaussian centres and the nearest city-model
//!   surface, in metres (median and lower quartile, [`AlignmentCheck::quartile_distance_m`]) —
//!   with a verdict (`alignment looks off by ~X m: run align --refine`).
//!
//! Severities: [`Severity::Error`] (the run would fail or give a silently bad result: nothing
//! runs), [`Severity::Warning`] (the run goes on; say it), [`Severity::Note`] (what the run
//! will do with what it finds: masks, features, ground truth).
//!
//! The distance check triangulates each used polygon's exterior ring as a fan (holes ignored):
//! good enough for a plausibility check at metre scale, and it keeps this module on the ground
//! floor (the citymodel stage's triangulation is not needed). Simulation truth is never read:
//! `gt/` is only noted as present or absent (it decides the default test-view split).
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::Serialize;

use crate::alignment::Alignment;
use crate::camera::View;
use crate::citygml::CityModel;
use crate::splat::{Gaussians, ReadOptions};

/// Errors of the scene check: the problems of a scene that must not run.
#[derive(Debug, thiserror::Error)]
pub enum InspectError {
    #[error(
        "scene {scene}: {} problem{} (gs4city check --scene {} lists them all):\n  {}",
        lines.len(),
        if lines.len() == 1 { "" } else { "s" },
        scene.display(),
        lines.join("\n  ")
    )]
    Problems { scene: PathBuf, lines: Vec<String> },
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
}

/// How much a finding matters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Severity {
    /// Nothing runs.
    Error,
    /// The run goes on.
    Warning,
    /// What the run will do.
    Note,
}

/// One line of the check: a file and what is wrong with it (or what was found).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Finding {
    pub severity: Severity,
    pub file: PathBuf,
    pub message: String,
}

impl std::fmt::Display for Finding {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.file.display(), self.message)
    }
}

/// The alignment's plausibility.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AlignmentCheck {
    pub views: usize,
    /// Views in which at least one city-model vertex projects inside the image, in front of
    /// the camera.
    pub views_seeing_model: usize,
    /// Opaque Gaussian centres measured (a regular subsample).
    pub gaussians_measured: usize,
    /// Lower quartile of the distances of those centres to the nearest city-model surface, in
    /// metres (scene units divided by the alignment's scale): the verdict's measure. A 3DGS
    /// city scene holds much besides the modelled buildings (ground, trees, cars), which moves
    /// the median even when the alignment is exact (3.35 m on a sparse simulated scene whose
    /// buildings' Gaussians lie on the surfaces); the buildings' own Gaussians, a quarter of the
    /// scene or more, keep the lower quartile near 0 until the model moves away from them.
    pub quartile_distance_m: f64,
    /// The median of the same distances, in metres.
    pub median_distance_m: f64,
    /// Whether both measures pass ([`CheckOptions`]).
    pub plausible: bool,
}

/// What the check found.
#[derive(Debug, Clone, Serialize)]
pub struct CheckReport {
    pub scene: PathBuf,
    pub findings: Vec<Finding>,
    pub views: usize,
    pub images: usize,
    pub gaussians: usize,
    pub gml_files: usize,
    pub alignment: Option<AlignmentCheck>,
    pub seconds: f64,
}

impl CheckReport {
    /// The findings of one severity, in order.
    pub fn of(&self, s: Severity) -> impl Iterator<Item = &Finding> {
        self.findings.iter().filter(move |f| f.severity == s)
    }

    /// Whether nothing is an error.
    pub fn is_ok(&self) -> bool {
        self.of(Severity::Error).next().is_none()
    }

    /// The report, or [`InspectError::Problems`] listing every error.
    pub fn into_result(self) -> Result<CheckReport, InspectError> {
        if self.is_ok() {
            return Ok(self);
        }
        Err(InspectError::Problems {
            scene: self.scene.clone(),
            lines: self.of(Severity::Error).map(|f| f.to_string()).collect(),
        })
    }
}

/// Options of the check.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct CheckOptions {
    /// A scene without `citymodel/alignment.json` is fine (the run uses a local origin).
    pub local_origin: bool,
    /// The alignment is written next (`scene import` before `gs4city align`): a missing
    /// `citymodel/alignment.json` is a note naming the command that writes it.
    #[serde(default)]
    pub pending_alignment: bool,
    /// Largest plausible lower-quartile distance (metres) of opaque Gaussian centres to the city
    /// model.
    pub max_offset_m: f64,
    /// Smallest plausible share of views in which the city model projects inside the image.
    pub min_view_share: f64,
    /// At most this many Gaussian centres are measured.
    pub max_samples: usize,
    /// The alignment is refined next (`run --refine-alignment`): an implausible alignment is a
    /// warning, not an error (the refinement reports whether it recovers it).
    pub refine_next: bool,
}

impl Default for CheckOptions {
    fn default() -> Self {
        CheckOptions {
            local_origin: false,
            pending_alignment: false,
            max_offset_m: 2.0,
            min_view_share: 0.5,
            max_samples: 100_000,
            refine_next: false,
        }
    }
}

impl CheckOptions {
    /// Range checks.
    pub fn validate(&self) -> Result<(), InspectError> {
        crate::check::positive("max_offset_m", self.max_offset_m)?;
        crate::check::unit("min_view_share", self.min_view_share)?;
        crate::check::at_least("max_samples", self.max_samples, 1)?;
        Ok(())
    }
}

/// Collects findings.
struct Findings(Vec<Finding>);

impl Findings {
    fn push(&mut self, severity: Severity, file: &Path, message: impl Into<String>) {
        self.0.push(Finding {
            severity,
            file: file.to_path_buf(),
            message: message.into(),
        });
    }
    fn error(&mut self, file: &Path, message: impl Into<String>) {
        self.push(Severity::Error, file, message)
    }
    fn warn(&mut self, file: &Path, message: impl Into<String>) {
        self.push(Severity::Warning, file, message)
    }
    fn note(&mut self, file: &Path, message: impl Into<String>) {
        self.push(Severity::Note, file, message)
    }
    /// A reader's error: its message already names the file; keep it as the one line.
    fn error_of(&mut self, file: &Path, e: &dyn std::fmt::Display) {
        let text = e.to_string();
        let shown = file.display().to_string();
        // An error about a file inside the folder `file` names that file (and its line): it
        // becomes the finding's file (`S/sparse/0/images.txt:5: …`, not
        // `S/sparse/0: S/sparse/0/images.txt:5: …`).
        if let Some((name, rest)) = text
            .strip_prefix(&shown)
            .filter(|t| t.starts_with('/'))
            .and_then(|t| t.split_once(": "))
        {
            return self.error(Path::new(&format!("{shown}{name}")), rest);
        }
        // `file:430: …` (a reader's file and line): `line 430: …`, the file said once.
        if let Some((line, rest)) = text
            .strip_prefix(&shown)
            .and_then(|t| t.strip_prefix(':'))
            .and_then(|t| t.split_once(": "))
            .filter(|(n, _)| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
        {
            return self.error(file, format!("line {line}: {rest}"));
        }
        let message = text
            .strip_prefix(&shown)
            .and_then(|t| t.strip_prefix(": "))
            .map(str::to_string)
            .unwrap_or(text);
        self.error(file, message)
    }
}

/// How many files of `images/` not in the COLMAP model are listed one by one.
const MAX_LISTED: usize = 20;

/// Checks the scene folder `root` (module docs). Never fails: every problem is a finding.
pub fn check(root: &Path, opts: &CheckOptions) -> CheckReport {
    let t0 = std::time::Instant::now();
    let mut f = Findings(Vec::new());
    let mut report = CheckReport {
        scene: root.to_path_buf(),
        findings: Vec::new(),
        views: 0,
        images: 0,
        gaussians: 0,
        gml_files: 0,
        alignment: None,
        seconds: 0.0,
    };
    if !root.is_dir() {
        f.error(root, "not a directory (the scene folder: docs/design.md)");
        report.findings = f.0;
        return report;
    }
    let gml = gml_files(root, &mut f);
    report.gml_files = gml.len();
    let alignment = read_alignment(root, opts, &mut f);
    let views = read_views(root, &mut f);
    report.views = views.as_ref().map_or(0, Vec::len);
    // The images, the PLY and the CityGML files are read side by side, each into its own
    // findings, listed in this order.
    let ((images, fi), ((gaussians, fg), (models, fm))) = rayon::join(
        || {
            let mut f = Findings(Vec::new());
            (check_images(root, views.as_deref(), &mut f), f)
        },
        || {
            rayon::join(
                || {
                    let mut f = Findings(Vec::new());
                    (read_gaussians(root, &mut f), f)
                },
                || {
                    let mut f = Findings(Vec::new());
                    (read_citygml(&gml, &mut f), f)
                },
            )
        },
    );
    for part in [fi, fg, fm] {
        f.0.extend(part.0);
    }
    report.images = images;
    report.gaussians = gaussians.as_ref().map_or(0, Gaussians::len);
    optional_parts(root, views.as_deref(), &mut f);
    scene_meta(root, views.as_deref(), &mut f);
    if let (Some(models), Some(a)) = (&models, alignment) {
        let a = a.unwrap_or_else(|| local_alignment(models));
        if scene_frame(models, &a, &mut f)
            && let (Some(views), Some(g)) = (&views, &gaussians)
        {
            report.alignment = plausibility(root, views, g, models, &a, opts, &mut f);
        }
    }
    report.findings = f.0;
    report.seconds = t0.elapsed().as_secs_f64();
    report
}

/// `citymodel/*.gml` (and `*.xml`, CityJSON), sorted by name, each file once
/// (`scene::citymodel_files`, as `Scene::open` finds them).
fn gml_files(root: &Path, f: &mut Findings) -> Vec<PathBuf> {
    let cm = root.join("citymodel");
    let Ok((gml, twins)) = crate::scene::citymodel_files(&cm) else {
        f.error(
            &cm,
            "missing: the LoD3 CityGML model goes here (citymodel/*.gml)",
        );
        return Vec::new();
    };
    for (p, first) in twins {
        f.warn(
            &p,
            format!("the same file as {}: it is read once", first.display()),
        );
    }
    if gml.is_empty() {
        f.error(
            &cm,
            "holds no city model (.gml, .xml, .city.json, .city.jsonl: the CityGML or CityJSON model)",
        );
    }
    gml
}

/// `scene.json` (optional): readable, and its test views images of the COLMAP model; a note
/// says which split the run will use.
fn scene_meta(root: &Path, views: Option<&[View]>, f: &mut Findings) {
    let p = root.join(crate::scene::SceneMeta::FILE);
    let meta = match crate::scene::SceneMeta::read(root) {
        Ok(Some(m)) => m,
        Ok(None) => {
            f.note(
                &p,
                "absent: no declared test views, every view trains (`gs4city run --test-every N` holds every N-th back)",
            );
            return;
        }
        Err(e) => {
            f.error(&p, e.why);
            return;
        }
    };
    match (&meta.test_views, views) {
        (Some(names), Some(views)) => match crate::scene::Split::declared(views.to_vec(), names) {
            Ok(s) if s.train.is_empty() => {
                f.error(&p, "every view is a declared test view: nothing trains")
            }
            Ok(s) => f.note(
                &p,
                format!(
                    "{} declared test views, {} training views",
                    s.test.len(),
                    s.train.len()
                ),
            ),
            Err(why) => f.error(&p, why),
        },
        (None, _) => f.note(&p, "no declared test views: every view trains"),
        (Some(_), None) => {}
    }
}

/// `Some(Some(a))`: read; `Some(None)`: a local origin is asked for; `None`: unusable (or still
/// to be written).
fn read_alignment(root: &Path, opts: &CheckOptions, f: &mut Findings) -> Option<Option<Alignment>> {
    let p = root.join("citymodel/alignment.json");
    if !p.is_file() {
        if opts.local_origin {
            f.note(
                &p,
                "absent: the CityGML coordinates minus a local origin are the scene frame (--local-origin)",
            );
            return Some(None);
        }
        if opts.pending_alignment {
            f.note(
                &p,
                "absent: the next step writes it from ground-control points (`gs4city align --points pairs.csv --out <scene>/citymodel/alignment.json`; README, \"Run it on your own capture\")",
            );
            return None;
        }
        f.error(
            &p,
            "missing: the transform from the CityGML CRS to the 3DGS scene frame (README, \
             \"Run it on your own capture\": `gs4city align --points pairs.csv`), or run with --local-origin",
        );
        return None;
    }
    match Alignment::read(&p) {
        Ok(a) => Some(Some(a)),
        Err(e) => {
            f.error_of(&p, &e);
            None
        }
    }
}

/// The COLMAP model and its cameras.
fn read_views(root: &Path, f: &mut Findings) -> Option<Vec<View>> {
    let Some(sparse) = [root.join("sparse/0"), root.join("sparse")]
        .into_iter()
        .find(|p| p.join("images.bin").is_file() || p.join("images.txt").is_file())
    else {
        f.error(
            &root.join("sparse/0"),
            "missing: the COLMAP model the 3DGS scene was trained from (cameras, images: .bin or .txt)",
        );
        return None;
    };
    let views = match crate::colmap::read_model(&sparse) {
        Ok(v) => v,
        Err(e) => {
            f.error_of(&sparse, &e);
            return None;
        }
    };
    if views.is_empty() {
        f.error(&sparse, "the COLMAP model holds no images");
        return None;
    }
    let mut ok = true;
    // Every per-view file is named by the image's stem: two images with one (a rig's
    // `camA/x.png` and `camB/x.png`) would overwrite each other's outputs.
    let clashes = crate::camera::stem_problems(&views);
    for (name, why) in clashes.iter().take(MAX_LISTED) {
        f.error(
            &sparse,
            format!(
                "image {name}: {why}; rename one of them (in the COLMAP model and in images/), \
                 e.g. with its folder in the name"
            ),
        );
    }
    if clashes.len() > MAX_LISTED {
        f.error(
            &sparse,
            format!(
                "{} more images share a file stem",
                clashes.len() - MAX_LISTED
            ),
        );
    }
    ok &= clashes.is_empty();
    for v in &views {
        if let Err(e) = v.camera.validate() {
            f.error(
                &sparse,
                format!("image {} (camera {}): {e}", v.name, v.camera_id),
            );
            ok = false;
        }
    }
    ok.then_some(views)
}

/// Every regular file under `dir`, relative, sorted (hidden files skipped).
fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![PathBuf::new()];
    while let Some(rel) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(dir.join(&rel)) else {
            continue;
        };
        for e in rd.flatten() {
            let name = e.file_name();
            if name.to_string_lossy().starts_with('.') {
                continue;
            }
            let r = rel.join(&name);
            let p = dir.join(&r);
            if p.is_dir() {
                stack.push(r);
            } else if p.is_file() {
                out.push(r);
            }
        }
    }
    out.sort();
    out
}

/// The size a PNG or JPEG file declares (reads a growing prefix).
fn image_size(p: &Path) -> Option<(u32, u32)> {
    use std::io::Read;
    let mut file = std::fs::File::open(p).ok()?;
    let mut buf = vec![0u8; 1 << 16];
    let n = file.read(&mut buf).ok()?;
    buf.truncate(n);
    if let Some(s) = crate::imageio::declared_size(&buf) {
        return Some(s);
    }
    // A JPEG with a large EXIF block: read it all.
    file.read_to_end(&mut buf).ok()?;
    crate::imageio::declared_size(&buf)
}

/// Why a PNG or JPEG whose header reads well looks cut short (a partial copy or download):
/// a PNG ends with its `IEND` chunk, a JPEG with an end-of-image marker (`FF D9`, searched
/// in the last 4 KiB, since cameras may append bytes after it). Reads the file's tail only.
fn truncated(p: &Path) -> Option<String> {
    use std::io::{Read, Seek, SeekFrom};
    let mut file = std::fs::File::open(p).ok()?;
    let len = file.metadata().ok()?.len();
    let mut head = [0u8; 8];
    file.read_exact(&mut head).ok()?;
    let tail_len = len.min(4096);
    file.seek(SeekFrom::Start(len - tail_len)).ok()?;
    let mut tail = Vec::with_capacity(tail_len as usize);
    file.read_to_end(&mut tail).ok()?;
    let grey = "mask overlays and report.html show a grey panel for it";
    if head == *b"\x89PNG\r\n\x1a\n" {
        const IEND: [u8; 12] = [0, 0, 0, 0, b'I', b'E', b'N', b'D', 0xAE, 0x42, 0x60, 0x82];
        return (!tail.ends_with(&IEND)).then(|| {
            format!("truncated: a PNG ends with its IEND chunk and this one ({len} bytes) does not; {grey}")
        });
    }
    if head.starts_with(&[0xFF, 0xD8]) {
        return (!tail.windows(2).any(|w| w == [0xFF, 0xD9])).then(|| {
            format!("truncated: no JPEG end-of-image marker in its last {tail_len} bytes; {grey}")
        });
    }
    None
}

/// One view's image in `dir` (listed in `present`): its presence, declared size and tail.
fn check_image(dir: &Path, v: &View, present: &BTreeSet<&PathBuf>, f: &mut Findings) {
    let p = dir.join(&v.name);
    if !present.contains(&PathBuf::from(&v.name)) {
        f.error(
            &p,
            format!(
                "missing: the COLMAP model names image {} (id {}) but images/ has no such file",
                v.name, v.image_id
            ),
        );
        return;
    }
    let k = &v.camera.intrinsics;
    match image_size(&p) {
        Some((w, h)) if (w, h) != (k.width, k.height) => f.error(
            &p,
            format!(
                "{w}×{h} pixels, but its COLMAP camera {} is {}×{} (images resized after \
                 reconstruction? use the images the model was made from)",
                v.camera_id, k.width, k.height
            ),
        ),
        Some(_) => {
            if let Some(why) = truncated(&p) {
                f.warn(&p, why);
            }
        }
        None => f.warn(
            &p,
            "not a PNG or JPEG whose size can be read from its header",
        ),
    }
}

/// `images/` against the COLMAP names and camera sizes; returns the number of images found.
fn check_images(root: &Path, views: Option<&[View]>, f: &mut Findings) -> usize {
    let dir = root.join("images");
    if !dir.is_dir() {
        f.warn(
            &dir,
            "missing: the run needs no pixels, but mask overlays and report.html show grey \
             panels instead of the photos (link the images/ folder 3DGS was trained from)",
        );
        return 0;
    }
    let files = files_under(&dir);
    let Some(views) = views else {
        return files.len();
    };
    let named: BTreeSet<PathBuf> = views.iter().map(|v| PathBuf::from(&v.name)).collect();
    let present: BTreeSet<&PathBuf> = files.iter().collect();
    // Each view's image read in parallel, its findings listed in view order.
    let per_view: Vec<Findings> = {
        use rayon::prelude::*;
        views
            .par_iter()
            .map(|v| {
                let mut f = Findings(Vec::new());
                check_image(&dir, v, &present, &mut f);
                f
            })
            .collect()
    };
    for part in per_view {
        f.0.extend(part.0);
    }
    let extra: Vec<&PathBuf> = files.iter().filter(|p| !named.contains(*p)).collect();
    for p in extra.iter().take(MAX_LISTED) {
        f.error(
            &dir.join(p),
            "not in the COLMAP model (renamed, or not registered by COLMAP): every image of \
             images/ must be named in sparse/0/images.*; move it out of images/",
        );
    }
    if extra.len() > MAX_LISTED {
        f.error(
            &dir,
            format!(
                "{} more files are not in the COLMAP model",
                extra.len() - MAX_LISTED
            ),
        );
    }
    files.len()
}

/// The PLY: header, payload, per-Gaussian values.
fn read_gaussians(root: &Path, f: &mut Findings) -> Option<Gaussians> {
    let p = root.join("point_cloud.ply");
    if !p.is_file() {
        f.error(
            &p,
            "missing: the pre-trained 3DGS scene (INRIA layout; from a training output: \
             point_cloud/iteration_N/point_cloud.ply, see `gs4city scene import`)",
        );
        return None;
    }
    let (g, r) = match crate::splat::read_ply(&p, &ReadOptions::KEEP) {
        Ok(x) => x,
        Err(e) => {
            f.error_of(&p, &e);
            return None;
        }
    };
    if g.is_empty() {
        f.error(&p, "holds no Gaussians (vertex count 0)");
        return None;
    }
    let first = r.invalid_examples.first().cloned().unwrap_or_default();
    if r.kept_non_finite_position > 0 {
        f.error(
            &p,
            format!(
                "{} of {} Gaussians have a non-finite position (NaN or infinite x, y, z; the \
                 export is broken), first: {first}",
                r.kept_non_finite_position,
                g.len()
            ),
        );
        return None;
    }
    if r.kept_invalid == g.len() {
        f.error(
            &p,
            format!(
                "none of the {} Gaussians can be drawn (every one is invalid: nothing to render \
                 or label), first: {first}",
                g.len()
            ),
        );
        return None;
    }
    if r.kept_invalid > 0 {
        f.warn(
            &p,
            format!(
                "{} of {} Gaussians are invalid (kept in place, never drawn, labelled −1 in \
                 semantic.ply), first: {first}",
                r.kept_invalid,
                g.len()
            ),
        );
    }
    Some(g)
}

/// Every CityGML file: parse errors, reader warnings, gml:ids of city objects repeated across
/// files. `None` when a file cannot be read.
fn read_citygml(gml: &[PathBuf], f: &mut Findings) -> Option<Vec<CityModel>> {
    use rayon::prelude::*;
    let mut models = Vec::with_capacity(gml.len());
    let mut ok = !gml.is_empty();
    // Parsed in parallel, reported in file order.
    let parsed: Vec<_> = gml
        .par_iter()
        .map(|p| crate::cityjson::read_any(p))
        .collect();
    for (p, parsed) in gml.iter().zip(parsed) {
        match parsed {
            Ok(m) => {
                for w in &m.warnings {
                    let id =
                        w.id.as_deref()
                            .map(|i| format!("gml:id {i}: "))
                            .unwrap_or_default();
                    f.warn(p, format!("line {}: {id}{}", w.line, w.message));
                }
                for poly in m
                    .used_polygons()
                    .filter(|q| q.points() > crate::citygml::MAX_POLYGON_POINTS)
                {
                    f.warn(
                        p,
                        format!(
                            "line {}: {}: {} points, more than the {} a polygon may have: the \
                             citymodel stage skips it",
                            poly.line,
                            poly.name(),
                            poly.points(),
                            crate::citygml::MAX_POLYGON_POINTS
                        ),
                    );
                }
                if m.used_polygons().next().is_none() {
                    f.error(
                        p,
                        "no building geometry the pipeline can use (no polygon of a building, \
                         its surfaces or openings in LoD 1–3)",
                    );
                    ok = false;
                }
                models.push(m);
            }
            Err(e) => {
                f.error_of(p, &e);
                ok = false;
            }
        }
    }
    for w in crate::citygml::disambiguate(&mut models) {
        f.warn(
            Path::new(&w.file),
            format!(
                "line {}: gml:id {}: {}",
                w.line,
                w.id.as_deref().unwrap_or(""),
                w.message
            ),
        );
    }
    ok.then_some(models)
}

/// masks/ and features/: notes on what the run will use, and every SAM list, feature array
/// and prompts file read as the masks stage reads them (each problem an error naming its
/// file; [`MAX_LISTED`] of them, then a count).
fn optional_parts(root: &Path, views: Option<&[View]>, f: &mut Findings) {
    use rayon::prelude::*;
    let masks = root.join("masks");
    let features = root.join("features");
    if !masks.is_dir() {
        f.note(
            &masks,
            "absent: the masks stage uses the mask-free source (components of the 3DGS scene in \
             front of the city model); README, \"Masks and features\"",
        );
        return;
    }
    if !features.is_dir() {
        f.note(
            &features,
            "absent: masks are associated by geometry alone, and text queries are not available",
        );
    }
    let Some(views) = views else { return };
    let with: Vec<&View> = views
        .iter()
        .filter(|v| masks.join(format!("{}.json", v.stem())).is_file())
        .collect();
    f.note(
        &masks,
        format!("SAM lists for {} of {} views", with.len(), views.len()),
    );
    if let Some(v) = views
        .iter()
        .find(|v| !masks.join(format!("{}.json", v.stem())).is_file())
    {
        f.warn(
            &masks,
            format!(
                "no SAM list for {} of {} views (first: {}.json): the masks stage stops at a \
                 training view without one",
                views.len() - with.len(),
                views.len(),
                v.stem()
            ),
        );
    }
    // The prompts decide whether features are read, and their dimension.
    let prompts = features.join("prompts.json");
    let dim = if prompts.is_file() {
        match crate::sam::read_prompts_json(&prompts) {
            Ok(p) => Some(p.dim),
            Err(e) => {
                f.error_of(&prompts, &e);
                None
            }
        }
    } else {
        None
    };
    let problems: Vec<(PathBuf, String)> = with
        .par_iter()
        .flat_map_iter(|v| {
            let stem = v.stem();
            let k = &v.camera.intrinsics;
            let list = masks.join(format!("{stem}.json"));
            let size = [k.height as usize, k.width as usize];
            let mut out = Vec::new();
            match crate::sam::read_sam_json_sized(&list, Some(size)) {
                Err(e) => out.push((list, e.to_string())),
                Ok(sam) => {
                    if let Some(dim) = dim {
                        let npy = features.join(format!("{stem}.npy"));
                        if let Err(e) =
                            crate::sam::read_view_features(&npy, sam.len(), dim, &prompts)
                        {
                            out.push((npy, e.to_string()));
                        }
                    }
                }
            }
            out
        })
        .collect();
    for (file, why) in problems.iter().take(MAX_LISTED) {
        f.error_of(file, why);
    }
    if problems.len() > MAX_LISTED {
        f.error(
            &masks,
            format!(
                "{} more problems in masks/ and features/",
                problems.len() - MAX_LISTED
            ),
        );
    }
}

/// Every used polygon's vertices inside the scene frame once aligned, as `citymodel` requires
/// (`camera::outside_scene_frame`; non-finite coordinates are the triangulator's to skip):
/// the first polygon of each file that leaves it is an error. Whether all are inside.
fn scene_frame(models: &[CityModel], a: &Alignment, f: &mut Findings) -> bool {
    let mut ok = true;
    for m in models {
        let bad = m.used_polygons().find_map(|p| {
            std::iter::once(&p.exterior)
                .chain(&p.interiors)
                .flat_map(|r| &r.points)
                .filter(|q| q.is_finite())
                .find_map(|q| crate::camera::outside_scene_frame(a.apply(*q)))
                .map(|why| (p, why))
        });
        if let Some((p, why)) = bad {
            let line = if p.line > 0 {
                format!("line {}: ", p.line)
            } else {
                String::new()
            };
            f.error(&m.path, format!("{line}{}: {why}", p.name()));
            ok = false;
        }
    }
    ok
}

/// The local origin `citymodel` uses without an alignment: the whole-metre minimum corner.
fn local_alignment(models: &[CityModel]) -> Alignment {
    let mut lo = DVec3::splat(f64::INFINITY);
    for m in models {
        for p in m.used_polygons() {
            for q in p.exterior.points.iter().filter(|q| q.is_finite()) {
                lo = lo.min(*q);
            }
        }
    }
    Alignment::local(if lo.is_finite() {
        lo.floor()
    } else {
        DVec3::ZERO
    })
}

/// The used polygons' exterior rings in the scene frame, fan-triangulated (those the
/// citymodel stage skips as too long are left out).
fn fan_mesh(models: &[CityModel], a: &Alignment) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let (mut vertices, mut faces) = (Vec::new(), Vec::new());
    for m in models {
        for p in m.used_polygons() {
            let pts = &p.exterior.points;
            if pts.len() < 3
                || p.points() > crate::citygml::MAX_POLYGON_POINTS
                || pts.iter().any(|q| !q.is_finite())
            {
                continue;
            }
            let base = vertices.len() as u32;
            vertices.extend(pts.iter().map(|&q| a.apply(q).as_vec3().to_array()));
            for i in 1..pts.len() as u32 - 1 {
                faces.push([base, base + i, base + i + 1]);
            }
        }
    }
    (vertices, faces)
}

/// The alignment's plausibility (module docs).
fn plausibility(
    root: &Path,
    views: &[View],
    g: &Gaussians,
    models: &[CityModel],
    a: &Alignment,
    opts: &CheckOptions,
    f: &mut Findings,
) -> Option<AlignmentCheck> {
    let file = root.join("citymodel/alignment.json");
    let (vertices, faces) = fan_mesh(models, a);
    if faces.is_empty() || vertices.iter().flatten().any(|c| !c.is_finite()) {
        return None;
    }
    // Views in which the model projects inside the image.
    let step = vertices.len().div_ceil(5000).max(1);
    let seeing = views
        .iter()
        .filter(|v| {
            let k = &v.camera.intrinsics;
            vertices.iter().step_by(step).any(|q| {
                let p = DVec3::from(q.map(f64::from));
                v.camera
                    .project(v.camera.pose.world_to_camera(p))
                    .is_some_and(|px| {
                        px.x >= 0.0
                            && px.y >= 0.0
                            && px.x < f64::from(k.width)
                            && px.y < f64::from(k.height)
                    })
            })
        })
        .count();
    // Distances of opaque Gaussian centres to the model.
    let device = match crate::embree::Device::new() {
        Ok(d) => d,
        Err(e) => {
            f.warn(
                &file,
                format!("the distance check needs Embree, which failed: {e}"),
            );
            return None;
        }
    };
    let committed = crate::embree::Scene::new(&device).and_then(|mut s| {
        s.add_triangles(&vertices, &faces)?;
        s.commit()
    });
    let scene = match committed {
        Ok(s) => s,
        Err(e) => {
            f.warn(&file, format!("the distance check failed in Embree: {e}"));
            return None;
        }
    };
    let opaque: Vec<usize> = (0..g.len())
        .filter(|&i| crate::splat::ply::is_valid(g, i) && g.activated_opacity(i) >= 0.5)
        .collect();
    let step = opaque.len().div_ceil(opts.max_samples).max(1);
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for q in &vertices {
        let q = DVec3::from(q.map(f64::from));
        (lo, hi) = (lo.min(q), hi.max(q));
    }
    for v in views {
        let c = v.camera.pose.center();
        (lo, hi) = (lo.min(c), hi.max(c));
    }
    let cap = 10.0 * (hi - lo).length().max(1.0);
    let mut d: Vec<f64> = opaque
        .iter()
        .step_by(step)
        .map(|&i| {
            let p = g.positions[i].map(f64::from);
            scene.closest_point(p, cap).map_or(cap, |h| h.distance)
        })
        .collect();
    if d.is_empty() {
        f.warn(
            &file,
            "no opaque Gaussian (opacity ≥ 0.5): the distance check is skipped",
        );
        return None;
    }
    d.sort_by(f64::total_cmp);
    let median = d[d.len() / 2] / a.scale;
    let quartile = d[d.len() / 4] / a.scale;
    let share = seeing as f64 / views.len() as f64;
    let plausible = quartile <= opts.max_offset_m && share >= opts.min_view_share;
    let facts = format!(
        "the city model projects into {seeing} of {} views; distance of {} opaque Gaussian \
         centres to the nearest city-model surface: lower quartile {quartile:.2} m, median \
         {median:.2} m",
        views.len(),
        d.len()
    );
    if plausible {
        f.note(&file, format!("alignment plausible: {facts}"));
    } else {
        let reach = crate::alignment::REFINE_REACH_M;
        let s = root.display();
        // The advice the next command follows. The refinement's first search radius is its
        // reach: it needs Gaussians within it of the surface they belong to. Half of the opaque
        // centres within it (the median) is where it was measured to recover the alignment
        // (SIMULATED small preset: shifts up to 4 m along a facade, 8 m diagonally, median
        // ≤ 2.8 m / 4.6 m; refused from 5 m along a facade, median 3.4 m; docs/capture.md);
        // the lower quartile underestimates a shift along the facades by a factor of about
        // three, so it does not decide this.
        let fix = if median <= reach && share >= opts.min_view_share {
            format!(
                "half of the opaque Gaussian centres lie within the reach of `gs4city align \
                 --refine` ({reach} m, its first search radius): refine it (`gs4city run --scene \
                 {s} --out R --refine-alignment`, or `gs4city align --refine --citymodel \
                 {s}/citymodel --ply {s}/point_cloud.ply --colmap {s}/sparse/0 --out \
                 A/alignment.json`)"
            )
        } else {
            format!(
                "beyond the reach of `gs4city align --refine` (its first search radius is \
                 {reach} m; the median distance is {median:.1} m): collect ground-control points \
                 again (`gs4city view --scene {s}` gives a clicked point's scene coordinates) and \
                 `gs4city align --points pairs.csv --out {s}/citymodel/alignment.json` (README, \
                 \"Run it on your own capture\")"
            )
        };
        let msg = format!(
            "alignment looks off by ~{:.0} m ({facts}; plausible: a lower quartile ≤ {} m \
                 and ≥ {:.0} % of views); {fix}",
            quartile.max(0.5),
            opts.max_offset_m,
            100.0 * opts.min_view_share
        );
        if opts.refine_next {
            f.warn(&file, msg);
        } else {
            f.error(&file, msg);
        }
    }
    Some(AlignmentCheck {
        views: views.len(),
        views_seeing_model: seeing,
        gaussians_measured: d.len(),
        quartile_distance_m: quartile,
        median_distance_m: median,
        plausible,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_reader_error_names_its_file_once() {
        let mut f = Findings(Vec::new());
        let p = Path::new("S/citymodel/a.gml");
        f.error_of(
            p,
            &"S/citymodel/a.gml:430: file ends inside 12 open element(s)",
        );
        f.error_of(p, &"S/citymodel/a.gml: not a CityGML file");
        f.error_of(
            Path::new("S/sparse/0"),
            &"S/sparse/0/images.txt:5: bad pose",
        );
        f.error_of(p, &"something else entirely");
        let shown: Vec<String> =
            f.0.iter()
                .map(|x| format!("{}: {}", x.file.display(), x.message))
                .collect();
        assert_eq!(
            shown,
            [
                "S/citymodel/a.gml: line 430: file ends inside 12 open element(s)",
                "S/citymodel/a.gml: not a CityGML file",
                "S/sparse/0/images.txt:5: bad pose",
                "S/citymodel/a.gml: something else entirely",
            ]
        );
    }
}
