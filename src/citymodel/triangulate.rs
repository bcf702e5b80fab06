//! Polygon triangulation with spade's constrained Delaunay triangulation.
//!
//! Each polygon is projected onto its best-fit plane (Newell normal of the exterior ring),
//! the outer ring minus the holes is triangulated (all ring edges are constraints; faces are
//! kept by the even-odd rule, counting how many ring edges cover each CDT edge so coincident
//! edges cancel), and the triangles are lifted back onto the original 3D vertices. No Steiner
//! points are added except where a self-intersecting ring is repaired by splitting its edges
//! at the crossings (a named warning).
use std::collections::HashMap;

use glam::{DVec2, DVec3};
use spade::handles::FixedVertexHandle;
use spade::{ConstrainedDelaunayTriangulation, Point2, Triangulation};

use crate::citygml::MAX_POLYGON_POINTS;

/// Why a polygon produced no triangles.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
pub enum SkipReason {
    /// The exterior ring has fewer than 3 distinct points.
    TooFewPoints,
    /// The exterior ring encloses no area (all points collinear or coincident).
    ZeroArea,
    /// A coordinate is NaN or infinite.
    NonFinite,
    /// spade refused a vertex (coordinates out of its range) or failed on the ring.
    Cdt(String),
    /// The constraints enclose no face.
    Empty,
    /// More points than [`MAX_POLYGON_POINTS`] (all rings together): skipped, not triangulated.
    TooManyPoints(usize),
}

impl std::fmt::Display for SkipReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SkipReason::TooFewPoints => {
                f.write_str("exterior ring has fewer than 3 distinct points")
            }
            SkipReason::ZeroArea => f.write_str("exterior ring has zero area"),
            SkipReason::NonFinite => f.write_str("non-finite (NaN/Inf) coordinate"),
            SkipReason::Cdt(e) => write!(f, "triangulation failed: {e}"),
            SkipReason::Empty => f.write_str("rings enclose no area"),
            SkipReason::TooManyPoints(n) => write!(
                f,
                "{n} points, more than the {MAX_POLYGON_POINTS} a polygon may have"
            ),
        }
    }
}

/// A repair or a dropped part of a polygon that still produced triangles.
#[derive(Debug, Clone, PartialEq)]
pub enum Repair {
    /// Consecutive duplicate points removed.
    DuplicatePoints(usize),
    /// An interior ring with < 3 distinct points or zero area was dropped.
    DegenerateHole(usize),
    /// An interior ring with a vertex outside the exterior ring (beyond a tolerance of
    /// 10⁻³ of the polygon's size) was dropped: filling by the even-odd rule would turn its
    /// outside part into an extra island. `crossing`: other vertices lie inside.
    HoleNotInside { hole: usize, crossing: bool },
    /// Ring edges crossed each other; they were split at the crossings (even-odd rule).
    SelfIntersection,
}

impl std::fmt::Display for Repair {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Repair::DuplicatePoints(n) => write!(f, "{n} repeated consecutive points removed"),
            Repair::DegenerateHole(k) => write!(
                f,
                "interior ring {} has fewer than 3 distinct points or no area: ignored",
                k + 1
            ),
            Repair::HoleNotInside {
                hole,
                crossing: false,
            } => write!(
                f,
                "interior ring {} lies outside the exterior ring: ignored (a hole must lie inside its polygon)",
                hole + 1
            ),
            Repair::HoleNotInside {
                hole,
                crossing: true,
            } => write!(
                f,
                "interior ring {} crosses the exterior ring: ignored (a hole must lie inside its polygon)",
                hole + 1
            ),
            Repair::SelfIntersection => f.write_str(
                "ring edges cross each other: split at the crossings and filled by the even-odd rule",
            ),
        }
    }
}

