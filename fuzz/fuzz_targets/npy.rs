#![no_main]
//! .npy reader for every element type: an accepted array re-encodes to the same values.
//! The check itself lives in `fuzz/src/checks.rs` (shared with `tests/hardening.rs`).
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = gs4city_fuzz::checks::run("npy", data);
});
