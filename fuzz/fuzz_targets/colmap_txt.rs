#![no_main]
//! COLMAP text model (cameras.txt + images.txt, split by the first two bytes; the same bytes as points3D.txt).
//! The check itself lives in `fuzz/src/checks.rs` (shared with `tests/hardening.rs`).
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = gs4city_fuzz::checks::run("colmap_txt", data);
});
