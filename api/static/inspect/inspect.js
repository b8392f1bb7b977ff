// The shadowopt inspector: a scene, its camera and sun, the service's shadow setup (POST /v1/optimize)
// rendered in WebGL2 with the listings of docs/engine-integration.md (shaders/*.glsl, the document's
// tagged blocks verbatim: tests/test_inspect.py asserts they are equal), and what evaluate measures.
// Plain WebGL2, no library. Every request carries the tab's bearer token (sessionStorage) when it has one.

const $ = (id) => document.getElementById(id);
const TOKEN_KEY = "shadowopt-token";
// cascades (or a point light's faces) 1-6
const CASCADE_COLOURS = [[0.9, 0.3, 0.3], [0.3, 0.8, 0.3], [0.3, 0.5, 1.0], [0.95, 0.8, 0.2], [0.8, 0.3, 0.9],
                         [0.2, 0.85, 0.85]];
// renderers/heatmap.py's errors mode (Okabe and Ito 2008 colours).
const WRONGLY_SHADOWED = [213, 94, 0], WRONGLY_LIT = [0, 114, 178];

const state = {
  scenes: [], sceneId: null, info: null, geometry: null, solution: null, renderSolution: null,
  evaluation: null, orbit: null, seq: 0, inFlight: false, pending: false, evalSeq: 0,
  // drawnResponses: optimizeResponses as of the last frame drawn with nothing queued (a split view's optimize
  // has two responses and one frame, so latencies.length counts frames, not responses)
  stats: { optimizeRequests: 0, optimizeResponses: 0, renders: 0, lastInputAt: null, lastLatencyMs: null,
           lastOptimizeMs: null, lastRenderMs: null, latencies: [], drawnResponses: 0 },
};

// --- the service --------------------------------------------------------------------------------

function token() { return sessionStorage.getItem(TOKEN_KEY) || ""; }

async function api(path, opts = {}) {
  const headers = Object.assign({}, opts.headers || {});
  if (token()) headers["Authorization"] = "Bearer " + token();
  let body = opts.body;
  if (opts.json !== undefined) { headers["Content-Type"] = "application/json"; body = JSON.stringify(opts.json); }
  const r = await fetch(path, { method: opts.method || (body ? "POST" : "GET"), headers, body });
  if (r.status === 401) { $("token-form").hidden = false; }
  if (!r.ok) {
    let msg = `${r.status}`;
    try { const e = (await r.json()).error; msg = `${r.status} ${e.code}: ${e.message}`; } catch (_) { /* not JSON */ }
    throw new Error(msg);
  }
  return r;
}

function status(text, isError = false) {
  const s = $("status");
  s.textContent = text;
  s.classList.toggle("error", isError);
}

async function refreshScenes(select) {
  const list = (await (await api("/v1/scenes")).json()).scenes;
  state.scenes = list;
  state.listings = (state.listings || 0) + 1;
  const sel = $("scene");
  sel.innerHTML = "";
  for (const s of list) {
    const o = document.createElement("option");
    o.value = s.scene_id;
    o.textContent = `${s.filename} (${s.triangles} triangles)`;
    sel.appendChild(o);
  }
  if (!list.length) { status("no scenes yet: drop a USD file or upload the demo scene"); return; }
  const has = (id) => id && list.some((s) => s.scene_id === id);
  const id = has(select) ? select : (has(state.sceneId) ? state.sceneId : list[0].scene_id);
  sel.value = id;
  if (id !== state.sceneId) await openScene(id);  // the open scene stays as it is
}

async function upload(file) {
  status(`uploading ${file.name}…`);
  const r = await api(`/v1/scenes?filename=${encodeURIComponent(file.name)}`,
                      { method: "POST", body: file, headers: { "Content-Type": "application/octet-stream" } });
  const info = await r.json();
  status(`uploaded ${info.filename}: ${info.triangles} triangles`);
  await refreshScenes(info.scene_id);
}

async function openScene(id) {
  state.sceneId = id;
  state.solution = state.renderSolution = state.evaluation = null;
  status("loading the scene…");
  state.info = await (await api(`/v1/scenes/${id}`)).json();
  const r = await api(`/v1/scenes/${id}/geometry.glb`);
  const served = r.headers.get("X-Served-Triangles"), total = r.headers.get("X-Scene-Triangles");
  const budget = r.headers.get("X-Triangle-Budget"), decimated = r.headers.get("X-Decimated") === "true";
  state.geometry = parseGLB(await r.arrayBuffer());
  state.geometry.decimated = decimated;
  $("scene-info").textContent = `${total} triangles; served ${served} (budget ${budget})` +
    (decimated ? ": decimated, a preview (its shadows are not the scene's)" : "");
  renderer.setGeometry(state.geometry);
  // cameras: the scene's USD cameras, then orbit
  const cam = $("camera");
  cam.innerHTML = "";
  for (const c of state.info.cameras) cam.add(new Option(c.usd_path, c.usd_path));
  cam.add(new Option("orbit (drag, wheel to zoom; fly: W A S D, Q E)", "orbit"));
  const lo = state.info.bounds.min, hi = state.info.bounds.max;
  const centre = lo.map((v, i) => (v + hi[i]) / 2), extent = Math.hypot(...hi.map((v, i) => v - lo[i]));
  state.orbit = { target: centre, radius: extent * 0.6, az: 0.6, el: 0.45, extent };
  const first = state.info.cameras[0];
  if (first) {  // orbit starts at the scene's first camera, turning about a point a little ahead of it
    const f = unit(first.forward), d = Math.max(extent * 0.04, 1e-3);
    state.orbit = { target: first.position.map((v, i) => v + d * f[i]), radius: d, extent,
                    az: Math.atan2(-f[0], -f[2]), el: Math.asin(Math.max(-1, Math.min(1, -f[1]))) };
  }
  // lights: the scene's directional lights (their direction sets the sliders) or the sliders' sun
  const light = $("light");
  light.innerHTML = "";
  light.add(new Option("sun from the sliders", "sliders"));
  for (const l of state.info.lights) {
    if (l.type === "ignored") continue;
    light.add(new Option(`${l.usd_path} (${l.type})`, l.usd_path));
  }
  const sun = state.info.lights.find((l) => l.type === "directional" && l.direction);
  if (sun) setSliders(sun.direction);
  drawDome();
  status(`${state.info.filename}: optimizing…`);
  requestOptimize();
}

// --- the rig and the request --------------------------------------------------------------------

