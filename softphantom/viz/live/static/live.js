// softphantom live view: three.js draws the phantom, uPlot the plots; both are served from this
// package (static/vendor/, built from the npm registry by scripts/vendor-live.sh): nothing is
// fetched from elsewhere. Data: GET /api/geometry (surfaces at rest, mm), GET /api/state, then
// Server-Sent Events /api/events (docs/stream.md). Model frame: y = needle, z = up, mm.
import { THREE, OrbitControls, CSS2DRenderer, CSS2DObject, ViewHelper, Lut, uPlot } from "./vendor/live-libs.min.js";

const WINDOW_S = 10;            // plot time window
const PLOT_PERIOD_MS = 200;     // the plots redraw at most this often (5/s: a redraw of the four costs a browser without a GPU ~8 ms), the texts 4/s
const TEXT_PERIOD_MS = 250;
const KEEP_S = 12;              // samples kept for the plots
const ARROW_MM_PER_N = 10;      // force arrow scale
const MIN_COLOR_MAX_MM = 0.4;   // the colour scale never spans less
const VIRIDIS = ["#440154", "#482878", "#3e4989", "#31688e", "#26828e", "#1f9e89", "#35b779", "#6ece58", "#b5de2b", "#fde725"];
// the arms' colours in the sensor order, repeating beyond eight (softphantom.stream.foxglove.ARM_PALETTE)
const ARM_PALETTE = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22"];
const BIP_ARMS = ["front_zpos", "front_zneg", "back_xpos", "back_xneg"];  // a server that does not name them
const BIP_CAVITIES = ["urethra"];  // the internal cavities of a server that does not name them (not plotted)
const OTHER_CAVITY = "#8c8c8c";
const TRACKER_COLOR = "#ff6a00";
const XYZ_COLORS = ["#d62728", "#2ca02c", "#1f77b4", "#111111"];
const params = new URLSearchParams(location.search);

const S = {  // the page's state; window.__softphantomLive for tests and the curious
  geo: null, arms: BIP_ARMS, cavities: BIP_CAVITIES, latest: null, status: null, connected: false, ended: false, tracker: null, hasTracker: false,
  frames: 0, renders: 0, fps: 0, colorMax: MIN_COLOR_MAX_MM, surfaceMax: 0, lastSeq: -1,
  dirty: true, plotsDirty: false,
  cost: { parse: 0, frame: 0, surface: 0, render: 0, labels: 0, plots: 0 },  // ms spent so far, per part
};
window.__softphantomLive = S;

// ---------- colour map (viridis) ----------
const lut = new Lut();
lut.addColorMap("viridis", VIRIDIS.map((c, i) => [i / (VIRIDIS.length - 1), parseInt(c.slice(1), 16)]));
lut.setColorMap("viridis", 256);
for (const c of lut.lut) c.convertSRGBToLinear();  // Lut keeps the hex values as linear: make them the sRGB colours shown
document.getElementById("colorbar-ramp").style.background = `linear-gradient(to top, ${VIRIDIS.join(", ")})`;

function niceColorMax(x) {      // the colour range's top: steps fine enough that the range is well used
  if (!(x > 0)) return MIN_COLOR_MAX_MM;
  const p = Math.pow(10, Math.floor(Math.log10(x))), m = x / p;
  for (const s of [1, 1.2, 1.6, 2, 2.4, 3.2, 4, 6, 8, 10]) if (m <= s) return Math.max(s * p, MIN_COLOR_MAX_MM);  // quarters are round
  return 10 * p;
}
function drawColorbarTicks() {
  const el = document.getElementById("colorbar-ticks");
  el.textContent = "";
  for (let i = 0; i <= 4; i++) {
    const span = document.createElement("span");
    span.style.top = `${100 * i / 4}%`;
    span.textContent = (S.colorMax * (1 - i / 4)).toFixed(S.colorMax < 10 ? 2 : 1);
    el.appendChild(span);
  }
}

