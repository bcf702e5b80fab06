//! Evaluating a selection over the semantic table: the city entities of `semantics.json` and the
//! labels of the fused label table (city labels = entities, image labels = mask groups).
//!
//! Term semantics (docs/query.md):
//! * `class=X` — entities of CityGML class X **or below one** (`Building` selects its parts,
//!   installations, surfaces and openings). 2.0 and 3.0 names are the same class
//!   (`Window` ≡ `WindowSurface`, `Door` ≡ `DoorSurface`); `Opening` = windows and doors,
//!   `BoundarySurface` = the six thematic surfaces. Image labels have no CityGML class.
//! * `level=L` — the entity's own level. `id=G` — the entity with gml:id G alone;
//!   `within(G)` — G and all its descendants.
//! * `category=C` — labels (city or image) whose evaluation class is C (`docs/design.md` class ids).
//! * `label=N` — label id N.
//! * `name OP value` — the entity's attribute `name`, **inherited**: an entity without it takes
//!   its nearest ancestor's value (so `measuredHeight>15` selects whole buildings). Numbers
//!   compare as numbers, a unit on the literal is converted to the entity's `name.uom` (a number
//!   without a unit is in the file's unit, and needs one when the file uses several); other
//!   values compare as text (`<`, `>` lexicographically: ISO dates order correctly). A list
//!   value matches when one element does (`!=`: when no element equals). A missing attribute
//!   satisfies no comparison, `!=` included (`not name=v` selects it).
//! * `text(P)` — labels whose feature's relevancy for prompt P reaches the threshold ([`super::text`]).
use std::cmp::Ordering;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};

use serde_json::Value;

use super::grammar::{Expr, Literal, Op, Term};
use super::text::{self, Candidate, FreeText, LabelFeatures, TextMatch, TextOptions, TextQuery};
use super::units;
use crate::citygml::{Class, Level};
use crate::classes;
use crate::labels::LabelTable;
use crate::sam::Prompts;
use crate::semantics::Entity;

/// Errors of a selection that parses but does not fit the scene (each names the column).
#[derive(Debug, thiserror::Error)]
pub enum SelectError {
    #[error("column {column}: {why}")]
    Invalid { column: usize, why: String },
    #[error(transparent)]
    Text(#[from] text::TextError),
}

/// Every class name `class=` accepts, CityGML 2.0 and 3.0 (local names).
pub const CLASSES: [Class; 14] = [
    Class::Building,
    Class::BuildingPart,
    Class::BuildingInstallation,
    Class::BuildingConstructiveElement,
    Class::WallSurface,
    Class::RoofSurface,
    Class::GroundSurface,
    Class::ClosureSurface,
    Class::OuterCeilingSurface,
    Class::OuterFloorSurface,
    Class::Window,
    Class::Door,
    Class::WindowSurface,
    Class::DoorSurface,
];

/// Abstract class names: the concrete classes they stand for.
const ABSTRACT: [(&str, &[Class]); 2] = [
    (
        "Opening",
        &[
            Class::Window,
            Class::Door,
            Class::WindowSurface,
            Class::DoorSurface,
        ],
    ),
    (
        "BoundarySurface",
        &[
            Class::WallSurface,
            Class::RoofSurface,
            Class::GroundSurface,
            Class::ClosureSurface,
            Class::OuterCeilingSurface,
            Class::OuterFloorSurface,
        ],
    ),
];

/// The concrete class names a `class=` name stands for (namespace prefix and case ignored),
/// or `None` for an unknown name.
pub fn class_names(name: &str) -> Option<Vec<&'static str>> {
    let local = name.rsplit(':').next().unwrap_or(name).trim();
    let local = local.strip_prefix('_').unwrap_or(local);
    let local = local
        .strip_prefix("Abstract")
        .filter(|s| !s.is_empty())
        .unwrap_or(local);
    if let Some((_, cs)) = ABSTRACT.iter().find(|(n, _)| n.eq_ignore_ascii_case(local)) {
        return Some(cs.iter().map(|c| c.name()).collect());
    }
    let c = CLASSES
        .iter()
        .find(|c| c.name().eq_ignore_ascii_case(local))?;
    Some(
        CLASSES
            .iter()
            .filter(|o| *o == c || (c.is_window() && o.is_window()) || (c.is_door() && o.is_door()))
            .map(|o| o.name())
            .collect(),
    )
}

