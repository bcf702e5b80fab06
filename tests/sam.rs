//! SAM mask files: pycocotools-made fixtures (`scripts/make_rle_fixtures.py`), broken files,
//! and a two-way cross-check against pycocotools (`scripts/rle_crosscheck.py`, skipped with a
//! message where python3 cannot import pycocotools).
use std::path::{Path, PathBuf};
use std::process::Command;

use gs4city::sam::{self as masks, Rle, RleCounts, RleError, SamError as MasksError, SamMask};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/masks")
        .join(name)
}

fn tmp_dir(tag: &str) -> PathBuf {
    let d = crate::common::temp_dir().join(format!("gs4city-masks-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn expected_masks() -> Vec<Array2<bool>> {
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data("sam_small.expected.json")).unwrap()).unwrap();
    let h = v["size"][0].as_u64().unwrap() as usize;
    let w = v["size"][1].as_u64().unwrap() as usize;
    v["masks"]
        .as_array()
        .unwrap()
        .iter()
        .map(|rows| {
            let rows: Vec<&str> = rows
                .as_array()
                .unwrap()
                .iter()
                .map(|r| r.as_str().unwrap())
                .collect();
            Array2::from_shape_fn((h, w), |(y, x)| rows[y].as_bytes()[x] == b'1')
        })
        .collect()
}

#[test]
fn pycocotools_fixtures_decode() {
    let got = masks::read_sam_json(&data("sam_small.json")).unwrap();
    let want = expected_masks();
    assert_eq!(got.len(), want.len());
    for (i, (m, w)) in got.iter().zip(&want).enumerate() {
        assert_eq!(m.segmentation.decode().unwrap(), *w, "mask {i}");
        // Our encoder writes pycocotools' exact string and SAM's derived fields.
        let again = SamMask::from_mask(
            w,
            m.predicted_iou,
            m.stability_score,
            m.point_coords.clone(),
        );
        assert_eq!(again, *m, "mask {i}");
    }
    let unc = masks::read_sam_json_sized(&data("sam_uncompressed.json"), Some([24, 48])).unwrap();
    assert_eq!(unc.len(), 3);
    for (i, m) in unc.iter().enumerate() {
        assert!(matches!(m.segmentation.counts, RleCounts::Uncompressed(_)));
        assert_eq!(m.segmentation.decode().unwrap(), want[i]);
        assert_eq!(m.segmentation.to_compressed().unwrap(), got[i].segmentation);
    }
}

#[test]
fn write_then_read_round_trips() {
    let dir = tmp_dir("rw");
    let got = masks::read_sam_json(&data("sam_small.json")).unwrap();
    let p = dir.join("x.json");
    masks::write_sam_json(&p, &got).unwrap();
    assert_eq!(masks::read_sam_json(&p).unwrap(), got);
    masks::write_sam_json(&p, &[]).unwrap();
    assert!(masks::read_sam_json(&p).unwrap().is_empty());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn broken_files_name_file_and_mask() {
    let e = masks::read_sam_json(&data("bad_truncated.json")).unwrap_err();
    let msg = e.to_string();
    assert!(
        matches!(
            e,
            MasksError::Rle {
                index: 2,
                err: RleError::Truncated { .. },
                ..
            }
        ),
        "{msg}"
    );
    assert!(
        msg.contains("bad_truncated.json") && msg.contains("mask 2"),
        "{msg}"
    );

    let e = masks::read_sam_json(&data("bad_size.json")).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, MasksError::Size { index: 2, .. }), "{msg}");
    assert!(
        msg.contains("bad_size.json") && msg.contains("mask 2"),
        "{msg}"
    );

    let e = masks::read_sam_json(&data("bad_area.json")).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, MasksError::Area { index: 2, .. }), "{msg}");
    assert!(
        msg.contains("bad_area.json") && msg.contains("mask 2"),
        "{msg}"
    );

    // The expected image size is checked from mask 0 on.
    let e = masks::read_sam_json_sized(&data("sam_small.json"), Some([48, 24])).unwrap_err();
    assert!(matches!(e, MasksError::Size { index: 0, .. }), "{e}");

    let dir = tmp_dir("bad");
    let p = dir.join("fields.json");
    std::fs::write(&p, r#"[{"segmentation": {"size": [1, 1], "counts": "01"}, "area": 1, "bbox": [0, 0, 0, 0], "predicted_iou": 1, "stability_score": 1}, {"area": 3}]"#).unwrap();
    let e = masks::read_sam_json(&p).unwrap_err();
    assert!(matches!(e, MasksError::Field { index: 1, .. }), "{e}");
    assert!(e.to_string().contains("fields.json"), "{e}");
    // A box value of 10³⁰⁰ is named as 1e300, not printed in 301 digits.
    std::fs::write(&p, r#"[{"segmentation": {"size": [1, 1], "counts": "01"}, "area": 1, "bbox": [1e300, 0, 0, 0], "predicted_iou": 1, "stability_score": 1}]"#).unwrap();
    let e = masks::read_sam_json(&p).unwrap_err().to_string();
    assert!(
        e.contains("fields.json") && e.contains("box value 1e300 is not an integer"),
        "{e}"
    );
    std::fs::write(&p, "{").unwrap();
    assert!(matches!(
        masks::read_sam_json(&p),
        Err(MasksError::Json { .. })
    ));
    let e = masks::read_sam_json(&dir.join("missing.json")).unwrap_err();
    assert!(e.to_string().contains("missing.json"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn two_way_cross_check_with_pycocotools() {
    if !crate::common::python_can_import(
        "sam::two_way_cross_check_with_pycocotools",
        &["pycocotools.mask", "numpy"],
    ) {
        return;
    }
    let dir = tmp_dir("xcheck");
    let mut rng = ChaCha8Rng::seed_from_u64(99);
    let (h, w) = (31usize, 46usize);
    let mut pix: Vec<u8> = Vec::new();
    let mut recs = Vec::new();
    for k in 0..60 {
        let m = match k % 5 {
            0 => Array2::from_elem((h, w), false),
            1 => Array2::from_elem((h, w), true),
            2 => {
                let mut m = Array2::from_elem((h, w), false);
                m[[rng.random_range(0..h), rng.random_range(0..w)]] = true;
                m
            }
            _ => {
                let p: f64 = rng.random();
                Array2::from_shape_fn((h, w), |_| rng.random_bool(p))
            }
        };
        pix.extend(m.iter().map(|&v| u8::from(v)));
        recs.push(SamMask::from_mask(&m, 0.9, 0.95, vec![[1.0, 2.0]]));
    }
    masks::write_sam_json(&dir.join("rust.json"), &recs).unwrap();
    gs4city::npy::write(&dir.join("rust_masks.npy"), &[recs.len(), h, w], &pix).unwrap();
    let out = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/rle_crosscheck.py"))
        .arg(&dir)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.starts_with("OK 60"),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let py = masks::read_sam_json(&dir.join("py.json")).unwrap();
    let (shape, px) = gs4city::npy::read::<u8>(&dir.join("py_masks.npy")).unwrap();
    let (ph, pw) = (shape[1], shape[2]);
    assert_eq!(shape[0], py.len());
    for (i, m) in py.iter().enumerate() {
        let want = Array2::from_shape_fn((ph, pw), |(y, x)| px[i * ph * pw + y * pw + x] != 0);
        assert_eq!(m.segmentation.decode().unwrap(), want, "python mask {i}");
        assert_eq!(Rle::encode(&want), m.segmentation, "python mask {i}");
        assert_eq!(
            m.segmentation.sam_bbox().unwrap(),
            m.bbox,
            "python mask {i}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
