//! What `report.html` of a finished run shows (called by `run::metrics_against_the_analytic_truth…`
//! on its run of the hand-built wall scene): the command line, the link to `semantic.ply`, the
//! confusion matrix, the per-building table whose counts are recounted here from the run's files
//! (gaussians.npy → labels.json → semantics.json, read as plain JSON), the outlined legend, and
//! per test view a render of the Gaussians painted in their class colours that agrees with the
//! predicted class map. `check_simulated` (also called on the demo's run, tests/readme.rs): the
//! SIMULATED line at the top exactly when the scene's own `scene.json` says so, and the order of
//! the report — what the run produced (the Gaussians per class, recounted here), the scores, the
//! method's diagnostics.
use std::collections::HashMap;
use std::path::Path;

use gs4city::npy;
use serde_json::Value;

/// The palette by hand (docs/design.md): wall, roof, window, door.
const PALETTE: [[u8; 3]; 4] = [
    [200, 180, 140],
    [180, 60, 50],
    [60, 140, 230],
    [240, 160, 40],
];

/// The class names by id, by hand (docs/design.md).
const NAMES: [&str; 12] = [
    "wall",
    "roof",
    "window",
    "door",
    "ground_surface",
    "installation",
    "tree",
    "person",
    "car",
    "road",
    "water",
    "other",
];

/// `out/report.html` says SIMULATED before its title exactly when `simulated` (and nowhere when
/// not); it leads with what the run produced — the Gaussians per class, recounted here from
/// `lift/gaussians.npy` — then the test views, the scores, and last the method's diagnostics.
pub fn check_simulated(out: &Path, simulated: bool) {
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    let h1 = html.find("<h1>").expect("a title");
    assert_eq!(
        html[..h1].contains("SIMULATED"),
        simulated,
        "SIMULATED at the top of the report: expected {simulated}"
    );
    if !simulated {
        assert!(!html.contains("SIMULATED"), "no SIMULATED anywhere");
    }
    let at = |s: &str| {
        html.find(s)
            .unwrap_or_else(|| panic!("`{s}` in the report"))
    };
    let order = [
        at("What the run produced"),
        at("<h2>Buildings</h2>"),
        at("<h2>Test views"),
        at("<h2>Metrics"),
        at("<h2>Method diagnostics"),
        at("Time per stage"),
    ];
    assert!(order.is_sorted(), "report sections out of order: {order:?}");
    let (_, table) = npy::read::<i32>(&out.join("lift/gaussians.npy")).unwrap();
    let mut count: HashMap<i32, usize> = HashMap::new();
    for row in table.chunks(2) {
        *count.entry(row[1]).or_default() += 1;
    }
    assert!(html.contains(&format!(
        "What the run produced: {} Gaussians",
        table.len() / 2
    )));
    for (c, n) in count {
        let name = usize::try_from(c).map_or("no class", |k| NAMES[k]);
        let cell = format!("{name}</td><td>{n}</td>");
        assert!(html.contains(&cell), "{cell} in the class table");
    }
}

pub fn check_report(out: &Path, test_view: &str) {
    check_simulated(out, false);
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    let first = std::env::args().next().unwrap();
    assert!(
        html.contains("Command: <code>") && html.contains(&first),
        "the command line"
    );
    assert!(html.contains("<a href=\"lift/semantic.ply\">"));
    assert!(out.join("lift/semantic.ply").is_file());
    assert!(html.contains("Confusion matrix") && html.contains("<th>other</th>"));
    assert!(
        html.contains("border:1px solid #333"),
        "legend swatches outlined"
    );

    // Gaussians per building, recounted: label → entity (labels.json) → building (semantics.json).
    let (_, table) = npy::read::<i32>(&out.join("lift/gaussians.npy")).unwrap();
    let read = |p: &str| -> Value {
        serde_json::from_slice(&std::fs::read(out.join(p)).unwrap()).unwrap()
    };
    let labels = read("fuse/labels.json");
    let sem = read("citymodel/semantics.json");
    let entities = sem["entities"].as_array().unwrap();
    let entity_of: HashMap<i64, i64> = labels["labels"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|l| Some((l["id"].as_i64()?, l["entity"].as_i64()?)))
        .collect();
    let mut per_building: HashMap<String, usize> = HashMap::new();
    for row in table.chunks(2) {
        if let Some(e) = entity_of.get(&i64::from(row[0])) {
            let b = entities[*e as usize]["building"].as_i64().unwrap();
            let gml = entities[b as usize]["object_id"]
                .as_str()
                .unwrap()
                .to_string();
            *per_building.entry(gml).or_default() += 1;
        }
    }
    assert!(!per_building.is_empty());
    for (gml, n) in &per_building {
        let cell = format!("<td style=\"text-align:left\">{gml}</td><td>{n}</td>");
        assert!(html.contains(&cell), "{cell} in the building table");
    }

    // The class-coloured render (second panel) against the predicted class map: where the
    // prediction is a building class, the render shows its colour (within 40 per channel) on
    // most pixels (edges blend).
    let panel = gs4city::imageio::read_rgb(&out.join(format!("report/{test_view}.png"))).unwrap();
    let (shape, pred) = npy::read::<i32>(&out.join(format!("lift/{test_view}.class.npy"))).unwrap();
    let (h, w) = (shape[0], shape[1]);
    assert_eq!(panel.dim(), (h, 4 * w + 12, 3), "four panels, 4 px apart");
    let (mut n, mut agree) = (0usize, 0usize);
    for y in 0..h {
        for x in 0..w {
            let c = pred[y * w + x];
            if !(0..4).contains(&c) {
                continue;
            }
            n += 1;
            let want = PALETTE[c as usize];
            if (0..3)
                .all(|k| (i32::from(panel[[y, w + 4 + x, k]]) - i32::from(want[k])).abs() <= 40)
            {
                agree += 1;
            }
        }
    }
    assert!(n > 100, "{n} building pixels");
    assert!(
        agree as f64 > 0.8 * n as f64,
        "{agree} of {n} pixels show the predicted class colour"
    );
}