function sunDirection() {  // where the light travels (the rig's `direction`), world frame +Y up
  const az = +$("azimuth").value * Math.PI / 180, el = +$("elevation").value * Math.PI / 180;
  return [-Math.cos(el) * Math.sin(az), -Math.sin(el), -Math.cos(el) * Math.cos(az)];
}

function setSliders(direction) {
  const [x, y, z] = direction.map((v) => -v);
  const el = Math.asin(Math.max(-1, Math.min(1, y / Math.hypot(x, y, z))));
  $("elevation").value = Math.round(Math.max(1, Math.min(89, el * 180 / Math.PI)));
  $("azimuth").value = Math.round(Math.atan2(x, z) * 180 / Math.PI);
  showSliders();
}

function showSliders() {
  $("azimuth-out").textContent = $("azimuth").value;
  $("elevation-out").textContent = $("elevation").value;
}

function resolution() { return $("resolution").value.split("x").map(Number); }

function orbitCamera() {
  const o = state.orbit;
  const p = [o.target[0] + o.radius * Math.cos(o.el) * Math.sin(o.az), o.target[1] + o.radius * Math.sin(o.el),
             o.target[2] + o.radius * Math.cos(o.el) * Math.cos(o.az)];
  // far: the scene's farthest corner from here (it bounds the cascades' splits); near: a small part of it
  const lo = state.info.bounds.min, hi = state.info.bounds.max;
  let far = 0;
  for (let i = 0; i < 8; i++) far = Math.max(far, Math.hypot(...[(i & 1 ? hi : lo)[0], (i & 2 ? hi : lo)[1], (i & 4 ? hi : lo)[2]].map((v, k) => v - p[k])));
  far = Math.max(far * 1.01, o.extent * 1e-3);
  return { position: p, target: o.target, fov_y_deg: 60, near: Math.max(far * 1e-4, 1e-3), far };
}

function rig() {
  const camSel = $("camera").value;
  const camera = camSel === "orbit" ? orbitCamera() : { usd_path: camSel };
  camera.resolution = resolution();
  const lightSel = $("light").value;
  const light = lightSel === "sliders" ? { type: "directional", direction: sunDirection() } : { usd_path: lightSel };
  const c = $("cascades").value, budget = +$("budget").value;
  // a given count of cascades: one size for every map, the budget shared equally; "auto": the service sizes
  // each map from the budget (drawn each at its own resolution in the largest map's array)
  const side = Math.floor(Math.sqrt(budget / (c === "auto" ? 1 : +c)));
  const shadow = c === "auto" ? { texel_budget: budget, cascades: "auto" } : { resolution: [side, side], cascades: +c };
  if ($("point-maps").value !== "auto") shadow.point_light_maps = $("point-maps").value;  // a point light's maps
  return { camera, lights: [light], shadow,
           coarse_long_side: +$("coarse").value };
}

function output(preset) {
  if (preset.startsWith("engine:")) return { engine: preset.slice(7) };
  if (preset === "reversed_z") return { convention: "d3d", reversed_z: true };
  return { convention: preset };
}

// At most one optimize in flight; slider events while it runs are folded into one more request with the
// newest values, sent when it returns (a trailing debounce: the last event is always served).
function requestOptimize() {
  clearTimeout(evalTimer);  // a measurement waits for the user to pause: it never competes with a solve
  if (renderer) clearTimeout(renderer.mapTimer);  // nor does the light-space view's read-back
  state.stats.lastInputAt = performance.now();
  if (state.inFlight) { state.pending = true; return; }
  optimize();
}

async function optimize() {
  if (!state.sceneId) return;
  state.inFlight = true;
  state.pending = false;
  const seq = ++state.seq;
  const preset = $("preset").value;
  const method = $("method").value;
  const base = { scene_id: state.sceneId, method, rig: rig() };
  // only the searching methods take a time budget (the server refuses an option a method would ignore)
  if (method === "optimized" || method === "path") base.time_budget_ms = +$("time-budget").value;
  const t0 = performance.now();
  try {
    const asked = structuredClone(base);
    asked.rig.output = output(preset);
    const jobs = [postOptimize(asked)];
    // the picture needs world-frame matrices: an engine preset's frame is the engine's, so the same request
    // in the world frame is solved beside it (its numbers are the preset's)
    const compare = $("compare").value;
    jobs.push(preset.startsWith("engine:") ? postOptimize(base) : Promise.resolve(null));
    if (compare) {  // the compared method, with the time budget only if it searches
      const other = Object.assign(structuredClone(base), { method: compare });
      if (compare === "optimized" || compare === "path") other.time_budget_ms = +$("time-budget").value;
      else delete other.time_budget_ms;
      jobs.push(postOptimize(other));
    }
    const [sol, worldSol, compared] = await Promise.all(jobs);
    state.stats.lastOptimizeMs = performance.now() - t0;
    if (seq === state.seq) {
      state.solution = sol;
      state.solution.rig = asked.rig;
      state.renderSolution = worldSol || sol;
      state.compareSolution = compared || null;
      state.evaluation = null;
      drawOverlay();
      const tr = performance.now();
      renderer.render();
      state.stats.lastRenderMs = performance.now() - tr;
      showSolution();
      status(`${state.info.filename}: ${sol.method}, ${sol.lights[0].cascades.length} map(s)`);
      const answered = state.stats.optimizeResponses;  // the answers this frame draws
      afterFrame(() => {  // counted only when these shadows answer the last input (sent after it)
        if (!state.pending && state.stats.lastInputAt !== null && t0 >= state.stats.lastInputAt) {
          state.stats.drawnResponses = Math.max(state.stats.drawnResponses, answered);
          const ms = performance.now() - state.stats.lastInputAt;
          state.stats.lastLatencyMs = ms;
          state.stats.latencies.push(ms);
          showInteraction();
        }
      });
      if ($("auto-evaluate").checked || $("overlay").value !== "none") scheduleEvaluate();
    }
  } catch (e) {
    status(e.message, true);
  } finally {
    state.inFlight = false;
    if (state.pending) optimize();
  }
}

async function postOptimize(body) {
  state.stats.optimizeRequests++;
  const r = await api("/v1/optimize", { json: body });
  state.stats.optimizeResponses++;
  return r.json();
}

function afterFrame(fn) { requestAnimationFrame(() => requestAnimationFrame(fn)); }

let evalTimer = null;
function scheduleEvaluate(delay = 600) {
  clearTimeout(evalTimer);
  evalTimer = setTimeout(evaluate, delay);
}

