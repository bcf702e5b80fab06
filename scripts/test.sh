#!/usr/bin/env bash
# The test command of the README: installs what is missing, then runs every test
# (unit, integration, the CGAL and Open3D reference cross-checks against ../shared data).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
python3 scripts/test_cgal_reference.py
cargo test --release 2>&1
