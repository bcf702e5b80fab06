#!/usr/bin/env bash
# Tiles of a SIMULATED city (`gs4city synth --preset street --blocks NxN`, docs/synth.md `[city]`:
# the copies are drawn in each other's images) through `gs4city tile` + `run-plan`, one row per set
# of `tile` options, against the untiled run where it is given (BENCHMARKS.md, "Tiles").
#
#   bash scripts/city_scaling.sh SCENE WORK UNTILED_RUN|- "" "--crop-below 0.3" [more variants…]
#
# SCENE: the synth scene; WORK: a scratch folder (one plan at a time, removed after its figures
# are taken; the rows, the merge summaries and the join scores stay in WORK); UNTILED_RUN: `gs4city
# run --scene SCENE --out R` (or `-`: no comparison). Tiles of $SIZE m (60), margin $MARGIN m (25),
# `run-plan --jobs $JOBS` (2); with SLURM=1 the plan runs as Slurm job arrays instead, on the
# single-node Slurm of `scripts/slurm_test.sh` (root; SLURM_PLAN mode). Prints one TSV row per
# variant: tiles run, views joined, views cropped, CPU s of all tiles (user + system, the tiles'
# status.json), peak memory per tile (max), disk per tile (max, with the cache), views per tile
# (max), wall s, merged fine mIoU of the test views, Gaussians keeping the untiled run's class, the
# merge's joined groups; and writes WORK/<variant>.joins.txt (scripts/score_tile_joins.py: objects
# split by borders before and after the join).
#
# Disk: once a tile's run is done, run-plan removes its cache and the per-view maps the merge does
# not read (docs/tile.md); the disk per tile in the row is the tile job's own peak (status.json).
set -euo pipefail
scene=$1 work=$2 untiled=$3
shift 3
here=$(cd "$(dirname "$0")" && pwd)
bin=$(realpath "${GS4CITY:-target/release/gs4city}")
size=${SIZE:-60} margin=${MARGIN:-25} jobs=${JOBS:-2}
mkdir -p "$work"
printf 'variant\ttiles\tviews\tcropped\ttile_cpu_s\tpeak_mb_max\tdisk_mb_max\tviews_max\twall_s\tfine_miou\tkeep_class\tjoined\n'
for variant in "$@"; do
  tag=$(echo "${variant:-default}" | tr -c 'a-zA-Z0-9.\n' '_')
  p="$work/plan_$tag"
  rm -rf "$p"
  # shellcheck disable=SC2086
  "$bin" -q tile --scene "$scene" --size "$size" --margin "$margin" $variant --out "$p" >"$work/$tag.tile.log" 2>&1
  t0=$(date +%s.%N)
  if [ "${SLURM:-0}" = 1 ]; then
    GS4CITY="$bin" SLURM_PLAN="$p" bash "$here/slurm_test.sh" "$bin" >"$work/$tag.run.log" 2>&1
  else
    "$bin" -q run-plan "$p" --jobs "$jobs" >"$work/$tag.run.log" 2>&1
  fi
  t1=$(date +%s.%N)
  cp "$p/merged/summary.json" "$work/$tag.merged_summary.json"
  python3 - "$p" "$variant" "$(echo "$t1 - $t0" | bc)" "$untiled" <<'EOF'
import json, sys, glob, os
import numpy as np
p, variant, wall, untiled = sys.argv[1:]
plan = json.load(open(os.path.join(p, "plan.json")))
st = [json.load(open(f)) for f in glob.glob(os.path.join(p, "tiles/*/status.json"))]
m = json.load(open(os.path.join(p, "merged/summary.json")))
run = [t for t in plan["tiles"] if t["runnable"]]
keep = "-"
if untiled != "-":
    a = np.load(os.path.join(untiled, "lift/gaussians.npy"))
    b = np.load(os.path.join(p, "merged/lift/gaussians.npy"))
    keep = f"{100 * (a[:, 1] == b[:, 1]).mean():.2f}%"
print("\t".join(str(x) for x in [
    variant or "(default)", len(st), sum(t["views"] for t in run),
    sum(t.get("views_cropped", 0) for t in run),
    round(sum(s["cpu_seconds"] for s in st), 1),
    round(max(s["peak_rss_mb"] for s in st)),
    round(max(s["disk_bytes"] for s in st) / 1e6),
    max(t["views"] for t in run),
    round(float(wall), 1),
    round(100 * m["paper_fine_miou"], 2) if m.get("paper_fine_miou") is not None else "-",
    keep, m["joined_groups"]]), flush=True)
EOF
  python3 "$here/score_tile_joins.py" "$scene" "$p" "$untiled" --fractions 0.4 >"$work/$tag.joins.txt" 2>&1 || true
  rm -rf "$p"
done
