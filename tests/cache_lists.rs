//! The cache's list rules and its version 4 file, checked from outside: the mass rule against
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

/// Writes a view with lists that share ids between neighbours (and large ids) and a median
/// plane, reads the file with the Python decoder below (stdlib only), and compares every list,
/// the alpha and the median plane bit for bit.
#[test]
fn a_python_reader_written_from_the_docs_decodes_version_4() {
    if !crate::common::python_can_import(
        "cache_lists::a_python_reader_written_from_the_docs_decodes_version_4",
        &["struct", "json"],
    ) {
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
        // A median plane with NaN (no median) at every fourth pixel.
        median: (0..w * h)
            .map(|p| {
                if p % 4 == 1 {
                    f32::NAN
                } else {
                    p as f32 * 0.75 - 3.0
                }
            })
            .collect(),
    };
    let dir = crate::common::temp_dir().join(format!("gs4c-v4-{}", std::process::id()));
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
    let (lists, alpha, median): (Vec<Vec<u32>>, Vec<u32>, Option<Vec<u32>>) =
        serde_json::from_slice(&out.stdout).unwrap();
    for (p, l) in lists.iter().enumerate() {
        assert_eq!(&l[..], v.pixel(p).0, "pixel {p}");
    }
    assert_eq!(lists.len(), w * h);
    let bits = |x: &[f32]| x.iter().map(|f| f.to_bits()).collect::<Vec<u32>>();
    assert_eq!(alpha, bits(&v.alpha));
    assert_eq!(
        median,
        Some(bits(&v.median)),
        "the median plane, NaNs included"
    );
    // And the readers of the crate agree with its own writer on the same file.
    let back = ViewContrib::read(Path::new(&file), Some(4_000_000_001)).unwrap();
    assert_eq!(bits(&back.median), bits(&v.median));
    assert_eq!(
        (back.lists.offsets, back.lists.ids),
        (v.lists.offsets, v.lists.ids)
    );
    let planes = gs4city::cache::ViewPlanes::read(Path::new(&file), Some(4_000_000_001)).unwrap();
    assert_eq!(bits(&planes.alpha), bits(&v.alpha));
    assert_eq!(bits(&planes.depth), bits(&v.depth));
    assert_eq!(planes.median.as_deref().map(bits), Some(bits(&v.median)));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The format of `src/cache.rs`'s docs, read with the standard library only.
const PY_READER: &str = r#"
import json, struct, sys
b = open(sys.argv[1], "rb").read()
assert b[:8] == b"GS4CCONT"
version, width, height, k = struct.unpack_from("<4I", b, 8)
gaussians, entries, code_bytes = struct.unpack_from("<3Q", b, 24)
(flags,) = struct.unpack_from("<I", b, 48)
assert version == 4 and flags in (0, 1)
npx = width * height
planes = 4 if flags & 1 else 3
assert len(b) == 64 + 2 * npx + 8 * height + code_bytes + 2 * entries + 4 * planes * npx
tail = 64 + 2 * npx + 8 * height + code_bytes + 2 * entries
plane = lambda i: list(struct.unpack_from("<%dI" % npx, b, tail + 4 * npx * i))
alpha, median = plane(1), (plane(3) if flags & 1 else None)
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
print(json.dumps([lists, alpha, median]))
"#;

/// The render stage's median-depth plane against the median computed here from the lists read
/// back (the camera z of the first Gaussian at which the running sum of kept weights reaches
/// 0.5, NaN where it never does); the planes-only reader against the full reader; and a cache
/// without the plane (as before version 4) giving the same median through the Gaussians'
/// centres, or, without them, an error naming the file.
#[test]
fn the_stored_median_depth_is_the_median_of_the_stored_lists() {
    use gs4city::cache::{Cache, CacheOptions, cache_file};
    use gs4city::layout::Summary;
    let dir = crate::common::wall::tmp("median-plane");
    let (_, s) = crate::common::wall::write_scene(&dir.join("scene"), 5);
    let views = crate::common::wall::views();
    let prepared = gs4city::render::PreparedScene::new(&s.gaussians).unwrap();
    let built = dir.join("cache");
    gs4city::render::cache::build(&prepared, &views, &CacheOptions::default(), &built).unwrap();
    let cache = Cache::open(&built).unwrap();
    assert!(cache.summary.median_depth);
    // The same views without their planes, in a cache whose summary says so.
    let old = dir.join("old");
    std::fs::create_dir_all(&old).unwrap();
    let mut summary = cache.summary.clone();
    summary.median_depth = false;
    summary.write(&old).unwrap();
    let old_cache = Cache::open(&old).unwrap();
    let pos = &s.gaussians.positions;
    let bits = |x: &[f32]| x.iter().map(|f| f.to_bits()).collect::<Vec<u32>>();
    let mut with_median = 0;
    for v in &views {
        let stem = v.stem();
        let c = cache.load(&stem).unwrap();
        assert_eq!(c.median.len(), c.pixels());
        for p in 0..c.pixels() {
            let (ids, ws) = c.pixel(p);
            let (mut acc, mut want) = (0.0f32, f64::NAN);
            for (&i, &w) in ids.iter().zip(ws) {
                acc += w;
                if acc >= 0.5 {
                    let q = pos[i as usize];
                    let x = glam::DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64);
                    want = (v.camera.pose.rotation * x + v.camera.pose.translation).z;
                    break;
                }
            }
            let got = f64::from(c.median[p]);
            if want.is_nan() {
                assert!(got.is_nan(), "{stem} pixel {p}: {got}, no median");
            } else {
                with_median += 1;
                assert!(
                    (got - want).abs() <= 1e-5 * want.abs().max(1.0),
                    "{stem} pixel {p}"
                );
            }
        }
        let planes = cache.load_planes(&stem).unwrap();
        assert_eq!((planes.width, planes.height), (c.width, c.height));
        assert_eq!(bits(&planes.alpha), bits(&c.alpha));
        assert_eq!(bits(&planes.depth), bits(&c.depth));
        assert_eq!(planes.median.as_deref().map(bits), Some(bits(&c.median)));
        let (_, m) = cache.median_depth(&stem, None, &v.camera.pose).unwrap();
        assert_eq!(bits(&m), bits(&c.median));
        // Without the plane: the lists and the centres give the same bits.
        let mut bare = c.clone();
        bare.median.clear();
        bare.write(&cache_file(&old, &stem)).unwrap();
        let (p, m) = old_cache
            .median_depth(&stem, Some(pos), &v.camera.pose)
            .unwrap();
        assert!(p.median.is_none());
        assert_eq!(bits(&m), bits(&c.median), "{stem}");
        let e = old_cache
            .median_depth(&stem, None, &v.camera.pose)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(&format!("{stem}.contrib")) && e.contains("median"),
            "{e}"
        );
    }
    assert!(with_median > 1000, "{with_median} pixels with a median");
    std::fs::remove_dir_all(&dir).unwrap();
}