/// The triangles of one polygon, in the polygon's local frame (`point − origin`).
#[derive(Debug, Clone, Default)]
pub struct PolygonTriangles {
    /// Vertex positions (local frame, f64).
    pub vertices: Vec<DVec3>,
    /// Triangles, counter-clockwise seen from the side the exterior ring's normal points to.
    pub triangles: Vec<[u32; 3]>,
    /// Sum of the 3D triangle areas.
    pub area: f64,
    /// Exterior minus hole areas in the projection plane.
    pub area_projected: f64,
    /// Largest distance of a vertex from the best-fit plane.
    pub planarity: f64,
    /// Unit Newell normal of the exterior ring.
    pub normal: DVec3,
    pub repairs: Vec<Repair>,
}

/// Removes consecutive duplicates (and a closing duplicate); returns the number removed.
fn dedup_ring(ring: &[DVec3]) -> (Vec<DVec3>, usize) {
    let mut out: Vec<DVec3> = Vec::with_capacity(ring.len());
    for &p in ring {
        if out.last() != Some(&p) {
            out.push(p);
        }
    }
    while out.len() > 1 && out.first() == out.last() {
        out.pop();
    }
    let removed = ring.len() - out.len();
    (out, removed)
}

fn newell(ring: &[DVec3]) -> DVec3 {
    let mut n = DVec3::ZERO;
    for i in 0..ring.len() {
        let (a, b) = (ring[i], ring[(i + 1) % ring.len()]);
        n += DVec3::new(
            (a.y - b.y) * (a.z + b.z),
            (a.z - b.z) * (a.x + b.x),
            (a.x - b.x) * (a.y + b.y),
        );
    }
    n
}

/// Normal of the least-squares plane through `pts` (smallest covariance eigenvector);
/// `None` when the points do not span a plane.
fn best_fit_normal(pts: &[DVec3], centroid: DVec3, scale: f64) -> Option<DVec3> {
    let mut c = [[0.0; 3]; 3];
    for p in pts {
        let d = (*p - centroid).to_array();
        for i in 0..3 {
            for j in 0..3 {
                c[i][j] += d[i] * d[j];
            }
        }
    }
    let (vals, vecs) = crate::alignment::jacobi_eigen::<3>(c);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| vals[a].total_cmp(&vals[b]));
    if vals[order[1]].is_nan() || vals[order[1]] <= 1e-12 * scale * scale {
        return None;
    }
    let k = order[0];
    DVec3::new(vecs[0][k], vecs[1][k], vecs[2][k]).try_normalize()
}

fn shoelace(ring: &[DVec2]) -> f64 {
    let mut a = 0.0;
    for i in 0..ring.len() {
        let (p, q) = (ring[i], ring[(i + 1) % ring.len()]);
        a += p.x * q.y - q.x * p.y;
    }
    0.5 * a
}

/// An orthonormal basis (u, v) of the plane with normal `n`, such that (u, v, n) is right-handed.
fn plane_basis(n: DVec3) -> (DVec3, DVec3) {
    let a = n.abs();
    let helper = if a.x <= a.y && a.x <= a.z {
        DVec3::X
    } else if a.y <= a.z {
        DVec3::Y
    } else {
        DVec3::Z
    };
    let u = helper.cross(n).normalize();
    let v = n.cross(u);
    (u, v)
}

/// Distance from `p` to the closed ring's edges.
fn distance_to_ring(p: DVec2, ring: &[DVec2]) -> f64 {
    let mut best = f64::INFINITY;
    for i in 0..ring.len() {
        let (a, b) = (ring[i], ring[(i + 1) % ring.len()]);
        let ab = b - a;
        let t = if ab.length_squared() > 0.0 {
            ((p - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0)
        } else {
            0.0
        };
        best = best.min((a + ab * t - p).length());
    }
    best
}

fn point_in_rings(p: DVec2, rings: &[Vec<DVec2>]) -> bool {
    let mut inside = false;
    for ring in rings {
        let n = ring.len();
        let mut j = n - 1;
        for i in 0..n {
            let (a, b) = (ring[i], ring[j]);
            if (a.y > p.y) != (b.y > p.y) && p.x < (b.x - a.x) * (p.y - a.y) / (b.y - a.y) + a.x {
                inside = !inside;
            }
            j = i;
        }
    }
    inside
}

/// Triangulates one polygon given as an exterior ring and interior rings (already in a local
/// frame: subtract a georeferenced origin in f64 before calling).
pub fn triangulate(
    exterior: &[DVec3],
    interiors: &[Vec<DVec3>],
) -> Result<PolygonTriangles, SkipReason> {
    // spade has internal assertions that extreme rings can trip ("Failed to locate position.
    // This is a bug in spade.", on a self-crossing ring 100 km tall and 12 cm deep, found by a
    // mutation sweep): such a polygon is skipped with the triangulator's words, not a crash.
    match quietly(|| triangulate_ring(exterior, interiors)) {
        Ok(r) => r,
        Err(payload) => {
            let why = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "no message".into());
            Err(SkipReason::Cdt(format!(
                "spade: {}",
                why.replace('\n', " ")
            )))
        }
    }
}

