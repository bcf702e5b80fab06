//! The query language over a finished run — a library module shared by the `query` stage and
//! the query-driven evaluation (`eval::by_query`): [`SemanticRun`] loads a run's semantic
//! table, label table, per-Gaussian labels and label features; [`grammar`] parses `--where`
//! expressions (one-line errors with the column), [`select`] evaluates them over the entities
//! and the label table, [`text`] scores per-label features against a prompt (LERF/LangSplat
//! relevancy) and resolves free text to a prompt, class or attribute name (sentence
//! embeddings, [`crate::textembed`]), [`masks`] turns a selection into per-view masks through the contributions cache.
//! It imports formats only.
pub mod grammar;
pub mod masks;
pub mod select;
pub mod text;
pub mod units;

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::cache::{Cache, CacheError};
use crate::labels::LabelTable;
pub use crate::layout::Mode;
use crate::sam::Prompts;
use crate::scene::{Scene, SceneError};
use crate::semantics::{self, Entity};
use crate::{classes, npy};
pub use grammar::{Expr, ParseError, Term};
pub use masks::MaskRule;
pub use select::SelectError;
pub use text::{Candidate, FreeText, LabelFeatures, TextMatch, TextOptions};

/// An expression as error messages quote it: whole up to 200 characters, else its start and
/// its length (a machine-made expression can be megabytes long).
fn shown(text: &str) -> String {
    const MAX: usize = 200;
    if text.chars().count() <= MAX {
        return text.to_string();
    }
    let head: String = text.chars().take(MAX / 2).collect();
    format!("{head}… ({} characters)", text.chars().count())
}

/// Errors of loading a finished run and evaluating selections over it.
#[derive(Debug, thiserror::Error)]
pub enum SelectionError {
    /// `what` names where the text came from (`--where`, `--attr`, …); the error is part of
    /// the message and not a `source`, so a printed chain says it once.
    #[error("{what} `{}`: {error}", shown(.text))]
    Parse {
        what: String,
        text: String,
        error: ParseError,
    },
    #[error("{what} `{}`: {error}", shown(.text))]
    Select {
        what: String,
        text: String,
        error: Box<SelectError>,
    },
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
    IdMap(#[from] crate::idmap::IdMapError),
    #[error(transparent)]
    Text(#[from] text::TextError),
    #[error(transparent)]
    Sam(#[from] crate::sam::SamError),
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
    /// The sentence-embedding model of free text, loaded on the first free-text term.
    pub text_model: crate::textembed::Lazy,
    /// Seconds spent loading.
    pub load_s: f64,
}

impl SemanticRun {
    /// Loads run folder `run` made from scene folder `scene`, in `mode` (default:
    /// [`Mode::default_for`]).
    pub fn open(
        run: &Path,
        scene: &Path,
        mode: Option<Mode>,
    ) -> Result<SemanticRun, SelectionError> {
        let t0 = Instant::now();
        let mode = mode.unwrap_or_else(|| Mode::default_for(run));
        let scene = Scene::open(scene)?;
        let entities = semantics::read(&crate::layout::semantics_file(run))?;
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
            return Err(SelectionError::Inputs(format!(
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
            return Err(SelectionError::Inputs(format!(
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
            return Err(SelectionError::Inputs(format!(
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
            text_model: crate::textembed::Lazy::default(),
            load_s: t0.elapsed().as_secs_f64(),
        })
    }

    /// The contributions cache of the run (`R/render`), checked against the Gaussian count.
    pub fn cache(&self) -> Result<Cache, SelectionError> {
        let dir = self.run.join("render");
        let c = Cache::open(&dir)?;
        if c.summary.gaussians != self.label_of.len() {
            return Err(SelectionError::Inputs(format!(
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
    pub fn test_views(&self) -> Result<Vec<String>, SelectionError> {
        Ok(
            crate::idmap::list_class_maps(&self.run.join(self.mode.dir()))?
                .into_keys()
                .collect(),
        )
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
            embed: Some(&self.text_model),
        }
    }

    /// Parses `text` (`what` names the flag in errors) and evaluates it.
    pub fn select_text(
        &self,
        what: &str,
        text: &str,
        opts: TextOptions,
    ) -> Result<(Expr, select::Selected), SelectionError> {
        let expr = grammar::parse(text).map_err(|error| SelectionError::Parse {
            what: what.to_string(),
            text: text.to_string(),
            error,
        })?;
        let sel = self.select_as(what, text, &expr, opts)?;
        Ok((expr, sel))
    }

    /// Evaluates a parsed selection.
    pub fn select(
        &self,
        expr: &Expr,
        opts: TextOptions,
    ) -> Result<select::Selected, SelectionError> {
        self.select_as("selection", &expr.to_string(), expr, opts)
    }

    /// [`SemanticRun::select`] of an expression parsed from `text`, given as `what` (a flag such
    /// as `--where`): an error names them, and its columns refer to `text`.
    pub fn select_as(
        &self,
        what: &str,
        text: &str,
        expr: &Expr,
        opts: TextOptions,
    ) -> Result<select::Selected, SelectionError> {
        let index = select::Index::new(&self.entities);
        select::evaluate(&self.context(opts), &index, expr).map_err(|error| {
            SelectionError::Select {
                what: what.to_string(),
                text: text.to_string(),
                error: Box::new(error),
            }
        })
    }

    /// Whether each Gaussian's label is among `labels`.
    pub fn gaussian_selection(&self, labels: &[i32]) -> Vec<bool> {
        let set: HashSet<i32> = labels.iter().copied().collect();
        self.label_of.iter().map(|l| set.contains(l)).collect()
    }
}
