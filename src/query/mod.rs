//! The `query` stage (`docs/design.md`, "Stage contract"; docs/query.md): selections over a finished
//! run's semantic Gaussian scene — by CityGML class with its descendants, hierarchy level,
//! ancestry, attribute, gml:id, evaluation category, label, text (with a calibrated "no match")
//! or a picked pixel — and their outputs: `selection.json`, per-view masks through the
//! contributions cache, `extract.ply` / `remove.ply`, and the semantic table as SQLite.
//!
//! The selections themselves are the library [`crate::selection`]; this stage writes their
//! outputs: [`export`] (PLY split), [`sqlite`] (the semantic table), `selection.json` and the
//! per-view masks. The paper's query-driven evaluation is `eval::by_query`. The 3D Tiles
//! export selects and colours here ([`tiles`]) and is written by [`crate::tiles3d`].
pub mod export;
pub mod sqlite;

use std::collections::{BTreeMap, HashSet};
use std::path::Path;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use ndarray::Array3;

use crate::cache::{Cache, CacheError};
use crate::citygml::Level;
use crate::layout::Mode;
use crate::selection::{
    self, Expr, FreeText, MaskRule, SelectionError, SemanticRun, Term, TextMatch, TextOptions,
    masks, select,
};
use crate::semantics;
use crate::{classes, fsutil, npy};
pub use export::{ColorBy, ExportCounts, ExportOptions, SplitBy, SplitFile, UpAxis};

/// Errors of the query stage.
#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    #[error(transparent)]
    Selection(#[from] SelectionError),
    #[error("{0}")]
    Inputs(String),
    #[error(transparent)]
    Npy(#[from] npy::NpyError),
    #[error(transparent)]
    Cache(#[from] CacheError),
    #[error(transparent)]
    Ply(#[from] crate::splat::PlyError),
    #[error(transparent)]
    Image(#[from] crate::imageio::ImageError),
    #[error(transparent)]
    Fs(#[from] fsutil::FsError),
    #[error(transparent)]
    Sqlite(#[from] sqlite::SqliteError),
    #[error(transparent)]
    Tiles(#[from] crate::tiles3d::TilesError),
}

/// Writes `<stem>.mask.npy` (uint8 H×W) and `<stem>.mask.png` into `out`.
pub fn write_mask(
    out: &Path,
    stem: &str,
    width: usize,
    height: usize,
    mask: &[u8],
    image: Option<&Array3<u8>>,
) -> Result<(), QueryError> {
    crate::npy::write(
        &out.join(format!("{stem}.mask.npy")),
        &[height, width],
        mask,
    )?;
    crate::imageio::write_png(
        &out.join(format!("{stem}.mask.png")),
        &selection::masks::overlay(mask, width, height, image),
    )?;
    Ok(())
}

/// What to select.
#[derive(Debug, Clone)]
pub enum Request {
    /// A selection expression (flags are combined into one with `and`).
    Select(Expr),
    /// The label under pixel (x, y) of a view (stem or image name); with `level`, the ancestor
    /// entity at that level and its descendants.
    Pick {
        view: String,
        x: usize,
        y: usize,
        level: Option<Level>,
    },
}

/// Which views get masks.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Views {
    /// The test views (those with predictions in the mode's folder).
    Test,
    /// Every cached view.
    All,
    /// These views (stems or image names).
    Named(Vec<String>),
    /// No masks (selection and exports only).
    None,
}

/// Options of the stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QueryOptions {
    pub views: Views,
    /// Write `extract.ply` and `remove.ply`.
    pub export: bool,
    /// Colour, frame and per-group files of the export.
    #[serde(default)]
    pub export_options: ExportOptions,
    pub rule: MaskRule,
    pub text: TextOptions,
    /// Write `semantic.sqlite`.
    pub sqlite: bool,
}

impl Default for QueryOptions {
    fn default() -> Self {
        QueryOptions {
            views: Views::Test,
            export: false,
            export_options: ExportOptions::default(),
            rule: MaskRule::Argmax,
            text: TextOptions::default(),
            sqlite: true,
        }
    }
}

/// One weighted Gaussian of a picked pixel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PickEntry {
    pub gaussian: u32,
    pub weight: f32,
    pub label: i32,
}

/// One entity of a picked chain (building → surface → part).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChainEntry {
    pub level: Level,
    pub id: i32,
    pub object_id: String,
    pub class: crate::semantics::Class,
    pub attributes: BTreeMap<String, serde_json::Value>,
}

/// What lies under a picked pixel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pick {
    pub view: String,
    pub x: usize,
    pub y: usize,
    /// The pixel's predicted label (the per-pixel argmax of the predicted maps; −1 none).
    pub label: i32,
    pub category: String,
    /// The label's source (`city` / `image`), when it has one.
    pub source: Option<String>,
    /// Image labels: the mask group.
    pub group: Option<i32>,
    /// Accumulated alpha of the pixel.
    pub alpha: f32,
    /// The cached list of the pixel, in depth order.
    pub gaussians: Vec<PickEntry>,
    /// City labels: feature → surface → part, each with its attributes.
    pub chain: Vec<ChainEntry>,
    /// The point of the splat surface under the pixel, in the scene frame (the ray through
    /// the pixel's centre where its transmittance falls to one half, `splat::surface`); `None`
    /// where the pixel's alpha stays below one half.
    #[serde(default)]
    pub point: Option<[f64; 3]>,
    /// The same point in the city model's CRS (f64, through the inverse of the run's
    /// `citymodel/alignment.json`).
    #[serde(default)]
    pub geo: Option<[f64; 3]>,
}

/// Pixels of one view's mask.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewCount {
    pub stem: String,
    pub width: usize,
    pub height: usize,
    pub pixels: u64,
}

/// `selection.json` (`docs/design.md`: `match`, `labels`, `entities`, `gaussians`, `score`; the rest
/// is detail).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SelectionFile {
    /// Whether the selection holds at least one Gaussian.
    #[serde(rename = "match")]
    pub matched: bool,
    /// Selected label ids.
    pub labels: Vec<i32>,
    /// gml:ids of the selected entities (entities without Gaussians included).
    pub entities: Vec<String>,
    /// Selected Gaussians.
    pub gaussians: usize,
    /// Text queries: the best relevancy over all labels (also when below the threshold).
    pub score: Option<f64>,
    /// The selection, canonical text.
    pub query: String,
    pub mode: Mode,
    /// gml:ids of the selected entities whose parent is not selected.
    pub roots: Vec<String>,
    pub text: Vec<TextMatch>,
    /// Free-text terms: the prompt, class or attribute each resolved to (null: no match).
    pub free_text: Vec<FreeText>,
    pub pick: Option<Pick>,
    pub views: Vec<ViewCount>,
    pub warnings: Vec<String>,
}