// ---------- the 3-D scene ----------
const host = document.getElementById("view3d");
const software = (() => {       // software GL (a headless browser, no GPU): no multisampling, it costs too much
  const gl = document.createElement("canvas").getContext("webgl2");
  const info = gl && gl.getExtension("WEBGL_debug_renderer_info");
  return !!info && /swiftshader|llvmpipe|software/i.test(gl.getParameter(info.UNMASKED_RENDERER_WEBGL));
})();
const renderer = new THREE.WebGLRenderer({ antialias: !software, alpha: false });
// resolution of the 3-D view: lowered while the browser cannot keep up (software GL), ?scale=X fixes it
const DPR = window.devicePixelRatio || 1;
S.scale = params.has("scale") ? Number(params.get("scale")) : 1;
renderer.setPixelRatio(DPR * S.scale);
renderer.setClearColor(0xffffff, 1);
renderer.autoClear = false;
host.appendChild(renderer.domElement);
const labels = new CSS2DRenderer();
Object.assign(labels.domElement.style, { position: "absolute", left: "0", top: "0", pointerEvents: "none" });
host.appendChild(labels.domElement);
const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(35, 1, 1, 5000);
camera.up.set(0, 0, 1);
scene.add(camera, new THREE.HemisphereLight(0xffffff, 0x8890a0, 1.6));
const headlight = new THREE.DirectionalLight(0xffffff, 1.6);
headlight.position.set(0.3, 0.4, 1);
camera.add(headlight);
const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;
controls.autoRotate = params.get("spin") === "1";  // continuous rendering: the benchmark's frames per second
controls.autoRotateSpeed = 4;
// the orientation gizmo in a canvas of its own, drawn only when the camera turns (not with every estimate)
const gizmoRenderer = new THREE.WebGLRenderer({ alpha: true, antialias: !software });
gizmoRenderer.setPixelRatio(DPR);
gizmoRenderer.setSize(128, 128);
gizmoRenderer.domElement.className = "gizmo";
host.appendChild(gizmoRenderer.domElement);
const gizmo = new ViewHelper(camera, gizmoRenderer.domElement);
const timer = new THREE.Timer();

const view = {};  // the scene's objects once the geometry is known
function decodePositions(b64) {
  if (Uint8Array.fromBase64) return new Float32Array(Uint8Array.fromBase64(b64).buffer);
  const bin = atob(b64), u8 = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) u8[i] = bin.charCodeAt(i);
  return new Float32Array(u8.buffer);
}
function poseMatrix(p) {        // R = Rz(yaw)·Rx(pitch)·Ry(roll) (three's intrinsic "ZXY"), then translate
  const r = Math.PI / 180;
  const e = new THREE.Euler(p.pitch_deg * r, p.roll_deg * r, p.yaw_deg * r, "ZXY");
  return new THREE.Matrix4().makeRotationFromEuler(e).setPosition(p.x_mm, p.y_mm, p.z_mm);
}
S.poseMatrix = (p) => poseMatrix(p).elements;  // for the test of the convention

function armColor(name) {        // an arm's colour (its cavity, its plot lines); another cavity grey
  const i = S.arms.indexOf(name);
  return i < 0 ? OTHER_CAVITY : ARM_PALETTE[i % ARM_PALETTE.length];
}

function setText(el, text) {     // a DOM write only when the text changes (each costs a layout)
  if (el.textContent !== text) el.textContent = text;
}
function label(text, cls) {
  const div = document.createElement("div");
  div.className = `label3d ${cls}`;
  div.textContent = text;
  return new CSS2DObject(div);
}

