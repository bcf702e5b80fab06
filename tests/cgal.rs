//! gs4city's triangulation (spade) against the committed CGAL reference triangulations
//! (`tests/reference/cgal/*.json`, made by `scripts/cgal_reference.py`), polygon by polygon.
use std::path::Path;

use glam::{DVec2, DVec3};
use gs4city::citygml;
use gs4city::citymodel::triangulate::{self, Repair, SkipReason};

fn inside(p: DVec2, rings: &[Vec<DVec2>]) -> bool {
    let mut c = false;
    for r in rings {
        let mut j = r.len() - 1;
        for i in 0..r.len() {
            if (r[i].y > p.y) != (r[j].y > p.y)
                && p.x < (r[j].x - r[i].x) * (p.y - r[i].y) / (r[j].y - r[i].y) + r[i].x
            {
                c = !c;
            }
            j = i;
        }
    }
    c
}

#[derive(Default, Debug)]
struct Tally {
    polygons: usize,
    both_ok: usize,
    both_skipped: usize,
    repaired_vs_cgal_split: usize,
    nonplanar: usize,
    /// Polygons where CGAL's centroid filter kept more triangles than a simple ring can have.
    cgal_extra_slivers: usize,
    max_rel_projected: f64,
    max_rel_area_planar: f64,
    max_area_excess_nonplanar: f64,
}

