//! Progress bars (`src/progress.rs`) as a user sees them: `gs4city synth` (a small SIMULATED
//! scene, three views) draws its `synth … views` bar on a terminal — a pseudo-terminal opened
//! by Python's `pty`, the process's standard error a real tty — and nothing of it, no escape
//! sequence either, on a pipe or with `-q` on the terminal.
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common::python_can_import;

const TEST: &str = "progress::bars_draw_on_a_terminal_only";

/// Runs `python3 -c PTY gs4city ARGS` (the child's standard output and error on the
/// pseudo-terminal); returns its exit status and everything it wrote there.
const PTY: &str = r#"
import os, pty, sys
pid, fd = pty.fork()
if pid == 0:
    os.execv(sys.argv[1], sys.argv[1:])
out = b""
while True:
    try:
        chunk = os.read(fd, 65536)
    except OSError:
        break
    if not chunk:
        break
    out += chunk
_, status = os.waitpid(pid, 0)
sys.stdout.buffer.write(out)
sys.exit(os.waitstatus_to_exitcode(status))
"#;

fn scene_args(dir: &Path, name: &str) -> Vec<String> {
    let config = dir.join("three-views.toml");
    std::fs::write(
        &config,
        "[cameras]\norbit_views = 3\nstreet_views = 0\nwidth = 160\nheight = 120\n",
    )
    .unwrap();
    [
        "synth",
        "--preset",
        "small",
        "--config",
        config.to_str().unwrap(),
        "--out",
        dir.join(name).to_str().unwrap(),
    ]
    .map(String::from)
    .to_vec()
}

fn on_a_terminal(args: &[String]) -> String {
    let o = Command::new("python3")
        .args(["-c", PTY, env!("CARGO_BIN_EXE_gs4city")])
        .args(args)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    text
}

#[test]
fn bars_draw_on_a_terminal_only() {
    if !python_can_import(TEST, &["pty"]) {
        return;
    }
    let dir: PathBuf =
        crate::common::temp_dir().join(format!("gs4city-progress-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    // The bar's template: `synth [=====>    ] 2/3 views …`, and escape sequences to redraw it.
    let tty = on_a_terminal(&scene_args(&dir, "tty"));
    assert!(has_bar(&tty), "no bar on the terminal: {tty:?}");
    assert!(
        tty.contains("\u{1b}["),
        "no escape sequence on the terminal: {tty:?}"
    );
    let mut quiet = vec!["-q".to_string()];
    quiet.extend(scene_args(&dir, "quiet"));
    let q = on_a_terminal(&quiet);
    assert!(
        !has_bar(&q) && !q.contains("\u{1b}["),
        "-q on a terminal: {q:?}"
    );
    let o = Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(scene_args(&dir, "pipe"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        !has_bar(&err) && !err.contains("\u{1b}["),
        "on a pipe: {err:?}"
    );
    // The same work was done each time.
    assert!(err.contains("3 views") && tty.contains("3 views"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Whether `text` holds the bar: `synth [` … `] k/3 views`.
fn has_bar(text: &str) -> bool {
    text.contains("synth [") && (0..=3).any(|k| text.contains(&format!("] {k}/3 views")))
}
