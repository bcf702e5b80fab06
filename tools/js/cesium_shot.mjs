// Loads a 3D Tiles tileset in CesiumJS (npm `cesium`) in headless Chromium (Debian's
// /usr/bin/chromium driven by npm `playwright-core`, WebGL by SwiftShader), flies to it, takes a
// screenshot and measures it: prints one JSON object with the canvas size, the tileset's
// bounding sphere (centre longitude/latitude/height, its projection on the canvas and radius
// in pixels), the camera's longitude/latitude/height, and per palette colour the pixels that
// show it (and their centroid). Everything is served by a node http server on 127.0.0.1 (the
// tileset, Cesium's build, one page; tiles whose splats are not SPZ-compressed are served with
// their KHR_gaussian_splatting:* semantics renamed, glb_rename.mjs); no Cesium ion, no imagery, no terrain, no internet.
// Usage: node cesium_shot.mjs TILESET_DIR OUT.png PALETTE_JSON [VIEWS_JSON]
//   PALETTE_JSON: {"name": [r, g, b], …} the colours to count.
//   VIEWS_JSON (optional): {"fov": radians (Cesium's: the wider side's), "wait": "splats" or
//   "tiles", "views": [{"name", "eye": [e, n, u], "target": [e, n, u], "up": [e, n, u]}]} in
//   the root tile's frame (east, north, up about its origin): instead of flying to the tileset,
//   the camera is put at each view in turn and the picture measured (the peak green value and
//   the pixels at or above half of it: count, centroid, second moments; OUT-NAME.png). The
//   server counts every tile requested (uri, bytes), in total and per view.
import { writeFile } from "node:fs/promises";
import path from "node:path";
import { fileURLToPath } from "node:url";
import { launchChromium } from "./chromium.mjs";
import { renameGaussianSemantics } from "./glb_rename.mjs";
import { measureCanvas, serveFolders } from "./shot_server.mjs";

const here = path.dirname(fileURLToPath(import.meta.url));
const [tilesetDir, outPng, paletteJson, viewsJson] = process.argv.slice(2);
const palette = JSON.parse(paletteJson);
const viewSpec = viewsJson ? JSON.parse(viewsJson) : null;
const requests = [];
const cesiumDir = path.join(here, "node_modules/cesium/Build/Cesium");

