// fluxdrive scope page: envelopes from /ws (see fluxdrive_bringup/scope_tap.py for the
// document), charts with uPlot (vendored), parameter panel and fault reset over /api.
"use strict";

const TOKEN = new URLSearchParams(location.search).get("token") || "";
const COLORS = ["#1565c0", "#c62828", "#2e7d32", "#ef6c00", "#6a1b9a", "#00838f", "#ad1457",
                "#4e342e"];
const stats = { envelopes: 0, redraws: 0, fps: 0, dataRate: 0, lastSeq: -1, simT: 0 };
window.scopeStats = stats; // read by the browser test
window.scopeDebug = {        // non-null envelope points per stream:field (the browser test)
  points: () => {
    const out = {};
    for (const [s, st] of Object.entries(store)) {
      for (const [f, a] of Object.entries(st.f)) out[s + ":" + f] = a[1].filter((v) => v !== null).length;
    }
    return out;
  },
};

let modes = {};
let bucket = 20, tsS = 1e-4;
let observers = [];
let charts = [];           // {def, u (uPlot) | canvas, el}
let store = {};            // stream -> {k: [], f: {field: [mins, maxs]}}
let locus = {};            // observer -> {t: [], x: [], y: []}
let dirty = false;

const $ = (id) => document.getElementById(id);
const winS = () => parseFloat($("win").value);
const paused = () => $("pause").checked;

// ------------------------------------------------------------------ data
function resetStore() { store = {}; locus = {}; }

function ingest(doc) {
  bucket = doc.bucket; tsS = doc.ts_s;
  const seq = doc.seq;
  if (seq >= 0 && stats.lastSeq >= 0 && seq < stats.lastSeq - 1000) resetStore(); // a new run
  if (seq >= 0) { stats.lastSeq = seq; stats.simT = seq * tsS; }
  for (const [name, st] of Object.entries(doc.streams)) {
    // st: k = bucket indices, n = field names, lo/hi = rows (one per bucket) of the fields
    let s = store[name];
    if (!s) s = store[name] = { k: [], f: {} };
    const n0 = s.k.length;
    const col = {};
    st.n.forEach((f, j) => {
      col[f] = j;
      if (!s.f[f]) s.f[f] = [new Array(n0).fill(null), new Array(n0).fill(null)];
    });
    let start = 0;
    if (n0 && st.k.length && st.k[0] === s.k[n0 - 1]) { // a bucket cut by the period: merge
      for (const [f, j] of Object.entries(col)) {
        const a = s.f[f];
        a[0][n0 - 1] = minN(a[0][n0 - 1], st.lo[0][j]);
        a[1][n0 - 1] = maxN(a[1][n0 - 1], st.hi[0][j]);
      }
      start = 1;
    }
    for (let i = start; i < st.k.length; i++) {
      s.k.push(st.k[i]);
      for (const [f, a] of Object.entries(s.f)) {
        const j = col[f];
        a[0].push(j === undefined ? null : st.lo[i][j]);
        a[1].push(j === undefined ? null : st.hi[i][j]);
      }
    }
  }
  const tNow = stats.simT;
  for (const [name, [xs, ys]] of Object.entries(doc.locus || {})) {
    let l = locus[name];
    if (!l) l = locus[name] = { t: [], x: [], y: [] };
    for (let i = 0; i < xs.length; i++) { l.t.push(tNow); l.x.push(xs[i]); l.y.push(ys[i]); }
  }
  trim();
  updateDrive(doc);
  const obs = doc.observers || [];
  if (obs.join(",") !== observers.join(",")) { observers = obs; buildCharts(); }
  noteArrival();
  dirty = true;
}

function minN(a, b) { return a === null ? b : b === null ? a : Math.min(a, b); }
function maxN(a, b) { return a === null ? b : b === null ? a : Math.max(a, b); }

function trim() {
  const kmin = Math.floor((stats.simT - winS()) / (bucket * tsS));
  for (const s of Object.values(store)) {
    let i = 0;
    while (i < s.k.length && s.k[i] < kmin) i++;
    if (i) { s.k.splice(0, i); for (const a of Object.values(s.f)) { a[0].splice(0, i); a[1].splice(0, i); } }
  }
  const tmin = stats.simT - winS();
  for (const l of Object.values(locus)) {
    let i = 0;
    while (i < l.t.length && l.t[i] < tmin) i++;
    if (i) { l.t.splice(0, i); l.x.splice(0, i); l.y.splice(0, i); }
  }
}

