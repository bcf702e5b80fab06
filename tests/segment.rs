//! `gs4city segment` (SAM-family automatic masks through ONNX Runtime) against an independent
//! NumPy implementation of automatic mask generation (`scripts/sam_amg_reference.py`, networks
//! run by the pip package onnxruntime), on a small random-weight model with SAM's signatures
//! (`scripts/make_test_models.py --size tiny`); and the errors: no model, a corrupt or wrong
//! model file, no ONNX Runtime. The Python cross-checks are skipped like every other one
//! (`common::skip`) where onnx/onnxruntime are not installed.
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use gs4city::sam;

use crate::common::python_can_import;

const PY: &[&str] = &["numpy", "onnx", "onnxruntime", "scipy", "pycocotools"];

fn root() -> PathBuf {
    let d = crate::common::temp_dir().join(format!("gs4city-segment-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Runs `python SCRIPT args --out root()/name` (a model generator) and returns the folder.
fn generate(python: &str, script: &str, args: &[&str], name: &str) -> PathBuf {
    let dir = root().join(name);
    crate::common::python_script(python, script, args, &dir);
    dir
}

/// The tiny random-weight model, generated once per test binary.
pub(crate) fn tiny_model() -> PathBuf {
    static M: OnceLock<PathBuf> = OnceLock::new();
    M.get_or_init(|| {
        let args = ["--size", "tiny", "--seed", "3"];
        generate("python3", "scripts/make_test_models.py", &args, "tiny")
    })
    .clone()
}

/// Options under which the tiny model keeps several masks and NMS keeps them all.
const NMS_OFF: [&str; 8] = [
    "--points-per-side",
    "4",
    "--pred-iou-thresh",
    "0.86",
    "--stability-score-thresh",
    "0.8",
    "--box-nms-thresh",
    "1.0",
];

/// A 330×247 test image (gradient, rectangles, a disc) as PNG in `scene/images/` and as .npy.
pub(crate) fn scene(name: &str) -> (PathBuf, PathBuf) {
    let (h, w) = (247usize, 330usize);
    let mut rgb = ndarray::Array3::<u8>::zeros((h, w, 3));
    for y in 0..h {
        for x in 0..w {
            let mut p = [(x * 255 / w) as u8, (y * 255 / h) as u8, 90];
            if (30..100).contains(&y) && (40..150).contains(&x) {
                p = [200, 40, 40];
            }
            if (125..225).contains(&y) && (175..300).contains(&x) {
                p = [30, 160, 220];
            }
            let (dx, dy) = (x as f64 - 240.0, y as f64 - 60.0);
            if dx * dx + dy * dy < 900.0 {
                p = [250, 250, 250];
            }
            rgb[[y, x, 0]] = p[0];
            rgb[[y, x, 1]] = p[1];
            rgb[[y, x, 2]] = p[2];
        }
    }
    let s = root().join(name);
    let _ = std::fs::remove_dir_all(&s);
    std::fs::create_dir_all(s.join("images")).unwrap();
    gs4city::imageio::write_png(&s.join("images/v000.png"), &rgb).unwrap();
    let npy = s.join("v000.npy");
    gs4city::npy::write(&npy, &[h, w, 3], rgb.as_slice().unwrap()).unwrap();
    (s, npy)
}

pub(crate) fn gs4city(args: &[&str], env: &[(&str, &str)]) -> std::process::Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_gs4city"));
    c.args(args);
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

/// Same masks as the NumPy reference: the same count, in the same order, each with IoU ≥ 0.99
/// (RLE decoded) and the same predicted IoU; with NMS off (every candidate that passes the
/// filters) and with NMS and small-region removal on.
#[test]
fn masks_match_the_numpy_reference() {
    const TEST: &str = "segment::masks_match_the_numpy_reference";
    if !python_can_import(TEST, PY) {
        return;
    }
    let model = tiny_model();
    for (i, opts) in [
        &NMS_OFF[..],
        &[
            "--points-per-side",
            "3",
            "--pred-iou-thresh",
            "0.8",
            "--stability-score-thresh",
            "0.6",
            "--box-nms-thresh",
            "0.7",
            "--min-mask-region-area",
            "40",
            "--scale",
            "0.5",
        ][..],
    ]
    .into_iter()
    .enumerate()
    {
        let (s, npy) = scene(&format!("ref{i}"));
        let args = segment_ok(&s, &model, opts);
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        assert_matches_reference(&s, &model, &npy, opts, &format!("config {i}"));
        // resumable: a second run skips the image and leaves its file alone
        let before = std::fs::read(s.join("masks/v000.json")).unwrap();
        let again = gs4city(&args, &[]);
        assert!(again.status.success());
        assert!(
            String::from_utf8_lossy(&again.stderr).contains("1 skipped"),
            "{}",
            String::from_utf8_lossy(&again.stderr)
        );
        assert_eq!(std::fs::read(s.join("masks/v000.json")).unwrap(), before);
    }
}

/// `gs4city segment --scene s --model model OPTS`, which must succeed; returns its arguments.
fn segment_ok(s: &Path, model: &Path, opts: &[&str]) -> Vec<String> {
    let mut args: Vec<String> = ["segment", "--scene"].map(String::from).to_vec();
    args.push(s.to_str().unwrap().into());
    args.push("--model".into());
    args.push(model.to_str().unwrap().into());
    args.extend(opts.iter().map(|o| o.to_string()));
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    let out = gs4city(&refs, &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    args
}

/// `s/masks/v000.json` against `scripts/sam_amg_reference.py` run with the same options: the
/// same mask count and order, each with IoU ≥ 0.99 (RLE decoded), the same predicted IoU and
/// stability score, the same point.
fn assert_matches_reference(s: &Path, model: &Path, npy: &Path, opts: &[&str], tag: &str) {
    let reference = s.join("reference.json");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/sam_amg_reference.py");
    let r = Command::new("python3")
        .arg(&script)
        .arg("--model")
        .arg(model)
        .arg("--image")
        .arg(npy)
        .arg("--out")
        .arg(&reference)
        .args(opts)
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let ours = sam::read_sam_json_sized(&s.join("masks/v000.json"), Some([247, 330])).unwrap();
    let theirs = sam::read_sam_json_sized(&reference, Some([247, 330])).unwrap();
    assert!(
        !ours.is_empty(),
        "{tag}: no masks: the test would prove nothing"
    );
    assert_eq!(ours.len(), theirs.len(), "{tag}: mask counts differ");
    for (k, (a, b)) in ours.iter().zip(&theirs).enumerate() {
        let (ma, mb) = (
            a.segmentation.decode().unwrap(),
            b.segmentation.decode().unwrap(),
        );
        let inter = ma.iter().zip(mb.iter()).filter(|(x, y)| **x && **y).count();
        let union = ma.iter().zip(mb.iter()).filter(|(x, y)| **x || **y).count();
        let iou = inter as f64 / union.max(1) as f64;
        assert!(iou >= 0.99, "{tag} mask {k}: IoU {iou}");
        assert!(
            (a.predicted_iou - b.predicted_iou).abs() < 1e-3,
            "{tag} mask {k}"
        );
        assert!(
            (a.stability_score - b.stability_score).abs() < 0.01,
            "{tag} mask {k}"
        );
        assert_eq!(a.point_coords, b.point_coords, "{tag} mask {k}");
    }
}

/// A decoder with a fixed batch of 1 (as SAM's own export: one prompt per call) is decoded by
/// single-threaded workers side by side: the masks file is byte-identical for 1 and 3 workers
/// and matches the NumPy reference decoding one prompt per call.
#[test]
fn a_fixed_batch_decoder_gives_the_same_masks_on_any_number_of_workers() {
    const TEST: &str =
        "segment::a_fixed_batch_decoder_gives_the_same_masks_on_any_number_of_workers";
    if !python_can_import(TEST, PY) {
        return;
    }
    let args = ["--size", "tiny", "--seed", "3", "--fixed-batch"];
    let model = generate(
        "python3",
        "scripts/make_test_models.py",
        &args,
        "tiny-fixed-batch",
    );
    let opts = NMS_OFF;
    let mut files = Vec::new();
    for threads in ["1", "3"] {
        let (s, npy) = scene(&format!("fixed{threads}"));
        let mut with_threads = opts.to_vec();
        with_threads.extend_from_slice(&["--threads", threads]);
        segment_ok(&s, &model, &with_threads);
        files.push(std::fs::read(s.join("masks/v000.json")).unwrap());
        if threads == "3" {
            let mut ref_opts = opts.to_vec();
            ref_opts.extend_from_slice(&["--points-per-batch", "1"]);
            assert_matches_reference(&s, &model, &npy, &ref_opts, "fixed batch, 3 workers");
        }
    }
    assert!(
        files[0] == files[1],
        "the masks depend on the number of workers"
    );
}

/// SAM's own exports (not generated by us): `scripts/export_sam_model.py --random-init` builds
/// SAM ViT-B with segment-anything's own code and exports its encoder and its decoder as
/// segment-anything's export script does (batch 1, 1 148 nodes); `segment` (decoder pruned,
/// workers) matches the NumPy reference on them. Ignored by default: it needs torch and
/// segment-anything (several GB), which CI does not install. Run it with
/// `GS4CITY_TORCH_PYTHON=/path/to/venv/bin/python cargo test --release --test tests
/// segment::sams_own_export -- --ignored` (the reference itself runs on `python3`).
#[test]
#[ignore = "needs torch + segment-anything; see the doc comment for the command"]
fn sams_own_export_matches_the_reference() {
    let python = std::env::var("GS4CITY_TORCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let args = ["--model-type", "vit_b", "--random-init"];
    let model = generate(
        &python,
        "scripts/export_sam_model.py",
        &args,
        "sam-vit-b-export",
    );
    let (s, npy) = scene("sam-export");
    let opts = [
        "--points-per-side",
        "6",
        "--pred-iou-thresh",
        "0.0",
        "--stability-score-thresh",
        "0.0",
        "--box-nms-thresh",
        "1.0",
    ];
    segment_ok(&s, &model, &opts);
    let mut ref_opts = opts.to_vec();
    ref_opts.extend_from_slice(&["--points-per-batch", "1"]);
    assert_matches_reference(&s, &model, &npy, &ref_opts, "SAM's own export");
}

/// No model folder content: one line naming the expected files and where the weights are.
#[test]
fn no_model_names_the_expected_files() {
    let (s, _) = scene("nomodel");
    let empty = root().join("empty-model");
    std::fs::create_dir_all(&empty).unwrap();
    let out = gs4city(
        &[
            "segment",
            "--scene",
            s.to_str().unwrap(),
            "--model",
            empty.to_str().unwrap(),
        ],
        &[],
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    for want in [
        "encoder.onnx, decoder.onnx, model.json missing",
        "segment-anything",
        "MobileSAM",
        "docs/segment.md",
    ] {
        assert!(err.contains(want), "{want} not in: {err}");
    }
    assert!(!s.join("masks/v000.json").exists());
}

/// No ONNX Runtime (ORT_DYLIB_PATH to a missing file, or to a file that is no library): one
/// clear line, no panic.
#[test]
fn missing_runtime_is_one_clear_line() {
    let (s, _) = scene("noruntime");
    let m = root().join("garbage-model");
    std::fs::create_dir_all(&m).unwrap();
    for f in ["encoder.onnx", "decoder.onnx", "model.json"] {
        std::fs::write(m.join(f), b"{\"family\": \"sam\"}").unwrap();
    }
    let args = [
        "segment",
        "--scene",
        s.to_str().unwrap(),
        "--model",
        m.to_str().unwrap(),
    ];
    let out = gs4city(
        &args,
        &[("ORT_DYLIB_PATH", "/nonexistent/libonnxruntime.so")],
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("ORT_DYLIB_PATH=/nonexistent/libonnxruntime.so is not a file"),
        "{err}"
    );
    let not_lib = m.join("model.json");
    let out = gs4city(&args, &[("ORT_DYLIB_PATH", not_lib.to_str().unwrap())]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("cannot load ONNX Runtime from") && !err.contains("panicked"),
        "{err}"
    );
}

/// A corrupt encoder and a decoder that is no SAM decoder: each error names its file.
#[test]
fn corrupt_or_wrong_model_file_is_named() {
    const TEST: &str = "segment::corrupt_or_wrong_model_file_is_named";
    if !python_can_import(TEST, PY) {
        return;
    }
    let model = tiny_model();
    let (s, _) = scene("corrupt");
    let bad = root().join("corrupt-model");
    std::fs::create_dir_all(&bad).unwrap();
    for f in ["encoder.onnx", "decoder.onnx", "model.json"] {
        std::fs::copy(model.join(f), bad.join(f)).unwrap();
    }
    let enc = std::fs::read(model.join("encoder.onnx")).unwrap();
    std::fs::write(bad.join("encoder.onnx"), &enc[..enc.len() / 3]).unwrap();
    let args = [
        "segment",
        "--scene",
        s.to_str().unwrap(),
        "--model",
        bad.to_str().unwrap(),
    ];
    let out = gs4city(&args, &[]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "model file {}",
            bad.join("encoder.onnx").display()
        )),
        "{err}"
    );
    // the encoder where the decoder belongs
    std::fs::copy(model.join("encoder.onnx"), bad.join("encoder.onnx")).unwrap();
    std::fs::copy(model.join("encoder.onnx"), bad.join("decoder.onnx")).unwrap();
    let out = gs4city(&args, &[]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "model file {}",
            bad.join("decoder.onnx").display()
        )) && err.contains("has no input `image_embeddings`"),
        "{err}"
    );
    // a model.json that is no JSON object
    std::fs::copy(model.join("decoder.onnx"), bad.join("decoder.onnx")).unwrap();
    std::fs::write(bad.join("model.json"), b"[1, 2").unwrap();
    let out = gs4city(&args, &[]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("model.json"), "{err}");
    // a truncated decoder: the pruning cannot read it either, and the file is named
    std::fs::copy(model.join("model.json"), bad.join("model.json")).unwrap();
    let dec = std::fs::read(model.join("decoder.onnx")).unwrap();
    std::fs::write(bad.join("decoder.onnx"), &dec[..dec.len() / 2]).unwrap();
    let out = gs4city(&args, &[]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "model file {}",
            bad.join("decoder.onnx").display()
        )),
        "{err}"
    );
    assert!(!s.join("masks/v000.json").exists());
}

