//! The raycasting stage's files: per view `<stem>.ids.npy` (int32 4×H×W: feature,
//! surface, part, city), `<stem>.depth.npy` (float32 H×W, NaN = no hit), on request
//! `<stem>.overlay.png` ([`Overlays`]), and the run summary.
use std::path::Path;
use std::time::Instant;

use ndarray::Array3;
use rayon::prelude::*;

use super::{RaycastError, RaycastOptions, TwoPassScene, ViewIds, raycast_view};
use crate::camera::View;
use crate::mesh::TriMesh;
use crate::{fsutil, idmap, imageio};

/// Per-view numbers of a run.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ViewSummary {
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Pixels with any hit.
    pub hit_pixels: usize,
    /// Pixels with a part id (final).
    pub part_pixels: usize,
    /// Pixels whose part was accepted by the part pass where single pass had none.
    pub recovered_pixels: usize,
    /// Distinct part ids among those pixels.
    pub recovered_parts: usize,
    /// Pixels whose ray could not be undistorted (traced as misses).
    pub undistort_failures: usize,
    /// Seconds spent raycasting this view (without file output).
    pub seconds: f64,
    /// Whether the overlay was blended over the input image (false without an overlay).
    pub overlay_blended: bool,
}

/// The numbers of one raycasting run (serialised into `summary.json` by the CLI).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RaycastSummary {
    pub views: usize,
    /// Primary rays (one per pixel); the part pass adds at most as many again.
    pub rays: u64,
    pub raycast_seconds: f64,
    pub rays_per_second: f64,
    pub scene_build_seconds: f64,
    pub faces: usize,
    pub part_faces: usize,
    pub tau_scene_units: f64,
    pub single_pass: bool,
    pub per_view: Vec<ViewSummary>,
}

/// The overlay PNGs `<stem>.overlay.png` of a raycasting run: pictures for a person to look
/// at, which no stage reads, so `gs4city run` writes none and `gs4city raycast` only with
/// `--overlays`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Overlays<'a> {
    /// No overlay.
    Off,
    /// The city-id colours, blended over `<dir>/<name>` where the folder is given and holds
    /// the view's image (of its size, or an integer multiple of it: box-averaged down).
    On(Option<&'a Path>),
}

/// A stable, distinct-looking colour per id (black for −1).
fn id_colour(id: i32) -> [u8; 3] {
    if id < 0 {
        return [0, 0, 0];
    }
    let mut x = (id as u32).wrapping_mul(0x9E37_79B9) ^ 0x5bd1_e995;
    x ^= x >> 15;
    x = x.wrapping_mul(0x2C1B_3C6D);
    x ^= x >> 12;
    [
        64 + (x & 0xBF) as u8,
        64 + ((x >> 8) & 0xBF) as u8,
        64 + ((x >> 16) & 0xBF) as u8,
    ]
}

/// The overlay: city-id colours, blended 50 % over `image` where given (same size); without
/// an image, the colours alone (id −1 is black, its own colour).
fn overlay(ids: &ViewIds, image: Option<&Array3<u8>>) -> Array3<u8> {
    let colour = |p: usize| {
        let id = ids.city[p];
        (image.is_none() || id >= 0).then(|| id_colour(id))
    };
    let alpha = if image.is_some() { 0.5 } else { 1.0 };
    imageio::blend_overlay(image, ids.height, ids.width, 0.0, alpha, 1.0, colour)
}