function buildScene(geo) {
  const rest = new Float32Array(geo.nodes_mm.flat());
  const position = new THREE.BufferAttribute(rest.slice(), 3);
  position.setUsage(THREE.DynamicDrawUsage);
  const color = new THREE.BufferAttribute(new Float32Array(rest.length), 3);
  color.setUsage(THREE.DynamicDrawUsage);
  const surface = new THREE.BufferGeometry();
  surface.setAttribute("position", position);
  surface.setAttribute("color", color);
  surface.setIndex(geo.faces.flat());
  surface.computeVertexNormals();
  // see-through (the cavities and targets inside show): the front faces only, blended
  const front = new THREE.Mesh(surface, new THREE.MeshLambertMaterial({ vertexColors: true, transparent: true, opacity: 0.55, depthWrite: false }));
  front.renderOrder = 1;
  front.frustumCulled = false;  // the nodes move: no stale bounding sphere
  scene.add(front);
  const outerNodes = new Uint32Array([...new Set(geo.faces.flat())]);
  // cavities: the same moving nodes, their own triangles, solid, each in its arm's plot colour; one
  // mesh (one draw): their nodes are not on the outer surface, so their colours sit in the same
  // attribute. One side only (half the rasterizing): a closed wall shows the same either way round.
  const legend = document.getElementById("legend");
  const cavIndex = [], cavities = [];
  for (const [name, faces] of Object.entries(geo.cavities || {})) {
    const col = armColor(name), lin = new THREE.Color(col);
    for (const i of faces.flat()) { cavIndex.push(i); color.setXYZ(i, lin.r, lin.g, lin.b); }
    const row = document.createElement("div"), sw = document.createElement("i");
    sw.style.background = col;
    row.append(sw, name);
    legend.appendChild(row);
  }
  if (cavIndex.length) {
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", position);
    g.setAttribute("color", color);
    g.setIndex(cavIndex);
    const m = new THREE.Mesh(g, new THREE.MeshLambertMaterial({ vertexColors: true, flatShading: true }));
    m.frustumCulled = false;
    scene.add(m);
    cavities.push(m);
  }
  // the tracker's pose: the rest surface moved rigidly by it, drawn as an orange wire cage
  const ghost = new THREE.Mesh(new THREE.BufferGeometry().setAttribute("position", new THREE.BufferAttribute(rest, 3)).setIndex(geo.faces.flat()),
    new THREE.MeshBasicMaterial({ color: TRACKER_COLOR, wireframe: true, transparent: true, opacity: 0.45 }));
  ghost.matrixAutoUpdate = false;
  ghost.visible = false;
  const trackerAxes = new THREE.AxesHelper(14);
  trackerAxes.matrixAutoUpdate = false;
  trackerAxes.visible = false;
  const poseAxes = new THREE.AxesHelper(14);  // the estimated pose of the marker body
  poseAxes.matrixAutoUpdate = false;
  scene.add(ghost, trackerAxes, poseAxes);
  // targets: rest (black wire sphere) → now (magenta sphere), a line between, a label with the
  // shift's length; all the rest spheres one draw, the moved ones one, the lines one
  const targets = {}, names = Object.keys(geo.targets_mm || {}), nt = names.length;
  const rings = new THREE.InstancedMesh(new THREE.SphereGeometry(1.3, 12, 8),
    new THREE.MeshBasicMaterial({ color: 0x222222, wireframe: true }), Math.max(nt, 1));
  const dots = new THREE.InstancedMesh(new THREE.SphereGeometry(1.4, 16, 12),
    new THREE.MeshLambertMaterial({ color: 0xff2d95 }), Math.max(nt, 1));
  const links = new THREE.LineSegments(new THREE.BufferGeometry().setAttribute("position",
    new THREE.BufferAttribute(new Float32Array(6 * Math.max(nt, 1)), 3)), new THREE.LineBasicMaterial({ color: 0xff2d95 }));
  rings.count = dots.count = nt;
  links.geometry.setDrawRange(0, 2 * nt);
  names.forEach((name, i) => {
    const r = new THREE.Vector3(...geo.targets_mm[name]), at = new THREE.Matrix4().makeTranslation(r);
    rings.setMatrixAt(i, at);
    dots.setMatrixAt(i, at);
    links.geometry.attributes.position.setXYZ(2 * i, r.x, r.y, r.z);
    links.geometry.attributes.position.setXYZ(2 * i + 1, r.x, r.y, r.z);
    const anchor = new THREE.Object3D(), text = label(name, "target");  // the label follows the moved target
    anchor.position.copy(r);
    anchor.add(text);
    text.position.set(2.5, 0, 2.5);
    scene.add(anchor);
    targets[name] = { rest: r, i, anchor, text };
  });
  for (const o of [rings, dots, links]) o.frustumCulled = false;  // they move
  scene.add(rings, dots, links);
  // the contact point (deformed p_ext) and the force arrow ending on it
  const contact = new THREE.Mesh(new THREE.SphereGeometry(1.8, 16, 12), new THREE.MeshLambertMaterial({ color: 0xe0201b }));
  const arrow = new THREE.ArrowHelper(new THREE.Vector3(0, 1, 0), new THREE.Vector3(), 20, 0xe0201b, 6, 3.5);
  const forceText = label("", "force");
  arrow.add(forceText);
  arrow.visible = false;
  scene.add(contact, arrow);
  S.surfaceTriangles = geo.faces.length;
  S.cavityTriangles = Object.values(geo.cavities || {}).reduce((n, f) => n + f.length, 0);
  Object.assign(view, { rest, position, color, surface, front, outerNodes, cavities, ghost, trackerAxes, poseAxes,
    targets, dots, links, contact, arrow, forceText, pext: geo.p_ext_node });
  // camera: the whole bulb, from the front-left and above
  surface.computeBoundingSphere();
  const { center, radius } = surface.boundingSphere;  // at rest
  controls.target.copy(center);
  camera.position.copy(center).add(new THREE.Vector3(-1.1, -1.6, 0.9).normalize().multiplyScalar(radius * 4.2));
  camera.near = radius * 0.05; camera.far = radius * 50;
  camera.updateProjectionMatrix();
  controls.saveState();
  gizmo.center = controls.target;
  updateSurface(null);
}

