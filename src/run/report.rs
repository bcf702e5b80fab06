//! `report.html` of a run: per test view the image, the ground-truth class overlay and the
//! predicted class overlay side by side, the metrics table and the time per stage.
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use ndarray::Array3;

use super::StageReport;
use crate::camera::View;
use crate::classes;
use crate::eval::EvalSummary;
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
}

/// What a report shows.
pub struct ReportInputs<'a> {
    pub scene: &'a Scene,
    /// The run folder (`report.html` and `report/` are written into it).
    pub out: &'a Path,
    /// The views shown (the test views).
    pub views: &'a [View],
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
}

/// Writes `out/report.html` and `out/report/<stem>.png`; returns the report path.
pub fn write(r: &ReportInputs<'_>) -> Result<PathBuf, ReportError> {
    let (scene, out) = (r.scene, r.out);
    let dir = out.join("report");
    crate::fsutil::create_dir(&dir)?;

    let mut html = String::new();
    let _ = write!(
        html,
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>gs4city report</title><style>\
         body{{font-family:sans-serif;margin:2em;max-width:1400px}} table{{border-collapse:collapse;margin:1em 0}}\
         td,th{{border:1px solid #bbb;padding:3px 8px;text-align:right}} th{{background:#eee}} img{{max-width:100%}}\
         .sw{{display:inline-block;width:1em;height:1em;vertical-align:middle;margin:0 4px 0 12px}}</style></head><body>\
         <h1>gs4city report</h1><p>Scene <code>{}</code>, run output <code>{}</code>.</p>",
        esc(&scene.root.display().to_string()),
        esc(&out.display().to_string())
    );
    for w in r.warnings {
        let _ = write!(
            html,
            "<p style=\"background:#fdd;border:2px solid #c00;padding:8px\"><b>Warning:</b> {}</p>",
            esc(w)
        );
    }
    if !r.choices.is_empty() {
        html.push_str("<h2>Thresholds chosen from the scene</h2><ul>");
        for c in r.choices {
            let _ = write!(html, "<li>{}</li>", esc(c));
        }
        html.push_str("</ul>");
    }
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
    }
    html.push_str(
        "<h2>Time per stage</h2><table><tr><th>stage</th><th>seconds now</th><th>resumed</th><th>seconds when computed</th></tr>",
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
            "<h2>Masks (paper §3.2): {} of {} kept ({:?} source, {:?} test)</h2><table><tr><th>rule</th><th>masks</th></tr>",
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
            let _ = write!(html, "<h3>{}</h3><img src=\"masks/{}\">", esc(o), esc(o));
        }
    }
    html.push_str("<h2>Test views: image | ground truth | prediction</h2><p>");
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
        let (w, h) = (
            v.camera.intrinsics.width as usize,
            v.camera.intrinsics.height as usize,
        );
        let img = match scene.images.as_ref().map(|d| d.join(&v.name)) {
            Some(p) if p.is_file() => crate::imageio::read_rgb(&p)?,
            _ => Array3::from_elem((h, w, 3), 128u8),
        };
        if img.dim() != (h, w, 3) {
            return Err(ReportError::Data {
                path: v.name.clone().into(),
                why: format!("image is {:?}, camera is {w}×{h}", img.dim()),
            });
        }
        let pred = read_map(&crate::idmap::class_file(r.predictions, stem), h, w)?;
        let gt = match scene.gt.as_ref().map(|g| crate::idmap::class_file(g, stem)) {
            Some(p) if p.is_file() => read_map(&p, h, w)?,
            _ => vec![-1; w * h],
        };
        let panel = hstack(&[img.clone(), overlay(&img, &gt), overlay(&img, &pred)]);
        crate::imageio::write_png(&dir.join(format!("{stem}.png")), &panel)?;
        let _ = write!(
            html,
            "<h3>{}</h3><img src=\"report/{}.png\">",
            esc(stem),
            esc(stem)
        );
    }
    html.push_str("</body></html>\n");
    let path = out.join("report.html");
    crate::fsutil::write_bytes(&path, html.as_bytes())?;
    Ok(path)
}
