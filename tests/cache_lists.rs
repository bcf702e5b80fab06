//! The cache's list rules and its version 3 file, checked from outside: the mass rule against
//! the complete lists of the same render (which entries it must keep, what it may drop), and
//! the id code decoded by an independent Python reader written from the format's docs.
use std::path::Path;

use gs4city::cache::{Contributions, ViewContrib};
use gs4city::render::ContributionMode;

use crate::render::{load_scene, render_mode};

#[test]
fn the_mass_rule_keeps_the_fewest_largest_weights_that_reach_1_minus_epsilon() {
    let (_, scene) = load_scene("mixed3");
    let all = render_mode(&scene, ContributionMode::All);
    let full = all.contributions.as_ref().unwrap();
    let npx = all.width * all.height;
    for (epsilon, cap) in [(0.02f32, 0usize), (0.1, 0), (0.05, 3)] {
        let out = render_mode(&scene, ContributionMode::Mass { epsilon, cap });
        assert_eq!(out.rgb, all.rgb, "lists do not change the image");
        let c = out.contributions.as_ref().unwrap();
        let (mut shorter, mut kept_entries) = (0usize, 0usize);
        for p in 0..npx {
            let (ids, ws) = c.pixel(p);
            let (all_ids, all_ws) = full.pixel(p);
            kept_entries += ids.len();
            // A subsequence of the complete list (same ids, same weights, depth order).
            let mut j = 0;
            for (id, w) in ids.iter().zip(ws) {
                while j < all_ids.len() && all_ids[j] != *id {
                    j += 1;
                }
                assert!(j < all_ids.len(), "pixel {p}: id {id} not in order");
                assert_eq!(*w, all_ws[j]);
                j += 1;
            }
            let total: f64 = all_ws.iter().map(|&w| f64::from(w)).sum();
            let kept: f64 = ws.iter().map(|&w| f64::from(w)).sum();
            assert!(
                (kept + f64::from(c.residual[p]) - total).abs() < 1e-5,
                "pixel {p}: kept + residual = total"
            );
            if ids.len() < all_ids.len() {
                shorter += 1;
                // Every kept weight is at least every dropped one.
                let min_kept = ws.iter().copied().fold(f32::INFINITY, f32::min);
                let mut dropped: Vec<f32> = all_ws.to_vec();
                for w in ws {
                    let i = dropped.iter().position(|x| x == w).unwrap();
                    dropped.swap_remove(i);
                }
                let max_dropped = dropped.iter().copied().fold(0.0f32, f32::max);
                assert!(min_kept >= max_dropped, "pixel {p}");
                let target = (1.0 - f64::from(epsilon)) * total;
                if cap == 0 || ids.len() < cap {
                    // Enough mass, and not one entry more than needed.
                    assert!(kept >= target - 1e-5, "pixel {p}: {kept} < {target}");
                    assert!(
                        kept - f64::from(min_kept) < target + 1e-5,
                        "pixel {p}: the smallest kept entry was not needed"
                    );
                } else {
                    assert_eq!(ids.len(), cap);
                }
            } else {
                assert_eq!(c.residual[p], 0.0);
            }
        }
        assert!(
            shorter > npx / 20,
            "ε {epsilon}: the rule drops entries somewhere"
        );
        assert!(kept_entries < full.ids.len(), "ε {epsilon}");
    }
}

/// Writes a view with lists that share ids between neighbours (and large ids), reads the
/// file with the Python decoder below (stdlib only), and compares every list.
#[test]
fn a_python_reader_written_from_the_docs_decodes_version_3() {
    if !crate::common::python_can_import("cache_lists::python_reader", &["struct", "json"]) {
        return;
    }
    let (w, h) = (7usize, 5usize);
    let mut offsets = vec![0u64];
    let mut ids: Vec<u32> = Vec::new();
    for p in 0..w * h {
        // Neighbours overlap: pixel p holds p/2, p/2 + 1, and every third one a large id.
        let mut l = vec![(p / 2) as u32, (p / 2 + 1) as u32];
        if p % 3 == 0 {
            l.insert(1, 4_000_000_000 - p as u32);
        }
        if p % 5 == 4 {
            l.clear();
        }
        ids.extend(&l);
        offsets.push(ids.len() as u64);
    }
    let n = ids.len();
    let v = ViewContrib {
        width: w,
        height: h,
        k: 0,
        gaussians: 4_000_000_001,
        lists: Contributions {
            offsets,
            ids,
            weights: (0..n).map(|i| 1.0 / (i + 2) as f32).collect(),
            residual: vec![0.0; w * h],
        },
        alpha: vec![1.0; w * h],
        depth: vec![2.0; w * h],
    };
    let dir = crate::common::temp_dir().join(format!("gs4c-v3-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("v.contrib");
    v.write(&file).unwrap();
    let out = std::process::Command::new("python3")
        .args(["-c", PY_READER, file.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lists: Vec<Vec<u32>> = serde_json::from_slice(&out.stdout).unwrap();
    for (p, l) in lists.iter().enumerate() {
        assert_eq!(&l[..], v.pixel(p).0, "pixel {p}");
    }
    assert_eq!(lists.len(), w * h);
    // And the reader of the crate agrees with its own writer on the same file.
    let back = ViewContrib::read(Path::new(&file), Some(4_000_000_001)).unwrap();
    assert_eq!(
        (back.lists.offsets, back.lists.ids),
        (v.lists.offsets, v.lists.ids)
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The format of `src/cache.rs`'s docs, read with the standard library only.
const PY_READER: &str = r#"
import json, struct, sys
b = open(sys.argv[1], "rb").read()
assert b[:8] == b"GS4CCONT"
version, width, height, k = struct.unpack_from("<4I", b, 8)
gaussians, entries, code_bytes = struct.unpack_from("<3Q", b, 24)
assert version == 3
npx = width * height
o = 64
counts = struct.unpack_from("<%dH" % npx, b, o); o += 2 * npx
ends = struct.unpack_from("<%dQ" % height, b, o); o += 8 * height
code = b[o:o + code_bytes]
lists, start = [], 0
for y in range(height):
    pos, base, prev = start, 0, []
    for x in range(width):
        cur = []
        for _ in range(counts[y * width + x]):
            v, shift = 0, 0
            while True:
                byte = code[pos]; pos += 1
                v |= (byte & 0x7F) << shift; shift += 7
                if byte < 0x80:
                    break
            if v < len(prev):
                cur.append(prev[v])
            else:
                zz = v - len(prev)
                base += (zz >> 1) ^ -(zz & 1)
                cur.append(base)
        lists.append(cur)
        prev = cur
    assert pos == ends[y]
    start = ends[y]
assert sum(counts) == entries and start == code_bytes
print(json.dumps(lists))
"#;