async function evaluate() {
  if (!state.solution || state.inFlight || state.pending) { if (state.solution) scheduleEvaluate(); return; }
  const seq = ++state.evalSeq, solSeq = state.seq;
  const overlay = $("overlay").value;
  const [w, h] = renderer.size();
  const body = { scene_id: state.sceneId, rig: state.solution.rig, solution: state.solution, screen: [w, h],
                 heatmap: true, heatmap_mode: overlay === "errors" || overlay === "none" ? "errors" : "m" };
  if (overlay === "grid") body.grid_every = 16;
  status("measuring against ray-traced shadows…");
  try {
    const t0 = performance.now();
    const ev = await (await api("/v1/evaluate", { json: body })).json();
    if (seq !== state.evalSeq || solSeq !== state.seq) return;
    ev.page_ms = performance.now() - t0;
    ev.mode = body.heatmap_mode;
    state.evaluation = ev;
    state.evaluation.image = await loadImage("data:image/png;base64," + ev.heatmap_png_base64[0]);
    drawOverlay();
    showEvaluation();
    status(`${state.info.filename}: measured`);
  } catch (e) {
    status(e.message, true);
  }
}

function loadImage(src) {
  return new Promise((ok, fail) => { const i = new Image(); i.onload = () => ok(i); i.onerror = fail; i.src = src; });
}

// --- numbers beside the picture -----------------------------------------------------------------

const fmt = (v, d = 3) => (v === null || v === undefined ? "–" : (typeof v === "number" ? +v.toPrecision(d) : v));

function rows(table, entries) {
  table.innerHTML = "";
  for (const [k, v] of entries) {
    const tr = table.insertRow();
    tr.insertCell().textContent = k;
    tr.insertCell().textContent = v;
  }
}

function showSolution() {
  const s = state.solution, L = s.lights[0], p = L.predicted_error || {};
  const maps = L.cascades;
  rows($("solution-table"), [
    ["method", s.method], ["maps", L.shadow === "none" ? `none: ${L.reason || ""}` : maps.map((c) => c.resolution.join("×")).join(", ")],
    ["splits (m)", maps.map((c) => c.split.map((v) => fmt(v, 3)).join("–")).join(" | ")],
    ["warp", maps.map((c) => c.warp.kind).join(", ")],
    ["depth mode", maps.map((c) => (c.depth || {}).mode).join(", ")],
    ["predicted p95 m", fmt(p.p95_m)], ["predicted mean m", fmt(p.mean_m)],
    ["predicted misclassified px", fmt(p.misclassified_pixels, 4)],
    ["setup ms (server)", fmt(s.timings_ms.total, 4)], ["round trip ms", fmt(state.stats.lastOptimizeMs, 4)],
    ["convention", `${s.convention.api}${s.convention.reversed_z ? ", reversed Z" : ""}` +
                   (s.convention.engine ? ` (${s.convention.engine}: ${s.convention.handedness}-handed, ${s.convention.up_axis} up, ${s.convention.length_unit})` : "")],
    ...(L.notes && L.notes.length ? [["notes", L.notes.join("; ")]] : []),
  ]);
  const rep = $("solver-report");
  const sv = s.solver;
  const lines = sv ? [`${sv.name || ""}: ${sv.message || ""}, ${sv.nfev || 0} evaluations, ${fmt(sv.time_ms, 3)} ms`]
                   : ["no search: the method's closed form"];
  for (const c of (sv && sv.cascades) || []) {
    const base = c.baselines || {};
    const names = Object.keys(base);
    const best = names.length ? names.reduce((a, b) => (base[a] <= base[b] ? a : b)) : null;
    let line = `map ${c.cascade}: chosen ${c.chosen}, objective ${fmt(c.objective)}`;
    if (best) line += `; best baseline ${best} ${fmt(base[best])}` +
      (c.objective > 0 ? ` (${fmt(base[best] / c.objective, 3)}× the chosen)` : "");
    lines.push(line);
  }
  const cmp = state.compareSolution;
  if (cmp) {  // the method right of the split
    const q = cmp.lights[0].predicted_error || {};
    lines.push(`compared (right of the split): ${cmp.method}, predicted p95 m ${fmt(q.p95_m)} (left ${fmt(p.p95_m)}), ` +
               `misclassified px ${fmt(q.misclassified_pixels, 4)} (left ${fmt(p.misclassified_pixels, 4)}), ` +
               `setup ${fmt(cmp.timings_ms.total, 4)} ms`);
  }
  rep.textContent = lines.join("\n");
  rep.style.whiteSpace = "pre-wrap";
}

function showEvaluation() {
  const e = state.evaluation;
  const m = e.measured_error || {};
  rows($("evaluation-table"), [
    ["screen", (e.screen || []).join("×")], ["receiver px", e.receiver_pixels],
    ["misclassified px", `${e.misclassified_pixels} (${fmt(100 * e.misclassified_fraction, 3)} %)`],
    ["wrongly shadowed px", e.wrongly_shadowed_pixels], ["wrongly lit px", e.wrongly_lit_pixels],
    ["outside px", e.outside_pixels], ["measured p95 m", fmt(m.p95_m)], ["measured mean m", fmt(m.mean_m)],
    ["depth test", e.depth], ["evaluate ms (server)", fmt((e.timings_ms || {}).total, 4)],
  ]);
  const legend = $("legend");
  legend.innerHTML = "";
  if ($("overlay").value !== "none" && e.image) {  // the legend: the strip below the screen-sized picture
    const [w, h] = e.screen;
    const c = document.createElement("canvas");
    c.width = e.image.width; c.height = Math.max(1, e.image.height - h);
    c.getContext("2d").drawImage(e.image, 0, h, e.image.width, c.height, 0, 0, e.image.width, c.height);
    legend.appendChild(c);
  }
}

function showInteraction() {
  const s = state.stats;
  rows($("interaction-table"), [
    ["optimize requests", s.optimizeRequests], ["last slider → shadows ms", fmt(s.lastLatencyMs, 4)],
    ["last optimize round trip ms", fmt(s.lastOptimizeMs, 4)],
    ["server setup ms", state.solution ? fmt(state.solution.timings_ms.total, 4) : "–"],
    ["renderer", renderer.name],
  ]);
}

// --- overlay ------------------------------------------------------------------------------------