function updateSurface(pos) {
  const v = view, n = v.rest.length / 3, p = v.position.array, c = v.color.array;
  if (pos) p.set(pos);
  let maxMag = 0;
  const mag = v.mag || (v.mag = new Float32Array(n));
  for (const i of v.outerNodes) {
    const m = Math.hypot(p[3 * i] - v.rest[3 * i], p[3 * i + 1] - v.rest[3 * i + 1], p[3 * i + 2] - v.rest[3 * i + 2]);
    mag[i] = m;
    if (m > maxMag) maxMag = m;
  }
  // colour range, a round number: grows at once, shrinks once it has been too wide for 2 s (no flicker)
  const want = niceColorMax(maxMag), now = performance.now(), before = S.colorMax;
  if (want >= S.colorMax) { S.colorMax = want; S.shrink = null; }
  else if (!S.shrink) S.shrink = { since: now, to: want };
  else if (now - S.shrink.since > 2000) { S.colorMax = Math.max(S.shrink.to, want); S.shrink = null; }
  else S.shrink.to = Math.max(S.shrink.to, want);
  if (S.colorMax !== before || !S.ticksDrawn) { drawColorbarTicks(); S.ticksDrawn = true; }
  lut.setMax(S.colorMax);
  for (const i of v.outerNodes) {
    const col = lut.getColor(mag[i]);
    c[3 * i] = col.r; c[3 * i + 1] = col.g; c[3 * i + 2] = col.b;
  }
  S.surfaceMax = maxMag;
  v.position.needsUpdate = true;
  v.color.needsUpdate = true;
  v.surface.computeVertexNormals();
  placeContact();
}

function placeContact() {
  const v = view, p = v.position.array, i = v.pext, m = S.latest;
  const tip = new THREE.Vector3(p[3 * i], p[3 * i + 1], p[3 * i + 2]);
  v.contact.position.copy(tip);
  const F = m ? new THREE.Vector3(m.force_x_N, m.force_y_N, m.force_z_N) : null;
  const Fn = F ? F.length() : 0;
  v.arrow.visible = Fn > 1e-3;
  if (v.arrow.visible) {
    const L = Math.min(60, Math.max(12, ARROW_MM_PER_N * Fn)), dir = F.clone().divideScalar(Fn);
    v.arrow.position.copy(tip).addScaledVector(dir, -L);
    v.arrow.setDirection(dir);
    v.arrow.setLength(L, Math.min(8, 0.35 * L), 4);
  }
  v.forceN = Fn;
}

