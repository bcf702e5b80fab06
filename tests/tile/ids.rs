//! A city model whose two files give two different buildings one gml:id: the SIMULATED `small`
//! scene with its second building's gml:id (and one of its windows' gml:id) set to the first's.
//! Expectations come from the input files and the scene's PLY alone (each building's ground box
//! from its `gml:posList` numbers, each Gaussian's ground position by the alignment written out
//! here) and from the plan of the same scene with unique ids, which never meets a repeated id.
use std::path::Path;

use serde_json::Value;

use super::{f32_at, gs, plan_of, ply_rows, scene, scene_beside, tile, tmp, to_ground};

/// The first `gml:id` written on a start tag `<tag `.
fn first_id(text: &str, tag: &str) -> String {
    let at = text.find(&format!("<{tag} gml:id=\"")).unwrap() + tag.len() + 10;
    text[at..at + text[at..].find('"').unwrap()].to_string()
}

/// Ground box `[x0, y0, x1, y1]` of every coordinate in the file's `gml:posList`s.
fn ground_box(text: &str) -> [f64; 4] {
    let mut b = [
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    ];
    for part in text.split("<gml:posList").skip(1) {
        let body = &part[part.find('>').unwrap() + 1..part.find("</gml:posList>").unwrap()];
        let v: Vec<f64> = body
            .split_whitespace()
            .map(|x| x.parse().unwrap())
            .collect();
        for p in v.chunks(3) {
            b = [
                b[0].min(p[0]),
                b[1].min(p[1]),
                b[2].max(p[0]),
                b[3].max(p[1]),
            ];
        }
    }
    b
}

fn inside(b: [f64; 4], g: [f64; 2]) -> bool {
    g[0] >= b[0] && g[0] <= b[2] && g[1] >= b[1] && g[1] <= b[3]
}

