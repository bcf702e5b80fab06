//! `gs4city query` on a hand-built run whose every answer is known: 13 city entities in three
//! buildings (one with a BuildingPart of its own height, one CityGML 3.0 WindowSurface), three
//! image labels (tree, person, "other"), 16 Gaussians with hand-assigned labels, a 4×2-pixel
//! contributions cache with hand-written lists, per-label features and prompts on orthogonal
//! axes. Expected selections, masks, scores, exports and table rows are worked out by hand in
//! the comments, not by the code under test.
use std::path::{Path, PathBuf};
use std::process::Command;

use gs4city::cache::Contributions;
use gs4city::cache::{CacheOptions, CacheSummary, CachedView, ViewContrib};
use gs4city::citygml::Level;
use gs4city::labels::{Label, LabelTable, Source};
use gs4city::layout::Summary;
use gs4city::query::{self, QueryOptions, Request, Views};
use gs4city::sam::Prompts;
use gs4city::selection::{self, MaskRule, SemanticRun, TextOptions};
use gs4city::semantics::Entity;
use gs4city::splat::{Gaussians, PlyEncoding};
use gs4city::{fsutil, npy, splat};
use serde_json::{Value, json};

const N: usize = 16;
const D: usize = 8;

fn entity(
    id: i32,
    oid: &str,
    class: &str,
    level: Level,
    parent: Option<i32>,
    building: i32,
    attrs: Value,
) -> Entity {
    Entity {
        id,
        object_id: oid.into(),
        class: gs4city::semantics::Class::from_local_name(class).unwrap(),
        level,
        parent,
        building,
        source: "hand.gml".into(),
        lod: Some(3),
        attributes: serde_json::from_value(attrs).unwrap(),
    }
}

fn entities() -> Vec<Entity> {
    use Level::*;
    vec![
        entity(
            0,
            "B1",
            "Building",
            Feature,
            None,
            0,
            json!({"measuredHeight": 12.5, "measuredHeight.uom": "m", "function": "1000", "creationDate": "2020-06-24"}),
        ),
        entity(1, "W1", "WallSurface", Surface, Some(0), 0, json!({})),
        entity(
            2,
            "Win1",
            "Window",
            Part,
            Some(1),
            0,
            json!({"paneMaterialClass": ["glass", "metal"]}),
        ),
        entity(3, "Win2", "Window", Part, Some(1), 0, json!({})),
        entity(4, "R1", "RoofSurface", Surface, Some(0), 0, json!({})),
        entity(
            5,
            "B2",
            "Building",
            Feature,
            None,
            5,
            json!({"measuredHeight": 20, "measuredHeight.uom": "m", "function": "2000", "creationDate": "2020-09-30"}),
        ),
        entity(6, "W2", "WallSurface", Surface, Some(5), 5, json!({})),
        entity(7, "D1", "Door", Part, Some(6), 5, json!({})),
        entity(
            8,
            "BP",
            "BuildingPart",
            Feature,
            Some(5),
            5,
            json!({"measuredHeight": 800, "measuredHeight.uom": "cm"}),
        ),
        entity(9, "R2", "RoofSurface", Surface, Some(8), 5, json!({})),
        entity(
            10,
            "B3",
            "Building",
            Feature,
            None,
            10,
            json!({"function": "1000"}),
        ),
        entity(11, "W3", "WallSurface", Surface, Some(10), 10, json!({})),
        entity(12, "WS", "WindowSurface", Part, Some(11), 10, json!({})),
    ]
}

/// Entity classes (DESIGN.md ids) by hand: B1 wall 0, W1 0, windows 2, R1 roof 1, B2 0, W2 0,
/// D1 door 3, BP 0, R2 1, B3 0, W3 0, WS 2.
const CITY_CLASS: [i32; 13] = [0, 0, 2, 2, 1, 0, 0, 3, 0, 1, 0, 0, 2];

fn label_table() -> LabelTable {
    let mut labels: Vec<Label> = (0..13)
        .map(|i| Label {
            id: i,
            source: Source::City,
            entity: Some(i),
            group: None,
            class: CITY_CLASS[i as usize],
            level: Some(entities()[i as usize].level),
        })
        .collect();
    for (g, class) in [(0, 6), (1, 7), (2, 11)] {
        labels.push(Label {
            id: 10_000 + g,
            source: Source::Image,
            entity: None,
            group: Some(g),
            class,
            level: None,
        });
    }
    LabelTable::new(10_000, labels).unwrap()
}

/// Label per Gaussian: g0 g1 Win1, g2 Win2, g3 g4 W1, g5 R1, g6 B1, g7 W2, g8 D1, g9 R2,
/// g10 W3, g11 WS, g12 g13 tree, g14 person, g15 none.
const LABEL: [i32; N] = [
    2, 2, 3, 1, 1, 4, 0, 6, 7, 9, 11, 12, 10_000, 10_000, 10_001, -1,
];

fn class_of(l: i32) -> i32 {
    match l {
        -1 => -1,
        10_000 => 6,
        10_001 => 7,
        10_002 => 11,
        l => CITY_CLASS[l as usize],
    }
}

fn e(i: usize) -> Vec<f32> {
    let mut v = vec![0.0; D];
    v[i] = 1.0;
    v
}

fn mix(a: &[(usize, f32)]) -> Vec<f32> {
    let mut v = vec![0.0; D];
    for &(i, x) in a {
        v[i] = x;
    }
    v
}

