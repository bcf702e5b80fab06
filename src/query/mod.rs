//! The `query` stage (DESIGN.md, "Wave 2 contract"; docs/query.md): selections over a finished
//! run's semantic Gaussian scene — by CityGML class with its descendants, hierarchy level,
//! ancestry, attribute, gml:id, evaluation category, label, text (with a calibrated "no match")
//! or a picked pixel — and their outputs: `selection.json`, per-view masks through the
//! contributions cache, `extract.ply` / `remove.ply`, and the semantic table as SQLite.
//!
//! * [`grammar`] parses `--where` expressions (one-line errors with the column),
//! * [`select`] evaluates them over the entities and the label table,
//! * [`text`] scores per-label features against a prompt (LERF/LangSplat relevancy),
//! * [`masks`], [`export`], [`sqlite`] write the outputs,
//! * [`evaluate`] is the paper's query-driven evaluation (`gs4city eval --by-query`).
pub mod evaluate;
pub mod export;
pub mod grammar;
pub mod masks;
pub mod select;
pub mod sqlite;
pub mod text;
pub mod units;

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::citygml::Level;
use crate::semantics::{self, Entity};
use crate::labels::LabelTable;
use crate::cache::{Cache, CacheError};
use crate::sam::Prompts;
use crate::scene::{Scene, SceneError};
use crate::{classes, fsutil, npy};
pub use export::ExportCounts;
pub use grammar::{Expr, ParseError, Term};
pub use masks::MaskRule;
pub use select::SelectError;
pub use text::{LabelFeatures, TextMatch, TextOptions};

