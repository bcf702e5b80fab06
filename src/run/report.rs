//! `report.html` of a run. At the top, SIMULATED when the scene says so (its own `scene.json`,
//! [`crate::scene::SceneMeta`]; never `gt/`), the exact command line, a link to `semantic.ply`
//! and the stages' loud warnings. Then what the run produced: the Gaussians per class, a
//! per-building table (Gaussians per class, the building's CityGML attributes) and per test view
//! the image, the semantic Gaussians in their class colours (composited from the run's
//! contributions cache), the ground-truth class overlay and the predicted class overlay side by
//! side, under a legend whose swatches are outlined (visible on white); the completeness report.
//! Then the scores (metrics tables, confusion matrix) and last the method's diagnostics
//! (thresholds chosen from the scene, time per stage, the masks stage's rules).
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use ndarray::Array3;
use rayon::prelude::*;

use super::StageReport;
use crate::camera::View;
use crate::classes;
use crate::eval::EvalSummary;
use crate::fsutil;
use crate::scene::Scene;

/// Errors of report writing.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error(transparent)]
    Image(#[from] crate::imageio::ImageError),
    #[error(transparent)]
    Npy(#[from] crate::npy::NpyError),
    #[error(transparent)]
    Fs(#[from] crate::fsutil::FsError),
    #[error(transparent)]
    Colmap(#[from] crate::colmap::ColmapError),
    #[error(transparent)]
    IdMap(#[from] crate::idmap::IdMapError),
    #[error("{path}: {why}")]
    Data { path: PathBuf, why: String },
    #[error(transparent)]
    Cache(#[from] crate::cache::CacheError),
}

/// Blends class colours over an image (α = 0.55 where a class is set).
pub fn overlay(img: &Array3<u8>, class: &[i32]) -> Array3<u8> {
    let (h, w, _) = img.dim();
    let colour = |p: usize| (class[p] >= 0).then(|| classes::color(class[p]));
    crate::imageio::blend_overlay(Some(img), h, w, 0.0, 0.55, 0.6, colour)
}

fn hstack(panels: &[Array3<u8>]) -> Array3<u8> {
    let (h, w, _) = panels[0].dim();
    let gap = 4;
    let total = panels.len() * w + (panels.len() - 1) * gap;
    let mut out = Array3::from_elem((h, total, 3), 255u8);
    for (i, p) in panels.iter().enumerate() {
        let x0 = i * (w + gap);
        out.slice_mut(ndarray::s![.., x0..x0 + w, ..]).assign(p);
    }
    out
}

fn read_map(path: &Path, h: usize, w: usize) -> Result<Vec<i32>, ReportError> {
    Ok(crate::idmap::read_checked(path, &[h, w], "for this view")?)
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// A relative path as a URL in an attribute: every byte but unreserved characters and `/`
/// percent-encoded (UTF-8), so names with spaces, `#`, `?`, `%` or non-ASCII letters link.
fn url(path: &str) -> String {
    let mut out = String::with_capacity(path.len());
    for b in path.bytes() {
        if b.is_ascii_alphanumeric() || b"-._~/".contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// What a report shows.
pub struct ReportInputs<'a> {
    pub scene: &'a Scene,
    /// The run folder (`report.html` and `report/` are written into it).
    pub out: &'a Path,
    /// The views shown: the test views, or (without any) a few training views.
    pub views: &'a [View],
    /// Whether `views` have predictions (test views): the prediction panel.
    pub predicted: bool,
    /// The folder of the scored predictions (`<stem>.class.npy`).
    pub predictions: &'a Path,
    pub stages: &'a [StageReport],
    pub eval: Option<&'a EvalSummary>,
    /// The masks stage's summary, when the run has one: its counts per rule and overlays.
    pub masks: Option<&'a crate::masks::MasksSummary>,
    /// The stages' loud lines (a stage that contributed almost nothing), shown first.
    pub warnings: &'a [String],
    /// Thresholds a stage chose from the scene, and why (e.g. the association's τ_sim).
    pub choices: &'a [String],
    /// The command line that made the run (shown as is).
    pub command: &'a str,
    /// The run's semantic PLY, when written (linked relative to `out`).
    pub semantic_ply: Option<&'a Path>,
    /// The run's per-Gaussian semantics (the class-coloured panels and the per-building table).
    pub semantics: Option<&'a crate::selection::SemanticRun>,
    /// The run's contributions cache: the class-coloured panels are composited from it
    /// (each pixel's kept list of α·T times its Gaussians' colours).
    pub cache: &'a crate::cache::Cache,
}

/// Quotes a command-line word for a POSIX shell when it needs it.
pub fn shell_word(w: &str) -> String {
    let plain = !w.is_empty()
        && w.chars()
            .all(|c| c.is_ascii_alphanumeric() || "_-./=:,+@%".contains(c));
    if plain {
        w.to_string()
    } else {
        format!("'{}'", w.replace('\'', "'\\''"))
    }
}

/// The per-building table: per root building its gml:id, Gaussians per building class and its
/// own attributes.
fn building_table(sr: &crate::selection::SemanticRun) -> String {
    let cols = crate::query::columns(sr);
    let shown: Vec<i32> = (classes::WALL..=classes::INSTALLATION).collect();
    let mut counts: std::collections::BTreeMap<i32, Vec<u64>> = Default::default();
    for (i, &b) in cols.building.iter().enumerate() {
        if b < 0 {
            continue;
        }
        let row = counts.entry(b).or_insert_with(|| vec![0; shown.len() + 2]);
        row[0] += 1;
        let c = sr.class_of[i];
        let k = shown
            .iter()
            .position(|&x| x == c)
            .map_or(shown.len() + 1, |k| k + 1);
        row[k] += 1;
    }
    let mut html = String::from(
        "<h2>Buildings</h2><p>Gaussians per building (the root of their label's hierarchy) and class; the building's own CityGML attributes.</p><table><tr><th>building (gml:id)</th><th>Gaussians</th>",
    );
    for &c in &shown {
        let _ = write!(html, "<th>{}</th>", classes::name(c));
    }
    html.push_str("<th>other</th><th>attributes</th></tr>");
    for e in sr.entities.iter().filter(|e| e.parent.is_none()) {
        let row = counts
            .get(&e.id)
            .cloned()
            .unwrap_or_else(|| vec![0; shown.len() + 2]);
        let _ = write!(
            html,
            "<tr><td style=\"text-align:left\">{}</td>",
            esc(&e.object_id)
        );
        for n in &row {
            let _ = write!(html, "<td>{n}</td>");
        }
        let attrs = crate::semantics::attribute_texts(&e.attributes);
        let _ = write!(
            html,
            "<td style=\"text-align:left\">{}</td></tr>",
            esc(&attrs.join(", "))
        );
    }
    html.push_str("</table>");
    html
}

/// The confusion matrix of the evaluation (pixel counts; row share in brackets).
fn confusion_table(c: &crate::eval::Confusion) -> String {
    let mut html = String::from(
        "<h3>Confusion matrix (dataset level, pixels; rows ground truth, columns prediction)</h3><table><tr><th></th>",
    );
    for col in &c.columns {
        let _ = write!(html, "<th>{}</th>", esc(col));
    }
    html.push_str("</tr>");
    for (name, row) in c.rows.iter().zip(&c.counts) {
        let total: u64 = row.iter().sum();
        let _ = write!(html, "<tr><th>{}</th>", esc(name));
        for &n in row {
            let share = if total > 0 {
                format!(" ({:.0} %)", 100.0 * n as f64 / total as f64)
            } else {
                String::new()
            };
            let _ = write!(html, "<td>{n}{share}</td>");
        }
        html.push_str("</tr>");
    }
    html.push_str("</table>");
    html
}

/// The class-coloured image of a cached view, composited from its lists instead of rendering
/// the scene again: per pixel `Σ α·T·colour` over the kept list, scaled to the pixel's whole
/// mass (kept + dropped: the dropped share, ≤ ε of it, takes the kept entries' mean colour),
/// plus `T` of white. The colour of a Gaussian is what the renderer shows for a Gaussian
/// painted in its class colour (SH degree 0 of `paint`'s DC term), so with complete lists the
/// image is the render's up to the cache's half-float weights.
fn composite(c: &crate::cache::ViewContrib, colours: &[[f32; 3]]) -> Array3<u8> {
    let (w, h) = (c.width, c.height);
    let mut out = Array3::<u8>::zeros((h, w, 3));
    for (p, px) in out
        .as_slice_mut()
        .expect("a fresh array is contiguous")
        .chunks_exact_mut(3)
        .enumerate()
    {
        let (ids, ws) = c.pixel(p);
        let (mut acc, mut kept) = ([0.0f32; 3], 0.0f32);
        for (&g, &wt) in ids.iter().zip(ws) {
            let col = colours.get(g as usize).copied().unwrap_or([0.0; 3]);
            for (a, v) in acc.iter_mut().zip(col) {
                *a += wt * v;
            }
            kept += wt;
        }
        let dropped = c.lists.residual.get(p).copied().unwrap_or(0.0);
        let scale = if kept > 0.0 {
            (kept + dropped) / kept
        } else {
            0.0
        };
        let t = 1.0 - c.alpha[p];
        for (o, a) in px.iter_mut().zip(acc) {
            *o = ((a * scale + t).clamp(0.0, 1.0) * 255.0).round() as u8;
        }
    }
    out
}

/// Each Gaussian's colour as the renderer shows a Gaussian painted in its class colour (SH
/// degree 0 of `paint`'s DC term), computed once per class (−1 and any unknown id:
/// `classes::color`).
fn class_colours(class_of: &[i32]) -> Vec<[f32; 3]> {
    let mut table: std::collections::BTreeMap<i32, [f32; 3]> = Default::default();
    class_of
        .iter()
        .map(|&k| {
            *table.entry(k).or_insert_with(|| {
                let dc = crate::splat::transform::dc_of_color(classes::color(k));
                crate::render::project::sh_color(&[dc], 0, glam::DVec3::Z)
            })
        })
        .collect()
}

/// The line at the top of a SIMULATED scene's report.
const SIMULATED_BANNER: &str = "<p style=\"background:#ffeaa0;border:3px solid #b80;padding:10px;\
     font-size:1.4em\"><b>SIMULATED scene.</b> Its Gaussians, images, masks and features were \
     made by <code>gs4city synth</code> from a real city model (the scene's own <code>scene.json\
     </code> says so): the results below measure the method on simulated data, not a real \
     capture.</p>";

/// The Gaussians per class of the run's semantic scene, in class order; unlabelled last.
fn class_table(class_of: &[i32]) -> String {
    let mut count = vec![0usize; classes::NAMES.len()];
    let mut none = 0usize;
    for &c in class_of {
        match usize::try_from(c).ok().filter(|&k| k < count.len()) {
            Some(k) => count[k] += 1,
            None => none += 1,
        }
    }
    let mut s = format!(
        "<h2>What the run produced: {} Gaussians by class</h2><table><tr><th>class</th><th>Gaussians</th><th>share</th></tr>",
        class_of.len()
    );
    let share = |n: usize| 100.0 * n as f64 / class_of.len().max(1) as f64;
    for (k, name) in classes::NAMES.iter().enumerate() {
        if count[k] > 0 {
            let [r, g, b] = classes::PALETTE[k];
            let _ = write!(
                s,
                "<tr><td style=\"text-align:left\"><span class=\"sw\" style=\"background:rgb({r},{g},{b})\"></span>{name}</td><td>{}</td><td>{:.1} %</td></tr>",
                count[k],
                share(count[k])
            );
        }
    }
    if none > 0 {
        let _ = write!(
            s,
            "<tr><td style=\"text-align:left\">no class</td><td>{none}</td><td>{:.1} %</td></tr>",
            share(none)
        );
    }
    s.push_str("</table>");
    s
}

/// Writes `out/report.html` and `out/report/<stem>.png`; returns the report path.
pub fn write(r: &ReportInputs<'_>) -> Result<PathBuf, ReportError> {
    let (scene, out) = (r.scene, r.out);
    let dir = out.join("report");
    crate::fsutil::create_dir(&dir)?;

    let simulated = scene.meta.simulated;
    let mut html = String::new();
    let _ = write!(
        html,
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>gs4city report{}</title><style>\
         body{{font-family:sans-serif;margin:2em;max-width:1400px}} table{{border-collapse:collapse;margin:1em 0}}\
         td,th{{border:1px solid #bbb;padding:3px 8px;text-align:right}} th{{background:#eee}} img{{max-width:100%}}\
         .sw{{display:inline-block;width:1em;height:1em;vertical-align:middle;margin:0 4px 0 12px;border:1px solid #333}}</style></head><body>",
        if simulated { " (SIMULATED scene)" } else { "" }
    );
    if simulated {
        html.push_str(SIMULATED_BANNER);
    }
    let _ = write!(
        html,
        "<h1>gs4city report</h1><p>Scene <code>{}</code>, run output <code>{}</code>.</p>",
        esc(&scene.root.display().to_string()),
        esc(&out.display().to_string())
    );
    let _ = write!(html, "<p>Command: <code>{}</code></p>", esc(r.command));
    if let Some(p) = r.semantic_ply {
        let rel = p.strip_prefix(out).unwrap_or(p);
        let _ = write!(
            html,
            "<p>Semantic Gaussians: <a href=\"{}\">{}</a> (the input PLY with label, class, feature_id, surface_id, part_id per Gaussian).</p>",
            url(&rel.display().to_string()),
            esc(&rel.display().to_string())
        );
    }
    for w in r.warnings {
        let _ = write!(
            html,
            "<p style=\"background:#fdd;border:2px solid #c00;padding:8px\"><b>Warning:</b> {}</p>",
            esc(w)
        );
    }
    // What the run produced first: its classes and buildings, then the test views in class
    // colours; the scores and the method's diagnostics after them.
    if let Some(sr) = r.semantics {
        html.push_str(&class_table(&sr.class_of));
        html.push_str(&building_table(sr));
    }
    // The panels: a ground-truth panel only where the scene has ground truth, a prediction only
    // for test views.
    let has_gt = scene.gt.is_some();
    let mut columns = vec!["image"];
    if r.semantics.is_some() {
        columns.push("semantic Gaussians in class colours (from the contributions cache)");
    }
    if has_gt {
        columns.push("ground truth");
    }
    if r.predicted {
        columns.push("prediction");
    }
    let _ = write!(
        html,
        "<h2>{}: {}</h2><p>",
        if r.predicted {
            "Test views"
        } else {
            "Views (the scene declares no test views: every view trains)"
        },
        columns.join(" | ")
    );
    for (k, name) in classes::NAMES.iter().enumerate() {
        let [r, g, b] = classes::PALETTE[k];
        let _ = write!(
            html,
            "<span class=\"sw\" style=\"background:rgb({r},{g},{b})\"></span>{name}"
        );
    }
    html.push_str("</p>");
    for v in r.views {
        let stem = &v.stem();
        let _ = write!(
            html,
            "<h3>{}</h3><img src=\"report/{}.png\">",
            esc(stem),
            url(stem)
        );
    }
    completeness_table(&mut html, r.out);
    if let Some(e) = r.eval {
        let _ = write!(
            html,
            "<h2>Metrics ({} test views{})</h2><pre>{}</pre>",
            e.images,
            e.mode
                .as_deref()
                .map_or(String::new(), |m| format!(", {m} predictions")),
            esc(&e.tables)
        );
        if let Some(t) = &e.by_query_tables {
            let _ = write!(
                html,
                "<h3>Query-driven evaluation (the paper's protocol: one selection per class)</h3><pre>{}</pre>",
                esc(t)
            );
        }
        if let Some(c) = &e.confusion {
            html.push_str(&confusion_table(c));
        }
    }
    html.push_str(
        "<h2>Method diagnostics</h2><p>How the stages ran: thresholds chosen from the scene, \
         time per stage, the masks stage's rules.</p>",
    );
    if !r.choices.is_empty() {
        html.push_str("<h3>Thresholds chosen from the scene</h3><ul>");
        for c in r.choices {
            let _ = write!(html, "<li>{}</li>", esc(c));
        }
        html.push_str("</ul>");
    }
    html.push_str(
        "<h3>Time per stage</h3><table><tr><th>stage</th><th>seconds now</th><th>resumed</th><th>seconds when computed</th></tr>",
    );
    for st in r.stages {
        let _ = write!(
            html,
            "<tr><td>{}</td><td>{:.2}</td><td>{}</td><td>{:.2}</td></tr>",
            st.stage, st.seconds, st.resumed, st.compute_seconds
        );
    }
    html.push_str("</table>");
    if let Some(m) = r.masks {
        let _ = write!(
            html,
            "<h3>Masks (paper §3.2): {} of {} kept ({:?} source, {:?} test)</h3><table><tr><th>rule</th><th>masks</th></tr>",
            m.kept, m.input, m.source, m.test
        );
        for (rule, n) in &m.rules {
            let _ = write!(html, "<tr><td>{}</td><td>{n}</td></tr>", esc(rule));
        }
        html.push_str(
            "</table><p>Kept masks by rule: blue low overlap, orange features, red occluder (depth), \
             magenta occluder and features, green mask-free component.</p>",
        );
        for o in &m.overlays {
            let _ = write!(html, "<h4>{}</h4><img src=\"masks/{}\">", esc(o), url(o));
        }
    }
    let cache = r.cache;
    // Each Gaussian's class colour, when the run has per-Gaussian semantics.
    let colours = match r.semantics {
        Some(sr) if !r.views.is_empty() => {
            if cache.summary.gaussians != sr.class_of.len() {
                return Err(ReportError::Data {
                    path: cache.dir.clone(),
                    why: format!(
                        "the cache indexes {} Gaussians, the run labels {}",
                        cache.summary.gaussians,
                        sr.class_of.len()
                    ),
                });
            }
            Some(class_colours(&sr.class_of))
        }
        _ => None,
    };
    // One panel per test view (image | class colours | truth | prediction), views side by
    // side; the HTML lists them in view order.
    let panel = |v: &View| -> Result<(), ReportError> {
        let stem = &v.stem();
        let (w, h) = (
            v.camera.intrinsics.width as usize,
            v.camera.intrinsics.height as usize,
        );
        // The image is only shown: one that cannot be decoded (cut short, empty) or has another
        // size than the camera is a grey panel with a warning, as `gs4city check` promises.
        let grey = || Array3::from_elem((h, w, 3), 128u8);
        let img = match scene.images.as_ref().map(|d| d.join(&v.name)) {
            Some(p) if p.is_file() => match crate::imageio::read_rgb(&p) {
                Ok(img) if img.dim() == (h, w, 3) => img,
                Ok(img) => {
                    log::warn!(
                        "report: {}: {}×{} pixels, the camera's are {w}×{h}: a grey panel instead",
                        p.display(),
                        img.dim().1,
                        img.dim().0
                    );
                    grey()
                }
                Err(e) => {
                    log::warn!("report: {e}: a grey panel instead");
                    grey()
                }
            },
            _ => grey(),
        };
        let mut panels = vec![img.clone()];
        if let Some(colours) = &colours {
            let c = cache.load(stem)?;
            if (c.width, c.height) != (w, h) {
                return Err(ReportError::Data {
                    path: crate::cache::cache_file(&cache.dir, stem),
                    why: format!("{}×{} pixels, the camera has {w}×{h}", c.width, c.height),
                });
            }
            panels.push(composite(&c, colours));
        }
        if let Some(g) = &scene.gt {
            let p = crate::idmap::class_file(g, stem);
            let gt = if p.is_file() {
                read_map(&p, h, w)?
            } else {
                vec![-1; w * h]
            };
            panels.push(overlay(&img, &gt));
        }
        if r.predicted {
            let pred = read_map(&crate::idmap::class_file(r.predictions, stem), h, w)?;
            panels.push(overlay(&img, &pred));
        }
        crate::imageio::write_png(&dir.join(format!("{stem}.png")), &hstack(&panels))?;
        Ok(())
    };
    // Two views at once (each holds its decoded cache view); the first failing view in view
    // order is the one reported.
    for pair in r.views.chunks(2) {
        let done: Vec<Result<(), ReportError>> = pair.par_iter().map(panel).collect();
        done.into_iter().collect::<Result<Vec<()>, _>>()?;
    }
    html.push_str("</body></html>\n");
    let path = out.join("report.html");
    crate::fsutil::write_bytes(&path, html.as_bytes())?;
    Ok(path)
}

/// The completeness report of `R/openings/completeness.json` (docs/completeness.md), when the
/// run has one: per building the model's openings, those the images confirm, those the model
/// lacks and those no image supports; then every finding with its polygon.
fn completeness_table(html: &mut String, out: &Path) {
    let p = out.join("openings/completeness.json");
    let Ok(c) = fsutil::read_json::<crate::openings::Completeness>(&p) else {
        return;
    };
    let _ = write!(
        html,
        "<h2>City-model completeness: {} openings the images show but the model lacks, {} model \
         openings no image supports</h2><p>Machine-readable: <a href=\"openings/completeness.city.json\">\
         openings/completeness.city.json</a> (CityJSON 2.0), <a href=\"openings/completeness.json\">\
         openings/completeness.json</a>.</p><table><tr><th>building</th><th>model openings</th>\
         <th>confirmed by images</th><th>missing in model</th><th>unsupported</th></tr>",
        c.missing_in_model.len(),
        c.unsupported.len()
    );
    for b in c
        .buildings
        .iter()
        .filter(|b| b.model_openings + b.missing_in_model > 0)
    {
        let _ = write!(
            html,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(&b.object_id),
            b.model_openings,
            b.confirmed,
            b.missing_in_model,
            b.unsupported
        );
    }
    html.push_str("</table><table><tr><th>finding</th><th>class</th><th>id</th><th>wall</th><th>views</th><th>size (m)</th><th>polygon (CRS)</th></tr>");
    let rows = c
        .missing_in_model
        .iter()
        .map(|o| ("missing in model", o))
        .chain(c.unsupported.iter().map(|o| ("unsupported", o)));
    for (what, o) in rows {
        let poly: Vec<String> = o
            .polygon
            .iter()
            .map(|q| format!("({:.2}, {:.2}, {:.2})", q[0], q[1], q[2]))
            .collect();
        let _ = write!(
            html,
            "<tr><td>{what}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.2} × {:.2}</td><td>{}</td></tr>",
            esc(&o.class),
            esc(&o.object_id),
            esc(&o.wall_object_id),
            o.views,
            o.rect_m[2] - o.rect_m[0],
            o.rect_m[3] - o.rect_m[1],
            esc(&poly.join(" "))
        );
    }
    html.push_str("</table>");
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cache::CacheOptions;
    use crate::render::tests::{camera_at, random_scene};

    /// The panel composited from the cache against the scene painted and rendered again (the
    /// reference): with complete lists only the half-float weights differ; with the default
    /// mass rule the dropped mass takes the kept mean colour.
    #[test]
    fn the_cached_panel_matches_the_painted_render() {
        let scene = random_scene(6000, 6.0, 23);
        let n = scene.len();
        let class_of: Vec<i32> = (0..n).map(|i| (i % 9) as i32 - 1).collect();
        // The reference: every Gaussian painted in its class colour, rendered on white.
        let mut painted = scene.clone();
        for (i, &k) in class_of.iter().enumerate() {
            painted.sh[i * painted.coeffs] =
                crate::splat::transform::dc_of_color(classes::color(k));
            for c in 1..painted.coeffs {
                painted.sh[i * painted.coeffs + c] = [0.0; 3];
            }
        }
        let white = crate::render::RenderOptions {
            background: [1.0; 3],
            features: false,
            max_sh_degree: 0,
            ..Default::default()
        };
        let mut checked = 0;
        for (k, yaw) in [0.3f64, 2.0, -1.2].into_iter().enumerate() {
            let camera = camera_at(
                glam::DVec3::new(0.5, -0.3, -14.0),
                yaw * 0.1,
                0.05 * k as f64,
                120,
                90,
                110.0,
            );
            let view = View {
                image_id: k as u32,
                camera_id: 1,
                name: format!("v{k}.png"),
                camera,
            };
            let reference = crate::render::render_view(&painted, &camera, &white)
                .unwrap()
                .rgb8();
            // The view sees the scene: a blank white reference would make the test empty.
            let coloured = reference.iter().filter(|&&v| v < 200).count();
            assert!(
                coloured > reference.len() / 10,
                "view {k}: {coloured} coloured values"
            );
            for (opts, max_levels, mean_levels) in [
                (
                    CacheOptions {
                        top_k: 0,
                        epsilon: 0.0,
                        t_stop: 0.0,
                        alpha_min: crate::cache::INRIA_ALPHA_MIN,
                    },
                    2,
                    0.05,
                ),
                (
                    CacheOptions {
                        top_k: 32,
                        epsilon: 0.05,
                        t_stop: 0.0,
                        alpha_min: crate::cache::INRIA_ALPHA_MIN,
                    },
                    16,
                    2.5,
                ),
            ] {
                let c = crate::render::cache::contrib(&scene, &view, &opts).unwrap();
                let got = composite(&c, &class_colours(&class_of));
                assert_eq!(got.dim(), reference.dim());
                let d: Vec<i32> = got
                    .iter()
                    .zip(reference.iter())
                    .map(|(&a, &b)| (i32::from(a) - i32::from(b)).abs())
                    .collect();
                let max = *d.iter().max().unwrap();
                let mean = d.iter().map(|&x| f64::from(x)).sum::<f64>() / d.len() as f64;
                assert!(
                    max <= max_levels && mean <= mean_levels,
                    "view {k}, {opts:?}: max {max}, mean {mean}"
                );
                checked += d.iter().filter(|&&x| x == 0).count();
            }
        }
        // Most values agree exactly.
        assert!(checked > 3 * 2 * 120 * 90 * 3 / 2, "{checked}");
    }

    #[test]
    fn links_are_percent_encoded_and_text_escaped() {
        assert_eq!(url("report/orbit 000.png"), "report/orbit%20000.png");
        assert_eq!(url("masks/Ansicht-ü#1.png"), "masks/Ansicht-%C3%BC%231.png");
        assert_eq!(url("a-b_c.d~/e"), "a-b_c.d~/e");
        assert_eq!(esc("<a \"b\" & c>"), "&lt;a &quot;b&quot; &amp; c&gt;");
    }
}
