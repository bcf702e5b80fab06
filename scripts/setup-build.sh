#!/usr/bin/env bash
# Installs what building and running gs4city needs on Debian 12 (run as root, or with sudo
# available), and nothing else: `scripts/demo.sh` runs this. Debian packages named as arguments
# are installed with them (`scripts/setup.sh` passes the tests' packages). Idempotent: skips what
# is already there.
#
# Build (Cargo.toml, build.rs):
#   build-essential, pkg-config       the C/C++ compilers of the -sys crates; pkg-config finds PROJ, SQLite
#   libembree-dev                     Embree 3 (build.rs: bindgen over ffi/embree.h, links libembree3)
#   libclang1-14, libclang-common-14-dev, clang
#                                     libclang and its builtin headers, loaded at build time by bindgen
#                                     (build.rs, proj-sys) and the opencv crate's binding generator,
#                                     which also runs the clang binary to find the system headers
#   libopencv-{core,imgproc,imgcodecs}-dev
#                                     the three OpenCV modules gs4city links (src/imageio.rs); found
#                                     through the OPENCV_* variables of .cargo/config.toml
#   libproj-dev                       PROJ 9.1 (the proj crate; `export --format 3dtiles`); it brings
#                                     libsqlite3-dev, which rusqlite links (`query`'s SQLite output)
# Run (the binary's own libraries: `readelf -d target/release/gs4city | grep NEEDED`):
#   libembree3-3, libopencv-{core,imgproc,imgcodecs}406, libproj25 (+ proj-data), libsqlite3-0,
#   all installed as dependencies of the packages above.
# Rust itself (1.85 or newer, Cargo.toml's rust-version) comes from rustup: Debian 12's rustc is
# too old. This script does not install it.
set -euo pipefail
SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
pkgs=(build-essential pkg-config libembree-dev libclang1-14 libclang-common-14-dev clang
      libopencv-core-dev libopencv-imgproc-dev libopencv-imgcodecs-dev libproj-dev "$@")
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup-build: installing ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends -o DPkg::Lock::Timeout=600 "${missing[@]}" >/dev/null
fi
if ! command -v cargo >/dev/null 2>&1; then
  echo "setup-build: cargo not found: install Rust 1.85 or newer with rustup (https://rustup.rs), then run this again" >&2
  exit 1
fi
echo "setup-build: done"