/// Errors of the query stage.
#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    #[error("{what} `{text}`: {source}")]
    Parse {
        what: String,
        text: String,
        source: ParseError,
    },
    #[error("selection `{text}`: {source}")]
    Select { text: String, source: SelectError },
    #[error("{0}")]
    Inputs(String),
    #[error(transparent)]
    Scene(#[from] SceneError),
    #[error(transparent)]
    Semantics(#[from] semantics::SemanticsError),
    #[error(transparent)]
    Labels(#[from] crate::labels::LabelsError),
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
    Text(#[from] text::TextError),
    #[error(transparent)]
    Sam(#[from] crate::sam::SamError),
    #[error(transparent)]
    Eval(#[from] crate::eval::EvalError),
}

/// Which per-Gaussian labels a query reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// The closed-form vote (`R/lift/gaussians.npy`).
    Vote,
    /// Identity learning (`R/train/gaussians.npy`).
    Learned,
}

impl std::str::FromStr for Mode {
    type Err = String;
    fn from_str(s: &str) -> Result<Mode, String> {
        match s {
            "vote" => Ok(Mode::Vote),
            "learned" => Ok(Mode::Learned),
            _ => Err(format!("{s:?} is not one of vote, learned")),
        }
    }
}

impl Mode {
    /// The run subfolder that holds this mode's `gaussians.npy` and test-view predictions.
    pub fn dir(self) -> &'static str {
        match self {
            Mode::Vote => "lift",
            Mode::Learned => "train",
        }
    }

    /// `learned` when the run has `train/gaussians.npy`, else `vote`.
    pub fn default_for(run: &Path) -> Mode {
        if run.join("train/gaussians.npy").is_file() {
            Mode::Learned
        } else {
            Mode::Vote
        }
    }
}

/// A finished run, loaded for queries: the semantic table, the label table, one label per
/// Gaussian, and (where present) per-label features and prompts.
pub struct SemanticRun {
    pub run: PathBuf,
    pub scene: Scene,
    pub mode: Mode,
    pub entities: Vec<Entity>,
    pub labels: LabelTable,
    /// Where the label table came from (`fuse/labels.json`, or the city table).
    pub labels_source: String,
    /// Label id per Gaussian (−1 none).
    pub label_of: Vec<i32>,
    /// Class id per Gaussian (−1 none).
    pub class_of: Vec<i32>,
    /// Row of each label id in `labels.labels`.
    pub row_of: HashMap<i32, usize>,
    pub features: Option<LabelFeatures>,
    pub features_path: PathBuf,
    pub prompts: Option<(Prompts, PathBuf)>,
    /// Seconds spent loading.
    pub load_s: f64,
}

impl SemanticRun {
    /// Loads run folder `run` made from scene folder `scene`, in `mode` (default:
    /// [`Mode::default_for`]).
    pub fn open(run: &Path, scene: &Path, mode: Option<Mode>) -> Result<SemanticRun, QueryError> {
        let t0 = Instant::now();
        let mode = mode.unwrap_or_else(|| Mode::default_for(run));
        let scene = Scene::open(scene)?;
        let entities = semantics::read(&run.join("citymodel/semantics.json"))?;
        let fuse = run.join("fuse");
        let (labels, labels_source) = if fuse.is_dir() {
            let p = fuse.join("labels.json");
            (LabelTable::read(&p)?, p.display().to_string())
        } else {
            (
                LabelTable::city(&entities, &classes::table(&entities))?,
                "city labels of semantics.json (the run has no fuse/)".to_string(),
            )
        };
        let gpath = run.join(mode.dir()).join("gaussians.npy");
        if !gpath.is_file() {
            return Err(QueryError::Inputs(format!(
                "{}: missing; the run has no {} labels (--mode {})",
                gpath.display(),
                mode.dir(),
                match mode {
                    Mode::Vote => "vote",
                    Mode::Learned => "learned",
                }
            )));
        }
        let (shape, table) = npy::read::<i32>(&gpath)?;
        if shape.len() != 2 || shape[1] != 2 {
            return Err(QueryError::Inputs(format!(
                "{}: expected int32 N×2 (label, class), found shape {shape:?}",
                gpath.display()
            )));
        }
        let label_of: Vec<i32> = table.chunks(2).map(|r| r[0]).collect();
        let class_of: Vec<i32> = table.chunks(2).map(|r| r[1]).collect();
        let row_of: HashMap<i32, usize> = labels
            .labels
            .iter()
            .enumerate()
            .map(|(i, l)| (l.id, i))
            .collect();
        if let Some(g) = label_of
            .iter()
            .position(|l| *l != -1 && !row_of.contains_key(l))
        {
            return Err(QueryError::Inputs(format!(
                "{}: Gaussian {g} has label {}, which the label table ({labels_source}) does not list",
                gpath.display(),
                label_of[g]
            )));
        }
        let features_path = fuse.join("label_features.npy");
        let features = if features_path.is_file() {
            Some(LabelFeatures::read(&features_path, labels.labels.len())?)
        } else {
            None
        };
        let prompts = match scene.prompts_file() {
            Some(p) => Some((crate::sam::read_prompts_json(&p)?, p)),
            None => None,
        };
        Ok(SemanticRun {
            run: run.to_path_buf(),
            scene,
            mode,
            entities,
            labels,
            labels_source,
            label_of,
            class_of,
            row_of,
            features,
            features_path,
            prompts,
            load_s: t0.elapsed().as_secs_f64(),
        })
    }

    /// The contributions cache of the run (`R/render`), checked against the Gaussian count.
    pub fn cache(&self) -> Result<Cache, QueryError> {
        let dir = self.run.join("render");
        let c = Cache::open(&dir)?;
        if c.summary.gaussians != self.label_of.len() {
            return Err(QueryError::Inputs(format!(
                "{}: the cache indexes {} Gaussians, {}/gaussians.npy labels {}",
                dir.display(),
                c.summary.gaussians,
                self.mode.dir(),
                self.label_of.len()
            )));
        }
        Ok(c)
    }

    /// The stems of the test views: those with a prediction `<stem>.class.npy` in the mode's folder.
    pub fn test_views(&self) -> Result<Vec<String>, QueryError> {
        Ok(crate::eval::list_maps(&self.run.join(self.mode.dir()))?
            .into_keys()
            .collect())
    }

    /// The selection context of [`select::evaluate`].
    pub fn context(&self, text: TextOptions) -> select::Context<'_> {
        select::Context {
            entities: &self.entities,
            labels: &self.labels,
            features: self.features.as_ref(),
            prompts: self.prompts.as_ref().map(|(p, f)| (p, f.as_path())),
            features_path: self.features_path.clone(),
            text,
        }
    }

    /// Parses `text` (`what` names the flag in errors) and evaluates it.
    pub fn select_text(
        &self,
        what: &str,
        text: &str,
        opts: TextOptions,
    ) -> Result<(Expr, select::Selected), QueryError> {
        let expr = grammar::parse(text).map_err(|source| QueryError::Parse {
            what: what.to_string(),
            text: text.to_string(),
            source,
        })?;
        let sel = self.select(&expr, opts)?;
        Ok((expr, sel))
    }

    /// Evaluates a parsed selection.
    pub fn select(&self, expr: &Expr, opts: TextOptions) -> Result<select::Selected, QueryError> {
        let index = select::Index::new(&self.entities);
        select::evaluate(&self.context(opts), &index, expr).map_err(|source| QueryError::Select {
            text: expr.to_string(),
            source,
        })
    }

    /// Whether each Gaussian's label is among `labels`.
    pub fn gaussian_selection(&self, labels: &[i32]) -> Vec<bool> {
        let set: HashSet<i32> = labels.iter().copied().collect();
        self.label_of.iter().map(|l| set.contains(l)).collect()
    }
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
}

/// Pixels of one view's mask.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewCount {
    pub stem: String,
    pub width: usize,
    pub height: usize,
    pub pixels: u64,
}

/// `selection.json` (DESIGN.md: `match`, `labels`, `entities`, `gaussians`, `score`; the rest
/// is detail).
#[derive(Debug, Clone, PartialEq, Serialize)]
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
    pub options: QueryOptions,
    pub labels_source: String,
    pub timing: QueryTiming,
    pub warnings: Vec<String>,
}

