//! `gs4city` processes started by `gs4city` die with the process that started them.
//!
//! [`command`] starts `gs4city` with the hidden global option `--owned-by <this pid>`; the child
//! calls [`die_with_parent`] first thing: it arms the parent-death signal (`prctl(2)`
//! `PR_SET_PDEATHSIG` = `SIGKILL`) and then checks that its parent is still the process named
//! (a parent that died before the signal was armed has left the child to another parent: the
//! child ends at once). The kernel then kills the child when its parent ends, however it ends —
//! `kill -9` included — and, since every `gs4city` child does the same, the child's own
//! `gs4city` children in turn: a whole tree goes down with its root.
//!
//! The signal fires when the *thread* that started the child ends, not the process: start
//! children from a thread that lives as long as the process (the main thread).
use std::path::Path;
use std::process::Command;

use rustix::process::{Signal, getppid, set_parent_process_death_signal};

/// The hidden global option that names the parent a child dies with.
pub const OWNED_BY: &str = "--owned-by";

/// A `gs4city` command (the binary `exe`) that dies with this process: add its subcommand and
/// arguments, then spawn it from a long-lived thread.
pub fn command(exe: &Path) -> Command {
    let mut cmd = Command::new(exe);
    cmd.arg(OWNED_BY).arg(std::process::id().to_string());
    cmd
}

/// Arms the parent-death signal of this process (`SIGKILL`) and checks that its parent is still
/// `parent`; the error is one line for the child to end with.
pub fn die_with_parent(parent: u32) -> Result<(), String> {
    set_parent_process_death_signal(Some(Signal::KILL))
        .map_err(|e| format!("cannot arm the parent-death signal: {e}"))?;
    let now = getppid().map_or(0, |p| p.as_raw_nonzero().get() as u32);
    if now != parent {
        return Err(format!(
            "the process that started this one (pid {parent}) has ended; not starting"
        ));
    }
    Ok(())
}
