//! Text queries: a query vector (a prompt of `features/prompts.json`, or a vector file) matched
//! against the per-label features (`fuse/label_features.npy`) with a calibrated "no match".
//!
//! The score of a label is LERF's / LangSplat's *relevancy*: with the label feature `f`, the
//! query `q` and negatives `n_j` (all unit vectors),
//!
//! ```text
//! relevancy(f) = min_j  exp(T·f·q) / (exp(T·f·q) + exp(T·f·n_j))  =  min_j σ(T·(f·q − f·n_j))
//! ```
//!
//! with the temperature `T` = 10 of both papers. LERF's negatives are the canonical phrases
//! "object", "things", "stuff", "texture"; here they are **every other prompt of
//! `prompts.json`** (add those canonical phrases to the file to get them too), except the
//! query's synonyms (prompts whose cosine with the query is ≥ `synonym_cos`, e.g. "a wall of a
//! building" and "a facade of a building"). A label matches when its relevancy is at least
//! `min_relevancy`: it is closer to the query than to every negative by a margin
//! `ln(τ/(1−τ))/T`. Unlike the reference's per-view min–max normalisation (REFERENCE.md §5),
//! the score is absolute, so a query for something absent returns nothing.
//!
//! **Free text** (a query that is not a prompt of `prompts.json`) is first [`resolve`]d with a
//! sentence-embedding model ([`crate::textembed`]) to the nearest of the run's candidates —
//! the prompts, the CityGML class names and the attribute names, by cosine — and refused as
//! "no match" unless that cosine beats the query's cosine with every one of LERF's canonical
//! phrases ([`CANONICAL`]) by at least [`MIN_MARGIN`] (calibrated in docs/query.md).
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::npy;
use crate::sam::Prompts;

/// Errors of text queries.
#[derive(Debug, thiserror::Error)]
pub enum TextError {
    #[error(transparent)]
    Npy(#[from] npy::NpyError),
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error("{0}")]
    Refused(String),
    #[error(transparent)]
    Options(#[from] crate::check::OutOfRange),
    #[error(transparent)]
    Embed(#[from] crate::textembed::EmbedError),
}

/// Options of text matching.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TextOptions {
    /// Softmax temperature T (LERF, LangSplat: 10).
    pub temperature: f64,
    /// A label matches when its relevancy is ≥ this (calibrated on the simulated street
    /// features, docs/query.md).
    pub min_relevancy: f64,
    /// Prompts at least this similar to the query are synonyms, not negatives.
    pub synonym_cos: f64,
    /// Free text resolves to its nearest candidate (prompt, class, attribute) only when their
    /// cosine beats the text's cosine with every canonical phrase by at least this
    /// ([`MIN_MARGIN`]).
    #[serde(default = "min_margin")]
    pub min_margin: f64,
}

/// The calibrated default threshold (docs/query.md, "Calibration").
pub const MIN_RELEVANCY: f64 = 0.85;

/// The calibrated margin below which free text matches no candidate (docs/query.md, "Free
/// text").
pub const MIN_MARGIN: f64 = 0.13;

fn min_margin() -> f64 {
    MIN_MARGIN
}

/// LERF's canonical phrases: what anything is somewhat similar to. Free text must be closer
/// to its candidate than to each of them by [`TextOptions::min_margin`].
pub const CANONICAL: [&str; 4] = ["object", "things", "stuff", "texture"];

impl Default for TextOptions {
    fn default() -> Self {
        TextOptions {
            temperature: 10.0,
            min_relevancy: MIN_RELEVANCY,
            synonym_cos: 0.8,
            min_margin: MIN_MARGIN,
        }
    }
}

impl TextOptions {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<(), TextError> {
        use crate::check::{End, positive, range, unit};
        positive("temperature", self.temperature)?;
        unit("min relevancy", self.min_relevancy)?;
        range(
            "synonym cosine",
            self.synonym_cos,
            End::Closed(-1.0),
            End::Closed(1.0),
        )?;
        range(
            "free-text margin",
            self.min_margin,
            End::Closed(-2.0),
            End::Closed(2.0),
        )?;
        Ok(())
    }
}

/// Per-label features: row `i` belongs to `labels.labels[i]`; unit length, `None` for a zero
/// row (no feature).
#[derive(Debug, Clone, PartialEq)]
pub struct LabelFeatures {
    pub dim: usize,
    pub rows: Vec<Option<Vec<f32>>>,
}

fn unit(v: &[f32]) -> Option<Vec<f32>> {
    let n = v
        .iter()
        .map(|&x| f64::from(x) * f64::from(x))
        .sum::<f64>()
        .sqrt();
    (n.is_finite() && n > 1e-12).then(|| v.iter().map(|&x| (f64::from(x) / n) as f32).collect())
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(&x, &y)| f64::from(x) * f64::from(y))
        .sum()
}

