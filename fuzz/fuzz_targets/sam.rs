#![no_main]
//! SAM mask JSON (COCO RLE), RLE strings and prompts JSON.
//! The check itself lives in `fuzz/src/checks.rs` (shared with `tests/hardening.rs`).
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = gs4city_fuzz::checks::run("sam", data);
});
