//! The totals line of `scripts/test.sh` (`scripts/test_totals.sh`) on a hand-written `cargo
//! test` output and skip log, with the counts worked out by hand: ignored tests are counted, a
//! test that wrote several skip lines is one skipped test, a skip line of a failed test leaves
//! it failed, a cargo line after a child process's text is still read; a skip line naming no
//! test, or totals that do not add up, fail the script.
use std::path::Path;
use std::process::Command;

const LOG: &str = "\
running 3 tests
test a::x ... ok
test a::y ... FAILED
test a::z ... ignored, needs torch + segment-anything
test result: FAILED. 1 passed; 1 failed; 1 ignored; 0 measured; 0 filtered out; finished in 1.00s

running 4 tests
test b::p ... ok
test b::q has been running for over 60 seconds
test b::q ... ok
gs4city: warning: a child's line without its newlinetest b::r ... ok
test src/lib.rs - f (line 3) ... ok
test result: ok. 4 passed; 0 failed; 0 ignored; 0 measured; 2 filtered out; finished in 9.00s
";

/// Runs `scripts/test_totals.sh` on `log` and `skips`: (exit code, stdout, stderr).
fn totals(name: &str, log: &str, skips: &str) -> (i32, String, String) {
    let dir =
        crate::common::temp_dir().join(format!("gs4city-totals-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("log"), log).unwrap();
    std::fs::write(dir.join("skips"), skips).unwrap();
    let o = Command::new("bash")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/test_totals.sh"))
        .arg(dir.join("log"))
        .arg(dir.join("skips"))
        .output()
        .unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

#[test]
fn each_skipped_test_counts_once_and_ignored_tests_count() {
    // b::p skipped three cross-checks, b::r one, a::y one and then failed: 2 skipped tests.
    // Cargo: 5 passed (a::x, b::p, b::q, b::r, the doc test), 1 failed, 1 ignored, 7 run.
    let skips = "\
SKIPPED: b::p: python3 cannot `import numpy`
SKIPPED: b::p: python3 cannot `import numpy`
SKIPPED: b::p: python3 cannot `import cjio`
SKIPPED: b::r: needs root (slurmd and munged run as root), running as uid 1000
SKIPPED: a::y: python3 cannot `import scipy`
";
    let (code, out, err) = totals("ok", LOG, skips);
    assert_eq!(code, 0, "{out}{err}");
    assert_eq!(
        out.lines().last(),
        Some("tests: 3 passed, 1 failed, 2 skipped, 1 ignored (7 run)"),
        "{out}"
    );
    assert!(
        out.contains("  b::p: python3 cannot `import numpy`"),
        "{out}"
    );
    assert!(out.contains("  b::r: needs root"), "{out}");
    assert!(
        out.contains("failed after skipping a cross-check (counted as failed): a::y"),
        "{out}"
    );
    // Without skips: cargo's own counts, ignored included.
    let (code, out, _) = totals("none", LOG, "");
    assert_eq!(code, 0);
    assert_eq!(
        out.trim(),
        "tests: 5 passed, 1 failed, 0 skipped, 1 ignored (7 run)"
    );
}

#[test]
fn a_skip_naming_no_test_or_totals_that_do_not_add_up_fail() {
    let (code, out, err) = totals("bad-name", LOG, "SKIPPED: tile_slurm: needs root\n");
    assert_eq!(code, 1, "{out}{err}");
    assert!(
        err.contains("the skip log names tile_slurm, which is no test"),
        "{err}"
    );
    let short = LOG.replacen("running 4 tests", "running 5 tests", 1);
    let (code, out, err) = totals("short", &short, "");
    assert_eq!(code, 1, "{out}{err}");
    assert!(
        err.contains("5 passed + 1 failed + 0 skipped + 1 ignored is not the 8 tests cargo ran"),
        "{err}"
    );
}