const page = `<!doctype html>
<html><head><meta charset="utf-8">
<link rel="stylesheet" href="/cesium/Widgets/widgets.css">
<style>html,body,#c{margin:0;width:100%;height:100%;overflow:hidden;background:#000}</style>
<script src="/cesium/Cesium.js"></script></head>
<body><div id="c"></div><script>
window.CESIUM_BASE_URL = "/cesium/";
window.__views = ${viewSpec ? "true" : "false"};
(async () => {
  try {
    const viewer = new Cesium.Viewer("c", {
      baseLayer: false, baseLayerPicker: false, geocoder: false, homeButton: false,
      sceneModePicker: false, navigationHelpButton: false, animation: false, timeline: false,
      fullscreenButton: false, infoBox: false, selectionIndicator: false,
      terrainProvider: new Cesium.EllipsoidTerrainProvider(),
      contextOptions: { webgl: { preserveDrawingBuffer: true, antialias: false } },
      msaaSamples: 1,
    });
    viewer.scene.globe.baseColor = Cesium.Color.BLACK;
    viewer.scene.backgroundColor = Cesium.Color.BLACK;
    viewer.scene.skyAtmosphere.show = false;
    viewer.scene.globe.showGroundAtmosphere = false;
    viewer.scene.fog.enabled = false;
    if (viewer.scene.skyBox) viewer.scene.skyBox.show = false;
    viewer.scene.sun.show = false;
    viewer.scene.moon.show = false;
    viewer.scene.globe.depthTestAgainstTerrain = false;
    const tileset = await Cesium.Cesium3DTileset.fromUrl("/tiles/tileset.json", {
      maximumScreenSpaceError: 1,
    });
    tileset.pointCloudShading.attenuation = true;
    tileset.pointCloudShading.maximumAttenuation = 6;
    tileset.pointCloudShading.baseResolution = 0.05;
    tileset.pointCloudShading.eyeDomeLighting = false;
    viewer.scene.primitives.add(tileset);
    const sphere = tileset.boundingSphere;
    window.__viewer = viewer;
    window.__tileset = tileset;
    if (window.__views) {
      window.__result = { ok: true, views: true };
      return;
    }
    viewer.camera.flyToBoundingSphere(sphere, {
      duration: 0,
      offset: new Cesium.HeadingPitchRange(0.3, -0.8, sphere.radius * 2.2),
    });
    // Gaussian splats are drawn once Cesium has gathered every tile's splats into its one
    // splat primitive and sorted them (asynchronously): wait for 20 frames with all of them
    // (the export's summary.json count) sorted, or 20 frames after loading without splats.
    const expected = await fetch("/tiles/summary.json").then((r) => (r.ok ? r.json() : null))
      .then((s) => (s ? s.splats : null)).catch(() => null);
    const splatsReady = () => {
      const p = tileset.gaussianSplatPrimitive;
      if (!p) return true;
      return p._numSplats === expected && p._indexes !== undefined && p._indexes.length === p._numSplats;
    };
    let frames = 0, steady = 0;
    const t0 = performance.now();
    await new Promise((resolve) => {
      const done = () => {
        frames += 1;
        steady = tileset.tilesLoaded && splatsReady() ? steady + 1 : 0;
        if (steady > 20 || performance.now() - t0 > 180000) {
          viewer.scene.postRender.removeEventListener(done);
          resolve();
        }
      };
      viewer.scene.postRender.addEventListener(done);
    });
    viewer.scene.render();
    const centre = Cesium.Cartographic.fromCartesian(sphere.center);
    const cam = viewer.camera.positionCartographic;
    const win = Cesium.SceneTransforms.worldToWindowCoordinates(viewer.scene, sphere.center);
    const edge = Cesium.SceneTransforms.worldToWindowCoordinates(
      viewer.scene,
      Cesium.Cartesian3.add(sphere.center,
        Cesium.Cartesian3.multiplyByScalar(viewer.camera.rightWC, sphere.radius, new Cesium.Cartesian3()),
        new Cesium.Cartesian3()),
    );
    // Which tiles Cesium drew through its Gaussian splat path.
    let contents = 0, splatContents = 0;
    const walk = (tile) => {
      if (tile.hasRenderableContent) {
        contents += 1;
        if (tile.content instanceof Cesium.GaussianSplat3DTileContent) splatContents += 1;
      }
      tile.children.forEach(walk);
    };
    walk(tileset.root);
    const canvas = viewer.scene.canvas;
    window.__result = {
      ok: true,
      frames,
      tilesLoaded: tileset.tilesLoaded,
      splatsReady: splatsReady(),
      contents,
      splatContents,
      canvas: [canvas.width, canvas.height],
      client: [canvas.clientWidth, canvas.clientHeight],
      centre: { lon: Cesium.Math.toDegrees(centre.longitude), lat: Cesium.Math.toDegrees(centre.latitude), height: centre.height },
      camera: { lon: Cesium.Math.toDegrees(cam.longitude), lat: Cesium.Math.toDegrees(cam.latitude), height: cam.height },
      centreWindow: win ? [win.x, win.y] : null,
      radiusPixels: win && edge ? Math.hypot(edge.x - win.x, edge.y - win.y) : null,
    };
  } catch (e) {
    window.__result = { ok: false, error: String(e && e.stack || e) };
  }
})();
</script></body></html>`;

// Tiles requested are counted; uncompressed splats are served with their semantics renamed for
// Cesium's shader (docs/export.md); SPZ tiles (KHR_gaussian_splatting_compression_spz_2) as written.
const server = await serveFolders(page, { "/cesium": cesiumDir, "/tiles": tilesetDir }, (pathname, file, body) => {
  if (pathname.startsWith("/tiles/") && file.endsWith(".glb")) {
    requests.push({ uri: pathname.slice("/tiles/".length), bytes: body.length });
  }
  if (file.endsWith(".glb") && !body.includes("KHR_gaussian_splatting_compression_spz_2")) {
    return Buffer.from(renameGaussianSemantics(new Uint8Array(body)));
  }
  return body;
});
const port = server.address().port;

