//! Closest-point queries on a committed triangle scene (`rtcPointQuery`): Embree traverses
//! its BVH with a shrinking sphere and calls back for every candidate triangle; the exact
//! point-to-triangle distance is computed here, in `f64`, from the scene's own buffers.
use std::any::Any;
use std::os::raw::c_void;
use std::panic::{AssertUnwindSafe, catch_unwind, resume_unwind};

use super::scene::CommittedScene;
use super::sys;

/// The nearest point of a scene to a query point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointHit {
    /// The nearest point on the triangle (f64, from the f32 vertices).
    pub point: [f64; 3],
    /// Euclidean distance from the query point.
    pub distance: f64,
    /// Geometry id (as [`super::Hit::geom_id`]).
    pub geom_id: u32,
    /// Triangle index within its geometry.
    pub prim_id: u32,
}

/// The state one query shares with [`point_query_callback`] through Embree's `userPtr`.
struct QueryState<'a> {
    scene: &'a CommittedScene,
    p: [f64; 3],
    /// Largest distance accepted (the caller's `max_distance`).
    max_distance: f64,
    /// Distance between `p` and the f32 point Embree traverses with: added to the radius
    /// Embree culls with, so that rounding never culls a triangle within reach of `p`.
    slack: f64,
    best: Option<PointHit>,
    accept: &'a mut dyn FnMut(u32, u32) -> bool,
    /// A panic raised by `accept`, resumed once Embree has returned.
    panic: Option<Box<dyn Any + Send>>,
}

/// Closest point to `p` on the triangle `a, b, c` (Ericson, *Real-Time Collision Detection*,
/// §5.1.5: Voronoi regions of the vertices, then of the edges, else the face). Degenerate
/// triangles are handled (they fall into a vertex or edge region).
pub fn closest_point_on_triangle(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [f64; 3] {
    let sub = |u: [f64; 3], v: [f64; 3]| [u[0] - v[0], u[1] - v[1], u[2] - v[2]];
    let dot = |u: [f64; 3], v: [f64; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let lerp =
        |u: [f64; 3], d: [f64; 3], t: f64| [u[0] + t * d[0], u[1] + t * d[1], u[2] + t * d[2]];
    let ab = sub(b, a);
    let ac = sub(c, a);
    let ap = sub(p, a);
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = sub(p, b);
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let den = d1 - d3;
        return if den > 0.0 { lerp(a, ab, d1 / den) } else { a };
    }
    let cp = sub(p, c);
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let den = d2 - d6;
        return if den > 0.0 { lerp(a, ac, d2 / den) } else { a };
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let den = (d4 - d3) + (d5 - d6);
        return if den > 0.0 {
            lerp(b, sub(c, b), (d4 - d3) / den)
        } else {
            b
        };
    }
    let den = va + vb + vc;
    if den == 0.0 || !den.is_finite() {
        return a;
    }
    let v = vb / den;
    let w = vc / den;
    [
        a[0] + ab[0] * v + ac[0] * w,
        a[1] + ab[1] * v + ac[1] * w,
        a[2] + ab[2] * v + ac[2] * w,
    ]
}

/// The smallest f32 ≥ `x` (≥ 0, finite): Embree's radius must not cull what `x` reaches.
fn round_up(x: f64) -> f32 {
    let y = x as f32;
    if f64::from(y) >= x || !y.is_finite() {
        y
    } else {
        f32::from_bits(y.to_bits() + 1) // y ≥ 0: the next representable value up
    }
}

