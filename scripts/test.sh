#!/usr/bin/env bash
# The test command of the README: installs what is missing, then runs every test
# (unit, integration, the CGAL, Open3D, NumPy, pycocotools and plyfile reference cross-checks,
# the simulated ground truth against its NumPy re-derivation, against ../shared data) and ends
# with one totals line (scripts/test_totals.sh): `tests: P passed, F failed, S skipped, I ignored
# (N run)`, which add up to the tests cargo ran.
#
# A Python cross-check whose package python3 cannot import is never counted as passed: it prints
# `SKIPPED: <test>: <why>` into $GS4CITY_SKIP_LOG and is counted as skipped, once per test. Once
# setup has installed the packages (always, unless GS4CITY_SKIP_PY=1) a missing package fails the
# test (GS4CITY_REQUIRE_PY=1), as it does where CI is set. The Slurm test needs root: another user
# gets it skipped with that reason (CI runs as root and runs it).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ "${GS4CITY_SKIP_PY:-0}" != 1 ]; then export GS4CITY_REQUIRE_PY=1; fi
python3 scripts/test_cgal_reference.py
log=$(mktemp)
skips=$(mktemp)
export GS4CITY_SKIP_LOG="$skips"
cargo_status=0
cargo test --release 2>&1 | tee "$log" || cargo_status=$?
status=0
bash scripts/test_totals.sh "$log" "$skips" || status=1
if [ "$cargo_status" != 0 ]; then status=$cargo_status; fi
rm -f "$log" "$skips"
exit "$status"