/// Pseudo-random values in [−1, 1) from a 64-bit linear congruential generator: test inputs
/// independent of the code under test.
fn lcg(seed: u64) -> impl FnMut() -> f32 {
    let mut state = seed;
    move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }
}

/// The inputs of SAM's decoder export for `b` prompts (no mask prompt).
fn decoder_inputs(
    path: &Path,
    emb: &[f32],
    coords: Vec<f32>,
    labels: Vec<f32>,
    b: usize,
) -> Vec<(&'static str, ort::value::DynValue)> {
    use gs4city::segment::model::tensor;
    let n = labels.len() / b;
    vec![
        (
            "image_embeddings",
            tensor(&[1, 256, 64, 64], emb.to_vec(), path)
                .unwrap()
                .into_dyn(),
        ),
        (
            "point_coords",
            tensor(&[b, n, 2], coords, path).unwrap().into_dyn(),
        ),
        (
            "point_labels",
            tensor(&[b, n], labels, path).unwrap().into_dyn(),
        ),
        (
            "mask_input",
            tensor(&[1, 1, 256, 256], vec![0.0; 256 * 256], path)
                .unwrap()
                .into_dyn(),
        ),
        (
            "has_mask_input",
            tensor(&[1], vec![0.0], path).unwrap().into_dyn(),
        ),
        (
            "orig_im_size",
            tensor(&[2], vec![247.0, 330.0], path).unwrap().into_dyn(),
        ),
    ]
}

