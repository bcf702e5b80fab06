#!/usr/bin/env bash
# CPU, peak memory and disk per tile of `gs4city tile` + `run-plan` on a SIMULATED scene
# replicated K× (scripts/replicate_scene.py), for each K and each set of `tile` options,
# interleaved (K outer, variants inner) so that the machine's load falls on all of them alike
# (BENCHMARKS.md, "Tiles").
#
#   bash scripts/tile_scaling.sh SRC WORK "1 4 16" "--crop-below 0" "" [more variants…]
#
# SRC: a scene folder (e.g. `gs4city synth --preset small --out SRC`); WORK: a scratch folder
# (one replicated scene and one plan at a time; removed as it goes). Tiles of $SIZE m (72),
# margin $MARGIN m (10). Prints one TSV row per (K, variant): tiles, views assigned, views
# cropped, CPU s of all tiles (user + system, the tiles' status.json), the plan's seconds and
# peak, peak memory per tile (max), disk per tile (max, with the cache).
set -euo pipefail
src=$1 work=$2 ks=$3
shift 3
bin=${GS4CITY:-target/release/gs4city}
size=${SIZE:-72} margin=${MARGIN:-10}
mkdir -p "$work"
printf 'K\tvariant\ttiles\tviews\tcropped\ttile_cpu_s\tplan_s\tplan_peak_mb\tpeak_mb_max\tdisk_mb_max\twall_s\n'
for k in $ks; do
  rm -rf "$work/scene_x$k"
  python3 "$(dirname "$0")/replicate_scene.py" "$src" "$work/scene_x$k" "$k" >/dev/null
  for variant in "$@"; do
    p="$work/plan_x$k"
    rm -rf "$p"
    # shellcheck disable=SC2086
    "$bin" tile --scene "$work/scene_x$k" --size "$size" --margin "$margin" $variant --out "$p" >/dev/null 2>&1
    t0=$(date +%s.%N)
    "$bin" run-plan "$p" --jobs 2 --no-test-views >"$work/run_x$k.log" 2>&1
    t1=$(date +%s.%N)
    python3 - "$p" "$k" "$variant" "$(echo "$t1 - $t0" | bc)" <<'EOF'
import json, sys, glob, os
p, k, variant, wall = sys.argv[1:]
plan = json.load(open(os.path.join(p, "plan.json")))
st = [json.load(open(f)) for f in glob.glob(os.path.join(p, "tiles/*/status.json"))]
views = sum(t["views"] for t in plan["tiles"] if t["runnable"])
cropped = sum(t.get("views_cropped", 0) for t in plan["tiles"] if t["runnable"])
print("\t".join(str(x) for x in [
    k, variant or "(default)", len(st), views, cropped,
    round(sum(s["cpu_seconds"] for s in st), 1),
    round(plan["seconds"], 1), round(plan["peak_rss_mb"] or 0),
    round(max(s["peak_rss_mb"] for s in st)),
    round(max(s["disk_bytes"] for s in st) / 1e6),
    round(float(wall), 1)]))
EOF
    rm -rf "$p"
  done
  rm -rf "$work/scene_x$k"
done
