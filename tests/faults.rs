//! Commands interrupted, doubled or slowed, with real processes: two `run`s on one folder (the
//! second is refused naming the first, which finishes as a run alone would), `kill -9` of
//! `run-plan` (its tiles die with it; a rerun merges as an uninterrupted plan), a byte flipped in
//! a finished stage's output with its size and modification time put back (the stage reruns with
//! a warning), a tile whose `run/` is gone under a status that says ok (merge names it), and
//! error lines that give the operating system's reason once. The scenes are SIMULATED
//! (`synth --preset small`).
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_gs4city"))
}

fn tmp(name: &str) -> PathBuf {
    let d = crate::common::temp_dir().join(format!("gs4city-faults-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Runs `gs4city ARGS`: (exit code, stdout + stderr).
fn gs(args: &[&str]) -> (i32, String) {
    let o = bin().args(args).output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        format!(
            "{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        ),
    )
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The SIMULATED small scene, made once for the tests here.
fn scene() -> &'static Path {
    static S: OnceLock<PathBuf> = OnceLock::new();
    S.get_or_init(|| {
        let d = tmp("scene");
        let sc = d.join("small");
        let (code, out) = gs(&["-q", "synth", "--preset", "small", "--out", s(&sc)]);
        assert_eq!(code, 0, "{out}");
        sc
    })
}

/// The files of a run folder that stand for its result, by relative path → bytes: every
/// stage folder's files except the time- and run-dependent records (`summary.json` holds
/// seconds and peak memory, `run.json` run ids, the report its timings; `.lock` the holder).
fn result_files(run: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![run.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            if p.is_dir() {
                stack.push(p);
            } else if !matches!(
                name.as_str(),
                "summary.json" | "run.json" | "report.html" | ".lock" | "log.txt" | "status.json"
            ) {
                let rel = p.strip_prefix(run).unwrap().display().to_string();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

fn assert_same_files(a: &Path, b: &Path) {
    assert_same_files_but(a, b, None);
}

/// `bytes` with every `from` replaced by `to`.
fn replaced(bytes: &[u8], from: &[u8], to: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i..].starts_with(from) {
            out.extend_from_slice(to);
            i += from.len();
        } else {
            out.push(bytes[i]);
            i += 1;
        }
    }
    out
}

/// As [`assert_same_files`], with `rename = (from, to)` replaced in `a`'s files first (a
/// folder's own path recorded in a file, as `semantics.json` names its CityGML sources).
fn assert_same_files_but(a: &Path, b: &Path, rename: Option<(&str, &str)>) {
    let (mut fa, fb) = (result_files(a), result_files(b));
    if let Some((from, to)) = rename {
        for v in fa.values_mut() {
            *v = replaced(v, from.as_bytes(), to.as_bytes());
        }
    }
    assert_eq!(
        fa.keys().collect::<Vec<_>>(),
        fb.keys().collect::<Vec<_>>(),
        "{} vs {}",
        a.display(),
        b.display()
    );
    for (k, v) in &fa {
        assert!(
            v == &fb[k],
            "{k} differs between {} and {}",
            a.display(),
            b.display()
        );
    }
}

/// The pids of the live processes whose command line contains `needle` (from /proc).
fn processes_with(needle: &str) -> Vec<u32> {
    let mut out = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let Ok(cmd) = std::fs::read(e.path().join("cmdline")) else {
            continue;
        };
        let cmd = String::from_utf8_lossy(&cmd).replace('\0', " ");
        // A zombie has an empty command line: it has ended.
        if cmd.contains(needle) && pid != std::process::id() {
            out.push(pid);
        }
    }
    out
}

/// Waits until `f` holds (polling every 50 ms), at most `limit`.
fn wait_for(limit: Duration, mut f: impl FnMut() -> bool) -> bool {
    let t0 = Instant::now();
    while t0.elapsed() < limit {
        if f() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    f()
}

fn spawn(args: &[&str]) -> Child {
    bin()
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn finish(c: Child) -> (i32, String) {
    let o = c.wait_with_output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        format!(
            "{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        ),
    )
}

#[test]
fn a_second_run_on_a_locked_folder_is_refused_naming_the_first_which_finishes_as_alone() {
    let sc = scene();
    let d = tmp("two-runs");
    let (solo, r) = (d.join("solo"), d.join("R"));
    let (code, out) = gs(&["-q", "run", "--scene", s(sc), "--out", s(&solo)]);
    assert_eq!(code, 0, "{out}");
    let first = spawn(&["-q", "run", "--scene", s(sc), "--out", s(&r)]);
    // The first holds the lock once its lock file names it.
    let pid = first.id();
    assert!(
        wait_for(Duration::from_secs(30), || {
            std::fs::read_to_string(r.join(".lock"))
                .is_ok_and(|t| t.contains(&format!("\"pid\":{pid}")))
        }),
        "the first run never took its lock"
    );
    // Same options, and other options: both refused, naming the first by pid and command.
    for extra in [&[][..], &["--supervision", "city"][..]] {
        let mut args = vec!["-q", "run", "--scene", s(sc), "--out", s(&r)];
        args.extend_from_slice(extra);
        let (code, text) = gs(&args);
        assert_eq!(code, 75, "{text}");
        let line = text.lines().find(|l| l.starts_with("error:")).unwrap();
        assert_eq!(text.trim().lines().count(), 1, "one line: {text}");
        assert!(
            line.contains(&format!("pid {pid}")) && line.contains(" run ") && line.contains(s(&r)),
            "{line}"
        );
    }
    // A reader is refused while the run writes.
    let (code, text) = gs(&[
        "-q",
        "query",
        "--run",
        s(&r),
        "--class",
        "Window",
        "--out",
        s(&d.join("Q")),
    ]);
    assert_eq!(code, 75, "{text}");
    assert!(text.contains(&format!("pid {pid}")), "{text}");
    let (code, text) = finish(first);
    assert_eq!(code, 0, "{text}");
    assert_same_files(&solo, &r);
    // Readers side by side, and a run refused while one reads (naming the reader).
    let view = bin()
        .args(["view", "--run", s(&r), "--port", "0"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let vpid = view.id();
    let mut view = scopeguard(view);
    assert!(wait_for(Duration::from_secs(60), || {
        lock_holders_of(&r.join(".lock")).contains(&vpid)
    }));
    let (code, text) = gs(&[
        "-q",
        "query",
        "--run",
        s(&r),
        "--class",
        "Window",
        "--out",
        s(&d.join("Q")),
    ]);
    assert_eq!(code, 0, "a second reader: {text}");
    let (code, text) = gs(&["-q", "run", "--scene", s(sc), "--out", s(&r)]);
    assert_eq!(code, 75, "{text}");
    assert!(
        text.contains(&format!("pid {vpid}")) && text.contains("view"),
        "{text}"
    );
    view.kill();
    let (code, text) = gs(&["-q", "run", "--scene", s(sc), "--out", s(&r)]);
    assert_eq!(code, 0, "once the viewer is gone: {text}");
    let _ = std::fs::remove_dir_all(&d);
}

/// A child process killed (and reaped) when dropped.
struct Guard(Child);

impl Guard {
    fn kill(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Drop for Guard {
    fn drop(&mut self) {
        self.kill();
    }
}

fn scopeguard(c: Child) -> Guard {
    Guard(c)
}

/// The pids `/proc/locks` lists as holding an flock on `path`.
pub fn lock_holders_of(path: &Path) -> Vec<u32> {
    use std::os::unix::fs::MetadataExt;
    let Ok(m) = std::fs::metadata(path) else {
        return Vec::new();
    };
    let text = std::fs::read_to_string("/proc/locks").unwrap_or_default();
    let dev = m.dev();
    // Linux's encoding of a device number (glibc's gnu_dev_major / gnu_dev_minor).
    let major = ((dev >> 8) & 0xfff) | ((dev >> 32) & !0xfff);
    let minor = (dev & 0xff) | ((dev >> 12) & !0xff);
    let want = format!("{major:02x}:{minor:02x}:{}", m.ino());
    text.lines()
        .filter(|l| l.contains(" FLOCK ") && !l.contains("->"))
        .filter_map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            (f.get(5) == Some(&want.as_str()))
                .then(|| f[4].parse().ok())
                .flatten()
        })
        .collect()
}

#[test]
fn a_byte_flipped_with_size_and_mtime_restored_reruns_its_stage_with_a_warning() {
    let sc = scene();
    let d = tmp("flip");
    let r = d.join("R");
    let (code, out) = gs(&["-q", "run", "--scene", s(sc), "--out", s(&r)]);
    assert_eq!(code, 0, "{out}");
    let clean = result_files(&r);
    // gaussians.npy: the vote's output; the byte of one label in the middle of the array.
    let f = r.join("lift/gaussians.npy");
    let meta = std::fs::metadata(&f).unwrap();
    let mtime = meta.modified().unwrap();
    let mut bytes = std::fs::read(&f).unwrap();
    let k = bytes.len() / 2;
    bytes[k] ^= 0x01;
    std::fs::write(&f, &bytes).unwrap();
    std::fs::File::options()
        .write(true)
        .open(&f)
        .unwrap()
        .set_modified(mtime)
        .unwrap();
    let after = std::fs::metadata(&f).unwrap();
    assert_eq!(
        (after.len(), after.modified().unwrap()),
        (meta.len(), mtime)
    );
    let (code, text) = gs(&["run", "--scene", s(sc), "--out", s(&r)]);
    assert_eq!(code, 0, "{text}");
    let warnings: Vec<&str> = text
        .lines()
        .filter(|l| l.contains("lift/gaussians.npy"))
        .collect();
    assert_eq!(warnings.len(), 1, "{text}");
    assert!(
        warnings[0].contains("changed since it was written") && warnings[0].contains("runs again"),
        "{}",
        warnings[0]
    );
    // The vote reran (and the stages after it); the stages before it were resumed.
    let resumed = |stage: &str| {
        text.lines()
            .any(|l| l.starts_with(stage) && l.trim_end().ends_with("(resumed)"))
    };
    assert!(
        !resumed("lift") && resumed("render") && resumed("citymodel"),
        "{text}"
    );
    assert_eq!(result_files(&r), clean, "the rerun restored every output");
    // A truncated cache file: re-rendered, and the line says why.
    let c = std::fs::read_dir(r.join("render"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .find(|p| p.extension().is_some_and(|x| x == "contrib"))
        .unwrap();
    let len = std::fs::metadata(&c).unwrap().len();
    std::fs::File::options()
        .write(true)
        .open(&c)
        .unwrap()
        .set_len(len - 1)
        .unwrap();
    let (code, text) = gs(&["run", "--scene", s(sc), "--out", s(&r)]);
    assert_eq!(code, 0, "{text}");
    let name = c.file_name().unwrap().to_string_lossy().into_owned();
    assert!(
        text.lines().any(|l| l.contains(&format!(
            "render/{name} has {} bytes, {len} when it was written",
            len - 1
        ))),
        "{text}"
    );
    assert_eq!(result_files(&r), clean);
    let _ = std::fs::remove_dir_all(&d);
}

fn tile_plan(sc: &Path, p: &Path) {
    let (code, out) = gs(&[
        "-q",
        "tile",
        "--scene",
        s(sc),
        "--size",
        "10",
        "--margin",
        "4",
        "--out",
        s(p),
    ]);
    assert_eq!(code, 0, "{out}");
}

#[test]
fn killing_run_plan_kills_its_tiles_and_a_rerun_merges_as_an_uninterrupted_plan() {
    let sc = scene();
    let d = tmp("kill-plan");
    let (p, q) = (d.join("P"), d.join("Q"));
    tile_plan(sc, &p);
    tile_plan(sc, &q);
    let (code, out) = gs(&["-q", "run-plan", s(&q), "--jobs", "2", "--no-test-views"]);
    assert_eq!(code, 0, "uninterrupted: {out}");
    // Killed while both tiles run (their runs have started: each has taken its run's lock).
    let mut plan = scopeguard(spawn(&[
        "-q",
        "run-plan",
        s(&p),
        "--jobs",
        "2",
        "--no-test-views",
    ]));
    let tiles: Vec<PathBuf> = std::fs::read_dir(p.join("tiles"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .collect();
    assert_eq!(tiles.len(), 2);
    assert!(
        wait_for(Duration::from_secs(60), || tiles
            .iter()
            .all(|t| t.join("run/.lock").is_file())),
        "the tiles never started"
    );
    std::thread::sleep(Duration::from_millis(500));
    let needle = format!("{} --tile", s(&p));
    assert_eq!(processes_with(&needle).len(), 2, "two tile processes run");
    rustix_kill(plan.0.id());
    let _ = plan.0.wait();
    std::thread::sleep(Duration::from_secs(2));
    assert_eq!(
        processes_with(&needle),
        Vec::<u32>::new(),
        "tile processes outlived run-plan"
    );
    // No status says a tile succeeded, and a rerun at once finishes the plan.
    let (code, out) = gs(&["-q", "run-plan", s(&p), "--jobs", "2", "--no-test-views"]);
    assert_eq!(code, 0, "rerun: {out}");
    // (The tiles' `semantics.json` name their CityGML files, inside P or Q.)
    let rename = Some((s(&p), s(&q)));
    assert_same_files_but(&p.join("merged"), &q.join("merged"), rename);
    for t in &tiles {
        let name = t.file_name().unwrap();
        assert_same_files_but(
            &t.join("run"),
            &q.join("tiles").join(name).join("run"),
            rename,
        );
    }
    let _ = std::fs::remove_dir_all(&d);
}

/// `kill -9 PID` by the system's own `kill` command.
fn rustix_kill(pid: u32) {
    let st = Command::new("kill")
        .args(["-9", &pid.to_string()])
        .status()
        .unwrap();
    assert!(st.success());
}

#[test]
fn a_second_run_plan_on_a_tile_waits_for_it_and_force_reruns_its_stages() {
    let sc = scene();
    let d = tmp("two-plans");
    let p = d.join("P");
    tile_plan(sc, &p);
    // `run-plan P --tile 0` twice: the second is refused naming the first.
    let first = spawn(&["-q", "run-plan", s(&p), "--tile", "0"]);
    let pid = first.id();
    let t0 = p.join("tiles/t000_000");
    assert!(wait_for(Duration::from_secs(30), || {
        std::fs::read_to_string(t0.join(".lock"))
            .is_ok_and(|t| t.contains(&format!("\"pid\":{pid}")))
    }));
    let (code, text) = gs(&["-q", "run-plan", s(&p), "--tile", "0"]);
    assert_eq!(code, 75, "{text}");
    assert!(
        text.contains(&format!("pid {pid}")) && text.contains("--tile 0"),
        "{text}"
    );
    // The whole plan beside it: it waits for tile 0 instead of running it twice, then merges.
    let (code, text) = gs(&["run-plan", s(&p), "--jobs", "2", "--no-test-views"]);
    assert_eq!(code, 0, "{text}");
    assert!(text.contains("waiting for it"), "{text}");
    assert!(text.contains("1 tiles run, 1 reused"), "{text}");
    let (code, text) = finish(first);
    assert_eq!(code, 0, "{text}");
    // --force reruns every stage of every tile (not only the plan's bookkeeping).
    let (code, text) = gs(&[
        "run-plan",
        s(&p),
        "--jobs",
        "1",
        "--force",
        "--no-test-views",
    ]);
    assert_eq!(code, 0, "{text}");
    for t in ["t000_000", "t000_001"] {
        let log = std::fs::read_to_string(p.join("tiles").join(t).join("log.txt")).unwrap();
        assert!(!log.contains("resumed"), "{t}: {log}");
    }
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn merge_names_a_tile_whose_outputs_are_gone_and_allow_missing_merges_around_it() {
    let sc = scene();
    let d = tmp("merge-check");
    let p = d.join("P");
    tile_plan(sc, &p);
    let (code, out) = gs(&["-q", "run-plan", s(&p), "--jobs", "2", "--no-test-views"]);
    assert_eq!(code, 0, "{out}");
    let m = d.join("M");
    // One stage output deleted, then the whole run folder, under a status that says ok.
    let t1 = p.join("tiles/t000_001");
    std::fs::remove_file(t1.join("run/fuse/labels.json")).unwrap();
    let (code, text) = gs(&["-q", "merge", s(&p), "--out", s(&m), "--no-test-views"]);
    assert_ne!(code, 0);
    assert!(
        text.contains("t000_001") && text.contains("fuse/labels.json is missing"),
        "{text}"
    );
    assert!(!m.exists());
    std::fs::remove_dir_all(t1.join("run")).unwrap();
    let (code, text) = gs(&["-q", "merge", s(&p), "--out", s(&m), "--no-test-views"]);
    assert_ne!(code, 0);
    assert_eq!(text.lines().count(), 1, "{text}");
    assert!(
        text.contains("t000_001") && text.contains("run folder") && text.contains("missing"),
        "{text}"
    );
    assert!(!text.contains("os error"), "{text}");
    let (code, text) = gs(&[
        "merge",
        s(&p),
        "--out",
        s(&m),
        "--no-test-views",
        "--allow-missing",
    ]);
    assert_eq!(code, 0, "{text}");
    assert!(text.contains("HOLE: tile t000_001 missing"), "{text}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(m.join("summary.json")).unwrap()).unwrap();
    let plan: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(p.join("plan.json")).unwrap()).unwrap();
    assert_eq!(summary["in_holes"], plan["tiles"][1]["core_gaussians"]);
    let _ = std::fs::remove_dir_all(&d);
}

/// Every error line of a set of failing commands gives an operating system's reason at most
/// once (`No such file or directory (os error 2)` was printed twice where an error type kept
/// the I/O error in its message and also exposed it as its source).
#[test]
fn an_error_line_gives_the_os_reason_once() {
    let sc = scene();
    let d = tmp("os-reason");
    let r = d.join("R");
    let (code, out) = gs(&["-q", "run", "--scene", s(sc), "--out", s(&r)]);
    assert_eq!(code, 0, "{out}");
    // A cache file replaced by a folder, another removed: lift reads them.
    let contribs: Vec<PathBuf> = std::fs::read_dir(r.join("render"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "contrib"))
        .collect();
    std::fs::remove_file(&contribs[0]).unwrap();
    let nope = d.join("nope");
    let file = d.join("file");
    std::fs::write(&file, "x").unwrap();
    let cases: Vec<Vec<String>> = vec![
        vec![
            "lift".into(),
            "--ply".into(),
            s(&sc.join("point_cloud.ply")).into(),
            "--colmap".into(),
            s(&sc.join("sparse/0")).into(),
            "--cache".into(),
            s(&r.join("render")).into(),
            "--citymodel".into(),
            s(&r.join("citymodel")).into(),
            "--fuse".into(),
            s(&r.join("fuse")).into(),
            "--out".into(),
            s(&d.join("L")).into(),
        ],
        vec![
            "run".into(),
            "--scene".into(),
            s(&nope).into(),
            "--out".into(),
            s(&d.join("R2")).into(),
        ],
        vec![
            "run".into(),
            "--scene".into(),
            s(sc).into(),
            "--out".into(),
            s(&file.join("R")).into(),
        ],
        vec![
            "query".into(),
            "--run".into(),
            s(&nope).into(),
            "--class".into(),
            "Window".into(),
            "--out".into(),
            s(&d.join("Q")).into(),
        ],
        vec![
            "eval".into(),
            "--pred".into(),
            s(&file).into(),
            "--gt".into(),
            s(&nope).into(),
            "--out".into(),
            s(&d.join("E")).into(),
        ],
        vec![
            "merge".into(),
            s(&nope).into(),
            "--out".into(),
            s(&d.join("M")).into(),
        ],
        vec![
            "citymodel".into(),
            s(&nope).into(),
            "--out".into(),
            s(&d.join("C")).into(),
        ],
        vec!["check".into(), "--scene".into(), s(&file).into()],
        vec![
            "view".into(),
            "--run".into(),
            s(&file).into(),
            "--port".into(),
            "0".into(),
        ],
    ];
    let mut os_lines = 0;
    for args in &cases {
        let (code, text) = gs(&args.iter().map(String::as_str).collect::<Vec<_>>());
        assert_ne!(code, 0, "{args:?}: {text}");
        for line in text.lines() {
            let n = line.matches("(os error").count();
            assert!(n <= 1, "{args:?}: the OS reason is given {n} times: {line}");
            os_lines += usize::from(n == 1);
        }
    }
    assert!(
        os_lines >= 3,
        "the cases reach the operating system's errors: {os_lines}"
    );
    let _ = std::fs::remove_dir_all(&d);
}

/// The cause of a repeated reason, found in the source: a `thiserror` message that prints a
/// field which is also the error's source (a field named `source`, or marked `#[source]` or
/// `#[from]`). `main` prints the whole chain (`{:#}`), so such a message gives the source's
/// text twice. `#[error(transparent)]` forwards both and is fine.
#[test]
fn no_error_message_prints_its_own_source() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    let mut stack = vec![root];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                if p.file_name().is_some_and(|n| n != "vendor") {
                    stack.push(p);
                }
            } else if p.extension().is_some_and(|x| x == "rs") {
                files.push(p);
            }
        }
    }
    let mut found = Vec::new();
    let mut checked = 0;
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap();
        for (fmt, fields) in error_items(&text) {
            checked += 1;
            for (name, is_source) in &fields {
                if *is_source
                    && (fmt.contains(&format!("{{{name}}}")) || fmt.contains(&format!("{{{name}:")))
                {
                    found.push(format!(
                        "{}: #[error(\"{fmt}\")] prints its source `{name}`",
                        f.display()
                    ));
                }
            }
        }
    }
    assert!(
        checked > 100,
        "only {checked} error messages found: the scan is broken"
    );
    assert!(found.is_empty(), "{}", found.join("\n"));
}

/// Each `#[error("…")]` of `text` with the fields of the variant or struct that follows it:
/// (format string, [(field name or tuple index, whether it is a source)]).
fn error_items(text: &str) -> Vec<(String, Vec<(String, bool)>)> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find("#[error(") {
        rest = &rest[i + 8..];
        let Some(q) = rest.find('"') else { break };
        if rest[..q].contains("transparent") || rest[..q].trim().starts_with(')') {
            continue;
        }
        // The format string (escapes kept as written).
        let b = rest.as_bytes();
        let mut j = q + 1;
        while j < b.len() && b[j] != b'"' {
            if b[j] == b'\\' {
                j += 1;
            }
            j += 1;
        }
        let fmt = rest[q + 1..j].to_string();
        // Past the attribute and any further attributes to the item's fields: `{…}` or `(…)`
        // (or `;`/`,` for a unit variant).
        let after = &rest[j..];
        let close = after.find(")]").map_or(0, |k| k + 2);
        let item = &after[close..];
        let open = item.find(['{', '(', ',', ';']).unwrap_or(0);
        let fields = match item.as_bytes().get(open) {
            Some(b'{') | Some(b'(') => {
                let (o, c) = if item.as_bytes()[open] == b'{' {
                    ('{', '}')
                } else {
                    ('(', ')')
                };
                let mut depth = 0;
                let mut end = open;
                for (k, ch) in item[open..].char_indices() {
                    if ch == o || (o == '{' && ch == '(') || (o == '(' && ch == '{') {
                        depth += 1;
                    } else if ch == c || (o == '{' && ch == ')') || (o == '(' && ch == '}') {
                        depth -= 1;
                        if depth == 0 {
                            end = open + k;
                            break;
                        }
                    }
                }
                parse_fields(&item[open + 1..end], o == '(')
            }
            _ => Vec::new(),
        };
        out.push((fmt, fields));
    }
    out
}

/// The fields of a struct body (`a: T, #[source] b: U`) or tuple body (`#[from] T, U`), split at
/// top-level commas: (name or index, whether it is a source).
fn parse_fields(body: &str, tuple: bool) -> Vec<(String, bool)> {
    let mut parts = Vec::new();
    let (mut depth, mut start) = (0i32, 0);
    for (k, ch) in body.char_indices() {
        match ch {
            '<' | '(' | '[' | '{' => depth += 1,
            '>' | ')' | ']' | '}' => depth -= 1,
            ',' if depth == 0 => {
                parts.push(&body[start..k]);
                start = k + 1;
            }
            _ => {}
        }
    }
    parts.push(&body[start..]);
    parts
        .iter()
        .map(|p| {
            // Doc comments and attributes, then the field.
            let code: String = p
                .lines()
                .filter(|l| !l.trim_start().starts_with("//"))
                .collect::<Vec<_>>()
                .join(" ");
            (code.contains("#[source]") || code.contains("#[from]"), code)
        })
        .filter(|(_, code)| !code.trim().is_empty())
        .enumerate()
        .map(|(i, (marked, code))| {
            let bare = code
                .replace("#[source]", "")
                .replace("#[from]", "")
                .replace("pub ", "");
            if tuple {
                (i.to_string(), marked)
            } else {
                let name = bare.split(':').next().unwrap_or("").trim().to_string();
                let is_source = marked || name == "source";
                (name, is_source)
            }
        })
        .collect()
}