thread_local! {
    /// Set while [`quietly`] runs a closure on this thread.
    static QUIET: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f`, catching a panic in it without printing the panic message (the hook installed
/// once here stays silent only on a thread inside `quietly`; every other panic is printed by
/// the hook that was installed before).
fn quietly<T>(f: impl FnOnce() -> T) -> std::thread::Result<T> {
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(std::cell::Cell::get) {
                previous(info);
            }
        }));
    });
    QUIET.with(|q| q.set(true));
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    QUIET.with(|q| q.set(false));
    r
}

fn triangulate_ring(
    exterior: &[DVec3],
    interiors: &[Vec<DVec3>],
) -> Result<PolygonTriangles, SkipReason> {
    if exterior
        .iter()
        .chain(interiors.iter().flatten())
        .any(|p| !p.is_finite())
    {
        return Err(SkipReason::NonFinite);
    }
    let points = exterior.len() + interiors.iter().map(Vec::len).sum::<usize>();
    if points > MAX_POLYGON_POINTS {
        return Err(SkipReason::TooManyPoints(points));
    }
    let mut repairs = Vec::new();
    let (ext, removed) = dedup_ring(exterior);
    let mut dups = removed;
    if ext.len() < 3 {
        return Err(SkipReason::TooFewPoints);
    }
    let n_raw = newell(&ext);
    let scale = ext
        .iter()
        .map(|p| (*p - ext[0]).length())
        .fold(0.0f64, f64::max);
    let centroid = ext.iter().copied().sum::<DVec3>() / ext.len() as f64;
    let newell_ok = scale > 0.0 && n_raw.length() > 1e-12 * scale * scale;
    let normal = if newell_ok {
        n_raw.normalize()
    } else {
        // Lobes of opposite orientation (a bow tie) cancel in the Newell normal: fall back
        // to the least-squares plane; collinear or coincident points have none.
        best_fit_normal(&ext, centroid, scale).ok_or(SkipReason::ZeroArea)?
    };
    let (u, v) = plane_basis(normal);
    let project = |p: DVec3| {
        let d = p - centroid;
        DVec2::new(d.dot(u), d.dot(v))
    };

    let ext2 = vec![ext.iter().map(|&p| project(p)).collect::<Vec<DVec2>>()];
    let tol = 1e-3 * scale;
    let mut rings3: Vec<Vec<DVec3>> = vec![ext];
    for (k, hole) in interiors.iter().enumerate() {
        let (h, removed) = dedup_ring(hole);
        dups += removed;
        if h.len() < 3 || newell(&h).length() <= 1e-12 * scale * scale {
            repairs.push(Repair::DegenerateHole(k));
            continue;
        }
        // Vertices on the exterior ring (within `tol`) count as inside.
        let (mut inside, mut outside) = (0usize, 0usize);
        for q in h.iter().map(|&p| project(p)) {
            if distance_to_ring(q, &ext2[0]) <= tol {
                continue;
            }
            if point_in_rings(q, &ext2) {
                inside += 1;
            } else {
                outside += 1;
            }
        }
        if outside > 0 {
            repairs.push(Repair::HoleNotInside {
                hole: k,
                crossing: inside > 0,
            });
            continue;
        }
        rings3.push(h);
    }
    if dups > 0 {
        repairs.push(Repair::DuplicatePoints(dups));
    }
    let planarity = rings3
        .iter()
        .flatten()
        .map(|p| (*p - centroid).dot(normal).abs())
        .fold(0.0f64, f64::max);
    let rings2: Vec<Vec<DVec2>> = rings3
        .iter()
        .map(|r| r.iter().map(|&p| project(p)).collect())
        .collect();
    let area_projected = rings2
        .iter()
        .enumerate()
        .map(|(i, r)| {
            if i == 0 {
                shoelace(r).abs()
            } else {
                -shoelace(r).abs()
            }
        })
        .sum::<f64>();

    let mut cdt: ConstrainedDelaunayTriangulation<Point2<f64>> =
        ConstrainedDelaunayTriangulation::new();
    let mut pos3: Vec<DVec3> = Vec::new();
    let mut handles: Vec<Vec<FixedVertexHandle>> = Vec::with_capacity(rings2.len());
    for (r2, r3) in rings2.iter().zip(&rings3) {
        let mut hs = Vec::with_capacity(r2.len());
        for (p2, p3) in r2.iter().zip(r3) {
            let h = cdt.insert(Point2::new(p2.x, p2.y)).map_err(|e| {
                SkipReason::Cdt(match e {
                    spade::InsertionError::NAN => "a coordinate is not a number".into(),
                    spade::InsertionError::TooLarge => {
                        "a coordinate is too large for the triangulator".into()
                    }
                    spade::InsertionError::TooSmall => {
                        "a coordinate is too small (subnormal) for the triangulator".into()
                    }
                })
            })?;
            if h.index() == pos3.len() {
                pos3.push(*p3 - centroid);
            }
            hs.push(h);
        }
        handles.push(hs);
    }
    // Constraint edges with their multiplicity (vertex pairs are stable under later flips).
    let mut cover: HashMap<(usize, usize), u32> = HashMap::new();
    let mut split = false;
    let mut pending: Vec<(FixedVertexHandle, FixedVertexHandle)> = Vec::new();
    for hs in &handles {
        for i in 0..hs.len() {
            let (a, b) = (hs[i], hs[(i + 1) % hs.len()]);
            if a == b {
                continue;
            }
            let edges = cdt.try_add_constraint(a, b);
            if edges.is_empty() {
                pending.push((a, b));
                continue;
            }
            for e in edges {
                let [p, q] = cdt.directed_edge(e).vertices().map(|h| h.fix().index());
                *cover.entry((p.min(q), p.max(q))).or_default() += 1;
            }
        }
    }
    for (a, b) in pending {
        // Crossing constraints: split at the crossings (new vertices lie on the plane).
        split = true;
        cdt.add_constraint_and_split(a, b, |p| p);
    }
    while pos3.len() < cdt.num_vertices() {
        let p = cdt
            .vertex(FixedVertexHandle::from_index(pos3.len()))
            .position();
        pos3.push(u * p.x + v * p.y);
    }

    let mut keep: Vec<bool> = vec![false; cdt.num_all_faces()];
    if split {
        repairs.push(Repair::SelfIntersection);
        for face in cdt.inner_faces() {
            let [a, b, c] = face.positions();
            let m = DVec2::new((a.x + b.x + c.x) / 3.0, (a.y + b.y + c.y) / 3.0);
            keep[face.fix().index()] = point_in_rings(m, &rings2);
        }
    } else {
        let odd =
            |e: spade::handles::DirectedEdgeHandle<'_, Point2<f64>, (), spade::CdtEdge<()>, ()>| {
                let [p, q] = e.vertices().map(|h| h.fix().index());
                cover.get(&(p.min(q), p.max(q))).is_some_and(|c| c % 2 == 1)
            };
        let mut seen = vec![false; cdt.num_all_faces()];
        let mut stack = Vec::new();
        for face in cdt.inner_faces() {
            for e in face.adjacent_edges() {
                if e.rev().face().is_outer() && !seen[face.fix().index()] {
                    seen[face.fix().index()] = true;
                    keep[face.fix().index()] = odd(e);
                    stack.push(face.fix());
                }
            }
        }
        while let Some(f) = stack.pop() {
            let face = cdt.face(f);
            let inside = keep[f.index()];
            for e in face.adjacent_edges() {
                let nb = e.rev().face();
                if let Some(inner) = nb.as_inner() {
                    let i = inner.fix().index();
                    if !seen[i] {
                        seen[i] = true;
                        keep[i] = inside ^ odd(e);
                        stack.push(inner.fix());
                    }
                }
            }
        }
    }

    let mut out = PolygonTriangles {
        planarity,
        normal,
        area_projected,
        repairs,
        ..Default::default()
    };
    let mut remap: HashMap<usize, u32> = HashMap::new();
    for face in cdt.inner_faces() {
        if !keep[face.fix().index()] {
            continue;
        }
        let vs = face.vertices().map(|h| h.fix().index());
        let tri = vs.map(|i| {
            *remap.entry(i).or_insert_with(|| {
                out.vertices.push(pos3[i]);
                (out.vertices.len() - 1) as u32
            })
        });
        let [a, b, c] = tri.map(|i| out.vertices[i as usize]);
        out.area += 0.5 * (b - a).cross(c - a).length();
        out.triangles.push(tri);
    }
    // spade's faces are counter-clockwise in (u, v); (u, v, n) is right-handed, so the
    // triangles face along the exterior ring's normal. Shift back to the caller's frame.
    for p in &mut out.vertices {
        *p += centroid;
    }
    if out.triangles.is_empty() {
        // A ring folding back onto itself has a zero Newell normal and encloses nothing.
        return Err(if newell_ok {
            SkipReason::Empty
        } else {
            SkipReason::ZeroArea
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rect(x0: f64, y0: f64, x1: f64, y1: f64) -> Vec<DVec3> {
        vec![
            DVec3::new(x0, y0, 0.0),
            DVec3::new(x1, y0, 0.0),
            DVec3::new(x1, y1, 0.0),
            DVec3::new(x0, y1, 0.0),
        ]
    }

    /// `n` points on a circle of radius `r` (z = 0), counter-clockwise.
    fn circle(n: usize, r: f64) -> Vec<DVec3> {
        (0..n)
            .map(|i| {
                let t = std::f64::consts::TAU * i as f64 / n as f64;
                DVec3::new(r * t.cos(), r * t.sin(), 0.0)
            })
            .collect()
    }

    /// A polygon of more than MAX_POLYGON_POINTS points (rings together) is skipped with its
    /// count; one at the limit is triangulated (n − 2 triangles of a convex ring, area of
    /// the inscribed polygon).
    #[test]
    fn a_polygon_over_the_point_limit_is_skipped_with_its_count() {
        let n = MAX_POLYGON_POINTS;
        assert_eq!(
            triangulate(&circle(n + 1, 10.0), &[]).unwrap_err(),
            SkipReason::TooManyPoints(n + 1)
        );
        let half = n / 2;
        assert_eq!(
            triangulate(&circle(half, 10.0), &[circle(n - half + 1, 5.0)]).unwrap_err(),
            SkipReason::TooManyPoints(n + 1)
        );
        assert!(
            SkipReason::TooManyPoints(n + 1)
                .to_string()
                .contains(&format!("{} points, more than the {n}", n + 1))
        );
        let t = triangulate(&circle(n, 10.0), &[]).unwrap();
        assert_eq!(t.triangles.len(), n - 2);
        let inscribed = 0.5 * n as f64 * 100.0 * (std::f64::consts::TAU / n as f64).sin();
        assert!((t.area_projected - inscribed).abs() < 1e-9 * inscribed);
    }

    /// A vertical wall (x–z plane) 4×3 with a 1.5×1.2 window hole: area 10.2, 8 triangles (BUILD.md, CGAL).
    #[test]
    fn wall_with_window_matches_cgal_numbers() {
        let to_wall = |r: Vec<DVec3>| {
            r.into_iter()
                .map(|p| DVec3::new(p.x, 5.0, p.y))
                .collect::<Vec<_>>()
        };
        let wall = to_wall(rect(0.0, 0.0, 4.0, 3.0));
        let hole = to_wall(rect(1.0, 1.0, 2.5, 2.2));
        let t = triangulate(&wall, &[hole]).unwrap();
        assert_eq!(t.triangles.len(), 8);
        assert!((t.area - 10.2).abs() < 1e-12, "{}", t.area);
        assert!((t.area_projected - 10.2).abs() < 1e-12);
        assert!(t.planarity < 1e-12);
        // Triangle normals agree with the ring's normal.
        for tri in &t.triangles {
            let [a, b, c] = tri.map(|i| t.vertices[i as usize]);
            assert!((b - a).cross(c - a).dot(t.normal) > 0.0);
        }
    }

    #[test]
    fn degenerate_rings() {
        let line = vec![DVec3::ZERO, DVec3::X, DVec3::new(2.0, 0.0, 0.0)];
        assert_eq!(triangulate(&line, &[]).unwrap_err(), SkipReason::ZeroArea);
        let two = vec![DVec3::ZERO, DVec3::X, DVec3::X, DVec3::ZERO];
        assert_eq!(
            triangulate(&two, &[]).unwrap_err(),
            SkipReason::TooFewPoints
        );
        let nan = vec![DVec3::ZERO, DVec3::X, DVec3::new(f64::NAN, 1.0, 0.0)];
        assert_eq!(triangulate(&nan, &[]).unwrap_err(), SkipReason::NonFinite);
        // Repeated and collinear vertices still give the full area.
        let mut r = rect(0.0, 0.0, 2.0, 1.0);
        r.insert(1, DVec3::new(1.0, 0.0, 0.0));
        r.insert(1, DVec3::new(1.0, 0.0, 0.0));
        let t = triangulate(&r, &[vec![DVec3::ZERO, DVec3::ZERO]]).unwrap();
        assert!((t.area - 2.0).abs() < 1e-12);
        // One duplicate in the exterior, one in the (dropped) degenerate hole.
        assert!(
            t.repairs.contains(&Repair::DuplicatePoints(2)),
            "{:?}",
            t.repairs
        );
        assert!(t.repairs.contains(&Repair::DegenerateHole(0)));
    }

    #[test]
    fn self_intersecting_bowtie_is_repaired_even_odd() {
        // Bow tie: two triangles of area 0.25 each meeting at (0.5, 0.5).
        let bow = vec![
            DVec3::ZERO,
            DVec3::new(1.0, 1.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        ];
        let t = triangulate(&bow, &[]).unwrap_or_else(|e| panic!("{e}"));
        assert!(t.repairs.contains(&Repair::SelfIntersection));
        assert!((t.area - 0.5).abs() < 1e-9, "{}", t.area);
    }

    #[test]
    fn hole_touching_the_exterior_and_a_tiny_polygon() {
        // Hole sharing a vertex with the exterior.
        let outer = rect(0.0, 0.0, 4.0, 4.0);
        let hole = vec![
            DVec3::ZERO,
            DVec3::new(1.0, 2.0, 0.0),
            DVec3::new(2.0, 1.0, 0.0),
        ];
        let t = triangulate(&outer, &[hole]).unwrap();
        assert!((t.area - (16.0 - 1.5)).abs() < 1e-12, "{}", t.area);
        // A 1 mm² polygon far from the origin of its local frame.
        let tiny: Vec<DVec3> = rect(0.0, 0.0, 1e-3, 1e-3)
            .into_iter()
            .map(|p| p + DVec3::new(50.0, 50.0, 3.0))
            .collect();
        let t = triangulate(&tiny, &[]).unwrap();
        assert!((t.area - 1e-6).abs() < 1e-15);
    }

    #[test]
    fn non_planar_polygon_reports_deviation() {
        let mut r = rect(0.0, 0.0, 2.0, 2.0);
        r[2].z = 0.1;
        let t = triangulate(&r, &[]).unwrap();
        assert!(t.planarity > 0.02 && t.planarity < 0.1, "{}", t.planarity);
        assert_eq!(t.triangles.len(), 2);
    }
}