#[test]
fn triangulation_matches_cgal_reference_on_every_polygon() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let refs = root.join("tests/reference/cgal");
    let mut jsons: Vec<_> = std::fs::read_dir(&refs)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    jsons.sort();
    assert!(
        jsons.len() >= 30,
        "expected the reference files of the 30 shared CityGML files"
    );
    let mut t = Tally::default();
    let mut failures: Vec<String> = Vec::new();
    for json in &jsons {
        let r: serde_json::Value = serde_json::from_slice(&std::fs::read(json).unwrap()).unwrap();
        let gml = root.join(r["file"].as_str().unwrap());
        assert!(
            gml.is_file(),
            "{} (from {}) is missing: the shared data must sit beside the repo",
            gml.display(),
            json.display()
        );
        let model = citygml::read(&gml).unwrap();
        let polys = r["polygons"].as_array().unwrap();
        assert_eq!(
            model.polygons.len(),
            polys.len(),
            "{}: patch count",
            gml.display()
        );
        assert_eq!(
            model.stats.holes as u64,
            r["holes"].as_u64().unwrap(),
            "{}: holes",
            gml.display()
        );
        for (p, c) in model.polygons.iter().zip(polys) {
            t.polygons += 1;
            assert_eq!(
                p.id.as_deref(),
                c["id"].as_str(),
                "{}: ordinal {}",
                gml.display(),
                p.ordinal
            );
            let o = p.exterior.points.first().copied().unwrap_or(DVec3::ZERO);
            let ext: Vec<DVec3> = p.exterior.points.iter().map(|q| *q - o).collect();
            let holes: Vec<Vec<DVec3>> = p
                .interiors
                .iter()
                .map(|h| h.points.iter().map(|q| *q - o).collect())
                .collect();
            let mine = triangulate::triangulate(&ext, &holes);
            let cgal_ok = c["status"] == "ok";
            let reason = c["reason"].as_str().unwrap_or("");
            let label = format!("{} {}", gml.display(), p.label());
            match (&mine, cgal_ok) {
                (Err(SkipReason::TooFewPoints | SkipReason::ZeroArea), false)
                    if reason.starts_with("degenerate") =>
                {
                    t.both_skipped += 1
                }
                (Ok(m), false) if reason.starts_with("intersecting constraints") => {
                    // CGAL splits crossing ring edges too; gs4city keeps the even-odd area and says so.
                    if !m.repairs.contains(&Repair::SelfIntersection) {
                        failures.push(format!(
                            "{label}: CGAL found crossing edges, gs4city did not"
                        ));
                    }
                    t.repaired_vs_cgal_split += 1;
                }
                (Ok(m), true) => {
                    t.both_ok += 1;
                    let ap = c["area_projected"].as_f64().unwrap();
                    // Relative 1e-9, with a floor of 1e-15 m² for µm-sized slivers.
                    let rel = (m.area_projected - ap).abs() / ap.abs().max(1e-6);
                    t.max_rel_projected = t.max_rel_projected.max(rel);
                    if (m.area_projected - ap).abs() > 1e-9 * ap.abs() + 1e-15 {
                        failures.push(format!(
                            "{label}: projected area {} vs CGAL {ap}",
                            m.area_projected
                        ));
                    }
                    // Without Steiner points, any triangulation of n points in 1 + h simple rings
                    // has n − 2 + 2h triangles (Euler).
                    let n_points = c["points"].as_u64().unwrap() as usize;
                    let euler = n_points + 2 * holes.len() - 2;
                    let cg = c["triangles"].as_u64().unwrap() as usize;
                    if m.triangles.len() != cg {
                        if m.triangles.len() == euler && cg != euler {
                            t.cgal_extra_slivers += 1;
                        } else {
                            failures.push(format!(
                                "{label}: {} triangles vs CGAL {cg} (Euler count {euler})",
                                m.triangles.len()
                            ));
                        }
                    }
                    let a = c["area"].as_f64().unwrap();
                    let planarity = c["planarity"].as_f64().unwrap_or(0.0);
                    if planarity <= 1e-9 * ap.sqrt().max(1.0) {
                        let rel = (m.area - a).abs() / a.max(1e-12);
                        t.max_rel_area_planar = t.max_rel_area_planar.max(rel);
                        if rel > 1e-9 {
                            failures.push(format!("{label}: planar area {} vs CGAL {a}", m.area));
                        }
                    } else {
                        // Non-planar: the 3D area depends on the diagonals chosen (cocircular corners);
                        // it is bounded by the deviation from the plane times the perimeter.
                        t.nonplanar += 1;
                        let perimeter: f64 = std::iter::once(&ext)
                            .chain(&holes)
                            .map(|r| {
                                (0..r.len())
                                    .map(|i| (r[(i + 1) % r.len()] - r[i]).length())
                                    .sum::<f64>()
                            })
                            .sum();
                        let excess = (m.area - a).abs() / (planarity * perimeter);
                        t.max_area_excess_nonplanar = t.max_area_excess_nonplanar.max(excess);
                        if excess > 1.0 {
                            failures.push(format!(
                                "{label}: non-planar area {} vs CGAL {a} (planarity {planarity})",
                                m.area
                            ));
                        }
                    }
                    // No triangle outside the polygon, holes stay empty (in the polygon's plane).
                    let u = m.normal.any_orthonormal_vector();
                    let v = m.normal.cross(u);
                    let proj = |q: DVec3| DVec2::new(q.dot(u), q.dot(v));
                    let rings: Vec<Vec<DVec2>> = std::iter::once(&ext)
                        .chain(&holes)
                        .map(|r| r.iter().map(|&q| proj(q)).collect())
                        .collect();
                    for tri in &m.triangles {
                        let cen = tri.iter().map(|&i| m.vertices[i as usize]).sum::<DVec3>() / 3.0;
                        if !inside(proj(cen), &rings) {
                            failures.push(format!(
                                "{label}: a triangle lies outside the polygon or in a hole"
                            ));
                            break;
                        }
                    }
                }
                (mine, _) => failures.push(format!(
                    "{label}: gs4city {:?} vs CGAL {} {reason}",
                    mine.as_ref().map(|m| m.triangles.len()),
                    c["status"]
                )),
            }
        }
    }
    println!("{t:#?}");
    assert!(
        failures.is_empty(),
        "{} mismatches:\n{}",
        failures.len(),
        failures.join("\n")
    );
    assert!(t.both_ok > 20_000, "{t:?}");
}
