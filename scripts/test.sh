#!/usr/bin/env bash
# The test command of the README: installs what is missing, then runs every test
# (unit, integration, the CGAL, Open3D, NumPy and pycocotools reference cross-checks against
# ../shared data) and ends with one totals line.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
python3 scripts/test_cgal_reference.py
log=$(mktemp)
status=0
cargo test --release 2>&1 | tee "$log" || status=$?
read -r passed failed < <(awk '/^test result:/ { for (i = 1; i <= NF; i++) { if ($(i+1) ~ /^passed/) p += $i; if ($(i+1) ~ /^failed/) f += $i } } END { print p + 0, f + 0 }' "$log")
rm -f "$log"
echo "tests: ${passed:-0} passed, ${failed:-0} failed"
exit "$status"
