#![no_main]
//! COLMAP binary model (cameras.bin + images.bin, split by the first two bytes; the same bytes as points3D.bin).
//! The check itself lives in `fuzz/src/checks.rs` (shared with `tests/hardening.rs`).
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = gs4city_fuzz::checks::run("colmap_bin", data);
});
