// gs4city view (docs/view.md). The run's Gaussians are drawn by Spark (@sparkjsdev/spark, a 3D
// Gaussian Splatting renderer on three.js, vendored from npm and embedded in the binary): every
// Gaussian as an anisotropic, depth-sorted, alpha-blended splat from its centre, scales,
// rotation, opacity and colour. The colour modes and the query highlight rewrite the splats'
// colours (RGB = the DC colour, Class, Building). Picking is a pass of our own with the same
// camera matrices: every Gaussian with opacity ≥ MIN_OPACITY is drawn as a depth-tested disc of
// diameter 4σ (σ its largest scale) with its index + 1 as its RGBA colour into an offscreen
// target of a second WebGL2 context, the clicked pixel is read back, and the server is asked
// for the hierarchy of the Gaussian the splat stands for (/api/pick). A run of more Gaussians
// than the server's splat budget comes as a coarse set: each splat stands for its heaviest
// Gaussian (class, building, query bit, pick). Every click also asks the server for the point of the
// splat surface under the cursor (/api/point: the renderer's own blend list of that pixel, with
// this page's camera), shown in the scene frame and, once the scene is aligned, in the city
// model's CRS, and listed for copying (ground-control points). Without a run (`gs4city view
// --scene S`) the page shows the scene's own colours and the clicked points only.
import * as THREE from 'three';
import { PackedSplats, SparkRenderer, SplatMesh, setPackedSplat, utils } from '@sparkjsdev/spark';

const MIN_OPACITY = 0.05;
const FOVY = 50;
const BACKGROUND = 0x1c2025;
const $ = (id) => document.getElementById(id);
const api = { ready: false, error: null, frames: 0 };
window.gs4city = api;
const fail = (msg) => { api.error = msg; $('status').textContent = msg; };

