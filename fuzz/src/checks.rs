//! What each fuzz target does with one input, shared with the regression test
//! (`tests/hardening.rs` includes this file by path and replays `tests/data/bad/<reader>/`).
//!
//! Each function runs a reader on `data` and checks properties that must hold for any input:
//! no panic, and where the reader accepts the input, that what it returns is consistent (a
//! round trip through the writer gives the same value, both decoding paths agree, the
//! cameras pass `Camera::validate`). It returns the reader's error message when the input
//! was refused, so that callers can check the message too.
use std::path::Path;

use gs4city::alignment::{self as align, Alignment};
use gs4city::mesh::TriMesh;
use gs4city::semantics;
use gs4city::splat::{InvalidPolicy, ReadOptions, read_ply_bytes};
use gs4city::{citygml, citymodel, colmap, npy, sam, selection};

/// The readers, by fuzz-target name.
pub const READERS: [&str; 10] = [
    "citygml",
    "citymodel",
    "where",
    "ply_splat",
    "ply_mesh",
    "colmap_bin",
    "colmap_txt",
    "sam",
    "npy",
    "align",
];

/// Runs the check of reader `name` (one of [`READERS`]).
pub fn run(name: &str, data: &[u8]) -> Option<String> {
    match name {
        "citygml" => citygml(data),
        "citymodel" => citymodel_triangles(data),
        "where" => where_expr(data),
        "ply_splat" => ply_splat(data),
        "ply_mesh" => ply_mesh(data),
        "colmap_bin" => colmap_model(data, true),
        "colmap_txt" => colmap_model(data, false),
        "sam" => sam_json(data),
        "npy" => npy_all(data),
        "align" => align_json(data),
        other => panic!("unknown reader {other}"),
    }
}

/// Splits `data` into two parts at a length given by its first two bytes (little-endian),
/// for readers of two files at once (COLMAP cameras + images).
pub fn split2(data: &[u8]) -> (&[u8], &[u8]) {
    if data.len() < 2 {
        return (data, &[]);
    }
    let n = u16::from_le_bytes([data[0], data[1]]) as usize;
    let rest = &data[2..];
    rest.split_at(n.min(rest.len()))
}

/// CityGML: a model or one error.
pub fn citygml(data: &[u8]) -> Option<String> {
    citygml::read_bytes(Path::new("fuzz.gml"), data)
        .err()
        .map(|e| e.to_string())
}

/// 3DGS PLY: both decoding paths agree; both invalid-value policies run.
pub fn ply_splat(data: &[u8]) -> Option<String> {
    let p = Path::new("fuzz.ply");
    let fast = read_ply_bytes(p, data, &ReadOptions::default());
    let general = read_ply_bytes(
        p,
        data,
        &ReadOptions {
            force_general_path: true,
            ..Default::default()
        },
    );
    match (&fast, &general) {
        // Debug text compares NaN extras as equal, bit patterns otherwise.
        (Ok((a, _)), Ok((b, _))) => {
            assert_eq!(
                format!("{a:?}"),
                format!("{b:?}"),
                "decoding paths disagree"
            )
        }
        (Err(a), Err(b)) => assert_eq!(a.to_string(), b.to_string(), "different errors"),
        _ => panic!("one decoding path accepted what the other refused"),
    }
    let _ = read_ply_bytes(
        p,
        data,
        &ReadOptions {
            invalid: InvalidPolicy::Drop,
            ..Default::default()
        },
    );
    fast.err().map(|e| e.to_string())
}

/// mesh.ply: an accepted mesh survives write → read unchanged.
pub fn ply_mesh(data: &[u8]) -> Option<String> {
    let p = Path::new("fuzz.ply");
    match TriMesh::from_ply_bytes(p, data) {
        Ok(m) => {
            let back = TriMesh::from_ply_bytes(p, &m.to_ply_bytes()).expect("written mesh reads");
            assert_eq!(back, m);
            let _ = m.check_label_range(16);
            None
        }
        Err(e) => Some(e.to_string()),
    }
}

/// COLMAP cameras + images (split by [`split2`]) and the same bytes as points3D: every
/// returned camera passes `Camera::validate`.
pub fn colmap_model(data: &[u8], binary: bool) -> Option<String> {
    let (cams, imgs) = split2(data);
    let ext = if binary { "bin" } else { "txt" };
    let cam_path = format!("cameras.{ext}");
    let img_path = format!("images.{ext}");
    let model = colmap::parse_model(
        Path::new(&cam_path),
        cams,
        Path::new(&img_path),
        imgs,
        binary,
    );
    let _ = colmap::parse_points(Path::new(&format!("points3D.{ext}")), data, binary);
    match model {
        Ok(views) => {
            for v in &views {
                v.camera
                    .validate()
                    .expect("the reader returns only valid cameras");
            }
            None
        }
        Err(e) => Some(e.to_string()),
    }
}