/// Timing of the stage.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct QueryTiming {
    pub load_s: f64,
    pub select_s: f64,
    pub export_s: f64,
    pub masks_s: f64,
    pub sqlite_s: f64,
    pub total_s: f64,
}

/// The stage's `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QuerySummary {
    pub query: String,
    pub mode: Mode,
    #[serde(rename = "match")]
    pub matched: bool,
    pub labels: usize,
    pub entities: usize,
    pub gaussians: usize,
    pub score: Option<f64>,
    pub views: Vec<ViewCount>,
    pub export: Option<ExportCounts>,
    /// The per-group files of `export_options.split_by` (`split/`).
    #[serde(default)]
    pub split: Vec<SplitFile>,
    pub options: QueryOptions,
    pub labels_source: String,
    pub timing: QueryTiming,
    pub warnings: Vec<String>,
}

impl crate::layout::Summary for QuerySummary {}

/// The cached view named `name` (a stem or an image name).
fn find_view<'c>(cache: &'c Cache, name: &str) -> Result<&'c crate::cache::CachedView, QueryError> {
    cache
        .summary
        .views
        .iter()
        .find(|v| v.stem == name || v.name == name)
        .ok_or_else(|| {
            let some: Vec<&str> = cache
                .summary
                .views
                .iter()
                .take(8)
                .map(|v| v.stem.as_str())
                .collect();
            QueryError::Inputs(format!(
                "view `{name}` is not in the contributions cache {} (views: {}{})",
                cache.dir.display(),
                some.join(", "),
                if cache.summary.views.len() > 8 {
                    ", …"
                } else {
                    ""
                }
            ))
        })
}

