// Drives `gs4city view` in headless Chromium (Debian's /usr/bin/chromium, WebGL2 on SwiftShader)
// for tests/view.rs: sets the camera, waits until Spark has sorted and drawn the splats, reads
// the colour Spark drew at a 3D point (projected with the page's own camera matrix) in the Class
// mode, clicks there with the real mouse, reads the pick panel, types queries into the box and
// reads the highlighted count, and takes a screenshot. Prints one JSON object on stdout. With
// `scene_only` (`gs4city view --scene S`, no run) it clicks at the point and reads the clicked
// point's coordinates the page shows (#pick-point) and lists (#points) instead.
//
//   node view_click.mjs SPEC.json
//
// SPEC: { url, eye: [x,y,z], target: [x,y,z], click: [x,y,z], queries: [..], screenshot: PATH,
//         screenshot_query, screenshot_overview (the page's first view), width, height,
//         scene_only }
import { readFileSync } from 'node:fs';
import { launchChromium } from './chromium.mjs';

const spec = JSON.parse(readFileSync(process.argv[2], 'utf8'));
const browser = await launchChromium();
const out = { console: [] };
try {
  const page = await browser.newPage({ viewport: { width: spec.width || 960, height: spec.height || 640 } });
  // SwiftShader draws and sorts 10⁵ splats in seconds, slower on a loaded machine.
  page.setDefaultTimeout(180000);
  page.on('console', (m) => out.console.push(`${m.type()}: ${m.text()}`));
  page.on('pageerror', (e) => out.console.push(`pageerror: ${e.message}`));
  const cam = [...spec.eye, ...spec.target].map((v) => v.toPrecision(12)).join(',');
  await page.goto(`${spec.url}#camera=${cam}`);
  await page.waitForFunction(() => window.gs4city && (window.gs4city.ready || window.gs4city.error), null, { timeout: 180000 });
  out.error = await page.evaluate(() => window.gs4city.error);
  if (out.error) throw new Error(out.error);
  out.gaussians = await page.evaluate(() => window.gs4city.n);
  out.renderer = await page.evaluate(() => window.gs4city.renderer);
  // What Spark drew: the mean colour of a (2r+1)² patch of the WebGL canvas around CSS pixel
  // (x, y), and the share of the canvas that is not the background.
  const settle = () => page.evaluate(() => window.gs4city.settled());
  const drawn = (x, y, r) => page.evaluate(([x, y, r]) => {
    const gl = document.getElementById('gl');
    const c = document.createElement('canvas');
    c.width = gl.width; c.height = gl.height;
    const ctx = c.getContext('2d', { willReadFrequently: true });
    ctx.drawImage(gl, 0, 0);
    const all = ctx.getImageData(0, 0, c.width, c.height).data;
    let bg = 0;
    for (let i = 0; i < all.length; i += 4) bg += (all[i] === 0x1c && all[i + 1] === 0x20 && all[i + 2] === 0x25) ? 1 : 0;
    const s = gl.width / gl.clientWidth;
    const px = ctx.getImageData(Math.round(x * s) - r, Math.round(y * s) - r, 2 * r + 1, 2 * r + 1).data;
    const m = [0, 0, 0];
    for (let i = 0; i < px.length; i += 4) for (let k = 0; k < 3; k++) m[k] += px[i + k] / (px.length / 4);
    return { rgb: m.map(Math.round), background_share: bg / (all.length / 4) };
  }, [x, y, r]);

  // The click point: the page's camera matrix (column-major) applied to spec.click.
  const vp = await page.evaluate(() => window.gs4city.viewProj());
  const [x, y, z] = spec.click;
  const c = [0, 1, 2, 3].map((r) => vp[r] * x + vp[4 + r] * y + vp[8 + r] * z + vp[12 + r]);
  const box = await page.locator('#gl').boundingBox();
  const px = box.x + (c[0] / c[3] + 1) / 2 * box.width;
  const py = box.y + (1 - c[1] / c[3]) / 2 * box.height;
  out.pixel = [px, py];
  await settle();
  // The clicked point's coordinates, as the page shows them after a click.
  const readPoint = async () => {
    await page.waitForSelector('#pick-point', { timeout: 180000 });
    return page.evaluate(() => {
      const p = document.querySelector('#pick-point');
      return {
        hit: p.dataset.hit === '1',
        scene: p.dataset.scene ? p.dataset.scene.split(',').map(Number) : null,
        geo: p.dataset.geo ? p.dataset.geo.split(',').map(Number) : null,
        text: p.innerText,
        list: document.querySelector('#points').value,
        buttons_shown: getComputedStyle(document.querySelector('#colour')).display !== 'none',
      };
    });
  };
  if (spec.scene_only) {
    out.status = await page.evaluate(() => document.querySelector('#status').textContent);
    await page.mouse.click(px, py);
    out.point = await readPoint();
    if (spec.screenshot) await page.screenshot({ path: spec.screenshot });
    throw null; // done: nothing of a run to look at
  }
  out.rgb_at_click = await drawn(px - box.x, py - box.y, 2);
  await page.click('#color-class');
  await settle();
  out.class_at_click = await drawn(px - box.x, py - box.y, 2);
  await page.mouse.click(px, py);
  await page.waitForSelector('#pick-gaussian, #pick-none', { timeout: 180000 });
  out.picked_gaussian = await page.evaluate(() => {
    const g = document.querySelector('#pick-gaussian');
    return g ? Number(g.dataset.gaussian) : -1;
  });
  out.panel = await page.$$eval('#pick .entry', (es) => es.map((e) => ({
    level: e.dataset.level, class: e.dataset.class, gml_id: e.dataset.gmlid, text: e.innerText,
  })));
  out.point = await readPoint();

  // Each query typed into the box (Class colours).
  out.queries = [];
  for (const q of spec.queries) {
    await page.fill('#query', '');
    await page.click('#query');
    await page.keyboard.type(q);
    await page.evaluate(() => { window.gs4city.lastQuery = null; });
    await page.keyboard.press('Enter');
    await page.waitForFunction(() => window.gs4city.lastQuery, null, { timeout: 180000 });
    const shown = await page.evaluate(() => {
      const c = document.querySelector('#count');
      return {
        count: c.hasAttribute('data-count') ? Number(c.dataset.count) : null,
        count_text: c.textContent,
        error: document.querySelector('#query-error').textContent,
      };
    });
    out.queries.push({ query: q, ...shown });
  }
  if (spec.screenshot) {
    // The screenshot: class colours, `screenshot_query` highlighted, the pick panel filled in.
    if (spec.screenshot_query) {
      await page.fill('#query', spec.screenshot_query);
      await page.evaluate(() => { window.gs4city.lastQuery = null; });
      await page.keyboard.press('Enter');
      await page.waitForFunction(() => window.gs4city.lastQuery, null, { timeout: 180000 });
    }
    if (spec.screenshot_overview) await page.evaluate(() => window.gs4city.resetCamera());
    await settle();
    out.overview = await drawn(0, 0, 0);
    await page.screenshot({ path: spec.screenshot });
  }
} catch (e) {
  if (e !== null) out.error = String(e && e.stack || e);
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
