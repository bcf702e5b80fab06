//! The Slurm batch scripts of a plan: one job array per resource class (array index = tile
//! index, `#SBATCH --mem/--cpus-per-task/--time` from the tiles' sizes), a merge job that
//! depends on all of them (`--dependency=afterok:…`), and `P/slurm.sh`, which submits them.
//! Every task runs `gs4city run-plan P --tile $SLURM_ARRAY_TASK_ID` (the binary that wrote the
//! plan, or `$GS4CITY`).
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::{Plan, Resources, TileError};

/// Shell-quotes a path.
fn q(p: &Path) -> String {
    format!("'{}'", p.display().to_string().replace('\'', "'\\''"))
}

/// Writes `slurm.sh` and `slurm/*.sbatch` into `dir`, for a plan that will live at `final_dir`.
pub fn write(dir: &Path, final_dir: &Path, plan: &Plan) -> Result<Vec<PathBuf>, TileError> {
    let abs = if final_dir.is_absolute() {
        final_dir.to_path_buf()
    } else {
        std::env::current_dir()
            .map_err(|err| TileError::Io {
                path: final_dir.to_path_buf(),
                err,
            })?
            .join(final_dir)
    };
    let exe = plan
        .exe
        .as_ref()
        .map(|e| e.display().to_string())
        .unwrap_or_else(|| "gs4city".into());
    let sdir = dir.join("slurm");
    crate::fsutil::create_dir(&sdir.join("logs"))?;
    let mut classes: BTreeMap<(u64, usize, u64), Vec<usize>> = BTreeMap::new();
    for t in plan.tiles.iter().filter(|t| t.runnable) {
        let Resources {
            cpus,
            mem_mb,
            time_min,
        } = t.resources;
        // Time rounded up to 30 min so that tiles of one memory class share one array.
        let time = time_min.div_ceil(30) * 30;
        classes
            .entry((mem_mb, cpus, time))
            .or_default()
            .push(t.index);
    }
    let logs = abs.join("slurm/logs");
    let mut written = Vec::new();
    let mut submit = String::from(
        "#!/bin/bash\n# Submits the tile plan to Slurm: one job array per resource class, then the merge\n\
         # (afterok on every array). Written by `gs4city tile`; run it from any directory.\n\
         set -euo pipefail\n",
    );
    submit.push_str(&format!("P={}\n", q(&abs)));
    let mut deps = Vec::new();
    for (k, ((mem, cpus, time), idx)) in classes.iter().enumerate() {
        let name = format!("tiles_{k}.sbatch");
        let array = idx
            .iter()
            .map(|i| i.to_string())
            .collect::<Vec<_>>()
            .join(",");
        let text = format!(
            "#!/bin/bash\n\
             #SBATCH --job-name=gs4city-tiles-{k}\n\
             #SBATCH --array={array}\n\
             #SBATCH --cpus-per-task={cpus}\n\
             #SBATCH --mem={mem}M\n\
             #SBATCH --time={time}\n\
             #SBATCH --output={logs}/tile_%a.out\n\
             # One task per tile (the array index is the tile index of plan.json).\n\
             set -euo pipefail\n\
             GS4CITY=\"${{GS4CITY:-{exe}}}\"\n\
             exec \"$GS4CITY\" -q run-plan {p} --tile \"$SLURM_ARRAY_TASK_ID\"\n",
            logs = logs.display(),
            p = q(&abs),
        );
        crate::fsutil::write_bytes(&sdir.join(&name), text.as_bytes())?;
        written.push(sdir.join(&name));
        submit.push_str(&format!(
            "J{k}=$(sbatch --parsable \"$P/slurm/{name}\")\necho \"tiles ({} tasks, {mem} MB each): job $J{k}\"\n",
            idx.len()
        ));
        deps.push(format!("$J{k}"));
    }
    let merge = format!(
        "#!/bin/bash\n\
         #SBATCH --job-name=gs4city-merge\n\
         #SBATCH --cpus-per-task=2\n\
         #SBATCH --mem={mem}M\n\
         #SBATCH --time=120\n\
         #SBATCH --output={logs}/merge.out\n\
         set -euo pipefail\n\
         GS4CITY=\"${{GS4CITY:-{exe}}}\"\n\
         exec \"$GS4CITY\" -q merge {p} --out {m}\n",
        mem = merge_mem_mb(plan),
        logs = logs.display(),
        p = q(&abs),
        m = q(&abs.join("merged")),
    );
    crate::fsutil::write_bytes(&sdir.join("merge.sbatch"), merge.as_bytes())?;
    written.push(sdir.join("merge.sbatch"));
    if deps.is_empty() {
        submit.push_str("M=$(sbatch --parsable \"$P/slurm/merge.sbatch\")\n");
    } else {
        submit.push_str(&format!(
            "M=$(sbatch --parsable --dependency=afterok:{} \"$P/slurm/merge.sbatch\")\n",
            deps.join(":")
        ));
    }
    submit.push_str("echo \"merge: job $M (into $P/merged)\"\n");
    let sh = dir.join("slurm.sh");
    crate::fsutil::write_bytes(&sh, submit.as_bytes())?;
    written.push(sh);
    Ok(written)
}

/// Memory of the merge job: the scene's Gaussians in memory (the semantic PLY and the test
/// views' render hold the whole PLY), with room.
fn merge_mem_mb(plan: &Plan) -> u64 {
    let mb = 1024.0 + 3.0 * plan.ply_bytes as f64 / 1e6;
    ((mb / 512.0).ceil() * 512.0) as u64
}