/// The decoder without SAM's `masks` tail (`onnxproto::keep_outputs`, what `segment` loads)
/// gives `iou_predictions` and `low_res_masks` bit for bit as the whole graph does, for the
/// same inputs, and has fewer nodes; ONNX Runtime runs both.
#[test]
fn the_pruned_decoder_gives_the_same_outputs_bit_for_bit() {
    const TEST: &str = "segment::the_pruned_decoder_gives_the_same_outputs_bit_for_bit";
    if !python_can_import(TEST, PY) {
        return;
    }
    use gs4city::segment::model;
    let path = tiny_model().join("decoder.onnx");
    let bytes = std::fs::read(&path).unwrap();
    let (pruned, dropped) =
        gs4city::onnxproto::keep_outputs(&bytes, &["iou_predictions", "low_res_masks"]).unwrap();
    assert_eq!(dropped, vec!["masks".to_string()]);
    assert!(pruned.len() < bytes.len());
    let mut whole = model::open_session(&path, 1).unwrap();
    let mut cut = model::open_session_from(&path, Some(&pruned), 1).unwrap();
    let names = |s: &ort::session::Session| -> Vec<String> {
        s.outputs().iter().map(|o| o.name().to_string()).collect()
    };
    assert_eq!(names(&whole), ["masks", "iou_predictions", "low_res_masks"]);
    assert_eq!(names(&cut), ["iou_predictions", "low_res_masks"]);
    // inputs independent of the code under test: a fixed pseudo-random embedding and prompts
    let b = 5usize;
    let mut next = lcg(12345);
    let emb: Vec<f32> = (0..256 * 64 * 64).map(|_| next()).collect();
    let coords: Vec<f32> = (0..b * 4).map(|_| (next() + 1.0) * 500.0).collect();
    let labels: Vec<f32> = (0..b).flat_map(|_| [1.0, -1.0]).collect();
    let mut outputs = Vec::new();
    for session in [&mut whole, &mut cut] {
        let inputs = decoder_inputs(&path, &emb, coords.clone(), labels.clone(), b);
        let out = session.run(inputs).unwrap();
        let get = |n: &str| -> Vec<u32> {
            let (_, v) = out[n].try_extract_tensor::<f32>().unwrap();
            v.iter().map(|x| x.to_bits()).collect()
        };
        outputs.push((get("iou_predictions"), get("low_res_masks")));
    }
    assert_eq!(outputs[0].0.len(), b * 4);
    assert_eq!(outputs[0].1.len(), b * 4 * 256 * 256);
    assert!(outputs[0].1.iter().any(|&x| x != 0));
    assert!(
        outputs[0] == outputs[1],
        "the pruned decoder's outputs differ"
    );
}

