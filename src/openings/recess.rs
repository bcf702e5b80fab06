//! The geometric cue of the openings stage: windows and doors are **recessed** behind their
//! wall's plane (a reveal of a decimetre or more), so on an LoD2 wall, where the model has a
//! plain polygon, the pre-trained 3DGS scene stands behind the wall's own surface there.
//!
//! Per training view, with the 3DGS median depth of the contributions cache
//! ([`crate::cache::Cache::median_depth`]):
//! 1. each pixel whose raycast surface is a framed wall (not a model opening, and the same wall
//!    `guard_px` pixels up, down, left and right: no silhouette blur) gets the signed distance
//!    of its 3DGS point behind the wall's plane (positive: away from the camera);
//! 2. per wall the median of those distances is the wall's own offset in this view (an LoD2
//!    wall may stand a few decimetres off its facade; openings cover less than half a wall);
//! 3. pixels `recess_m[0]`–`recess_m[1]` behind that offset are *recessed*; the mask is opened
//!    (erode, dilate: radius 1) and split into connected components (OpenCV, 8-connected);
//! 4. a component of ≥ `min_px` pixels, ≥ `min_wall_share` of them on one wall, becomes a
//!    rectangle on that wall's plane exactly as a mask does (the raycast hits, back-projected,
//!    the `trim` quantiles), with the same size rule and an aspect ratio ≤ `max_aspect`.
//!    It is a door when its bottom lies within `door_sill_m` of the wall's bottom and it is
//!    at least `door_height_m` tall (its bottom then moves down to the wall's: the ground in
//!    front and the guard band cut it), else a window (facade practice: doors start at the
//!    ground, windows at a sill). Where masks with features join the same cluster, their
//!    classes decide (appearance tells doors from windows better).
//!
//! The components are strong candidates: they found and shape clusters like masks, and the
//! same cross-view rule (≥ `m_view` views) accepts them.
use std::collections::BTreeMap;

use ndarray::Array2;

use super::plane::WallFrame;
use super::{
    Candidate, OpeningsError, OpeningsOptions, ViewMaps, dominant_wall, plane_rect, quantile,
};
use crate::imageio::{self, Morph};

