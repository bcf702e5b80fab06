//! Wall frames: the plane of each wall surface of the city mesh with an in-plane frame
//! `(u, v)` (u horizontal, v up the wall), and axis-aligned rectangles in that frame.
use std::collections::BTreeMap;

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::mesh::TriMesh;

/// A wall's plane: origin `c` (area-weighted centroid of its own faces), unit normal `n`,
/// horizontal unit axis `u = up × n`, and `v = n × u` (up the wall); the extent of its own
/// faces in `(u, v)`; the feature id its faces carry.
#[derive(Debug, Clone, Copy)]
pub struct WallFrame {
    pub c: DVec3,
    pub n: DVec3,
    pub u: DVec3,
    pub v: DVec3,
    pub extent: Rect,
    pub feature: i32,
}

impl WallFrame {
    /// `(u, v)` of a scene-frame point.
    pub fn to_plane(&self, p: DVec3) -> [f64; 2] {
        let d = p - self.c;
        [d.dot(self.u), d.dot(self.v)]
    }

    /// The scene-frame point of `(u, v)` on the plane.
    pub fn to_scene(&self, uv: [f64; 2]) -> DVec3 {
        self.c + self.u * uv[0] + self.v * uv[1]
    }
}

/// An axis-aligned rectangle `[u0, v0, u1, v1]` on a wall plane (scene units).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Rect(pub [f64; 4]);

impl Rect {
    /// An empty rectangle that [`Rect::grow`] extends.
    pub fn empty() -> Rect {
        Rect([
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ])
    }

    /// Extends the rectangle by a point.
    pub fn grow(&mut self, p: [f64; 2]) {
        let r = &mut self.0;
        r[0] = r[0].min(p[0]);
        r[1] = r[1].min(p[1]);
        r[2] = r[2].max(p[0]);
        r[3] = r[3].max(p[1]);
    }

    pub fn width(&self) -> f64 {
        (self.0[2] - self.0[0]).max(0.0)
    }

    pub fn height(&self) -> f64 {
        (self.0[3] - self.0[1]).max(0.0)
    }

    pub fn area(&self) -> f64 {
        self.width() * self.height()
    }

    /// The intersection (empty: zero width or height).
    pub fn intersect(&self, o: &Rect) -> Rect {
        let (a, b) = (self.0, o.0);
        Rect([
            a[0].max(b[0]),
            a[1].max(b[1]),
            a[2].min(b[2]),
            a[3].min(b[3]),
        ])
    }

    /// Intersection over union (0 when either is empty).
    pub fn iou(&self, o: &Rect) -> f64 {
        let i = self.intersect(o).area();
        let u = self.area() + o.area() - i;
        if u > 0.0 { i / u } else { 0.0 }
    }

    /// Intersection over the smaller area (0 when either is empty).
    pub fn overlap_min(&self, o: &Rect) -> f64 {
        let i = self.intersect(o).area();
        let m = self.area().min(o.area());
        if m > 0.0 { i / m } else { 0.0 }
    }

    /// The four corners, counter-clockwise in `(u, v)`.
    pub fn corners(&self) -> [[f64; 2]; 4] {
        let r = self.0;
        [[r[0], r[1]], [r[2], r[1]], [r[2], r[3]], [r[0], r[3]]]
    }
}

