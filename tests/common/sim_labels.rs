//! SIMULATED per-label features for text-query checks, standing in for the fuse stage's
//! `label_features.npy` until that stage exists: the scene's simulated per-mask features
//! (`features/<stem>.npy`) grouped by their ground-truth source instance across views
//! (`masks/<stem>.sim.json` — simulation truth, read by tests and benchmarks only). A group's
//! feature is the normalised mean of its masks' features (the association's running mean);
//! merged masks and false positives stay groups of their own. Included with `#[path]` by
//! `tests/query.rs` and `benches/query.rs`.
#![allow(dead_code)]
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

#[derive(serde::Deserialize)]
struct SimMask {
    source_instances: Vec<i64>,
    class: i32,
    kind: String,
}

/// A simulated label: its true class, its (unnormalised) feature, and how many masks made it.
pub struct SimLabel {
    pub class: i32,
    pub feature: Vec<f32>,
    pub masks: usize,
}

/// `(single masks, instance groups)` of a simulated scene folder.
pub fn simulated_labels(scene: &Path) -> (Vec<SimLabel>, Vec<SimLabel>) {
    let mut singles = Vec::new();
    let mut groups: BTreeMap<i64, (i32, Vec<f64>, usize)> = BTreeMap::new();
    let mut sims: Vec<PathBuf> = std::fs::read_dir(scene.join("masks"))
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.to_string_lossy().ends_with(".sim.json"))
        .collect();
    sims.sort();
    let mut own = -1i64;
    for p in sims {
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        let stem = name.trim_end_matches(".sim.json");
        let sim: Vec<SimMask> = gs4city::fsutil::read_json(&p).unwrap();
        let (shape, f) =
            gs4city::npy::read::<f32>(&scene.join(format!("features/{stem}.npy"))).unwrap();
        assert_eq!(shape[0], sim.len(), "{stem}");
        let d = shape[1];
        for (i, m) in sim.iter().enumerate() {
            let row = &f[i * d..(i + 1) * d];
            singles.push(SimLabel {
                class: m.class,
                feature: row.to_vec(),
                masks: 1,
            });
            let key =
                if m.source_instances.len() == 1 && (m.kind == "instance" || m.kind == "split") {
                    m.source_instances[0]
                } else {
                    own -= 1;
                    own
                };
            let g = groups.entry(key).or_insert((m.class, vec![0.0; d], 0));
            g.1.iter_mut()
                .zip(row)
                .for_each(|(a, &b)| *a += f64::from(b));
            g.2 += 1;
        }
    }
    let groups = groups
        .into_values()
        .map(|(class, s, masks)| SimLabel {
            class,
            feature: s.iter().map(|&x| x as f32).collect(),
            masks,
        })
        .collect();
    (singles, groups)
}
