#!/usr/bin/env bash
# Copies the splat renderer of `gs4city view` from the npm packages pinned in tools/js
# (package.json + package-lock.json: @sparkjsdev/spark, three) into src/view/vendor/, with their
# licences. The binary embeds these files (src/view/assets.rs), so an installed gs4city needs
# neither npm nor the checkout. Run after changing the pins:
#   (cd tools/js && npm ci) && bash scripts/vendor_viewer.sh
# tests/view.rs (`vendored_renderer_is_the_npm_package`) checks the copies byte for byte.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
nm="$root/tools/js/node_modules"
out="$root/src/view/vendor"
for p in "$nm/@sparkjsdev/spark/package.json" "$nm/three/package.json"; do
  [ -f "$p" ] || { echo "vendor_viewer: $p is missing: run npm ci in tools/js first" >&2; exit 1; }
done
mkdir -p "$out/three/addons/postprocessing"
cp "$nm/@sparkjsdev/spark/dist/spark.module.min.js" "$out/spark.module.min.js"
cp "$nm/@sparkjsdev/spark/LICENSE" "$out/LICENSE.spark"
cp "$nm/three/build/three.module.min.js" "$nm/three/build/three.core.min.js" "$out/"
cp "$nm/three/examples/jsm/postprocessing/Pass.js" "$out/three/addons/postprocessing/Pass.js"
cp "$nm/three/LICENSE" "$out/LICENSE.three"
node -e '
const nm = process.argv[1];
for (const p of ["@sparkjsdev/spark", "three"]) {
  const j = require(nm + "/" + p + "/package.json");
  console.log(`vendor_viewer: ${j.name} ${j.version} (${j.license})`);
}' "$nm"
du -cb "$out"/*.js "$out"/three/addons/postprocessing/Pass.js | tail -1 | sed 's/^/vendor_viewer: bytes of JavaScript: /'
