//! Progress bars and log lines for long work.
//!
//! * [`Bar`]: an `indicatif` bar on standard error, drawn only when standard error is a terminal
//!   and the verbosity is not quiet; on a pipe (or in tests) it draws nothing and costs almost
//!   nothing. It is `Clone + Send + Sync`, so rayon workers can tick it.
//! * Log lines go through the `log` facade; [`init`] installs the binary's logger (standard
//!   error, `gs4city: ` prefix) at a level set by `-q`/`-v`. Library code only calls `log::…!`;
//!   without a logger (tests, library users) they do nothing.
//! * [`done`]: the one line every stage ends with — what it did, how long, peak memory.
use std::io::IsTerminal;
use std::sync::atomic::{AtomicI8, Ordering};
use std::time::Duration;

use std::sync::OnceLock;

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};

/// −1 = quiet (errors and warnings only), 0 = normal, 1 = verbose (debug), 2 = trace.
static VERBOSITY: AtomicI8 = AtomicI8::new(0);

struct Logger;

/// All bars hang off one `MultiProgress`, so log lines can be printed above them.
fn multi() -> &'static MultiProgress {
    static MULTI: OnceLock<MultiProgress> = OnceLock::new();
    MULTI.get_or_init(|| MultiProgress::with_draw_target(ProgressDrawTarget::stderr()))
}

impl log::Log for Logger {
    fn enabled(&self, metadata: &log::Metadata<'_>) -> bool {
        metadata.level() <= max_level()
    }

    fn log(&self, record: &log::Record<'_>) {
        if !self.enabled(record.metadata()) {
            return;
        }
        let line = match record.level() {
            log::Level::Error => format!("gs4city: error: {}", record.args()),
            log::Level::Warn => format!("gs4city: warning: {}", record.args()),
            _ => format!("gs4city: {}", record.args()),
        };
        // Printed above the bars that are being drawn.
        multi().suspend(|| eprintln!("{line}"));
    }

    fn flush(&self) {}
}

fn max_level() -> log::Level {
    match VERBOSITY.load(Ordering::Relaxed) {
        i8::MIN..=-1 => log::Level::Warn,
        0 => log::Level::Info,
        1 => log::Level::Debug,
        _ => log::Level::Trace,
    }
}

/// Installs the logger at `verbosity` (−1 quiet, 0 normal, 1 verbose, 2 trace). Only the binary
/// calls this; a second call only changes the level.
pub fn init(verbosity: i8) {
    VERBOSITY.store(verbosity.clamp(-1, 2), Ordering::Relaxed);
    static LOGGER: Logger = Logger;
    let _ = log::set_logger(&LOGGER);
    log::set_max_level(max_level().to_level_filter());
}

/// Whether `-v` (or `-vv`) was given: lists that are shortened by default are shown whole.
pub fn verbose() -> bool {
    VERBOSITY.load(Ordering::Relaxed) >= 1
}

/// Whether bars are drawn: standard error is a terminal and the verbosity is not quiet.
pub fn bars_enabled() -> bool {
    VERBOSITY.load(Ordering::Relaxed) >= 0 && std::io::stderr().is_terminal()
}

/// A progress bar for `len` steps of one stage; hidden on a pipe or when quiet.
#[derive(Clone)]
pub struct Bar(ProgressBar);

impl Bar {
    /// A bar titled `what` (e.g. `"raycast"`) over `len` items named `unit` (e.g. `"views"`).
    pub fn new(what: &str, len: u64, unit: &str) -> Bar {
        if !bars_enabled() {
            return Bar(ProgressBar::hidden());
        }
        let bar = multi().add(ProgressBar::new(len));
        let template = format!(
            "{{prefix:>10}} [{{bar:30}}] {{pos}}/{{len}} {unit} {{elapsed}} (eta {{eta}}) {{msg}}"
        );
        bar.set_style(
            ProgressStyle::with_template(&template)
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        bar.set_prefix(what.to_string());
        bar.enable_steady_tick(Duration::from_millis(250));
        Bar(bar)
    }

    /// A bar that never draws (library callers without a terminal, tests).
    pub fn hidden() -> Bar {
        Bar(ProgressBar::hidden())
    }

    /// Advances by `n`.
    pub fn inc(&self, n: u64) {
        self.0.inc(n);
    }

    /// Sets the text after the counter (e.g. the current loss).
    pub fn message(&self, msg: impl Into<std::borrow::Cow<'static, str>>) {
        self.0.set_message(msg);
    }

    /// Removes the bar from the terminal.
    pub fn finish(&self) {
        self.0.finish_and_clear();
    }
}

/// Peak resident memory of this process in MB (`VmHWM` of `/proc/self/status`; `None` where
/// the file does not exist).
pub fn peak_rss_mb() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// Logs the line a stage ends with: `"<stage>: <what> in <t> s (peak <m> MB)"`.
pub fn done(stage: &str, what: &str, seconds: f64) {
    match peak_rss_mb() {
        Some(mb) => log::info!("{stage}: {what} in {seconds:.2} s (peak memory {mb:.0} MB)"),
        None => log::info!("{stage}: {what} in {seconds:.2} s"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn peak_memory_is_positive_on_linux() {
        if std::path::Path::new("/proc/self/status").exists() {
            let mb = peak_rss_mb().expect("VmHWM is readable");
            assert!(mb > 1.0 && mb < 1e6, "{mb}");
        }
    }
}