async function main() {
  let meta, buf;
  try {
    meta = await (await fetch('api/meta')).json();
    const r = await fetch('api/splats.bin');
    if (!r.ok) throw new Error('api/splats.bin: HTTP ' + r.status);
    buf = await r.arrayBuffer();
  } catch (e) { fail('Cannot load the scene: ' + e); return; }
  const isRun = !!meta.run;
  const head = new DataView(buf);
  const magic = String.fromCharCode(head.getUint8(0), head.getUint8(1), head.getUint8(2), head.getUint8(3));
  const n = head.getUint32(8, true);
  if (magic !== 'GS4V' || head.getUint32(4, true) !== 3 || buf.byteLength !== 16 + 60 * n) {
    fail('api/splats.bin: not a version-3 GS4V buffer'); return;
  }
  let off = 16;
  const take = (T, count, bytes) => { const a = new T(buf, off, count); off += bytes; return a; };
  const pos = take(Float32Array, 3 * n, 12 * n);
  const size = take(Float32Array, n, 4 * n);
  const scl = take(Float32Array, 3 * n, 12 * n);
  const quat = take(Float32Array, 4 * n, 16 * n);
  const rgba = take(Uint8Array, 4 * n, 4 * n);
  const cls = take(Uint8Array, 4 * n, 4 * n);
  const bld = take(Uint8Array, 4 * n, 4 * n);
  // The Gaussian each splat stands for (itself, or the heaviest of a merged splat's).
  const gaussianOf = take(Uint32Array, n, 4 * n);
  const sel = new Uint8Array(n);

  // --- the splat renderer ---------------------------------------------------------------
  const canvas = $('gl');
  let renderer;
  try {
    renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
  } catch (e) { fail('WebGL2 is not available in this browser: ' + e.message); return; }
  renderer.setPixelRatio(1);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(BACKGROUND);
  const camera = new THREE.PerspectiveCamera(FOVY, 1, 0.01, 100);
  let pending = false;
  const redraw = () => {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; draw(); });
  };
  // Spark sorts the splats by depth in a worker; `onDirty` asks for the frame that shows it.
  const spark = new SparkRenderer({ renderer, onDirty: redraw });
  scene.add(spark);
  const packed = new Uint32Array(utils.computeMaxSplats(n) * 4);
  for (let i = 0; i < n; i++) {
    setPackedSplat(packed, i, pos[3 * i], pos[3 * i + 1], pos[3 * i + 2],
      scl[3 * i], scl[3 * i + 1], scl[3 * i + 2], quat[4 * i], quat[4 * i + 1], quat[4 * i + 2], quat[4 * i + 3],
      rgba[4 * i + 3] / 255, rgba[4 * i] / 255, rgba[4 * i + 1] / 255, rgba[4 * i + 2] / 255);
  }
  const splats = new PackedSplats({ packedArray: packed, numSplats: n });
  const mesh = new SplatMesh({ packedSplats: splats });
  scene.add(mesh);
  await mesh.initialized;

  // --- the pick pass: a second WebGL2 context, discs of 4σ, index + 1 as the colour -------
  const pickCanvas = document.createElement('canvas');
  const gl = pickCanvas.getContext('webgl2', { antialias: false });
  if (!gl) { fail('WebGL2 is not available in this browser.'); return; }
  const VS = `#version 300 es
  layout(location=0) in vec3 aPos;
  layout(location=1) in float aSize;
  layout(location=2) in float aAlpha;
  uniform mat4 uViewProj;
  uniform float uFocal;
  uniform float uMaxPoint;
  flat out uint vId;
  void main() {
    vec4 c = uViewProj * vec4(aPos, 1.0);
    vId = uint(gl_VertexID) + 1u;
    if (aAlpha < ${MIN_OPACITY.toFixed(4)} || c.w <= 0.0) {
      gl_Position = vec4(2.0, 2.0, 2.0, 1.0); gl_PointSize = 1.0; return;
    }
    gl_Position = c;
    gl_PointSize = clamp(4.0 * aSize * uFocal / c.w, 1.0, uMaxPoint);
  }`;
  const FS = `#version 300 es
  precision highp float;
  flat in uint vId;
  out vec4 o;
  void main() {
    vec2 d = gl_PointCoord * 2.0 - 1.0;
    if (dot(d, d) > 1.0) discard;
    o = vec4(float(vId & 255u), float((vId >> 8) & 255u), float((vId >> 16) & 255u), float((vId >> 24) & 255u)) / 255.0;
  }`;
  const compile = (type, src) => {
    const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  };
  const prog = gl.createProgram();
  try {
    gl.attachShader(prog, compile(gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  } catch (e) { fail('Shader: ' + e.message); return; }
  const U = {};
  for (const u of ['uViewProj', 'uFocal', 'uMaxPoint']) U[u] = gl.getUniformLocation(prog, u);
  const vao = gl.createVertexArray();
  gl.bindVertexArray(vao);
  const attr = (loc, data, comps, type, normalized, stride, offset) => {
    const b = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, b);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, comps, type, normalized, stride, offset);
  };
  attr(0, pos, 3, gl.FLOAT, false, 0, 0);
  attr(1, size, 1, gl.FLOAT, false, 0, 0);
  attr(2, rgba, 1, gl.UNSIGNED_BYTE, true, 4, 3);
  const maxPoint = Math.min(256, gl.getParameter(gl.ALIASED_POINT_SIZE_RANGE)[1]);

  // --- camera: orbit about a target, `up` the scene's up axis ---------------------------
  const v3 = {
    sub: (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]],
    add: (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]],
    mul: (a, s) => [a[0] * s, a[1] * s, a[2] * s],
    dot: (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2],
    cross: (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]],
    norm: (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; },
  };
  const up = v3.norm(meta.up);
  const e1 = v3.norm(Math.abs(up[0]) < 0.9 ? v3.cross(up, [1, 0, 0]) : v3.cross(up, [0, 1, 0]));
  const e2 = v3.cross(up, e1);
  const cam = {};
  const eye = () => {
    const h = Math.cos(cam.pitch);
    const dir = v3.add(v3.add(v3.mul(e1, h * Math.cos(cam.yaw)), v3.mul(e2, h * Math.sin(cam.yaw))), v3.mul(up, Math.sin(cam.pitch)));
    return v3.add(cam.target, v3.mul(dir, cam.dist));
  };
  const resetCamera = () => {
    Object.assign(cam, { target: meta.center.slice(), dist: meta.extent * 1.6, yaw: 0.6, pitch: 0.6 });
    redraw();
  };
  const setCamera = (e, t) => {
    cam.target = t.slice();
    const d = v3.sub(e, t);
    cam.dist = Math.max(1e-6, Math.hypot(d[0], d[1], d[2]));
    const dn = v3.mul(d, 1 / cam.dist);
    cam.pitch = Math.asin(Math.max(-1, Math.min(1, v3.dot(dn, up))));
    cam.yaw = Math.atan2(v3.dot(dn, e2), v3.dot(dn, e1));
    redraw();
  };
  const resize = () => {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) renderer.setSize(w, h, false);
  };
  // The three.js camera from the orbit state; both passes draw with its matrices.
  const applyCamera = () => {
    resize();
    const e = eye();
    // Looking straight along `up`: another up vector keeps lookAt defined.
    const fwd = v3.norm(v3.sub(cam.target, e));
    camera.up.fromArray(Math.abs(v3.dot(fwd, up)) > 0.999 ? e1 : up);
    camera.position.fromArray(e);
    camera.lookAt(...cam.target);
    camera.aspect = canvas.width / canvas.height;
    camera.near = Math.max(cam.dist * 0.005, meta.extent * 1e-5);
    camera.far = cam.dist + meta.extent * 6;
    camera.updateProjectionMatrix();
    camera.updateMatrixWorld();
  };
  // Column-major projection × view, as the pick pass and the test use it.
  const viewProj = () => {
    applyCamera();
    return new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse).toArray();
  };
  const draw = () => {
    applyCamera();
    renderer.render(scene, camera);
    api.frames += 1;
  };

  // --- colours: RGB / class / building, the query highlight -----------------------------
  let mode = 0, queryOn = 0;
  const recolor = () => {
    const src = mode === 1 ? cls : (mode === 2 ? bld : rgba);
    for (let i = 0; i < n; i++) {
      let r = src[4 * i] / 255, g = src[4 * i + 1] / 255, b = src[4 * i + 2] / 255;
      if (queryOn) {
        if (sel[i]) { r = Math.min(r * 1.15 + 0.05, 1); g = Math.min(g * 1.15 + 0.05, 1); b = Math.min(b * 1.15 + 0.05, 1); }
        else { r = r * 0.18 + 0.03; g = g * 0.18 + 0.03; b = b * 0.18 + 0.03; }
      }
      utils.setPackedSplatRgb(packed, i, r, g, b);
    }
    splats.needsUpdate = true;
    mesh.updateVersion();
    redraw();
  };

  // The index of the splat under CSS pixel (x, y) of the canvas, or −1.
  const pickFbo = { fb: null, tex: null, depth: null, w: 0, h: 0 };
  const pickAt = (x, y) => {
    const m = viewProj();
    const w = canvas.width, h = canvas.height;
    if (pickFbo.w !== w || pickFbo.h !== h) {
      if (pickFbo.fb) { gl.deleteFramebuffer(pickFbo.fb); gl.deleteTexture(pickFbo.tex); gl.deleteRenderbuffer(pickFbo.depth); }
      pickFbo.tex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, pickFbo.tex);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, w, h, 0, gl.RGBA, gl.UNSIGNED_BYTE, null);
      pickFbo.depth = gl.createRenderbuffer();
      gl.bindRenderbuffer(gl.RENDERBUFFER, pickFbo.depth);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, w, h);
      pickFbo.fb = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, pickFbo.fb);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, pickFbo.tex, 0);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, pickFbo.depth);
      pickFbo.w = w; pickFbo.h = h;
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, pickFbo.fb);
    gl.useProgram(prog);
    gl.bindVertexArray(vao);
    gl.uniformMatrix4fv(U.uViewProj, false, new Float32Array(m));
    gl.uniform1f(U.uFocal, h / (2 * Math.tan(FOVY * Math.PI / 360)));
    gl.uniform1f(U.uMaxPoint, maxPoint);
    gl.viewport(0, 0, w, h);
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    gl.disable(gl.BLEND);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.drawArrays(gl.POINTS, 0, n);
    const dpr = w / canvas.clientWidth;
    const px = Math.min(w - 1, Math.max(0, Math.floor(x * dpr)));
    const py = Math.min(h - 1, Math.max(0, h - 1 - Math.floor(y * dpr)));
    const p = new Uint8Array(4);
    gl.readPixels(px, py, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, p);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    const id = (p[0] | (p[1] << 8) | (p[2] << 16)) + p[3] * 16777216;
    return id - 1;
  };

  // --- the panel ------------------------------------------------------------------------
  const el = (tag, attrs, text) => {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
    if (text !== undefined) e.textContent = text;
    return e;
  };
  const LEVEL = { feature: 'building', surface: 'surface', part: 'part' };
  // The point of the splat surface under CSS pixel (x, y) of the canvas, from the server.
  const pointAt = async (x, y) => {
    applyCamera();
    const q = new URLSearchParams({
      eye: eye().join(','), target: cam.target.join(','), up: camera.up.toArray().join(','),
      fovy: String(FOVY), width: String(canvas.clientWidth), height: String(canvas.clientHeight),
      x: String(x), y: String(y),
    });
    const r = await fetch('api/point?' + q.toString());
    const j = await r.json();
    if (!r.ok) throw new Error(j.error);
    return j;
  };
  const fmt = (v, d) => v.map((c) => c.toFixed(d)).join(' ');
  const showPoint = async (x, y) => {
    const box = $('point');
    box.replaceChildren();
    let j;
    try { j = await pointAt(x, y); } catch (e) { box.append(el('div', { class: 'muted' }, String(e.message || e))); return; }
    api.lastPoint = j;
    if (!j.hit) { box.append(el('div', { id: 'pick-point', 'data-hit': '0', class: 'muted' }, 'No surface under the cursor (' + j.why + ').')); return; }
    const d = el('div', { id: 'pick-point', 'data-hit': '1', 'data-scene': j.scene.join(','), 'data-geo': j.geo ? j.geo.join(',') : '' });
    d.append(el('div', {}, 'scene: ' + fmt(j.scene, 4)));
    if (j.geo) d.append(el('div', {}, (j.crs || 'CRS') + ': ' + fmt(j.geo, 3)));
    box.append(d);
    const list = $('points');
    list.value += (j.geo ? fmt(j.geo, 3) + '   ' : '') + fmt(j.scene, 4) + '\n';
    list.scrollTop = list.scrollHeight;
  };
  $('copy-points').addEventListener('click', () => { $('points').select(); navigator.clipboard?.writeText($('points').value); });
  $('clear-points').addEventListener('click', () => { $('points').value = ''; });
  const showPick = async (i) => {
    const box = $('pick');
    box.className = '';
    box.replaceChildren();
    if (i < 0) { box.append(el('div', { id: 'pick-none', class: 'muted' }, 'No splat under the cursor.')); api.lastPick = { gaussian: -1 }; return; }
    const r = await fetch('api/pick?i=' + gaussianOf[i]);
    const j = await r.json();
    if (!r.ok) { box.append(el('div', { class: 'muted' }, j.error)); return; }
    box.append(el('div', { id: 'pick-gaussian', 'data-gaussian': String(j.gaussian) },
      `Gaussian ${j.gaussian}: ${j.category} (label ${j.label}${j.source ? ', ' + j.source : ''})`));
    if (j.chain.length === 0) box.append(el('div', { class: 'muted' }, 'Not part of the city model.'));
    for (const c of j.chain) {
      const d = el('div', { class: 'entry', 'data-level': c.level, 'data-class': c.class, 'data-gmlid': c.object_id });
      d.append(el('div', { class: 'head' }, `${LEVEL[c.level] || c.level}: ${c.class}`));
      d.append(el('div', { class: 'gmlid' }, c.object_id));
      const ul = el('ul', { class: 'attrs' });
      for (const [k, v] of Object.entries(c.attributes || {})) {
        const val = (v && typeof v === 'object' && 'value' in v) ? `${v.value}${v.uom ? ' ' + v.uom : ''}` : (typeof v === 'string' ? v : JSON.stringify(v));
        ul.append(el('li', {}, `${k}: ${val}`));
      }
      d.append(ul);
      box.append(d);
    }
    api.lastPick = j;
  };

  const setMode = (m) => {
    mode = m;
    for (const b of document.querySelectorAll('button[data-mode]')) b.classList.toggle('active', Number(b.dataset.mode) === m);
    $('legend').style.display = m === 1 ? '' : 'none';
    recolor();
  };
  for (const b of document.querySelectorAll('button[data-mode]')) b.addEventListener('click', () => setMode(Number(b.dataset.mode)));
  for (const c of meta.classes) {
    const d = el('div');
    const sw = el('span', { class: 'sw' });
    sw.style.background = `rgb(${c.color.join(',')})`;
    d.append(sw, document.createTextNode(c.name));
    $('legend').append(d);
  }
  $('legend').style.display = 'none';
  for (const f of meta.files) { const a = el('a', { href: 'files/' + f, target: '_blank' }, f); $('files').append(a, el('br')); }

  const clearQuery = () => {
    const was = queryOn;
    sel.fill(0); queryOn = 0;
    $('count').textContent = ''; $('count').removeAttribute('data-count');
    $('query-info').textContent = '';
    if (was) recolor();
  };
  const runQuery = async (text) => {
    $('query-error').textContent = '';
    const r = await fetch('api/query?where=' + encodeURIComponent(text));
    const j = await r.json();
    if (!r.ok) { clearQuery(); $('query-error').textContent = j.error; api.lastQuery = { error: j.error }; return; }
    const bin = atob(j.mask);
    const bit = (g) => (bin.charCodeAt(g >> 3) >> (g & 7)) & 1;
    let count = 0;
    for (let g = 0; g < meta.gaussians; g++) count += bit(g);
    for (let i = 0; i < n; i++) sel[i] = bit(gaussianOf[i]);
    queryOn = 1;
    recolor();
    $('count').textContent = `${count} Gaussians`;
    $('count').setAttribute('data-count', String(count));
    $('query-info').textContent = `${j.query}: ${j.labels} labels, ${j.entities} entities` + (j.warnings.length ? ' — ' + j.warnings.join('; ') : '');
    api.lastQuery = { count, server: j.count, query: j.query };
  };
  $('query-form').addEventListener('submit', (e) => { e.preventDefault(); runQuery($('query').value); });
  $('clear-query').addEventListener('click', () => { $('query').value = ''; $('query-error').textContent = ''; clearQuery(); });

  // --- mouse ----------------------------------------------------------------------------
  let drag = null;
  canvas.addEventListener('contextmenu', (e) => e.preventDefault());
  canvas.addEventListener('pointerdown', (e) => {
    drag = { x: e.clientX, y: e.clientY, moved: false, pan: e.shiftKey || e.button === 2 };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener('pointermove', (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    if (!drag.moved && Math.hypot(dx, dy) < 4) return;
    drag.moved = true; drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) {
      const e0 = eye();
      const f = v3.norm(v3.sub(cam.target, e0));
      const s = v3.norm(v3.cross(f, up));
      const u = v3.cross(s, f);
      const k = cam.dist * 2 * Math.tan(FOVY * Math.PI / 360) / canvas.clientHeight;
      cam.target = v3.add(cam.target, v3.add(v3.mul(s, -dx * k), v3.mul(u, dy * k)));
    } else {
      cam.yaw -= dx * 0.008;
      cam.pitch = Math.max(-1.55, Math.min(1.55, cam.pitch + dy * 0.008));
    }
    redraw();
  });
  canvas.addEventListener('pointerup', (e) => {
    const d = drag; drag = null;
    if (d && !d.moved && e.button === 0) {
      const r = canvas.getBoundingClientRect();
      const x = e.clientX - r.left, y = e.clientY - r.top;
      showPoint(x, y);
      if (isRun) showPick(pickAt(x, y));
    }
  });
  canvas.addEventListener('wheel', (e) => { e.preventDefault(); cam.dist *= Math.exp(e.deltaY * 0.001); redraw(); }, { passive: false });
  window.addEventListener('resize', redraw);

  // #camera=ex,ey,ez,tx,ty,tz (scene frame) sets the view.
  const fromHash = () => {
    const m = /camera=([^&]+)/.exec(location.hash);
    if (!m) return;
    const v = m[1].split(',').map(Number);
    if (v.length === 6 && v.every(Number.isFinite)) setCamera(v.slice(0, 3), v.slice(3));
  };
  window.addEventListener('hashchange', fromHash);
  resetCamera();
  fromHash();

  // Resolves true once Spark has sorted for the current camera and that frame is on the canvas
  // (false after `limitMs`).
  const settled = async (limitMs = 240000) => {
    const t0 = performance.now();
    for (let quiet = 0; quiet < 3;) {
      if (performance.now() - t0 > limitMs) return false;
      await new Promise((r) => setTimeout(r, 50));
      quiet = (pending || spark.sorting || spark.sortDirty || spark.dirty) ? 0 : quiet + 1;
    }
    return true;
  };
  Object.assign(api, {
    n,
    renderer: 'spark',
    spark,
    viewProj,
    setCamera,
    resetCamera,
    pickAt,
    pointAt,
    runQuery,
    setMode,
    settled,
  });
  if (isRun) {
    $('status').textContent = `${n} Gaussians · ${meta.mode} labels · ${meta.run}`;
  } else {
    for (const id of ['colour', 'query-section', 'pick-section', 'files-section']) $(id).style.display = 'none';
    $('status').textContent = `${n} Gaussians · scene ${meta.scene}${meta.simulated ? ' (SIMULATED)' : ''} · no run yet: a click gives the point's coordinates`;
  }
  requestAnimationFrame(() => { draw(); api.ready = true; document.body.dataset.ready = '1'; });
}

main().catch((e) => fail('viewer: ' + (e && e.message || e)));
