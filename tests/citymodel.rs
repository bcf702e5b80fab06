//! The citymodel stage on real CityGML (../shared/data/citygml) and on hand-made bad input.
use std::path::{Path, PathBuf};

use glam::{DVec2, DVec3};
use gs4city::citygml::{self, Class};
use gs4city::citymodel::{self, triangulate};
use rand::{Rng, SeedableRng};

fn shared() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/citygml")
}

/// The real data sits beside the repository (as in CI); without it these tests cannot run.
fn require_shared() -> PathBuf {
    let dir = shared();
    assert!(
        dir.is_dir(),
        "{} is missing: the real-data tests need the shared CityGML folder beside the repo",
        dir.display()
    );
    dir
}

/// (file, buildings, wall, roof, ground, windows, doors, polygons, holes) from SOURCES.md.
type Counts = (
    &'static str,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
    usize,
);
const SINGLE_FILES: &[Counts] = &[
    (
        "citygml1_FZK-House-LoD3-KIT-IAI-KHH-V2.gml",
        1,
        4,
        2,
        1,
        11,
        2,
        210,
        13,
    ),
    (
        "citygml2_ingolstadt_lod3_4018133.gml",
        1,
        31,
        4,
        2,
        16,
        3,
        130,
        39,
    ),
    (
        "citygml3_FZK-Haus-LoD3-KIT-IAI-KHH-B36-V1__v3.gml",
        1,
        4,
        2,
        1,
        11,
        2,
        210,
        13,
    ),
];

#[test]
fn single_files_match_sources_counts() {
    let dir = require_shared();
    for &(name, b, w, r, g, win, door, polys, holes) in SINGLE_FILES {
        let out = citymodel::run(&[dir.join(name)], &Default::default()).unwrap();
        let s = &serde_json::to_value(&out.summary).unwrap();
        assert_eq!(s["buildings"], b, "{name}");
        assert_eq!(s["surfaces"]["WallSurface"], w, "{name}");
        assert_eq!(s["surfaces"]["RoofSurface"], r, "{name}");
        assert_eq!(s["surfaces"]["GroundSurface"], g, "{name}");
        assert_eq!(s["windows"], win, "{name}");
        assert_eq!(s["doors"], door, "{name}");
        assert_eq!(s["polygons"], polys, "{name}");
        assert_eq!(s["holes"], holes, "{name}");
        out.mesh.validate().unwrap();
        // Every face label points at entities of the right level, and parts sit on their surface.
        for l in &out.mesh.labels {
            let f = &out.entities[l.feature as usize];
            assert_eq!(format!("{:?}", f.level), "Feature");
            if l.part >= 0 {
                let p = &out.entities[l.part as usize];
                assert_eq!(
                    p.parent,
                    Some(l.surface),
                    "{name}: part {} not under surface {}",
                    p.object_id,
                    l.surface
                );
            }
        }
    }
}

#[test]
fn cityml1_and_3_of_the_same_house_agree() {
    let dir = require_shared();
    let a = citymodel::run(&[dir.join(SINGLE_FILES[0].0)], &Default::default()).unwrap();
    let b = citymodel::run(&[dir.join(SINGLE_FILES[2].0)], &Default::default()).unwrap();
    assert_eq!(a.mesh.faces.len(), b.mesh.faces.len());
    let area = |m: &gs4city::mesh::TriMesh| {
        m.faces
            .iter()
            .map(|f| {
                let [p, q, r] =
                    f.map(|i| glam::Vec3::from_array(m.vertices[i as usize]).as_dvec3());
                0.5 * (q - p).cross(r - p).length()
            })
            .sum::<f64>()
    };
    assert!((area(&a.mesh) - area(&b.mesh)).abs() < 1e-3 * area(&a.mesh));
    // 3.0 keeps con:height and generic attributes; 1.0 keeps measuredHeight.
    assert_eq!(a.entities[0].attributes["measuredHeight"], 6.52);
    assert!(
        b.entities[0]
            .attributes
            .keys()
            .any(|k| k.starts_with("height")),
        "{:?}",
        b.entities[0].attributes.keys()
    );
}