/// The Gaussians (input rows) whose merged label a query of `id` in run `m` selects.
fn query(m: &Path, out: &Path, id: &str) -> Vec<usize> {
    let (ok, text) = gs(&[
        "query",
        "--run",
        m.to_str().unwrap(),
        "--id",
        id,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let sel: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("selection.json")).unwrap())
            .unwrap();
    let labels: std::collections::HashSet<i32> = sel["labels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_i64().unwrap() as i32)
        .collect();
    let l = gs4city::npy::read::<i32>(&m.join("lift/gaussians.npy"))
        .unwrap()
        .1;
    let rows: Vec<usize> = (0..l.len() / 2)
        .filter(|&i| labels.contains(&l[2 * i]))
        .collect();
    assert_eq!(sel["gaussians"].as_u64().unwrap() as usize, rows.len());
    rows
}

#[test]
fn two_buildings_of_two_files_with_one_gml_id_tile_merge_and_answer_a_query_each() {
    let s = scene();
    let d = tmp("dupid");
    let (s2, gml) = scene_beside(
        s,
        &d,
        &[
            "images",
            "sparse",
            "point_cloud.ply",
            "masks",
            "features",
            "scene.json",
        ],
    );
    let a = std::fs::read_to_string(&gml[0]).unwrap();
    let b = std::fs::read_to_string(&gml[1]).unwrap();
    let (id_a, id_b) = (first_id(&a, "bldg:Building"), first_id(&b, "bldg:Building"));
    let (win_a, win_b) = (first_id(&a, "bldg:Window"), first_id(&b, "bldg:Window"));
    assert_ne!(id_a, id_b);
    let attr = |id: &str| format!("gml:id=\"{id}\"");
    assert_eq!(b.matches(&attr(&id_b)).count(), 1);
    assert_eq!(b.matches(&attr(&win_b)).count(), 1);
    let b2 = b
        .replace(&attr(&id_b), &attr(&id_a))
        .replace(&attr(&win_b), &attr(&win_a));
    let (name_a, name_b) = (
        gml[0].file_name().unwrap().to_str().unwrap(),
        gml[1].file_name().unwrap().to_str().unwrap(),
    );
    std::fs::write(s2.join("citymodel").join(name_a), &a).unwrap();
    std::fs::write(s2.join("citymodel").join(name_b), &b2).unwrap();
    // The first file reached a second time (a link) is the same objects, not two more.
    std::os::unix::fs::symlink(
        s2.join("citymodel").join(name_a),
        s2.join("citymodel/zz_twin.gml"),
    )
    .unwrap();
    let (box_a, box_b) = (ground_box(&a), ground_box(&b));
    assert!(
        box_a[2] < box_b[0] || box_b[2] < box_a[0] || box_a[3] < box_b[1] || box_b[3] < box_a[1],
        "the two buildings' ground boxes are apart"
    );

    let p = d.join("P");
    let (ok, text) = gs(&[
        "tile",
        "--scene",
        s2.to_str().unwrap(),
        "--size",
        "10",
        "--margin",
        "1",
        "--out",
        p.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let id_b2 = format!("{id_a}~2");
    let win_b2 = format!("{win_a}~2");
    let warning = text
        .lines()
        .find(|l| l.starts_with("warning:") && l.contains(&id_b2))
        .unwrap_or_else(|| panic!("no warning names {id_b2}: {text}"));
    assert!(
        warning.contains(name_a) && warning.contains(name_b),
        "{warning}"
    );
    assert!(!text.contains("~3") && !text.contains("zz_twin"), "{text}");
    let plan = plan_of(&p);
    let mut owned: Vec<String> = Vec::new();
    let mut known: Vec<String> = Vec::new();
    for t in plan["tiles"].as_array().unwrap() {
        for v in t["owned"].as_array().unwrap() {
            owned.push(v.as_str().unwrap().into());
        }
        for v in t["neighbours"].as_array().unwrap() {
            known.push(v.as_str().unwrap().into());
        }
    }
    owned.sort();
    known.extend(owned.iter().cloned());
    known.sort();
    known.dedup();
    assert_eq!(owned, [id_a.clone(), id_b2.clone()]);
    assert_eq!(known, owned, "two objects, not three");
    // The tile owning the second building (alone: a 1 m margin reaches no neighbour, so its
    // run never meets the first) carries its new ids in its scene, every other byte as written.
    let t_b = plan["tiles"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["owned"][0] == id_b2.as_str())
        .unwrap();
    assert_eq!(t_b["neighbours"].as_array().unwrap().len(), 0);
    let sub = std::fs::read_to_string(
        p.join("tiles")
            .join(t_b["name"].as_str().unwrap())
            .join("scene/citymodel")
            .join(name_b),
    )
    .unwrap();
    assert!(
        sub == b2
            .replace(&attr(&id_a), &attr(&id_b2))
            .replace(&attr(&win_a), &attr(&win_b2)),
        "the tile's {name_b} is the file with the two ids renamed"
    );

    let (ok, text) = gs(&["run-plan", p.to_str().unwrap(), "--jobs", "2"]);
    assert!(ok, "{text}");
    let m = p.join("merged");
    let ents = gs4city::semantics::read(&m.join("citymodel/semantics.json")).unwrap();
    let roots: Vec<(&str, &str)> = ents
        .iter()
        .filter(|e| e.parent.is_none())
        .map(|e| (e.object_id.as_str(), e.source.as_str()))
        .collect();
    assert_eq!(roots.len(), 2, "{roots:?}");
    assert!(roots.iter().any(|(o, f)| *o == id_a && f.ends_with(name_a)));
    assert!(
        roots
            .iter()
            .any(|(o, f)| *o == id_b2 && f.ends_with(name_b))
    );

    // Each query finds its building's Gaussians: in its ground box, none of the other's.
    let bytes = std::fs::read(s.join("point_cloud.ply")).unwrap();
    let (head, n, stride, _) = ply_rows(&bytes);
    let al: Value =
        serde_json::from_str(&std::fs::read_to_string(s.join("citymodel/alignment.json")).unwrap())
            .unwrap();
    let ground = |i: usize| {
        let row = &bytes[head + i * stride..head + (i + 1) * stride];
        to_ground(&al, [f32_at(row, 0), f32_at(row, 1), f32_at(row, 2)])
    };
    let q_a = query(&m, &d.join("QA"), &id_a);
    let q_b = query(&m, &d.join("QB"), &id_b2);
    assert!(
        q_a.len() > 1000 && q_b.len() > 1000,
        "{} {}",
        q_a.len(),
        q_b.len()
    );
    for (rows, own, other) in [(&q_a, box_a, box_b), (&q_b, box_b, box_a)] {
        let own_share =
            rows.iter().filter(|&&i| inside(own, ground(i))).count() as f64 / rows.len() as f64;
        let other_share =
            rows.iter().filter(|&&i| inside(other, ground(i))).count() as f64 / rows.len() as f64;
        assert!(own_share >= 0.98, "{own_share:.4} in its own box");
        assert!(other_share <= 0.01, "{other_share:.4} in the other's box");
    }
    let set_a: std::collections::HashSet<usize> = q_a.iter().copied().collect();
    assert!(q_b.iter().all(|i| !set_a.contains(i)), "disjoint");
    let q_w = query(&m, &d.join("QW"), &win_b2);
    assert!(!q_w.is_empty());
    assert!(
        q_w.iter().all(|i| q_b.contains(i)),
        "the renamed window is the second building's"
    );

    // The same city with unique ids (the scene as synthesised) gives the same labels, and the
    // same Gaussians for each building.
    let p0 = d.join("P0");
    tile(s, &p0, "10", "1");
    let (ok, text) = gs(&["run-plan", p0.to_str().unwrap(), "--jobs", "2"]);
    assert!(ok, "{text}");
    let m0 = p0.join("merged");
    let read = |m: &Path| {
        gs4city::npy::read::<i32>(&m.join("lift/gaussians.npy"))
            .unwrap()
            .1
    };
    assert_eq!(read(&m0).len(), 2 * n);
    assert!(
        read(&m0) == read(&m),
        "the merged labels of the two plans differ"
    );
    assert_eq!(query(&m0, &d.join("Q0A"), &id_a), q_a);
    assert_eq!(query(&m0, &d.join("Q0B"), &id_b), q_b);
}

/// `tile` cuts CityGML only: a scene whose model is CityJSON is refused in one line naming the
/// file (`gs4city run` reads it untiled).
#[test]
fn a_cityjson_model_is_refused_by_tile_naming_the_file() {
    let d = tmp("cityjson");
    let (s2, _) = scene_beside(
        scene(),
        &d,
        &["images", "sparse", "point_cloud.ply", "scene.json"],
    );
    std::fs::write(
        s2.join("citymodel/m.city.jsonl"),
        "{\"type\":\"CityJSON\",\"version\":\"2.0\",\"transform\":{\"scale\":[1,1,1],\"translate\":[0,0,0]},\"CityObjects\":{},\"vertices\":[]}\n",
    )
    .unwrap();
    let (ok, text) = gs(&[
        "tile",
        "--scene",
        s2.to_str().unwrap(),
        "--out",
        d.join("P").to_str().unwrap(),
    ]);
    assert!(!ok, "{text}");
    let line = text
        .lines()
        .find(|l| l.contains("m.city.jsonl"))
        .unwrap_or_default();
    assert!(
        line.contains("CityJSON") && line.contains("CityGML"),
        "{text}"
    );
    assert!(!d.join("P").exists());
}