function updateOverlay() {     // targets, pose, tracker, force: from the latest estimate
  const v = view, m = S.latest;
  if (!v.surface || !m) return;
  const ends = v.links.geometry.attributes.position, at = new THREE.Matrix4();
  for (const [name, t] of Object.entries(v.targets)) {
    const d = [m[`${name}_dx_mm`] || 0, m[`${name}_dy_mm`] || 0, m[`${name}_dz_mm`] || 0], p = t.anchor.position;
    p.set(t.rest.x + d[0], t.rest.y + d[1], t.rest.z + d[2]);
    v.dots.setMatrixAt(t.i, at.makeTranslation(p));
    ends.setXYZ(2 * t.i + 1, p.x, p.y, p.z);
    t.shift = Math.hypot(...d);
  }
  v.dots.instanceMatrix.needsUpdate = true;
  ends.needsUpdate = true;
  v.poseAxes.matrix.copy(poseMatrix(m));
  const tr = S.tracker;
  v.ghost.visible = v.trackerAxes.visible = !!tr;
  if (tr) { v.ghost.matrix.copy(poseMatrix(tr)); v.trackerAxes.matrix.copy(v.ghost.matrix); }
  placeContact();
}

function resize() {
  const w = host.clientWidth, h = host.clientHeight;
  renderer.setSize(w, h);
  labels.setSize(w, h);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
  for (const p of plots) p.u.setSize(plotSize(p.el));
  S.dirty = S.gizmoDirty = true;
}

const renderTimes = [], ticks = [];
function adaptScale(now) {      // once a second: fewer pixels while frames queue up, more when they flow
  if (params.has("scale") || now - (S.scaledAt || 0) < 1000) return;
  S.scaledAt = now;
  // frames come slower than the display's 60/s and most of them render: the 3-D view is the bottleneck
  const rate = ticks.length, busy = rate < 45 && renderTimes.length > 0.6 * rate;
  const next = busy ? Math.max(0.4, S.scale * 0.8) : rate >= 57 ? Math.min(1, S.scale * 1.1) : S.scale;
  if (next !== S.scale) {
    S.scale = next;
    renderer.setPixelRatio(DPR * S.scale);
    renderer.setSize(host.clientWidth, host.clientHeight);
  }
}
function loop(now) {
  requestAnimationFrame(loop);
  timer.update(now);
  const dt = timer.getDelta();
  ticks.push(now);
  while (ticks[0] < now - 1000) ticks.shift();
  adaptScale(now);
  const moved = controls.update(dt);
  const turning = gizmo.animating;  // its last step ends the animation: draw that one too
  if (turning) { gizmo.update(dt); S.dirty = true; }
  S.moving = moved || turning;  // the camera still moving (orbit damping, the gizmo's turn)
  const draw = S.dirty || moved, since = now - (S.plottedAt || 0);
  // the plots redraw with a 3-D frame (one compositor frame for both), or alone if none comes
  if (S.plotsDirty && since >= PLOT_PERIOD_MS && (draw || since >= 2 * PLOT_PERIOD_MS)) {
    updatePlots(); S.plotsDirty = false; S.plottedAt = now;
    S.cost.plots += performance.now() - now;
  }
  if (S.textDirty && (S.textNow || now - (S.textAt || 0) >= TEXT_PERIOD_MS)) {
    drawTexts(); S.textAt = now; S.textNow = false;
  }
  if (!draw) return;
  const t0 = performance.now();
  renderer.clear();
  renderer.render(scene, camera);
  S.triangles = renderer.info.render.triangles;
  if (moved || turning || S.gizmoDirty !== false) { gizmo.render(gizmoRenderer); S.gizmoDirty = false; }
  const t1 = performance.now();
  labels.render(scene, camera);
  S.cost.render += t1 - t0;
  S.cost.labels += performance.now() - t1;
  S.dirty = false;
  S.renders++;
  renderTimes.push(now);
  while (renderTimes[0] < now - 1000) renderTimes.shift();
  S.fps = renderTimes.length;
}

