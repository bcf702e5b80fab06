//! `gs4city` binary: parse the command line, run it, map the result to an exit code.
use std::process::ExitCode;

fn main() -> ExitCode {
    match gs4city::cli::main() {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::from(1)
        }
    }
}
