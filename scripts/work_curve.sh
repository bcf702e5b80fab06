#!/usr/bin/env bash
# The speed–error curve of the work knobs (BENCHMARKS.md, "Work knobs"; docs/quality.md).
#
#   scripts/work_curve.sh SCENE OUT_DIR 'LABEL|FLAGS' ['LABEL|FLAGS' ...]
#
# Runs `gs4city -q run --scene SCENE --out OUT_DIR/LABEL FLAGS` for each point, one after the
# other, under `/usr/bin/time -v`, and prints one Markdown row per point: wall time, CPU time
# (user + system), peak memory, the run folder's size on disk, paper-protocol fine mIoU and the
# IoU of every fine class (from R/eval/metrics.json; the scene must have gt/). Each run folder
# is deleted after its row unless KEEP=1. GS4CITY (default: the release build beside this
# script) names the binary. DROP_CACHES=1 (root) empties the page cache before each point, so
# that every point writes its files into the same free memory. Example:
#
#   scripts/work_curve.sh S /tmp/curve 'full|--quality full' 'default|' 'half|--train-scale 2'
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
bin="${GS4CITY:-$here/target/release/gs4city}"
scene="$1"
out="$2"
shift 2
mkdir -p "$out"
printf '| point | flags | wall s | CPU s (user + sys) | peak MB | disk MB | fine mIoU | door | roof | wall | window | car | person | tree |\n'
printf '|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n'
for point in "$@"; do
    label="${point%%|*}"
    flags="${point#*|}"
    run="$out/$label"
    rm -rf "$run"
    if [ "${DROP_CACHES:-0}" = 1 ]; then
        sync
        echo 1 > /proc/sys/vm/drop_caches
    fi
    # shellcheck disable=SC2086
    /usr/bin/time -v -o "$out/$label.time" "$bin" -q run --scene "$scene" --out "$run" $flags \
        > "$out/$label.log" 2>&1 || {
        echo "| $label | \`$flags\` | failed: $(tail -1 "$out/$label.log") |"
        continue
    }
    python3 - "$out/$label.time" "$run" "$label" "$flags" <<'EOF'
import json, os, sys
tf, run, label, flags = sys.argv[1:5]
t = {}
for line in open(tf):
    k, _, v = line.strip().rpartition(': ')
    t[k] = v
def secs(s):
    parts = [float(x) for x in s.split(':')]
    return sum(p * 60 ** i for i, p in enumerate(reversed(parts)))
wall = secs(t['Elapsed (wall clock) time (h:mm:ss or m:ss)'])
cpu = float(t['User time (seconds)']) + float(t['System time (seconds)'])
rss = int(t['Maximum resident set size (kbytes)']) / 1024
disk = 0
for root, _, files in os.walk(run):
    for f in files:
        p = os.path.join(root, f)
        if not os.path.islink(p):
            disk += os.stat(p).st_size
m = json.load(open(os.path.join(run, 'eval', 'metrics.json')))['paper']
iou = m['iou']
cls = ['door', 'roof', 'wall', 'window', 'car', 'person', 'tree']
def pct(v):
    return '–' if v is None else f"{100 * v:.2f}"
cells = ' | '.join(pct(iou[c]['mean']) if c in iou else '–' for c in cls)
print(f"| {label} | `{flags}` | {wall:.1f} | {cpu:.1f} ({t['User time (seconds)']} + "
      f"{t['System time (seconds)']}) | {rss:.0f} | {disk / 1e6:.0f} | "
      f"{pct(m['miou']['mean'])} | {cells} |")
EOF
    if [ "${KEEP:-0}" != 1 ]; then
        rm -rf "$run"
    if [ "${DROP_CACHES:-0}" = 1 ]; then
        sync
        echo 1 > /proc/sys/vm/drop_caches
    fi
    fi
done
