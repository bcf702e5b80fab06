// gs4city view: a small WebGL2 splat viewer (docs/view.md). Each Gaussian is drawn as a
// depth-tested round sprite whose diameter is 4σ (its largest activated scale) in perspective;
// Gaussians with opacity below MIN_OPACITY are not drawn. Picking renders every splat's
// index + 1 as an RGBA colour into an offscreen target with the same geometry and reads the
// clicked pixel, then asks the server for the Gaussian's hierarchy (/api/pick).
'use strict';
(async function () {
  const MIN_OPACITY = 0.05;
  const FOVY = 50 * Math.PI / 180;
  const $ = (id) => document.getElementById(id);
  const api = { ready: false, error: null };
  window.gs4city = api;
  const fail = (msg) => { api.error = msg; $('status').textContent = msg; };

  const canvas = $('gl');
  const gl = canvas.getContext('webgl2', { antialias: false, preserveDrawingBuffer: true });
  if (!gl) { fail('WebGL2 is not available in this browser.'); return; }

  let meta, buf;
  try {
    meta = await (await fetch('api/meta')).json();
    const r = await fetch('api/splats.bin');
    if (!r.ok) throw new Error('api/splats.bin: HTTP ' + r.status);
    buf = await r.arrayBuffer();
  } catch (e) { fail('Cannot load the run: ' + e); return; }
  const head = new DataView(buf);
  const magic = String.fromCharCode(head.getUint8(0), head.getUint8(1), head.getUint8(2), head.getUint8(3));
  const n = head.getUint32(8, true);
  if (magic !== 'GS4V' || head.getUint32(4, true) !== 1 || buf.byteLength !== 16 + 28 * n) {
    fail('api/splats.bin: not a version-1 GS4V buffer'); return;
  }
  let off = 16;
  const take = (T, count, bytes) => { const a = new T(buf, off, count); off += bytes; return a; };
  const pos = take(Float32Array, 3 * n, 12 * n);
  const size = take(Float32Array, n, 4 * n);
  const rgba = take(Uint8Array, 4 * n, 4 * n);
  const cls = take(Uint8Array, 4 * n, 4 * n);
  const bld = take(Uint8Array, 4 * n, 4 * n);
  const sel = new Uint8Array(n);

  // --- shaders -------------------------------------------------------------------------
  const VS = `#version 300 es
  layout(location=0) in vec3 aPos;
  layout(location=1) in float aSize;
  layout(location=2) in vec4 aRgb;
  layout(location=3) in vec4 aClass;
  layout(location=4) in vec4 aBuilding;
  layout(location=5) in float aSel;
  uniform mat4 uViewProj;
  uniform float uFocal;
  uniform float uMaxPoint;
  uniform int uMode;
  uniform int uQuery;
  out vec4 vColor;
  flat out uint vId;
  void main() {
    vec4 c = uViewProj * vec4(aPos, 1.0);
    vId = uint(gl_VertexID) + 1u;
    if (aRgb.a < ${MIN_OPACITY.toFixed(4)} || c.w <= 0.0) {
      gl_Position = vec4(2.0, 2.0, 2.0, 1.0); gl_PointSize = 1.0; vColor = vec4(0.0); return;
    }
    gl_Position = c;
    gl_PointSize = clamp(4.0 * aSize * uFocal / c.w, 1.0, uMaxPoint);
    vec3 col = uMode == 1 ? aClass.rgb : (uMode == 2 ? aBuilding.rgb : aRgb.rgb);
    if (uQuery == 1) col = aSel > 0.5 ? min(col * 1.15 + 0.05, 1.0) : col * 0.18 + 0.03;
    vColor = vec4(col, 1.0);
  }`;
  const FS = `#version 300 es
  precision highp float;
  in vec4 vColor;
  flat in uint vId;
  uniform int uPick;
  out vec4 o;
  void main() {
    vec2 d = gl_PointCoord * 2.0 - 1.0;
    if (dot(d, d) > 1.0) discard;
    if (uPick == 1) {
      o = vec4(float(vId & 255u), float((vId >> 8) & 255u), float((vId >> 16) & 255u), float((vId >> 24) & 255u)) / 255.0;
    } else {
      o = vColor;
    }
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
  for (const u of ['uViewProj', 'uFocal', 'uMaxPoint', 'uMode', 'uQuery', 'uPick']) U[u] = gl.getUniformLocation(prog, u);

  const vao = gl.createVertexArray();
  gl.bindVertexArray(vao);
  const attr = (loc, data, comps, type, normalized) => {
    const b = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, b);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, comps, type, normalized, 0, 0);
    return b;
  };
  attr(0, pos, 3, gl.FLOAT, false);
  attr(1, size, 1, gl.FLOAT, false);
  attr(2, rgba, 4, gl.UNSIGNED_BYTE, true);
  attr(3, cls, 4, gl.UNSIGNED_BYTE, true);
  attr(4, bld, 4, gl.UNSIGNED_BYTE, true);
  const selBuf = attr(5, sel, 1, gl.UNSIGNED_BYTE, true);
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
  const resetCamera = () => {
    Object.assign(cam, { target: meta.center.slice(), dist: meta.extent * 1.6, yaw: 0.6, pitch: 0.6 });
    redraw();
  };
  const eye = () => {
    const h = Math.cos(cam.pitch);
    const dir = v3.add(v3.add(v3.mul(e1, h * Math.cos(cam.yaw)), v3.mul(e2, h * Math.sin(cam.yaw))), v3.mul(up, Math.sin(cam.pitch)));
    return v3.add(cam.target, v3.mul(dir, cam.dist));
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
  // Column-major 4×4 matrices.
  const lookAt = (e, t, u) => {
    const f = v3.norm(v3.sub(t, e));
    const s = v3.norm(v3.cross(f, u));
    const uu = v3.cross(s, f);
    return [s[0], uu[0], -f[0], 0, s[1], uu[1], -f[1], 0, s[2], uu[2], -f[2], 0,
      -v3.dot(s, e), -v3.dot(uu, e), v3.dot(f, e), 1];
  };
  const perspective = (fovy, aspect, near, far) => {
    const f = 1 / Math.tan(fovy / 2);
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, 2 * far * near / (near - far), 0];
  };
  const mul4 = (a, b) => {
    const o = new Array(16).fill(0);
    for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) for (let k = 0; k < 4; k++) o[c * 4 + r] += a[k * 4 + r] * b[c * 4 + k];
    return o;
  };
  const viewProj = () => {
    const w = canvas.width, h = canvas.height;
    const near = Math.max(cam.dist * 0.005, meta.extent * 1e-5);
    const far = cam.dist + meta.extent * 6;
    // Looking straight along `up`: another up vector keeps lookAt defined.
    const e = eye();
    const fwd = v3.norm(v3.sub(cam.target, e));
    const u = Math.abs(v3.dot(fwd, up)) > 0.999 ? e1 : up;
    return mul4(perspective(FOVY, w / h, near, far), lookAt(e, cam.target, u));
  };

  // --- drawing --------------------------------------------------------------------------
  let mode = 0, queryOn = 0, pending = false;
  const pickFbo = { fb: null, tex: null, depth: null, w: 0, h: 0 };
  const resize = () => {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  };
  const draw = (pick) => {
    resize();
    const w = canvas.width, h = canvas.height;
    gl.useProgram(prog);
    gl.bindVertexArray(vao);
    gl.uniformMatrix4fv(U.uViewProj, false, new Float32Array(viewProj()));
    gl.uniform1f(U.uFocal, h / (2 * Math.tan(FOVY / 2)));
    gl.uniform1f(U.uMaxPoint, maxPoint);
    gl.uniform1i(U.uMode, mode);
    gl.uniform1i(U.uQuery, queryOn);
    gl.uniform1i(U.uPick, pick ? 1 : 0);
    gl.viewport(0, 0, w, h);
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    gl.disable(gl.BLEND);
    if (pick) gl.clearColor(0, 0, 0, 0); else gl.clearColor(0.11, 0.125, 0.145, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.drawArrays(gl.POINTS, 0, n);
  };
  const redraw = () => {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; draw(false); });
  };
  // The index of the splat under CSS pixel (x, y) of the canvas, or −1.
  const pickAt = (x, y) => {
    resize();
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
    draw(true);
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
  const showPick = async (i) => {
    const box = $('pick');
    box.className = '';
    box.replaceChildren();
    if (i < 0) { box.append(el('div', { id: 'pick-none', class: 'muted' }, 'No splat under the cursor.')); api.lastPick = { gaussian: -1 }; return; }
    const r = await fetch('api/pick?i=' + i);
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
    redraw();
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
    sel.fill(0); queryOn = 0;
    gl.bindBuffer(gl.ARRAY_BUFFER, selBuf); gl.bufferSubData(gl.ARRAY_BUFFER, 0, sel);
    $('count').textContent = ''; $('count').removeAttribute('data-count');
    $('query-info').textContent = '';
    redraw();
  };
  const runQuery = async (text) => {
    $('query-error').textContent = '';
    const r = await fetch('api/query?where=' + encodeURIComponent(text));
    const j = await r.json();
    if (!r.ok) { clearQuery(); $('query-error').textContent = j.error; api.lastQuery = { error: j.error }; return; }
    const bin = atob(j.mask);
    let count = 0;
    for (let i = 0; i < n; i++) {
      const on = (bin.charCodeAt(i >> 3) >> (i & 7)) & 1;
      sel[i] = on ? 255 : 0;
      count += on;
    }
    gl.bindBuffer(gl.ARRAY_BUFFER, selBuf); gl.bufferSubData(gl.ARRAY_BUFFER, 0, sel);
    queryOn = 1;
    $('count').textContent = `${count} Gaussians`;
    $('count').setAttribute('data-count', String(count));
    $('query-info').textContent = `${j.query}: ${j.labels} labels, ${j.entities} entities` + (j.warnings.length ? ' — ' + j.warnings.join('; ') : '');
    api.lastQuery = { count, server: j.count, query: j.query };
    redraw();
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
      const k = cam.dist * 2 * Math.tan(FOVY / 2) / canvas.clientHeight;
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
      showPick(pickAt(e.clientX - r.left, e.clientY - r.top));
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

  Object.assign(api, {
    n,
    viewProj: () => viewProj(),
    setCamera,
    resetCamera,
    pickAt,
    runQuery,
    setMode,
  });
  $('status').textContent = `${n} Gaussians · ${meta.mode} labels · ${meta.run}`;
  requestAnimationFrame(() => { draw(false); api.ready = true; document.body.dataset.ready = '1'; });
})();