function drawOverlay() {
  const oc = $("overlay-canvas");
  const [w, h] = renderer.size();
  oc.width = w; oc.height = h;
  const ctx = oc.getContext("2d");
  ctx.clearRect(0, 0, w, h);
  const e = state.evaluation, mode = $("overlay").value;
  if (!e || !e.image || mode === "none") return;
  ctx.globalAlpha = mode === "errors" ? 1.0 : 0.85;  // the m heatmap lets the picture show through a little
  ctx.drawImage(e.image, 0, 0, w, h, 0, 0, w, h);  // the picture is the PNG's top-left region
  ctx.globalAlpha = 1.0;
  if (mode === "errors") {  // only the misclassified pixels, over the WebGL picture
    const img = ctx.getImageData(0, 0, w, h), d = img.data;
    for (let i = 0; i < d.length; i += 4) {
      const ws = d[i] === WRONGLY_SHADOWED[0] && d[i + 1] === WRONGLY_SHADOWED[1] && d[i + 2] === WRONGLY_SHADOWED[2];
      const wl = d[i] === WRONGLY_LIT[0] && d[i + 1] === WRONGLY_LIT[1] && d[i + 2] === WRONGLY_LIT[2];
      d[i + 3] = ws || wl ? 255 : 0;
    }
    ctx.putImageData(img, 0, 0);
  }
}

// --- geometry: binary glTF ----------------------------------------------------------------------

function parseGLB(buf) {
  const dv = new DataView(buf);
  if (dv.getUint32(0, true) !== 0x46546c67) throw new Error("not a binary glTF");
  let off = 12, json = null, bin = null;
  while (off < buf.byteLength) {
    const len = dv.getUint32(off, true), type = dv.getUint32(off + 4, true);
    const chunk = buf.slice(off + 8, off + 8 + len);
    if (type === 0x4e4f534a) json = JSON.parse(new TextDecoder().decode(chunk));
    else if (type === 0x004e4942) bin = chunk;
    off += 8 + len;
  }
  const node = json.nodes[0];
  const origin = node.translation || (node.matrix ? node.matrix.slice(12, 15) : [0, 0, 0]);
  const prim = json.meshes[node.mesh].primitives[0];
  const view = (acc) => {
    const a = json.accessors[acc], bv = json.bufferViews[a.bufferView];
    const start = (bv.byteOffset || 0) + (a.byteOffset || 0);
    const n = a.count * (a.type === "VEC3" ? 3 : 1);
    if (a.componentType === 5126) return new Float32Array(bin, start, n);
    if (a.componentType === 5125) return new Uint32Array(bin, start, n);
    if (a.componentType === 5123) return Uint32Array.from(new Uint16Array(bin, start, n));
    throw new Error(`accessor component type ${a.componentType}`);
  };
  return { positions: view(prim.attributes.POSITION), indices: view(prim.indices), origin };
}

// --- matrices (column-major flat arrays of 16, as the solution returns them) ---------------------

function mul(a, b) {
  const o = new Array(16).fill(0);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0;
    for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
    o[c * 4 + r] = s;
  }
  return o;
}
function translation(t) { return [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, t[0], t[1], t[2], 1]; }
const sub = (a, b) => a.map((v, i) => v - b[i]);
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = (a) => { const n = Math.hypot(...a); return a.map((v) => v / n); };

// The evaluator's camera (solvers.cameras.Camera: right = forward x up, pixel centres at (i + 0.5) / w)
// as an OpenGL view and projection on re-centred points; far pulled in to the scene's extent.
function cameraMatrices(cam, origin, bounds, aspect) {
  const f = unit(cam.forward), u0 = unit(cam.up), r = unit(cross(f, u0)), u = cross(r, f);
  const p = sub(cam.position, origin);
  const view = [r[0], u[0], -f[0], 0, r[1], u[1], -f[1], 0, r[2], u[2], -f[2], 0,
                -dot(r, p), -dot(u, p), dot(f, p), 1];
  let far = cam.far;
  const lo = bounds.min, hi = bounds.max;
  let reach = 0;
  for (let i = 0; i < 8; i++) {
    const c = [(i & 1 ? hi : lo)[0], (i & 2 ? hi : lo)[1], (i & 4 ? hi : lo)[2]];
    reach = Math.max(reach, dot(sub(c, cam.position), f));
  }
  far = Math.min(far, reach * 1.01 + cam.near);
  const near = cam.near, t = Math.tan(cam.fov_y_deg * Math.PI / 360);
  const proj = [1 / (t * aspect), 0, 0, 0, 0, 1 / t, 0, 0, 0, 0, -(far + near) / (far - near), -1,
                0, 0, -2 * far * near / (far - near), 0];
  return { view, proj, position: p };
}

// --- WebGL2 -------------------------------------------------------------------------------------