/// `gs4city run --model-dir`: a scene without masks (SIMULATED synth small preset, its masks/
/// and features/ removed) is segmented first — every image gets masks/<stem>.json in the SAM
/// format the masks stage reads — and the whole pipeline runs on those masks.
#[test]
fn run_with_a_model_segments_a_scene_without_masks() {
    const TEST: &str = "segment::run_with_a_model_segments_a_scene_without_masks";
    if !python_can_import(TEST, PY) {
        return;
    }
    let model = tiny_model();
    let dir = root().join("run");
    let (s, r, out) = run_without_masks(&dir, &model);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let images = gs4city::segment::list_images(&s.join("images")).unwrap();
    assert_eq!(images.len(), 3);
    for img in &images {
        let f = gs4city::segment::mask_path(&s.join("masks"), img);
        sam::read_sam_json_sized(&f, Some([247, 330])).unwrap();
    }
    assert!(r.join("masks").is_dir() && r.join("lift/gaussians.npy").is_file());
    let _ = std::fs::remove_dir_all(&dir);
}

/// `gs4city run --model-dir MODEL` on a SIMULATED scene (synth small preset, 3 orbit views of
/// 330×247) whose masks/ and features/ are removed, in `dir`: (scene, run folder, the output).
pub(crate) fn run_without_masks(
    dir: &Path,
    model: &Path,
) -> (PathBuf, PathBuf, std::process::Output) {
    let _ = std::fs::remove_dir_all(dir);
    let mut cfg = gs4city::synth::SynthConfig::preset(gs4city::synth::Preset::Small);
    cfg.cameras.orbit_views = 3;
    cfg.cameras.street_views = 0;
    cfg.cameras.width = 330;
    cfg.cameras.height = 247;
    let s = dir.join("scene");
    gs4city::synth::run(&cfg, &s).unwrap();
    std::fs::remove_dir_all(s.join("masks")).unwrap();
    let _ = std::fs::remove_dir_all(s.join("features"));
    let r = dir.join("out");
    let out = gs4city(
        &[
            "run",
            "--scene",
            s.to_str().unwrap(),
            "--out",
            r.to_str().unwrap(),
            "--model-dir",
            model.to_str().unwrap(),
            "--segment-points-per-side",
            "4",
            "--test-every",
            "3",
        ],
        &[],
    );
    (s, r, out)
}

