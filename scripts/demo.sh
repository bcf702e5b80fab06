#!/usr/bin/env bash
# The README's demo: installs what is missing, builds, and runs the pipeline stages that exist
# on the bundled data (data/), printing where the results are.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo build --release --quiet
out=out/demo
rm -rf "$out"
./target/release/gs4city citymodel data/citygml --out "$out/citymodel"
echo
echo "demo: results in $out/citymodel (mesh.ply, semantics.json, summary.json, alignment.json)"
