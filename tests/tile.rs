//! `gs4city tile`, `run-plan`, `merge` on a SIMULATED scene (`synth --preset small`: two real
//! buildings ~20 m apart, so 10 m tiles make two tiles). Expectations are computed here from the
//! plan's own numbers and the input files, by formulas that share no code with the cut or the
//! merge: membership of each Gaussian by its distance to each tile's core box, rows compared
//! byte for byte, the merged labels re-derived from the tiles' outputs by object id and offset;
//! the padded PLY headers are read back by plyfile; the Slurm job array runs on a real
//! single-node Slurm (`scripts/slurm_test.sh`).
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use serde_json::Value;

use crate::common;

mod ids;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_gs4city"))
}

fn tmp(name: &str) -> PathBuf {
    let d = crate::common::temp_dir().join(format!("gs4city-tile-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Runs `gs4city ARGS`; returns (success, stdout + stderr).
fn gs(args: &[&str]) -> (bool, String) {
    let o = bin().arg("-q").args(args).output().unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    (o.status.success(), text)
}

/// The SIMULATED small scene, made once for every test here.
fn scene() -> &'static Path {
    static S: OnceLock<PathBuf> = OnceLock::new();
    S.get_or_init(|| {
        let d = tmp("scene");
        let s = d.join("small");
        let (ok, out) = gs(&["synth", "--preset", "small", "--out", s.to_str().unwrap()]);
        assert!(ok, "{out}");
        s
    })
}

/// The untiled run of `scene()`, made once for every test here.
fn untiled_run() -> &'static Path {
    static R: OnceLock<PathBuf> = OnceLock::new();
    R.get_or_init(|| {
        let r = tmp("untiled").join("R");
        let (ok, text) = gs(&[
            "run",
            "--scene",
            scene().to_str().unwrap(),
            "--out",
            r.to_str().unwrap(),
        ]);
        assert!(ok, "{text}");
        r
    })
}

/// The merged run `m` of a plan of `scene()` agrees with its untiled run: at least 95 % of the
/// Gaussians keep their class and the test views' fine mIoU is within 0.02. Returns the merged
/// (label, class) pairs per Gaussian.
fn assert_agrees_with_untiled(m: &Path) -> Vec<i32> {
    let r = untiled_run();
    let a = gs4city::npy::read::<i32>(&r.join("lift/gaussians.npy"))
        .unwrap()
        .1;
    let b = gs4city::npy::read::<i32>(&m.join("lift/gaussians.npy"))
        .unwrap()
        .1;
    assert_eq!(a.len(), b.len());
    let same = a
        .chunks(2)
        .zip(b.chunks(2))
        .filter(|(x, y)| x[1] == y[1])
        .count();
    let share = same as f64 / (a.len() / 2) as f64;
    assert!(
        share >= 0.95,
        "{share:.4} of the Gaussians keep their class"
    );
    let u = json(&r.join("eval/metrics.json"))["paper"]["miou"]["mean"]
        .as_f64()
        .unwrap();
    let t = json(&m.join("summary.json"))["paper_fine_miou"]
        .as_f64()
        .unwrap();
    assert!(
        (u - t).abs() < 0.02,
        "fine mIoU untiled {u:.4}, tiled {t:.4}"
    );
    b
}

fn plan_of(dir: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("plan.json")).unwrap()).unwrap()
}