/// What a selection is evaluated over.
pub struct Context<'a> {
    pub entities: &'a [Entity],
    pub labels: &'a LabelTable,
    /// Per-label features (rows ↔ `labels.labels`), for `text(…)`.
    pub features: Option<&'a LabelFeatures>,
    /// The prompts (and their file, for messages), for `text(…)`.
    pub prompts: Option<(&'a Prompts, &'a Path)>,
    /// Where the features would come from (for messages when they are missing).
    pub features_path: PathBuf,
    pub text: TextOptions,
    /// The sentence-embedding model that resolves free text (`text(…)` that is not a prompt);
    /// `None`: only prompts are accepted.
    pub embed: Option<&'a dyn text::Embed>,
}

/// The outcome of a selection over the table.
#[derive(Debug, Clone, PartialEq)]
pub struct Selected {
    /// Selected label ids, ascending.
    pub labels: Vec<i32>,
    /// Selected entity ids, ascending (entities without a label included).
    pub entities: Vec<i32>,
    /// Selected entities whose parent is not selected (the tops of the selected subtrees).
    pub roots: Vec<i32>,
    /// One per text term, in order.
    pub text: Vec<TextMatch>,
    /// Relevancy per label row of the first text term (for the SQLite table).
    pub relevancy: Option<Vec<Option<f64>>>,
    /// One per free-text term (a `text(…)` that is not a prompt), in order.
    pub free_text: Vec<FreeText>,
    /// Counts of comparisons that could not be made, as sentences.
    pub warnings: Vec<String>,
}

/// A row of the evaluation domain: a label of the table, or an entity without a label.
#[derive(Clone, Copy)]
struct Row {
    label: Option<usize>,
    entity: Option<usize>,
}

/// A checked term, ready to evaluate.
enum Check {
    Classes(BTreeSet<&'static str>),
    Level(Level),
    Id(usize),
    Within(usize),
    Category(i32),
    Label(i32),
    /// Index into the text results.
    Text(usize),
    /// Entities that have the attribute (own or inherited): free text resolved to its name.
    HasAttr(String),
    /// Nothing: free text that matches no candidate.
    Nothing,
    Attr {
        name: String,
        op: Op,
        value: Literal,
    },
}

enum Compiled {
    And(Box<Compiled>, Box<Compiled>),
    Or(Box<Compiled>, Box<Compiled>),
    Not(Box<Compiled>),
    Term(Check),
}

fn invalid(column: usize, why: impl Into<String>) -> SelectError {
    SelectError::Invalid {
        column,
        why: why.into(),
    }
}

/// Levenshtein distance (case-insensitive), for suggestions.
fn distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.to_lowercase().chars().collect();
    let b: Vec<char> = b.to_lowercase().chars().collect();
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.iter().enumerate() {
        let mut cur = vec![i + 1; b.len() + 1];
        for (j, cb) in b.iter().enumerate() {
            cur[j + 1] = (prev[j] + usize::from(ca != cb))
                .min(prev[j + 1] + 1)
                .min(cur[j] + 1);
        }
        prev = cur;
    }
    prev[b.len()]
}

/// " (did you mean `x`?)" for the nearest candidate within distance 3.
fn suggest<'a>(name: &str, candidates: impl Iterator<Item = &'a str>) -> String {
    candidates
        .map(|c| (distance(name, c), c))
        .filter(|(d, _)| *d <= 3)
        .min()
        .map(|(_, c)| format!(" (did you mean `{c}`?)"))
        .unwrap_or_default()
}

fn list<'a>(items: impl Iterator<Item = &'a str>, max: usize) -> String {
    let v: Vec<&str> = items.collect();
    let mut s = v.iter().take(max).copied().collect::<Vec<_>>().join(", ");
    if v.len() > max {
        s.push_str(&format!(", … ({} more)", v.len() - max));
    }
    s
}

/// How the values of one attribute look across the table.
#[derive(Default)]
struct AttrInfo {
    numbers: usize,
    texts: usize,
    has_uom: bool,
}

/// The indexes a selection needs, built once per table.
pub struct Index<'a> {
    entities: &'a [Entity],
    by_object_id: HashMap<&'a str, usize>,
    attrs: BTreeMap<&'a str, AttrInfo>,
}

