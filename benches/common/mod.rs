//! What the model benches (`segment`, `features`) share: arguments, CPU time, the generated
//! random-weight models.
use std::path::{Path, PathBuf};
use std::process::Command;

/// The value after `name` on the command line.
pub fn arg(name: &str) -> Option<String> {
    let a: Vec<String> = std::env::args().collect();
    a.iter()
        .position(|x| x == name)
        .and_then(|i| a.get(i + 1).cloned())
}

/// `target/bench-models/<name>/`, written by `scripts/make_test_models.py <gen…>` unless `check`
/// is there already from the same script and arguments (a stamp of both is kept beside it: a
/// model left by an older generator is made again, not timed).
pub fn model(name: &str, gen_args: &[&str], check: &str) -> PathBuf {
    use std::hash::{Hash, Hasher};
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = root.join("target/bench-models").join(name);
    let script = root.join("scripts/make_test_models.py");
    let mut h = std::collections::hash_map::DefaultHasher::new();
    std::fs::read(&script)
        .expect("scripts/make_test_models.py")
        .hash(&mut h);
    gen_args.hash(&mut h);
    let stamp = format!("{:016x}\n", h.finish());
    let stamp_file = dir.join("generator.stamp");
    let current = std::fs::read_to_string(&stamp_file).is_ok_and(|s| s == stamp);
    if !(current && dir.join(check).is_file()) {
        eprintln!(
            "generating the random-weight {name} model in {}",
            dir.display()
        );
        let _ = std::fs::remove_dir_all(&dir);
        let ok = Command::new("python3")
            .arg(&script)
            .args(gen_args)
            .arg("--out")
            .arg(&dir)
            .status()
            .expect("python3");
        assert!(ok.success(), "make_test_models.py failed");
        std::fs::write(&stamp_file, stamp).expect("generator stamp");
    }
    dir
}

/// CPU seconds (user + system, all threads) of this process so far, from /proc/self/stat.
pub fn cpu_s() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // fields 14 and 15 of stat (utime, stime) are items 11 and 12 after the command name
    (ticks(11) + ticks(12)) / 100.0
}
