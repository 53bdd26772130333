// softphantom live view: a hand-written canvas renderer (no library, nothing fetched from outside).
// Data: GET /api/geometry (rest surface, mm), GET /api/state, then Server-Sent Events /api/events.
"use strict";

const WINDOW_S = 10;            // plot time window
const MAX_SAMPLES = 6000;       // kept for the plots
const ARROW_MM_PER_N = 10;      // force arrow scale
const S = {
  geo: null, rest: null, pos: null, faces: null, samples: [], latest: null, status: null,
  view: { az: -2.2, el: 0.42, zoom: 1.0 }, colorMax: 1.0, frames: 0, connected: false,
};
window.__softphantomLive = S;   // for tests and the curious

// ---------- colours ----------
const VIRIDIS = [[68, 1, 84], [72, 40, 120], [62, 74, 137], [49, 104, 142], [38, 130, 142],
  [31, 158, 137], [53, 183, 121], [109, 205, 89], [180, 222, 44], [253, 231, 37]];
function cmap(v) {               // v in [0, 1]
  v = Math.min(1, Math.max(0, v)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(v)), f = v - i, a = VIRIDIS[i], b = VIRIDIS[i + 1];
  return [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2])];
}
const SERIES_COLORS = ["#d62728", "#2ca02c", "#1f77b4", "#111111"];
const ARM_COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd"];

// ---------- data ----------
function decodePositions(b64) {
  const bin = atob(b64), buf = new ArrayBuffer(bin.length), u8 = new Uint8Array(buf);
  for (let i = 0; i < bin.length; i++) u8[i] = bin.charCodeAt(i);
  return new Float32Array(buf);
}
function niceMax(x) {
  if (!(x > 0)) return 1;
  const p = Math.pow(10, Math.floor(Math.log10(x))), m = x / p;
  return (m <= 1 ? 1 : m <= 2 ? 2 : m <= 5 ? 5 : 10) * p;
}
function niceColorMax(x) {       // finer steps than niceMax so the colour range is well used
  if (!(x > 0)) return 1;
  const p = Math.pow(10, Math.floor(Math.log10(x))), m = x / p;
  for (const s of [1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8, 10]) if (m <= s) return s * p;
  return 10 * p;
}
function applyFrame(f) {
  if (f.samples && f.samples.length) {
    const lastSeq = S.samples.length ? S.samples[S.samples.length - 1].seq : -1;
    for (const m of f.samples) if (m.seq > lastSeq) S.samples.push(m);
    if (S.samples.length > MAX_SAMPLES) S.samples.splice(0, S.samples.length - MAX_SAMPLES);
    if (S.samples.length) S.latest = S.samples[S.samples.length - 1];
    if (!S.tracker && f.samples.some((m) => m.tracker)) S.tracker = true;
  }
  if (f.surface_mm_f32_b64 && S.rest) {
    const p = decodePositions(f.surface_mm_f32_b64);
    if (p.length === S.rest.length) S.pos = p;
  }
  if (f.status) S.status = f.status;
  S.frames++;
  drawAll();
}