// ---------- plots ----------
function trackerOf(k) { return (m) => (m.tracker ? m.tracker[k] : null); }
const isBip = (cavities) => cavities.length === 1 && cavities[0] === BIP_CAVITIES[0];
const plotsOf = (arms, cavities) => [  // the cavity plot: one measured (solid) and one predicted (dashed) line per arm
  ["plot-force", [["Fx", "force_x_N"], ["Fy", "force_y_N"], ["Fz", "force_z_N"],
    ["|F|", (m) => (m.force_x_N == null ? null : Math.hypot(m.force_x_N, m.force_y_N, m.force_z_N))]]],
  ["plot-position", [["x", "x_mm"], ["y", "y_mm"], ["z", "z_mm"],
    ...["x_mm", "y_mm", "z_mm"].map((k, i) => [`${k[0]} trk`, trackerOf(k), XYZ_COLORS[i], true])]],
  ["plot-rotation", [["yaw", "yaw_deg"], ["pitch", "pitch_deg"], ["roll", "roll_deg"],
    ...["yaw_deg", "pitch_deg", "roll_deg"].map((k, i) => [`${k.split("_")[0]} trk`, trackerOf(k), XYZ_COLORS[i], true])]],
  ["plot-cavities", arms.flatMap((a) => [[a, `dVmeas_${a}_mm3`, armColor(a)],
    [`${a} pred`, `dVpred_${a}_mm3`, armColor(a), true]])],
  // the internal cavities' measured pressures, one line each (the BIP's urethra alone: no plot)
  ...(cavities.length && !isBip(cavities) ? [["plot-pressures", cavities.map((c) => [c, `p_${c}_kPa`])]] : []),
];
const T = [];                   // sample times, s
const plots = [];
function plotSize(el) { return { width: el.clientWidth, height: Math.max(el.clientHeight - 44, 60) }; }
function buildPlots() {
  S.series = {};  // plot id → its series' labels (for tests and the curious)
  const all = plotsOf(S.arms, S.cavities);
  if (all.length > 4 && !document.getElementById("plot-pressures")) {
    const box = document.getElementById("plots");
    const el = document.createElement("div");
    el.id = "plot-pressures";
    el.className = "plot";
    el.dataset.title = "Internal cavities' pressure (kPa)";
    box.appendChild(el);
    box.style.gridTemplateRows = `repeat(${all.length}, 1fr)`;
  }
  for (const [id, series] of all) {
    S.series[id] = series.map(([name]) => name);
    const el = document.getElementById(id);
    const get = series.map(([, k]) => (typeof k === "function" ? k : (m) => m[k]));
    const cols = series.map(() => []);
    const opts = {
      title: el.dataset.title, ...plotSize(el),
      scales: { x: { time: false, range: () => (T.length ? [T[T.length - 1] - WINDOW_S, T[T.length - 1]] : [0, WINDOW_S]) } },
      axes: [{ label: "t s", size: 36 }, { size: 48 }],
      cursor: { drag: { x: false, y: false } },
      series: [{ label: "t s", value: (u, v) => (v == null ? "–" : v.toFixed(2)) },
        ...series.map(([name, , col, dashed], i) => ({
          label: name, stroke: col || XYZ_COLORS[i % XYZ_COLORS.length], width: 1.6, dash: dashed ? [6, 4] : undefined,
          show: !name.endsWith(" trk"), value: (u, v) => (v == null ? "–" : v.toFixed(2)),
        }))],
    };
    const u = new uPlot(opts, [T, ...cols], el);
    plots.push({ el, u, get, cols, series });
  }
}
function addSamples(samples) {
  for (const m of samples) {
    if (m.seq <= S.lastSeq) continue;
    S.lastSeq = m.seq;
    T.push(m.t_s);
    for (const p of plots) p.get.forEach((g, i) => { const v = g(m); p.cols[i].push(v == null || !isFinite(v) ? null : v); });
    if (m.tracker) S.tracker = m.tracker;
    if (m.force_x_N != null) S.latest = m;  // a link event's marker has no numbers: keep the last estimate
  }
  const t0 = T.length ? T[T.length - 1] - KEEP_S : 0;
  let k = 0;
  while (k < T.length && T[k] < t0) k++;
  if (k > 0) { T.splice(0, k); for (const p of plots) for (const c of p.cols) c.splice(0, k); }
  if (S.tracker && !S.hasTracker) {  // show the tracker's series once it is there
    S.hasTracker = true;
    for (const p of plots) p.series.forEach(([name], i) => { if (name.endsWith(" trk")) p.u.setSeries(i + 1, { show: true }); });
  }
}
function updatePlots() {
  for (const p of plots) {
    p.u.setData([T, ...p.cols]);
    if (T.length && p.u.cursor.left < 0) p.u.setLegend({ idx: T.length - 1 });  // the latest values
  }
}