/// The recessed-region candidates of one view (module docs).
pub(super) fn candidates(
    rv: &ViewMaps<'_>,
    gs: &[f32],
    frames: &BTreeMap<i32, WallFrame>,
    opts: &OpeningsOptions,
    scale: f64,
) -> Result<Vec<Candidate>, OpeningsError> {
    let cam = &rv.view.camera;
    let (w, h) = (
        cam.intrinsics.width as usize,
        cam.intrinsics.height as usize,
    );
    let n = w * h;
    let centre = cam.pose.center();
    let to_world = cam.pose.rotation.transpose();
    let g = opts.guard_px;
    let same_around = |p: usize, s: i32| -> bool {
        let (x, y) = (p % w, p / w);
        x >= g
            && y >= g
            && x + g < w
            && y + g < h
            && rv.surface[p - g] == s
            && rv.surface[p + g] == s
            && rv.surface[p - g * w] == s
            && rv.surface[p + g * w] == s
    };
    // 1. Distance of the 3DGS point behind its wall's plane (scene units).
    let mut behind = vec![f64::NAN; n];
    let mut per_wall: BTreeMap<i32, Vec<f64>> = BTreeMap::new();
    for p in 0..n {
        let s = rv.surface[p];
        let d = gs[p];
        if s < 0 || rv.part[p] >= 0 || !d.is_finite() || !same_around(p, s) {
            continue;
        }
        let Some(fr) = frames.get(&s) else { continue };
        let ray = cam.pixel_ray((p % w) as f64 + 0.5, (p / w) as f64 + 0.5);
        if ray.z <= 0.0 {
            continue;
        }
        let q = centre + to_world * ray * (d as f64 / ray.z);
        // The plane's side facing the camera: away from the camera is positive.
        let away = if (fr.c - centre).dot(fr.n) >= 0.0 {
            fr.n
        } else {
            -fr.n
        };
        let b = (q - fr.c).dot(away);
        behind[p] = b;
        per_wall.entry(s).or_default().push(b);
    }
    // 2. Each wall's own offset in this view.
    let offset: BTreeMap<i32, f64> = per_wall
        .into_iter()
        .filter(|(_, v)| v.len() >= opts.min_px.max(1) * 4)
        .map(|(s, mut v)| {
            v.sort_by(f64::total_cmp);
            (s, quantile(&v, 0.5))
        })
        .collect();
    // 3. Recessed pixels, opened, in components.
    let [lo, hi] = opts.recess_m.map(|x| x * scale);
    let mask = Array2::from_shape_fn((h, w), |(y, x)| {
        let p = y * w + x;
        let b = behind[p];
        b.is_finite()
            && offset
                .get(&rv.surface[p])
                .is_some_and(|o| (lo..=hi).contains(&(b - o)))
    });
    let mask = imageio::morphology(&mask, Morph::Erode, 1)
        .and_then(|m| imageio::morphology(&m, Morph::Dilate, 1))
        .and_then(|m| imageio::connected_components(&m.mapv(u8::from)))
        .map_err(|e| OpeningsError::Invalid {
            path: std::path::PathBuf::from(&rv.view.name),
            why: format!("recess components: {e}"),
        })?;
    let (labels, areas) = mask;
    let mut comps: Vec<Vec<usize>> = vec![Vec::new(); areas.len()];
    for (p, &l) in labels.iter().enumerate() {
        if l > 0 && areas[l as usize] >= opts.min_px {
            comps[l as usize].push(p);
        }
    }
    // 4. Rectangles on the wall plane.
    let mut out = Vec::new();
    for px in comps.into_iter().filter(|c| !c.is_empty()) {
        let Some(wall) = dominant_wall(rv.surface, &px, opts.min_wall_share) else {
            continue;
        };
        let Some(fr) = frames.get(&wall) else {
            continue;
        };
        let Some(mut rect) = plane_rect(rv, fr, wall, &px, opts.trim) else {
            continue;
        };
        // A door starts at the ground: its bottom, cut by the guard band at the wall's
        // lower edge, goes down to the wall's bottom.
        let door = rect.0[1] - fr.extent.0[1] <= opts.door_sill_m * scale
            && rect.height() >= opts.door_height_m * scale;
        if door {
            rect.0[1] = fr.extent.0[1];
        }
        let [smin, smax] = opts.size_m;
        let ok = |x: f64| (smin * scale..=smax * scale).contains(&x);
        let (rw, rh) = (rect.width(), rect.height());
        if !(ok(rw) && ok(rh)) || rw.max(rh) > opts.max_aspect * rw.min(rh) {
            continue;
        }
        out.push(Candidate {
            view: rv.index,
            wall,
            rect,
            class: if door {
                crate::classes::DOOR
            } else {
                crate::classes::WINDOW
            },
            recess: true,
            strong: true,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;
    use crate::camera::{Camera, Distortion, Intrinsics, Pose, View};
    use crate::mesh::{FaceLabel, TriMesh};
    use crate::openings::plane::wall_frames;

    /// A 10 m × 6 m wall in the plane y = 10 (x ∈ [−5, 5], z ∈ [0, 6]) seen head-on from
    /// (0, 0, 3); the 3DGS depth is `gs(x, z)` at the wall's pixels.
    fn scene(gs_at: impl Fn(f64, f64) -> f64) -> (View, Vec<i32>, Vec<f32>, Vec<f32>, TriMesh) {
        let (w, h) = (200u32, 160u32);
        let cam = Camera {
            intrinsics: Intrinsics {
                width: w,
                height: h,
                fx: 100.0,
                fy: 100.0,
                cx: 100.0,
                cy: 80.0,
                distortion: Distortion::None,
            },
            pose: Pose::look_at(
                DVec3::new(0.0, 0.0, 3.0),
                DVec3::new(0.0, 10.0, 3.0),
                DVec3::Z,
            )
            .unwrap(),
        };
        let view = View {
            image_id: 1,
            camera_id: 1,
            name: "v.png".into(),
            camera: cam,
        };
        let n = (w * h) as usize;
        let (mut surface, mut city, mut gs) = (vec![-1; n], vec![f32::NAN; n], vec![f32::NAN; n]);
        for p in 0..n {
            // The camera looks along +y: a pixel's ray hits y = 10 at z-depth 10, at
            // x = 10·(u − cx)/fx and z = 3 − 10·(v − cy)/fy (image y is down).
            let (u, v) = ((p % w as usize) as f64 + 0.5, (p / w as usize) as f64 + 0.5);
            let (x, z) = (10.0 * (u - 100.0) / 100.0, 3.0 - 10.0 * (v - 80.0) / 100.0);
            if (-5.0..=5.0).contains(&x) && (0.0..=6.0).contains(&z) {
                surface[p] = 1;
                city[p] = 10.0;
                gs[p] = gs_at(x, z) as f32;
            }
        }
        let mesh = TriMesh {
            vertices: vec![
                [-5.0, 10.0, 0.0],
                [5.0, 10.0, 0.0],
                [5.0, 10.0, 6.0],
                [-5.0, 10.0, 6.0],
            ],
            faces: vec![[0, 1, 2], [0, 2, 3]],
            labels: vec![
                FaceLabel {
                    feature: 0,
                    surface: 1,
                    part: -1,
                };
                2
            ],
        };
        (view, surface, city, gs, mesh)
    }

    fn inside(x: f64, z: f64, r: [f64; 4]) -> bool {
        (r[0]..=r[2]).contains(&x) && (r[1]..=r[3]).contains(&z)
    }

    /// The candidates' rectangles as `[x0, z0, x1, z1]` in the scene, with their classes.
    fn found(offset: f64, gs_at: impl Fn(f64, f64) -> f64) -> Vec<([f64; 4], i32)> {
        let (view, surface, city, gs, mesh) = scene(|x, z| offset + gs_at(x, z));
        let part = vec![-1; surface.len()];
        let frames = wall_frames(&mesh, &[1], DVec3::Z, 0.3);
        let vm = ViewMaps {
            view: &view,
            index: 0,
            surface: &surface,
            part: &part,
            city: &city,
        };
        let opts = OpeningsOptions::default();
        let fr = frames[&1];
        candidates(&vm, &gs, &frames, &opts, 1.0)
            .unwrap()
            .into_iter()
            .map(|c| {
                let (a, b) = (
                    fr.to_scene([c.rect.0[0], c.rect.0[1]]),
                    fr.to_scene([c.rect.0[2], c.rect.0[3]]),
                );
                (
                    [a.x.min(b.x), a.z.min(b.z), a.x.max(b.x), a.z.max(b.z)],
                    c.class,
                )
            })
            .collect()
    }

    const WINDOW: [f64; 4] = [1.0, 2.0, 2.2, 3.5];
    const DOOR: [f64; 4] = [-3.0, 0.0, -2.0, 2.1];

    #[test]
    fn a_recessed_window_and_door_become_rectangles_on_the_wall_plane() {
        // Window 15 cm and door 20 cm behind the wall; the rest of the wall on its plane.
        for offset in [10.0, 10.3] {
            let got = found(offset, |x, z| {
                if inside(x, z, WINDOW) {
                    0.15
                } else if inside(x, z, DOOR) {
                    0.2
                } else {
                    0.0
                }
            });
            assert_eq!(got.len(), 2, "wall offset {offset}: {got:?}");
            let mut got = got;
            got.sort_by(|a, b| a.0[0].total_cmp(&b.0[0]));
            // One pixel is 0.1 m on the wall; the opening (erode, dilate) and the 2 % trim
            // move an edge by at most about a pixel and a half.
            for ((r, class), (want, want_class)) in got.iter().zip([
                (DOOR, crate::classes::DOOR),
                (WINDOW, crate::classes::WINDOW),
            ]) {
                assert_eq!(*class, want_class, "{r:?}");
                for k in 0..4 {
                    assert!(
                        (r[k] - want[k]).abs() <= 0.16,
                        "offset {offset}: {r:?} vs {want:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn regions_in_front_too_deep_or_too_small_are_no_candidates() {
        // In front of the wall (a person), 2 m behind (a passage), a 20 cm square recess.
        let got = found(10.0, |x, z| {
            if inside(x, z, WINDOW) {
                -0.5
            } else if inside(x, z, DOOR) {
                2.0
            } else if inside(x, z, [3.0, 4.0, 3.2, 4.2]) {
                0.15
            } else {
                0.0
            }
        });
        assert!(got.is_empty(), "{got:?}");
    }
}
