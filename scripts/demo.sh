#!/usr/bin/env bash
# The README's demo: installs what is missing, builds, and runs `gs4city demo`: the bundled
# CityGML (data/) → a SIMULATED scene (synth, small preset) → citymodel → raycast → lift → eval
# → out/demo/run/report.html. Ends by printing the metrics table and the report path.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --release --quiet
./target/release/gs4city demo --out out/demo