fn tile(scene: &Path, out: &Path, size: &str, margin: &str) {
    let (ok, text) = gs(&[
        "tile",
        "--scene",
        scene.to_str().unwrap(),
        "--size",
        size,
        "--margin",
        margin,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
}

/// A scene folder `d/scene` made of links to the `parts` of scene `s` and a copy of its
/// alignment, its `citymodel/` otherwise empty; with `s`'s CityGML files, sorted.
fn scene_beside(s: &Path, d: &Path, parts: &[&str]) -> (PathBuf, Vec<PathBuf>) {
    let s2 = d.join("scene");
    std::fs::create_dir_all(s2.join("citymodel")).unwrap();
    for part in parts {
        std::os::unix::fs::symlink(s.join(part), s2.join(part)).unwrap();
    }
    std::fs::copy(
        s.join("citymodel/alignment.json"),
        s2.join("citymodel/alignment.json"),
    )
    .unwrap();
    let mut gml: Vec<PathBuf> = std::fs::read_dir(s.join("citymodel"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "gml"))
        .collect();
    gml.sort();
    (s2, gml)
}

/// A binary little-endian all-float PLY: (header length, rows, stride, property names).
fn ply_rows(bytes: &[u8]) -> (usize, usize, usize, Vec<String>) {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    let head = std::str::from_utf8(&bytes[..end]).unwrap();
    assert!(head.contains("format binary_little_endian 1.0"));
    let mut n = 0;
    let mut props = Vec::new();
    for l in head.lines() {
        let w: Vec<&str> = l.split_whitespace().collect();
        match w.as_slice() {
            ["element", "vertex", c] => n = c.parse().unwrap(),
            ["property", "float", name] => props.push(name.to_string()),
            ["property", ..] => panic!("not an all-float PLY: {l}"),
            _ => {}
        }
    }
    (end, n, 4 * props.len(), props)
}

fn f32_at(row: &[u8], k: usize) -> f64 {
    f64::from(f32::from_le_bytes(
        row[4 * k..4 * k + 4].try_into().unwrap(),
    ))
}

/// The scene → ground transform of `alignment.json`, written out here: geo = Rᵀ(p − t)/s + origin.
fn to_ground(al: &Value, p: [f64; 3]) -> [f64; 2] {
    let r = &al["rotation"];
    let s = al["scale"].as_f64().unwrap();
    let d: Vec<f64> = (0..3)
        .map(|k| (p[k] - al["translation"][k].as_f64().unwrap()) / s)
        .collect();
    let g = |c: usize| -> f64 {
        (0..3)
            .map(|k| r[k][c].as_f64().unwrap() * d[k])
            .sum::<f64>()
            + al["origin"][c].as_f64().unwrap()
    };
    [g(0), g(1)]
}

fn npy_i64(path: &Path) -> Vec<i64> {
    gs4city::npy::read::<i64>(path).unwrap().1
}

#[test]
fn the_cut_puts_every_gaussian_byte_for_byte_into_the_tiles_within_the_margin_of_it() {
    let s = scene();
    let p = tmp("cut").join("P");
    tile(s, &p, "10", "4");
    let plan = plan_of(&p);
    let tiles = plan["tiles"].as_array().unwrap();
    assert_eq!(tiles.len(), 2, "two buildings ~20 m apart, 10 m tiles");
    let margin = 4.0;
    let al: Value =
        serde_json::from_str(&std::fs::read_to_string(s.join("citymodel/alignment.json")).unwrap())
            .unwrap();
    let src = std::fs::read(s.join("point_cloud.ply")).unwrap();
    let (h0, n, stride, props) = ply_rows(&src);
    assert_eq!(plan["gaussians"].as_u64().unwrap() as usize, n);
    let (ix, iy, iz) = (
        props.iter().position(|p| p == "x").unwrap(),
        props.iter().position(|p| p == "y").unwrap(),
        props.iter().position(|p| p == "z").unwrap(),
    );
    let row = |i: usize| &src[h0 + i * stride..h0 + (i + 1) * stride];
    let mut cores = vec![0usize; n];
    for t in tiles {
        let name = t["name"].as_str().unwrap();
        let c: Vec<f64> = (0..4)
            .map(|k| {
                t["core"][k].as_f64().unwrap_or(if k < 2 {
                    f64::NEG_INFINITY
                } else {
                    f64::INFINITY
                })
            })
            .collect();
        // Expected: every Gaussian whose ground point lies within `margin` of the core box (a
        // square ring); in the core where inside the half-open box.
        let mut expect = Vec::new();
        for i in 0..n {
            let r = row(i);
            let g = to_ground(&al, [f32_at(r, ix), f32_at(r, iy), f32_at(r, iz)]);
            let dx = (c[0] - g[0]).max(g[0] - c[2]).max(0.0);
            let dy = (c[1] - g[1]).max(g[1] - c[3]).max(0.0);
            let core = g[0] >= c[0] && g[0] < c[2] && g[1] >= c[1] && g[1] < c[3];
            if dx <= margin && dy <= margin || core {
                expect.push((i as i64, i64::from(core)));
            }
        }
        let dir = p.join("tiles").join(name);
        let got = npy_i64(&dir.join("source.npy"));
        let got: Vec<(i64, i64)> = got.chunks(2).map(|r| (r[0], r[1])).collect();
        assert_eq!(
            got.len(),
            expect.len(),
            "{name}: Gaussians in core + margin"
        );
        assert_eq!(got, expect, "{name}: source indices and core flags");
        assert_eq!(
            t["core_gaussians"].as_u64().unwrap() as usize,
            expect.iter().filter(|e| e.1 == 1).count()
        );
        let out = std::fs::read(dir.join("scene/point_cloud.ply")).unwrap();
        let (h1, m, stride1, props1) = ply_rows(&out);
        assert_eq!((m, stride1, &props1), (expect.len(), stride, &props));
        assert_eq!(out.len(), h1 + m * stride, "{name}: no trailing bytes");
        for (k, (i, core)) in expect.iter().enumerate() {
            assert_eq!(
                &out[h1 + k * stride..h1 + (k + 1) * stride],
                row(*i as usize),
                "{name}: row {k}"
            );
            cores[*i as usize] += *core as usize;
        }
        // Images and SAM lists are links, never copies, but for the views cropped to the
        // window where the tile shows (written cut: as many as the plan says).
        for sub in ["images", "masks"] {
            let written = std::fs::read_dir(dir.join("scene").join(sub))
                .unwrap()
                .filter(|e| {
                    !e.as_ref()
                        .unwrap()
                        .path()
                        .symlink_metadata()
                        .unwrap()
                        .file_type()
                        .is_symlink()
                })
                .count();
            assert_eq!(
                written as u64,
                t["views_cropped"].as_u64().unwrap(),
                "{name}: {sub}"
            );
        }
        assert!(!dir.join("scene/gt").exists() && !dir.join("scene/masks/README.json").exists());
    }
    assert!(
        cores.iter().all(|&c| c == 1),
        "every Gaussian in exactly one core"
    );
    // The padded headers read in an independent PLY reader.
    if common::python_can_import(
        "tile::the_cut_puts_every_gaussian_byte_for_byte_into_the_tiles_within_the_margin_of_it",
        &["plyfile"],
    ) {
        let py = "import sys, plyfile\nfor f in sys.argv[1:]:\n    print(len(plyfile.PlyData.read(f)['vertex'].data))";
        let files: Vec<String> = tiles
            .iter()
            .map(|t| {
                p.join("tiles")
                    .join(t["name"].as_str().unwrap())
                    .join("scene/point_cloud.ply")
                    .display()
                    .to_string()
            })
            .collect();
        let o = Command::new("python3")
            .arg("-c")
            .arg(py)
            .args(&files)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let counts: Vec<u64> = String::from_utf8_lossy(&o.stdout)
            .lines()
            .map(|l| l.parse().unwrap())
            .collect();
        let want: Vec<u64> = tiles
            .iter()
            .map(|t| t["gaussians"].as_u64().unwrap())
            .collect();
        assert_eq!(counts, want);
    }
    let (ok, text) = gs(&[
        "tile",
        "--scene",
        s.to_str().unwrap(),
        "--out",
        p.to_str().unwrap(),
    ]);
    assert!(!ok && text.contains("exists"), "{text}");
}

#[test]
fn a_file_holding_buildings_of_two_tiles_is_cut_and_each_keeps_its_ids_and_attributes() {
    let d = tmp("gml");
    let (s2, gml) = scene_beside(
        scene(),
        &d,
        &["images", "sparse", "point_cloud.ply", "masks", "features"],
    );
    let a = std::fs::read_to_string(&gml[0]).unwrap();
    let b = std::fs::read_to_string(&gml[1]).unwrap();
    let (open, close) = ("<core:cityObjectMember>", "</core:cityObjectMember>");
    let members = &b[b.find(open).unwrap()..b.rfind(close).unwrap() + close.len()];
    let end = a.rfind("</core:CityModel>").unwrap();
    let both = format!("{}{}\n{}", &a[..end], members, &a[end..]);
    std::fs::write(s2.join("citymodel/both.gml"), &both).unwrap();
    let whole = gs4city::citygml::read(&s2.join("citymodel/both.gml")).unwrap();
    let roots: Vec<&gs4city::citygml::CityObject> = whole
        .objects
        .iter()
        .filter(|o| o.parent.is_none())
        .collect();
    assert_eq!(roots.len(), 2);

    let p = d.join("P");
    tile(&s2, &p, "10", "1");
    let plan = plan_of(&p);
    let mut seen = Vec::new();
    for t in plan["tiles"].as_array().unwrap() {
        let owned: Vec<&str> = t["owned"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        assert_eq!(owned.len(), 1, "one building per tile");
        assert!(
            t["neighbours"].as_array().unwrap().is_empty(),
            "1 m margin: no neighbour"
        );
        let f = p
            .join("tiles")
            .join(t["name"].as_str().unwrap())
            .join("scene/citymodel/both.gml");
        assert!(
            !f.symlink_metadata().unwrap().file_type().is_symlink(),
            "a cut, not a link"
        );
        let sub = gs4city::citygml::read(&f).unwrap();
        let sub_roots: Vec<&gs4city::citygml::CityObject> =
            sub.objects.iter().filter(|o| o.parent.is_none()).collect();
        assert_eq!(sub_roots.len(), 1);
        assert_eq!(sub_roots[0].object_id, owned[0]);
        let orig = roots.iter().find(|o| o.object_id == owned[0]).unwrap();
        assert_eq!(sub_roots[0].attributes, orig.attributes);
        // Every object of that building, with its id and attributes, and all its polygons.
        let of_root = |m: &gs4city::citygml::CityModel, id: &str| {
            let mut v: Vec<(String, String)> = m
                .objects
                .iter()
                .filter(|o| {
                    let mut r = *o;
                    while let Some(p) = r.parent {
                        r = &m.objects[p];
                    }
                    r.object_id == id
                })
                .map(|o| (o.object_id.clone(), format!("{:?}", o.attributes)))
                .collect();
            v.sort();
            v
        };
        assert_eq!(of_root(&sub, owned[0]), of_root(&whole, owned[0]));
        seen.push(owned[0].to_string());
    }
    seen.sort();
    let mut want: Vec<String> = roots.iter().map(|o| o.object_id.clone()).collect();
    want.sort();
    assert_eq!(seen, want);
}

/// The instance id of each joined group, from the summary's `joins`: the smallest id of its
/// connected component (a union–find written here).
fn join_roots(summary: &Value) -> HashMap<i64, i64> {
    let mut parent: HashMap<i64, i64> = HashMap::new();
    fn find(p: &HashMap<i64, i64>, mut x: i64) -> i64 {
        while let Some(&y) = p.get(&x) {
            x = y;
        }
        x
    }
    for j in summary["joins"].as_array().unwrap() {
        let (a, b) = (
            find(&parent, j["groups"][0].as_i64().unwrap()),
            find(&parent, j["groups"][1].as_i64().unwrap()),
        );
        if a != b {
            parent.insert(a.max(b), a.min(b));
        }
    }
    let keys: Vec<i64> = parent.keys().copied().collect();
    keys.into_iter().map(|k| (k, find(&parent, k))).collect()
}

/// Labels of a merged run re-derived from the tiles: for a Gaussian in tile t's core, a city
/// label is the merged entity with the tile entity's object id, an image label is
/// `Δ + offset_t + (tile label − tile Δ)` — or, where the summary lists that group as joined,
/// the smallest id joined with it — and the class is the tile's.
fn check_merged_against_tiles(p: &Path, m: &Path, holes: &[&str]) {
    let plan = plan_of(p);
    let summary: Value =
        serde_json::from_str(&std::fs::read_to_string(m.join("summary.json")).unwrap()).unwrap();
    let roots = join_roots(&summary);
    let merged = gs4city::npy::read::<i32>(&m.join("lift/gaussians.npy"))
        .unwrap()
        .1;
    let ments = gs4city::semantics::read(&m.join("citymodel/semantics.json")).unwrap();
    let delta = summary["delta"].as_i64().unwrap();
    let n = plan["gaussians"].as_u64().unwrap() as usize;
    assert_eq!(merged.len(), 2 * n);
    let mut covered = 0;
    for (t, row) in plan["tiles"]
        .as_array()
        .unwrap()
        .iter()
        .zip(summary["tiles"].as_array().unwrap())
    {
        let name = t["name"].as_str().unwrap();
        assert_eq!(row["tile"].as_str().unwrap(), name);
        let dir = p.join("tiles").join(name);
        let src = npy_i64(&dir.join("source.npy"));
        if holes.contains(&name) {
            assert_eq!(row["state"], "failed");
            for r in src.chunks(2).filter(|r| r[1] == 1) {
                assert_eq!(&merged[2 * r[0] as usize..2 * r[0] as usize + 2], &[-1, -1]);
                covered += 1;
            }
            continue;
        }
        let offset = row["image_offset"].as_i64().unwrap();
        let run = dir.join("run");
        let tl = gs4city::npy::read::<i32>(&run.join("lift/gaussians.npy"))
            .unwrap()
            .1;
        let tents = gs4city::semantics::read(&run.join("citymodel/semantics.json")).unwrap();
        let tdelta: Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("fuse/labels.json")).unwrap())
                .unwrap();
        let tdelta = tdelta["delta"].as_i64().unwrap();
        for (r, g) in src.chunks(2).zip(tl.chunks(2)) {
            if r[1] == 0 {
                continue;
            }
            covered += 1;
            let i = r[0] as usize;
            let (ml, mc) = (merged[2 * i], merged[2 * i + 1]);
            assert_eq!(mc, g[1], "{name}: class of Gaussian {i}");
            let l = i64::from(g[0]);
            if l < 0 {
                assert_eq!(ml, -1);
            } else if l < tdelta {
                let oid = &tents[l as usize].object_id;
                match ments.iter().find(|e| &e.object_id == oid) {
                    Some(e) => assert_eq!(ml, e.id, "{name}: Gaussian {i} ({oid})"),
                    None => assert_eq!(ml, -1),
                }
            } else {
                let id = delta + offset + (l - tdelta);
                assert_eq!(
                    i64::from(ml),
                    roots.get(&id).copied().unwrap_or(id),
                    "{name}: Gaussian {i}"
                );
            }
        }
    }
    assert_eq!(covered, n, "every Gaussian is in one core");
}

#[test]
fn run_plan_merges_into_one_queryable_run_that_agrees_with_the_untiled_run() {
    let s = scene();
    let d = tmp("merge");
    let p = d.join("P");
    tile(s, &p, "10", "4");
    let (ok, text) = gs(&["run-plan", p.to_str().unwrap(), "--jobs", "2"]);
    assert!(ok, "{text}");
    let m = p.join("merged");
    check_merged_against_tiles(&p, &m, &[]);
    // The merge predicts the test views with the lists the tiles' runs used (the default
    // preset's, docs/quality.md), not the cache's own defaults (ε 0.05, t_stop 0.02, 1/255).
    let cached: Value =
        serde_json::from_str(&std::fs::read_to_string(m.join("render/summary.json")).unwrap())
            .unwrap();
    let o = |k: &str| cached["options"][k].as_f64().unwrap() as f32;
    assert_eq!(
        (o("epsilon"), o("t_stop"), o("alpha_min")),
        (0.1, 0.2, 1.0 / 32.0)
    );
    let summary: Value =
        serde_json::from_str(&std::fs::read_to_string(m.join("summary.json")).unwrap()).unwrap();
    for t in summary["tiles"].as_array().unwrap() {
        assert_eq!(t["state"], "merged");
        assert!(t["peak_rss_mb"].as_f64().unwrap() > 10.0);
        assert!(t["disk_bytes"].as_u64().unwrap() > 1_000_000);
        let st: Value = serde_json::from_str(
            &std::fs::read_to_string(
                p.join("tiles")
                    .join(t["tile"].as_str().unwrap())
                    .join("status.json"),
            )
            .unwrap(),
        )
        .unwrap();
        assert_eq!(st["cache_removed"], true);
        let tdir = p.join("tiles").join(t["tile"].as_str().unwrap());
        assert!(!tdir.join("run/render").exists());
        // The per-view maps the merge does not read are gone, what it reads is kept, and the
        // status's sizes are the folder's (summed here by walking it).
        for gone in ["raycast", "masks", "associate", "openings/raycast"] {
            assert!(!tdir.join("run").join(gone).exists(), "{gone}");
        }
        for kept in [
            "fuse/labels.json",
            "lift/gaussians.npy",
            "citymodel/semantics.json",
        ] {
            assert!(tdir.join("run").join(kept).is_file(), "{kept}");
        }
        fn walk(d: &Path) -> u64 {
            std::fs::read_dir(d)
                .unwrap()
                .flatten()
                .map(|e| {
                    let m = e.path().symlink_metadata().unwrap();
                    if m.is_dir() { walk(&e.path()) } else { m.len() }
                })
                .sum()
        }
        // status.json is written after the measure and the job's log.txt may grow by its last
        // lines after it.
        let kept = walk(&tdir) - tdir.join("status.json").metadata().unwrap().len();
        let measured = st["kept_bytes"].as_u64().unwrap();
        assert!(
            measured <= kept && kept - measured < 65_536,
            "{measured} vs {kept}"
        );
        assert!(st["pruned_bytes"].as_u64().unwrap() > 1_000_000, "{st}");
        assert!(
            st["kept_bytes"].as_u64().unwrap() + st["pruned_bytes"].as_u64().unwrap()
                <= st["disk_bytes"].as_u64().unwrap()
        );
    }
    // The untiled run of the same scene: same test views, nearly the same classes.
    let b = assert_agrees_with_untiled(&m);
    // query --run M: the selection's Gaussians are those whose merged label it lists.
    let q = d.join("Q");
    let (ok, text) = gs(&[
        "query",
        "--run",
        m.to_str().unwrap(),
        "--class",
        "Window",
        "--out",
        q.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let sel: Value =
        serde_json::from_str(&std::fs::read_to_string(q.join("selection.json")).unwrap()).unwrap();
    let labels: std::collections::HashSet<i64> = sel["labels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_i64().unwrap())
        .collect();
    let want = b
        .chunks(2)
        .filter(|g| labels.contains(&i64::from(g[0])))
        .count();
    assert!(want > 0);
    assert_eq!(sel["gaussians"].as_u64().unwrap() as usize, want);
    assert!(q.join("semantic.sqlite").is_file());
}

/// `tile --crop-below`: views that glimpse a tile run cropped to the window where it shows, and
/// the merged city still agrees with the untiled run of the same scene (its classes and its
/// test views' fine mIoU), as the whole-view plan does above.
#[test]
fn a_plan_with_cropped_views_runs_merges_and_agrees_with_the_untiled_run() {
    let s = scene();
    let d = tmp("crop-run");
    let p = d.join("P");
    let (ok, text) = gs(&[
        "tile",
        "--scene",
        s.to_str().unwrap(),
        "--size",
        "10",
        "--margin",
        "4",
        "--crop-below",
        "0.75",
        "--out",
        p.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let cropped: u64 = plan_of(&p)["tiles"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["views_cropped"].as_u64().unwrap())
        .sum();
    assert!(
        cropped > 0,
        "no view was cropped: the test would not test the crop"
    );
    let (ok, text) = gs(&["run-plan", p.to_str().unwrap(), "--jobs", "2"]);
    assert!(ok, "{text}");
    let m = p.join("merged");
    check_merged_against_tiles(&p, &m, &[]);
    assert_agrees_with_untiled(&m);
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_missing_or_failed_tile_is_named_and_a_partial_city_needs_allow_missing() {
    let s = scene();
    let d = tmp("bad");
    let p = d.join("P");
    tile(s, &p, "10", "4");
    let ps = p.to_str().unwrap();
    // A missing tile folder.
    let gone = p.join("tiles/t000_001");
    std::fs::rename(&gone, d.join("aside")).unwrap();
    let (ok, text) = gs(&["run-plan", ps, "--tile", "1"]);
    assert!(
        !ok && text.contains("t000_001") && text.contains("missing"),
        "{text}"
    );
    let (ok, text) = gs(&["merge", ps, "--out", d.join("M").to_str().unwrap()]);
    assert!(
        !ok && text.contains("t000_001") && text.contains("missing"),
        "{text}"
    );
    assert!(!d.join("M").exists());
    std::fs::rename(d.join("aside"), &gone).unwrap();
    // A tile whose run fails: its PLY truncated.
    let ply = p.join("tiles/t000_000/scene/point_cloud.ply");
    let bytes = std::fs::read(&ply).unwrap();
    std::fs::write(&ply, &bytes[..bytes.len() / 2]).unwrap();
    let (ok, text) = gs(&["run-plan", ps, "--jobs", "2"]);
    assert!(
        !ok && text.contains("t000_000") && text.contains("failed"),
        "{text}"
    );
    let st: Value = serde_json::from_str(
        &std::fs::read_to_string(p.join("tiles/t000_000/status.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(st["ok"], false);
    assert!(
        st["error"].as_str().unwrap().contains("point_cloud.ply"),
        "{st}"
    );
    let m = d.join("M");
    let (ok, text) = gs(&["merge", ps, "--out", m.to_str().unwrap()]);
    assert!(
        !ok && text.contains("t000_000 failed") && text.contains("--allow-missing"),
        "{text}"
    );
    let (ok, text) = gs(&[
        "merge",
        ps,
        "--out",
        m.to_str().unwrap(),
        "--allow-missing",
        "--no-test-views",
    ]);
    assert!(ok, "{text}");
    assert!(text.contains("HOLE: tile t000_000 failed"), "{text}");
    let summary: Value =
        serde_json::from_str(&std::fs::read_to_string(m.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["holes"].as_array().unwrap().len(), 1);
    let core0 = plan_of(&p)["tiles"][0]["core_gaussians"].as_u64().unwrap();
    assert_eq!(summary["in_holes"].as_u64().unwrap(), core0);
    check_merged_against_tiles(&p, &m, &["t000_000"]);
}

/// Needs root (slurmd and munged run as root here): for another user it is a counted skip with
/// that reason, also under `GS4CITY_REQUIRE_PY` (`scripts/test.sh`), but not under `CI`, which
/// runs as root.
#[test]
fn the_plans_job_arrays_run_on_a_real_slurm_and_match_run_plan() {
    const TEST: &str = "tile::the_plans_job_arrays_run_on_a_real_slurm_and_match_run_plan";
    if let Some(uid) = common::uid().filter(|&u| u != 0) {
        return common::skip_unless_ci(
            TEST,
            &format!("needs root (slurmd and munged run as root), running as uid {uid}"),
        );
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/slurm_test.sh");
    let o = Command::new("bash")
        .arg(&script)
        .arg(env!("CARGO_BIN_EXE_gs4city"))
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    if o.status.code() == Some(77) {
        common::skip(TEST, text.trim());
        return;
    }
    assert!(o.status.success(), "{text}");
    assert!(text.contains("slurm_test: passed"), "{text}");
}

/// A PLY with bytes after its last row, or an ASCII PLY (the cut copies fixed-size binary rows):
/// `tile` refuses each with a line naming the PLY, and leaves no plan behind.
#[test]
fn a_ply_with_trailing_bytes_or_in_ascii_is_refused_naming_it() {
    let src = scene();
    let ply = std::fs::read(src.join("point_cloud.ply")).unwrap();
    let end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let header = String::from_utf8(ply[..end].to_vec()).unwrap();
    // An ASCII PLY of the same element (the first row only, the count set to 1).
    let names: Vec<&str> = header
        .lines()
        .filter_map(|l| l.strip_prefix("property float "))
        .collect();
    let count_line = header
        .lines()
        .find(|l| l.starts_with("element vertex"))
        .unwrap();
    let mut ascii = header
        .replace("binary_little_endian", "ascii")
        .replace(count_line, "element vertex 1");
    let row: Vec<String> = (0..names.len())
        .map(|k| {
            let b = &ply[end + 4 * k..end + 4 * k + 4];
            f32::from_le_bytes([b[0], b[1], b[2], b[3]]).to_string()
        })
        .collect();
    ascii.push_str(&row.join(" "));
    ascii.push('\n');
    let mut trailing = ply.clone();
    trailing.extend_from_slice(b"\x00\x01\x02");
    for (name, bytes, why) in [
        ("trailing", trailing, "more data than the header declares"),
        ("ascii", ascii.into_bytes(), "ASCII PLY"),
    ] {
        let d = tmp(&format!("bad-ply-{name}"));
        let s = d.join("scene");
        link_except(src, &s, "point_cloud.ply");
        std::fs::write(s.join("point_cloud.ply"), bytes).unwrap();
        let p = d.join("plan");
        let (ok, text) = gs(&[
            "tile",
            "--scene",
            s.to_str().unwrap(),
            "--size",
            "60",
            "--margin",
            "10",
            "--out",
            p.to_str().unwrap(),
        ]);
        assert!(!ok, "{name}: {text}");
        assert!(
            text.contains("point_cloud.ply") && text.contains(why),
            "{name}: {text}"
        );
        assert!(!p.join("plan.json").exists(), "{name}: a plan was left");
    }
}

/// Folder `dst` (made) with a symbolic link to every entry of `src` but `except`.
fn link_except(src: &Path, dst: &Path, except: &str) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        if e.file_name() != except {
            std::os::unix::fs::symlink(e.path(), dst.join(e.file_name())).unwrap();
        }
    }
}

/// The training views in tile `name` of plan `p` (its scene's linked images).
fn tile_views(p: &Path, name: &str) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(p.join("tiles").join(name).join("scene/images"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// The view rule on the SIMULATED small scene replicated 2×2 (`scripts/replicate_scene.py`:
/// copies 72.3 m apart, views renamed `r<k>_…`, ids suffixed `_r<k>`), 72 m tiles so that each
/// tile owns one copy. The expectations come from the names alone: a copy's own views look at
/// it from its orbit and streets, so they join its tile under every rule; the orbit cameras
/// also see the neighbouring copies, so with `--min-share 0` views join several tiles and the
/// share rule must drop some of those; with `--min-share 1 --min-views 3` each tile keeps
/// exactly its 3 best views, which are its own copy's.
#[test]
fn a_view_joins_the_tiles_that_take_a_share_of_its_screen_and_each_tile_keeps_its_best() {
    let test = "tile view share rule";
    if !common::python_can_import(test, &["numpy"]) {
        return;
    }
    let d = tmp("share");
    let x4 = d.join("x4");
    let o = Command::new("python3")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/scripts/replicate_scene.py"
        ))
        .args([scene().to_str().unwrap(), x4.to_str().unwrap(), "4"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let plan = |share: &str, min_views: &str| -> (PathBuf, Value) {
        let p = d.join(format!("p{share}_{min_views}"));
        let (ok, text) = gs(&[
            "tile",
            "--scene",
            x4.to_str().unwrap(),
            "--size",
            "72",
            "--margin",
            "10",
            "--min-share",
            share,
            "--min-views",
            min_views,
            // The replica declares no test views: 3DGS's split, as the expectations assume.
            "--test-every",
            "8",
            "--out",
            p.to_str().unwrap(),
        ]);
        assert!(ok, "{text}");
        let v = plan_of(&p);
        (p, v)
    };
    // Per tile: its copy's prefix (from the ids it owns) and its views.
    let views_of = |p: &Path, v: &Value| -> Vec<(String, Vec<String>)> {
        let tiles = v["tiles"].as_array().unwrap();
        assert_eq!(tiles.len(), 4, "72 m tiles over 4 copies");
        tiles
            .iter()
            .map(|t| {
                let owned: Vec<&str> = t["owned"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|o| o.as_str().unwrap())
                    .collect();
                let k = owned[0].rsplit_once("_r").unwrap().1;
                assert!(
                    owned.iter().all(|o| o.ends_with(&format!("_r{k}"))),
                    "{owned:?}"
                );
                let name = t["name"].as_str().unwrap();
                let views = tile_views(p, name);
                assert_eq!(views.len() as u64, t["views"].as_u64().unwrap(), "{name}");
                (format!("r{k}_"), views)
            })
            .collect()
    };
    let (p0, v0) = plan("0", "0");
    let test_views: Vec<&str> = v0["test_views"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_str().unwrap())
        .collect();
    let all_train: Vec<String> = std::fs::read_dir(x4.join("images"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| !test_views.contains(&n.as_str()))
        .collect();
    let own = |prefix: &str| -> Vec<String> {
        let mut v: Vec<String> = all_train
            .iter()
            .filter(|n| n.starts_with(prefix))
            .cloned()
            .collect();
        v.sort();
        v
    };
    let every = views_of(&p0, &v0);
    let (p1, v1) = plan("0.1", "8");
    let shared = views_of(&p1, &v1);
    let total = |t: &[(String, Vec<String>)]| t.iter().map(|(_, v)| v.len()).sum::<usize>();
    for ((prefix, all), (_, kept)) in every.iter().zip(&shared) {
        let mine = own(prefix);
        assert!(!mine.is_empty());
        for m in &mine {
            assert!(
                all.contains(m),
                "{m} missing from its copy's tile (share 0)"
            );
            assert!(
                kept.contains(m),
                "{m} missing from its copy's tile (share 0.1)"
            );
        }
        assert!(
            kept.iter().all(|k| all.contains(k)),
            "the rule only removes"
        );
    }
    assert!(
        total(&every) > all_train.len(),
        "with share 0 the orbit views join neighbouring copies' tiles too ({} of {})",
        total(&every),
        all_train.len()
    );
    assert!(
        total(&shared) < total(&every),
        "share 0.1 drops glimpses: {} vs {}",
        total(&shared),
        total(&every)
    );
    let glimpsing: u64 = v1["tiles"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["views_glimpsing"].as_u64().unwrap())
        .sum();
    assert_eq!(glimpsing as usize, total(&every) - total(&shared));
    let (p3, v3) = plan("1", "3");
    for (prefix, kept) in views_of(&p3, &v3) {
        assert_eq!(kept.len(), 3, "{prefix}: min-views 3 with share 1");
        assert!(
            kept.iter().all(|k| k.starts_with(&prefix)),
            "{prefix}: the best views are the copy's own: {kept:?}"
        );
    }
    // `--crop-below 0.75`: the same views join the same tiles, and a cropped view's image is
    // the scene image's window at the corner its camera's principal point moved by (read by
    // OpenCV here, written by the `png` crate in the plan).
    let pc = d.join("pcrop");
    let (ok, text) = gs(&[
        "tile",
        "--scene",
        x4.to_str().unwrap(),
        "--size",
        "72",
        "--margin",
        "10",
        "--crop-below",
        "0.75",
        "--test-every",
        "8",
        "--out",
        pc.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let vc = plan_of(&pc);
    let cropped = views_of(&pc, &vc);
    assert_eq!(
        cropped.iter().map(|(_, v)| v.clone()).collect::<Vec<_>>(),
        every.iter().map(|(_, v)| v.clone()).collect::<Vec<_>>()
    );
    let src = gs4city::colmap::read_model(&x4.join("sparse/0")).unwrap();
    let mut seen = 0;
    for t in vc["tiles"].as_array().unwrap() {
        let tdir = pc
            .join("tiles")
            .join(t["name"].as_str().unwrap())
            .join("scene");
        for v in gs4city::colmap::read_model(&tdir.join("sparse/0")).unwrap() {
            let img = tdir.join("images").join(&v.name);
            if img.symlink_metadata().unwrap().file_type().is_symlink() {
                continue;
            }
            seen += 1;
            let s = src.iter().find(|s| s.name == v.name).unwrap();
            let (k, ks) = (&v.camera.intrinsics, &s.camera.intrinsics);
            let (x0, y0) = (ks.cx - k.cx, ks.cy - k.cy);
            assert!(x0 >= 0.0 && y0 >= 0.0 && x0.fract() == 0.0 && y0.fract() == 0.0);
            assert_eq!((k.fx, k.fy), (ks.fx, ks.fy));
            let (x0, y0) = (x0 as usize, y0 as usize);
            let a = gs4city::imageio::read_rgb(&img).unwrap();
            let b = gs4city::imageio::read_rgb(&x4.join("images").join(&s.name)).unwrap();
            assert_eq!(a.dim(), (k.height as usize, k.width as usize, 3));
            let want = b.slice(ndarray::s![
                y0..y0 + k.height as usize,
                x0..x0 + k.width as usize,
                ..
            ]);
            assert_eq!(a.view(), want, "{}", v.name);
        }
    }
    let n_cropped: u64 = vc["tiles"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["views_cropped"].as_u64().unwrap())
        .sum();
    assert!(
        seen > 0 && seen as u64 == n_cropped,
        "{seen} vs {n_cropped}"
    );
    let _ = std::fs::remove_dir_all(&d);
}

/// One building 700 km from the rest (another CRS, a coordinate slip): the plan is refused in
/// one line that names it and its file, before any tile is allocated or made (the grid over
/// its footprints would hold 21.8 M tiles of 150 m).
#[test]
fn a_footprint_far_from_the_others_is_named_instead_of_planning_millions_of_tiles() {
    let src = scene();
    let d = tmp("far-footprint");
    let s = d.join("scene");
    link_except(src, &s, "citymodel");
    link_except(&src.join("citymodel"), &s.join("citymodel"), "");
    let al: Value =
        serde_json::from_slice(&std::fs::read(src.join("citymodel/alignment.json")).unwrap())
            .unwrap();
    let o: Vec<f64> = (0..3).map(|k| al["origin"][k].as_f64().unwrap()).collect();
    let (x, y, z) = (o[0] + 700_000.0, o[1] + 700_000.0, o[2]);
    let ring: Vec<[f64; 3]> = [(0.0, 0.0), (10.0, 0.0), (10.0, 8.0), (0.0, 8.0), (0.0, 0.0)]
        .iter()
        .map(|(dx, dz)| [x + dx, y, z + dz])
        .collect();
    let gml = crate::common::one_wall_citygml("FAR_AWAY", "FAR_POLY", &ring);
    std::fs::write(s.join("citymodel/zz_far.gml"), gml).unwrap();
    let p = d.join("plan");
    let (ok, text) = gs(&[
        "tile",
        "--scene",
        s.to_str().unwrap(),
        "--out",
        p.to_str().unwrap(),
    ]);
    assert!(!ok, "{text}");
    assert!(
        text.contains("FAR_AWAY") && text.contains("zz_far.gml") && text.contains("100000"),
        "{text}"
    );
    assert_eq!(text.trim().lines().count(), 1, "{text}");
    assert!(!p.exists() && !d.join("plan.partial").exists());
}

/// A JSON file.
fn json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// The classes of the image labels of a `labels.json`, by `id(label id)`.
fn image_classes(table: &Value, id: impl Fn(i64) -> i64) -> HashMap<i64, i64> {
    table["labels"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|l| l["source"] == "image")
        .map(|l| (id(l["id"].as_i64().unwrap()), l["class"].as_i64().unwrap()))
        .collect()
}

/// A tile's outputs as the join test reads them: per row of `source.npy` the Gaussian, whether
/// it is in the tile's core, and its image label as a merged id before any join
/// (`Δ + offset + tile label − tile Δ`, −1 for a city label or none); the classes of its image
/// labels by that id.
struct TileRows {
    tile: i64,
    rows: Vec<(usize, bool, i64)>,
    class: HashMap<i64, i64>,
}

fn tile_rows(p: &Path, summary: &Value) -> Vec<TileRows> {
    let plan = plan_of(p);
    let delta = summary["delta"].as_i64().unwrap();
    let mut out = Vec::new();
    for (t, (tp, row)) in plan["tiles"]
        .as_array()
        .unwrap()
        .iter()
        .zip(summary["tiles"].as_array().unwrap())
        .enumerate()
    {
        assert_eq!(row["state"], "merged");
        let dir = p.join("tiles").join(tp["name"].as_str().unwrap());
        let offset = row["image_offset"].as_i64().unwrap();
        let src = npy_i64(&dir.join("source.npy"));
        let tl = gs4city::npy::read::<i32>(&dir.join("run/lift/gaussians.npy"))
            .unwrap()
            .1;
        let table: Value = json(&dir.join("run/fuse/labels.json"));
        let tdelta = table["delta"].as_i64().unwrap();
        let merged = |l: i64| delta + offset + l - tdelta;
        let class = image_classes(&table, merged);
        let rows = src
            .chunks(2)
            .zip(tl.chunks(2))
            .map(|(r, g)| {
                let l = i64::from(g[0]);
                (
                    r[0] as usize,
                    r[1] == 1,
                    if l >= tdelta { merged(l) } else { -1 },
                )
            })
            .collect();
        out.push(TileRows {
            tile: t as i64,
            rows,
            class,
        });
    }
    out
}

/// The join rule of docs/tile.md re-derived by brute force: for every pair of image groups of
/// two tiles, the Gaussians both tiles hold that one labels with the first and the other with
/// the second, against each group's Gaussians that the other tile holds; joined when the classes
/// agree and the common Gaussians are at least `f` of both. Sorted (groups, tiles, class,
/// common, each group's Gaussians in the shared region).
fn joins_by_rule(tiles: &[TileRows], f: f64) -> Vec<Value> {
    let mut held: HashMap<usize, Vec<(i64, i64)>> = HashMap::new();
    for t in tiles {
        for &(i, _, l) in &t.rows {
            held.entry(i).or_default().push((t.tile, l));
        }
    }
    let mut common: HashMap<(i64, i64), ([i64; 2], u64)> = HashMap::new();
    let mut in_shared: HashMap<(i64, i64), u64> = HashMap::new();
    for v in held.values() {
        for a in v {
            for b in v {
                if a.0 >= b.0 {
                    continue;
                }
                if a.1 >= 0 {
                    *in_shared.entry((a.1, b.0)).or_default() += 1;
                }
                if b.1 >= 0 {
                    *in_shared.entry((b.1, a.0)).or_default() += 1;
                }
                if a.1 >= 0 && b.1 >= 0 {
                    common.entry((a.1, b.1)).or_insert(([a.0, b.0], 0)).1 += 1;
                }
            }
        }
    }
    let class: HashMap<i64, i64> = tiles.iter().flat_map(|t| t.class.clone()).collect();
    let mut out: Vec<Value> = common
        .iter()
        .filter_map(|(&(a, b), &(tt, n))| {
            let (sa, sb) = (in_shared[&(a, tt[1])], in_shared[&(b, tt[0])]);
            (class[&a] == class[&b] && n as f64 >= f * sa as f64 && n as f64 >= f * sb as f64).then(
                || {
                    serde_json::json!({"tiles": tt, "groups": [a, b], "class": class[&a],
                        "shared": n, "in_shared": [sa, sb]})
                },
            )
        })
        .collect();
    out.sort_by_key(|j| (j["groups"][0].as_i64(), j["groups"][1].as_i64()));
    out
}

/// Per class (tree 6, person 7, car 8): the labels of that class that hold at least a fifth of
/// the Gaussians of a SIMULATED object of that class (truth, `gt/gaussians.npy`: class,
/// instance), so a stray fragment is not counted as an instance; and the labels of that class
/// any Gaussian carries.
fn instances(labels: &[i64], class: &HashMap<i64, i64>, truth: &[i32]) -> [(usize, usize); 3] {
    let mut objects: HashMap<i32, (i32, Vec<usize>)> = HashMap::new();
    for (i, t) in truth.chunks(5).enumerate() {
        if t[1] >= 1_000_010 {
            objects.entry(t[1]).or_insert((t[0], Vec::new())).1.push(i);
        }
    }
    let mut out = [(0, 0); 3];
    for (k, c) in [6i64, 7, 8].into_iter().enumerate() {
        let mut held: HashSet<i64> = HashSet::new();
        for (oc, members) in objects.values() {
            if i64::from(*oc) != c {
                continue;
            }
            let mut per: HashMap<i64, usize> = HashMap::new();
            for &i in members {
                *per.entry(labels[i]).or_default() += 1;
            }
            held.extend(
                per.into_iter()
                    .filter(|&(l, n)| class.get(&l) == Some(&c) && 5 * n >= members.len())
                    .map(|(l, _)| l),
            );
        }
        let any: HashSet<i64> = labels
            .iter()
            .filter(|l| class.get(l) == Some(&c))
            .copied()
            .collect();
        out[k] = (held.len(), any.len());
    }
    out
}

/// A run's per-Gaussian labels and the classes of its image labels.
fn run_labels(r: &Path) -> (Vec<i64>, HashMap<i64, i64>) {
    let g = gs4city::npy::read::<i32>(&r.join("lift/gaussians.npy"))
        .unwrap()
        .1;
    let table: Value = json(&r.join("fuse/labels.json"));
    let class = image_classes(&table, |l| l);
    (g.chunks(2).map(|x| i64::from(x[0])).collect(), class)
}

/// A SIMULATED `small` scene with 8 trees, 10 cars and 16 persons (seed 3): 9 m tiles make three
/// tiles whose two core borders cut trees, cars and a person. Untiled and tiled (`tile`,
/// `run-plan`, merge), the merged run has the untiled run's instances of each class — counted
/// against the simulation's objects, by the labels that hold a fifth of one — and fewer labels
/// of each class than the tiles' groups before the join; the summary's joins are those of the
/// rule re-derived here by brute force, and every merged label follows from them.
#[test]
fn objects_cut_by_tile_borders_are_one_instance_as_in_the_untiled_run() {
    let d = tmp("join");
    let s = d.join("scene");
    let cfg = d.join("objects.toml");
    std::fs::write(&cfg, "[objects]\ntrees = 8\ncars = 10\npersons = 16\n").unwrap();
    let (ok, text) = gs(&[
        "synth",
        "--preset",
        "small",
        "--config",
        cfg.to_str().unwrap(),
        "--seed",
        "3",
        "--out",
        s.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let r = d.join("R");
    let (ok, text) = gs(&[
        "run",
        "--scene",
        s.to_str().unwrap(),
        "--out",
        r.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let p = d.join("P");
    tile(&s, &p, "9", "4");
    let (ok, text) = gs(&["run-plan", p.to_str().unwrap(), "--jobs", "2"]);
    assert!(ok, "{text}");
    let m = p.join("merged");
    let summary: Value = json(&m.join("summary.json"));
    let truth = gs4city::npy::read::<i32>(&s.join("gt/gaussians.npy"))
        .unwrap()
        .1;
    let tiles = tile_rows(&p, &summary);
    assert_eq!(tiles.len(), 3);

    // The borders cut objects of each class: their Gaussians lie in two tiles' cores.
    let mut cores: HashMap<i32, HashSet<i64>> = HashMap::new();
    for t in &tiles {
        for &(i, core, _) in &t.rows {
            if core && truth[5 * i + 1] >= 1_000_010 {
                cores.entry(truth[5 * i + 1]).or_default().insert(t.tile);
            }
        }
    }
    for c in [6, 7, 8] {
        let cut = cores
            .iter()
            .filter(|(o, ts)| ts.len() > 1 && truth.chunks(5).any(|t| t[1] == **o && t[0] == c))
            .count();
        assert!(cut >= 1, "class {c}: no object cut by a border");
    }

    // Instances: merged = untiled; before the join, the tiles' groups as they were.
    let n = summary["gaussians"].as_u64().unwrap() as usize;
    let mut before = vec![-1i64; n];
    let mut before_class = HashMap::new();
    for t in &tiles {
        before_class.extend(t.class.clone());
        for &(i, core, l) in &t.rows {
            if core {
                before[i] = l;
            }
        }
    }
    let (ml, mc) = run_labels(&m);
    let (rl, rc) = run_labels(&r);
    let merged = instances(&ml, &mc, &truth);
    let untiled = instances(&rl, &rc, &truth);
    let unjoined = instances(&before, &before_class, &truth);
    for (k, name) in ["tree", "person", "car"].iter().enumerate() {
        assert_eq!(
            merged[k].0, untiled[k].0,
            "{name}: instances merged {:?}, untiled {:?}, before the join {:?}",
            merged, untiled, unjoined
        );
    }
    for (k, name) in ["tree", "person", "car"].iter().enumerate() {
        assert!(
            merged[k].1 < unjoined[k].1,
            "{name}: labels merged {:?}, before the join {:?}",
            merged,
            unjoined
        );
    }
    assert!(
        (0..3).any(|k| unjoined[k].0 > untiled[k].0),
        "without the join an object cut by a border counts twice: {unjoined:?} vs {untiled:?}"
    );

    // The joins are the rule's, and every merged label follows from them.
    let f = summary["join_fraction"].as_f64().unwrap();
    assert!(f > 0.0 && f <= 1.0, "{f}");
    let want = joins_by_rule(&tiles, f);
    assert_eq!(summary["joins"].as_array().unwrap(), &want);
    check_merged_against_tiles(&p, &m, &[]);
    let roots = join_roots(&summary);
    assert!(!roots.is_empty());
    assert_eq!(
        summary["joined_groups"].as_u64().unwrap() as usize,
        roots.len()
    );
    assert!(
        text.contains(&format!(
            "objects cut by tile borders: {} groups joined",
            roots.len()
        )),
        "{text}"
    );

    // A query sees the joined instances: category=car selects the merged table's car labels,
    // fewer than the tiles' car groups.
    let q = d.join("Q");
    let (ok, text) = gs(&[
        "query",
        "--run",
        m.to_str().unwrap(),
        "--where",
        "category=car",
        "--views",
        "none",
        "--no-sqlite",
        "--out",
        q.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let sel: Value = json(&q.join("selection.json"));
    let got: HashSet<i64> = sel["labels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_i64().unwrap())
        .collect();
    let cars: HashSet<i64> = before_class
        .iter()
        .filter(|&(_, &c)| c == 8)
        .map(|(&l, _)| roots.get(&l).copied().unwrap_or(l))
        .collect();
    assert_eq!(got, cars);
    assert!(cars.len() < before_class.values().filter(|&&c| c == 8).count());

    // The same merge on one thread: the same ids.
    let m1 = d.join("M1");
    let o = bin()
        .args(["-q", "merge", p.to_str().unwrap(), "--out"])
        .arg(&m1)
        .arg("--no-test-views")
        .env("RAYON_NUM_THREADS", "1")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in ["lift/gaussians.npy", "fuse/labels.json"] {
        assert!(
            std::fs::read(m.join(f)).unwrap() == std::fs::read(m1.join(f)).unwrap(),
            "{f} differs on one thread"
        );
    }
}