// ------------------------------------------------------------------ charts
function chartDefs() {
  const o = observers.map((n, i) => ({ n, c: COLORS[i % COLORS.length] }));
  const per = (f) => o.map((x) => ({ s: "est/" + x.n, f, label: x.n, c: x.c }));
  const truth = (f) => ({ s: "truth", f, label: "true", c: "#000", w: 1.5 });
  return [
    { id: "theta", title: "θ̂ per observer and true θ [deg]", series: [...per("theta"), truth("theta")] },
    { id: "err", title: "θ̃ = θ̂ − θ (against the truth) [deg]", series: per("err") },
    { id: "omega", title: "ω̂ [rad/s, electrical]", series: [...per("omega_e"), truth("omega_e")] },
    { id: "flux", title: "|λ̂| [mV·s]", series: per("flux_mag") },
    { id: "locus", kind: "xy", title: "flux locus λ̂β over λ̂α [mV·s]" },
    { id: "idq", title: "i_d, i_q and their references [A]", series: [
      { s: "state", f: "i_d", label: "i_d", c: COLORS[0] },
      { s: "state", f: "i_d_ref", label: "i_d ref", c: COLORS[0], dash: [5, 4] },
      { s: "state", f: "i_q", label: "i_q", c: COLORS[1] },
      { s: "state", f: "i_q_ref", label: "i_q ref", c: COLORS[1], dash: [5, 4] }] },
    { id: "speed", title: "speed and its reference [rpm]", series: [
      { s: "state", f: "speed_ref", label: "reference", c: "#888", dash: [5, 4] },
      { s: "state", f: "speed_fb", label: "feedback", c: COLORS[0] },
      { s: "truth", f: "speed", label: "true", c: "#000" }] },
    { id: "duty", title: "duty a, b, c [-]", series: [
      { s: "duty", f: "a", label: "a", c: COLORS[0] }, { s: "duty", f: "b", label: "b", c: COLORS[1] },
      { s: "duty", f: "c", label: "c", c: COLORS[2] }] },
  ];
}

function legendHtml(def) {
  if (def.kind === "xy") {
    return observers.map((n, i) => `<span class="lg" data-i="${i}"><i style="background:${COLORS[i % COLORS.length]}"></i>${n}</span>`).join("");
  }
  return def.series.map((s, i) => `<span class="lg" data-i="${i}"><i style="background:${s.c}"></i>${s.label}</span>`).join("") +
    '<span style="color:#777">(band = min…max of each bucket; click a name to hide it)</span>';
}

const hidden = new Set();  // "chart:label" the user switched off (kept across rebuilds)

function wireLegend(ch) {
  for (const el of ch.el.querySelectorAll(".lg")) {
    const i = +el.dataset.i;
    const label = ch.def.kind === "xy" ? observers[i] : ch.def.series[i].label;
    const key = ch.def.id + ":" + label;
    const apply = () => {
      const off = hidden.has(key);
      el.classList.toggle("off", off);
      if (ch.u) { ch.u.setSeries(1 + 2 * i, { show: !off }); ch.u.setSeries(2 + 2 * i, { show: !off }); }
      dirty = true;
    };
    el.addEventListener("click", () => { if (hidden.has(key)) hidden.delete(key); else hidden.add(key); apply(); });
    if (hidden.has(key)) apply();
  }
}

