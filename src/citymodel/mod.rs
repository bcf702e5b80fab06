//! The `citymodel` stage: CityGML files → hierarchy table (`semantics.json`) → triangulated,
//! aligned mesh with per-face `(feature, surface, part)` ids (`mesh.ply`) → `summary.json`.
pub mod triangulate;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::alignment::{AlignError, Alignment};
use crate::camera::outside_scene_frame;
use crate::citygml::{self, CityGmlError, CityModel, Class};
use crate::cityjson::{self, CityJsonError};
use crate::fsutil::{self, FsError};
use crate::mesh::{MeshError, TriMesh};
use crate::semantics::{self, Entity, SemanticsError};
use triangulate::{Repair, SkipReason};

/// Errors of the citymodel stage.
#[derive(Debug, thiserror::Error)]
pub enum CityModelError {
    #[error(transparent)]
    CityGml(#[from] CityGmlError),
    #[error(transparent)]
    CityJson(#[from] CityJsonError),
    #[error(transparent)]
    Align(#[from] AlignError),
    #[error(transparent)]
    Mesh(#[from] MeshError),
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error(transparent)]
    Semantics(#[from] SemanticsError),
    #[error("no city-model input files (CityGML or CityJSON)")]
    NoInput,
    #[error("{path}: {why}")]
    Input { path: PathBuf, why: String },
    #[error("{}: {polygon}: {why}", at_line(path, *line))]
    Frame {
        path: PathBuf,
        line: u64,
        polygon: String,
        why: String,
    },
    #[error("no polygon of {files} could be triangulated: nothing to write ({why})")]
    Empty { files: String, why: String },
}

/// `path:line`, or `path` where there is no line (CityJSON: line 0).
fn at_line(path: &Path, line: u64) -> String {
    match line {
        0 => path.display().to_string(),
        l => format!("{}:{l}", path.display()),
    }
}

/// A polygon that produced no triangles.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Skipped {
    pub file: String,
    pub line: u64,
    pub polygon: Option<String>,
    pub object: String,
    pub reason: String,
}

/// Options of the stage.
#[derive(Debug, Clone, Default)]
pub struct Options {
    /// Georeferenced → scene transform; `None`: subtract a local origin only.
    pub alignment: Option<Alignment>,
}

/// Everything the stage computed (also written to disk by [`write()`]).
pub struct Output {
    pub mesh: TriMesh,
    pub entities: Vec<Entity>,
    pub summary: CitymodelSummary,
    pub alignment: Alignment,
}

/// The CityGML files found by [`collect_files`] and what the search noticed.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct InputFiles {
    /// Files in a reproducible order: inputs in the order given, each folder's files sorted.
    pub files: Vec<PathBuf>,
    /// Sentences about inputs that were skipped or read once although named twice.
    pub warnings: Vec<String>,
}

/// Expands `inputs` into city-model files: files as given, folders searched recursively for
/// CityGML (`*.gml` / `*.xml`) and CityJSON (`*.city.json`, `*.jsonl`, other `*.json` that
/// declare `"type": "CityJSON"`; see [`cityjson::is_model_file`]), case-insensitive. Symbolic links are followed, but a folder is
/// searched once (by canonical path), so link loops and links to `.` cannot recurse; a
/// file reached twice (named twice, or through a link) is read once, with a warning.
/// Missing inputs and folders without CityGML files are errors.
pub fn collect_files(inputs: &[PathBuf]) -> Result<InputFiles, CityModelError> {
    let mut out = InputFiles::default();
    let mut seen_files: BTreeMap<PathBuf, PathBuf> = BTreeMap::new();
    let mut seen_dirs: BTreeMap<PathBuf, PathBuf> = BTreeMap::new();
    let input_err = |path: &Path, why: String| CityModelError::Input {
        path: path.to_path_buf(),
        why,
    };
    for input in inputs {
        let meta = std::fs::metadata(input)
            .map_err(|e| input_err(input, format!("cannot use this input: {e}")))?;
        let mut found = Vec::new();
        if meta.is_dir() {
            let searched = walk_dir(input, &mut seen_dirs, &mut found, &mut out.warnings)?;
            if searched && found.is_empty() {
                return Err(input_err(
                    input,
                    "no city-model files (.gml, .xml, .city.json, .city.jsonl) below this folder"
                        .into(),
                ));
            }
            found.sort();
        } else {
            found.push(input.clone());
        }
        for f in found {
            let canon = std::fs::canonicalize(&f)
                .map_err(|e| input_err(&f, format!("cannot resolve this path: {e}")))?;
            match seen_files.get(&canon) {
                Some(first) => out.warnings.push(format!(
                    "{} is the same file as {}: it is read once",
                    f.display(),
                    first.display()
                )),
                None => {
                    seen_files.insert(canon, f.clone());
                    out.files.push(f);
                }
            }
        }
    }
    if out.files.is_empty() {
        return Err(CityModelError::NoInput);
    }
    Ok(out)
}

/// Searches `dir` unless its canonical path was searched already; returns whether it was.
fn walk_dir(
    dir: &Path,
    seen_dirs: &mut BTreeMap<PathBuf, PathBuf>,
    out: &mut Vec<PathBuf>,
    warnings: &mut Vec<String>,
) -> Result<bool, CityModelError> {
    let err = |path: &Path, e: std::io::Error| CityModelError::Input {
        path: path.to_path_buf(),
        why: format!("cannot list this folder: {e}"),
    };
    let canon = std::fs::canonicalize(dir).map_err(|e| err(dir, e))?;
    if let Some(first) = seen_dirs.get(&canon) {
        warnings.push(format!(
            "{} leads to {}, which is already searched (a symbolic-link loop or a second link): skipped",
            dir.display(),
            first.display()
        ));
        return Ok(false);
    }
    seen_dirs.insert(canon, dir.to_path_buf());
    let mut entries = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| err(dir, e))? {
        entries.push(entry.map_err(|e| err(dir, e))?.path());
    }
    entries.sort();
    for path in entries {
        match std::fs::metadata(&path) {
            Ok(m) if m.is_dir() => {
                walk_dir(&path, seen_dirs, out, warnings)?;
            }
            Ok(_) => {
                if cityjson::is_model_file(&path) {
                    out.push(path);
                }
            }
            Err(e) => warnings.push(format!("{} cannot be read ({e}): skipped", path.display())),
        }
    }
    Ok(true)
}

/// One input file in [`CitymodelSummary`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileSummary {
    pub path: String,
    pub citygml: String,
    pub srs_name: Option<String>,
    pub bytes: u64,
    pub objects: usize,
    pub polygons: usize,
}