/// Embree's per-candidate callback: exact distance to the candidate triangle, keep the
/// nearest accepted one, shrink the query sphere to it. Returns whether the radius changed.
/// Never unwinds into C: a panic of the caller's filter is stored and resumed later.
unsafe extern "C" fn point_query_callback(args: *mut sys::RTCPointQueryFunctionArguments) -> bool {
    if args.is_null() {
        return false;
    }
    // SAFETY: Embree passes a valid, exclusive argument record for the duration of the call.
    let args = unsafe { &mut *args };
    if args.userPtr.is_null() || args.query.is_null() {
        return false;
    }
    // SAFETY: `userPtr` is the `QueryState` that `closest_point_filtered` handed to
    // `rtcPointQuery`; it lives on that function's stack for the whole (synchronous) query
    // and nothing else touches it meanwhile. `query` is the `RTCPointQuery` of that call.
    let (state, query) = unsafe {
        (
            &mut *(args.userPtr as *mut QueryState<'_>),
            &mut *args.query,
        )
    };
    if state.panic.is_some() {
        return false;
    }
    let (geom, prim) = (args.geomID, args.primID);
    let Some((verts, faces)) = state.scene.triangles(geom) else {
        return false;
    };
    let Some(f) = faces.get(prim as usize) else {
        return false;
    };
    let accept = &mut *state.accept;
    match catch_unwind(AssertUnwindSafe(|| accept(geom, prim))) {
        Err(payload) => {
            state.panic = Some(payload);
            query.radius = 0.0; // end the traversal as early as Embree allows
            return true;
        }
        Ok(false) => return false,
        Ok(true) => {}
    }
    // Indices were checked against the vertex count in `Scene::add_triangles`.
    let v = |i: u32| verts[i as usize].map(f64::from);
    let q = closest_point_on_triangle(state.p, v(f[0]), v(f[1]), v(f[2]));
    let d =
        ((q[0] - state.p[0]).powi(2) + (q[1] - state.p[1]).powi(2) + (q[2] - state.p[2]).powi(2))
            .sqrt();
    let better = match &state.best {
        None => true,
        // Ties are broken by ids, so the answer does not depend on traversal order.
        Some(b) => (d, geom, prim) < (b.distance, b.geom_id, b.prim_id),
    };
    if d.is_nan() || d > state.max_distance || !better {
        return false;
    }
    state.best = Some(PointHit {
        point: q,
        distance: d,
        geom_id: geom,
        prim_id: prim,
    });
    let r = round_up(d + state.slack);
    if r < query.radius {
        query.radius = r;
        true
    } else {
        false
    }
}

impl CommittedScene {
    /// The nearest point of the scene to `p` within `max_distance`, or `None`.
    pub fn closest_point(&self, p: [f64; 3], max_distance: f64) -> Option<PointHit> {
        self.closest_point_filtered(p, max_distance, &mut |_, _| true)
    }

    /// The nearest point to `p` within `max_distance` on the triangles `(geom_id, prim_id)`
    /// that `accept` admits (e.g. only triangles whose normal matches). Non-finite `p` or
    /// `max_distance < 0` give `None`. A panic in `accept` is propagated after the query.
    pub fn closest_point_filtered(
        &self,
        p: [f64; 3],
        max_distance: f64,
        accept: &mut dyn FnMut(u32, u32) -> bool,
    ) -> Option<PointHit> {
        if p.iter().any(|c| !c.is_finite()) || max_distance.is_nan() || max_distance < 0.0 {
            return None;
        }
        let p32 = p.map(|c| c as f32);
        if p32.iter().any(|c| !c.is_finite()) {
            return None;
        }
        let slack = p
            .iter()
            .zip(&p32)
            .map(|(a, b)| (a - f64::from(*b)).powi(2))
            .sum::<f64>()
            .sqrt();
        let radius = if max_distance.is_finite() {
            round_up(max_distance + slack)
        } else {
            f32::INFINITY
        };
        let mut state = QueryState {
            scene: self,
            p,
            max_distance,
            slack,
            best: None,
            accept,
            panic: None,
        };
        let mut query = sys::RTCPointQuery {
            x: p32[0],
            y: p32[1],
            z: p32[2],
            time: 0.0,
            radius,
        };
        // `rtcInitPointQueryContext` is inline in Embree's header (no symbol): no instance
        // on the stack. The remaining fields (matrices; Embree 4's instPrimID) stay zero and
        // are not read while the stack is empty.
        let mut context = sys::RTCPointQueryContext {
            instStackSize: 0,
            ..Default::default()
        };
        context.instID[0] = u32::MAX; // RTC_INVALID_GEOMETRY_ID
        // SAFETY: the scene is live and committed (read-only; concurrent traversals are
        // allowed, see `CommittedScene`'s Send/Sync note). `query` (16-byte aligned by its
        // type) and `context` are valid and exclusively borrowed for the call. `userPtr`
        // points to `state`, which outlives the call; the callback is the only user and
        // runs synchronously on this thread, so no other reference to `state` is live.
        unsafe {
            sys::rtcPointQuery(
                self.raw(),
                &mut query,
                &mut context,
                Some(point_query_callback),
                (&mut state as *mut QueryState<'_>).cast::<c_void>(),
            );
        }
        if let Some(payload) = state.panic.take() {
            resume_unwind(payload);
        }
        state.best
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::embree::{Device, Scene};

    /// Brute force over every triangle, for comparison.
    fn brute(v: &[[f32; 3]], f: &[[u32; 3]], p: [f64; 3]) -> (f64, u32) {
        let mut best = (f64::INFINITY, 0);
        for (i, t) in f.iter().enumerate() {
            let w = |k: usize| v[t[k] as usize].map(f64::from);
            let q = closest_point_on_triangle(p, w(0), w(1), w(2));
            let d = ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) + (q[2] - p[2]).powi(2)).sqrt();
            if d < best.0 {
                best = (d, i as u32);
            }
        }
        best
    }

    #[test]
    fn closest_point_on_triangle_regions() {
        let (a, b, c) = ([0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]);
        // Face region: straight down.
        assert_eq!(
            closest_point_on_triangle([0.5, 0.5, 3.0], a, b, c),
            [0.5, 0.5, 0.0]
        );
        // Vertex regions.
        assert_eq!(closest_point_on_triangle([-1.0, -1.0, 1.0], a, b, c), a);
        assert_eq!(closest_point_on_triangle([3.0, -0.5, 0.0], a, b, c), b);
        assert_eq!(closest_point_on_triangle([-0.5, 3.0, 0.0], a, b, c), c);
        // Edge regions: ab, ac, bc (hypotenuse x + y = 2).
        assert_eq!(
            closest_point_on_triangle([1.0, -1.0, 0.0], a, b, c),
            [1.0, 0.0, 0.0]
        );
        assert_eq!(
            closest_point_on_triangle([-1.0, 1.0, 5.0], a, b, c),
            [0.0, 1.0, 0.0]
        );
        let q = closest_point_on_triangle([2.0, 2.0, 0.0], a, b, c);
        assert!((q[0] - 1.0).abs() < 1e-15 && (q[1] - 1.0).abs() < 1e-15);
        // Degenerate triangles: a segment and a point.
        let q = closest_point_on_triangle([1.0, 1.0, 0.0], a, b, b);
        assert_eq!(q, [1.0, 0.0, 0.0]);
        assert_eq!(closest_point_on_triangle([1.0, 1.0, 1.0], a, a, a), a);
    }

    #[test]
    fn point_query_matches_brute_force_and_filters() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        // A soup of random triangles (some far from the others) in two geometries.
        let mut v = Vec::new();
        let mut f = Vec::new();
        for i in 0..300u32 {
            let o = [
                rng.random_range(-20.0..20.0f32),
                rng.random_range(-20.0..20.0f32),
                rng.random_range(-5.0..5.0f32),
            ];
            for _ in 0..3 {
                v.push([
                    o[0] + rng.random_range(-1.5..1.5f32),
                    o[1] + rng.random_range(-1.5..1.5f32),
                    o[2] + rng.random_range(-1.5..1.5f32),
                ]);
            }
            f.push([3 * i, 3 * i + 1, 3 * i + 2]);
        }
        let dev = Device::new().unwrap();
        let mut s = Scene::new(&dev).unwrap();
        assert_eq!(s.add_triangles(&v, &f[..150]).unwrap(), Some(0));
        let shifted: Vec<[u32; 3]> = f[150..].iter().map(|t| t.map(|k| k - 450)).collect();
        assert_eq!(s.add_triangles(&v[450..], &shifted).unwrap(), Some(1));
        let sc = s.commit().unwrap();
        for _ in 0..400 {
            let p = [
                rng.random_range(-25.0..25.0),
                rng.random_range(-25.0..25.0),
                rng.random_range(-8.0..8.0),
            ];
            let (d, i) = brute(&v, &f, p);
            let hit = sc.closest_point(p, f64::INFINITY).unwrap();
            let global = hit.prim_id + 150 * hit.geom_id;
            assert!((hit.distance - d).abs() < 1e-12, "{} vs {d}", hit.distance);
            assert_eq!(global, i);
            // Limited radius: found exactly when within reach.
            assert_eq!(sc.closest_point(p, d * 0.999).is_none(), d > 0.0);
            assert!(sc.closest_point(p, d * 1.001 + 1e-9).is_some());
            // Filter: only geometry 1 (global indices ≥ 150).
            let (d1, i1) = brute(&v[450..], &shifted, p);
            let h1 = sc
                .closest_point_filtered(p, f64::INFINITY, &mut |g, _| g == 1)
                .unwrap();
            assert_eq!((h1.geom_id, h1.prim_id), (1, i1));
            assert!((h1.distance - d1).abs() < 1e-12);
        }
        assert!(sc.closest_point([f64::NAN, 0.0, 0.0], 1.0).is_none());
        assert!(sc.closest_point([0.0; 3], -1.0).is_none());
        assert!(
            sc.closest_point_filtered([0.0; 3], f64::INFINITY, &mut |_, _| false)
                .is_none()
        );
    }

    #[test]
    fn filter_panic_propagates_and_far_coordinates_are_exact() {
        let dev = Device::new().unwrap();
        let mut s = Scene::new(&dev).unwrap();
        // A unit square far from the origin (f32 spacing there is 2⁻⁷ m).
        let o = 70_000.0f32;
        let v = [
            [o, o, 0.0],
            [o + 1.0, o, 0.0],
            [o + 1.0, o + 1.0, 0.0],
            [o, o + 1.0, 0.0],
        ];
        s.add_triangles(&v, &[[0, 1, 2], [0, 2, 3]]).unwrap();
        let sc = s.commit().unwrap();
        // A query point that f32 cannot represent: the distance is still computed in f64.
        let p = [70_000.3, 70_000.6, 0.123_456_789];
        let h = sc.closest_point(p, 0.2).unwrap();
        assert!((h.distance - 0.123_456_789).abs() < 1e-12);
        let r = std::panic::catch_unwind(|| {
            sc.closest_point_filtered(p, 1.0, &mut |_, _| panic!("filter failed"))
        });
        assert!(r.is_err());
        // The scene is still usable afterwards.
        assert!(sc.closest_point(p, 1.0).is_some());
    }
}
