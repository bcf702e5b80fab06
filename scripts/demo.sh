#!/usr/bin/env bash
# The README's demo: installs what building and running gs4city needs (scripts/setup-build.sh:
# Debian packages only; no browser, Slurm, npm or Python package), builds the binary and runs
# `gs4city demo`: the bundled CityGML (data/) → a SIMULATED scene (synth, small preset) → every
# stage → out/demo/run/report.html. Ends by printing the metrics table and the report path.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-build.sh
cargo build --release --locked --bin gs4city
./target/release/gs4city demo --out out/demo
