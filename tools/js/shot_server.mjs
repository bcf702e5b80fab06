// What the browser probes of the 3D Tiles export share (cesium_shot.mjs, playcanvas_shot.mjs):
// a static server on 127.0.0.1 for one page and a few folders, and the measure of a picture.
import { createServer } from "node:http";
import { readFile, stat } from "node:fs/promises";
import path from "node:path";

const TYPES = { ".js": "text/javascript", ".mjs": "text/javascript", ".css": "text/css",
  ".json": "application/json", ".glb": "model/gltf-binary", ".html": "text/html",
  ".png": "image/png", ".wasm": "application/wasm" };

// The file `rel` (a URL path) names below `root`, or null when it leaves `root`.
function inside(root, rel) {
  const p = path.resolve(root, "." + decodeURIComponent(rel));
  return p.startsWith(path.resolve(root) + path.sep) ? p : null;
}

// Serves `page` at "/" and the files of `routes` ({"/prefix": folder}) below their prefixes,
// uncached; `body(pathname, file, bytes)` may replace what a file sends. 404 for anything else.
// Resolves to the listening server (its port: server.address().port).
export async function serveFolders(page, routes, body = (_p, _f, bytes) => bytes) {
  const server = createServer(async (req, res) => {
    try {
      const url = new URL(req.url, "http://127.0.0.1");
      if (url.pathname === "/" || url.pathname === "/index.html") {
        res.writeHead(200, { "content-type": "text/html" });
        res.end(page);
        return;
      }
      const prefix = Object.keys(routes).find((r) => url.pathname.startsWith(r + "/"));
      const file = prefix ? inside(routes[prefix], url.pathname.slice(prefix.length)) : null;
      if (!file || !(await stat(file)).isFile()) throw new Error("not found");
      const bytes = body(url.pathname, file, await readFile(file));
      res.writeHead(200, { "content-type": TYPES[path.extname(file)] ?? "application/octet-stream",
        "cache-control": "no-store" });
      res.end(bytes);
    } catch {
      res.writeHead(404);
      res.end();
    }
  });
  await new Promise((r) => server.listen(0, "127.0.0.1", r));
  return server;
}

// Runs in the page (`tab.evaluate(measureCanvas, [selector, palette])`; it must stay
// self-contained): the canvas's peak green value, the pixels at or above half of it (count,
// centroid, second moments), the lit pixels (> 30 in r + g + b) and, with a palette
// ({"name": [r, g, b], …}), per colour the pixels within 12 of it in each channel (count, centroid).
export function measureCanvas([selector, palette]) {
  const src = document.querySelector(selector);
  const c = document.createElement("canvas");
  c.width = src.width;
  c.height = src.height;
  const g = c.getContext("2d");
  g.drawImage(src, 0, 0);
  const d = g.getImageData(0, 0, c.width, c.height).data;
  const colours = Object.entries(palette ?? {});
  const byColor = {};
  for (const [name] of colours) byColor[name] = { count: 0, sx: 0, sy: 0 };
  let peak = 0, lit = 0;
  for (let i = 0; i < d.length; i += 4) {
    peak = Math.max(peak, d[i + 1]);
    if (d[i] + d[i + 1] + d[i + 2] > 30) lit += 1;
    for (const [name, rgb] of colours) {
      if (Math.abs(d[i] - rgb[0]) <= 12 && Math.abs(d[i + 1] - rgb[1]) <= 12 && Math.abs(d[i + 2] - rgb[2]) <= 12) {
        const p = i / 4;
        byColor[name].count += 1;
        byColor[name].sx += p % c.width;
        byColor[name].sy += Math.floor(p / c.width);
      }
    }
  }
  for (const v of Object.values(byColor)) {
    v.centroid = v.count ? [v.sx / v.count, v.sy / v.count] : null;
    delete v.sx;
    delete v.sy;
  }
  let n = 0, sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0;
  for (let i = 0; i < d.length; i += 4) {
    if (peak > 0 && d[i + 1] >= peak / 2) {
      const p = i / 4, x = p % c.width, y = Math.floor(p / c.width);
      n += 1; sx += x; sy += y; sxx += x * x; syy += y * y; sxy += x * y;
    }
  }
  const mx = n ? sx / n : null, my = n ? sy / n : null;
  return { size: [c.width, c.height], peak, lit, half: n, centroid: n ? [mx, my] : null,
    moments: n ? [sxx / n - mx * mx, syy / n - my * my, sxy / n - mx * my] : null, byColor };
}