// ---------- status ----------
function fmt(v, n, unit = "") { return v == null ? "–" : `${Number(v).toFixed(n)}${unit}`; }
function badge(id, level, text) {
  const el = document.getElementById(id);
  el.dataset.level = level;
  setText(el, text);
  el.title = text;
}
function drawStatus() {
  const st = S.status;
  const ended = S.ended || (!S.connected && st && st.finished);
  badge("badge-server", S.connected ? "ok" : ended ? "wait" : "bad",
    S.connected ? "server: live" : ended ? "server: ended" : "server: reconnecting");
  if (!st) return;
  const link = st.link, detail = st.link_detail || "";
  const linkLevel = { ok: "ok", outage: "bad", stalled: "bad", error: "bad", waiting: "wait", ended: "wait" }[link] || "warn";
  badge("badge-link", linkLevel, link === "outage" ? `LINK OUTAGE: ${detail}` : link === "stalled" ? `link stalled: ${detail}`
    : link === "error" ? `error: ${detail}` : `link: ${link}`);
  const env = st.in_envelope;
  badge("badge-envelope", env == null ? "wait" : env ? "ok" : "warn", env == null ? "envelope: –" : env ? "in envelope" : "OUT OF ENVELOPE");
  const banner = document.getElementById("banner");
  const bad = linkLevel === "bad", warn = env === false;
  banner.hidden = !(bad || warn);
  banner.dataset.level = bad ? "bad" : warn ? "warn" : "none";
  setText(banner, link === "outage" ? `LINK OUTAGE — ${detail} — showing the last estimate`
    : link === "stalled" ? `NO ESTIMATE — ${detail}` : link === "error" ? `ERROR — ${detail}`
    : warn ? "OUT OF ENVELOPE — the estimate is clamped to the loads the model covers" : "");
  const s = st.stream || {}, m = S.latest;
  const parts = [
    `rate ${fmt(st.rate_Hz, 1, " Hz")}`, `step ${fmt(st.step_ms, 2, " ms")} (p99 ${fmt(st.step_p99_ms, 2, " ms")})`,
    `skipped ${st.skipped_total} · view drop ${st.view_dropped}`,
    s.enabled ? `stream ${s.endpoint.replace("tcp://", "")} ${s.subscribers} sub` : "stream off",
    `QP ${st.qp_status || "–"}`, `cond(W) ${fmt(st.cond_W, 1)}`, `t ${m ? fmt(m.t_s, 2, " s") : "–"}`, `#${st.estimates}`,
  ];
  if (st.last_event) parts.push(`last event ${st.last_event}`);
  if (st.recording && st.recording.enabled) parts.push(`rec ${st.recording.messages} msg`);
  setText(document.getElementById("status"), parts.join(" │ "));
}
function drawTargets() {       // the table's cells are made once, then only their text changes
  const tb = document.querySelector("#targets tbody"), m = S.latest;
  if (!S.geo || !m) return;
  const names = Object.keys(S.geo.targets_mm || {});
  if (tb.rows.length !== names.length) {
    tb.textContent = "";
    for (const name of names) {
      const tr = tb.insertRow();
      for (let k = 0; k < 5; k++) tr.insertCell();
      tr.cells[0].textContent = name;
    }
  }
  names.forEach((name, r) => {
    const d = ["dx", "dy", "dz"].map((k) => m[`${name}_${k}_mm`] || 0), cells = tb.rows[r].cells;
    [...d, Math.hypot(...d)].forEach((x, k) => setText(cells[k + 1], x.toFixed(2)));
  });
}
// the numbers in the view, the status and the table: at most 4 times a second (a number changing
// 30 times a second cannot be read, and each change costs a layout and a repaint), at once when the
// link's state changes
function drawTexts() {
  const v = view;
  if (v.surface) {
    setText(document.getElementById("surface-max"), `max |u| ${S.surfaceMax.toFixed(2)} mm`);
    if (v.arrow.visible) setText(v.forceText.element, `F ${v.forceN.toFixed(2)} N`);
    for (const [name, t] of Object.entries(v.targets)) if (t.shift != null) setText(t.text.element, `${name} ${t.shift.toFixed(2)} mm`);
  }
  drawStatus();
  drawTargets();
  S.textDirty = false;
}