impl LabelFeatures {
    /// From rows (normalised here; all-zero rows become `None`). Non-finite values are an
    /// error naming the row.
    pub fn new(path: &Path, dim: usize, data: &[f32]) -> Result<LabelFeatures, TextError> {
        if dim == 0 || data.len() % dim != 0 {
            return Err(TextError::Invalid {
                path: path.to_path_buf(),
                why: format!("{} values do not make rows of {dim}", data.len()),
            });
        }
        let mut rows = Vec::with_capacity(data.len() / dim);
        for (i, r) in data.chunks(dim).enumerate() {
            if let Some(j) = r.iter().position(|x| !x.is_finite()) {
                return Err(TextError::Invalid {
                    path: path.to_path_buf(),
                    why: format!("row {i}, column {j} is {} (not finite)", r[j]),
                });
            }
            rows.push(unit(r));
        }
        Ok(LabelFeatures { dim, rows })
    }

    /// Reads `label_features.npy` (float32 L×D); `labels` is L, the size of the label table.
    pub fn read(path: &Path, labels: usize) -> Result<LabelFeatures, TextError> {
        let (shape, data) = npy::read::<f32>(path)?;
        let bad = |why: String| TextError::Invalid {
            path: path.to_path_buf(),
            why,
        };
        let [l, d] = shape[..] else {
            return Err(bad(format!(
                "expected a 2-D L×D array, found shape {shape:?}"
            )));
        };
        if l != labels {
            return Err(bad(format!(
                "{l} rows, the label table (labels.json) has {labels} labels"
            )));
        }
        if d == 0 {
            return Err(bad("feature dimension 0".into()));
        }
        LabelFeatures::new(path, d, &data)
    }
}

/// A query vector and its negatives.
#[derive(Debug, Clone, PartialEq)]
pub struct TextQuery {
    /// The prompt, or the vector file's path.
    pub query: String,
    pub vector: Vec<f32>,
    /// Negative prompts (text, unit vector).
    pub negatives: Vec<(String, Vec<f32>)>,
    /// Prompts left out of the negatives as synonyms of the query.
    pub synonyms: Vec<String>,
}

/// The prompt named `text` (exact, else ignoring case and surrounding spaces).
pub fn find_prompt<'a>(prompts: &'a Prompts, text: &str) -> Option<(&'a String, &'a Vec<f32>)> {
    prompts.prompts.get_key_value(text).or_else(|| {
        let t = text.trim();
        prompts
            .prompts
            .iter()
            .find(|(k, _)| k.trim().eq_ignore_ascii_case(t))
    })
}

