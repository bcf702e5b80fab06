#!/usr/bin/env bash
# Regenerates the rows of README.md's results table: runs the demo and the `street` preset, each
# with the default (fused masks) and the city-model-only supervision, and prints one Markdown
# row per run (paper protocol, % per image then averaged over the test views; "–" where the
# class is absent from the test views' ground truth). Paste the rows into README.md's
# "Results" table; tests/readme.rs checks the demo rows against a fresh `gs4city demo`.
#
#   bash scripts/results.sh [--demo-only] [--out DIR]     (default DIR: out/results)
#
# The city-only run resumes the default run's folder (citymodel, raycast and the cache are
# reused; only the vote and eval run again). `street` takes minutes (the synth alone about a
# minute on two cores, the run several); --demo-only stops after the demo (seconds).
# GS4CITY_BIN names the binary (default: target/release/gs4city, built if missing). Needs python3
# (standard library only) to read metrics.json.
set -euo pipefail
cd "$(dirname "$0")/.."
out=out/results
demo_only=0
while [ $# -gt 0 ]; do
  case "$1" in
    --demo-only) demo_only=1 ;;
    --out) out="$2"; shift ;;
    *) echo "results.sh: unknown argument $1" >&2; exit 2 ;;
  esac
  shift
done
bin="${GS4CITY_BIN:-target/release/gs4city}"
if [ ! -x "$bin" ]; then
  cargo build --release --locked --bin gs4city
fi
mkdir -p "$out"
rows="$out/rows.md"
: > "$rows"

# One row from a run folder's eval/metrics.json.
row() { # scene supervision run_dir
  python3 - "$1" "$2" "$3/eval/metrics.json" >> "$rows" <<'EOF'
import json, sys
scene, supervision, path = sys.argv[1:4]
m = json.load(open(path))["paper"]
def pct(x):
    return "–" if x is None else f"{100 * x:.1f}"
cells = [m["coarse"][k]["mean"] for k in ("iou", "accuracy", "precision", "recall")]
cells.append(m["miou"]["mean"])
cells += [m["iou"][c]["mean"] for c in ("door", "roof", "wall", "window", "car", "person", "tree")]
print(f"| {scene} | {supervision} | " + " | ".join(pct(c) for c in cells) + " |")
EOF
}

# scene_dir run_dir label: the default run, then the city-only run in the same folder.
both() {
  "$bin" -q run --scene "$1" --out "$2"
  row "$3" "fused masks (default)" "$2"
  "$bin" -q run --scene "$1" --supervision city --out "$2"
  row "$3" "city model only" "$2"
}

rm -rf "$out/demo"
"$bin" -q demo --out "$out/demo" > /dev/null
both "$out/demo/scene" "$out/demo/run" demo
if [ "$demo_only" != 1 ]; then
  if [ ! -f "$out/street/scene/scene.json" ]; then
    rm -rf "$out/street"
    "$bin" -q synth --preset street --out "$out/street/scene"
  fi
  both "$out/street/scene" "$out/street/run" street
fi
echo "| scene | supervision | IoU | Acc | Prec | Rec | mIoU | Door | Roof | Wall | Window | Car | Person | Tree |"
echo "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
cat "$rows"
