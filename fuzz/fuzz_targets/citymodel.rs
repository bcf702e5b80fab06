#![no_main]
//! CityGML read + every polygon triangulated as the citymodel stage does.
//! The check itself lives in `fuzz/src/checks.rs` (shared with `tests/hardening.rs`).
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = gs4city_fuzz::checks::run("citymodel", data);
});