/// Runs the stage: builds the scenes once, raycasts every view and writes its files and
/// `summary.json` (last) into `out_dir`, with the overlays `overlays` asks for.
pub fn run(
    mesh: &TriMesh,
    views: &[View],
    opts: &RaycastOptions,
    overlays: Overlays<'_>,
    out_dir: &Path,
) -> Result<RaycastSummary, RaycastError> {
    opts.validate()?;
    for v in views {
        let k = &v.camera.intrinsics;
        if k.width == 0 || k.height == 0 {
            return Err(RaycastError::View {
                name: v.name.clone(),
                why: format!("empty image size {}×{}", k.width, k.height),
            });
        }
    }
    if let Some((name, why)) = crate::camera::stem_problems(views).into_iter().next() {
        return Err(RaycastError::View { name, why });
    }
    let t0 = Instant::now();
    let scene = TwoPassScene::build(mesh)?;
    fsutil::create_dir(out_dir)?;
    let _ = std::fs::remove_file(out_dir.join("summary.json"));
    let bar = crate::progress::Bar::new("raycast", views.len() as u64, "views");
    let (faces, part_faces) = scene.face_counts();
    // Each view is traced alone (its strips in parallel), so its `seconds` are its own; the
    // files of a pair of views (maps, PNG overlay: serial work per view) are then written
    // side by side. Summaries stay in view order: nothing depends on the number of threads.
    let write = |v: &View, ids: &ViewIds| -> Result<bool, RaycastError> {
        let (h, w) = (ids.height, ids.width);
        let stem = v.stem();
        idmap::write_raycast(
            out_dir,
            &stem,
            w,
            h,
            [&ids.feature, &ids.surface, &ids.part, &ids.city],
        )?;
        idmap::write_depth(out_dir, &stem, w, h, &ids.depth)?;
        let Overlays::On(images_dir) = overlays else {
            bar.inc(1);
            return Ok(false);
        };
        let image = images_dir
            .map(|d| d.join(&v.name))
            .filter(|p| p.is_file())
            .and_then(|p| match imageio::read_rgb_sized(&p, w, h) {
                Ok(img) => Some(img),
                Err(e) => {
                    log::warn!("raycast: {e}: its overlay is drawn on grey");
                    None
                }
            });
        imageio::write_png(
            &out_dir.join(format!("{stem}.overlay.png")),
            &overlay(ids, image.as_ref()),
        )?;
        bar.inc(1);
        Ok(image.is_some())
    };
    // Two views' maps in memory at once (one with a single thread): a 20 MP view's maps
    // take ≈ 0.5 GB.
    let width = rayon::current_num_threads().clamp(1, 2);
    let mut per_view = Vec::with_capacity(views.len());
    let (mut rays, mut seconds) = (0u64, 0.0f64);
    for group in views.chunks(width) {
        let traced: Vec<(ViewIds, f64)> = group
            .iter()
            .map(|v| {
                let t0 = Instant::now();
                let ids = raycast_view(&scene, &v.camera, opts);
                (ids, t0.elapsed().as_secs_f64())
            })
            .collect();
        let blended: Vec<Result<bool, RaycastError>> = group
            .par_iter()
            .zip(&traced)
            .map(|(v, (ids, _))| write(v, ids))
            .collect();
        for ((v, (ids, dt)), b) in group.iter().zip(traced).zip(blended) {
            seconds += dt;
            rays += (ids.width * ids.height) as u64;
            per_view.push(ViewSummary {
                name: v.name.clone(),
                width: ids.width as u32,
                height: ids.height as u32,
                hit_pixels: ids.face.iter().filter(|&&f| f >= 0).count(),
                part_pixels: ids.part_pixels(),
                recovered_pixels: ids.recovered_pixels(),
                recovered_parts: ids.recovered_parts(),
                undistort_failures: ids.undistort_failures,
                seconds: dt,
                overlay_blended: b?,
            });
        }
    }
    bar.finish();
    let summary = RaycastSummary {
        views: views.len(),
        rays,
        raycast_seconds: seconds,
        rays_per_second: if seconds > 0.0 {
            rays as f64 / seconds
        } else {
            0.0
        },
        scene_build_seconds: scene.build_seconds,
        faces,
        part_faces,
        tau_scene_units: opts.tau,
        single_pass: opts.single_pass,
        per_view,
    };
    crate::layout::Summary::write(&summary, out_dir)?;
    crate::progress::done(
        "raycast",
        &format!(
            "{} views, {:.1} M rays ({:.1} Mrays/s){}",
            summary.views,
            summary.rays as f64 / 1e6,
            summary.rays_per_second / 1e6,
            if opts.single_pass {
                ", single pass"
            } else {
                ""
            }
        ),
        t0.elapsed().as_secs_f64(),
    );
    Ok(summary)
}

impl crate::layout::Summary for RaycastSummary {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colours_are_stable_and_distinct() {
        assert_eq!(id_colour(-1), [0, 0, 0]);
        // Pinned values (the hash worked by hand in Python): a changed palette is a visible change.
        assert_eq!(id_colour(0), [66, 218, 237]);
        assert_eq!(id_colour(7), [78, 106, 120]);
        let cs: std::collections::BTreeSet<[u8; 3]> = (0..200).map(id_colour).collect();
        assert!(cs.len() > 195);
    }
}