/// (id, installations, wall, roof, ground, closure, outer_ceiling, outer_floor, windows, doors, polygons, holes)
#[test]
fn street_block_matches_sources_totals() {
    let dir = require_shared().join("ingolstadt_north");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .map(|d| d.join(format!("{}.gml", d.file_name().unwrap().to_string_lossy())))
        .collect();
    files.sort();
    assert_eq!(files.len(), 27);
    let out = citymodel::run(&files, &Default::default()).unwrap();
    let s = &serde_json::to_value(&out.summary).unwrap();
    assert_eq!(s["buildings"], 27);
    assert_eq!(s["building_parts"], 0);
    assert_eq!(s["installations"], 132);
    assert_eq!(s["surfaces"]["WallSurface"], 1393);
    assert_eq!(s["surfaces"]["RoofSurface"], 230);
    assert_eq!(s["surfaces"]["GroundSurface"], 33);
    assert_eq!(s["surfaces"]["ClosureSurface"], 4);
    assert_eq!(s["surfaces"]["OuterCeilingSurface"], 546);
    assert_eq!(s["surfaces"]["OuterFloorSurface"], 77);
    assert_eq!(s["windows"], 612);
    assert_eq!(s["doors"], 33);
    assert_eq!(s["polygons"], 24342);
    assert_eq!(s["holes"], 2694);
    // Every skip names its polygon and reason.
    let skipped = s["skipped"]["polygons"].as_array().unwrap();
    assert_eq!(
        skipped.len() as u64,
        s["skipped"]["count"].as_u64().unwrap()
    );
    for k in skipped {
        assert!(
            k["polygon"].is_string() && k["reason"].is_string() && k["line"].as_u64().unwrap() > 0,
            "{k}"
        );
    }
    // The mesh lives near the origin (local frame): f32 keeps millimetres.
    let max = out
        .mesh
        .vertices
        .iter()
        .flatten()
        .fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(max < 1000.0, "{max}");
    // Derived ids for surfaces without gml:id are unique.
    let mut ids: Vec<&str> = out.entities.iter().map(|e| e.object_id.as_str()).collect();
    ids.sort();
    let n = ids.len();
    ids.dedup();
    assert_eq!(ids.len(), n, "duplicate object ids");
}

fn read(snippet: &str) -> Result<citygml::CityModel, citygml::CityGmlError> {
    citygml::read_bytes(Path::new("test.gml"), snippet.as_bytes())
}

const HEAD: &str = r#"<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:bldg="http://www.opengis.net/citygml/building/2.0"
 xmlns:gml="http://www.opengis.net/gml" xmlns:xlink="http://www.w3.org/1999/xlink" xmlns:gen="http://www.opengis.net/citygml/generics/2.0">
<core:cityObjectMember><bldg:Building gml:id="B1">
<bldg:measuredHeight uom="m">12.5</bldg:measuredHeight>
<gen:stringAttribute name="note"><gen:value>a &amp; b</gen:value></gen:stringAttribute>
"#;
const TAIL: &str = "</bldg:Building></core:cityObjectMember></core:CityModel>\n";

fn wall(ring: &str) -> String {
    format!(
        "<bldg:boundedBy><bldg:WallSurface><bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember>\
         <gml:Polygon gml:id=\"P1\"><gml:exterior><gml:LinearRing><gml:posList srsDimension=\"3\">{ring}</gml:posList>\
         </gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface>\
         </bldg:WallSurface></bldg:boundedBy>\n"
    )
}

