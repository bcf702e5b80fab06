//! Building the contributions cache (format and readers: [`crate::cache`]): every view
//! rendered once with the lists of [`list_mode`] (top-k or the mass rule), weights rounded as
//! stored, two views at once, files coded and written on a second thread.
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;

use super::{ContributionMode, PreparedScene, RenderError, RenderOptions};
use crate::cache::{
    CacheError, CacheOptions, CacheSummary, CachedView, DEPTH_MIN_ALPHA, ViewContrib, cache_file,
    median_depth, round_weights,
};
use crate::camera::View;
use crate::fsutil;
use crate::progress::Bar;

/// Views rendered at once by [`build`].
const VIEWS_AT_ONCE: usize = 2;

/// The rasterizer's list rule of a cache: `epsilon > 0` keeps the largest weights until
/// `1 − ε` of the pixel's α·T mass, at most `top_k` of them (0 = no bound); `epsilon = 0`
/// keeps the `top_k` largest (0 = all).
pub fn list_mode(opts: &CacheOptions) -> ContributionMode {
    match (opts.epsilon > 0.0, opts.top_k) {
        (true, cap) => ContributionMode::Mass {
            epsilon: opts.epsilon,
            cap,
        },
        (false, 0) => ContributionMode::All,
        (false, k) => ContributionMode::TopK(k),
    }
}

/// Renders `view` with the lists of `opts` ([`list_mode`]), weights rounded as stored, and
/// the median depth of those lists.
pub fn contrib(
    scene: &PreparedScene,
    view: &View,
    opts: &CacheOptions,
) -> Result<ViewContrib, RenderError> {
    let mut v = contrib_unrounded(scene, view, opts)?;
    round_weights(&mut v.lists.weights);
    // The median depth of the stored (rounded) lists, as a reader would compute it.
    v.median = median_depth(&v, &scene.positions, &view.camera.pose);
    Ok(v)
}

/// [`contrib`] with the rasterizer's f32 weights (what the cache's rounding is
/// measured against).
pub fn contrib_unrounded(
    scene: &PreparedScene,
    view: &View,
    opts: &CacheOptions,
) -> Result<ViewContrib, RenderError> {
    let mode = list_mode(opts);
    let k = opts.top_k;
    // The cache keeps no colour: degree 0 skips the view-dependent SH evaluation, and the
    // blend skips the colour and median-depth images.
    let opts = RenderOptions {
        features: false,
        max_sh_degree: 0,
        images: false,
        contributions: mode,
        t_stop: opts.t_stop,
        alpha_min: opts.alpha_min,
        ..Default::default()
    };
    let out = super::render_view(scene, &view.camera, &opts).map_err(|e| match e {
        RenderError::Camera { why, .. } => RenderError::Camera {
            view: view.name.clone(),
            why,
        },
        e => e,
    })?;
    Ok(ViewContrib {
        width: out.width,
        height: out.height,
        k,
        gaussians: scene.len(),
        lists: out.contributions.unwrap_or_default(),
        alpha: out.alpha,
        depth: out.depth,
        median: Vec::new(),
    })
}

/// Renders every view once with the lists of `opts` ([`list_mode`]) and writes
/// `<stem>.contrib` per view and `summary.json` (last) into `out_dir`.
pub fn build(
    scene: &PreparedScene,
    views: &[View],
    opts: &CacheOptions,
    out_dir: &Path,
) -> Result<CacheSummary, RenderError> {
    opts.validate()?;
    super::check_inputs(scene, views)?;
    let t0 = Instant::now();
    fsutil::create_dir(out_dir)?;
    let _ = std::fs::remove_file(out_dir.join("summary.json"));
    let bar = Bar::new("render", views.len() as u64, "views");
    let mut summary = CacheSummary {
        gaussians: scene.len(),
        skipped_gaussians: scene.skipped,
        options: *opts,
        median_depth: true,
        views: Vec::with_capacity(views.len()),
        selection: None,
        bytes: 0,
        render_s: 0.0,
        write_s: 0.0,
        total_s: 0.0,
    };
    // Rendering (parallel over views and tiles) overlaps with writing the previous views'
    // files on a second thread; at most one finished view waits, so memory stays at
    // VIEWS_AT_ONCE + 2 views.
    let (tx, rx) = std::sync::mpsc::sync_channel::<(PathBuf, ViewContrib)>(1);
    let (written, sizes) = std::thread::scope(|sc| -> Result<(f64, Vec<u64>), RenderError> {
        let writer = sc.spawn(move || -> Result<(f64, Vec<u64>), CacheError> {
            let (mut secs, mut sizes) = (0.0, Vec::new());
            for (path, view) in rx {
                let t = Instant::now();
                sizes.push(view.write(&path)?);
                secs += t.elapsed().as_secs_f64();
            }
            Ok((secs, sizes))
        });
        let rendered = (|| -> Result<(), RenderError> {
            // Two views at once (one with a single thread): each view's serial steps (the
            // depth sort, assembling the lists) overlap with the other's parallel ones. Not
            // more: every view in flight holds its projected Gaussians (80 B each) and its
            // lists. Results are taken in view order, so the files and the summary do not
            // depend on the number of threads.
            let width = rayon::current_num_threads().clamp(1, VIEWS_AT_ONCE);
            for group in views.chunks(width) {
                let done: Vec<(Result<ViewContrib, RenderError>, f64)> = group
                    .par_iter()
                    .map(|v| {
                        let t = Instant::now();
                        (contrib(scene, v, opts), t.elapsed().as_secs_f64())
                    })
                    .collect();
                for (v, (c, render_s)) in group.iter().zip(done) {
                    let c = c?;
                    summary.render_s += render_s;
                    let npx = c.pixels();
                    let (mut covered, mut share) = (0usize, 0.0f64);
                    for p in 0..npx {
                        if c.alpha[p] >= DEPTH_MIN_ALPHA {
                            covered += 1;
                            share += f64::from(c.lists.residual[p]) / f64::from(c.alpha[p]);
                        }
                    }
                    summary.views.push(CachedView {
                        name: v.name.clone(),
                        stem: v.stem(),
                        width: c.width,
                        height: c.height,
                        entries: c.entries() as u64,
                        mean_list: c.entries() as f64 / npx as f64,
                        mean_dropped_share: if covered > 0 {
                            share / covered as f64
                        } else {
                            0.0
                        },
                        coverage: covered as f64 / npx as f64,
                        bytes: 0, // the writer's count, below
                        render_s,
                    });
                    if tx.send((cache_file(out_dir, &v.stem()), c)).is_err() {
                        return Ok(()); // the writer failed; its error is reported below
                    }
                    bar.inc(1);
                }
            }
            Ok(())
        })();
        drop(tx);
        let w = writer
            .join()
            .unwrap_or_else(|_| {
                Err(CacheError::Format {
                    path: out_dir.to_path_buf(),
                    why: "the writer thread panicked".into(),
                })
            })
            .map_err(RenderError::from);
        rendered?;
        w
    })?;
    summary.write_s = written;
    for (v, b) in summary.views.iter_mut().zip(sizes) {
        v.bytes = b;
        summary.bytes += b;
    }
    bar.finish();
    summary.total_s = t0.elapsed().as_secs_f64();
    crate::layout::Summary::write(&summary, out_dir)?;
    crate::progress::done(
        "render",
        &format!(
            "{} views cached, {}, {:.0} MB",
            views.len(),
            opts.describe(),
            summary.bytes as f64 / 1e6
        ),
        summary.total_s,
    );
    Ok(summary)
}