/// Prompts on axes: tree e0, person e1, car e2, wall e3, window e4, road e5; the facade is a
/// synonym of the wall (0.95·e3 + 0.3122·e6, cosine 0.95).
fn prompts() -> Prompts {
    Prompts {
        simulated: true,
        dim: D,
        prompts: [
            ("a tree", e(0)),
            ("a person", e(1)),
            ("a car", e(2)),
            ("a wall of a building", e(3)),
            ("a window of a building", e(4)),
            ("a road", e(5)),
            ("a facade of a building", mix(&[(3, 0.95), (6, 0.3122)])),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect(),
        classes: Default::default(),
    }
}

/// Label features (rows ↔ the table): walls e3, windows e4, the tree (e0 + 0.3·e7) (unnormalised
/// on purpose), the person e1, "other" e7; buildings, roofs and the door have none (zero rows).
fn label_features() -> Vec<f32> {
    let mut rows = vec![vec![0.0f32; D]; 16];
    for w in [1, 6, 11] {
        rows[w] = e(3);
    }
    for w in [2, 3, 12] {
        rows[w] = e(4);
    }
    rows[13] = mix(&[(0, 1.0), (7, 0.3)]);
    rows[14] = e(1);
    rows[15] = e(7);
    rows.concat()
}

/// View v0 (a test view) and v1, 4×2 pixels each. v0, per pixel (Gaussian weight):
/// p0 g0 .6, g3 .3 · p1 g3 .5, g0 .4 · p2 g2 .45, g12 .5 · p3 g0 .3, g2 .3, g12 .35 ·
/// p4 empty · p5 g15 .7, g11 .25 · p6 g11 .8 · p7 g14 .9.
fn views() -> [(String, ViewContrib); 2] {
    let make = |lists: Vec<Vec<(u32, f32)>>, alpha: Vec<f32>| {
        let mut offsets = vec![0u64];
        let (mut ids, mut weights) = (vec![], vec![]);
        for l in &lists {
            for &(g, w) in l {
                ids.push(g);
                weights.push(w);
            }
            offsets.push(ids.len() as u64);
        }
        ViewContrib {
            width: 4,
            height: 2,
            k: 16,
            gaussians: N,
            lists: Contributions {
                offsets,
                ids,
                weights,
                residual: vec![0.0; 8],
            },
            alpha,
            depth: vec![1.0; 8],
            median: Vec::new(),
        }
    };
    let v0 = make(
        vec![
            vec![(0, 0.6), (3, 0.3)],
            vec![(3, 0.5), (0, 0.4)],
            vec![(2, 0.45), (12, 0.5)],
            vec![(0, 0.3), (2, 0.3), (12, 0.35)],
            vec![],
            vec![(15, 0.7), (11, 0.25)],
            vec![(11, 0.8)],
            vec![(14, 0.9)],
        ],
        vec![0.9, 0.9, 0.95, 0.95, 0.0, 0.95, 0.8, 0.9],
    );
    // v1: every pixel is the door g8 (0.9) except pixel 5 (x 1, y 1): roof R2 g9 (0.9).
    let mut lists = vec![vec![(8u32, 0.9f32)]; 8];
    lists[5] = vec![(9, 0.9)];
    let v1 = make(lists, vec![0.9; 8]);
    [("v0".into(), v0), ("v1".into(), v1)]
}

fn gaussians() -> Gaussians {
    gaussians_of(&(0..N).collect::<Vec<_>>())
}

/// The fixture's Gaussians `ids` only, in that order, each built from its index by the same
/// formulas as [`gaussians`]: the expected content of an export, made without the export code.
fn gaussians_of(ids: &[usize]) -> Gaussians {
    Gaussians {
        positions: ids.iter().map(|&i| [i as f32, 0.5, -(i as f32)]).collect(),
        normals: None,
        sh_degree: 1,
        f_dc: ids.iter().map(|&i| [0.1 * i as f32, 0.2, 0.3]).collect(),
        f_rest: ids
            .iter()
            .flat_map(|&i| (i * 9..i * 9 + 9).map(|k| k as f32 * 0.01))
            .collect(),
        opacity: ids.iter().map(|&i| i as f32 - 8.0).collect(),
        scale: vec![[-2.0, -2.5, -3.0]; ids.len()],
        rotation: vec![[1.0, 0.0, 0.0, 0.0]; ids.len()],
        extras: vec![],
    }
}

struct Fixture {
    root: PathBuf,
    scene: PathBuf,
    run: PathBuf,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.root);
    }
}