/// SAM's decoder computed natively from the export's weights (`segment::native`) gives the
/// export's outputs as ONNX Runtime computes them from the graph: every predicted IoU and
/// every low-resolution logit of every mask, for prompts of one or two points (foreground,
/// background and padding labels) on a pseudo-random embedding, and on one whose tokens'
/// channels share a large offset; with one and with three
/// two-way transformer layers (the upscaling is unrolled through each layer's LayerNorm).
#[test]
fn the_native_decoder_computes_the_exports_outputs() {
    const TEST: &str = "segment::the_native_decoder_computes_the_exports_outputs";
    if !python_can_import(TEST, PY) {
        return;
    }
    for depth in ["1", "3"] {
        let dir = generate(
            "python3",
            "scripts/make_test_models.py",
            &["--size", "tiny", "--seed", "5", "--decoder-depth", depth],
            &format!("native-depth{depth}"),
        );
        native_against_onnx_runtime(&dir.join("decoder.onnx"), &format!("depth {depth}"), 4);
    }
}

/// The same at SAM's real decoder shape (`make_test_models.py --size vit_b`: 256-dim tokens,
/// 8 heads, two two-way layers with attention downsampling 2, MLP 2048, 3 + 1 masks, the
/// upscaling 256 → 64 → 32 channels), random weights: the native decoder reproduces ONNX
/// Runtime there too, not only at the tiny test shape.
#[test]
fn the_native_decoder_computes_the_exports_outputs_at_sams_real_shape() {
    const TEST: &str =
        "segment::the_native_decoder_computes_the_exports_outputs_at_sams_real_shape";
    if !python_can_import(TEST, PY) {
        return;
    }
    let dir = generate(
        "python3",
        "scripts/make_test_models.py",
        &["--size", "vit_b", "--seed", "5", "--decoder-only"],
        "native-vit-b",
    );
    native_against_onnx_runtime(&dir.join("decoder.onnx"), "SAM shape", 4);
}