/// Builds a query from a prompt text of `prompts` (`path` names the file in errors) or from a
/// given vector, with every other non-synonym prompt as a negative.
pub fn build_query(
    prompts: &Prompts,
    path: &Path,
    query: Result<&str, (&str, &[f32])>,
    opts: &TextOptions,
) -> Result<TextQuery, TextError> {
    let bad = |why: String| TextError::Invalid {
        path: path.to_path_buf(),
        why,
    };
    for (k, v) in &prompts.prompts {
        if v.len() != prompts.dim {
            return Err(bad(format!(
                "prompt \"{k}\" has {} values, the file says dim {}",
                v.len(),
                prompts.dim
            )));
        }
    }
    let (name, raw, self_key) = match query {
        Ok(text) => {
            let (k, v) = find_prompt(prompts, text).ok_or_else(|| {
                TextError::Refused(format!(
                    "\"{text}\" is not a prompt of {} (prompts: {}); give its vector with --text-feature",
                    path.display(),
                    prompts
                        .prompts
                        .keys()
                        .map(|k| format!("\"{k}\""))
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            })?;
            (k.clone(), v.as_slice(), Some(k.clone()))
        }
        Err((name, v)) => {
            if v.len() != prompts.dim {
                return Err(TextError::Refused(format!(
                    "{name}: the query vector has {} values, the prompts of {} have {}",
                    v.len(),
                    path.display(),
                    prompts.dim
                )));
            }
            (name.to_string(), v, None)
        }
    };
    let q = unit(raw).ok_or_else(|| {
        TextError::Refused(format!("{name}: the query vector is zero or not finite"))
    })?;
    let mut negatives = Vec::new();
    let mut synonyms = Vec::new();
    for (k, v) in &prompts.prompts {
        if self_key.as_ref() == Some(k) {
            continue;
        }
        let Some(n) = unit(v) else {
            return Err(bad(format!(
                "prompt \"{k}\" is a zero or non-finite vector"
            )));
        };
        if dot(&q, &n) >= opts.synonym_cos {
            synonyms.push(k.clone());
        } else {
            negatives.push((k.clone(), n));
        }
    }
    if negatives.is_empty() {
        return Err(TextError::Refused(format!(
            "{} holds no prompt to compare \"{name}\" against (a text query needs negatives: other prompts, or LERF's canonical phrases \"object\", \"things\", \"stuff\", \"texture\")",
            path.display()
        )));
    }
    Ok(TextQuery {
        query: name,
        vector: q,
        negatives,
        synonyms,
    })
}

/// The relevancy of unit feature `f` for `q` (module docs), and the negative that bounds it.
pub fn relevancy(q: &TextQuery, f: &[f32], temperature: f64) -> (f64, usize) {
    let fq = dot(f, &q.vector);
    let mut worst = (f64::INFINITY, 0);
    for (j, (_, n)) in q.negatives.iter().enumerate() {
        let r = 1.0 / (1.0 + (-temperature * (fq - dot(f, n))).exp());
        if r < worst.0 {
            worst = (r, j);
        }
    }
    worst
}

/// One text term's outcome.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TextMatch {
    pub query: String,
    pub threshold: f64,
    pub temperature: f64,
    pub negatives: Vec<String>,
    pub synonyms: Vec<String>,
    /// Labels with a feature that were scored.
    pub labels_scored: usize,
    /// Labels at or above the threshold.
    pub labels_matched: usize,
    /// Best relevancy over all scored labels (null when no label has a feature).
    pub best: Option<f64>,
    pub best_label: Option<i32>,
    /// The negative that bounds the best label's relevancy.
    pub best_against: Option<String>,
    /// Up to 5 best labels: (label id, relevancy).
    pub top: Vec<(i32, f64)>,
}

/// Scores every label: `(relevancy per label row (None without a feature), summary)`.
pub fn score_labels(
    q: &TextQuery,
    features: &LabelFeatures,
    label_ids: &[i32],
    opts: &TextOptions,
) -> (Vec<Option<f64>>, TextMatch) {
    use rayon::prelude::*;
    let scored: Vec<Option<(f64, usize)>> = features
        .rows
        .par_iter()
        .map(|row| row.as_ref().map(|f| relevancy(q, f, opts.temperature)))
        .collect();
    let scores: Vec<Option<f64>> = scored.iter().map(|s| s.map(|x| x.0)).collect();
    let mut ranked: Vec<(i32, f64, usize)> = scored
        .iter()
        .zip(label_ids)
        .filter_map(|(s, &id)| s.map(|(r, j)| (id, r, j)))
        .collect();
    ranked.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let m = TextMatch {
        query: q.query.clone(),
        threshold: opts.min_relevancy,
        temperature: opts.temperature,
        negatives: q.negatives.iter().map(|n| n.0.clone()).collect(),
        synonyms: q.synonyms.clone(),
        labels_scored: ranked.len(),
        labels_matched: ranked.iter().filter(|r| r.1 >= opts.min_relevancy).count(),
        best: ranked.first().map(|r| r.1),
        best_label: ranked.first().map(|r| r.0),
        best_against: ranked.first().map(|r| q.negatives[r.2].0.clone()),
        top: ranked.iter().take(5).map(|r| (r.0, r.1)).collect(),
    };
    (scores, m)
}

/// Sentence embeddings of texts (unit vectors): the model behind free text.
pub trait Embed {
    fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, TextError>;
}

impl Embed for crate::textembed::TextModel {
    fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, TextError> {
        Ok(crate::textembed::TextModel::embed(self, texts)?)
    }
}

impl Embed for crate::textembed::Lazy {
    fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, TextError> {
        Ok(self.get()?.embed(texts)?)
    }
}

/// What free text can resolve to.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", content = "name", rename_all = "lowercase")]
pub enum Candidate {
    /// A prompt of `prompts.json` (then scored against the label features like `text(P)`).
    Prompt(String),
    /// A CityGML class name (then selected like `class=NAME`).
    Class(String),
    /// An attribute name (then: the entities that have the attribute, inherited).
    Attribute(String),
}

/// Words of an identifier: namespace prefix dropped, camelCase and `_ - .` split, lowercase
/// (`bldg:WallSurface` → "wall surface", `measuredHeight` → "measured height").
pub fn words(name: &str) -> String {
    let local = name.rsplit(':').next().unwrap_or(name);
    let mut out = String::new();
    let mut prev: Option<char> = None;
    for c in local.chars() {
        if matches!(c, '_' | '-' | '.' | '@' | ' ') {
            prev = Some(' ');
            if !out.ends_with(' ') && !out.is_empty() {
                out.push(' ');
            }
            continue;
        }
        if c.is_uppercase() && prev.is_some_and(|p| p.is_lowercase() || p.is_ascii_digit()) {
            out.push(' ');
        }
        out.extend(c.to_lowercase());
        prev = Some(c);
    }
    out.trim().to_string()
}

impl Candidate {
    /// The phrase that is embedded: the prompt itself, or the name in words.
    pub fn phrase(&self) -> String {
        match self {
            Candidate::Prompt(p) => p.clone(),
            Candidate::Class(n) | Candidate::Attribute(n) => words(n),
        }
    }
}

impl std::fmt::Display for Candidate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Candidate::Prompt(p) => write!(f, "prompt \"{p}\""),
            Candidate::Class(n) => write!(f, "class {n}"),
            Candidate::Attribute(n) => write!(f, "attribute {n}"),
        }
    }
}