const browser = await launchChromium();
let result;
try {
  const ctx = await browser.newContext({ viewport: { width: 800, height: 600 } });
  const tab = await ctx.newPage();
  const logs = [];
  tab.on("console", (m) => logs.push(`${m.type()}: ${m.text()}`));
  tab.on("pageerror", (e) => logs.push(`pageerror: ${e}`));
  await tab.goto(`http://127.0.0.1:${port}/`);
  try {
    await tab.waitForFunction(() => window.__result !== undefined, null, { timeout: Number(process.env.CESIUM_TIMEOUT_MS ?? 240000) });
    result = await tab.evaluate(() => window.__result);
  } catch (e) {
    result = { ok: false, error: `no result: ${e.message}` };
  }
  if (result.ok && result.views) {
    result.views = {};
    for (const v of viewSpec.views) {
      const before = requests.length;
      const t0 = Date.now();
      await tab.evaluate(async ([v, fov, wait]) => {
        const viewer = window.__viewer, tileset = window.__tileset;
        const m = tileset.root.computedTransform;
        const at = (p) => Cesium.Matrix4.multiplyByPoint(m, new Cesium.Cartesian3(...p), new Cesium.Cartesian3());
        const dirOf = (p) => Cesium.Matrix4.multiplyByPointAsVector(m, new Cesium.Cartesian3(...p), new Cesium.Cartesian3());
        const eye = at(v.eye);
        const dir = Cesium.Cartesian3.normalize(Cesium.Cartesian3.subtract(at(v.target), eye, new Cesium.Cartesian3()), new Cesium.Cartesian3());
        const up = Cesium.Cartesian3.normalize(dirOf(v.up), new Cesium.Cartesian3());
        viewer.camera.frustum.fov = fov;
        viewer.camera.setView({ destination: eye, orientation: { direction: dir, up } });
        const splatsDone = () => {
          const p = tileset.gaussianSplatPrimitive;
          if (!p) return wait !== "splats";
          return p._indexes !== undefined && p._indexes.length === p._numSplats && p._numSplats > 0;
        };
        let steady = 0;
        const t0 = performance.now();
        await new Promise((resolve) => {
          const done = () => {
            steady = tileset.tilesLoaded && splatsDone() ? steady + 1 : 0;
            if (steady > 20 || performance.now() - t0 > 240000) {
              viewer.scene.postRender.removeEventListener(done);
              resolve();
            }
          };
          viewer.scene.postRender.addEventListener(done);
          viewer.scene.requestRender();
        });
        viewer.scene.render();
      }, [v, viewSpec.fov, viewSpec.wait ?? "splats"]);
      const m = await tab.evaluate(measureCanvas, ["#c canvas"]);
      Object.assign(m, await tab.evaluate(() => {
        const p = window.__tileset.gaussianSplatPrimitive;
        let splatContents = 0;
        const walk = (tile) => {
          if (tile.hasRenderableContent && tile.content instanceof Cesium.GaussianSplat3DTileContent) splatContents += 1;
          tile.children.forEach(walk);
        };
        walk(window.__tileset.root);
        return { numSplats: p ? p._numSplats : 0, splatContents };
      }));
      m.seconds = (Date.now() - t0) / 1000;
      m.requests = requests.slice(before);
      await tab.screenshot({ path: outPng.replace(/\.png$/, "") + "-" + v.name + ".png", timeout: 180000 });
      result.views[v.name] = m;
    }
  } else if (result.ok) {
    // Count palette colours in the canvas (the WebGL drawing buffer is preserved).
    const m = await tab.evaluate(measureCanvas, ["#c canvas", palette]);
    result.pixels = { lit: m.lit, byColor: m.byColor };
    await tab.screenshot({ path: outPng, timeout: 180000 });
  }
  result.logs = logs.slice(0, 30);
  result.requests = requests;
} finally {
  await browser.close();
  server.close();
}
console.log(JSON.stringify(result));