/// Polygons that produced no triangles.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SkippedSummary {
    pub count: usize,
    pub by_reason: BTreeMap<String, usize>,
    pub polygons: Vec<Skipped>,
}

/// A polygon whose vertices lie farther than this from their plane (the plane through their
/// centroid with the exterior ring's Newell normal), in the file's units (metres in a projected
/// CRS), gets a warning: val3dity's default distance-to-plane tolerance (`planarity_d2p`), the
/// usual limit of CityGML validation. Such a polygon is still triangulated; its triangles follow
/// its vertices. (The CityJSON reader refuses a folded surface outright, farther than
/// `cityjson::PLANARITY_TOLERANCE` of its extent and `cityjson::PLANARITY_MIN`; a
/// CityGML file keeps such a polygon with this warning.)
pub const PLANARITY_WARNING: f64 = 0.01;

/// The largest deviation of a polygon from its plane, and how many polygons exceed
/// [`PLANARITY_WARNING`].
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Planarity {
    pub metres: f64,
    pub polygon: String,
    /// Triangulated polygons farther than [`PLANARITY_WARNING`] from their plane (each one
    /// named in the warnings).
    #[serde(default)]
    pub beyond_tolerance: usize,
}

/// xlink statistics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Xlinks {
    pub shared: usize,
    pub adopted: usize,
    pub dangling: usize,
}

/// Warnings, as sentences.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Warnings {
    pub count: usize,
    pub items: Vec<String>,
}

/// The alignment used, as in `alignment.json`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AlignmentRecord {
    pub origin: [f64; 3],
    pub scale: f64,
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
}

impl From<&Alignment> for AlignmentRecord {
    fn from(a: &Alignment) -> Self {
        AlignmentRecord {
            origin: a.origin.to_array(),
            scale: a.scale,
            rotation: a.rotation_rows(),
            translation: a.translation.to_array(),
        }
    }
}

