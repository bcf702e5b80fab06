#![no_main]
//! A selection expression (`--where`, the viewer's query box): parsed, or one error.
//! The check itself lives in `fuzz/src/checks.rs` (shared with `tests/hardening.rs`).
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = gs4city_fuzz::checks::run("where", data);
});
