//! `gs4city check`: the whole scene folder checked before any stage runs (`crate::inspect`).
use std::path::PathBuf;

use clap::Args;

use crate::inspect::{self, CheckOptions, CheckReport, Severity};

#[derive(Debug, Args)]
pub struct CheckArgs {
    /// Scene folder (`docs/design.md`): images/, sparse/0/, point_cloud.ply, citymodel/*.gml +
    /// alignment.json, optional masks/, features/, gt/.
    #[arg(long)]
    pub scene: PathBuf,
    /// A scene without citymodel/alignment.json is fine (`run --local-origin`).
    #[arg(long)]
    pub local_origin: bool,
    #[command(flatten)]
    pub config: super::groups::ConfigArg,
    #[command(flatten, next_help_heading = "The alignment verdict (config [check])")]
    pub tuning: super::groups::CheckTuning,
    /// Write the report as JSON to this file.
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
}

impl CheckArgs {
    /// Validated options.
    pub fn options(&self) -> anyhow::Result<CheckOptions> {
        let t = super::groups::merged(&self.config.load()?.check, &self.tuning);
        let o = CheckOptions {
            local_origin: self.local_origin,
            max_offset_m: t.max_offset,
            ..CheckOptions::default()
        };
        o.validate()?;
        Ok(o)
    }
}

/// How many warnings of one file are printed without `-v`.
pub const SHOWN: usize = 5;

/// Prints the findings: every error, the first [`SHOWN`] warnings of each file (all with `-v`),
/// and the notes (not with `-q`).
pub fn print_report(r: &CheckReport, notes: bool) {
    for f in r.of(Severity::Error) {
        eprintln!("error: {f}");
    }
    let mut per_file: std::collections::BTreeMap<&std::path::Path, usize> = Default::default();
    for f in r.of(Severity::Warning) {
        let n = per_file.entry(&f.file).or_default();
        *n += 1;
        if *n <= SHOWN || crate::progress::verbose() {
            eprintln!("warning: {f}");
        }
    }
    for (file, n) in per_file {
        if n > SHOWN && !crate::progress::verbose() {
            eprintln!(
                "warning: {}: {} more warnings (-v shows them all)",
                file.display(),
                n - SHOWN
            );
        }
    }
    if notes {
        for f in r.of(Severity::Note) {
            eprintln!("note: {f}");
        }
    }
}

pub fn run(args: &CheckArgs) -> anyhow::Result<()> {
    let opts = args.options()?;
    let r = inspect::check(&args.scene, &opts);
    if let Some(p) = &args.json {
        crate::fsutil::write_json(p, &r)?;
    }
    print_report(&r, log::log_enabled!(log::Level::Info));
    let errors = r.of(Severity::Error).count();
    let warnings = r.of(Severity::Warning).count();
    let line = format!(
        "{} views, {} images, {} Gaussians, {} CityGML files: {errors} errors, {warnings} warnings ({:.1} s)",
        r.views, r.images, r.gaussians, r.gml_files, r.seconds
    );
    if errors > 0 {
        anyhow::bail!("check {}: {line}", args.scene.display());
    }
    println!("check {}: {line}", args.scene.display());
    Ok(())
}
