// Measures the memory `gs4city view` takes in headless Chromium (Debian's, WebGL2 on SwiftShader)
// once the page has drawn its first depth-sorted frame, for BENCHMARKS.md and docs/view.md. Not
// a test: it asserts nothing and prints one JSON object:
// - `js_heap_used_bytes`, `js_heap_total_bytes`: the page's JavaScript heap, from the Chrome
//   DevTools Protocol (`Performance.getMetrics`: JSHeapUsedSize, JSHeapTotalSize);
// - `browser_pss_bytes`: the proportional set size (Pss, /proc/PID/smaps_rollup) of every
//   Chromium process this script started (browser, renderer, GPU — SwiftShader keeps the
//   WebGL buffers and textures there), summed: shared pages counted once;
// - `splats`, `gaussians`: what the page drew and what the run holds (/api/meta);
// - `first_sorted_frame_ms`.
//
//   node tools/js/view_memory.mjs http://127.0.0.1:PORT/ [WIDTH HEIGHT]
import { readFileSync, readdirSync } from 'node:fs';
import { launchChromium } from './chromium.mjs';

const [url, width = 960, height = 640] = process.argv.slice(2);

/// Every process descending from `root` (by /proc/PID/stat's parent pid).
function descendants(root) {
  const parent = new Map();
  for (const d of readdirSync('/proc')) {
    if (!/^\d+$/.test(d)) continue;
    try {
      const stat = readFileSync(`/proc/${d}/stat`, 'utf8');
      const ppid = Number(stat.slice(stat.lastIndexOf(')') + 2).split(' ')[1]);
      parent.set(Number(d), ppid);
    } catch { /* gone */ }
  }
  const out = [];
  for (const pid of parent.keys()) {
    let p = pid;
    while (p > 1 && p !== root) p = parent.get(p) ?? 0;
    if (p === root && pid !== root) out.push(pid);
  }
  return out;
}

function pssBytes(pids) {
  let total = 0;
  for (const pid of pids) {
    try {
      const m = readFileSync(`/proc/${pid}/smaps_rollup`, 'utf8').match(/^Pss:\s+(\d+) kB/m);
      if (m) total += Number(m[1]) * 1024;
    } catch { /* gone */ }
  }
  return total;
}

const browser = await launchChromium();
const out = {};
try {
  const page = await browser.newPage({ viewport: { width: Number(width), height: Number(height) } });
  page.setDefaultTimeout(600000);
  const t = Date.now();
  await page.goto(url);
  await page.waitForFunction(() => window.gs4city && (window.gs4city.ready || window.gs4city.error), null, { timeout: 600000 });
  out.error = await page.evaluate(() => window.gs4city.error);
  await page.evaluate(() => window.gs4city.settled());
  out.first_sorted_frame_ms = Date.now() - t;
  const meta = await page.evaluate(async () => (await fetch('api/meta')).json());
  out.gaussians = meta.gaussians;
  out.splats = meta.splats;
  const cdp = await page.context().newCDPSession(page);
  await cdp.send('Performance.enable');
  const { metrics } = await cdp.send('Performance.getMetrics');
  const get = (n) => metrics.find((m) => m.name === n)?.value;
  out.js_heap_used_bytes = get('JSHeapUsedSize');
  out.js_heap_total_bytes = get('JSHeapTotalSize');
  const pids = descendants(process.pid);
  out.browser_processes = pids.length;
  out.browser_pss_bytes = pssBytes(pids);
} catch (e) {
  out.error = String(e && e.stack || e);
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