/// The frame of every wall surface of `walls` that has faces of its own (surface = the wall,
/// part = −1) and is near vertical (`|n · up| ≤ max_tilt_cos`); `up` is the scene frame's up.
pub fn wall_frames(
    mesh: &TriMesh,
    walls: &[i32],
    up: DVec3,
    max_tilt_cos: f64,
) -> BTreeMap<i32, WallFrame> {
    let wanted: std::collections::BTreeSet<i32> = walls.iter().copied().collect();
    // Per wall: faces (as vertex triples) in mesh order.
    let mut faces: BTreeMap<i32, Vec<usize>> = BTreeMap::new();
    for (f, l) in mesh.labels.iter().enumerate() {
        if l.part == -1 && wanted.contains(&l.surface) {
            faces.entry(l.surface).or_default().push(f);
        }
    }
    let vert = |i: u32| -> DVec3 {
        let p = mesh.vertices[i as usize];
        DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64)
    };
    let mut out = BTreeMap::new();
    for (wall, fs) in faces {
        let tris: Vec<[DVec3; 3]> = fs
            .iter()
            .map(|&f| {
                let [a, b, c] = mesh.faces[f];
                [vert(a), vert(b), vert(c)]
            })
            .collect();
        let cross = |t: &[DVec3; 3]| (t[1] - t[0]).cross(t[2] - t[0]);
        // Reference orientation: the largest triangle (windings may differ across faces).
        let Some(reference) = tris
            .iter()
            .map(cross)
            .max_by(|a, b| a.length_squared().total_cmp(&b.length_squared()))
        else {
            continue;
        };
        let (mut n, mut c, mut area) = (DVec3::ZERO, DVec3::ZERO, 0.0);
        for t in &tris {
            let x = cross(t);
            let a = 0.5 * x.length();
            n += if x.dot(reference) < 0.0 { -x } else { x };
            c += (t[0] + t[1] + t[2]) / 3.0 * a;
            area += a;
        }
        let Some(n) = n.try_normalize() else { continue };
        if area <= 0.0 || n.dot(up).abs() > max_tilt_cos {
            continue;
        }
        let c = c / area;
        let Some(u) = up.cross(n).try_normalize() else {
            continue;
        };
        let v = n.cross(u);
        let mut frame = WallFrame {
            c,
            n,
            u,
            v,
            extent: Rect::empty(),
            feature: mesh.labels[fs[0]].feature,
        };
        let mut extent = Rect::empty();
        for t in &tris {
            for p in t {
                extent.grow(frame.to_plane(*p));
            }
        }
        frame.extent = extent;
        out.insert(wall, frame);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::FaceLabel;

    #[test]
    fn rect_overlaps_are_closed_forms() {
        let a = Rect([0.0, 0.0, 2.0, 2.0]);
        let b = Rect([1.0, 1.0, 3.0, 3.0]);
        assert!((a.iou(&b) - 1.0 / 7.0).abs() < 1e-12);
        assert!((a.overlap_min(&b) - 0.25).abs() < 1e-12);
        assert_eq!(a.iou(&Rect([5.0, 5.0, 6.0, 6.0])), 0.0);
    }

    #[test]
    fn a_wall_in_the_xz_plane_gets_u_along_x_and_v_up() {
        // A 4 m × 3 m wall at y = 2, two triangles of opposite winding.
        let mesh = TriMesh {
            vertices: vec![
                [0.0, 2.0, 0.0],
                [4.0, 2.0, 0.0],
                [4.0, 2.0, 3.0],
                [0.0, 2.0, 3.0],
            ],
            faces: vec![[0, 1, 2], [0, 3, 2]],
            labels: vec![
                FaceLabel {
                    feature: 0,
                    surface: 1,
                    part: -1,
                };
                2
            ],
        };
        let f = wall_frames(&mesh, &[1], DVec3::Z, 0.3);
        let w = f[&1];
        assert!((w.n.dot(DVec3::Y).abs() - 1.0).abs() < 1e-12);
        assert!((w.u.dot(DVec3::X).abs() - 1.0).abs() < 1e-12);
        assert!((w.v - DVec3::Z).length() < 1e-12);
        assert!((w.extent.width() - 4.0).abs() < 1e-9 && (w.extent.height() - 3.0).abs() < 1e-9);
        let p = w.to_scene([0.5, 0.25]);
        let back = w.to_plane(p);
        assert!((back[0] - 0.5).abs() < 1e-12 && (back[1] - 0.25).abs() < 1e-12);
    }
}
