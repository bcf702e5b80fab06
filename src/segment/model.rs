//! The SAM-family model folder and ONNX Runtime.
//!
//! ONNX Runtime is loaded at run time (`ort` with `load-dynamic`): from `ORT_DYLIB_PATH`, else
//! the `libonnxruntime.so.*` that the pip package `onnxruntime` ships (found through
//! `python3 -c 'import onnxruntime'`). Nothing else of gs4city needs it.
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::Tensor;

use super::SegmentError;

/// Where the published weights are and how a model folder is laid out (part of the
/// no-weights error).
pub const LAYOUT_HELP: &str = "a SAM-family model folder holds encoder.onnx (image [1,3,1024,1024], SAM-normalised and zero-padded → image_embeddings [1,256,64,64]), decoder.onnx (SAM's ONNX export, segment_anything/scripts/export_onnx_model.py without --return-single-mask: image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size → masks, iou_predictions, low_res_masks) and model.json ({\"family\": \"sam\"|\"mobile_sam\"|…}); the published weights are SAM's ViT-B/L/H checkpoints (github.com/facebookresearch/segment-anything) and MobileSAM's mobile_sam.pt (github.com/ChaoningZhang/MobileSAM); export both networks to ONNX with the gs4city repository's scripts/export_sam_model.py --checkpoint FILE --model-type vit_b|vit_l|vit_h|vit_t --out DIR (needs torch; docs/segment.md)";

/// `model.json` of a model folder.
#[derive(Debug, Clone, serde::Deserialize, serde::Serialize)]
pub struct ModelInfo {
    /// `sam`, `mobile_sam`, … (informational; the graphs define the computation).
    pub family: String,
    /// `vit_b`, `vit_h`, … (informational).
    #[serde(default)]
    pub size: Option<String>,
}

static RUNTIME: OnceLock<Result<ort::environment::Environment, String>> = OnceLock::new();

/// The ONNX Runtime library: `ORT_DYLIB_PATH`, else the pip package's `capi/libonnxruntime.so*`.
pub fn find_runtime() -> Result<PathBuf, SegmentError> {
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        let p = PathBuf::from(p);
        if !p.is_file() {
            return Err(SegmentError::Runtime(format!(
                "ORT_DYLIB_PATH={} is not a file",
                p.display()
            )));
        }
        return Ok(p);
    }
    let missing = || {
        SegmentError::Runtime(
            "ONNX Runtime is not installed: `python3 -m pip install onnxruntime` (scripts/setup.sh does), or set ORT_DYLIB_PATH to a libonnxruntime.so".into(),
        )
    };
    let out = std::process::Command::new("python3")
        .args([
            "-c",
            "import os, onnxruntime; print(os.path.dirname(onnxruntime.__file__))",
        ])
        .stderr(std::process::Stdio::null())
        .output()
        .map_err(|_| missing())?;
    if !out.status.success() {
        return Err(missing());
    }
    let capi = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim()).join("capi");
    let mut libs: Vec<PathBuf> = std::fs::read_dir(&capi)
        .map_err(|_| missing())?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("libonnxruntime.so"))
        })
        .collect();
    libs.sort();
    libs.into_iter().next().ok_or_else(missing)
}

/// Loads ONNX Runtime once per process.
fn environment() -> Result<&'static ort::environment::Environment, SegmentError> {
    let env = RUNTIME.get_or_init(|| {
        let path = find_runtime().map_err(|e| e.to_string())?;
        let builder = ort::init_from(&path)
            .map_err(|e| format!("cannot load ONNX Runtime from {}: {e}", path.display()))?;
        builder
            .with_name("gs4city")
            .build()
            .map_err(|e| format!("cannot start ONNX Runtime ({}): {e}", path.display()))
    });
    env.as_ref()
        .map_err(|e| SegmentError::Runtime(e.trim_start_matches("ONNX Runtime ").to_string()))
}

/// Opens one ONNX file on `threads` intra-op threads (0 = ONNX Runtime's choice).
pub fn open_session(path: &Path, threads: usize) -> Result<Session, SegmentError> {
    open_session_from(path, None, threads)
}

/// Opens the ONNX file `path`, or, given `bytes`, that model in memory (errors still name
/// `path`), on `threads` intra-op threads (0 = ONNX Runtime's choice).
pub fn open_session_from(
    path: &Path,
    bytes: Option<&[u8]>,
    threads: usize,
) -> Result<Session, SegmentError> {
    let env = environment()?;
    let bad = |e: ort::Error| SegmentError::Model {
        path: path.to_path_buf(),
        why: e.to_string().replace('\n', " "),
    };
    let builder = Session::builder(env)
        .map_err(bad)?
        .with_optimization_level(GraphOptimizationLevel::Level3)
        .map_err(|e| bad(e.into()))?
        .with_intra_threads(threads)
        .map_err(|e| bad(e.into()))?
        // no busy-waiting between operators: the CPU goes to whoever else runs
        .with_intra_op_spinning(false)
        .map_err(|e| bad(e.into()))?;
    let mut builder = builder;
    match bytes {
        Some(b) => builder.commit_from_memory(b).map_err(bad),
        None => builder.commit_from_file(path).map_err(bad),
    }
}

/// The declared shape of input `name` (`-1` = dynamic), or an error naming the file.
pub fn input_shape(session: &Session, path: &Path, name: &str) -> Result<Vec<i64>, SegmentError> {
    let outlet = session
        .inputs()
        .iter()
        .find(|o| o.name() == name)
        .ok_or_else(|| SegmentError::Model {
            path: path.to_path_buf(),
            why: format!(
                "has no input `{name}` (its inputs: {})",
                session
                    .inputs()
                    .iter()
                    .map(|o| o.name().to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        })?;
    let shape = outlet
        .dtype()
        .tensor_shape()
        .ok_or_else(|| SegmentError::Model {
            path: path.to_path_buf(),
            why: format!("input `{name}` is not a tensor"),
        })?;
    Ok(shape.iter().copied().collect())
}

/// Checks that `session` has every named output.
pub fn require_outputs(session: &Session, path: &Path, names: &[&str]) -> Result<(), SegmentError> {
    for name in names {
        if !session.outputs().iter().any(|o| o.name() == *name) {
            return Err(SegmentError::Model {
                path: path.to_path_buf(),
                why: format!(
                    "has no output `{name}` (its outputs: {})",
                    session
                        .outputs()
                        .iter()
                        .map(|o| o.name().to_string())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            });
        }
    }
    Ok(())
}

/// An `f32` tensor of `shape` from `data`.
pub fn tensor(shape: &[usize], data: Vec<f32>, path: &Path) -> Result<Tensor<f32>, SegmentError> {
    let shape: Vec<i64> = shape.iter().map(|&d| d as i64).collect();
    Tensor::from_array((shape, data)).map_err(|e| SegmentError::Model {
        path: path.to_path_buf(),
        why: e.to_string(),
    })
}
