//! A STAND-IN for the masks stage (issue 12, not merged yet), used only by the associate/fuse
//! tests and benchmark to produce kept-mask files in the masks stage's format. It is NOT the
//! masks stage and no pipeline stage uses it. It reads only pipeline inputs (the scene's SAM
//! lists, features and prompts, the raycast feature channel), never simulation truth.
//!
//! Rule (the paper's filter, without its area filter): keep a SAM mask when
//! `predicted_iou ≥ 0.7` and either `R_ov < 0.8` against the raycast building support (rule
//! `low_overlap`), or — with `clip` and features — `S_fore > S_city + 0.05` over the prompts
//! (rule `clip`; building prompts = those whose class is 0–5). Its class is the class of the
//! most similar prompt (−1 without features).
use std::path::Path;

use gs4city::camera::View;
use gs4city::masks::{KeptMask, write_kept};
use gs4city::sam::{read_prompts_json, read_sam_json_sized};

/// Class of each prompt text of the simulated scenes (docs/sam.md); unknown texts: −1.
pub fn prompt_class(text: &str) -> i32 {
    match text {
        "a wall of a building" | "a facade of a building" | "a building" => 0,
        "a roof" => 1,
        "a window of a building" => 2,
        "a door" => 3,
        "the ground surface of a building" => 4,
        "a balcony of a building" => 5,
        "a tree" => 6,
        "a person" => 7,
        "a car" => 8,
        "a road" => 9,
        "water" => 10,
        _ => -1,
    }
}

/// Counts of the stand-in.
#[derive(Debug, Default, Clone, Copy)]
pub struct StandinCounts {
    pub masks: usize,
    pub kept_low_overlap: usize,
    pub kept_clip: usize,
}

/// Writes `<out>/<stem>.json` (kept masks) for every view; `min_quality` is `τ_q` (0.7).
pub fn standin_masks(
    scene: &Path,
    raycast: &Path,
    views: &[View],
    out: &Path,
    clip: bool,
    min_quality: f64,
) -> StandinCounts {
    std::fs::create_dir_all(out).unwrap();
    let prompts = read_prompts_json(&scene.join("features/prompts.json")).ok();
    let mut counts = StandinCounts::default();
    for v in views {
        let stem = v.stem();
        let (w, h) = (
            v.camera.intrinsics.width as usize,
            v.camera.intrinsics.height as usize,
        );
        let sam =
            read_sam_json_sized(&scene.join(format!("masks/{stem}.json")), Some([h, w])).unwrap();
        let (shape, ids) =
            gs4city::npy::read::<i32>(&raycast.join(format!("{stem}.ids.npy"))).unwrap();
        assert_eq!(shape, vec![4, h, w]);
        let feats = gs4city::npy::read::<f32>(&scene.join(format!("features/{stem}.npy"))).ok();
        let mut kept = Vec::new();
        for (i, m) in sam.iter().enumerate() {
            counts.masks += 1;
            if m.predicted_iou < min_quality {
                continue;
            }
            let dec = m.segmentation.decode().unwrap();
            let (mut n, mut on) = (0usize, 0usize);
            for ((y, x), &s) in dec.indexed_iter() {
                if s {
                    n += 1;
                    if ids[y * w + x] >= 0 {
                        on += 1;
                    }
                }
            }
            let r_ov = on as f64 / n.max(1) as f64;
            let (mut class, mut s_city, mut s_fore) = (-1, f64::NEG_INFINITY, f64::NEG_INFINITY);
            if let (Some(p), Some((fs, fd))) = (&prompts, &feats) {
                let d = fs[1];
                let f = &fd[i * d..(i + 1) * d];
                let mut best = f64::NEG_INFINITY;
                for (text, t) in &p.prompts {
                    let c: f64 = f
                        .iter()
                        .zip(t)
                        .map(|(&a, &b)| f64::from(a) * f64::from(b))
                        .sum();
                    let pc = prompt_class(text);
                    if (0..=5).contains(&pc) {
                        s_city = s_city.max(c);
                    } else {
                        s_fore = s_fore.max(c);
                    }
                    if c > best && pc >= 0 {
                        best = c;
                        class = pc;
                    }
                }
            }
            let rule = if r_ov < 0.8 {
                counts.kept_low_overlap += 1;
                "low_overlap"
            } else if clip && s_fore > s_city + 0.05 {
                counts.kept_clip += 1;
                "clip"
            } else {
                continue;
            };
            kept.push(KeptMask {
                sam: m.clone(),
                source_index: i as i64,
                r_ov,
                rule: rule.into(),
                class,
            });
        }
        write_kept(&out.join(format!("{stem}.json")), &kept).unwrap();
    }
    counts
}