impl<'a> Index<'a> {
    pub fn new(entities: &'a [Entity]) -> Index<'a> {
        let mut by_object_id = HashMap::with_capacity(entities.len());
        let mut attrs: BTreeMap<&str, AttrInfo> = BTreeMap::new();
        for (i, e) in entities.iter().enumerate() {
            by_object_id.entry(e.object_id.as_str()).or_insert(i);
            for (k, v) in &e.attributes {
                let a = attrs.entry(k.as_str()).or_default();
                let mut count = |v: &Value| match v {
                    Value::Number(_) => a.numbers += 1,
                    Value::Null => {}
                    _ => a.texts += 1,
                };
                match v {
                    Value::Array(xs) => xs.iter().for_each(&mut count),
                    v => count(v),
                }
            }
        }
        let uoms: Vec<String> = attrs
            .keys()
            .filter_map(|k| k.strip_suffix(".uom"))
            .map(String::from)
            .collect();
        for u in uoms {
            if let Some(a) = attrs.get_mut(u.as_str()) {
                a.has_uom = true;
            }
        }
        Index {
            entities,
            by_object_id,
            attrs,
        }
    }

    /// The entity with gml:id `id`.
    pub fn entity(&self, id: &str) -> Option<usize> {
        self.by_object_id.get(id).copied()
    }

    /// `e` and its ancestors, nearest first (bounded: a damaged parent cycle cannot hang).
    fn ancestry(&self, e: usize) -> impl Iterator<Item = &'a Entity> + '_ {
        let mut cur = self.entities.get(e);
        let mut steps = 0usize;
        std::iter::from_fn(move || {
            let x = cur?;
            steps += 1;
            cur = if steps > self.entities.len() {
                None
            } else {
                x.parent.and_then(|p| self.entities.get(p as usize))
            };
            Some(x)
        })
    }
}

/// Compares an attribute value with a literal; `None` when they cannot be compared (a unit on
/// the literal that the entity's value does not carry, or incompatible units).
fn compare(v: &Value, uom: Option<&str>, lit: &Literal) -> Option<Ordering> {
    let as_number = |v: &Value| -> Option<f64> {
        match v {
            Value::Number(n) => n.as_f64(),
            Value::String(s) => s.trim().parse::<f64>().ok().filter(|x| x.is_finite()),
            _ => None,
        }
    };
    let as_text = |v: &Value| -> String {
        match v {
            Value::String(s) => s.clone(),
            v => v.to_string(),
        }
    };
    match lit {
        Literal::Number { value, unit, text } => {
            let target = match (unit, uom) {
                (None, _) => *value,
                (Some(u), Some(to)) => units::convert(*value, u, to)?,
                (Some(_), None) => return None,
            };
            match as_number(v) {
                Some(x) => x.partial_cmp(&target),
                None => Some(as_text(v).as_str().cmp(text.as_str())),
            }
        }
        Literal::Text(t) => Some(as_text(v).as_str().cmp(t.as_str())),
    }
}

/// Evaluates a parsed selection over the table.
pub fn evaluate(
    ctx: &Context<'_>,
    index: &Index<'_>,
    expr: &Expr,
) -> Result<Selected, SelectError> {
    ctx.text.validate()?;
    let mut texts: Vec<(Vec<Option<f64>>, TextMatch)> = Vec::new();
    let mut free: Vec<FreeText> = Vec::new();
    let compiled = compile(ctx, index, expr, &mut texts, &mut free)?;
    // The domain: every label, then the entities that have no label in the table.
    let mut rows: Vec<Row> = Vec::with_capacity(ctx.labels.labels.len());
    let mut has_label = vec![false; ctx.entities.len()];
    for (i, l) in ctx.labels.labels.iter().enumerate() {
        let entity = l
            .entity
            .and_then(|e| usize::try_from(e).ok())
            .filter(|&e| e < ctx.entities.len());
        if let Some(e) = entity {
            has_label[e] = true;
        }
        rows.push(Row {
            label: Some(i),
            entity,
        });
    }
    rows.extend(
        (0..ctx.entities.len())
            .filter(|&e| !has_label[e])
            .map(|e| Row {
                label: None,
                entity: Some(e),
            }),
    );
    let mut skipped: BTreeMap<String, usize> = BTreeMap::new();
    let mut labels = Vec::new();
    let mut entity_sel = vec![false; ctx.entities.len()];
    for r in &rows {
        if eval(ctx, index, &compiled, r, &texts, &mut skipped) {
            if let Some(l) = r.label {
                labels.push(ctx.labels.labels[l].id);
            }
            if let Some(e) = r.entity {
                entity_sel[e] = true;
            }
        }
    }
    labels.sort_unstable();
    let entities: Vec<i32> = (0..ctx.entities.len() as i32)
        .filter(|&e| entity_sel[e as usize])
        .collect();
    let roots = entities
        .iter()
        .copied()
        .filter(|&e| {
            ctx.entities[e as usize]
                .parent
                .is_none_or(|p| !entity_sel.get(p as usize).copied().unwrap_or(false))
        })
        .collect();
    let mut warnings: Vec<String> = skipped
        .into_iter()
        .map(|(k, n)| format!("{n} entities: {k}"))
        .collect();
    for f in free.iter().filter(|f| f.resolved.is_none()) {
        warnings.push(format!(
            "text(\"{}\"): no match — the nearest prompt, class or attribute, {} (cosine {:.3}), is not closer than the canonical phrase \"{}\" ({:.3}) by {:.2}; nothing selected",
            f.query, f.best, f.cosine, f.canonical, f.canonical_cosine, f.threshold
        ));
    }
    let relevancy = texts.first().map(|t| t.0.clone());
    Ok(Selected {
        labels,
        entities,
        roots,
        text: texts.into_iter().map(|t| t.1).collect(),
        relevancy,
        free_text: free,
        warnings,
    })
}

fn compile(
    ctx: &Context<'_>,
    index: &Index<'_>,
    e: &Expr,
    texts: &mut Vec<(Vec<Option<f64>>, TextMatch)>,
    free: &mut Vec<FreeText>,
) -> Result<Compiled, SelectError> {
    Ok(match e {
        Expr::And(a, b) => Compiled::And(
            Box::new(compile(ctx, index, a, texts, free)?),
            Box::new(compile(ctx, index, b, texts, free)?),
        ),
        Expr::Or(a, b) => Compiled::Or(
            Box::new(compile(ctx, index, a, texts, free)?),
            Box::new(compile(ctx, index, b, texts, free)?),
        ),
        Expr::Not(a) => Compiled::Not(Box::new(compile(ctx, index, a, texts, free)?)),
        Expr::TextFeature { path, vector } => Compiled::Term(text_term(
            ctx,
            Err((path.as_str(), vector.as_slice())),
            1,
            texts,
        )?),
        Expr::Term(t) => Compiled::Term(check(ctx, index, t, texts, free)?),
    })
}

fn text_term(
    ctx: &Context<'_>,
    query: Result<&str, (&str, &[f32])>,
    column: usize,
    texts: &mut Vec<(Vec<Option<f64>>, TextMatch)>,
) -> Result<Check, SelectError> {
    let Some((prompts, ppath)) = ctx.prompts else {
        return Err(invalid(
            column,
            "text queries need the scene's features/prompts.json (the prompts and the negatives to compare against); this scene has none",
        ));
    };
    let Some(features) = ctx.features else {
        return Err(invalid(
            column,
            format!(
                "text queries need per-label features ({}), which this run does not have (the fuse stage writes them when the scene has features/)",
                ctx.features_path.display()
            ),
        ));
    };
    if features.dim != prompts.dim {
        return Err(invalid(
            column,
            format!(
                "the label features ({}) have dimension {}, the prompts ({}) {}",
                ctx.features_path.display(),
                features.dim,
                ppath.display(),
                prompts.dim
            ),
        ));
    }
    let q: TextQuery = text::build_query(prompts, ppath, query, &ctx.text)
        .map_err(|e| invalid(column, e.to_string()))?;
    let ids: Vec<i32> = ctx.labels.labels.iter().map(|l| l.id).collect();
    texts.push(text::score_labels(&q, features, &ids, &ctx.text));
    Ok(Check::Text(texts.len() - 1))
}

/// The candidates of free text: the prompts (when the run has label features to score them),
/// the CityGML class names, the attribute names of the table.
pub fn candidates(ctx: &Context<'_>, index: &Index<'_>) -> Vec<Candidate> {
    let mut out = Vec::new();
    if let (Some((prompts, _)), Some(f)) = (ctx.prompts, ctx.features) {
        if f.dim == prompts.dim {
            out.extend(prompts.prompts.keys().cloned().map(Candidate::Prompt));
        }
    }
    out.extend(
        CLASSES
            .iter()
            .map(|c| Candidate::Class(c.name().to_string())),
    );
    out.extend(
        index
            .attrs
            .keys()
            .filter(|k| !k.ends_with(".uom"))
            .map(|k| Candidate::Attribute(k.to_string())),
    );
    out
}

/// `text(T)` where T is not a prompt: resolved to a prompt, a class or an attribute
/// ([`text::resolve`]), or to nothing.
fn free_text_term(
    ctx: &Context<'_>,
    index: &Index<'_>,
    query: &str,
    column: usize,
    texts: &mut Vec<(Vec<Option<f64>>, TextMatch)>,
    free: &mut Vec<FreeText>,
) -> Result<Check, SelectError> {
    let not_prompt = match ctx.prompts {
        Some((p, path)) => format!(
            "\"{query}\" is not a prompt of {} (prompts: {})",
            path.display(),
            p.prompts
                .keys()
                .map(|k| format!("\"{k}\""))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        None => format!("\"{query}\" is free text (the scene has no features/prompts.json)"),
    };
    let Some(model) = ctx.embed else {
        return Err(invalid(
            column,
            format!("{not_prompt}, and free text needs a sentence-embedding model"),
        ));
    };
    let f = text::resolve(query, &candidates(ctx, index), model, ctx.text.min_margin)
        .map_err(|e| invalid(column, format!("{not_prompt}; {e}")))?;
    let c = match &f.resolved {
        None => Check::Nothing,
        Some(Candidate::Prompt(p)) => text_term(ctx, Ok(p.as_str()), column, texts)?,
        Some(Candidate::Class(n)) => Check::Classes(
            class_names(n)
                .expect("a name of CLASSES")
                .into_iter()
                .collect(),
        ),
        Some(Candidate::Attribute(a)) => Check::HasAttr(a.clone()),
    };
    free.push(f);
    Ok(c)
}

fn check(
    ctx: &Context<'_>,
    index: &Index<'_>,
    t: &Term,
    texts: &mut Vec<(Vec<Option<f64>>, TextMatch)>,
    free: &mut Vec<FreeText>,
) -> Result<Check, SelectError> {
    Ok(match t {
        Term::Class { name, column } => {
            let names = class_names(name).ok_or_else(|| {
                let all = CLASSES
                    .iter()
                    .map(|c| c.name())
                    .chain(ABSTRACT.iter().map(|a| a.0));
                invalid(
                    *column,
                    format!(
                        "unknown CityGML class `{name}`{}; known: {}",
                        suggest(name, all.clone()),
                        list(all, 20)
                    ),
                )
            })?;
            Check::Classes(names.into_iter().collect())
        }
        Term::Level { name, column } => match name.to_ascii_lowercase().as_str() {
            "feature" => Check::Level(Level::Feature),
            "surface" => Check::Level(Level::Surface),
            "part" => Check::Level(Level::Part),
            _ => {
                return Err(invalid(
                    *column,
                    format!("unknown level `{name}`; levels: feature, surface, part"),
                ));
            }
        },
        Term::Id { id, column } | Term::Within { id, column } => {
            let e = index.entity(id).ok_or_else(|| {
                invalid(
                    *column,
                    format!(
                        "no entity has gml:id `{id}`{}",
                        suggest(id, ctx.entities.iter().map(|e| e.object_id.as_str()))
                    ),
                )
            })?;
            if matches!(t, Term::Id { .. }) {
                Check::Id(e)
            } else {
                Check::Within(e)
            }
        }
        Term::Category { name, column } => {
            let id = classes::NAMES
                .iter()
                .position(|n| n.eq_ignore_ascii_case(name))
                .ok_or_else(|| {
                    invalid(
                        *column,
                        format!(
                            "unknown category `{name}`{}; categories: {}",
                            suggest(name, classes::NAMES.iter().copied()),
                            classes::NAMES.join(", ")
                        ),
                    )
                })?;
            Check::Category(id as i32)
        }
        Term::Label { id, column } => {
            let id = i32::try_from(*id)
                .ok()
                .filter(|&i| ctx.labels.get(i).is_some())
                .ok_or_else(|| invalid(*column, format!("label {id} is not in the label table")))?;
            Check::Label(id)
        }
        Term::Text { prompt, column } => {
            let is_prompt = ctx
                .prompts
                .is_some_and(|(p, _)| text::find_prompt(p, prompt).is_some());
            if is_prompt {
                text_term(ctx, Ok(prompt.as_str()), *column, texts)?
            } else {
                free_text_term(ctx, index, prompt, *column, texts, free)?
            }
        }
        Term::Attr {
            name,
            op,
            value,
            column,
        } => {
            let Some(info) = index.attrs.get(name.as_str()) else {
                return Err(invalid(
                    *column,
                    format!(
                        "unknown attribute `{name}`{}: no entity of semantics.json has it; attributes: {}",
                        suggest(name, index.attrs.keys().copied()),
                        list(
                            index.attrs.keys().copied().filter(|k| !k.ends_with(".uom")),
                            15
                        )
                    ),
                ));
            };
            let numeric_only = info.texts == 0 && info.numbers > 0;
            // The units the file uses for this attribute.
            let uoms: BTreeSet<&str> = ctx
                .entities
                .iter()
                .filter_map(|e| e.attributes.get(&format!("{name}.uom")))
                .filter_map(|v| v.as_str())
                .collect();
            match value {
                Literal::Number { unit: None, .. } if uoms.len() > 1 => {
                    return Err(invalid(
                        *column,
                        format!(
                            "attribute `{name}` comes in several units in semantics.json ({}): give the number a unit, e.g. `{name} {} 10 {}`",
                            uoms.iter().copied().collect::<Vec<_>>().join(", "),
                            op.as_str(),
                            units::normalise(uoms.iter().next().expect("two units"))
                        ),
                    ));
                }
                Literal::Number { unit: Some(u), .. } if !info.has_uom => {
                    return Err(invalid(
                        *column,
                        format!(
                            "attribute `{name}` has no unit in semantics.json (no `{name}.uom`): drop the unit `{u}`"
                        ),
                    ));
                }
                Literal::Number { unit: Some(u), .. } => {
                    // Every unit the file uses for this attribute must be convertible.
                    if let Some(bad) = uoms.iter().find(|to| units::convert(1.0, u, to).is_none()) {
                        return Err(invalid(
                            *column,
                            format!(
                                "unit `{u}` cannot be compared with `{name}` in `{bad}` (semantics.json)"
                            ),
                        ));
                    }
                }
                Literal::Text(t) if numeric_only && !matches!(op, Op::Eq | Op::Ne) => {
                    return Err(invalid(
                        *column,
                        format!(
                            "attribute `{name}` holds numbers: `{}` needs a number, found \"{t}\"",
                            op.as_str()
                        ),
                    ));
                }
                _ => {}
            }
            Check::Attr {
                name: name.clone(),
                op: *op,
                value: value.clone(),
            }
        }
    })
}

fn eval(
    ctx: &Context<'_>,
    index: &Index<'_>,
    c: &Compiled,
    r: &Row,
    texts: &[(Vec<Option<f64>>, TextMatch)],
    skipped: &mut BTreeMap<String, usize>,
) -> bool {
    match c {
        Compiled::And(a, b) => {
            eval(ctx, index, a, r, texts, skipped) && eval(ctx, index, b, r, texts, skipped)
        }
        Compiled::Or(a, b) => {
            eval(ctx, index, a, r, texts, skipped) || eval(ctx, index, b, r, texts, skipped)
        }
        Compiled::Not(a) => !eval(ctx, index, a, r, texts, skipped),
        Compiled::Term(t) => term(ctx, index, t, r, texts, skipped),
    }
}

fn term(
    ctx: &Context<'_>,
    index: &Index<'_>,
    t: &Check,
    r: &Row,
    texts: &[(Vec<Option<f64>>, TextMatch)],
    skipped: &mut BTreeMap<String, usize>,
) -> bool {
    let entity = r.entity;
    match t {
        Check::Classes(names) => {
            entity.is_some_and(|e| index.ancestry(e).any(|a| names.contains(a.class.name())))
        }
        Check::Level(l) => entity.is_some_and(|e| ctx.entities[e].level == *l),
        Check::Id(id) => entity == Some(*id),
        Check::Within(id) => {
            entity.is_some_and(|e| index.ancestry(e).any(|a| a.id as usize == *id))
        }
        Check::Category(c) => match r.label {
            Some(l) => ctx.labels.labels[l].class == *c,
            None => entity.is_some_and(|e| classes::of_entity(ctx.entities, e as i32) == *c),
        },
        Check::Label(id) => r.label.is_some_and(|l| ctx.labels.labels[l].id == *id),
        Check::HasAttr(name) => entity.is_some_and(|e| {
            index
                .ancestry(e)
                .any(|a| a.attributes.contains_key(name.as_str()))
        }),
        Check::Nothing => false,
        Check::Text(k) => r
            .label
            .and_then(|l| texts[*k].0[l])
            .is_some_and(|s| s >= ctx.text.min_relevancy),
        Check::Attr { name, op, value } => {
            let Some(e) = entity else { return false };
            let uom_key = format!("{name}.uom");
            // The nearest ancestor-or-self that has the attribute.
            let Some(holder) = index.ancestry(e).find(|a| a.attributes.contains_key(name)) else {
                return false;
            };
            let v = &holder.attributes[name];
            let uom = holder.attributes.get(&uom_key).and_then(|u| u.as_str());
            let mut cmp_one = |x: &Value| -> Option<bool> {
                if x.is_null() {
                    return Some(false);
                }
                match compare(x, uom, value) {
                    Some(o) => Some(if *op == Op::Ne {
                        o == Ordering::Equal
                    } else {
                        op.holds(o)
                    }),
                    None => {
                        *skipped
                            .entry(format!(
                                "`{name}` not compared with {value}: the value has no unit or an incompatible one"
                            ))
                            .or_insert(0) += 1;
                        None
                    }
                }
            };
            // For `!=`, `cmp_one` answers "equal?"; the term holds when no element is equal.
            let hits: Vec<Option<bool>> = match v {
                Value::Array(xs) => xs.iter().map(&mut cmp_one).collect(),
                x => vec![cmp_one(x)],
            };
            if hits.iter().any(|h| h.is_none()) {
                return false;
            }
            if *op == Op::Ne {
                !v.is_null() && !hits.contains(&Some(true))
            } else {
                hits.contains(&Some(true))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn class_names_cover_both_versions_and_abstract_classes() {
        assert_eq!(
            class_names("Window").unwrap(),
            vec!["Window", "WindowSurface"]
        );
        assert_eq!(
            class_names("con:WindowSurface").unwrap(),
            vec!["Window", "WindowSurface"]
        );
        assert_eq!(
            class_names("bldg:wallsurface").unwrap(),
            vec!["WallSurface"]
        );
        assert_eq!(class_names("_BoundarySurface").unwrap().len(), 6);
        assert_eq!(class_names("AbstractOpening").unwrap().len(), 4);
        assert!(class_names("Windw").is_none());
        assert_eq!(distance("Windw", "Window"), 1);
        assert_eq!(
            suggest("Windw", ["Door", "Window"].into_iter()),
            " (did you mean `Window`?)"
        );
    }

    #[test]
    fn comparisons_of_values() {
        let n = |v: f64, t: &str, u: Option<&str>| Literal::Number {
            value: v,
            text: t.into(),
            unit: u.map(String::from),
        };
        let j = |s: &str| serde_json::from_str::<Value>(s).unwrap();
        assert_eq!(
            compare(&j("16.3"), Some("m"), &n(10.0, "10", None)),
            Some(Ordering::Greater)
        );
        assert_eq!(
            compare(&j("16.3"), Some("m"), &n(1700.0, "1700", Some("cm"))),
            Some(Ordering::Less)
        );
        assert_eq!(
            compare(&j("16.3"), None, &n(1700.0, "1700", Some("cm"))),
            None
        );
        assert_eq!(
            compare(&j("\"211.9\""), None, &n(200.0, "200", None)),
            Some(Ordering::Greater)
        );
        assert_eq!(
            compare(&j("\"31001_1000\""), None, &n(1000.0, "1000", None)),
            Some("31001_1000".cmp("1000"))
        );
        assert_eq!(
            compare(
                &j("\"2020-09-01\""),
                None,
                &Literal::Text("2020-06-24".into())
            ),
            Some(Ordering::Greater)
        );
        assert_eq!(
            compare(&j("true"), None, &Literal::Text("true".into())),
            Some(Ordering::Equal)
        );
    }
}
