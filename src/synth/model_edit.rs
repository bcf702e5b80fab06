//! SIMULATED city-model edits: the model handed to the pipeline loses a seeded share of its
//! windows and doors (all of them: an LoD2 model), while the scene's truth keeps them. The
//! wall holes an opening filled are closed with it (an LoD2 wall is a plain polygon). The
//! dropped ids are simulation truth (`gt/model_edit.json`), for scoring only.
use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::citygml::{CityModel, Level, Polygon, Ring};

/// How far (metres, file units) a hole's centre may lie outside a dropped opening's outline
/// on the wall plane and still be the opening's hole.
const HOLE_MARGIN: f64 = 0.1;
/// How far (file units) the opening's centre may lie from a wall polygon's plane for the
/// polygon to hold its hole (openings are recessed; the hole may be in a sibling wall).
const PLANE_DISTANCE: f64 = 0.5;

/// One opening removed from the pipeline's model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DroppedOpening {
    pub object_id: String,
    pub class: String,
    /// The object id of its parent surface.
    pub wall: Option<String>,
    /// The object id of its building (root).
    pub building: String,
    /// The wall holes closed with it.
    pub holes_closed: usize,
}

/// Whether the opening `object_id` is dropped at `share` with `seed`: a SplitMix64 hash of
/// the seed and the id, uniform in [0, 1), below the share (independent of order and files).
pub fn is_dropped(object_id: &str, share: f64, seed: u64) -> bool {
    if share >= 1.0 {
        return true;
    }
    let mut h = crate::hash::splitmix64(seed ^ 0x6F70_656E_696E_6773);
    for b in object_id.bytes() {
        h = crate::hash::splitmix64(h ^ u64::from(b));
    }
    ((h >> 11) as f64 / (1u64 << 53) as f64) < share
}

/// A unit normal (Newell) and an in-plane basis of a ring, `None` when degenerate.
fn plane(points: &[DVec3]) -> Option<(DVec3, DVec3, DVec3)> {
    let o = *points.first()?;
    let mut n = DVec3::ZERO;
    for (i, a) in points.iter().enumerate() {
        n += (*a - o).cross(points[(i + 1) % points.len()] - o);
    }
    let n = n.try_normalize()?;
    let u = n.any_orthonormal_vector();
    Some((n, u, n.cross(u)))
}

fn centre(r: &Ring) -> DVec3 {
    r.points.iter().copied().sum::<DVec3>() / r.points.len().max(1) as f64
}

/// The model without the dropped openings (and anything below them), the holes they filled
/// closed, and the list of what was dropped.
pub fn drop_openings(model: &CityModel, share: f64, seed: u64) -> (CityModel, Vec<DroppedOpening>) {
    let objs = &model.objects;
    let mut gone = vec![false; objs.len()];
    let mut dropped_roots = Vec::new();
    for (i, o) in objs.iter().enumerate() {
        let parent_gone = o.parent.is_some_and(|p| gone[p]);
        let opening = o.class.level() == Level::Part && (o.class.is_window() || o.class.is_door());
        if parent_gone || (opening && is_dropped(&o.object_id, share, seed)) {
            gone[i] = true;
            if !parent_gone {
                dropped_roots.push(i);
            }
        }
    }
    let root_of = |mut i: usize| {
        while let Some(p) = objs[i].parent {
            i = p;
        }
        i
    };
    // The holes each dropped opening filled: interior rings of its building's wall polygons
    // within PLANE_DISTANCE of the opening whose centre lies within the opening's outline
    // (bounding box on the wall plane + margin). The hole need not be in the opening's own
    // parent surface: modellers attach openings to one wall object and cut the hole in another.
    let mut polygons: Vec<Polygon> = model.polygons.clone();
    let mut dropped = Vec::new();
    for &d in &dropped_roots {
        let wall = objs[d].parent;
        let mut closed = 0;
        if wall.is_some() {
            let pts: Vec<DVec3> = model
                .polygons
                .iter()
                .filter(|p| p.owner.is_some_and(|o| o == d || is_below(objs, o, d)))
                .flat_map(|p| p.exterior.points.iter().copied())
                .collect();
            let building = root_of(d);
            let walls: Vec<bool> = (0..objs.len())
                .map(|o| objs[o].class.level() == Level::Surface && root_of(o) == building)
                .collect();
            let centroid = pts.iter().copied().sum::<DVec3>() / pts.len().max(1) as f64;
            for poly in polygons
                .iter_mut()
                .filter(|p| p.owner.is_some_and(|o| walls[o]) && !p.interiors.is_empty())
            {
                let Some((n, u, v)) = plane(&poly.exterior.points) else {
                    continue;
                };
                if pts.is_empty()
                    || (centroid - poly.exterior.points[0]).dot(n).abs() > PLANE_DISTANCE
                {
                    continue;
                }
                let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
                for q in &pts {
                    let (a, b) = (q.dot(u), q.dot(v));
                    lo = [lo[0].min(a), lo[1].min(b)];
                    hi = [hi[0].max(a), hi[1].max(b)];
                }
                let before = poly.interiors.len();
                poly.interiors.retain(|r| {
                    let c = centre(r);
                    let (a, b) = (c.dot(u), c.dot(v));
                    !(a >= lo[0] - HOLE_MARGIN
                        && a <= hi[0] + HOLE_MARGIN
                        && b >= lo[1] - HOLE_MARGIN
                        && b <= hi[1] + HOLE_MARGIN)
                });
                closed += before - poly.interiors.len();
            }
        }
        dropped.push(DroppedOpening {
            object_id: objs[d].object_id.clone(),
            class: objs[d].class.name().to_string(),
            wall: wall.map(|w| objs[w].object_id.clone()),
            building: objs[root_of(d)].object_id.clone(),
            holes_closed: closed,
        });
    }
    // Re-index the objects that stay; polygons of dropped objects go.
    let mut new_index = vec![usize::MAX; objs.len()];
    let mut objects = Vec::new();
    for (i, o) in objs.iter().enumerate() {
        if gone[i] {
            continue;
        }
        new_index[i] = objects.len();
        let mut o = o.clone();
        o.parent = o.parent.map(|p| new_index[p]);
        objects.push(o);
    }
    let polygons: Vec<Polygon> = polygons
        .into_iter()
        .filter(|p| p.owner.is_none_or(|o| !gone[o]))
        .map(|mut p| {
            p.owner = p.owner.map(|o| new_index[o]);
            p
        })
        .collect();
    let mut out = model.clone();
    out.objects = objects;
    out.polygons = polygons;
    (out, dropped)
}

/// Whether object `o` lies below object `a`.
fn is_below(objs: &[crate::citygml::CityObject], mut o: usize, a: usize) -> bool {
    while let Some(p) = objs[o].parent {
        if p == a {
            return true;
        }
        o = p;
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn share_is_met_and_seeded() {
        let ids: Vec<String> = (0..4000).map(|i| format!("win-{i}")).collect();
        let n = ids.iter().filter(|i| is_dropped(i, 0.2, 7)).count();
        assert!((700..900).contains(&n), "{n} of 4000 at 0.2");
        let m = ids.iter().filter(|i| is_dropped(i, 0.2, 8)).count();
        let same = ids
            .iter()
            .filter(|i| is_dropped(i, 0.2, 7) == is_dropped(i, 0.2, 8))
            .count();
        assert!(
            same < 3900 && (700..900).contains(&m),
            "another seed, another draw"
        );
        assert!(ids.iter().all(|i| is_dropped(i, 1.0, 7)));
        assert!(!ids.iter().any(|i| is_dropped(i, 0.0, 7)));
    }
}