// ---------- 3-D view ----------
function project(view, w, h, scale) {
  const ca = Math.cos(view.az), sa = Math.sin(view.az), ce = Math.cos(view.el), se = Math.sin(view.el);
  const f = 400;  // mm, perspective distance
  return (x, y, z) => {
    const x1 = ca * x - sa * y, y1 = sa * x + ca * y;
    const depth = ce * y1 - se * z, sy = ce * z + se * y1;
    const k = scale * view.zoom * f / (f + depth);
    return [w / 2 + k * x1, h / 2 - k * sy, depth];
  };
}
function fitCanvas(c) {
  const r = c.getBoundingClientRect(), d = window.devicePixelRatio || 1;
  const W = Math.max(50, Math.round(r.width * d)), H = Math.max(50, Math.round(r.height * d));
  if (c.width !== W || c.height !== H) { c.width = W; c.height = H; }
  return d;
}
function drawArrow(ctx, a, b, color, width, head) {
  const dx = b[0] - a[0], dy = b[1] - a[1], L = Math.hypot(dx, dy) || 1, ux = dx / L, uy = dy / L;
  ctx.strokeStyle = color; ctx.fillStyle = color; ctx.lineWidth = width;
  ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0] - ux * head * 0.8, b[1] - uy * head * 0.8); ctx.stroke();
  ctx.beginPath(); ctx.moveTo(b[0], b[1]);
  ctx.lineTo(b[0] - ux * head - uy * head * 0.45, b[1] - uy * head + ux * head * 0.45);
  ctx.lineTo(b[0] - ux * head + uy * head * 0.45, b[1] - uy * head - ux * head * 0.45);
  ctx.closePath(); ctx.fill();
}
function label(ctx, text, x, y, color, bg) {
  ctx.font = `${13 * S.dpr}px "DejaVu Sans", sans-serif`;
  const w = ctx.measureText(text).width, p = 3 * S.dpr, h = 16 * S.dpr;
  ctx.fillStyle = bg || "rgba(255,255,255,0.85)"; ctx.fillRect(x - p, y - h + p, w + 2 * p, h + p);
  ctx.fillStyle = color; ctx.fillText(text, x, y);
}
function draw3d() {
  const c = document.getElementById("view3d"), ctx = c.getContext("2d");
  S.dpr = fitCanvas(c);
  const W = c.width, H = c.height, d = S.dpr;
  ctx.clearRect(0, 0, W, H);
  if (!S.geo) {
    label(ctx, "no geometry from this source: plots only", 20 * d, 40 * d, "#444");
    return;
  }
  const rest = S.rest, pos = S.pos || rest, faces = S.faces, n = rest.length / 3;
  const P = project(S.view, W, H, 0.36 * Math.min(W, H) / S.extent);
  const sx = new Float32Array(n), sy = new Float32Array(n), sz = new Float32Array(n), mag = new Float32Array(n);
  let maxMag = 0;
  for (let i = 0; i < n; i++) {
    const q = P(pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]);
    sx[i] = q[0]; sy[i] = q[1]; sz[i] = q[2];
    const m = Math.hypot(pos[3 * i] - rest[3 * i], pos[3 * i + 1] - rest[3 * i + 1], pos[3 * i + 2] - rest[3 * i + 2]);
    mag[i] = m; if (m > maxMag) maxMag = m;
  }
  // colour range: grows at once, shrinks slowly (no flicker)
  const want = Math.max(niceColorMax(maxMag), 0.5);
  S.colorMax = want >= S.colorMax ? want : Math.max(want, S.colorMax * 0.99);
  const nf = faces.length / 3, order = [], depth = new Float32Array(nf);
  for (let k = 0; k < nf; k++) {
    const a = faces[3 * k], b = faces[3 * k + 1], e = faces[3 * k + 2];
    const cross = (sx[b] - sx[a]) * (sy[e] - sy[a]) - (sy[b] - sy[a]) * (sx[e] - sx[a]);
    if (cross > 0) continue;  // back face (outward normals, y down on screen)
    depth[k] = sz[a] + sz[b] + sz[e]; order.push(k);
  }
  order.sort((p, q) => depth[q] - depth[p]);
  // ground shadow of the rest outline for reference: draw the rest silhouette faintly
  for (const k of order) {
    const a = faces[3 * k], b = faces[3 * k + 1], e = faces[3 * k + 2];
    // lambert shading from the 3-D normal
    const ax = pos[3 * a], ay = pos[3 * a + 1], az = pos[3 * a + 2];
    const ux = pos[3 * b] - ax, uy = pos[3 * b + 1] - ay, uz = pos[3 * b + 2] - az;
    const vx = pos[3 * e] - ax, vy = pos[3 * e + 1] - ay, vz = pos[3 * e + 2] - az;
    let nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
    const nl = Math.hypot(nx, ny, nz) || 1; nx /= nl; ny /= nl; nz /= nl;
    const lit = 0.55 + 0.45 * Math.abs(0.3 * nx - 0.5 * ny + 0.8 * nz);
    const col = cmap((mag[a] + mag[b] + mag[e]) / (3 * S.colorMax));
    ctx.fillStyle = `rgba(${col[0] * lit | 0},${col[1] * lit | 0},${col[2] * lit | 0},0.80)`;
    ctx.strokeStyle = ctx.fillStyle;
    ctx.lineWidth = 0.6;
    ctx.beginPath(); ctx.moveTo(sx[a], sy[a]); ctx.lineTo(sx[b], sy[b]); ctx.lineTo(sx[e], sy[e]); ctx.closePath();
    ctx.fill(); ctx.stroke();
  }
  // targets: rest (ring) → now (dot)
  const m = S.latest;
  for (const [name, r] of Object.entries(S.geo.targets_mm || {})) {
    const dx = m ? (m[name + "_dx_mm"] || 0) : 0, dy = m ? (m[name + "_dy_mm"] || 0) : 0, dz = m ? (m[name + "_dz_mm"] || 0) : 0;
    const a = P(r[0], r[1], r[2]), b = P(r[0] + dx, r[1] + dy, r[2] + dz);
    ctx.strokeStyle = "#fff"; ctx.lineWidth = 2 * d;
    ctx.beginPath(); ctx.arc(a[0], a[1], 5 * d, 0, 2 * Math.PI); ctx.stroke();
    ctx.strokeStyle = "#222"; ctx.lineWidth = 1 * d; ctx.stroke();
    ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.strokeStyle = "#ff2d95"; ctx.lineWidth = 2 * d; ctx.stroke();
    ctx.beginPath(); ctx.arc(b[0], b[1], 4.5 * d, 0, 2 * Math.PI); ctx.fillStyle = "#ff2d95"; ctx.fill();
    label(ctx, `${name} ${Math.hypot(dx, dy, dz).toFixed(2)} mm`, b[0] + 8 * d, b[1] - 6 * d, "#b0006a");
  }
  // force arrow ending at p_ext (deformed)
  if (m && m.force_x_N != null) {
    const F = [m.force_x_N, m.force_y_N, m.force_z_N], Fn = Math.hypot(F[0], F[1], F[2]);
    const pe = S.geo.p_ext_node, tip = [pos[3 * pe], pos[3 * pe + 1], pos[3 * pe + 2]];
    if (Fn > 1e-3) {
      const L = Math.min(60, Math.max(12, ARROW_MM_PER_N * Fn));
      const tail = [tip[0] - L * F[0] / Fn, tip[1] - L * F[1] / Fn, tip[2] - L * F[2] / Fn];
      const a = P(tail[0], tail[1], tail[2]), b = P(tip[0], tip[1], tip[2]);
      drawArrow(ctx, a, b, "#e0201b", 4 * d, 14 * d);
      label(ctx, `F ${Fn.toFixed(2)} N`, a[0] - 30 * d, a[1] - 10 * d, "#c0100b");
    } else {
      const b = P(tip[0], tip[1], tip[2]);
      ctx.fillStyle = "#e0201b"; ctx.beginPath(); ctx.arc(b[0], b[1], 4 * d, 0, 2 * Math.PI); ctx.fill();
    }
  }
  // axes triad (bottom left) and colour bar (right)
  const o = [48 * d, H - 48 * d], Q = project(S.view, 0, 0, 1);
  [["x", [1, 0, 0], "#d62728"], ["y (needle)", [0, 1, 0], "#2ca02c"], ["z", [0, 0, 1], "#1f77b4"]].forEach(([t, v, col]) => {
    const q = Q(28 * v[0], 28 * v[1], 28 * v[2]), z = Q(0, 0, 0);
    const e = [o[0] + (q[0] - z[0]) * d, o[1] + (q[1] - z[1]) * d];
    drawArrow(ctx, o, e, col, 2 * d, 7 * d); label(ctx, t, e[0] + 3 * d, e[1] - 3 * d, col, "rgba(255,255,255,0)");
  });
  const bx = W - 34 * d, by = 40 * d, bh = Math.min(220 * d, H - 110 * d), bw = 14 * d;
  for (let i = 0; i < bh; i++) { const col = cmap(1 - i / bh); ctx.fillStyle = `rgb(${col[0] | 0},${col[1] | 0},${col[2] | 0})`; ctx.fillRect(bx, by + i, bw, 1.5); }
  ctx.strokeStyle = "#444"; ctx.lineWidth = 1; ctx.strokeRect(bx, by, bw, bh);
  ctx.font = `${12 * d}px "DejaVu Sans", sans-serif`; ctx.fillStyle = "#222"; ctx.textAlign = "right";
  for (let i = 0; i <= 4; i++) ctx.fillText((S.colorMax * (1 - i / 4)).toFixed(S.colorMax < 10 ? 2 : 1), bx - 4 * d, by + bh * i / 4 + 4 * d);
  ctx.fillText("|u| mm", bx + bw, by - 10 * d); ctx.textAlign = "left";
  label(ctx, `surface max |u| ${maxMag.toFixed(2)} mm`, 14 * d, 22 * d, "#222");
}