/// Timing of the stage.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CitymodelTiming {
    pub parse_s: f64,
    pub parse_mb_per_s: f64,
    pub triangulate_s: f64,
}

/// The stage's `summary.json` (`docs/design.md`: counts, skipped polygons with reasons, warnings).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CitymodelSummary {
    pub files: Vec<FileSummary>,
    pub buildings: usize,
    pub building_parts: usize,
    pub installations: usize,
    /// Count per thematic surface class.
    pub surfaces: BTreeMap<String, usize>,
    pub surfaces_total: usize,
    pub windows: usize,
    pub doors: usize,
    pub entities: usize,
    pub polygons: usize,
    pub polygons_used: usize,
    pub polygons_unused: usize,
    pub holes: usize,
    pub holes_used: usize,
    pub triangles: usize,
    pub vertices: usize,
    pub skipped: SkippedSummary,
    pub repairs: BTreeMap<String, usize>,
    pub max_planarity_deviation: Planarity,
    pub curves_skipped: usize,
    pub implicit_geometries_skipped: usize,
    pub xlinks: Xlinks,
    pub unknown_elements: BTreeMap<String, usize>,
    pub warnings: Warnings,
    /// `None` without an alignment file: a local origin only (then the scene frame is metres).
    pub alignment: AlignmentRecord,
    /// Whether the alignment was given (`alignment.json` or point pairs) rather than a local origin.
    pub alignment_given: bool,
    /// The point pairs the alignment was estimated from, with residuals (`--align-points`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimated_from: Option<serde_json::Value>,
    pub timing: CitymodelTiming,
}

impl crate::layout::Summary for CitymodelSummary {}

/// Per-polygon triangulation outcome, for cross-checks (e.g. against CGAL).
#[derive(Debug, Clone)]
pub struct PolygonResult {
    pub ordinal: usize,
    pub id: Option<String>,
    pub result: Result<(usize, f64), SkipReason>,
    pub planarity: f64,
}

/// Triangulates every patch of a file in document order (whether the mesh uses it or not),
/// in a local frame (first exterior vertex subtracted).
pub fn triangulate_all(model: &CityModel) -> Vec<PolygonResult> {
    model
        .polygons
        .par_iter()
        .map(|p| {
            let o = p.exterior.points.first().copied().unwrap_or(DVec3::ZERO);
            let ext: Vec<DVec3> = p.exterior.points.iter().map(|q| *q - o).collect();
            let holes: Vec<Vec<DVec3>> = p
                .interiors
                .iter()
                .map(|r| r.points.iter().map(|q| *q - o).collect())
                .collect();
            let t = triangulate::triangulate(&ext, &holes);
            PolygonResult {
                ordinal: p.ordinal,
                id: p.id.clone(),
                planarity: t.as_ref().map(|t| t.planarity).unwrap_or(0.0),
                result: t.map(|t| (t.triangles.len(), t.area)),
            }
        })
        .collect()
}

