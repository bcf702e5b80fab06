#!/usr/bin/env bash
# The test command of the README: installs what is missing, then runs every test
# (unit, integration, the CGAL and Open3D cross-checks against ../shared data when present).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo test --release 2>&1