function applyFrame(f) {
  if (f.samples && f.samples.length) {
    if (S.resync && f.samples[f.samples.length - 1].seq < S.lastSeq) {  // a new session behind the same address
      S.lastSeq = -1; T.length = 0;
      for (const p of plots) for (const c of p.cols) c.length = 0;
    }
    addSamples(f.samples);
    S.plotsDirty = true;
  }
  S.resync = false;
  if (f.surface_mm_f32_b64 && view.surface) {
    const t0 = performance.now(), p = decodePositions(f.surface_mm_f32_b64);
    if (p.length === view.rest.length) updateSurface(p);
    S.cost.surface += performance.now() - t0;
  }
  if (f.status) S.status = f.status;
  updateOverlay();
  S.textDirty = true;
  if (f.status && f.status.link !== S.shownLink) { S.textNow = true; S.shownLink = f.status.link; }
  S.frames++;
  S.dirty = true;
}

// ---------- start ----------
async function init() {
  if (params.has("token")) {  // the cookie carries it from now on: keep it out of the address bar
    params.delete("token");
    history.replaceState(null, "", location.pathname + (params.toString() ? `?${params}` : ""));
  }
  document.getElementById("xray").addEventListener("change", (e) => {
    if (!view.front) return;
    const m = view.front.material;
    m.opacity = e.target.checked ? 0.55 : 1;
    m.transparent = e.target.checked;
    m.depthWrite = !e.target.checked;
    m.needsUpdate = true;
    S.dirty = true;
  });
  renderer.domElement.addEventListener("dblclick", () => { controls.reset(); S.dirty = S.gizmoDirty = true; });
  gizmoRenderer.domElement.addEventListener("pointerup", (e) => { if (gizmo.handleClick(e)) S.dirty = true; });
  let st = null;
  try {
    const g = await fetch("/api/geometry");
    if (g.ok) S.geo = await g.json();
    st = await (await fetch("/api/state")).json();  // the history comes with the first event
  } catch (err) {
    document.getElementById("status").textContent = `cannot reach the live server: ${err}`;
  }
  // the phantom's arms (the server names them; the geometry too): the cavities' colours, the plot's lines
  const arms = (st && st.arms) || (S.geo && S.geo.arms);
  if (Array.isArray(arms) && arms.length) S.arms = arms.map(String);
  if (st && Array.isArray(st.cavities)) S.cavities = st.cavities.map(String);
  buildPlots();
  const sizes = new ResizeObserver(resize);
  for (const el of [host, ...document.querySelectorAll(".plot")]) sizes.observe(el);
  if (S.geo) {
    buildScene(S.geo);
    if (S.geo.surface_shows) {  // a replay without the estimator's field: what the surface is instead
      const el = document.getElementById("surface-shows");
      el.textContent = `surface: ${S.geo.surface_shows}`;
      el.hidden = false;
    }
    if (params.get("xray") === "0") {
      const box = document.getElementById("xray");
      box.checked = false;
      box.dispatchEvent(new Event("change"));
    }
  } else if (st) {
    document.getElementById("surface-max").textContent = "no geometry from this source: plots only";
  }
  if (st) applyFrame({ status: st.status, surface_mm_f32_b64: st.surface_mm_f32_b64 });
  resize();
  requestAnimationFrame(loop);
  const es = new EventSource("/api/events");
  es.addEventListener("open", () => { S.connected = true; S.resync = true; drawStatus(); });
  es.addEventListener("error", () => { S.connected = false; drawStatus(); });
  // the session ended (the source ran out, or the server stops): the last frame came before this;
  // nothing to reconnect to
  es.addEventListener("end", () => { es.close(); S.connected = false; S.ended = true; S.textNow = true; drawStatus(); });
  // ?frames=N: stop listening after N frames (a fixed snapshot)
  const stopAfter = Number(params.get("frames") || 0);
  es.addEventListener("frame", (ev) => {
    const t0 = performance.now(), f = JSON.parse(ev.data), t1 = performance.now();
    applyFrame(f);
    S.cost.parse += t1 - t0;
    S.cost.frame += performance.now() - t1;
    if (stopAfter && S.frames >= stopAfter) { es.close(); S.connected = false; drawStatus(); }
  });
}
init();
