//! `gs4city` binary: parse the command line, run it, map the result to an exit code.
use std::process::ExitCode;

fn main() -> ExitCode {
    match gs4city::cli::main() {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            // A folder locked by another process: a temporary failure (run-plan retries it).
            let busy = err.chain().any(|e| {
                e.downcast_ref::<gs4city::lock::LockError>()
                    .is_some_and(|l| l.is_busy())
            });
            ExitCode::from(if busy { gs4city::lock::EXIT_BUSY } else { 1 })
        }
    }
}