const ES_HEADER = "#version 300 es\nprecision highp float;\nprecision highp int;\nprecision highp sampler2DArray;\n";
// GLSL 3.30 core (the document's) -> GLSL ES 3.00 (WebGL2): only the version line differs for these pieces.
const toES = (src) => src.replace(/^#version 330 core\n/, ES_HEADER);

// The harness around the document's lookup (not part of the document): the camera pass.
const CAMERA_VERTEX = `${ES_HEADER}
uniform mat4 uCamViewProj;
uniform mat4 uCamView;
in vec3 inPosition;
out vec3 vWorld;
out float vViewDepth;
void main() {
    vWorld = inPosition;
    vViewDepth = -(uCamView * vec4(inPosition, 1.0)).z;   // distance along the camera's forward axis
    gl_Position = uCamViewProj * vec4(inPosition, 1.0);
}
`;
const cameraFragment = (lookup, local) => `${ES_HEADER}
${lookup}
${local}
uniform int uView;          // 0 shaded, 1 cascade colours, 2 shadowed / lit classification
uniform vec3 uCamPos;       // re-centred
uniform vec3 uCascadeColours[6];
uniform vec4 uSpot;         // a spot light: xyz its axis (unit, where it shines), w cos(cone_deg); else w = -2
in vec3 vWorld;
in float vViewDepth;
out vec4 oColor;
void main() {
    vec3 N = normalize(cross(dFdx(vWorld), dFdy(vWorld)));   // the triangle's geometric normal
    if (dot(N, uCamPos - vWorld) < 0.0) N = -N;               // on the side the camera sees
    vec3 L = uToLight.w > 0.5 ? normalize(uToLight.xyz - vWorld) : uToLight.xyz;   // per point for a local light
    bool inCone = dot(-L, uSpot.xyz) >= uSpot.w;              // the evaluator's receivers: in the spot's cone
    bool facing = dot(N, L) > 0.0 && inCone;
    float vis = facing && uParams.x > 0.5 ? localShadowVisibility(vWorld, N, vViewDepth) : 0.0;
    if (uView == 2) { oColor = vec4(vis, facing ? 1.0 : 0.0, 1.0, 1.0); return; }
    float lambert = max(dot(N, L), 0.0);
    vec3 albedo = vec3(0.78, 0.76, 0.72);
    vec3 c = albedo * (0.22 + 0.78 * lambert * (uParams.x > 0.5 ? vis : 1.0));
    if (uView == 1 && uParams.x > 0.5) {
        int last = int(uParams.x) - 1, k = 0;
        if (uParams.z > 0.5) {                                // cube faces: the first face holding the point
            bool inside = false;
            for (k = 0; k <= last; k++) { shadowMapVisibility(k, vWorld, N, inside); if (inside) break; }
        } else {
            while (k < last && vViewDepth > uCascade[k].y) k++;   // the lookup's cascade selection
        }
        if (k <= last) c = mix(c, uCascadeColours[k], 0.3);
    }
    oColor = vec4(pow(c, vec3(1.0 / 2.2)), 1.0);
}
`;
const QUAD_VERTEX = `${ES_HEADER}
out vec2 vUV;
void main() { vec2 p = vec2(gl_VertexID & 1, gl_VertexID >> 1) * 2.0; vUV = p; gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0); }
`;
const QUAD_FRAGMENT = `${ES_HEADER}
uniform sampler2DArray uShadowMap;
uniform int uLayer;
uniform ivec2 uSize;        // the map's own resolution (the array is the largest map's size)
in vec2 vUV;
out vec4 oColor;
void main() {
    ivec2 size = uSize;
    float d = texelFetch(uShadowMap, ivec3(min(ivec2(vUV * vec2(size)), size - 1), uLayer), 0).r;
    oColor = vec4(d, d, d, 1.0);
}
`;

class Renderer {
  constructor(canvas) {
    this.canvas = canvas;
    const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, preserveDrawingBuffer: true });
    if (!gl) throw new Error("this browser has no WebGL2");
    this.gl = gl;
    this.ext = { clamp: gl.getExtension("EXT_depth_clamp"), offset: gl.getExtension("EXT_polygon_offset_clamp"),
                 clip: gl.getExtension("EXT_clip_control"), floatTarget: gl.getExtension("EXT_color_buffer_float") };
    const dbg = gl.getExtension("WEBGL_debug_renderer_info");
    this.name = gl.getParameter(dbg ? dbg.UNMASKED_RENDERER_WEBGL : gl.RENDERER);
    this.geometry = null;
    this.mapTex = null;
    this.mapKey = "";
  }

  async init() {
    const get = async (n) => (await fetch(`/inspect/static/shaders/${n}.glsl`)).text();
    const [vert, hard, lin, lookup, local] = await Promise.all(["light-pass-vertex", "light-pass-hardware",
                                                                 "light-pass-linear", "shadow-lookup",
                                                                 "shadow-lookup-local"].map(get));
    this.lookupSource = lookup;
    this.progs = {
      hardware: this.program(toES(vert), toES(hard)), linear: this.program(toES(vert), toES(lin)),
      camera: this.program(CAMERA_VERTEX, cameraFragment(lookup, local)), quad: this.program(QUAD_VERTEX, QUAD_FRAGMENT),
    };
    const gl = this.gl;
    this.ubo = gl.createBuffer();
    const cam = this.progs.camera;
    const bi = gl.getUniformBlockIndex(cam, "ShadowMaps");
    gl.uniformBlockBinding(cam, bi, 0);
    this.blockSize = gl.getActiveUniformBlockParameter(cam, bi, gl.UNIFORM_BLOCK_DATA_SIZE);
    const names = ["uTexMatrix[0]", "uLightView[0]", "uDepth[0]", "uLinear[0]", "uCascade[0]", "uToLight", "uParams"];
    const idx = gl.getUniformIndices(cam, names);
    const offs = gl.getActiveUniforms(cam, idx, gl.UNIFORM_OFFSET);
    this.offsets = Object.fromEntries(names.map((n, i) => [n.replace("[0]", ""), offs[i] / 4]));
  }

  program(vs, fs) {
    const gl = this.gl;
    const p = gl.createProgram();
    for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
      const s = gl.createShader(type);
      gl.shaderSource(s, src);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error("shader: " + gl.getShaderInfoLog(s));
      gl.attachShader(p, s);
    }
    gl.bindAttribLocation(p, 0, "inPosition");
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error("link: " + gl.getProgramInfoLog(p));
    return p;
  }

  setGeometry(g) {
    const gl = this.gl;
    if (this.vao) gl.deleteVertexArray(this.vao);
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const vb = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, vb);
    gl.bufferData(gl.ARRAY_BUFFER, g.positions, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    const ib = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, g.indices, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    this.geometry = g;
    this.count = g.indices.length;
    this.render();
  }

  size() { return [this.canvas.width, this.canvas.height]; }

  // The light pass of map k into layer k of the depth array: the document's OpenGL state block, through
  // EXT_depth_clamp, EXT_polygon_offset_clamp and EXT_clip_control (WebGL's names for the same calls).
  lightPass(k, map, clip, reversedZ, T) {
    const gl = this.gl, { clamp, offset, clip: cc } = this.ext;
    const [w, h] = map.resolution;
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTextureLayer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, this.mapTex, 0, k);
    gl.drawBuffers([gl.NONE]);
    gl.viewport(0, 0, w, h);
    if (cc) cc.clipControlEXT(clip === "opengl" ? cc.LOWER_LEFT_EXT : (clip === "vulkan" ? cc.LOWER_LEFT_EXT : cc.UPPER_LEFT_EXT),
                              clip === "opengl" ? cc.NEGATIVE_ONE_TO_ONE_EXT : cc.ZERO_TO_ONE_EXT);
    gl.enable(gl.DEPTH_TEST);
    gl.depthMask(true);
    gl.clearDepth(reversedZ ? 0.0 : 1.0);
    gl.clear(gl.DEPTH_BUFFER_BIT);
    const d = map.depth, mode = d.mode, blk = d[mode];
    const kk = mode === "hardware" ? blk.slope_scaled || 0 : 0, mm = mode === "hardware" ? blk.slope_clamp || 0 : 0;
    // light-pass-state-gl: glEnable(GL_DEPTH_CLAMP); glDisable(GL_CULL_FACE); glEnable(GL_POLYGON_OFFSET_FILL);
    // glPolygonOffsetClamp(reversedZ ? -k : k, 0, reversedZ ? -m : m); glDepthFunc(reversedZ ? GREATER : LESS)
    if (clamp) gl.enable(clamp.DEPTH_CLAMP_EXT);
    gl.disable(gl.CULL_FACE);
    gl.enable(gl.POLYGON_OFFSET_FILL);
    if (offset) offset.polygonOffsetClampEXT(reversedZ ? -kk : kk, 0.0, reversedZ ? -mm : mm);
    else gl.polygonOffset(reversedZ ? -kk : kk, 0.0);
    gl.depthFunc(reversedZ ? gl.GREATER : gl.LESS);
    const prog = this.progs[mode];
    gl.useProgram(prog);
    const view = mul(map.view_matrix, T);
    gl.uniformMatrix4fv(gl.getUniformLocation(prog, "uLightViewProj"), false, mul(map.projection_matrix, view));
    gl.uniformMatrix4fv(gl.getUniformLocation(prog, "uLightView"), false, view);
    if (mode === "linear") {
      gl.uniform3f(gl.getUniformLocation(prog, "uLinearDepth"), blk.near, blk.far, reversedZ ? 1 : 0);
      gl.uniform2f(gl.getUniformLocation(prog, "uLinearOffset"), blk.slope_scaled || 0, blk.slope_clamp || 0);
    }
    gl.bindVertexArray(this.vao);
    gl.drawElements(gl.TRIANGLES, this.count, gl.UNSIGNED_INT, 0);
    gl.bindVertexArray(null);
    if (clamp) gl.disable(clamp.DEPTH_CLAMP_EXT);
    gl.disable(gl.POLYGON_OFFSET_FILL);
    if (offset) offset.polygonOffsetClampEXT(0, 0, 0);
    if (cc) cc.clipControlEXT(cc.LOWER_LEFT_EXT, cc.NEGATIVE_ONE_TO_ONE_EXT);
    gl.depthFunc(gl.LESS);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.deleteFramebuffer(fbo);
  }

  render() {
    const gl = this.gl;
    const [w, h] = resolution();
    if (this.canvas.width !== w || this.canvas.height !== h) { this.canvas.width = w; this.canvas.height = h; }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, w, h);
    gl.disable(gl.SCISSOR_TEST);
    // the sky in the shaded views; black (no surface) in the classification, which is read back
    if ($("view").value === "classification") gl.clearColor(0, 0, 0, 1); else gl.clearColor(0.45, 0.6, 0.78, 1);
    gl.clearDepth(1.0);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    if (!this.geometry || !state.info) return;
    const origin = this.geometry.origin, T = translation(origin);
    const sol = state.renderSolution;
    const note = [];
    if (this.geometry.decimated) note.push("decimated geometry: the shadows are a preview");
    // the camera: the solution's (resolved) when there is one, the orbit's while dragging or before
    let cam;
    if ($("camera").value === "orbit" || !sol) {
      const c = $("camera").value === "orbit" ? orbitCamera() : state.info.cameras[0];
      if (!c) { note.push("no camera: choose orbit"); $("render-note").textContent = note.join("; "); return; }
      const fwd = c.forward || sub(c.target, c.position);
      cam = { position: c.position, forward: fwd, up: c.up || [0, 1, 0], fov_y_deg: c.fov_y_deg || 60,
              near: c.near || 0.1, far: c.far || 1000 };
    } else cam = sol.resolved.camera;
    const cm = cameraMatrices(cam, origin, state.info.bounds, w / h);
    // two methods side by side: the first left of the split, the compared one right of it
    const other = $("compare").value && state.compareSolution ? state.compareSolution : null;
    const splitX = other ? Math.round(w * +$("split").value / 100) : w;
    const nMaps = this.drawWith(sol, 0, 0, splitX, cm, T, note);
    if (other) {
      this.drawWith(other, 1, splitX, w, cm, T, note);
      this.mapTex = this.slots[0].tex;  // the light-space view shows the left method's maps
      gl.enable(gl.SCISSOR_TEST);  // the divide
      gl.scissor(Math.max(0, splitX - 1), 0, 2, h);
      gl.clearColor(1, 1, 1, 1);
      gl.clear(gl.COLOR_BUFFER_BIT);
    }
    gl.disable(gl.SCISSOR_TEST);
    state.stats.renders++;
    $("render-note").textContent = [...new Set(note)].join("; ");
    // the light-space view when the sun rests: its read-back waits for the GPU (on a software GL, for the
    // CPU the server's next solve needs), so the next input cancels it (requestOptimize)
    clearTimeout(this.mapTimer);
    if (nMaps && this.ext.floatTarget) this.mapTimer = setTimeout(() => this.drawMaps(nMaps), 250);
  }

  // The light passes of one solution into its slot's array texture, then the camera pass over the columns
  // [x0, x1) of the canvas; the number of maps drawn.
  drawWith(sol, slot, x0, x1, cm, T, note) {
    const gl = this.gl, [w, h] = this.size();
    this.slots = this.slots || [{}, {}];
    const sl = this.slots[slot];
    const block = new Float32Array(this.blockSize / 4);
    let nMaps = 0;
    const light = sol && sol.lights[0];
    if (light && (!light.cascades || !light.cascades.length)) {
      note.push(`no shadow map: ${light.reason || "the light reaches no receiver the camera sees"}`);
    }
    const lit = sol && sol.resolved && sol.resolved.lights[0];  // the light as solved (world frame)
    let spot = [0, 0, 0, -2];  // no cone
    if (light && light.cascades && light.cascades.length && lit) {
      const maps = light.cascades;
      const clip = sol.convention.reversed_z ? "reversed_z" : sol.convention.api;
      const reversedZ = !!sol.convention.reversed_z;
      // the document's array: as large as the largest map, map k in its first rows and columns
      const mw = Math.max(...maps.map((m) => m.resolution[0])), mh = Math.max(...maps.map((m) => m.resolution[1]));
      if (maps.some((m) => m.warp && m.warp.kind === "log")) note.push("a log-warped map: the listing's light pass has no log warp");
      const key = `${mw}x${mh}x${maps.length}`;
      if (key !== sl.key) {
        if (sl.tex) gl.deleteTexture(sl.tex);
        sl.tex = gl.createTexture();
        gl.bindTexture(gl.TEXTURE_2D_ARRAY, sl.tex);
        gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.DEPTH_COMPONENT32F, mw, mh, maps.length);
        for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D_ARRAY, p, gl.NEAREST);
        gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_COMPARE_MODE, gl.NONE);
        sl.key = key;
      }
      this.mapTex = sl.tex;
      if (!state.skipLight) maps.forEach((m, k) => this.lightPass(k, m, clip, reversedZ, T));
      const o = this.offsets;
      maps.forEach((m, k) => {
        const d = m.depth, blk = d[d.mode];
        block.set(mul(m.texture_matrix, T), o.uTexMatrix + 16 * k);
        block.set(mul(m.view_matrix, T), o.uLightView + 16 * k);
        block.set([blk.constant, blk.slope, blk.normal_offset || 0, d.mode === "linear" ? 1 : 0], o.uDepth + 4 * k);
        block.set([d.linear.near, d.linear.far, m.resolution[0], m.resolution[1]], o.uLinear + 4 * k);
        const band = m.blend_band || [m.split[1], m.split[1]];
        block.set([m.split[0], m.split[1], band[0], band[1]], o.uCascade + 4 * k);
      });
      // shadow-lookup-local: a spot or point light's position (re-centred) with w = 1; cube faces: uParams.z = 1
      if (lit.type === "directional") block.set([...unit(lit.direction).map((v) => -v), 0], o.uToLight);
      else block.set([...sub(lit.position, T.slice(12, 15)), 1], o.uToLight);
      if (lit.type === "spot") spot = [...unit(lit.direction), Math.cos(lit.cone_deg * Math.PI / 180)];
      const faces = maps.some((m) => m.face);
      block.set([maps.length, reversedZ ? 1 : 0, faces ? 1 : 0, 0], o.uParams);
      nMaps = maps.length;
      sl.sizes = maps.map((m) => m.resolution);
    } else if (lit && lit.type !== "directional") {  // no map (shadow "none"): the light unshadowed
      block.set([...sub(lit.position, T.slice(12, 15)), 1], this.offsets.uToLight);
      if (lit.type === "spot") spot = [...unit(lit.direction), Math.cos(lit.cone_deg * Math.PI / 180)];
    } else {
      block.set([...unit(lit ? lit.direction : sunDirection()).map((v) => -v), 0], this.offsets.uToLight);  // unshadowed
    }
    if (!sl.tex) {  // nothing to sample yet: a 1-texel array keeps the sampler complete
      sl.tex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D_ARRAY, sl.tex);
      gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.DEPTH_COMPONENT32F, 1, 1, 1);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D_ARRAY, p, gl.NEAREST);
      sl.key = "";
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, w, h);
    gl.enable(gl.SCISSOR_TEST);
    gl.scissor(x0, 0, x1 - x0, h);
    const prog = this.progs.camera;
    gl.useProgram(prog);
    gl.bindBuffer(gl.UNIFORM_BUFFER, this.ubo);
    gl.bufferData(gl.UNIFORM_BUFFER, block, gl.DYNAMIC_DRAW);
    gl.bindBufferBase(gl.UNIFORM_BUFFER, 0, this.ubo);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, sl.tex);
    gl.uniform1i(gl.getUniformLocation(prog, "uShadowMap"), 0);
    gl.uniformMatrix4fv(gl.getUniformLocation(prog, "uCamViewProj"), false, mul(cm.proj, cm.view));
    gl.uniformMatrix4fv(gl.getUniformLocation(prog, "uCamView"), false, cm.view);
    gl.uniform3fv(gl.getUniformLocation(prog, "uCamPos"), cm.position);
    gl.uniform3fv(gl.getUniformLocation(prog, "uCascadeColours"), CASCADE_COLOURS.flat());
    gl.uniform4fv(gl.getUniformLocation(prog, "uSpot"), spot);
    gl.uniform1i(gl.getUniformLocation(prog, "uView"), { shaded: 0, cascades: 1, classification: 2 }[$("view").value]);
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    gl.disable(gl.CULL_FACE);
    gl.bindVertexArray(this.vao);
    gl.drawElements(gl.TRIANGLES, this.count, gl.UNSIGNED_INT, 0);
    gl.bindVertexArray(null);
    gl.disable(gl.SCISSOR_TEST);
    if (slot === 0) this.mapTex = sl.tex;
    return nMaps;
  }

  // The stored depth of each map, side by side (light space; grey from the nearest to the farthest caster
  // depth of the map, white where nothing was drawn).
  drawMaps(n) {
    const gl = this.gl, side = 160;
    const out = $("maps");
    out.width = side * n; out.height = side;
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, side, side);
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
    gl.viewport(0, 0, side, side);
    gl.disable(gl.DEPTH_TEST);
    gl.useProgram(this.progs.quad);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.mapTex);
    gl.uniform1i(gl.getUniformLocation(this.progs.quad, "uShadowMap"), 0);
    const ctx = out.getContext("2d"), px = new Float32Array(side * side * 4);
    const empty = state.renderSolution && state.renderSolution.convention.reversed_z ? 0.0 : 1.0;
    for (let k = 0; k < n; k++) {
      gl.uniform1i(gl.getUniformLocation(this.progs.quad, "uLayer"), k);
      gl.uniform2i(gl.getUniformLocation(this.progs.quad, "uSize"), ...this.slots[0].sizes[k]);
      gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
      gl.readPixels(0, 0, side, side, gl.RGBA, gl.FLOAT, px);
      let lo = Infinity, hi = -Infinity;
      for (let i = 0; i < px.length; i += 4) if (px[i] !== empty) { lo = Math.min(lo, px[i]); hi = Math.max(hi, px[i]); }
      const img = ctx.createImageData(side, side);
      for (let y = 0; y < side; y++) for (let x = 0; x < side; x++) {
        const d = px[((side - 1 - y) * side + x) * 4], o = (y * side + x) * 4;
        const g = d === empty ? 255 : Math.round(30 + 190 * (d - lo) / Math.max(hi - lo, 1e-12));
        img.data[o] = img.data[o + 1] = img.data[o + 2] = g;
        img.data[o + 3] = 255;
      }
      ctx.putImageData(img, k * side, 0);
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.deleteFramebuffer(fbo);
    gl.deleteTexture(tex);
    gl.enable(gl.DEPTH_TEST);
  }

  // Per pixel, row 0 at the top: "0" no surface, "1" facing away from the light, "L" lit, "S" shadowed
  // (visibility <= 1/2, as the evaluator counts a blend), from a classification render.
  classification() {
    const keep = $("view").value;
    $("view").value = "classification";
    this.render();
    const gl = this.gl, [w, h] = this.size();
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    $("view").value = keep;
    this.render();
    const rowsOut = [];
    for (let y = h - 1; y >= 0; y--) {
      let s = "";
      for (let x = 0; x < w; x++) {
        const i = (y * w + x) * 4;
        s += px[i + 2] < 128 ? "0" : px[i + 1] < 128 ? "1" : px[i] > 128 ? "L" : "S";
      }
      rowsOut.push(s);
    }
    return { width: w, height: h, rows: rowsOut };
  }
}