/// Decodes five prompts (four label sets on a pseudo-random embedding, the first again on the
/// embedding with an offset of 40 on every channel) natively and with ONNX Runtime, and checks
/// every IoU within 10⁻⁴ and every low-resolution logit within 2·10⁻⁵ (10⁻⁴ with the offset)
/// of the largest; `masks` is the decoder's outputs per prompt.
fn native_against_onnx_runtime(path: &Path, what: &str, masks: usize) {
    use gs4city::segment::{model, native};
    let graph = gs4city::onnxproto::read_graph(&std::fs::read(path).unwrap()).unwrap();
    let dec = native::SamDecoder::from_graph(&graph).unwrap();
    assert_eq!(dec.masks(), masks, "{what}: masks per prompt");
    let mut session = model::open_session(path, 1).unwrap();
    let mut next = lcg(777);
    let emb: Vec<f32> = (0..256 * 64 * 64).map(|_| 1.5 * next()).collect();
    // the same with a common offset of 40 on every channel of every token: each row's
    // mean is 25× its spread, which the LayerNorms' centring must remove
    let offset: Vec<f32> = emb.iter().map(|v| v + 40.0).collect();
    let labels = [[1.0f32, -1.0], [0.0, -1.0], [1.0, 0.0], [1.0, 1.0]];
    // each embedding prepared once (the per-image work of the native decoder)
    let (prep_plain, prep_offset) = (dec.prepare(&emb), dec.prepare(&offset));
    for (k, (emb, labels)) in [&emb, &emb, &emb, &emb, &offset]
        .into_iter()
        .zip(labels.iter().chain(&labels[..1]))
        .enumerate()
    {
        let prep = if std::ptr::eq(emb, &offset) {
            &prep_offset
        } else {
            &prep_plain
        };
        let pts: Vec<[f32; 2]> = (0..2)
            .map(|_| [(next() + 1.0) * 511.0, (next() + 1.0) * 511.0])
            .collect();
        let coords: Vec<f32> = pts.iter().flatten().copied().collect();
        let inputs = decoder_inputs(path, emb, coords, labels.to_vec(), 1);
        let out = session.run(inputs).unwrap();
        let (_, iou) = out["iou_predictions"].try_extract_tensor::<f32>().unwrap();
        let (_, low) = out["low_res_masks"].try_extract_tensor::<f32>().unwrap();
        let d = dec.decode(prep, &pts, labels);
        let all: Vec<usize> = (0..dec.masks()).collect();
        let ours = dec.low_res(prep, &d, &all);
        assert_eq!(d.iou.len(), iou.len());
        assert_eq!(
            ours.len() * 256 * 256,
            low.len(),
            "{what}: low-resolution masks"
        );
        let scale = low.iter().fold(1f32, |m, v| m.max(v.abs()));
        for (a, b) in d.iou.iter().zip(iou.iter()) {
            assert!((a - b).abs() <= 1e-4, "{what} prompt {k}: IoU {a} vs {b}");
        }
        let worst = ours
            .iter()
            .flatten()
            .zip(low.iter())
            .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        // with the offset, both sides round values of 40 where the rows' spread is ≈ 1
        // (f32: ≈ 2.4·10⁻⁶ each), so the bound is 5× looser there
        let tol = if std::ptr::eq(emb, &offset) {
            1e-4
        } else {
            2e-5
        };
        assert!(
            worst <= tol * scale,
            "{what} prompt {k}: logits differ by {worst} (largest {scale})"
        );
        // the logits are not all alike (the comparison would prove little)
        let (lo, hi) = low
            .iter()
            .fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        assert!(hi - lo > 1.0, "{what} prompt {k}: logits {lo}..{hi}");
        eprintln!("{what} prompt {k}: max |Δ logit| {worst:.2e} of {scale:.2e}");
    }
}

