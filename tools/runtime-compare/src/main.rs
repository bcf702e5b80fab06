//! Times one forward pass of a SAM image encoder (`image [1,3,1024,1024]` →
//! `image_embeddings`) in ONNX Runtime and in candle-onnx on the same file and the same input,
//! and reports the largest difference of their outputs.
use std::collections::HashMap;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let path = args.get(1).expect("usage: runtime-compare MODEL.onnx [repeats]");
    let repeats: usize = args.get(2).map_or(2, |r| r.parse().expect("repeats"));
    // the same input for both: a fixed pseudo-random image
    let n = 3 * 1024 * 1024;
    let mut s = 0x9E37_79B9_7F4A_7C15u64;
    let data: Vec<f32> = (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32 * 4.0 - 2.0
        })
        .collect();

    let lib = std::env::var("ORT_DYLIB_PATH").expect("set ORT_DYLIB_PATH to libonnxruntime.so");
    let env = ort::init_from(&lib).expect("load ONNX Runtime").build().expect("environment");
    let mut session = ort::session::Session::builder(&env)
        .unwrap()
        .commit_from_file(path)
        .expect("ort session");
    let mut ort_out = Vec::new();
    let mut ort_s = f64::INFINITY;
    for _ in 0..repeats {
        let x = ort::value::Tensor::from_array((vec![1i64, 3, 1024, 1024], data.clone())).unwrap();
        let t = Instant::now();
        let out = session.run(ort::inputs!["image" => x]).expect("ort run");
        ort_s = ort_s.min(t.elapsed().as_secs_f64());
        ort_out = out[0].try_extract_tensor::<f32>().unwrap().1.to_vec();
    }

    let model = candle_onnx::read_file(path).expect("candle-onnx read");
    let mut candle_out = Vec::new();
    let mut candle_s = f64::INFINITY;
    for _ in 0..repeats {
        let x = candle_core::Tensor::from_vec(data.clone(), (1, 3, 1024, 1024), &candle_core::Device::Cpu).unwrap();
        let t = Instant::now();
        let mut inputs = HashMap::new();
        inputs.insert("image".to_string(), x);
        let out = candle_onnx::simple_eval(&model, inputs).expect("candle run");
        candle_s = candle_s.min(t.elapsed().as_secs_f64());
        candle_out = out["image_embeddings"].flatten_all().unwrap().to_vec1::<f32>().unwrap();
    }
    let diff = ort_out
        .iter()
        .zip(&candle_out)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    println!(
        "{path}: ONNX Runtime {ort_s:.2} s, candle-onnx {candle_s:.2} s (best of {repeats}); largest |difference| of the {} outputs {diff:.2e}",
        ort_out.len()
    );
}