// --- the sky dome and the orbit controls --------------------------------------------------------

function drawDome() {
  const c = $("dome"), ctx = c.getContext("2d"), R = c.width / 2 - 4, cx = c.width / 2, cy = c.height / 2;
  ctx.clearRect(0, 0, c.width, c.height);
  ctx.strokeStyle = "#5b6472";
  ctx.beginPath(); ctx.arc(cx, cy, R, 0, 2 * Math.PI); ctx.stroke();
  ctx.beginPath(); ctx.arc(cx, cy, R / 2, 0, 2 * Math.PI); ctx.stroke();
  ctx.fillStyle = "#9fb3c8"; ctx.font = "10px sans-serif";
  ctx.fillText("+Z", cx - 6, cy + R - 2); ctx.fillText("+X", cx + R - 14, cy + 3);
  const az = +$("azimuth").value * Math.PI / 180, el = +$("elevation").value * Math.PI / 180;
  const r = R * (1 - el / (Math.PI / 2));
  ctx.fillStyle = "#ffd34d";
  ctx.beginPath(); ctx.arc(cx + r * Math.sin(az), cy + r * Math.cos(az), 6, 0, 2 * Math.PI); ctx.fill();
}

function domeDrag(ev) {
  const c = $("dome"), b = c.getBoundingClientRect(), R = c.width / 2 - 4;
  const x = (ev.clientX - b.left) * c.width / b.width - c.width / 2, y = (ev.clientY - b.top) * c.height / b.height - c.height / 2;
  const r = Math.min(Math.hypot(x, y), R);
  $("azimuth").value = Math.round(Math.atan2(x, y) * 180 / Math.PI);
  $("elevation").value = Math.round(Math.max(1, Math.min(89, 90 * (1 - r / R))));
  $("light").value = "sliders";
  sunChanged();
}