/// SAM masks and prompts: an accepted mask's counts survive compress → decompress, and a
/// small one decodes to its stated area.
pub fn sam_json(data: &[u8]) -> Option<String> {
    let p = Path::new("fuzz.json");
    if let Ok(s) = std::str::from_utf8(data) {
        let _ = sam::counts_from_string(s);
    }
    let _ = sam::parse_prompts_json(p, data);
    match sam::parse_sam_json(p, data, None) {
        Ok(masks) => {
            for m in &masks {
                let rle = &m.segmentation;
                let counts = rle.counts().expect("validated on reading");
                let back = sam::counts_from_string(&sam::counts_to_string(&counts)).unwrap();
                assert_eq!(back, counts);
                if rle.size[0] * rle.size[1] <= 1 << 16 {
                    let mask = rle.decode().unwrap();
                    assert_eq!(mask.iter().filter(|&&b| b).count() as u64, m.area);
                    rle.sam_bbox().unwrap();
                }
            }
            None
        }
        Err(e) => Some(e.to_string()),
    }
}

fn npy_one<T: npy::NpyElement + std::fmt::Debug>(data: &[u8]) -> Option<String> {
    let p = Path::new("fuzz.npy");
    match npy::decode::<T>(p, data) {
        Ok((shape, v)) => {
            let (s2, v2) = npy::decode::<T>(p, &npy::encode(&shape, &v)).unwrap();
            assert_eq!(s2, shape);
            assert_eq!(format!("{v2:?}"), format!("{v:?}"));
            None
        }
        Err(e) => Some(e.to_string()),
    }
}

/// .npy for every element type; an accepted array re-encodes to the same values. Returns
/// `None` when some element type accepts the file, else the `float32` reading's error.
pub fn npy_all(data: &[u8]) -> Option<String> {
    let others = [
        npy_one::<i32>(data),
        npy_one::<u8>(data),
        npy_one::<u16>(data),
        npy_one::<f64>(data),
        npy_one::<i64>(data),
        npy_one::<u32>(data),
    ];
    let f32_answer = npy_one::<f32>(data);
    if others.iter().any(Option::is_none) {
        return None;
    }
    f32_answer
}

/// alignment.json (round trip), point pairs (+ estimation) and semantics.json. Returns the
/// alignment reading's error.
pub fn align_json(data: &[u8]) -> Option<String> {
    let Ok(text) = std::str::from_utf8(data) else {
        return Some("not UTF-8".into());
    };
    if let Ok(pairs) = align::parse_pairs(Path::new("pairs.csv"), text)
        && pairs.len() <= 1000
        && let Ok(est) = align::estimate(Path::new("pairs.csv"), &pairs)
    {
        assert!(est.rms.is_finite() && est.alignment.scale > 0.0);
    }
    let _ = semantics::parse(Path::new("semantics.json"), text);
    match Alignment::from_json_str(Path::new("alignment.json"), text) {
        Ok(a) => {
            let back = Alignment::from_json_str(Path::new("a.json"), &a.to_json().to_string())
                .expect("a written alignment reads back");
            assert_eq!(back, a);
            None
        }
        Err(e) => Some(e.to_string()),
    }
}

/// CityGML read, then every polygon triangulated as the citymodel stage does (after the
/// reader, where spade's assertions and our ring repairs run): a model whose triangulated
/// polygons have a finite, non-negative area and at least one triangle, or the reader's error.
pub fn citymodel_triangles(data: &[u8]) -> Option<String> {
    let model = match citygml::read_bytes(Path::new("fuzz.gml"), data) {
        Ok(m) => m,
        Err(e) => return Some(e.to_string()),
    };
    for p in citymodel::triangulate_all(&model) {
        if let Ok((triangles, area)) = p.result {
            assert!(triangles > 0, "polygon {:?}: no triangles", p.id);
            assert!(
                area.is_finite() && area >= 0.0,
                "polygon {:?}: area {area}",
                p.id
            );
        }
    }
    None
}

/// A selection expression (`--where`, the viewer's query box): parsed, or one error with a
/// column; an accepted expression prints as text that parses back to the same tree.
pub fn where_expr(data: &[u8]) -> Option<String> {
    let Ok(text) = std::str::from_utf8(data) else {
        return Some("not UTF-8".into());
    };
    match selection::grammar::parse(text) {
        Ok(e) => {
            let again = selection::grammar::parse(&e.to_string())
                .unwrap_or_else(|err| panic!("`{e}` does not parse back: {err}"));
            assert_eq!(again.to_string(), e.to_string());
            None
        }
        Err(e) => Some(e.to_string()),
    }
}