/// The city hierarchy of label `label` (feature → surface → part, each with its attributes;
/// empty for image labels and −1), given the run's `semantics::chains`.
pub fn chain(sr: &SemanticRun, chains: &[crate::mesh::FaceLabel], label: i32) -> Vec<ChainEntry> {
    sr.labels
        .get(label)
        .and_then(|l| l.entity)
        .and_then(|e| chains.get(e as usize).copied())
        .map(|fl| {
            [fl.feature, fl.surface, fl.part]
                .into_iter()
                .filter(|&i| i >= 0)
                .map(|i| {
                    let e = &sr.entities[i as usize];
                    ChainEntry {
                        level: e.level,
                        id: e.id,
                        object_id: e.object_id.clone(),
                        class: e.class,
                        attributes: e.attributes.clone(),
                    }
                })
                .collect()
        })
        .unwrap_or_default()
}

/// The point of the splat surface under pixel (x, y) of view `stem` (its ray through the
/// pixel's centre, the cached list `ids`/`ws` of the pixel), and that point in the city model's
/// CRS through the run's alignment.
/// The point under a picked pixel in the scene frame and in the city model's CRS.
type PickPoint = (Option<[f64; 3]>, Option<[f64; 3]>);

fn pick_point(
    sr: &SemanticRun,
    stem: &str,
    (x, y): (usize, usize),
    ids: &[u32],
    ws: &[f32],
) -> Result<PickPoint, QueryError> {
    // A run read without its scene's cameras (a cache alone): the label, no point.
    let Ok(views) = crate::colmap::read_model(&sr.scene.sparse) else {
        return Ok((None, None));
    };
    let Some(v) = views.iter().find(|v| v.stem() == stem) else {
        return Err(QueryError::Inputs(format!(
            "view `{stem}` is in the cache but not in {}",
            sr.scene.sparse.display()
        )));
    };
    let (g, _) = crate::splat::read_ply(&sr.scene.ply, &crate::splat::ReadOptions::KEEP)?;
    let cam = &v.camera;
    let dir = cam.pose.rotation.transpose() * cam.pixel_ray(x as f64 + 0.5, y as f64 + 0.5);
    let list = ids.iter().copied().zip(ws.iter().copied());
    let Some(p) = crate::splat::surface::surface_point(&g, list, cam.pose.center(), dir) else {
        return Ok((None, None));
    };
    let apath = crate::layout::Stage::Citymodel
        .path(&sr.run)
        .join("alignment.json");
    let geo = if apath.is_file() {
        let a = crate::alignment::Alignment::read(&apath)
            .map_err(|e| QueryError::Inputs(e.to_string()))?;
        Some(a.unapply(p.point).to_array())
    } else {
        None
    };
    Ok((Some(p.point.to_array()), geo))
}

/// Picks pixel (x, y) of `view`: the predicted label there and its chain, and the point of the
/// splat surface under it (scene frame and the city model's CRS).
pub fn pick(
    sr: &SemanticRun,
    cache: &Cache,
    view: &str,
    x: usize,
    y: usize,
) -> Result<Pick, QueryError> {
    let v = find_view(cache, view)?;
    if x >= v.width || y >= v.height {
        return Err(QueryError::Inputs(format!(
            "pixel ({x}, {y}) lies outside view `{}` ({}×{} pixels; x < {}, y < {})",
            v.stem, v.width, v.height, v.width, v.height
        )));
    }
    let c = cache.load(&v.stem)?;
    let p = y * c.width + x;
    let (_, label_map) = crate::cache::predict(&c, &sr.label_of, &sr.class_of);
    let label = label_map[p];
    let (ids, ws) = c.pixel(p);
    let l = sr.labels.get(label);
    let chain = chain(sr, &semantics::chains(&sr.entities), label);
    let (point, geo) = pick_point(sr, &v.stem, (x, y), ids, ws)?;
    Ok(Pick {
        view: v.stem.clone(),
        x,
        y,
        label,
        category: classes::name(sr.labels.class_of(label)).to_string(),
        source: l.map(|l| {
            match l.source {
                crate::labels::Source::City => "city",
                crate::labels::Source::Image => "image",
            }
            .to_string()
        }),
        group: l.and_then(|l| l.group),
        alpha: c.alpha[p],
        gaussians: ids
            .iter()
            .zip(ws)
            .map(|(&g, &w)| PickEntry {
                gaussian: g,
                weight: w,
                label: sr.label_of[g as usize],
            })
            .collect(),
        chain,
        point,
        geo,
    })
}

