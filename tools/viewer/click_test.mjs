// Drives `gs4city view` in headless Chromium (Debian's /usr/bin/chromium, WebGL2 on SwiftShader)
// for tests/view.rs: sets the camera, projects a 3D point with the page's own camera matrix,
// clicks there with the real mouse, reads the pick panel, types queries into the box and reads
// the highlighted count, and takes a screenshot. Prints one JSON object on stdout.
//
//   node click_test.mjs SPEC.json
//
// SPEC: { url, eye: [x,y,z], target: [x,y,z], click: [x,y,z], queries: [..], screenshot: PATH,
//         screenshot_query, screenshot_overview (the page's first view), width, height }
import { readFileSync } from 'node:fs';
import { chromium } from 'playwright-core';

const spec = JSON.parse(readFileSync(process.argv[2], 'utf8'));
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
  headless: true,
  args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--ignore-gpu-blocklist',
    '--disable-quic', '--no-first-run', '--disable-background-networking', '--disable-component-update',
    '--disable-sync'],
});
const out = { console: [] };
try {
  const page = await browser.newPage({ viewport: { width: spec.width || 960, height: spec.height || 640 } });
  page.on('console', (m) => out.console.push(`${m.type()}: ${m.text()}`));
  page.on('pageerror', (e) => out.console.push(`pageerror: ${e.message}`));
  const cam = [...spec.eye, ...spec.target].map((v) => v.toPrecision(12)).join(',');
  await page.goto(`${spec.url}#camera=${cam}`);
  await page.waitForFunction(() => window.gs4city && (window.gs4city.ready || window.gs4city.error), null, { timeout: 60000 });
  out.error = await page.evaluate(() => window.gs4city.error);
  if (out.error) throw new Error(out.error);
  out.gaussians = await page.evaluate(() => window.gs4city.n);

  // The click point: the page's camera matrix (column-major) applied to spec.click.
  const vp = await page.evaluate(() => window.gs4city.viewProj());
  const [x, y, z] = spec.click;
  const c = [0, 1, 2, 3].map((r) => vp[r] * x + vp[4 + r] * y + vp[8 + r] * z + vp[12 + r]);
  const box = await page.locator('#gl').boundingBox();
  const px = box.x + (c[0] / c[3] + 1) / 2 * box.width;
  const py = box.y + (1 - c[1] / c[3]) / 2 * box.height;
  out.pixel = [px, py];
  await page.mouse.click(px, py);
  await page.waitForSelector('#pick-gaussian, #pick-none', { timeout: 30000 });
  out.picked_gaussian = await page.evaluate(() => {
    const g = document.querySelector('#pick-gaussian');
    return g ? Number(g.dataset.gaussian) : -1;
  });
  out.panel = await page.$$eval('#pick .entry', (es) => es.map((e) => ({
    level: e.dataset.level, class: e.dataset.class, gml_id: e.dataset.gmlid, text: e.innerText,
  })));

  // Class colours, then each query typed into the box.
  await page.click('#color-class');
  out.queries = [];
  for (const q of spec.queries) {
    await page.fill('#query', '');
    await page.click('#query');
    await page.keyboard.type(q);
    await page.evaluate(() => { window.gs4city.lastQuery = null; });
    await page.keyboard.press('Enter');
    await page.waitForFunction(() => window.gs4city.lastQuery, null, { timeout: 30000 });
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
      await page.waitForFunction(() => window.gs4city.lastQuery, null, { timeout: 30000 });
    }
    if (spec.screenshot_overview) await page.evaluate(() => window.gs4city.resetCamera());
    await page.waitForTimeout(300);
    await page.screenshot({ path: spec.screenshot });
  }
} catch (e) {
  out.error = String(e && e.stack || e);
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