function buildCharts() {
  const host = $("charts");
  host.innerHTML = "";
  charts = [];
  for (const def of chartDefs()) {
    const el = document.createElement("div");
    el.className = "card";
    el.id = "chart-" + def.id;
    el.innerHTML = `<h3>${def.title}</h3><div class="legend">${legendHtml(def)}</div>`;
    host.appendChild(el);
    const width = Math.max(200, el.clientWidth - 12);
    if (def.kind === "xy") {
      const c = document.createElement("canvas");
      c.className = "locus";
      el.appendChild(c);
      charts.push({ def, canvas: c, el });
      wireLegend(charts[charts.length - 1]);
      continue;
    }
    const series = [{ label: "t [s]" }];
    const bands = [];
    def.series.forEach((s) => {
      const hi = series.length;
      series.push({ label: s.label + " max", stroke: s.c, width: s.w || 1, dash: s.dash, points: { show: false }, spanGaps: false });
      series.push({ label: s.label + " min", stroke: s.c, width: s.w || 1, dash: s.dash, points: { show: false }, spanGaps: false });
      bands.push({ series: [hi, hi + 1], fill: s.c + "33" });
    });
    const opts = {
      width, height: 190, legend: { show: false }, bands,
      cursor: { drag: { x: false, y: false } },
      scales: { x: { time: false } },
      axes: [{ size: 28 }, { size: 52 }],
      series,
    };
    const u = new uPlot(opts, [[], ...series.slice(1).map(() => [])], el);
    charts.push({ def, u, el });
    wireLegend(charts[charts.length - 1]);
  }
}

function chartData(def, px) {
  // union of the bucket indices of the streams the chart uses
  const streams = [...new Set(def.series.map((s) => s.s))].filter((s) => store[s]);
  const ks = new Set();
  for (const s of streams) for (const k of store[s].k) ks.add(k);
  const kk = [...ks].sort((a, b) => a - b);
  // about one point per pixel: g buckets merge into one (min of the minima, max of the
  // maxima: still no spike hidden); groups aligned on k so they do not shift as data comes
  const g = Math.max(1, Math.ceil(kk.length / Math.max(50, px)));
  const gk = [], gidx = new Map();
  for (const k of kk) {
    const q = Math.floor(k / g);
    if (!gidx.has(q)) { gidx.set(q, gk.length); gk.push(q); }
  }
  const out = [gk.map((q) => q * g * bucket * tsS)];
  for (const s of def.series) {
    const st = store[s.s];
    const hi = new Array(gk.length).fill(null), lo = new Array(gk.length).fill(null);
    if (st && st.f[s.f]) {
      const [mn, mx] = st.f[s.f];
      for (let i = 0; i < st.k.length; i++) {
        const j = gidx.get(Math.floor(st.k[i] / g));
        lo[j] = minN(lo[j], mn[i]); hi[j] = maxN(hi[j], mx[i]);
      }
    }
    out.push(hi, lo);
  }
  return out;
}

function drawLocus(ch) {
  const c = ch.canvas, dpr = window.devicePixelRatio || 1;
  const w = c.clientWidth, h = c.clientHeight;
  if (c.width !== w * dpr) { c.width = w * dpr; c.height = h * dpr; }
  const g = c.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  const shown = observers.filter((n) => !hidden.has(ch.def.id + ":" + n));
  let r = 1e-9;
  for (const n of shown) {
    const l = locus[n];
    if (l) for (let i = 0; i < l.x.length; i++) r = Math.max(r, Math.abs(l.x[i] || 0), Math.abs(l.y[i] || 0));
  }
  r *= 1.15;
  const cx = w / 2, cy = h / 2, sc = Math.min(w, h) / 2 / r;
  g.strokeStyle = "#ccc"; g.lineWidth = 1;
  g.beginPath(); g.moveTo(0, cy); g.lineTo(w, cy); g.moveTo(cx, 0); g.lineTo(cx, h); g.stroke();
  g.fillStyle = "#777"; g.font = "10px sans-serif";
  g.fillText(`±${r.toPrecision(3)} mV·s`, 4, 12);
  observers.forEach((n, i) => {
    const l = locus[n];
    if (!l || !shown.includes(n)) return;
    g.fillStyle = COLORS[i % COLORS.length];
    for (let j = 0; j < l.x.length; j++) {
      if (l.x[j] === null || l.y[j] === null) continue;
      g.fillRect(cx + l.x[j] * sc - 1, cy - l.y[j] * sc - 1, 2, 2);
    }
  });
}

