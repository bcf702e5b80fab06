// Times `gs4city view` in headless Chromium (Debian's, WebGL2 on SwiftShader) for BENCHMARKS.md:
// page load until the first frame, until Spark's first depth sort is on the canvas, a change of
// colour mode, a typed query, an orbit of the camera (each until Spark has sorted and drawn).
// Not a test: it asserts nothing and only prints one JSON object of milliseconds.
//
//   node tools/js/view_timing.mjs http://127.0.0.1:PORT/ [WIDTH HEIGHT]
import { launchChromium } from './chromium.mjs';

const [url, width = 960, height = 640] = process.argv.slice(2);
const browser = await launchChromium();
const out = {};
try {
  const page = await browser.newPage({ viewport: { width: Number(width), height: Number(height) } });
  page.setDefaultTimeout(300000);
  let t = Date.now();
  await page.goto(url);
  await page.waitForFunction(() => window.gs4city && (window.gs4city.ready || window.gs4city.error), null, { timeout: 300000 });
  out.first_frame_ms = Date.now() - t;
  await page.evaluate(() => window.gs4city.settled());
  out.first_sorted_frame_ms = Date.now() - t;
  const step = (f) => page.evaluate(async (src) => {
    const g = window.gs4city;
    const t0 = performance.now();
    await (0, eval)(src)(g);
    await g.settled();
    return Math.round(performance.now() - t0);
  }, f);
  out.color_class_ms = await step('(g) => g.setMode(1)');
  out.query_class_window_ms = await step('(g) => g.runQuery("class=Window")');
  out.orbit_ms = await step(`async (g) => {
    const m = await (await fetch('api/meta')).json();
    const c = m.center, e = m.extent;
    g.setCamera([c[0] + 1.2 * e, c[1] - 0.9 * e, c[2] + 0.7 * e], c);
  }`);
  out.color_rgb_ms = await step('(g) => g.setMode(0)');
  out.gaussians = await page.evaluate(() => window.gs4city.n);
} catch (e) {
  out.error = String(e && e.stack || e);
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