/// One free-text term's resolution.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FreeText {
    /// The text as given.
    pub query: String,
    /// The calibrated threshold of the margin ([`TextOptions::min_margin`]).
    pub threshold: f64,
    /// The candidate the text stands for; `None`: no match (the margin is below the
    /// threshold).
    pub resolved: Option<Candidate>,
    /// The nearest candidate and its cosine (also when there is no match).
    pub best: Candidate,
    pub cosine: f64,
    /// The canonical phrase nearest to the text, and its cosine.
    pub canonical: String,
    pub canonical_cosine: f64,
    /// `cosine − canonical_cosine`: the text matches when this is ≥ the threshold.
    pub margin: f64,
    /// Up to 5 nearest candidates with their cosines.
    pub top: Vec<(Candidate, f64)>,
    /// The text's content words ([`content_words`]) the resolution stands for: each one whose
    /// own nearest candidate is the resolved one, or that is a word of the resolved
    /// candidate's phrase (plural or not). Empty when nothing is resolved.
    #[serde(default)]
    pub used: Vec<String>,
    /// The content words the resolution does not stand for: one free-text term resolves to one
    /// prompt, class or attribute, so "windows of the tallest building" selects windows and
    /// says that "tallest" and "building" were not used.
    #[serde(default)]
    pub ignored: Vec<String>,
}