/// A decoder the native path does not reproduce (its token MLP's ReLU swapped for a sigmoid:
/// the weights are all found, the probe against ONNX Runtime disagrees) is decoded by ONNX
/// Runtime, and the command says so; `--onnx-decoder` forces ONNX Runtime, with the same masks
/// as the native decoder.
#[test]
fn a_decoder_the_native_path_does_not_reproduce_stays_on_onnx_runtime() {
    const TEST: &str =
        "segment::a_decoder_the_native_path_does_not_reproduce_stays_on_onnx_runtime";
    if !python_can_import(TEST, PY) {
        return;
    }
    let model = tiny_model();
    let odd = root().join("odd-decoder");
    std::fs::create_dir_all(&odd).unwrap();
    for f in ["encoder.onnx", "model.json"] {
        std::fs::copy(model.join(f), odd.join(f)).unwrap();
    }
    let py = format!(
        "import onnx\nm = onnx.load('{}')\nn = [n for n in m.graph.node if n.op_type == 'Relu'][0]\nn.op_type = 'Sigmoid'\nonnx.save(m, '{}')\n",
        model.join("decoder.onnx").display(),
        odd.join("decoder.onnx").display()
    );
    let r = Command::new("python3").args(["-c", &py]).output().unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let run = |m: &Path, extra: &[&str], name: &str| -> String {
        let (s, _) = scene(name);
        let mut args = vec![
            "segment".to_string(),
            "--scene".into(),
            s.to_str().unwrap().into(),
            "--model".into(),
            m.to_str().unwrap().into(),
        ];
        args.extend(NMS_OFF.iter().map(|o| o.to_string()));
        args.extend(extra.iter().map(|o| o.to_string()));
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let out = gs4city(&refs, &[]);
        let err = String::from_utf8_lossy(&out.stderr).to_string();
        assert!(out.status.success(), "{err}");
        err
    };
    let err = run(&odd, &[], "odd");
    assert!(
        err.contains("onnxruntime (the native decoder differs from the export"),
        "{err}"
    );
    let err = run(&model, &[], "native");
    assert!(err.contains("(native)"), "{err}");
    let err = run(&model, &["--onnx-decoder"], "onnx");
    assert!(err.contains("onnxruntime (ONNX Runtime asked for"), "{err}");
    let a = sam::read_sam_json_sized(&root().join("native/masks/v000.json"), Some([247, 330]));
    let b = sam::read_sam_json_sized(&root().join("onnx/masks/v000.json"), Some([247, 330]));
    let (a, b) = (a.unwrap(), b.unwrap());
    assert!(!a.is_empty());
    assert_eq!(
        a.len(),
        b.len(),
        "native and ONNX Runtime keep different masks"
    );
    for (x, y) in a.iter().zip(&b) {
        let (mx, my) = (
            x.segmentation.decode().unwrap(),
            y.segmentation.decode().unwrap(),
        );
        let inter = mx.iter().zip(my.iter()).filter(|(p, q)| **p && **q).count();
        let union = mx.iter().zip(my.iter()).filter(|(p, q)| **p || **q).count();
        assert!(inter as f64 / union.max(1) as f64 >= 0.99);
    }
}