// ---------- plots ----------
// the tracker (a NatNet source given to `live --tracker`): dashed, in the colour of its estimate DoF
function trackerSeries(keys) {
  return keys.map((k, i) => [(m) => (m.tracker ? m.tracker[k] : null), `${k.split("_")[0]} trk`, SERIES_COLORS[i], true, "tracker"]);
}
const PLOTS = [
  ["plot-force", [["force_x_N", "Fx"], ["force_y_N", "Fy"], ["force_z_N", "Fz"], [(m) => Math.hypot(m.force_x_N, m.force_y_N, m.force_z_N), "|F|"]]],
  ["plot-position", [["x_mm", "x"], ["y_mm", "y"], ["z_mm", "z"], ...trackerSeries(["x_mm", "y_mm", "z_mm"])]],
  ["plot-rotation", [["yaw_deg", "yaw"], ["pitch_deg", "pitch"], ["roll_deg", "roll"], ...trackerSeries(["yaw_deg", "pitch_deg", "roll_deg"])]],
  ["plot-cavities", null],
];
function cavitySeries() {
  const arms = (S.geo && S.geo.arms) || ["front_zpos", "front_zneg", "back_xpos", "back_xneg"], out = [];
  arms.forEach((a, i) => {
    out.push([`dVmeas_${a}_mm3`, a, ARM_COLORS[i], false]);
    out.push([`dVpred_${a}_mm3`, null, ARM_COLORS[i], true]);
  });
  return out;
}
function drawPlot(id, series) {
  const c = document.getElementById(id), ctx = c.getContext("2d"), d = fitCanvas(c), W = c.width, H = c.height;
  ctx.clearRect(0, 0, W, H);
  const L = 52 * d, R = 10 * d, T = 24 * d, B = 22 * d, pw = W - L - R, ph = H - T - B;
  ctx.font = `600 ${13 * d}px "DejaVu Sans", sans-serif`; ctx.fillStyle = "#1d2330";
  ctx.fillText(c.dataset.title, L, 16 * d);
  const sm = S.samples; if (!sm.length) return;
  const t1 = sm[sm.length - 1].t_s, t0 = t1 - WINDOW_S;
  let i0 = sm.length - 1; while (i0 > 0 && sm[i0 - 1].t_s >= t0) i0--;
  const get = series.map((s) => typeof s[0] === "function" ? s[0] : (m) => m[s[0]]);
  let lo = Infinity, hi = -Infinity;
  for (let i = i0; i < sm.length; i++) for (const g of get) { const v = g(sm[i]); if (v != null && isFinite(v)) { if (v < lo) lo = v; if (v > hi) hi = v; } }
  if (!isFinite(lo)) { lo = -1; hi = 1; }
  const span = Math.max(hi - lo, 1e-3), pad = 0.08 * span; lo -= pad; hi += pad;
  const X = (t) => L + pw * (t - t0) / WINDOW_S, Y = (v) => T + ph * (1 - (v - lo) / (hi - lo));
  // grid + ticks
  ctx.font = `${11 * d}px "DejaVu Sans", sans-serif`; ctx.strokeStyle = "#e6e9ee"; ctx.fillStyle = "#555"; ctx.lineWidth = 1;
  const step = niceMax((hi - lo) / 5) / (niceMax((hi - lo) / 5) / ((hi - lo) / 5) > 1.8 ? 2 : 1);
  ctx.textAlign = "right";
  for (let v = Math.ceil(lo / step) * step; v <= hi; v += step) {
    ctx.beginPath(); ctx.moveTo(L, Y(v)); ctx.lineTo(L + pw, Y(v)); ctx.stroke();
    ctx.fillText(Math.abs(v) < 1e-9 ? "0" : +v.toPrecision(3) + "", L - 5 * d, Y(v) + 4 * d);
  }
  ctx.textAlign = "center";
  for (let t = Math.ceil(t0); t <= t1; t += 2) { ctx.beginPath(); ctx.moveTo(X(t), T); ctx.lineTo(X(t), T + ph); ctx.stroke(); ctx.fillText(t.toFixed(0), X(t), H - 6 * d); }
  ctx.textAlign = "left"; ctx.fillText("t s", L + pw - 24 * d, H - 6 * d);
  ctx.strokeStyle = "#9aa3b0"; ctx.strokeRect(L, T, pw, ph);
  if (lo < 0 && hi > 0) { ctx.strokeStyle = "#b9c0ca"; ctx.beginPath(); ctx.moveTo(L, Y(0)); ctx.lineTo(L + pw, Y(0)); ctx.stroke(); }
  // lines
  const last = sm[sm.length - 1];
  let lx = L + 8 * d;
  series.forEach((s, k) => {
    const col = s[2] || SERIES_COLORS[k % SERIES_COLORS.length], g = get[k];
    ctx.strokeStyle = col; ctx.lineWidth = 1.6 * d; ctx.setLineDash(s[3] ? [5 * d, 4 * d] : []);
    ctx.beginPath(); let pen = false;
    for (let i = i0; i < sm.length; i++) {
      const v = g(sm[i]); if (v == null || !isFinite(v)) { pen = false; continue; }
      const x = X(sm[i].t_s), y = Y(v); if (pen) ctx.lineTo(x, y); else { ctx.moveTo(x, y); pen = true; }
    }
    ctx.stroke(); ctx.setLineDash([]);
    if (s[1] && !(s[4] === "tracker" && !S.tracker)) {  // legend with the latest value
      const v = g(last), txt = `${s[1]} ${v == null ? "–" : v.toFixed(2)}`;
      ctx.font = `${12 * d}px "DejaVu Sans Mono", monospace`;
      const w = ctx.measureText(txt).width;
      ctx.fillStyle = "rgba(255,255,255,0.85)"; ctx.fillRect(lx - 2 * d, T + 3 * d, w + 22 * d, 16 * d);
      ctx.fillStyle = col; ctx.fillRect(lx, T + 10 * d, 12 * d, 3 * d);
      ctx.fillStyle = "#1d2330"; ctx.fillText(txt, lx + 16 * d, T + 15 * d); lx += w + 30 * d;
    }
  });
}