function sunChanged() {
  showSliders();
  drawDome();
  requestOptimize();
}

function wire() {
  $("token-form").addEventListener("submit", (e) => {
    e.preventDefault();
    sessionStorage.setItem(TOKEN_KEY, $("token").value.trim());
    $("token-form").hidden = true;
    status("checking the token…");
    start();
  });
  $("scene").addEventListener("change", () => openScene($("scene").value).catch((e) => status(e.message, true)));
  $("file").addEventListener("change", () => { if ($("file").files[0]) upload($("file").files[0]).catch((e) => status(e.message, true)); });
  $("demo").addEventListener("click", async () => {
    try {
      const blob = await (await fetch("/inspect/demo/scene.usda")).blob();
      await upload(new File([blob], "demo_scene.usda"));
    } catch (e) { status(e.message, true); }
  });
  const drop = $("drop");
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => {
    e.preventDefault();
    drop.classList.remove("over");
    const f = e.dataTransfer.files[0];
    if (f) upload(f).catch((err) => status(err.message, true));
  });
  for (const id of ["azimuth", "elevation"]) $(id).addEventListener("input", () => { $("light").value = "sliders"; sunChanged(); });
  for (const id of ["camera", "resolution", "cascades", "budget", "method", "preset", "light", "time-budget", "coarse",
                    "point-maps"]) {
    $(id).addEventListener("change", () => { renderer.render(); drawOverlay(); requestOptimize(); });
  }
  $("view").addEventListener("change", () => renderer.render());
  $("split").addEventListener("input", () => renderer.render());
  $("compare").addEventListener("change", () => requestOptimize());
  $("overlay").addEventListener("change", () => { drawOverlay(); if ($("overlay").value !== "none") evaluate(); else showEvaluation(); });
  $("evaluate").addEventListener("click", () => evaluate());
  $("refresh").addEventListener("click", () => refreshScenes().catch((e) => status(e.message, true)));
  const dome = $("dome");
  let domeDown = false;
  dome.addEventListener("pointerdown", (e) => { domeDown = true; domeDrag(e); });
  window.addEventListener("pointerup", () => { domeDown = false; });
  dome.addEventListener("pointermove", (e) => { if (domeDown) domeDrag(e); });
  // orbit: drag turns around the scene's centre, the wheel zooms; the picture follows at once (the old maps),
  // the shadow setup for the new view is asked for when the drag ends
  const cv = $("view-canvas");
  let drag = null;
  cv.addEventListener("pointerdown", (e) => {
    if ($("camera").value !== "orbit") return;
    drag = { x: e.clientX, y: e.clientY };
    cv.setPointerCapture(e.pointerId);
  });
  cv.addEventListener("pointermove", (e) => {
    if (!drag) return;
    state.orbit.az -= (e.clientX - drag.x) * 0.01;
    state.orbit.el = Math.max(-1.4, Math.min(1.4, state.orbit.el + (e.clientY - drag.y) * 0.01));
    drag = { x: e.clientX, y: e.clientY };
    renderer.render();
  });
  cv.addEventListener("pointerup", () => { if (drag) { drag = null; requestOptimize(); } });
  // fly: W/S forward and back, A/D sideways, Q/E down and up (the orbit's centre moves with the camera)
  window.addEventListener("keydown", (e) => {
    if ($("camera").value !== "orbit" || /^(INPUT|SELECT|TEXTAREA)$/.test(document.activeElement.tagName)) return;
    const o = state.orbit, c = orbitCamera();
    const f = unit(sub(o.target, c.position)), r = unit(cross(f, [0, 1, 0])), step = o.radius * 0.15;
    const move = { w: f, s: f.map((v) => -v), d: r, a: r.map((v) => -v), e: [0, 1, 0], q: [0, -1, 0] }[e.key.toLowerCase()];
    if (!move) return;
    e.preventDefault();
    o.target = o.target.map((v, i) => v + step * move[i]);
    renderer.render();
    clearTimeout(state.wheelTimer);
    state.wheelTimer = setTimeout(requestOptimize, 200);
  });
  cv.addEventListener("wheel", (e) => {
    if ($("camera").value !== "orbit") return;
    e.preventDefault();
    state.orbit.radius *= Math.exp(e.deltaY * 0.001);
    renderer.render();
    clearTimeout(state.wheelTimer);
    state.wheelTimer = setTimeout(requestOptimize, 200);
  }, { passive: false });
}

let renderer;

async function start() {
  try {
    await refreshScenes();
    showInteraction();
  } catch (e) {
    status(e.message + (e.message.startsWith("401") ? " (give the server's token above)" : ""), true);
  }
}

async function main() {
  showSliders();
  drawDome();
  try {
    renderer = new Renderer($("view-canvas"));
    await renderer.init();
  } catch (e) { status(e.message, true); return; }
  wire();
  // for tests and the benchmark: read-only views of the page's state
  window.inspector = { state, renderer, classification: () => renderer.classification() };
  await start();
  document.body.dataset.ready = "1";
}

main();