/// Writes the scene and run folders; `fused`: with fuse/labels.json and label features.
fn fixture(name: &str, fused: bool, ply: PlyEncoding) -> Fixture {
    let root =
        crate::common::temp_dir().join(format!("gs4city-query-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let scene = root.join("scene");
    let run = root.join("run");
    for d in ["citymodel", "sparse/0", "features", "images"] {
        std::fs::create_dir_all(scene.join(d)).unwrap();
    }
    std::fs::write(scene.join("citymodel/hand.gml"), "<CityModel/>").unwrap();
    std::fs::write(scene.join("sparse/0/images.txt"), "").unwrap();
    splat::write_ply(&scene.join("point_cloud.ply"), &gaussians(), ply).unwrap();
    gs4city::sam::write_prompts_json(&scene.join("features/prompts.json"), &prompts()).unwrap();
    let img = ndarray::Array3::from_shape_fn((2, 4, 3), |(y, x, c)| (10 * (y * 4 + x) + c) as u8);
    gs4city::imageio::write_png(&scene.join("images/v0.png"), &img).unwrap();
    for d in ["citymodel", "lift", "render"] {
        std::fs::create_dir_all(run.join(d)).unwrap();
    }
    fsutil::write_json(
        &run.join("citymodel/semantics.json"),
        &json!({"entities": entities()}),
    )
    .unwrap();
    // Without fuse/, the run knows city labels only: the image labels' Gaussians are unlabelled.
    let label = |l: i32| if fused || l < 10_000 { l } else { -1 };
    let table: Vec<i32> = LABEL
        .iter()
        .flat_map(|&l| [label(l), class_of(label(l))])
        .collect();
    npy::write(&run.join("lift/gaussians.npy"), &[N, 2], &table).unwrap();
    npy::write(&run.join("lift/v0.class.npy"), &[2, 4], &[0i32; 8]).unwrap();
    let mut cached = vec![];
    for (stem, v) in views() {
        v.write(&run.join(format!("render/{stem}.contrib")))
            .unwrap();
        cached.push(CachedView {
            name: format!("{stem}.png"),
            stem,
            width: 4,
            height: 2,
            entries: v.entries() as u64,
            mean_list: 1.0,
            mean_dropped_share: 0.0,
            coverage: 1.0,
            bytes: v.file_bytes() as u64,
            render_s: 0.0,
        });
    }
    fsutil::write_json(
        &run.join("render/summary.json"),
        &CacheSummary {
            gaussians: N,
            skipped_gaussians: 0,
            options: CacheOptions {
                top_k: 16,
                epsilon: 0.0,
                t_stop: 0.0,
                alpha_min: gs4city::cache::INRIA_ALPHA_MIN,
            },
            median_depth: false,
            views: cached,
            selection: None,
            bytes: 0,
            render_s: 0.0,
            write_s: 0.0,
            total_s: 0.0,
        },
    )
    .unwrap();
    fsutil::write_json(
        &run.join("run.json"),
        &json!({"program": "gs4city", "version": "test", "scene": scene, "options": {}, "stages": {}}),
    )
    .unwrap();
    if fused {
        std::fs::create_dir_all(run.join("fuse")).unwrap();
        label_table().write(&run.join("fuse/labels.json")).unwrap();
        npy::write(
            &run.join("fuse/label_features.npy"),
            &[16, D],
            &label_features(),
        )
        .unwrap();
    }
    Fixture { root, scene, run }
}

fn open(f: &Fixture) -> SemanticRun {
    SemanticRun::open(&f.run, &f.scene, None).unwrap()
}

/// Selected label ids of a `--where` text.
fn labels(sr: &SemanticRun, text: &str) -> Vec<i32> {
    sr.select_text("--where", text, TextOptions::default())
        .unwrap()
        .1
        .labels
}

fn oids(sr: &SemanticRun, ids: &[i32]) -> Vec<String> {
    ids.iter()
        .map(|&i| sr.entities[i as usize].object_id.clone())
        .collect()
}

#[test]
fn structural_and_attribute_selections() {
    let f = fixture("select", true, PlyEncoding::BinaryLittleEndian);
    let sr = open(&f);
    // Class with descendants; 2.0 Window ≡ 3.0 WindowSurface.
    assert_eq!(labels(&sr, "class=Window"), vec![2, 3, 12]);
    assert_eq!(labels(&sr, "class=con:WindowSurface"), vec![2, 3, 12]);
    assert_eq!(
        labels(&sr, "class=WallSurface"),
        vec![1, 2, 3, 6, 7, 11, 12]
    );
    assert_eq!(
        labels(&sr, "class=WallSurface and level=surface"),
        vec![1, 6, 11]
    );
    assert_eq!(labels(&sr, "class=Building"), (0..13).collect::<Vec<_>>());
    assert_eq!(
        labels(&sr, "class=Building and level=feature"),
        vec![0, 5, 8, 10]
    );
    assert_eq!(labels(&sr, "class=Opening"), vec![2, 3, 7, 12]);
    assert_eq!(labels(&sr, "class!=Building"), vec![10_000, 10_001, 10_002]);
    // Ancestry: the windows of building B1.
    assert_eq!(labels(&sr, "class=Window and within(B1)"), vec![2, 3]);
    assert_eq!(labels(&sr, "within(B2)"), vec![5, 6, 7, 8, 9]);
    assert_eq!(labels(&sr, "id=B2"), vec![5]);
    assert_eq!(labels(&sr, "id=B2 or id=\"W3\""), vec![5, 11]);
    // Categories and labels reach image labels too.
    assert_eq!(
        labels(&sr, "category=tree or label=10001"),
        vec![10_000, 10_001]
    );
    assert_eq!(labels(&sr, "category=wall"), vec![0, 1, 5, 6, 8, 10, 11]);
    // Attributes are inherited from the nearest ancestor: B1 (12.5 m) and B2 (20 m) with their
    // descendants, but not the BuildingPart BP of B2 (its own 800 cm) nor its roof R2.
    let (_, s) = sr
        .select_text("--attr", "measuredHeight>10m", TextOptions::default())
        .unwrap();
    assert_eq!(s.labels, vec![0, 1, 2, 3, 4, 5, 6, 7]);
    assert_eq!(oids(&sr, &s.roots), vec!["B1", "B2"]);
    // Units: 1200 cm = 12 m; BP's 800 cm converts to 8 m; 0.009 km = 9 m.
    assert_eq!(
        labels(&sr, "measuredHeight >= 1200 cm"),
        vec![0, 1, 2, 3, 4, 5, 6, 7]
    );
    assert_eq!(labels(&sr, "measuredHeight < 10m"), vec![8, 9]);
    assert_eq!(
        labels(&sr, "measuredHeight > 0.009km and measuredHeight < 1300cm"),
        vec![0, 1, 2, 3, 4]
    );
    // A missing attribute satisfies no comparison; `not` selects it.
    assert_eq!(
        labels(&sr, "measuredHeight != 20 m"),
        vec![0, 1, 2, 3, 4, 8, 9]
    );
    assert_eq!(
        labels(&sr, "not measuredHeight > 0 m and level=feature"),
        vec![10]
    );
    // Text values, string "numbers", dates, lists.
    assert_eq!(
        labels(&sr, "function = 1000 and level=feature"),
        vec![0, 10]
    );
    assert_eq!(
        labels(&sr, "creationDate > 2020-07-01 and level=feature"),
        vec![5, 8]
    );
    assert_eq!(labels(&sr, "paneMaterialClass = metal"), vec![2]);
    assert_eq!(labels(&sr, "paneMaterialClass != glass"), Vec::<i32>::new());
    // Entities are reported by gml:id, roots are the tops of the selected subtrees.
    let (_, s) = sr
        .select_text(
            "--where",
            "within(B1) and not class=Window",
            TextOptions::default(),
        )
        .unwrap();
    assert_eq!(oids(&sr, &s.entities), vec!["B1", "W1", "R1"]);
    assert_eq!(oids(&sr, &s.roots), vec!["B1"]);
}

#[test]
fn bad_selections_get_one_clear_error_each() {
    let f = fixture("errors", false, PlyEncoding::BinaryLittleEndian);
    let sr = open(&f);
    let err = |t: &str| {
        sr.select_text("--where", t, TextOptions::default())
            .unwrap_err()
            .to_string()
    };
    let cases: [(&str, &[&str]); 15] = [
        (
            "measuredHeight > 10",
            &["column 1", "several units in semantics.json (cm, m)"],
        ),
        (
            "class=Windw",
            &[
                "column 1",
                "unknown CityGML class `Windw`",
                "did you mean `Window`",
            ],
        ),
        (
            "measuredHeigth > 10",
            &[
                "column 1",
                "unknown attribute `measuredHeigth`",
                "did you mean `measuredHeight`",
            ],
        ),
        ("measuredHeight >", &["column 17", "expected a value"]),
        (
            "class=Window and (level=part",
            &["column 29", "expected `)`"],
        ),
        ("measuredHeight 10", &["column 16", "expected a comparison"]),
        (
            "measuredHeight > abc",
            &["column 1", "holds numbers", "needs a number"],
        ),
        (
            "measuredHeight > 10 kg",
            &["column 21", "unknown unit `kg`"],
        ),
        (
            "measuredHeight > 10 m2",
            &["column 1", "cannot be compared", "`m2`"],
        ),
        (
            "function > 1000 m",
            &["column 1", "no unit", "function.uom"],
        ),
        ("class < Window", &["column 7", "`=` or `!=` only"]),
        ("level=floor", &["column 1", "unknown level `floor`"]),
        ("category=bus", &["column 1", "unknown category `bus`"]),
        (
            "id=NOPE or id=B1",
            &["column 1", "no entity has gml:id `NOPE`"],
        ),
        (
            "label=99",
            &["column 1", "label 99 is not in the label table"],
        ),
    ];
    for (t, wants) in cases {
        let e = err(t);
        assert!(!e.contains('\n'), "{t}: one line: {e}");
        for w in wants {
            assert!(e.contains(w), "{t}: `{e}` lacks `{w}`");
        }
    }
    // Text queries on a run without per-label features are refused clearly.
    let e = err("text(\"a car\")");
    assert!(
        e.contains("per-label features") && e.contains("label_features.npy"),
        "{e}"
    );
}

/// σ(x) = 1/(1+e^−x).
fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

#[test]
fn text_queries_match_present_classes_and_refuse_absent_ones() {
    let f = fixture("text", true, PlyEncoding::BinaryLittleEndian);
    let sr = open(&f);
    let o = TextOptions::default();
    // "a tree": the tree label (e0 + 0.3 e7)/√1.09 is 1/√1.09 closer to the query than to any
    // negative (all 0) → relevancy σ(10/√1.09) ≈ 0.99993; every other label is σ(−10) or, for
    // "other" (e7, orthogonal to every prompt), σ(0) = 0.5.
    let (_, s) = sr.select_text("--text", "text(\"a tree\")", o).unwrap();
    assert_eq!(s.labels, vec![10_000]);
    let t = &s.text[0];
    assert!(
        (t.best.unwrap() - sigmoid(10.0 / 1.09f64.sqrt())).abs() < 1e-6,
        "{t:?}"
    );
    assert_eq!(t.best_label, Some(10_000));
    assert_eq!(
        t.labels_scored, 9,
        "rows with a feature: 3 walls, 3 windows, tree, person, other"
    );
    // "a car" (no car in the scene): nothing reaches the threshold; the best is "other" at 0.5.
    let (_, s) = sr.select_text("--text", "text('a car')", o).unwrap();
    assert!(s.labels.is_empty());
    assert!(
        (s.text[0].best.unwrap() - 0.5).abs() < 1e-9,
        "{:?}",
        s.text[0]
    );
    assert_eq!(s.text[0].best_label, Some(10_002));
    // "a wall of a building": its synonym "a facade …" (cosine 0.95 ≥ 0.8) is not a negative,
    // so the walls match with σ(10); counting the synonym as a negative (synonym_cos 1) leaves
    // them at σ(10·(1 − 0.95)) = σ(0.5) ≈ 0.62 < 0.75: no match.
    let (_, s) = sr
        .select_text("--text", "text(\"a wall of a building\")", o)
        .unwrap();
    assert_eq!(s.labels, vec![1, 6, 11]);
    assert_eq!(
        s.text[0].synonyms,
        vec!["a facade of a building".to_string()]
    );
    let strict = TextOptions {
        synonym_cos: 1.0,
        ..o
    };
    let (_, s) = sr
        .select_text("--text", "text(\"a wall of a building\")", strict)
        .unwrap();
    assert!(s.labels.is_empty());
    let facade_cos = 0.95 / (0.95f64 * 0.95 + 0.3122 * 0.3122).sqrt();
    assert!((s.text[0].best.unwrap() - sigmoid(10.0 * (1.0 - facade_cos))).abs() < 1e-5);
    // Text and structure combine: the windows among "a window of a building" inside B1.
    assert_eq!(
        labels(&sr, "text(\"a window of a building\") and within(B1)"),
        vec![2, 3]
    );
    // A text that is not in prompts.json is free text; without a sentence-embedding model the
    // error lists the prompts (free text with the model: tests/textembed.rs).
    let mut ctx = sr.context(o);
    ctx.embed = None;
    let expr = selection::grammar::parse("text(\"a bus\")").unwrap();
    let e = selection::select::evaluate(&ctx, &selection::select::Index::new(&sr.entities), &expr)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("not a prompt") && e.contains("\"a car\"") && e.contains("free text needs"),
        "{e}"
    );

    // Through the stage: "a car" writes match false, the score, and empty masks.
    let out = f.root.join("q_car");
    let req = Request::Select(selection::grammar::parse("text(\"a car\")").unwrap());
    let s = query::run(&sr, &req, &QueryOptions::default(), &out).unwrap();
    assert!(!s.matched);
    let sel: Value = fsutil::read_json(&out.join("selection.json")).unwrap();
    assert_eq!(sel["match"], json!(false));
    assert_eq!(sel["labels"], json!([]));
    assert_eq!(sel["gaussians"], json!(0));
    assert!((sel["score"].as_f64().unwrap() - 0.5).abs() < 1e-9);
    let (_, m) = npy::read::<u8>(&out.join("v0.mask.npy")).unwrap();
    assert_eq!(m, vec![0; 8]);
}

#[test]
fn masks_counts_table_and_exports() {
    let f = fixture("stage", true, PlyEncoding::BinaryLittleEndian);
    let sr = open(&f);
    let out = f.root.join("q_window");
    let opts = QueryOptions {
        export: true,
        ..Default::default()
    };
    let req = Request::Select(selection::grammar::parse("class=Window").unwrap());
    let s = query::run(&sr, &req, &opts, &out).unwrap();
    // Windows: g0 g1 (Win1), g2 (Win2), g11 (WS).
    assert_eq!(
        (s.matched, s.labels, s.entities, s.gaussians),
        (true, 3, 3, 4)
    );
    // Only v0 has a prediction: the default views are the test views.
    assert_eq!(s.views.len(), 1);
    // v0, argmax with the windows as one label: p0 .6 > .3 → 1; p1 .4 < .5 → 0; p2 .45 < .5
    // (tree) → 0; p3 .3 + .3 = .6 > .35 → 1 although no single window wins; p4 empty → 0;
    // p5 .25 < .7 + .05 (unlabelled + transmittance) → 0; p6 .8 > .2 → 1; p7 → 0.
    let (shape, m) = npy::read::<u8>(&out.join("v0.mask.npy")).unwrap();
    assert_eq!(shape, vec![2, 4]);
    assert_eq!(m, vec![1, 0, 0, 1, 0, 0, 1, 0]);
    assert_eq!(s.views[0].pixels, 3);
    let png = gs4city::imageio::read_rgb(&out.join("v0.mask.png")).unwrap();
    assert_eq!(png.dim(), (2, 4, 3));
    // Pixel 0 of the image is (0, 1, 2): tinted red to (128, 21, 21); pixel 1 (10, 11, 12)
    // dimmed to 60 % (6, 7, 7).
    assert_eq!(
        [png[[0, 0, 0]], png[[0, 0, 1]], png[[0, 0, 2]]],
        [128, 21, 21]
    );
    assert_eq!([png[[0, 1, 0]], png[[0, 1, 1]], png[[0, 1, 2]]], [6, 7, 7]);
    // The majority rule agrees here (.6, .6 and .8 are majorities; .45 is not).
    let out_m = f.root.join("q_window_majority");
    let om = QueryOptions {
        rule: MaskRule::Majority,
        sqlite: false,
        ..Default::default()
    };
    query::run(&sr, &req, &om, &out_m).unwrap();
    assert_eq!(
        npy::read::<u8>(&out_m.join("v0.mask.npy")).unwrap().1,
        vec![1, 0, 0, 1, 0, 0, 1, 0]
    );

    // Exports partition the input: extract = g0 g1 g2 g11 in order, remove = the other 12.
    let (a, _) = splat::read_ply(&out.join("extract.ply"), &Default::default()).unwrap();
    let (b, _) = splat::read_ply(&out.join("remove.ply"), &Default::default()).unwrap();
    let xs = |g: &Gaussians| {
        g.positions
            .iter()
            .map(|p| p[0] as usize)
            .collect::<Vec<_>>()
    };
    assert_eq!(xs(&a), vec![0, 1, 2, 11]);
    assert_eq!(xs(&b), vec![3, 4, 5, 6, 7, 8, 9, 10, 12, 13, 14, 15]);
    // Each Gaussian carries its semantics: label, class, feature_id, surface_id, part_id.
    let strip = |mut g: Gaussians| {
        let cols: Vec<Vec<i32>> = g
            .extras
            .iter()
            .map(|e| e.values.iter().map(|&v| v as i32).collect())
            .collect();
        let names: Vec<String> = g.extras.iter().map(|e| e.name.clone()).collect();
        assert_eq!(
            names,
            ["label", "class", "feature_id", "surface_id", "part_id"]
        );
        g.extras.clear();
        (g, cols)
    };
    let (a, ca) = strip(a);
    let (b, cb) = strip(b);
    assert_eq!(a, gaussians_of(&[0, 1, 2, 11]));
    assert_eq!(b, gaussians_of(&[3, 4, 5, 6, 7, 8, 9, 10, 12, 13, 14, 15]));
    // g0 g1: Win1 (B1 → W1 → Win1), g2: Win2, g11: WS (B3 → W3 → WS); classes window.
    assert_eq!(ca[0], vec![2, 2, 3, 12]);
    assert_eq!(ca[1], vec![2, 2, 2, 2]);
    assert_eq!(ca[2], vec![0, 0, 0, 10]);
    assert_eq!(ca[3], vec![1, 1, 1, 11]);
    assert_eq!(ca[4], vec![2, 2, 3, 12]);
    // g3 g4: W1 (B1 → W1, no part); g12 g13: tree, g15: unlabelled (no hierarchy).
    assert_eq!(cb[0][0], 1);
    assert_eq!((cb[2][0], cb[3][0], cb[4][0]), (0, 1, -1));
    assert_eq!((cb[0][8], cb[1][8], cb[2][8]), (10_000, 6, -1));
    assert_eq!((cb[0][11], cb[1][11], cb[4][11]), (-1, -1, -1));
    // Byte for byte: the header differs in the count and the five int columns; each record is
    // the input's followed by its columns.
    let bytes = std::fs::read(f.scene.join("point_cloud.ply")).unwrap();
    let ea = std::fs::read(out.join("extract.ply")).unwrap();
    let er = std::fs::read(out.join("remove.ply")).unwrap();
    let hdr = |b: &[u8]| b.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let stride = (bytes.len() - hdr(&bytes)) / N;
    assert_eq!(stride, 4 * (3 + 3 + 9 + 1 + 3 + 4));
    let wide = stride + 4 * 5;
    let rec = |b: &[u8], i: usize, w: usize| b[hdr(b) + i * w..hdr(b) + i * w + stride].to_vec();
    let col = |b: &[u8], i: usize, c: usize| {
        let o = hdr(b) + i * wide + stride + 4 * c;
        i32::from_le_bytes(b[o..o + 4].try_into().unwrap())
    };
    assert_eq!(rec(&ea, 3, wide), rec(&bytes, 11, stride));
    assert_eq!(
        (0..5).map(|c| col(&ea, 3, c)).collect::<Vec<_>>(),
        [12, 2, 10, 11, 12]
    );
    assert_eq!(rec(&er, 0, wide), rec(&bytes, 3, stride));
    assert_eq!(
        ea.len() - hdr(&ea) + er.len() - hdr(&er),
        (bytes.len() - hdr(&bytes)) / stride * wide
    );

    // selection.json.
    let sel: Value = fsutil::read_json(&out.join("selection.json")).unwrap();
    assert_eq!(sel["match"], json!(true));
    assert_eq!(sel["labels"], json!([2, 3, 12]));
    assert_eq!(sel["entities"], json!(["Win1", "Win2", "WS"]));
    assert_eq!(sel["gaussians"], json!(4));
    assert_eq!(sel["score"], Value::Null);

    // The SQLite table: per-entity Gaussians and predicted pixels of v0. Predicted labels of
    // v0 by hand: p0 Win1, p1 W1, p2 tree, p3 tree (.35 > .3, .3), p4 none, p5 none, p6 WS,
    // p7 person.
    let db = rusqlite::Connection::open(out.join("semantic.sqlite")).unwrap();
    let q = |sql: &str| -> Vec<(String, i64, i64, i64, i64, i64)> {
        let mut st = db.prepare(sql).unwrap();
        st.query_map([], |r| {
            Ok((
                r.get(0)?,
                r.get(1)?,
                r.get(2)?,
                r.get(3)?,
                r.get(4)?,
                r.get(5)?,
            ))
        })
        .unwrap()
        .map(Result::unwrap)
        .collect()
    };
    let rows = q(
        "SELECT object_id, gaussians, gaussians_subtree, pixels, pixels_subtree, selected FROM entities WHERE object_id IN ('B1', 'W1', 'Win1', 'WS', 'B2') ORDER BY id",
    );
    assert_eq!(
        rows,
        vec![
            ("B1".into(), 1, 7, 0, 2, 0),
            ("W1".into(), 2, 5, 1, 2, 0),
            ("Win1".into(), 2, 2, 1, 1, 1),
            ("B2".into(), 0, 3, 0, 0, 0),
            ("WS".into(), 1, 1, 1, 1, 1),
        ]
    );
    let tall: Vec<String> = db
        .prepare("SELECT e.object_id FROM entities e JOIN attributes a ON a.entity_id = e.id WHERE a.name = 'measuredHeight' AND a.uom = 'm' AND a.number > 10 ORDER BY e.id")
        .unwrap()
        .query_map([], |r| r.get(0))
        .unwrap()
        .map(Result::unwrap)
        .collect();
    assert_eq!(tall, vec!["B1", "B2"]);
    let (uom, n): (String, i64) = db
        .query_row(
            "SELECT uom, count(*) FROM attributes WHERE name = 'measuredHeight' AND entity_id = 8",
            [],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .unwrap();
    assert_eq!((uom.as_str(), n), ("cm", 1));
    let lists: i64 = db
        .query_row(
            "SELECT count(*) FROM attributes WHERE name = 'paneMaterialClass'",
            [],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(lists, 2, "a list value is one row per element");
    let img: (i64, i64) = db
        .query_row(
            "SELECT gaussians, pixels FROM labels WHERE id = 10000",
            [],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .unwrap();
    assert_eq!(img, (2, 2));
    let px: i64 = db
        .query_row(
            "SELECT selected_pixels FROM views WHERE stem = 'v0'",
            [],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(px, 3);
    drop(db);

    // A second query into the same folder leaves nothing of the first behind.
    let again = QueryOptions {
        views: Views::None,
        sqlite: false,
        ..Default::default()
    };
    query::run(
        &sr,
        &Request::Select(selection::grammar::parse("class=Door").unwrap()),
        &again,
        &out,
    )
    .unwrap();
    for f in [
        "extract.ply",
        "remove.ply",
        "v0.mask.npy",
        "v0.mask.png",
        "semantic.sqlite",
    ] {
        assert!(!out.join(f).exists(), "{f} left over");
    }
}

#[test]
fn ascii_input_is_exported_through_the_typed_path() {
    let f = fixture("ascii", false, PlyEncoding::Ascii);
    let sr = open(&f);
    let out = f.root.join("q");
    let opts = QueryOptions {
        export: true,
        views: Views::None,
        sqlite: false,
        ..Default::default()
    };
    let s = query::run(
        &sr,
        &Request::Select(selection::grammar::parse("within(B2)").unwrap()),
        &opts,
        &out,
    )
    .unwrap();
    // B2's subtree owns g7 (W2), g8 (D1), g9 (R2).
    assert_eq!(s.gaussians, 3);
    let (mut a, _) = splat::read_ply(&out.join("extract.ply"), &Default::default()).unwrap();
    let (mut b, _) = splat::read_ply(&out.join("remove.ply"), &Default::default()).unwrap();
    // The semantic columns: g7 W2 (B2 → W2), g8 D1 (B2 → W2 → D1), g9 R2 (BP → R2).
    let class = a.extra("class").unwrap().values.clone();
    assert_eq!(class, vec![0.0, 3.0, 1.0]);
    let part = a.extra("part_id").unwrap().values.clone();
    assert_eq!(part, vec![-1.0, 7.0, -1.0]);
    let feature = a.extra("feature_id").unwrap().values.clone();
    assert_eq!(feature, vec![5.0, 5.0, 8.0]);
    a.extras.clear();
    b.extras.clear();
    assert_eq!(a, gaussians_of(&[7, 8, 9]));
    assert_eq!(
        b,
        gaussians_of(&[0, 1, 2, 3, 4, 5, 6, 10, 11, 12, 13, 14, 15])
    );
    assert_eq!(a.len() + b.len(), N);
}

#[test]
fn pick_reports_the_chain_under_a_pixel() {
    let f = fixture("pick", false, PlyEncoding::BinaryLittleEndian);
    let sr = open(&f);
    let cache = sr.cache().unwrap();
    // v0 pixel (0, 0): Win1 (.6) → B1 → W1 → Win1, with B1's attributes.
    let p = query::pick(&sr, &cache, "v0", 0, 0).unwrap();
    assert_eq!(p.label, 2);
    assert_eq!(p.category, "window");
    let chain: Vec<(&str, Level)> = p
        .chain
        .iter()
        .map(|c| (c.object_id.as_str(), c.level))
        .collect();
    assert_eq!(
        chain,
        vec![
            ("B1", Level::Feature),
            ("W1", Level::Surface),
            ("Win1", Level::Part)
        ]
    );
    assert_eq!(p.chain[0].attributes["measuredHeight"], json!(12.5));
    assert_eq!(p.gaussians.len(), 2);
    // v1.png pixel (1, 1) (by image name): R2 → the chain BP → R2 (a roof of the part).
    let p = query::pick(&sr, &cache, "v1.png", 1, 1).unwrap();
    let chain: Vec<&str> = p.chain.iter().map(|c| c.object_id.as_str()).collect();
    assert_eq!((p.label, chain), (9, vec!["BP", "R2"]));
    // Out of the image, unknown view: clear errors.
    let e = query::pick(&sr, &cache, "v0", 4, 0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("outside") && e.contains("4×2"), "{e}");
    let e = query::pick(&sr, &cache, "v9", 0, 0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("`v9` is not in the contributions cache"), "{e}");
    // Through the stage with --pick-level feature: all of B1 (g0..g6).
    let out = f.root.join("q");
    let req = Request::Pick {
        view: "v0".into(),
        x: 0,
        y: 0,
        level: Some(Level::Feature),
    };
    let s = query::run(
        &sr,
        &req,
        &QueryOptions {
            views: Views::Named(vec!["v1".into()]),
            ..Default::default()
        },
        &out,
    )
    .unwrap();
    assert_eq!((s.gaussians, s.query.as_str()), (7, "within(\"B1\")"));
    // The background pixel p4 selects nothing.
    let req = Request::Pick {
        view: "v0".into(),
        x: 0,
        y: 1,
        level: None,
    };
    let s = query::run(&sr, &req, &QueryOptions::default(), &f.root.join("q2")).unwrap();
    assert!(!s.matched && s.warnings[0].contains("no label"));
}

fn cli(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(args)
        .output()
        .expect("run gs4city");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn command_line() {
    let f = fixture("cli", true, PlyEncoding::BinaryLittleEndian);
    let run = f.run.to_str().unwrap();
    let out = f.root.join("q");
    let o = out.to_str().unwrap();
    // Flags combine with `and`; the scene comes from run.json.
    let (ok, stdout, stderr) = cli(&[
        "-q", "query", "--run", run, "--class", "Window", "--id", "B1", "--out", o,
    ]);
    assert!(ok, "{stderr}");
    assert!(
        stdout.contains("match true") && stdout.contains("2 labels"),
        "{stdout}"
    );
    let sel: Value = fsutil::read_json(&out.join("selection.json")).unwrap();
    assert_eq!(sel["labels"], json!([2, 3]));
    let summary = query::QuerySummary::read(&out).unwrap();
    assert_eq!(summary.gaussians, 3);
    // --text-feature: the car axis → no match.
    let fpath = f.root.join("car.npy");
    npy::write(&fpath, &[D], &e(2)).unwrap();
    let (ok, stdout, stderr) = cli(&[
        "-q",
        "query",
        "--run",
        run,
        "--text-feature",
        fpath.to_str().unwrap(),
        "--views",
        "none",
        "--out",
        o,
    ]);
    // No match is its own exit status (3), said in one line that names the outputs.
    assert!(!ok, "{stdout}");
    assert!(
        stderr.contains("no match") && stderr.contains("exit status 3"),
        "{stderr}"
    );
    // Errors: one line on stderr, failure status, nothing that looks done.
    let bad = f.root.join("bad");
    for (args, want) in [
        (vec!["--class", "Windw"], "unknown CityGML class `Windw`"),
        (
            vec!["--attr", "measuredHeight >"],
            "--attr `measuredHeight >`: column 17: expected a value",
        ),
        (vec!["--where", "foo = 3"], "unknown attribute `foo`"),
        (vec!["--pick", "v0", "9", "0"], "outside view"),
        (
            vec!["--views", "nope", "--class", "Door"],
            "`nope` is not in the contributions cache",
        ),
    ] {
        let mut a = vec!["-q", "query", "--run", run, "--out", bad.to_str().unwrap()];
        a.extend(args);
        let (ok, _, stderr) = cli(&a);
        assert!(!ok, "{a:?}");
        assert!(stderr.contains(want), "{a:?}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "{a:?}: {stderr}");
        assert!(!bad.join("summary.json").exists());
    }
}

#[test]
fn query_driven_evaluation_on_known_masks() {
    let f = fixture("eval", true, PlyEncoding::BinaryLittleEndian);
    let sr = open(&f);
    let cache = sr.cache().unwrap();
    // GT of v0 (class ids): p0 window, p1 wall, p2 tree, p3 window, p4 ignore, p5 wall,
    // p6 window, p7 person.
    let gt = f.root.join("gt");
    std::fs::create_dir_all(&gt).unwrap();
    npy::write(
        &gt.join("v0.class.npy"),
        &[2, 4],
        &[2, 0, 6, 2, -1, 0, 2, 7],
    )
    .unwrap();
    let r = gs4city::eval::by_query::evaluate(
        &sr,
        &cache,
        &gt,
        &["v0".into()],
        MaskRule::Argmax,
        TextOptions::default(),
    )
    .unwrap();
    assert_eq!(r.queries["tree"], "text(\"a tree\")");
    assert_eq!(r.queries["wall"], "category=wall");
    let m = &r.metrics.dataset;
    // Window (category=window: Win1, Win2, WS) mask = p0 p3 p6 = the GT windows → IoU 1.
    assert_eq!(m.fine.iou["window"], Some(1.0));
    // Wall (B1 W1 B2 W2 BP B3 W3): p1 (W1 .5 vs Win1 .4) only; GT walls p1 p5 → IoU 1/2.
    assert_eq!(m.fine.iou["wall"], Some(0.5));
    // Tree (text): p2 (.5 > .45); not p3, where the two windows (g0, g2: class window) weigh
    // .6 together against the tree's .35 — the class maps' rule, classes not labels compete →
    // tp 1 (p2), fp 0 → IoU 1, precision 1.
    assert_eq!(m.fine.iou["tree"], Some(1.0));
    assert_eq!(m.fine.precision["tree"], Some(1.0));
    // Person (text): p7 → 1.
    assert_eq!(m.fine.iou["person"], Some(1.0));
    // Coarse: building mask = p0 p1 p3 p6 (p2: tree .5 > .45; p5: none); GT building p0 p1 p3
    // p5 p6 → tp 4, fn 1 (p5), fp 0, tn 2 (p2 p7) → IoU 4/5, accuracy 6/7.
    assert_eq!(m.coarse.metrics.iou, Some(0.8));
    assert!((m.coarse.metrics.accuracy.unwrap() - 6.0 / 7.0).abs() < 1e-12);
    // Paper protocol, one image: mIoU over wall, window, tree, person = (.5 + 1 + 1 + 1)/4.
    assert!((r.metrics.paper.miou.mean.unwrap() - 0.875).abs() < 1e-12);
    assert!(r.tables.contains("Window"));
}

/// Attribute selections on real CityGML (the 27 Ingolstadt files of ../shared/data/citygml
/// and the FZK houses, CityGML 1.0 and 3.0) agree with an independent reading of the files
/// (`scripts/query_attr_check.py`, Python's ElementTree).
#[test]
fn attribute_selections_match_an_independent_reading_of_the_citygml() {
    let shared = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/citygml");
    assert!(
        shared.is_dir(),
        "{} is missing: the real-data tests need it",
        shared.display()
    );
    let mut files: Vec<PathBuf> = std::fs::read_dir(shared.join("ingolstadt_north"))
        .unwrap()
        .filter_map(|d| d.ok())
        .flat_map(|d| std::fs::read_dir(d.path()).into_iter().flatten())
        .filter_map(|f| f.ok().map(|f| f.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "gml"))
        .collect();
    files.sort();
    assert_eq!(files.len(), 27);
    files.push(shared.join("citygml1_FZK-House-LoD3-KIT-IAI-KHH-V2.gml"));
    files.push(shared.join("citygml3_FZK-Haus-LoD3-KIT-IAI-KHH-B36-V1__v3.gml"));
    let out = gs4city::citymodel::run(&files, &Default::default()).unwrap();
    let entities = out.entities;
    let table = LabelTable::city(&entities, &gs4city::classes::table(&entities)).unwrap();
    let index = selection::select::Index::new(&entities);
    let ctx = selection::select::Context {
        entities: &entities,
        labels: &table,
        features: None,
        prompts: None,
        features_path: PathBuf::new(),
        text: TextOptions::default(),
        embed: None,
    };
    if !crate::common::python_can_import(
        "query::attribute_selections_match_an_independent_reading_of_the_citygml",
        &[],
    ) {
        return;
    }
    for (op, value, expr) in [
        (">", "15", "measuredHeight > 15"),
        ("<=", "12.68", "measuredHeight <= 12.68"),
        (">=", "13", "measuredHeight >= 1300 cm"),
        ("<", "7", "measuredHeight < 0.007 km"),
    ] {
        let mut cmd = Command::new("python3");
        cmd.arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/query_attr_check.py"))
            .args(["--name", "measuredHeight", "--op", op, "--value", value])
            .args(&files);
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let want: Value = serde_json::from_slice(&o.stdout).unwrap();
        let sel =
            selection::select::evaluate(&ctx, &index, &selection::grammar::parse(expr).unwrap())
                .unwrap();
        let ids = |v: &[i32], features_only: bool| -> Vec<String> {
            let mut x: Vec<String> = v
                .iter()
                .map(|&e| &entities[e as usize])
                .filter(|e| !features_only || matches!(e.class.name(), "Building" | "BuildingPart"))
                .map(|e| e.object_id.clone())
                .collect();
            x.sort();
            x
        };
        let sorted = |v: &Value| -> Vec<String> {
            let mut x: Vec<String> = v
                .as_array()
                .unwrap()
                .iter()
                .map(|s| s.as_str().unwrap().to_string())
                .collect();
            x.sort();
            x
        };
        assert_eq!(ids(&sel.roots, false), sorted(&want["roots"]), "{expr}");
        assert_eq!(
            ids(&sel.entities, true),
            sorted(&want["selected"]),
            "{expr}"
        );
        assert!(
            !sel.roots.is_empty(),
            "{expr}: a check that selects nothing proves little"
        );
    }
}

use crate::sim_labels;

/// A SIMULATED scene without cars (`synth --preset small`, `objects.cars = 0`): with label
/// features standing in for the fuse stage's (instance groups of simulated mask features,
/// `common/sim_labels.rs`), "a car" matches nothing at the calibrated threshold while "a tree"
/// and "a person" match exactly labels of their class.
#[test]
fn absent_class_in_a_simulated_scene_without_cars() {
    let root =
        crate::common::temp_dir().join(format!("gs4city-query-nocar-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).unwrap();
    let cfg = root.join("nocar.toml");
    std::fs::write(&cfg, "[objects]\ncars = 0\n").unwrap();
    let scene = root.join("scene");
    let (ok, _, err) = cli(&[
        "-q",
        "synth",
        "--preset",
        "small",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        scene.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let (_, groups) = sim_labels::simulated_labels(&scene);
    assert!(
        groups.iter().all(|g| g.class != gs4city::classes::CAR),
        "the variant has no car"
    );
    let classes: Vec<i32> = groups.iter().map(|g| g.class).collect();
    let flat: Vec<f32> = groups
        .iter()
        .flat_map(|g| g.feature.iter().copied())
        .collect();
    let feats = selection::LabelFeatures::new(Path::new("simulated"), 512, &flat).unwrap();
    let prompts = gs4city::sam::read_prompts_json(&scene.join("features/prompts.json")).unwrap();
    let o = TextOptions::default();
    let ids: Vec<i32> = (0..groups.len() as i32).collect();
    for (prompt, class) in [
        ("a car", gs4city::classes::CAR),
        ("a tree", gs4city::classes::TREE),
        ("a person", gs4city::classes::PERSON),
    ] {
        let q = selection::text::build_query(&prompts, Path::new("prompts.json"), Ok(prompt), &o)
            .unwrap();
        let (scores, m) = selection::text::score_labels(&q, &feats, &ids, &o);
        let matched: Vec<usize> = (0..groups.len())
            .filter(|&i| scores[i].is_some_and(|s| s >= o.min_relevancy))
            .collect();
        let of_class = classes.iter().filter(|&&c| c == class).count();
        if class == gs4city::classes::CAR {
            assert!(matched.is_empty(), "{prompt}: {m:?}");
            assert!(m.best.unwrap() < o.min_relevancy);
        } else {
            assert!(of_class > 0, "{prompt}: the small scene has {prompt}s");
            assert_eq!(
                matched.len(),
                of_class,
                "{prompt}: every group of the class matches, nothing else: {m:?}"
            );
            assert!(matched.iter().all(|&i| classes[i] == class));
        }
    }
    let _ = std::fs::remove_dir_all(&root);
}