impl QuerySummary {
    /// Reads a query folder's `summary.json`.
    pub fn read(dir: &Path) -> Result<Self, fsutil::FsError> {
        fsutil::read_json(&dir.join("summary.json"))
    }
}

/// The cached view named `name` (a stem or an image name).
fn find_view<'c>(
    cache: &'c Cache,
    name: &str,
) -> Result<&'c crate::cache::CachedView, QueryError> {
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

/// Picks pixel (x, y) of `view`: the predicted label there and its chain.
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
    let chain = l
        .and_then(|l| l.entity)
        .and_then(|e| semantics::chains(&sr.entities).get(e as usize).copied())
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
        .unwrap_or_default();
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
    let export = if opts.export {
        Some(export::export(&sr.scene.ply, &selected, out)?)
    } else {
        None
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
        let merged = masks::merged_labels(&sr.label_of, &selected);
        let bar = crate::progress::Bar::new("query", stems.len() as u64, "views");
        for stem in &stems {
            let v = find_view(cache, stem)?;
            let c = cache.load(stem)?;
            let mask = masks::view_mask(&c, &merged, &selected, opts.rule);
            if opts.sqlite {
                let (_, label_map) = crate::cache::predict(&c, &sr.label_of, &sr.class_of);
                for &l in &label_map {
                    if let Some(&r) = sr.row_of.get(&l) {
                        label_pixels[r] += 1;
                    }
                }
            }
            let image = sr.scene.images.as_ref().map(|d| d.join(&v.name));
            let image = match image.map(|p| (crate::imageio::read_rgb(&p), p)) {
                Some((Ok(im), _)) if im.dim() == (c.height, c.width, 3) => Some(im),
                Some((Ok(im), p)) => {
                    warnings.push(format!(
                        "{}: {}×{} pixels, the cache view is {}×{}: overlay without the image",
                        p.display(),
                        im.dim().1,
                        im.dim().0,
                        c.width,
                        c.height
                    ));
                    None
                }
                Some((Err(e), _)) => {
                    warnings.push(format!("{e}: overlay without the image"));
                    None
                }
                None => None,
            };
            masks::write_mask(out, stem, c.width, c.height, &mask, image.as_ref())?;
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
        options: opts.clone(),
        labels_source: sr.labels_source.clone(),
        timing,
        warnings,
    };
    fsutil::write_json(&out.join("summary.json"), &summary)?;
    crate::progress::done(
        "query",
        &format!(
            "{} labels, {} entities, {} Gaussians selected{}",
            summary.labels,
            summary.entities,
            summary.gaussians,
            if summary.matched { "" } else { " (no match)" }
        ),
        summary.timing.total_s,
    );
    Ok(summary)
}
