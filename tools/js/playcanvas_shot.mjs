// Draws the tiles of a 3D Tiles tileset of KHR_gaussian_splatting glTF tiles with the PlayCanvas
// engine (npm `playcanvas`, whose glTF loader reads KHR_gaussian_splatting) in headless Chromium
// (Debian's /usr/bin/chromium driven by npm `playwright-core`, WebGL2 on SwiftShader), from
// given camera views, and measures each picture. PlayCanvas is no 3D Tiles client: the script
// walks tileset.json itself, loads the content of every tile of the chosen kind (the leaves, or
// every tile at one depth) as a glTF container and places it by the chain of tile transforms
// below the root, in the root's frame (east, north, up), glTF Y-up content turned Z-up as
// 3D Tiles does.
// Usage: node playcanvas_shot.mjs TILESET_DIR OUT_PREFIX SPEC_JSON
//   SPEC_JSON: {"width": 640, "height": 480, "fov": 40 (vertical, degrees), "depth": null (the
//   leaves) or N, "views": [{"name", "eye": [e, n, u], "target": [e, n, u], "up": [e, n, u]}]}
// Prints one JSON object: the tiles and splats loaded, and per view the peak green value, the
// pixels at or above half of it (count, centroid, second moments), the lit pixels (> 30 in
// r + g + b) and the screenshot OUT_PREFIX-NAME.png.
import path from "node:path";
import { fileURLToPath } from "node:url";
import { launchChromium } from "./chromium.mjs";
import { measureCanvas, serveFolders } from "./shot_server.mjs";

const here = path.dirname(fileURLToPath(import.meta.url));
const [tilesetDir, outPrefix, specJson] = process.argv.slice(2);
const spec = JSON.parse(specJson);
const pcDir = path.join(here, "node_modules/playcanvas/build");

const page = `<!doctype html>
<html><head><meta charset="utf-8">
<style>html,body{margin:0;background:#000}canvas{display:block}</style></head>
<body><canvas id="c" width="${spec.width}" height="${spec.height}" style="width:${spec.width}px;height:${spec.height}px"></canvas>
<script type="module">
import * as pc from "/pc/playcanvas.mjs";
const spec = ${JSON.stringify(spec)};
const Y_UP_TO_Z_UP = [1, 0, 0, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 0, 0, 1]; // column-major
function mul(a, b) {
  const o = new Array(16).fill(0);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) for (let k = 0; k < 4; k++) o[c * 4 + r] += a[k * 4 + r] * b[c * 4 + k];
  return o;
}
const I = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
(async () => {
  try {
    const canvas = document.getElementById("c");
    const app = new pc.Application(canvas, {
      graphicsDeviceOptions: { preserveDrawingBuffer: true, antialias: false, alpha: false },
    });
    app.setCanvasFillMode(pc.FILLMODE_NONE);
    app.setCanvasResolution(pc.RESOLUTION_FIXED, spec.width, spec.height);
    app.start();
    const camera = new pc.Entity("camera");
    camera.addComponent("camera", { clearColor: new pc.Color(0, 0, 0, 1), fov: spec.fov, nearClip: 0.1, farClip: 100000 });
    app.root.addChild(camera);
    const tileset = await fetch("/tiles/tileset.json").then((r) => r.json());
    // Tiles to draw: (uri, 4×4 from the content to the root frame).
    const chosen = [];
    const walk = (tile, m, depth) => {
      const t = depth === 0 ? I : (tile.transform ?? I);
      const mm = mul(m, t);
      const leaf = !(tile.children && tile.children.length);
      const want = spec.depth === null || spec.depth === undefined ? leaf : depth === spec.depth || (leaf && depth < spec.depth);
      if (tile.content && want) chosen.push([tile.content.uri, mul(mm, Y_UP_TO_Z_UP)]);
      for (const c of tile.children ?? []) walk(c, mm, depth + 1);
    };
    walk(tileset.root, I, 0);
    let splats = 0;
    for (const [uri, m] of chosen) {
      const asset = await new Promise((resolve, reject) => {
        app.assets.loadFromUrl("/tiles/" + uri, "container", (err, a) => (err ? reject(err) : resolve(a)));
      });
      for (const g of asset.resource.gsplats ?? []) splats += g.resource?.numSplats ?? g.resource?.gsplatData?.numSplats ?? 0;
      const e = asset.resource.instantiateRenderEntity();
      const mat = new pc.Mat4();
      mat.set(m);
      e.setLocalPosition(mat.getTranslation());
      e.setLocalRotation(new pc.Quat().setFromMat4(mat));
      app.root.addChild(e);
    }
    window.__pc = { app, camera, pc };
    window.__loaded = { tiles: chosen.length, uris: chosen.map((c) => c[0]), splats, gsplatAssets: app.assets.filter((a) => a.type === "gsplat").length };
  } catch (e) {
    window.__loaded = { error: String(e && e.stack || e) };
  }
})();
</script></body></html>`;

const server = await serveFolders(page, { "/pc": pcDir, "/tiles": tilesetDir });
const port = server.address().port;

const browser = await launchChromium();
const result = { ok: false, views: {} };
try {
  const ctx = await browser.newContext({ viewport: { width: spec.width, height: spec.height } });
  const tab = await ctx.newPage();
  const logs = [];
  tab.on("console", (m) => logs.push(`${m.type()}: ${m.text()}`));
  tab.on("pageerror", (e) => logs.push(`pageerror: ${e}`));
  await tab.goto(`http://127.0.0.1:${port}/`);
  await tab.waitForFunction(() => window.__loaded !== undefined, null, { timeout: 240000 });
  result.loaded = await tab.evaluate(() => window.__loaded);
  if (!result.loaded.error) {
    for (const v of spec.views) {
      await tab.evaluate((v) => {
        const { camera, pc } = window.__pc;
        camera.setPosition(v.eye[0], v.eye[1], v.eye[2]);
        camera.lookAt(new pc.Vec3(v.target[0], v.target[1], v.target[2]), new pc.Vec3(v.up[0], v.up[1], v.up[2]));
      }, v);
      // PlayCanvas sorts in a worker: wait until the picture holds still (3 reads 1 s apart).
      const measure = () => tab.evaluate(measureCanvas, ["#c"]);
      let last = null, same = 0, m = null;
      const t0 = Date.now();
      while (Date.now() - t0 < 180000) {
        await new Promise((r) => setTimeout(r, 1000));
        m = await measure();
        const key = JSON.stringify(m);
        same = key === last ? same + 1 : 0;
        last = key;
        if (same >= 2 && m.lit > 0) break;
      }
      m.seconds = (Date.now() - t0) / 1000;
      await tab.screenshot({ path: `${outPrefix}-${v.name}.png`, timeout: 180000 });
      result.views[v.name] = m;
    }
    result.ok = true;
  }
  result.logs = logs.filter((l) => !l.startsWith("debug")).slice(0, 20);
} catch (e) {
  result.error = String(e && e.stack || e);
} finally {
  await browser.close();
  server.close();
}
console.log(JSON.stringify(result));