/// The expression a pick selects: its label, or (with `level`) the chain entity at that level
/// and its descendants.
fn pick_expr(p: &Pick, level: Option<Level>) -> Option<Expr> {
    if p.label < 0 {
        return None;
    }
    let at = level.and_then(|l| p.chain.iter().find(|c| c.level == l));
    Some(Expr::Term(match at {
        Some(c) => Term::Within {
            id: c.object_id.clone(),
            column: 1,
        },
        None => Term::Label {
            id: i64::from(p.label),
            column: 1,
        },
    }))
}

/// The run's semantics per Gaussian for the exports: label, class, the city hierarchy of city
/// labels (`semantics::chains`, as `semantic.ply`), and the building (the hierarchy's root).
pub fn columns(sr: &SemanticRun) -> export::Columns {
    let chain = semantics::chains(&sr.entities);
    let entity = |l: i32| sr.labels.get(l).and_then(|x| x.entity);
    let hier = |l: i32| {
        entity(l)
            .and_then(|e| chain.get(e as usize).copied())
            .unwrap_or(crate::mesh::FaceLabel::NONE)
    };
    let h: Vec<_> = sr.label_of.iter().map(|&l| hier(l)).collect();
    export::Columns {
        values: [
            sr.label_of.clone(),
            sr.class_of.clone(),
            h.iter().map(|c| c.feature).collect(),
            h.iter().map(|c| c.surface).collect(),
            h.iter().map(|c| c.part).collect(),
        ],
        building: sr
            .label_of
            .iter()
            .map(|&l| {
                entity(l)
                    .and_then(|e| sr.entities.get(e as usize))
                    .map_or(-1, |e| e.building)
            })
            .collect(),
        gml_ids: sr.entities.iter().map(|e| e.object_id.clone()).collect(),
    }
}

/// `gs4city export --format 3dtiles`: the Gaussians `selected` of run `sr` (the scene's PLY,
/// invalid ones left out, coloured by `color_by`) with their building / surface / part and
/// class, written by [`crate::tiles3d::write`] into `out`. `query`: the selection's text.
#[allow(clippy::too_many_arguments)]
pub fn tiles(
    sr: &SemanticRun,
    selected: &[bool],
    query: &str,
    color_by: ColorBy,
    alignment: &crate::alignment::Alignment,
    georef: &crate::crs::Georef,
    opts: &crate::tiles3d::TilesOptions,
    out: &Path,
) -> Result<crate::tiles3d::TilesSummary, QueryError> {
    let t0 = Instant::now();
    if !selected.iter().any(|&s| s) {
        return Err(QueryError::Inputs(format!(
            "the selection `{query}` holds no Gaussian: nothing to export"
        )));
    }
    let ply = &sr.scene.ply;
    let (mut g, _) = crate::splat::read_ply(ply, &crate::splat::ReadOptions::KEEP)?;
    if g.len() != selected.len() {
        return Err(QueryError::Inputs(format!(
            "{} holds {} Gaussians, the run's labels have {}: the PLY is not the one the run was made from",
            ply.display(),
            g.len(),
            selected.len()
        )));
    }
    let cols = columns(sr);
    let keep: Vec<usize> = (0..g.len())
        .filter(|&i| selected[i] && crate::splat::ply::is_valid(&g, i))
        .collect();
    let invalid = selected.iter().filter(|&&s| s).count() - keep.len();
    if keep.is_empty() {
        return Err(QueryError::Inputs(format!(
            "the selection `{query}` holds only invalid Gaussians (NaN or degenerate values in {}): nothing to export",
            ply.display()
        )));
    }
    for &i in &keep {
        match color_by {
            ColorBy::Rgb => {}
            ColorBy::Class => {
                crate::splat::transform::paint(&mut g, i, classes::color(cols.values[1][i]))
            }
            ColorBy::Building => {
                crate::splat::transform::paint(&mut g, i, classes::building_color(cols.building[i]))
            }
        }
    }
    let splats = crate::tiles3d::Splats {
        gaussians: g.select(&keep),
        tags: keep
            .iter()
            .map(|&i| [2, 3, 4, 1].map(|c| cols.values[c][i]))
            .collect(),
        entities: &sr.entities,
        query: query.to_string(),
        invalid,
        color_by: color_by.to_string(),
        read_s: t0.elapsed().as_secs_f64() + sr.load_s,
    };
    Ok(crate::tiles3d::write(
        &splats, alignment, georef, opts, out,
    )?)
}