// ---------- status + table ----------
function fmt(v, n, unit) { return v == null ? "–" : `${Number(v).toFixed(n)}${unit || ""}`; }
function drawStatus() {
  const el = document.getElementById("status"), st = S.status, m = S.latest;
  if (!st) return;
  const h = String(st.sensor_health || "waiting");
  const sensorsOk = h === "ok", qpOk = !st.qp_status || /optimal|solved|ok/i.test(st.qp_status);
  el.dataset.health = st.estimates <= 0 ? "waiting" : h.startsWith("error") || h.startsWith("stalled") ? "bad" : sensorsOk && qpOk && st.skipped_total === 0 ? "ok" : "warn";
  const s = st.stream || {}, parts = [
    st.finished ? "■ ended" : S.connected ? "● live" : "○ offline",
    `rate ${fmt(st.rate_Hz, 1, " Hz")}`,
    `step ${fmt(st.step_ms, 2, " ms")} (p99 ${fmt(st.step_p99_ms, 2, " ms")})`,
    `skipped ${st.skipped_total} · view drop ${st.view_dropped}`,
    s.enabled ? `stream ${s.endpoint.replace("tcp://", "")} ${s.subscribers} sub` : "stream off",
    `sensors ${h}`, `QP ${st.qp_status || "–"}`, `cond(W) ${fmt(st.cond_W, 1)}`,
    `t ${m ? fmt(m.t_s, 2, " s") : "–"}`, `#${st.estimates}`,
  ];
  if (st.recording && st.recording.enabled) parts.push(`rec ${st.recording.messages} msg`);
  el.textContent = parts.join(" │ ");
}
function drawTargets() {
  const tb = document.querySelector("#targets tbody"), m = S.latest;
  if (!S.geo || !m) return;
  tb.innerHTML = "";
  for (const name of Object.keys(S.geo.targets_mm || {})) {
    const v = ["dx", "dy", "dz"].map((k) => m[`${name}_${k}_mm`] || 0);
    const tr = document.createElement("tr");
    for (const x of [name, ...v.map((x) => x.toFixed(2)), Math.hypot(...v).toFixed(2)]) { const td = document.createElement("td"); td.textContent = x; tr.appendChild(td); }
    tb.appendChild(tr);
  }
}
let pending = false;
function drawAll() {
  if (pending) return; pending = true;
  const run = () => { pending = false; draw3d(); PLOTS.forEach(([id, s]) => drawPlot(id, s || cavitySeries())); drawStatus(); drawTargets(); };
  if (document.visibilityState === "visible" && window.requestAnimationFrame) requestAnimationFrame(run); else setTimeout(run, 0);
}