#[test]
fn attributes_derived_ids_and_a_good_wall() {
    let m = read(&format!(
        "{HEAD}{}{TAIL}",
        wall("0 0 0 4 0 0 4 0 3 0 0 3 0 0 0")
    ))
    .unwrap();
    assert_eq!(m.objects.len(), 2);
    assert_eq!(m.objects[0].attributes["measuredHeight"], 12.5);
    assert_eq!(m.objects[0].attributes["measuredHeight.uom"], "m");
    assert_eq!(m.objects[0].attributes["note"], "a & b");
    assert_eq!(m.objects[1].object_id, "B1/WallSurface[1]");
    assert!(!m.objects[1].has_gml_id);
    assert_eq!(m.used_polygons().count(), 1);
    assert_eq!(
        m.polygons[0].exterior.points.len(),
        4,
        "closing point removed"
    );
}

#[test]
fn bad_input_gives_named_errors_or_warnings_never_panics() {
    // Truncated file: an error naming the file and a line.
    let full = format!("{HEAD}{}{TAIL}", wall("0 0 0 4 0 0 4 0 3 0 0 3 0 0 0"));
    for cut in [full.len() / 3, full.len() / 2, full.len() - 10] {
        let e = read(&full[..cut]).unwrap_err().to_string();
        assert!(e.contains("test.gml:"), "{e}");
    }
    // Not CityGML.
    let e = read("<?xml version=\"1.0\"?><html><body/></html>")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("not a CityGML file") && e.contains("html"),
        "{e}"
    );
    // A number that is no number: error with polygon id and line.
    let e = read(&format!("{HEAD}{}{TAIL}", wall("0 0 0 4 0 x 4 0 3 0 0 0")))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("P1") && e.contains("'x'") && e.contains("test.gml:"),
        "{e}"
    );
    // Wrong coordinate count.
    let e = read(&format!("{HEAD}{}{TAIL}", wall("0 0 0 4 0 0 4 0")))
        .unwrap_err()
        .to_string();
    assert!(e.contains("multiple of srsDimension"), "{e}");
    // Dangling xlink: a named warning, the rest is read.
    let dangling = format!(
        "{HEAD}<bldg:lod3Solid><gml:Solid><gml:exterior><gml:CompositeSurface><gml:surfaceMember xlink:href=\"#nowhere\"/>\
         </gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod3Solid>{}{TAIL}",
        wall("0 0 0 4 0 0 4 0 3 0 0 3 0 0 0")
    );
    let m = read(&dangling).unwrap();
    assert_eq!(m.stats.xlinks_dangling, 1);
    assert!(
        m.warnings
            .iter()
            .any(|w| w.message.contains("#nowhere") && w.id.as_deref() == Some("B1")),
        "{:?}",
        m.warnings
    );
    // A ring with 2 points and NaN coordinates: read, then skipped by the stage with a named reason.
    for (ring, why) in [
        ("0 0 0 4 0 0 0 0 0", "fewer than 3"),
        ("0 0 0 NaN 0 0 4 0 3 0 0 0", "non-finite"),
    ] {
        let dir = crate::common::temp_dir().join(format!("gs4city-bad-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("bad.gml");
        std::fs::write(
            &f,
            format!(
                "{HEAD}{}{}{TAIL}",
                wall(ring),
                wall("0 0 0 4 0 0 4 0 3 0 0 3 0 0 0").replace("P1", "P2")
            ),
        )
        .unwrap();
        let out = citymodel::run(&[f], &Default::default()).unwrap();
        let sk = &out.summary.skipped.polygons[0];
        assert_eq!(sk.polygon.as_deref(), Some("P1"));
        assert!(sk.reason.contains(why), "{sk:?}");
        assert_eq!(out.mesh.faces.len(), 2, "the good wall is kept");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

#[test]
fn building_parts_nested_without_end_are_refused_with_the_line() {
    // Parts without gml:id derive ids from their parents', which grow with the depth: 20
    // levels are read, 40 refused at the 33rd level with its line.
    let nest = |levels: usize| {
        let mut s = String::from(HEAD);
        for _ in 0..levels {
            s.push_str("<bldg:consistsOfBuildingPart>\n<bldg:BuildingPart>\n");
        }
        s.push_str(&wall("0 0 0 4 0 0 4 0 3 0 0 3 0 0 0"));
        for _ in 0..levels {
            s.push_str("</bldg:BuildingPart></bldg:consistsOfBuildingPart>\n");
        }
        s.push_str(TAIL);
        s
    };
    let m = read(&nest(20)).unwrap();
    assert_eq!(m.objects.len(), 22);
    let deepest = &m.objects[20].object_id;
    assert!(
        deepest.starts_with("B1/BuildingPart[1]/BuildingPart[1]/"),
        "{deepest}"
    );
    let e = read(&nest(40)).unwrap_err().to_string();
    // HEAD has 6 lines before the first part; each level adds 2 lines.
    let line = 6 + 2 * 32;
    assert!(
        e.contains(&format!("test.gml:{line}")) && e.contains("nested in 32 other city objects"),
        "{e}"
    );
}

#[test]
fn xlinked_solid_polygons_are_counted_once_and_reversed_surfaces_flip() {
    let snippet = format!(
        "{HEAD}<bldg:lod3Solid><gml:Solid><gml:exterior><gml:CompositeSurface><gml:surfaceMember xlink:href=\"#P1\"/>\
         <gml:surfaceMember><gml:OrientableSurface orientation=\"-\"><gml:baseSurface xlink:href=\"#P9\"/></gml:OrientableSurface></gml:surfaceMember>\
         </gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod3Solid>{}\
         <bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon gml:id=\"P9\"><gml:exterior><gml:LinearRing>\
         <gml:pos>0 0 5</gml:pos><gml:pos>1 0 5</gml:pos><gml:pos>1 1 5</gml:pos><gml:pos>0 0 5</gml:pos></gml:LinearRing></gml:exterior></gml:Polygon>\
         </gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface>{TAIL}",
        wall("0 0 0 4 0 0 4 0 3 0 0 3 0 0 0")
    );
    let m = read(&snippet).unwrap();
    assert_eq!(m.stats.polygons, 2);
    assert_eq!(
        m.stats.xlinks_shared, 2,
        "both references point at inline-owned polygons"
    );
    assert_eq!(m.used_polygons().count(), 2);
    assert_eq!(m.count(Class::WallSurface), 1);
}

/// A reference to a container whose members are themselves references (a CompositeSurface
/// of xlinks, here in a cycle C1 → C2 → C1) is followed to the polygons they name, not
/// reported as dangling; a container of references that name nothing is reported as such.
#[test]
fn nested_xlinks_are_followed_and_cycles_cut() {
    let p9 = "<bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon gml:id=\"P9\"><gml:exterior><gml:LinearRing>\
         <gml:pos>0 0 5</gml:pos><gml:pos>1 0 5</gml:pos><gml:pos>1 1 5</gml:pos><gml:pos>0 0 5</gml:pos></gml:LinearRing></gml:exterior></gml:Polygon>\
         </gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface>";
    let by_ref = |href: &str| {
        format!(
            "<bldg:boundedBy><bldg:WallSurface gml:id=\"W{href}\"><bldg:lod3MultiSurface><gml:MultiSurface>\
             <gml:surfaceMember xlink:href=\"#{href}\"/></gml:MultiSurface></bldg:lod3MultiSurface></bldg:WallSurface></bldg:boundedBy>"
        )
    };
    let snippet = format!(
        "{HEAD}<bldg:lod3Solid><gml:Solid><gml:exterior><gml:CompositeSurface gml:id=\"C1\">\
         <gml:surfaceMember xlink:href=\"#C2\"/></gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod3Solid>\
         <bldg:lod4Solid><gml:Solid><gml:exterior><gml:CompositeSurface gml:id=\"C2\">\
         <gml:surfaceMember xlink:href=\"#C1\"/><gml:surfaceMember xlink:href=\"#P9\"/></gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod4Solid>\
         {p9}{}{TAIL}",
        by_ref("C1")
    );
    let m = read(&snippet).unwrap();
    assert_eq!(m.stats.xlinks_dangling, 0, "{:?}", m.warnings);
    // #C1 (the wall's), #C2 (in C1), #C1 and #P9 (in C2): each names P9.
    assert_eq!(m.stats.xlinks_shared, 4, "{:?}", m.stats);
    // A container whose one member names nothing: that member and the reference to the
    // container are both reported, the container's by what it holds.
    let snippet = format!(
        "{HEAD}<bldg:lod3Solid><gml:Solid><gml:exterior><gml:CompositeSurface gml:id=\"C3\">\
         <gml:surfaceMember xlink:href=\"#nowhere\"/></gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod3Solid>\
         {p9}{}{TAIL}",
        by_ref("C3")
    );
    let m = read(&snippet).unwrap();
    assert_eq!(m.stats.xlinks_dangling, 2);
    assert!(
        m.warnings
            .iter()
            .any(|w| w.message.contains("#C3") && w.message.contains("name no geometry")),
        "{:?}",
        m.warnings
    );
}

#[test]
fn lod2_fallback_is_named() {
    let snippet = format!(
        "{HEAD}{}{TAIL}",
        wall("0 0 0 4 0 0 4 0 3 0 0 3 0 0 0").replace("lod3", "lod2")
    );
    let m = read(&snippet).unwrap();
    assert_eq!(m.objects[0].lod_used, Some(2));
    assert!(m.warnings.iter().any(|w| w.message.contains("using LoD2")));
}

/// Seeded property test: random star-shaped polygons with disjoint holes, in random 3D planes.
#[test]
fn random_polygons_with_holes_keep_area_and_empty_holes() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2026);
    for case in 0..300 {
        // Jittered angles with gaps < π/3, radii ≥ 6: every chord stays ≥ 6·cos(π/6) ≈ 5.2 from the centre.
        let n = rng.random_range(12..40);
        let step = std::f64::consts::TAU / n as f64;
        let angles: Vec<f64> = (0..n)
            .map(|k| (k as f64 + rng.random_range(-0.4..0.4)) * step)
            .collect();
        let outer: Vec<DVec2> = angles
            .iter()
            .map(|&a| DVec2::from_angle(a) * rng.random_range(6.0..10.0))
            .collect();
        // Holes: small squares on a 2 m grid within radius 5.15 (disjoint, inside the outer ring).
        let mut holes: Vec<Vec<DVec2>> = Vec::new();
        for gx in -2..2 {
            for gy in -2..2 {
                if rng.random_bool(0.4) {
                    let c = DVec2::new(gx as f64 * 2.0 + 1.0, gy as f64 * 2.0 + 1.0);
                    let h = rng.random_range(0.2..0.9);
                    let rot = rng.random_range(0.0..1.5);
                    holes.push(
                        (0..4)
                            .map(|k| {
                                c + DVec2::from_angle(rot + k as f64 * std::f64::consts::FRAC_PI_2)
                                    * h
                            })
                            .collect(),
                    );
                }
            }
        }
        let area_expected =
            shoelace(&outer).abs() - holes.iter().map(|h| shoelace(h).abs()).sum::<f64>();
        // Random plane through a random point.
        let nrm = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        let u = nrm.any_orthonormal_vector();
        let v = nrm.cross(u);
        let o = DVec3::new(
            rng.random_range(-50.0..50.0),
            rng.random_range(-50.0..50.0),
            rng.random_range(0.0..30.0),
        );
        let lift = |r: &[DVec2]| r.iter().map(|p| o + u * p.x + v * p.y).collect::<Vec<_>>();
        let t = triangulate::triangulate(
            &lift(&outer),
            &holes.iter().map(|h| lift(h)).collect::<Vec<_>>(),
        )
        .unwrap();
        assert!(
            (t.area - area_expected).abs() <= 1e-9 * area_expected,
            "case {case}: {} vs {area_expected}",
            t.area
        );
        // No triangle covers a hole: centroids outside every hole and inside the outer ring.
        for tri in &t.triangles {
            let c = tri.iter().map(|&i| t.vertices[i as usize]).sum::<DVec3>() / 3.0 - o;
            let c2 = DVec2::new(c.dot(u), c.dot(v));
            assert!(inside(c2, &outer), "case {case}: triangle outside");
            assert!(
                holes.iter().all(|h| !inside(c2, h)),
                "case {case}: triangle in a hole"
            );
        }
    }
}

fn shoelace(r: &[DVec2]) -> f64 {
    (0..r.len())
        .map(|i| r[i].perp_dot(r[(i + 1) % r.len()]))
        .sum::<f64>()
        * 0.5
}

fn inside(p: DVec2, r: &[DVec2]) -> bool {
    let mut c = false;
    let mut j = r.len() - 1;
    for i in 0..r.len() {
        if (r[i].y > p.y) != (r[j].y > p.y)
            && p.x < (r[j].x - r[i].x) * (p.y - r[i].y) / (r[j].y - r[i].y) + r[i].x
        {
            c = !c;
        }
        j = i;
    }
    c
}

/// When nothing can be triangulated, the error says why: the first skipped polygon with its
/// file, line and reason.
#[test]
fn nothing_triangulated_names_the_first_reason() {
    let dir = crate::common::temp_dir().join(format!("gs4city-none-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let f = dir.join("nan.gml");
    std::fs::write(
        &f,
        format!("{HEAD}{}{TAIL}", wall("0 0 0 NaN 0 0 4 0 3 0 0 0")),
    )
    .unwrap();
    let e = citymodel::run(&[f], &Default::default())
        .err()
        .expect("nothing to write")
        .to_string();
    assert!(
        e.contains("1 polygons skipped, first: ")
            && e.contains("nan.gml:")
            && e.contains("polygon P1")
            && e.contains("non-finite"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// A polygon farther than `PLANARITY_WARNING` from its plane is named in a warning with its
/// deviation and still triangulated; one within the tolerance is not named. The saddles'
/// expectations are by hand: corners (0,0,±h), (4,0,∓h), (4,4,±h), (0,4,∓h) have their centroid
/// at z = 0 and, by symmetry, the Newell normal (0,0,1), so every corner lies exactly h from the
/// plane.
#[test]
fn a_polygon_beyond_the_planarity_tolerance_is_named_with_its_deviation() {
    let dir = crate::common::temp_dir().join(format!("gs4city-planar-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let saddle = |id: &str, h: f64| {
        wall(&format!("0 0 {h} 4 0 {} 4 4 {h} 0 4 {} 0 0 {h}", -h, -h))
            .replace("\"P1\"", &format!("\"{id}\""))
    };
    let f = dir.join("saddles.gml");
    std::fs::write(
        &f,
        format!(
            "{HEAD}{}{}{}{TAIL}",
            saddle("BENT", 0.25),
            saddle("SLIGHT", 0.004),
            saddle("FLAT", 0.0)
        ),
    )
    .unwrap();
    let out = citymodel::run(std::slice::from_ref(&f), &Default::default()).unwrap();
    let s = &out.summary;
    let p = &s.max_planarity_deviation;
    assert!((p.metres - 0.25).abs() < 1e-12, "{p:?}");
    assert!(p.polygon.contains("BENT"), "{p:?}");
    assert_eq!(p.beyond_tolerance, 1, "{p:?}");
    let named: Vec<&String> = s
        .warnings
        .items
        .iter()
        .filter(|w| w.contains("from their plane"))
        .collect();
    assert_eq!(named.len(), 1, "{:?}", s.warnings.items);
    let w = named[0];
    assert!(
        w.contains("saddles.gml:") && w.contains("BENT") && w.contains("up to 0.250 "),
        "{w}"
    );
    // All three are triangulated: two triangles each.
    assert_eq!(s.polygons_used, 3, "{s:?}");
    assert_eq!(s.triangles, 6, "{s:?}");
    std::fs::remove_dir_all(&dir).ok();
}