// The page scrolls smoothly at up to FPS frames a second whatever the data rate: the window's
// right edge follows the newest data at the sample rate observed between documents, a little
// behind it, and each frame re-draws every chart at the new edge.
const FPS = 30;
let tShow = 0, simRate = 0, arrInt = 40, lastArrWall = null, lastArrT = 0, lastFrameWall = 0;
let dataDirty = false;

function noteArrival() {
  const now = performance.now();
  if (lastArrWall !== null && now > lastArrWall) {
    const r = (stats.simT - lastArrT) / (now - lastArrWall);  // sim s per wall ms
    if (r >= 0 && isFinite(r)) simRate = simRate ? 0.8 * simRate + 0.2 * r : r;
    arrInt = 0.8 * arrInt + 0.2 * Math.min(now - lastArrWall, 2000);  // ms between documents
  }
  lastArrWall = now; lastArrT = stats.simT;
  dataDirty = true;
}

function redraw(now) {
  const dt = lastFrameWall ? now - lastFrameWall : 0;
  const lagMax = simRate * arrInt * 1.3;  // about one document behind the newest data
  tShow = Math.min(stats.simT, Math.max(tShow + simRate * dt, stats.simT - lagMax));
  const win = winS();
  for (const ch of charts) {
    if (ch.u) {
      ch.u.batch(() => {
        if (dataDirty) ch.u.setData(chartData(ch.def, ch.el.clientWidth), false);
        ch.u.setScale("x", { min: tShow - win, max: tShow });
      });
    } else if (dataDirty) drawLocus(ch);
  }
  dataDirty = false;
}

function resize() {
  for (const ch of charts) if (ch.u) ch.u.setSize({ width: Math.max(200, ch.el.clientWidth - 12), height: 190 });
  dirty = true;
}
window.addEventListener("resize", resize);

function frame(now) {
  const moving = dirty || dataDirty || tShow < stats.simT;  // nothing new: no redraw
  if (moving && !paused() && stats.lastSeq >= 0 && now - lastFrameWall >= 1000 / FPS - 2) {
    if (dirty) dataDirty = true;
    const t0 = performance.now();
    redraw(now);
    stats.drawMs = 0.9 * (stats.drawMs || 0) + 0.1 * (performance.now() - t0);  // per frame
    lastFrameWall = now;
    dirty = false;
    stats.redraws++;
  }
  requestAnimationFrame(frame);
}

let lastRedraws = 0, lastEnv = 0, lastSeqT = null;
setInterval(() => {
  stats.fps = stats.redraws - lastRedraws; lastRedraws = stats.redraws;
  stats.dataRate = stats.envelopes - lastEnv; lastEnv = stats.envelopes;
  $("fps").textContent = stats.fps;
  $("rate").textContent = stats.dataRate;
  if (lastSeqT !== null && stats.lastSeq >= 0) $("srate").textContent = Math.max(0, stats.lastSeq - lastSeqT);
  lastSeqT = stats.lastSeq;
  $("simt").textContent = stats.simT.toFixed(3);
}, 1000);

// ------------------------------------------------------------------ drive state
function updateDrive(doc) {
  if (doc.mode !== undefined) {
    $("mode").textContent = modes[doc.mode] || String(doc.mode);
    $("mode").className = doc.mode === 4 ? "bad" : "ok";
    $("fault").textContent = doc.fault ? doc.fault : "none";
    $("fault").className = doc.fault ? "bad" : "ok";
  }
  if (doc.enable !== undefined) $("enable").textContent = doc.enable ? "on" : "off";
}

$("reset").addEventListener("click", async () => {
  $("resetmsg").textContent = "…";
  const r = await fetch("api/reset", { method: "POST", headers: { "X-Scope-Token": TOKEN } });
  const j = await r.json();
  $("resetmsg").textContent = (j.ok ? "ok: " : "refused: ") + j.message;
  $("resetmsg").className = j.ok ? "ok" : "bad";
});

// ------------------------------------------------------------------ parameters
function valueText(p) {
  if (Array.isArray(p.value)) return JSON.stringify(p.value);
  if (p.value === null || p.value === undefined) return "";
  return String(p.value);
}

function rangeText(p) {
  if (p.choices.length) return "one of " + p.choices.join(", ");
  if (p.min !== null && p.max !== null) return `[${p.min}, ${p.max}]`;
  return "";
}

