//! `report.html` of a run: per test view the image, the ground-truth class overlay and the
//! predicted class overlay side by side, the metrics table and the time per stage.
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use ndarray::Array3;

use crate::classes;
use crate::run::{Scene, StageReport};

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
    #[error("{path}: {why}")]
    Data { path: PathBuf, why: String },
}

/// Blends class colours over an image (α = 0.55 where a class is set).
pub fn overlay(img: &Array3<u8>, class: &[i32]) -> Array3<u8> {
    let (h, w, _) = img.dim();
    Array3::from_shape_fn((h, w, 3), |(y, x, c)| {
        let k = class[y * w + x];
        if k < 0 {
            (img[[y, x, c]] as f32 * 0.6) as u8
        } else {
            (img[[y, x, c]] as f32 * 0.45 + classes::color(k)[c] as f32 * 0.55).round() as u8
        }
    })
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
    let (shape, data) = crate::npy::read::<i32>(path)?;
    if shape != [h, w] {
        return Err(ReportError::Data {
            path: path.to_path_buf(),
            why: format!("shape {shape:?}, expected [{h}, {w}]"),
        });
    }
    Ok(data)
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

fn pct(v: &serde_json::Value) -> String {
    v.as_f64()
        .map_or("–".into(), |x| format!("{:.1}", 100.0 * x))
}

/// Writes `out/report.html` and `out/report/<stem>.png`; returns the report path.
pub fn write(
    scene: &Scene,
    out: &Path,
    stages: &[StageReport],
    metrics: Option<&serde_json::Value>,
) -> Result<PathBuf, ReportError> {
    let dir = out.join("report");
    crate::fsutil::create_dir(&dir)?;
    let test = crate::lift::test_views(&out.join("lift"));
    let views = crate::colmap::read_model(&scene.sparse)?;

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
    if let Some(m) = metrics {
        html.push_str("<h2>Metrics (test views)</h2><table><tr><th>protocol</th><th>coarse IoU</th><th>Acc.</th><th>Prec.</th><th>Rec.</th><th>mIoU</th>");
        for c in ["door", "roof", "wall", "window", "car", "person", "tree"] {
            let _ = write!(html, "<th>{c}</th>");
        }
        html.push_str("</tr>");
        let (p, d) = (&m["paper"], &m["dataset"]);
        let rows = [
            (
                "paper (per image)",
                [
                    &p["coarse"]["iou"]["mean"],
                    &p["coarse"]["accuracy"]["mean"],
                    &p["coarse"]["precision"]["mean"],
                    &p["coarse"]["recall"]["mean"],
                    &p["miou"]["mean"],
                ],
                "paper",
            ),
            (
                "dataset",
                [
                    &d["coarse"]["iou"],
                    &d["coarse"]["accuracy"],
                    &d["coarse"]["precision"],
                    &d["coarse"]["recall"],
                    &d["fine"]["miou"],
                ],
                "dataset",
            ),
        ];
        for (label, vals, proto) in rows {
            let _ = write!(html, "<tr><td>{label}</td>");
            for v in vals {
                let _ = write!(html, "<td>{}</td>", pct(v));
            }
            for c in ["door", "roof", "wall", "window", "car", "person", "tree"] {
                let v = if proto == "paper" {
                    &p["iou"][c]["mean"]
                } else {
                    &d["fine"]["iou"][c]
                };
                let _ = write!(html, "<td>{}</td>", pct(v));
            }
            html.push_str("</tr>");
        }
        html.push_str("</table><p>Values in %. Non-building classes cannot be predicted by the city-model vote alone and count as 0 where present.</p>");
    }
    html.push_str(
        "<h2>Time per stage</h2><table><tr><th>stage</th><th>seconds</th><th>resumed</th></tr>",
    );
    for st in stages {
        let _ = write!(
            html,
            "<tr><td>{}</td><td>{:.2}</td><td>{}</td></tr>",
            st.stage, st.seconds, st.resumed
        );
    }
    html.push_str("</table><h2>Test views: image | ground truth | prediction</h2><p>");
    for (k, name) in classes::NAMES.iter().enumerate() {
        let [r, g, b] = classes::PALETTE[k];
        let _ = write!(
            html,
            "<span class=\"sw\" style=\"background:rgb({r},{g},{b})\"></span>{name}"
        );
    }
    html.push_str("</p>");
    for stem in &test {
        let Some(v) = views.iter().find(|v| &v.stem() == stem) else {
            continue;
        };
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
        let pred = read_map(&out.join(format!("lift/{stem}.class.npy")), h, w)?;
        let gt = match scene
            .gt
            .as_ref()
            .map(|g| g.join(format!("{stem}.class.npy")))
        {
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
