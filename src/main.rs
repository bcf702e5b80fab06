//! `gs4city` binary: parse the command line, run it, map the result to an exit code (1: an
//! error; 3: a text query that matched nothing, `cli::NO_MATCH_STATUS`).
use std::process::ExitCode;

fn main() -> ExitCode {
    match gs4city::cli::main() {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            let status = gs4city::cli::exit_status(&err);
            if status == gs4city::cli::NO_MATCH_STATUS {
                eprintln!("{err:#}");
            } else {
                eprintln!("error: {err:#}");
            }
            ExitCode::from(status)
        }
    }
}