// ---------- interaction ----------
function setupMouse() {
  const c = document.getElementById("view3d"); let drag = null;
  c.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY, S.view.az, S.view.el]; c.style.cursor = "grabbing"; });
  window.addEventListener("mouseup", () => { drag = null; c.style.cursor = "grab"; });
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    S.view.az = drag[2] - (e.clientX - drag[0]) * 0.01;
    S.view.el = Math.max(-1.5, Math.min(1.5, drag[3] + (e.clientY - drag[1]) * 0.01)); drawAll();
  });
  c.addEventListener("wheel", (e) => { e.preventDefault(); S.view.zoom *= Math.exp(-e.deltaY * 0.001); drawAll(); }, { passive: false });
  c.addEventListener("dblclick", () => { S.view = { az: -2.2, el: 0.42, zoom: 1.0 }; drawAll(); });
  window.addEventListener("resize", drawAll);
}

async function init() {
  setupMouse();
  try {
    const g = await fetch("/api/geometry");
    if (g.ok) {
      S.geo = await g.json();
      S.rest = new Float32Array(S.geo.nodes_mm.flat());
      S.faces = new Int32Array(S.geo.faces.flat());
      let e = 1; for (const v of S.rest) e = Math.max(e, Math.abs(v)); S.extent = e;
    }
    const st = await (await fetch("/api/state")).json();
    if (st.latest) S.latest = st.latest;  // the history comes with the first SSE frame
    applyFrame({ status: st.status, surface_mm_f32_b64: st.surface_mm_f32_b64 });
  } catch (err) { document.getElementById("status").textContent = "cannot reach the live server: " + err; }
  const es = new EventSource("/api/events");
  es.addEventListener("open", () => { S.connected = true; });
  es.addEventListener("error", () => { S.connected = false; drawStatus(); });
  // ?frames=N: snapshot mode, stop listening after N frames (headless screenshots, static reports)
  const stopAfter = Number(new URLSearchParams(location.search).get("frames") || 0);
  es.addEventListener("frame", (ev) => {
    applyFrame(JSON.parse(ev.data));
    if (stopAfter && S.frames >= stopAfter) { es.close(); S.connected = false; drawAll(); }
  });
}
init();