/// Runs a query: selection, `selection.json`, masks of the chosen views, exports, the SQLite
/// table, and `summary.json` (last).
pub fn run(
    sr: &SemanticRun,
    req: &Request,
    opts: &QueryOptions,
    out: &Path,
) -> Result<QuerySummary, QueryError> {
    let t0 = Instant::now();
    fsutil::create_dir(out)?;
    // A previous query's outputs in `out` must not pass for this one's.
    let _ = std::fs::remove_file(out.join("summary.json"));
    for f in [
        "selection.json",
        "extract.ply",
        "remove.ply",
        "semantic.sqlite",
    ] {
        let _ = std::fs::remove_file(out.join(f));
    }
    if let Ok(rd) = std::fs::read_dir(out) {
        for e in rd.flatten() {
            let n = e.file_name().to_string_lossy().into_owned();
            if n.ends_with(".mask.npy") || n.ends_with(".mask.png") {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    let mut timing = QueryTiming {
        load_s: sr.load_s,
        ..Default::default()
    };
    let mut warnings = Vec::new();
    let needs_cache = matches!(req, Request::Pick { .. }) || opts.views != Views::None;
    let cache = if needs_cache { Some(sr.cache()?) } else { None };

    // 1. The selection.
    let (expr, picked) = match req {
        Request::Select(e) => (Some(e.clone()), None),
        Request::Pick { view, x, y, level } => {
            let p = pick(sr, cache.as_ref().expect("opened for picks"), view, *x, *y)?;
            if p.label < 0 {
                warnings.push(format!(
                    "pixel ({x}, {y}) of `{}` has no label (background or unlabelled Gaussians)",
                    p.view
                ));
            }
            (pick_expr(&p, *level), Some(p))
        }
    };
    let sel = match &expr {
        Some(e) => sr.select(e, opts.text)?,
        None => select::Selected {
            labels: vec![],
            entities: vec![],
            roots: vec![],
            text: vec![],
            relevancy: None,
            free_text: vec![],
            warnings: vec![],
        },
    };
    warnings.extend(sel.warnings.iter().cloned());
    let selected = sr.gaussian_selection(&sel.labels);
    let gaussians = selected.iter().filter(|&&s| s).count();
    let query = expr.as_ref().map_or_else(
        || "nothing (picked background)".to_string(),
        |e| e.to_string(),
    );
    timing.select_s = t0.elapsed().as_secs_f64();

    // 2. Exports.
    let t = Instant::now();
    let _ = std::fs::remove_dir_all(out.join("split"));
    let (export, split) = if opts.export {
        let eo = &opts.export_options;
        let frame = match eo.up {
            Some(up) => {
                let p = crate::layout::Stage::Citymodel
                    .path(&sr.run)
                    .join("alignment.json");
                let a = crate::alignment::Alignment::read(&p).map_err(|e| {
                    QueryError::Inputs(format!(
                        "an export with an up axis reads the run's alignment: {e}"
                    ))
                })?;
                Some(export::frame_motion(&a, up))
            }
            None => None,
        };
        let (c, f) = export::export(
            &sr.scene.ply,
            &columns(sr),
            &selected,
            eo,
            frame.as_ref(),
            out,
        )?;
        (Some(c), f)
    } else {
        (None, Vec::new())
    };
    timing.export_s = t.elapsed().as_secs_f64();

    // 3. Masks and per-label pixel counts.
    let t = Instant::now();
    let mut label_pixels = vec![0u64; sr.labels.labels.len()];
    let mut views = Vec::new();
    if let Some(cache) = &cache {
        let stems: Vec<String> = match &opts.views {
            Views::Test => sr.test_views()?,
            Views::All => cache.summary.views.iter().map(|v| v.stem.clone()).collect(),
            Views::Named(v) => v
                .iter()
                .map(|n| find_view(cache, n).map(|v| v.stem.clone()))
                .collect::<Result<_, _>>()?,
            Views::None => vec![],
        };
        if stems.is_empty() && opts.views == Views::Test {
            warnings.push(format!(
                "no test views: {} holds no <stem>.class.npy predictions; no masks written",
                sr.run.join(sr.mode.dir()).display()
            ));
        }
        let selection = masks::Selections::new(&sr.class_of, &[&selected]);
        let bar = crate::progress::Bar::new("query", stems.len() as u64, "views");
        for stem in &stems {
            let v = find_view(cache, stem)?;
            let c = cache.load(stem)?;
            let mask = selection.masks(&c, opts.rule).remove(0);
            if opts.sqlite {
                let (_, label_map) = crate::cache::predict(&c, &sr.label_of, &sr.class_of);
                for &l in &label_map {
                    if let Some(&r) = sr.row_of.get(&l) {
                        label_pixels[r] += 1;
                    }
                }
            }
            let image = sr.scene.images.as_ref().map(|d| d.join(&v.name));
            // A training view cached at a lower resolution than its image: the image averaged
            // down to it.
            let image = match image.map(|p| crate::imageio::read_rgb_sized(&p, c.width, c.height)) {
                Some(Ok(im)) => Some(im),
                Some(Err(e)) => {
                    warnings.push(format!("{e}: overlay without the image"));
                    None
                }
                None => None,
            };
            write_mask(out, stem, c.width, c.height, &mask, image.as_ref())?;
            views.push(ViewCount {
                stem: stem.clone(),
                width: c.width,
                height: c.height,
                pixels: mask.iter().map(|&m| u64::from(m)).sum(),
            });
            bar.inc(1);
        }
        bar.finish();
    }
    timing.masks_s = t.elapsed().as_secs_f64();

    // 4. selection.json.
    let score = sel.text.first().and_then(|t| t.best);
    let oid = |ids: &[i32]| -> Vec<String> {
        ids.iter()
            .map(|&e| sr.entities[e as usize].object_id.clone())
            .collect()
    };
    let file = SelectionFile {
        matched: gaussians > 0,
        labels: sel.labels.clone(),
        entities: oid(&sel.entities),
        gaussians,
        score,
        query: query.clone(),
        mode: sr.mode,
        roots: oid(&sel.roots),
        text: sel.text.clone(),
        free_text: sel.free_text.clone(),
        pick: picked,
        views: views.clone(),
        warnings: warnings.clone(),
    };
    fsutil::write_json(&out.join("selection.json"), &file)?;

    // 5. The semantic table.
    let t = Instant::now();
    if opts.sqlite {
        let mut label_gaussians = vec![0u64; sr.labels.labels.len()];
        for l in &sr.label_of {
            if let Some(&r) = sr.row_of.get(l) {
                label_gaussians[r] += 1;
            }
        }
        let sel_set: HashSet<i32> = sel.labels.iter().copied().collect();
        let selected_labels: Vec<bool> = sr
            .labels
            .labels
            .iter()
            .map(|l| sel_set.contains(&l.id))
            .collect();
        let mut selected_entities = vec![false; sr.entities.len()];
        for &e in &sel.entities {
            selected_entities[e as usize] = true;
        }
        let view_rows: Vec<(String, usize, usize, u64)> = views
            .iter()
            .map(|v| (v.stem.clone(), v.width, v.height, v.pixels))
            .collect();
        let meta = [
            ("program", format!("gs4city {}", env!("CARGO_PKG_VERSION"))),
            ("run", sr.run.display().to_string()),
            ("scene", sr.scene.root.display().to_string()),
            ("mode", sr.mode.dir().to_string()),
            ("labels_source", sr.labels_source.clone()),
            ("query", query.clone()),
            ("mask_rule", format!("{:?}", opts.rule).to_lowercase()),
            (
                "pixels",
                "predicted pixels (per-pixel argmax label) summed over the views table".to_string(),
            ),
        ];
        sqlite::write(
            &out.join("semantic.sqlite"),
            &sqlite::TableInputs {
                entities: &sr.entities,
                labels: &sr.labels,
                gaussians: &label_gaussians,
                pixels: &label_pixels,
                selected_labels: &selected_labels,
                selected_entities: &selected_entities,
                relevancy: sel.relevancy.as_deref(),
                views: &view_rows,
                meta: &meta,
            },
        )?;
    }
    timing.sqlite_s = t.elapsed().as_secs_f64();
    timing.total_s = t0.elapsed().as_secs_f64() + sr.load_s;
    let summary = QuerySummary {
        query,
        mode: sr.mode,
        matched: gaussians > 0,
        labels: sel.labels.len(),
        entities: sel.entities.len(),
        gaussians,
        score,
        views,
        export,
        split,
        options: opts.clone(),
        labels_source: sr.labels_source.clone(),
        timing,
        warnings,
    };
    crate::layout::Summary::write(&summary, out)?;
    Ok(summary)
}
