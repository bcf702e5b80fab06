#![no_main]
//! CityGML reader (1.0/2.0/3.0, any encoding): a model or one error.
//! The check itself lives in `fuzz/src/checks.rs` (shared with `tests/hardening.rs`).
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = gs4city_fuzz::checks::run("citygml", data);
});