function paramRow(node, p) {
  const tr = document.createElement("tr");
  tr.dataset.node = node; tr.dataset.name = p.name;
  if (p.read_only) tr.className = "ro";
  const td1 = document.createElement("td");
  td1.className = "name";
  td1.title = p.description;
  td1.innerHTML = `${p.name}<small>${escapeHtml(p.description)} ${escapeHtml(rangeText(p))}${p.read_only ? " (read-only)" : ""}</small>`;
  const td2 = document.createElement("td");
  let input;
  if (p.choices.length || typeof p.value === "boolean") {
    input = document.createElement("select");
    const opts = p.choices.length ? p.choices : ["true", "false"];
    for (const o of opts) { const op = document.createElement("option"); op.value = op.textContent = o; input.appendChild(op); }
    input.value = valueText(p);
  } else {
    input = document.createElement("input");
    input.value = valueText(p);
  }
  input.disabled = p.read_only;
  const td3 = document.createElement("div");  // the node's answer, under the description
  td3.className = "status";
  td1.appendChild(td3);
  const send = async () => {
    td3.textContent = "…"; td3.className = "status";
    const r = await fetch("api/param", { method: "POST", headers: { "Content-Type": "application/json", "X-Scope-Token": TOKEN },
                                         body: JSON.stringify({ node, name: p.name, value: input.value }) });
    const j = await r.json();
    td3.textContent = j.ok ? "✓ " + (j.reason || "set") : "✗ " + j.reason;
    td3.className = "status " + (j.ok ? "ok" : "bad");
  };
  if (input.tagName === "SELECT") input.addEventListener("change", send);
  else input.addEventListener("keydown", (e) => { if (e.key === "Enter") send(); });
  td2.appendChild(input);
  tr.append(td1, td2);
  return tr;
}

function escapeHtml(s) { return String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c])); }

const openNodes = new Set(), closedNodes = new Set();  // the user's choice, kept across reloads

async function loadParams() {
  $("nodes").textContent = "loading…";
  document.body.dataset.params = "loading";
  try {
    const r = await fetch("api/nodes", { headers: { "X-Scope-Token": TOKEN } });
    const j = await r.json();
    const host = $("nodes");
    host.innerHTML = "";
    if (j.error) { host.textContent = j.error; return; }
    for (const n of j.nodes) {
      const d = document.createElement("details");
      d.dataset.node = n.node;
      // open: what the user opened, and the controller unless the user closed it
      d.open = openNodes.has(n.node) || (n.node === "/controller" && !closedNodes.has(n.node));
      d.addEventListener("toggle", () => {
        if (d.open) { openNodes.add(n.node); closedNodes.delete(n.node); }
        else { openNodes.delete(n.node); closedNodes.add(n.node); }
      });
      d.innerHTML = `<summary>${n.node} <small>(${n.params.length})</small></summary>`;
      const t = document.createElement("table");
      for (const p of n.params) t.appendChild(paramRow(n.node, p));
      if (n.error) d.appendChild(document.createTextNode(n.error));
      d.appendChild(t);
      host.appendChild(d);
    }
    document.body.dataset.params = "loaded";
  } catch (e) {
    $("nodes").textContent = "cannot load parameters: " + e;
  }
}
$("reload").addEventListener("click", loadParams);

// ------------------------------------------------------------------ connection
function connect() {
  const ws = new WebSocket(`ws://${location.host}/ws?token=${encodeURIComponent(TOKEN)}`);
  ws.onopen = () => { $("conn").textContent = "connected"; $("conn").className = "ok"; };
  ws.onclose = () => {
    $("conn").textContent = "disconnected (retrying)"; $("conn").className = "bad";
    setTimeout(connect, 1000);
  };
  ws.onmessage = (ev) => {
    const doc = JSON.parse(ev.data);
    if (doc.hello) { modes = doc.hello.modes; return; }
    stats.envelopes++;
    if (!paused()) ingest(doc);
  };
}

$("win").addEventListener("change", () => { trim(); dirty = true; });
buildCharts();
connect();
loadParams();
requestAnimationFrame(frame);