/// Reads, flattens, triangulates and aligns the given CityGML / CityJSON files.
pub fn run(files: &[PathBuf], opts: &Options) -> Result<Output, CityModelError> {
    if files.is_empty() {
        return Err(CityModelError::NoInput);
    }
    let t0 = Instant::now();
    let mut models: Vec<CityModel> = files
        .par_iter()
        .map(|f| cityjson::read_any(f))
        .collect::<Result<_, _>>()?;
    let t_parse = t0.elapsed().as_secs_f64();

    // Hierarchy table: entity ids are global, in file order then document order; an id that
    // two files use names two objects, the later one renamed `id~n`.
    let cross_file_duplicates: Vec<String> = citygml::disambiguate(&mut models)
        .iter()
        .map(ToString::to_string)
        .collect();
    let mut entities: Vec<Entity> = Vec::new();
    let mut base = Vec::with_capacity(models.len());
    for m in &models {
        base.push(entities.len() as i32);
        let b = *base.last().unwrap_or(&0);
        let source = m.path.display().to_string();
        let mut root = vec![0i32; m.objects.len()];
        for (i, o) in m.objects.iter().enumerate() {
            root[i] = match o.parent {
                Some(p) => root[p],
                None => b + i as i32,
            };
            entities.push(Entity {
                id: b + i as i32,
                object_id: o.object_id.clone(),
                class: o.class,
                level: o.class.level(),
                parent: o.parent.map(|p| b + p as i32),
                building: root[i],
                source: source.clone(),
                lod: o.lod_used,
                attributes: o.attributes.clone(),
            });
        }
    }

    // Alignment: given, or a local origin at the bounding-box minimum (whole metres).
    let mut warnings: Vec<String> = cross_file_duplicates;
    let alignment = match opts.alignment {
        Some(a) => a,
        None => {
            warnings.push(
                "no alignment given: the mesh is in a local frame (CityGML coordinates minus a whole-metre origin), not in the frame of any camera model".into(),
            );
            let mut lo = DVec3::splat(f64::INFINITY);
            for m in &models {
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
    };

    // Triangulate used polygons (parallel), then assemble the mesh in a fixed order.
    let t1 = Instant::now();
    struct Job<'a> {
        file: usize,
        poly: &'a citygml::Polygon,
        label: crate::mesh::FaceLabel,
    }
    let mut jobs = Vec::new();
    let labels = semantics::chains(&entities);
    for (fi, m) in models.iter().enumerate() {
        for p in m.used_polygons() {
            // Every vertex must land inside the scene frame before the triangulator sees it:
            // a vertex far outside (a mistyped exponent) leaves the rest of its polygon
            // without precision in the plane, where constrained triangulation is not robust.
            for q in std::iter::once(&p.exterior)
                .chain(&p.interiors)
                .flat_map(|r| &r.points)
            {
                let s = alignment.apply(*q);
                // A non-finite coordinate is the triangulator's to skip (with its reason).
                if !q.is_finite() {
                    continue;
                }
                if let Some(why) = outside_scene_frame(s) {
                    return Err(CityModelError::Frame {
                        path: m.path.clone(),
                        line: p.line,
                        polygon: p.name(),
                        why,
                    });
                }
            }
            let owner = p.owner.expect("used polygons have owners");
            jobs.push(Job {
                file: fi,
                poly: p,
                label: labels[base[fi] as usize + owner],
            });
        }
    }
    let results: Vec<_> = jobs
        .par_iter()
        .map(|j| {
            let ext: Vec<DVec3> = j
                .poly
                .exterior
                .points
                .iter()
                .map(|q| *q - alignment.origin)
                .collect();
            let holes: Vec<Vec<DVec3>> = j
                .poly
                .interiors
                .iter()
                .map(|r| r.points.iter().map(|q| *q - alignment.origin).collect())
                .collect();
            triangulate::triangulate(&ext, &holes)
        })
        .collect();
    let t_tri = t1.elapsed().as_secs_f64();

    let mut mesh = TriMesh::default();
    let mut skipped: Vec<Skipped> = Vec::new();
    let mut repairs: BTreeMap<&'static str, usize> = BTreeMap::new();
    let mut planarity = Planarity::default();
    let mut holes_used = 0usize;
    for (job, res) in jobs.iter().zip(results) {
        let m = &models[job.file];
        let object = &m.objects[job.poly.owner.expect("owned")];
        match res {
            Err(reason) => skipped.push(Skipped {
                file: m.path.display().to_string(),
                line: job.poly.line,
                polygon: job.poly.id.clone(),
                object: object.object_id.clone(),
                reason: reason.to_string(),
            }),
            Ok(t) => {
                holes_used += job.poly.interiors.len();
                if t.planarity > planarity.metres {
                    planarity.metres = t.planarity;
                    planarity.polygon = format!("{} in {}", job.poly.label(), m.path.display());
                }
                if t.planarity > PLANARITY_WARNING {
                    planarity.beyond_tolerance += 1;
                    warnings.push(format!(
                        "{}:{}: {}: its vertices lie up to {:.3} from their plane (tolerance {PLANARITY_WARNING}, in the file's units): triangulated, its triangles following the vertices",
                        m.path.display(),
                        job.poly.line,
                        job.poly.name(),
                        t.planarity,
                    ));
                }
                for r in &t.repairs {
                    let key = match r {
                        Repair::DuplicatePoints(_) => "duplicate_points_removed",
                        Repair::DegenerateHole(_) => "degenerate_holes_dropped",
                        Repair::HoleNotInside { .. } => "holes_not_inside_dropped",
                        Repair::SelfIntersection => "self_intersections_split",
                    };
                    *repairs.entry(key).or_default() += 1;
                    if !matches!(r, Repair::DuplicatePoints(_)) {
                        warnings.push(format!(
                            "{}:{}: {}: {r}",
                            m.path.display(),
                            job.poly.line,
                            job.poly.name(),
                        ));
                    }
                }
                let base_v = mesh.vertices.len() as u32;
                for v in &t.vertices {
                    let s = alignment.apply(*v + alignment.origin);
                    if let Some(why) = outside_scene_frame(s) {
                        return Err(CityModelError::Frame {
                            path: m.path.clone(),
                            line: job.poly.line,
                            polygon: job.poly.name(),
                            why,
                        });
                    }
                    mesh.vertices.push([s.x as f32, s.y as f32, s.z as f32]);
                }
                for tri in &t.triangles {
                    let f = tri.map(|i| i + base_v);
                    mesh.faces.push(if job.poly.reversed {
                        [f[0], f[2], f[1]]
                    } else {
                        f
                    });
                    mesh.labels.push(job.label);
                }
            }
        }
    }
    if mesh.faces.is_empty() {
        let names = files
            .iter()
            .map(|f| f.display().to_string())
            .collect::<Vec<_>>()
            .join(", ");
        // Why: the first polygon the triangulator skipped, else the readers' first warning
        // (dropped geometry: a dangling xlink, a non-finite coordinate, …).
        let why = match skipped.first() {
            Some(k) => format!(
                "{} polygons skipped, first: {}: {}: {}",
                skipped.len(),
                at_line(Path::new(&k.file), k.line),
                k.polygon
                    .as_deref()
                    .map_or("polygon without gml:id".into(), |id| format!(
                        "polygon {id}"
                    )),
                k.reason
            ),
            None => models
                .iter()
                .flat_map(|m| m.warnings.iter().map(|w| w.to_string()))
                .next()
                .map_or_else(
                    || "no polygon of a building, its surfaces or openings in LoD 1–3".into(),
                    |w| format!("first reader warning: {w}"),
                ),
        };
        return Err(CityModelError::Empty { files: names, why });
    }

    let summary = summarize(
        &models,
        files,
        &mesh,
        &skipped,
        &repairs,
        &warnings,
        planarity,
        holes_used,
        &alignment,
        opts.alignment.is_some(),
        t_parse,
        t_tri,
    );
    Ok(Output {
        mesh,
        entities,
        summary,
        alignment,
    })
}

#[allow(clippy::too_many_arguments)]
fn summarize(
    models: &[CityModel],
    files: &[PathBuf],
    mesh: &TriMesh,
    skipped: &[Skipped],
    repairs: &BTreeMap<&'static str, usize>,
    warnings: &[String],
    planarity: Planarity,
    holes_used: usize,
    alignment: &Alignment,
    alignment_given: bool,
    t_parse: f64,
    t_tri: f64,
) -> CitymodelSummary {
    let count = |c: Class| models.iter().map(|m| m.count(c)).sum::<usize>();
    let surface_classes = [
        Class::WallSurface,
        Class::RoofSurface,
        Class::GroundSurface,
        Class::ClosureSurface,
        Class::OuterCeilingSurface,
        Class::OuterFloorSurface,
    ];
    let surfaces: BTreeMap<&str, usize> = surface_classes
        .iter()
        .map(|&c| (c.name(), count(c)))
        .collect();
    let mut by_reason: BTreeMap<String, usize> = BTreeMap::new();
    for s in skipped {
        *by_reason.entry(s.reason.clone()).or_default() += 1;
    }
    let mut unknown: BTreeMap<String, usize> = BTreeMap::new();
    for m in models {
        for (k, v) in &m.stats.unknown_elements {
            *unknown.entry(k.clone()).or_default() += v;
        }
    }
    let reader_warnings: Vec<String> = models
        .iter()
        .flat_map(|m| m.warnings.iter().map(|w| w.to_string()))
        .collect();
    let all_warnings: Vec<&String> = reader_warnings.iter().chain(warnings).collect();
    let sum = |f: &dyn Fn(&CityModel) -> usize| models.iter().map(f).sum::<usize>();
    let bytes: u64 = models.iter().map(|m| m.stats.bytes).sum();
    CitymodelSummary {
        files: models
            .iter()
            .zip(files)
            .map(|(m, f)| FileSummary {
                path: f.display().to_string(),
                citygml: serde_json::to_value(m.version)
                    .ok()
                    .and_then(|v| v.as_str().map(String::from))
                    .unwrap_or_default(),
                srs_name: m.srs_name.clone(),
                bytes: m.stats.bytes,
                objects: m.objects.len(),
                polygons: m.stats.polygons,
            })
            .collect(),
        buildings: count(Class::Building),
        building_parts: count(Class::BuildingPart),
        installations: count(Class::BuildingInstallation)
            + count(Class::BuildingConstructiveElement),
        surfaces_total: surfaces.values().sum::<usize>(),
        surfaces: surfaces
            .into_iter()
            .map(|(k, v)| (k.to_string(), v))
            .collect(),
        windows: count(Class::Window) + count(Class::WindowSurface),
        doors: count(Class::Door) + count(Class::DoorSurface),
        entities: models.iter().map(|m| m.objects.len()).sum::<usize>(),
        polygons: sum(&|m| m.stats.polygons),
        polygons_used: sum(&|m| m.used_polygons().count()),
        polygons_unused: sum(&|m| m.stats.polygons_unused),
        holes: sum(&|m| m.stats.holes),
        holes_used,
        triangles: mesh.faces.len(),
        vertices: mesh.vertices.len(),
        skipped: SkippedSummary {
            count: skipped.len(),
            by_reason,
            polygons: skipped.to_vec(),
        },
        repairs: repairs.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
        max_planarity_deviation: planarity,
        curves_skipped: sum(&|m| m.stats.curves_skipped),
        implicit_geometries_skipped: sum(&|m| m.stats.implicit_skipped),
        xlinks: Xlinks {
            shared: sum(&|m| m.stats.xlinks_shared),
            adopted: sum(&|m| m.stats.xlinks_adopted),
            dangling: sum(&|m| m.stats.xlinks_dangling),
        },
        unknown_elements: unknown,
        warnings: Warnings {
            count: all_warnings.len(),
            items: all_warnings.into_iter().cloned().collect(),
        },
        alignment: AlignmentRecord::from(alignment),
        alignment_given,
        estimated_from: None,
        timing: CitymodelTiming {
            parse_s: t_parse,
            parse_mb_per_s: bytes as f64 / 1e6 / t_parse.max(1e-9),
            triangulate_s: t_tri,
        },
    }
}

/// Writes `mesh.ply`, `semantics.json`, `alignment.json` and (last, as the completion
/// marker) `summary.json` into `out_dir`.
pub fn write(out: &Output, out_dir: &Path) -> Result<(), CityModelError> {
    fsutil::create_dir(out_dir)?;
    // A stale summary would make a half-rewritten folder look complete.
    let _ = std::fs::remove_file(out_dir.join("summary.json"));
    out.mesh.write_ply(&out_dir.join("mesh.ply"))?;
    semantics::write(&out_dir.join("semantics.json"), &out.entities)?;
    fsutil::write_json(&out_dir.join("alignment.json"), &out.alignment.to_json())?;
    crate::layout::Summary::write(&out.summary, out_dir)?;
    crate::progress::done(
        "citymodel",
        &format!(
            "{} buildings, {} surfaces, {} windows, {} doors → {} triangles ({} polygons skipped, {} warnings)",
            out.summary.buildings,
            out.summary.surfaces_total,
            out.summary.windows,
            out.summary.doors,
            out.summary.triangles,
            out.summary.skipped.count,
            out.summary.warnings.count
        ),
        out.summary.timing.parse_s + out.summary.timing.triangulate_s,
    );
    show_warnings(&out.summary.warnings.items);
    Ok(())
}

/// How many warnings a stage prints without `-v` (all of them are in `summary.json`).
pub const WARNINGS_SHOWN: usize = 5;

/// Prints the first [`WARNINGS_SHOWN`] warnings (file, line, gml:id, what), all with `-v`.
fn show_warnings(items: &[String]) {
    let all = crate::progress::verbose();
    for w in items
        .iter()
        .take(if all { items.len() } else { WARNINGS_SHOWN })
    {
        log::warn!("citymodel: {w}");
    }
    if !all && items.len() > WARNINGS_SHOWN {
        log::warn!(
            "citymodel: {} more warnings (-v shows them all; every one is in summary.json)",
            items.len() - WARNINGS_SHOWN
        );
    }
}