/// Words that carry no content of their own in a query.
const STOP_WORDS: [&str; 30] = [
    "a", "an", "the", "of", "in", "on", "at", "with", "and", "or", "to", "for", "by", "from",
    "that", "which", "is", "are", "all", "any", "some", "its", "their", "this", "these", "those",
    "show", "find", "select", "me",
];

/// The content words of a text: lowercase runs of letters and digits, stop words dropped, each
/// once, in order.
pub fn content_words(text: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for w in text
        .split(|c: char| !c.is_alphanumeric())
        .filter(|w| !w.is_empty())
        .map(str::to_lowercase)
    {
        if !STOP_WORDS.contains(&w.as_str()) && !out.contains(&w) {
            out.push(w);
        }
    }
    out
}

/// A word without a plural `s` (`windows` → `window`), for comparing words.
fn singular(w: &str) -> &str {
    match w.strip_suffix('s') {
        Some(s) if s.chars().count() >= 3 && !s.ends_with('s') => s,
        _ => w,
    }
}

/// Resolves free text `query` to the nearest of `candidates` by the cosine of their sentence
/// embeddings (ties: the earlier candidate), or to none when that cosine does not beat the
/// query's cosine with each [`CANONICAL`] phrase by `min_margin`.
pub fn resolve(
    query: &str,
    candidates: &[Candidate],
    model: &dyn Embed,
    min_margin: f64,
) -> Result<FreeText, TextError> {
    if candidates.is_empty() {
        return Err(TextError::Refused(format!(
            "\"{query}\": nothing to match free text against (no prompts, classes or attributes)"
        )));
    }
    let phrases: Vec<String> = candidates.iter().map(Candidate::phrase).collect();
    let words = content_words(query);
    // Each content word alone too, when there are several: which of them the result stands for.
    let alone: &[String] = if words.len() > 1 { &words } else { &[] };
    let mut texts: Vec<&str> = vec![query];
    texts.extend(CANONICAL);
    texts.extend(phrases.iter().map(String::as_str));
    texts.extend(alone.iter().map(String::as_str));
    let e = model.embed(&texts)?;
    let (q, rest) = e.split_first().expect("one embedding per text");
    let (canon, rest) = rest.split_at(CANONICAL.len());
    let (rest, word_vecs) = rest.split_at(phrases.len());
    let (canonical, canonical_cosine) = CANONICAL
        .iter()
        .zip(canon)
        .map(|(n, v)| (n.to_string(), dot(q, v)))
        .reduce(|a, b| if b.1 > a.1 { b } else { a }) // ties: the first
        .expect("canonical phrases");
    let mut ranked: Vec<(usize, f64)> = rest.iter().map(|c| dot(q, c)).enumerate().collect();
    ranked.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let (best, cosine) = ranked[0];
    let margin = cosine - canonical_cosine;
    let resolved = margin >= min_margin;
    let phrase_words: Vec<String> = content_words(&phrases[best])
        .iter()
        .map(|w| singular(w).to_string())
        .collect();
    let (mut used, mut ignored) = (Vec::new(), Vec::new());
    for (k, w) in words.iter().enumerate() {
        let own_nearest = word_vecs.get(k).map(|v| {
            rest.iter()
                .map(|c| dot(v, c))
                .enumerate()
                .fold(
                    (0, f64::NEG_INFINITY),
                    |a, (i, c)| if c > a.1 { (i, c) } else { a },
                )
                .0
        });
        let stands_for = words.len() == 1
            || own_nearest == Some(best)
            || phrase_words.iter().any(|p| p == singular(w));
        if resolved && stands_for {
            used.push(w.clone());
        } else {
            ignored.push(w.clone());
        }
    }
    Ok(FreeText {
        query: query.to_string(),
        threshold: min_margin,
        resolved: resolved.then(|| candidates[best].clone()),
        best: candidates[best].clone(),
        cosine,
        canonical,
        canonical_cosine,
        margin,
        top: ranked
            .iter()
            .take(5)
            .map(|&(i, c)| (candidates[i].clone(), c))
            .collect(),
        used,
        ignored,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn prompts(list: &[(&str, Vec<f32>)]) -> Prompts {
        Prompts {
            simulated: false,
            dim: list[0].1.len(),
            prompts: list
                .iter()
                .map(|(k, v)| (k.to_string(), v.clone()))
                .collect::<BTreeMap<_, _>>(),
            classes: BTreeMap::new(),
        }
    }

    #[test]
    fn relevancy_is_the_pairwise_softmax_against_the_worst_negative() {
        // Orthonormal axes: query e0, negatives e1, e2; a synonym close to e0.
        let p = prompts(&[
            ("car", vec![1.0, 0.0, 0.0, 0.0]),
            ("tree", vec![0.0, 1.0, 0.0, 0.0]),
            ("road", vec![0.0, 0.0, 1.0, 0.0]),
            ("automobile", vec![0.95, 0.0, 0.0, 0.31]),
        ]);
        let o = TextOptions::default();
        let q = build_query(&p, Path::new("p.json"), Ok(" CAR "), &o).unwrap();
        assert_eq!(q.query, "car");
        assert_eq!(q.synonyms, vec!["automobile".to_string()]);
        assert_eq!(q.negatives.len(), 2);
        // f = (0.6, 0.8, 0, 0): f·q = 0.6, f·tree = 0.8, f·road = 0 → min(σ(−2), σ(6)) = σ(−2).
        let (r, j) = relevancy(&q, &[0.6, 0.8, 0.0, 0.0], 10.0);
        let want = 1.0 / (1.0 + 2f64.exp());
        assert!((r - want).abs() < 1e-6, "{r} {want}"); // f32 inputs
        assert_eq!(q.negatives[j].0, "tree");
        // f = e0: σ(10) against both.
        let (r, _) = relevancy(&q, &[1.0, 0.0, 0.0, 0.0], 10.0);
        assert!((r - 1.0 / (1.0 + (-10f64).exp())).abs() < 1e-12);
        // Unknown prompt, wrong vector length, no negatives: refused with a reason.
        let e = build_query(&p, Path::new("p.json"), Ok("a bus"), &o)
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a prompt") && e.contains("\"tree\""), "{e}");
        let e = build_query(&p, Path::new("p.json"), Err(("q.npy", &[1.0, 0.0])), &o)
            .unwrap_err()
            .to_string();
        assert!(e.contains("2 values") && e.contains("have 4"), "{e}");
        let one = prompts(&[("car", vec![1.0, 0.0])]);
        let e = build_query(&one, Path::new("p.json"), Ok("car"), &o)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no prompt to compare"), "{e}");
    }

    /// A stand-in model: fixed unit vectors per text.
    struct Table(Vec<(&'static str, Vec<f32>)>);

    impl Embed for Table {
        fn embed(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, TextError> {
            texts
                .iter()
                .map(|t| {
                    self.0
                        .iter()
                        .find(|(k, _)| k == t)
                        .map(|(_, v)| unit(v).unwrap())
                        .ok_or_else(|| TextError::Refused(format!("no vector for {t:?}")))
                })
                .collect()
        }
    }

    #[test]
    fn free_text_resolves_to_the_nearest_candidate_beyond_the_canonical_margin() {
        // Axes: 0 car, 1 window, 2 the canonical phrases' direction, 3 other.
        let mut t = vec![
            ("a car", vec![1.0, 0.0, 0.0, 0.0]),
            ("window", vec![0.0, 1.0, 0.0, 0.0]),
            ("measured height", vec![0.0, 0.0, 0.0, 1.0]),
            ("automobile", vec![0.9, 0.0, 0.3, 0.0]),
            ("a submarine", vec![0.5, 0.0, 0.8, 0.0]),
        ];
        t.extend(CANONICAL.map(|c| (c, vec![0.0, 0.0, 1.0, 0.0])));
        let model = Table(t);
        let cands = [
            Candidate::Prompt("a car".into()),
            Candidate::Class("Window".into()),
            Candidate::Attribute("measuredHeight".into()),
        ];
        let f = resolve("automobile", &cands, &model, MIN_MARGIN).unwrap();
        let n = (0.81f64 + 0.09).sqrt();
        assert!((f.cosine - 0.9 / n).abs() < 1e-6 && (f.canonical_cosine - 0.3 / n).abs() < 1e-6);
        assert_eq!(f.resolved, Some(Candidate::Prompt("a car".into())));
        assert_eq!(f.top.len(), 3);
        // Nearest to "a car" (0.53), but nearer still to "object" (0.85): no match.
        let f = resolve("a submarine", &cands, &model, MIN_MARGIN).unwrap();
        assert_eq!(f.best, Candidate::Prompt("a car".into()));
        assert_eq!((f.resolved, f.canonical.as_str()), (None, "object"));
        assert!(f.margin < 0.0);
        // Class and attribute names are embedded in words.
        assert_eq!(words("bldg:WallSurface"), "wall surface");
        assert_eq!(words("measuredHeight"), "measured height");
        assert_eq!(words("@cityeditor:layer"), "layer");
        assert_eq!(words("storeys_above-ground2D"), "storeys above ground2 d");
        assert_eq!(cands[2].phrase(), "measured height");
        assert!(resolve("x", &[], &model, MIN_MARGIN).is_err());
    }

    /// A text of several content words says which of them its resolution stands for.
    #[test]
    fn free_text_names_the_words_it_used_and_those_it_ignored() {
        // Axes: 0 car, 1 window, 2 the canonical phrases' direction, 3 height.
        let mut t = vec![
            ("a car", vec![1.0, 0.0, 0.0, 0.0]),
            ("window", vec![0.0, 1.0, 0.0, 0.0]),
            ("measured height", vec![0.0, 0.0, 0.0, 1.0]),
            ("windows of the tallest building", vec![0.1, 0.9, 0.2, 0.3]),
            ("windows", vec![0.0, 1.0, 0.1, 0.0]),
            ("tallest", vec![0.0, 0.0, 0.3, 1.0]),
            ("building", vec![0.3, 0.1, 0.5, 0.2]),
            ("the car windows", vec![0.7, 0.7, 0.1, 0.0]),
            ("car", vec![1.0, 0.0, 0.1, 0.0]),
        ];
        t.extend(CANONICAL.map(|c| (c, vec![0.0, 0.0, 1.0, 0.0])));
        let model = Table(t);
        let cands = [
            Candidate::Prompt("a car".into()),
            Candidate::Class("Window".into()),
            Candidate::Attribute("measuredHeight".into()),
        ];
        assert_eq!(
            content_words("Windows of the tallest building"),
            ["windows", "tallest", "building"]
        );
        let f = resolve(
            "windows of the tallest building",
            &cands,
            &model,
            MIN_MARGIN,
        )
        .unwrap();
        assert_eq!(f.resolved, Some(Candidate::Class("Window".into())));
        assert_eq!(f.used, ["windows"]);
        assert_eq!(f.ignored, ["tallest", "building"]);
        // A tie between car and window goes to the earlier candidate, "a car": "windows" is
        // then the word left out.
        let f = resolve("the car windows", &cands, &model, MIN_MARGIN).unwrap();
        assert_eq!(f.resolved, Some(Candidate::Prompt("a car".into())));
        assert_eq!(
            (f.used, f.ignored),
            (vec!["car".to_string()], vec!["windows".to_string()])
        );
        // A single word is what it resolves to; nothing resolved uses nothing.
        let f = resolve("automobile", &cands, &model, MIN_MARGIN);
        assert!(f.is_err(), "no vector for automobile in this table");
        assert_eq!(singular("windows"), "window");
        assert_eq!(singular("glass"), "glass");
    }

    #[test]
    fn label_features_are_normalised_and_zero_rows_have_none() {
        let f = LabelFeatures::new(Path::new("f.npy"), 2, &[3.0, 4.0, 0.0, 0.0]).unwrap();
        assert_eq!(f.rows[0], Some(vec![0.6, 0.8]));
        assert_eq!(f.rows[1], None);
        let e = LabelFeatures::new(Path::new("f.npy"), 2, &[1.0, f32::NAN])
            .unwrap_err()
            .to_string();
        assert!(e.contains("row 0, column 1"), "{e}");
    }
}
