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
  chart: (id) => { const c = charts.find((x) => x.def.id === id); return c ? c.u : null; },
  zoom: () => zoom,
  dragView: () => dragView,
  timing: () => ({ tShow, simRate, arrInt, lastFrameWall, errors: stats.errors || 0, redraws: stats.redraws }),
  cursors: () => ({ ...cursors }),
  spectrum: () => spectrum,
  markers: () => markers,
};

let modes = {};
let bucket = 20, tsS = 1e-4;
let observers = [];
let charts = [];           // {def, u (uPlot) | canvas, el}
let store = {};            // stream -> {k: [], f: {field: [mins, maxs]}}
let locus = {};            // observer -> {t: [], x: [], y: []}
let dirty = false;
let markers = [];          // parameter changes: {t, text, ok} on every time axis
let spectrum = {};         // observer -> {orders, err, flux_alpha, periods} (the server's)
let zoom = null;           // [t0, t1] while zoomed (the view is held), else null
let zoomPaused = false;    // the zoom paused the page (unzoom resumes it)
let dragView = null;       // [t0, t1] held while a drag selects a span: the time axis
                           // must not scroll under the selection, or it means other times
let dragChart = null;      // the chart the drag started on: the only one whose selection
                           // (in its own pixels) zooms; synced charts have other widths
const cursors = { a: null, b: null };  // cursor times [s]: click = A, shift-click = B
let capture = null;        // the newest capture, reopened from its bag by the server
let captureChart = null;

// a number at its precision: 12 significant digits, trailing zeros dropped
// (20.00000000001 -> 20, 0.1 + 0.2 -> 0.3)
function fmt(v) {
  if (v === null || v === undefined) return "–";
  if (typeof v !== "number") return String(v);
  if (!isFinite(v)) return String(v);
  return String(Number(v.toPrecision(12)));
}
// a reading: 5 significant digits (a readout, not a value to type back)
function fmtR(v) { return v === null || v === undefined ? "–" : String(Number(v.toPrecision(5))); }

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
  for (const m of doc.markers || []) {
    markers.push({ t: m.seq * tsS, text: `${m.node.split("/").pop()} ${m.name}=${m.value}`, ok: m.ok });
  }
  if (doc.spectrum) Object.assign(spectrum, doc.spectrum), spectrumDirty = true;
  updateTrigger(doc);
  trim();
  updateDrive(doc);
  const obs = doc.observers || [];
  if (obs.join(",") !== observers.join(",")) { observers = obs; buildCharts(); }
  noteArrival();
  updateTraceList();
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
  markers = markers.filter((m) => m.t >= tmin);
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
    { id: "iabc", title: "phase currents i_a, i_b, i_c [A]", series: [
      { s: "frame", f: "i_a", label: "i_a", c: COLORS[0] }, { s: "frame", f: "i_b", label: "i_b", c: COLORS[1] },
      { s: "frame", f: "i_c", label: "i_c", c: COLORS[2] }] },
    { id: "vll", title: "line voltages v_ab, v_bc, v_ca (period averages) [V]", series: [
      { s: "frame", f: "v_ab", label: "v_ab", c: COLORS[0] }, { s: "frame", f: "v_bc", label: "v_bc", c: COLORS[1] },
      { s: "frame", f: "v_ca", label: "v_ca", c: COLORS[2] }] },
    { id: "vdc", title: "DC bus voltage [V]", series: [{ s: "frame", f: "vdc", label: "v_dc", c: COLORS[3] }] },
    { id: "mode", title: "drive state timeline", modes: true, series: [
      { s: "state", f: "mode", label: "mode", c: "#455a64", w: 2 }] },
    { id: "spec_err", kind: "spectrum", key: "err", title: "order spectrum of θ̃ against the rotor angle [deg]" },
    { id: "spec_flux", kind: "spectrum", key: "flux_alpha", title: "order spectrum of λ̂α against the rotor angle [mV·s]" },
  ];
}

function legendHtml(def) {
  if (def.kind === "xy" || def.kind === "spectrum") {
    return observers.map((n, i) => `<span class="lg" data-i="${i}"><i style="background:${COLORS[i % COLORS.length]}"></i>${n}</span>`).join("");
  }
  return def.series.map((s, i) => `<span class="lg" data-i="${i}"><i style="background:${s.c}"></i>${s.label}</span>`).join("") +
    '<span style="color:#777">(band = min…max of each bucket; click a name to hide it)</span>';
}

const hidden = new Set();  // "chart:label" the user switched off (kept across rebuilds)

function wireLegend(ch) {
  for (const el of ch.el.querySelectorAll(".lg")) {
    const i = +el.dataset.i;
    const label = ch.def.series ? ch.def.series[i].label : observers[i];
    const key = ch.def.id + ":" + label;
    const apply = () => {
      const off = hidden.has(key);
      el.classList.toggle("off", off);
      if (ch.u && ch.def.kind === "spectrum") ch.u.setSeries(1 + i, { show: !off });
      else if (ch.u) { ch.u.setSeries(1 + 2 * i, { show: !off }); ch.u.setSeries(2 + 2 * i, { show: !off }); }
      dirty = true;
    };
    el.addEventListener("click", () => { if (hidden.has(key)) hidden.delete(key); else hidden.add(key); apply(); });
    if (hidden.has(key)) apply();
  }
}

// y range of a chart from the 1st and 99th percentiles of what is in view (robust: one
// observer's start-up transient does not set the scale for all), 8 % margin; the full
// min..max with "robust" unticked
function yRange(u, dmin, dmax) {
  const [x0, x1] = [u.scales.x.min, u.scales.x.max];
  const xs = u.data[0], vals = [];
  for (let s = 1; s < u.data.length; s++) {
    if (!u.series[s].show) continue;
    const ys = u.data[s];
    for (let i = 0; i < xs.length; i++) {
      if (xs[i] >= x0 && xs[i] <= x1 && Number.isFinite(ys[i])) vals.push(ys[i]);
    }
  }
  if (!vals.length) return paddedRange(dmin ?? -1, dmax ?? 1);
  vals.sort((a, b) => a - b);
  const q = (p) => vals[Math.min(vals.length - 1, Math.max(0, Math.round(p * (vals.length - 1))))];
  const [lo, hi] = $("robust").checked ? [q(0.01), q(0.99)] : [vals[0], vals[vals.length - 1]];
  return paddedRange(lo, hi);
}

// [lo, hi] widened to a span uPlot can draw: its axis splits step from lo to hi, and on an
// empty, non-finite or round-off-sized span they never arrive ("Invalid array length")
function paddedRange(lo, hi) {
  if (!Number.isFinite(lo) || !Number.isFinite(hi)) [lo, hi] = [-1, 1];
  const least = 1e-6 * Math.max(1, Math.abs(lo), Math.abs(hi));
  if (!(hi - lo >= least)) {
    const c = (lo + hi) / 2, w = Math.max(0.5, least);
    [lo, hi] = [c - w, c + w];
  }
  const m = 0.08 * (hi - lo);
  return [lo - m, hi + m];
}

// a time span the x axis can show: finite and wider than round-off at its times
const drawableSpan = (t0, t1) =>
  Number.isFinite(t0) && Number.isFinite(t1) && t1 - t0 > 1e-9 * Math.max(1, Math.abs(t0), Math.abs(t1));

// cursor lines (A, B) and parameter-change markers on every time chart
function drawOverlay(u) {
  const g = u.ctx, top = u.bbox.top, h = u.bbox.height, dpr = devicePixelRatio || 1;
  g.save();
  g.font = `${10 * dpr}px sans-serif`;
  for (const m of markers) {
    if (m.t < u.scales.x.min || m.t > u.scales.x.max) continue;
    const x = Math.round(u.valToPos(m.t, "x", true));
    g.strokeStyle = m.ok ? "#ef6c00" : "#c62828"; g.setLineDash([4 * dpr, 3 * dpr]); g.lineWidth = dpr;
    g.beginPath(); g.moveTo(x, top); g.lineTo(x, top + h); g.stroke();
    g.fillStyle = g.strokeStyle; g.fillText((m.ok ? "" : "✗ ") + m.text, x + 3 * dpr, top + 10 * dpr);
  }
  g.setLineDash([]);
  for (const [k, c] of [["a", "#000"], ["b", "#6a1b9a"]]) {
    const t = cursors[k];
    if (t === null || t < u.scales.x.min || t > u.scales.x.max) continue;
    const x = Math.round(u.valToPos(t, "x", true));
    g.strokeStyle = c; g.lineWidth = dpr;
    g.beginPath(); g.moveTo(x, top); g.lineTo(x, top + h); g.stroke();
    g.fillStyle = c; g.fillText(k.toUpperCase(), x + 3 * dpr, top + h - 4 * dpr);
  }
  g.restore();
}

// value of each series at time t: the bucket (or merged group) holding t, "min…max"
function valueAt(ch, t) {
  const d = ch.u.data, xs = d[0];
  if (!xs.length) return null;
  let i = 0;
  while (i + 1 < xs.length && xs[i + 1] <= t) i++;
  return ch.def.series.map((s, j) => {
    const hi = d[1 + 2 * j][i], lo = d[2 + 2 * j][i];
    if (hi === null || lo === null) return `${s.label} –`;
    const v = ch.def.modes ? (modes[hi] || hi) : (Math.abs(hi - lo) <= 1e-12 * Math.max(1, Math.abs(hi)) ? fmtR(hi) : `${fmtR(lo)}…${fmtR(hi)}`);
    return `${s.label} ${v}`;
  }).join(", ");
}

function updateReadouts() {
  const { a, b } = cursors;
  let head = "";
  if (a !== null) head += `A t=${fmtR(a)} s`;
  if (b !== null) head += `  B t=${fmtR(b)} s`;
  if (a !== null && b !== null) head += `  Δt=${fmtR(b - a)} s (1/Δt=${fmtR(1 / Math.abs(b - a))} Hz)`;
  $("cursors").textContent = head || "click a chart: cursor A; shift-click: B";
  for (const ch of charts) {
    if (!ch.u || ch.def.kind === "spectrum") continue;
    const parts = [];
    if (a !== null) parts.push("A: " + valueAt(ch, a));
    if (b !== null) parts.push("B: " + valueAt(ch, b));
    ch.el.querySelector(".readout").textContent = parts.join("  |  ");
  }
}

function zoomTo(range) {
  if (range && !drawableSpan(range[0], range[1])) return;  // a click, not a span
  zoom = range;
  dragView = null;
  if (range && !paused()) { $("pause").checked = true; zoomPaused = true; }
  if (!range && zoomPaused) { $("pause").checked = false; zoomPaused = false; }
  $("zoomstate").textContent = range ? `zoom ${fmtR(range[0])}…${fmtR(range[1])} s (double-click: back)` : "";
  for (const ch of charts) {
    if (!ch.u || ch.def.kind === "spectrum") continue;
    if (range) ch.u.setScale("x", { min: range[0], max: range[1] });
  }
  dirty = true; dataDirty = true;
  if (range) updateReadouts();
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
    if (def.kind === "spectrum") {
      // one stem line with a dot per order and observer (orders 1..20)
      const series = [{ label: "order" }, ...observers.map((name, i) => ({
        label: name, stroke: COLORS[i % COLORS.length], width: 1,
        points: { show: true, size: 6, fill: COLORS[i % COLORS.length] } }))];
      const u = new uPlot({
        width, height: 170, legend: { show: false },
        scales: { x: { time: false, range: [0.4, 20.6] }, y: { range: (u, mn, mx) => [0, (Number.isFinite(mx) ? Math.max(mx, 1e-9) : 1) * 1.1] } },
        axes: [{ size: 28, splits: () => Array.from({ length: 20 }, (_, k) => k + 1) }, { size: 52 }],
        series,
      }, [[], ...observers.map(() => [])], el);
      const note = document.createElement("div");
      note.className = "readout";
      el.appendChild(note);
      charts.push({ def, u, el });
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
    const yAxis = { size: 52 };
    if (def.modes) {
      yAxis.size = 80;
      yAxis.splits = () => [0, 1, 2, 3, 4];
      yAxis.values = (u, vs) => vs.map((v) => modes[v] || v);
    }
    const opts = {
      width, height: def.modes ? 110 : 190, legend: { show: false }, bands,
      cursor: { drag: { x: true, y: false, setScale: false }, sync: { key: "scope-t" } },
      select: { show: true },
      scales: { x: { time: false }, y: def.modes ? { range: [-0.3, 4.3] } : { range: yRange } },
      axes: [{ size: 28 }, yAxis],
      series,
      hooks: {
        draw: [drawOverlay],
        setSelect: [(u) => {
          if (u.select.width > 4 && u === dragChart) {
            zoomTo([u.posToVal(u.select.left, "x"), u.posToVal(u.select.left + u.select.width, "x")]);
          }
          u.setSelect({ left: 0, width: 0, top: 0, height: 0 }, false);
        }],
      },
    };
    const u = new uPlot(opts, [[], ...series.slice(1).map(() => [])], el);
    const ro = document.createElement("div");
    ro.className = "readout";
    el.appendChild(ro);
    u.over.addEventListener("click", (e) => {
      const t = u.posToVal(e.offsetX, "x");
      if (e.shiftKey) cursors.b = t; else cursors.a = t;
      updateReadouts();
      for (const c of charts) if (c.u) c.u.redraw(false, false);
    });
    u.over.addEventListener("dblclick", () => zoomTo(null));
    u.over.addEventListener("mousedown", () => {
      dragChart = u;
      const [t0, t1] = [u.scales.x.min, u.scales.x.max];
      if (!zoom && drawableSpan(t0, t1)) dragView = [t0, t1];
    });
    charts.push({ def, u, el });
    wireLegend(charts[charts.length - 1]);
  }
  spectrumDirty = true;
}

let spectrumDirty = false;
function drawSpectra() {
  for (const ch of charts) {
    if (ch.def.kind !== "spectrum") continue;
    const orders = Array.from({ length: 20 }, (_, k) => k + 1);
    const data = [orders, ...observers.map((n) => {
      const sp = spectrum[n];
      return sp && sp[ch.def.key] ? sp[ch.def.key] : orders.map(() => null);
    })];
    ch.u.setData(data);
    const per = observers.filter((n) => spectrum[n]).map((n) => spectrum[n].periods).filter((p) => p);
    const top = observers.filter((n) => spectrum[n] && spectrum[n][ch.def.key]).map((n) => {
      const v = spectrum[n][ch.def.key];
      return `${n}: h1 ${fmtR(v[0])}, h6 ${fmtR(v[5])}`;
    });
    ch.el.querySelector(".readout").textContent =
      (per.length ? `over ${fmtR(per[0])} electrical periods; ` : "waiting for a window of samples; ") + top.join("; ");
  }
  spectrumDirty = false;
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
  const win = winS();
  // about one document behind the newest data, for a smooth scroll; but never more than
  // half the window, which is all the page keeps: a slow page with a fast graph (documents
  // many seconds of sim time apart) jumps instead of showing times it holds no data for
  const lagMax = Math.min(simRate * arrInt * 1.3, 0.5 * win);
  tShow = Math.min(stats.simT, Math.max(tShow + simRate * dt, stats.simT - lagMax));
  const [x0, x1] = zoom || dragView || [tShow - win, tShow];
  for (const ch of charts) {
    if (ch.def.kind === "spectrum") continue;
    if (ch.u) {
      ch.u.batch(() => {
        if (dataDirty) ch.u.setData(chartData(ch.def, ch.el.clientWidth), false);
        if (drawableSpan(x0, x1)) ch.u.setScale("x", { min: x0, max: x1 });
      });
    } else if (dataDirty) drawLocus(ch);
  }
  if (spectrumDirty) drawSpectra();
  if (dataDirty && (cursors.a !== null || cursors.b !== null)) updateReadouts();
  dataDirty = false;
}

function resize() {
  for (const ch of charts) if (ch.u) ch.u.setSize({ width: Math.max(200, ch.el.clientWidth - 12), height: ch.u.height });
  dirty = true;
}
window.addEventListener("resize", resize);
// capture phase: seen even when a chart's own handler stops the event; cleared after the
// chart has read its selection
window.addEventListener("mouseup", () => setTimeout(() => { dragView = null; dragChart = null; }, 0), true);

function frame(now) {
  // the next frame is asked for first: an error in one chart must not stop the page
  requestAnimationFrame(frame);
  const moving = dirty || dataDirty || spectrumDirty || tShow < stats.simT;  // nothing new: no redraw
  if (moving && (!paused() || dirty) && stats.lastSeq >= 0 && now - lastFrameWall >= 1000 / FPS - 2) {
    if (dirty) dataDirty = true;
    const t0 = performance.now();
    lastFrameWall = now;
    dirty = false;
    try {
      redraw(now);
    } catch (e) {
      stats.errors = (stats.errors || 0) + 1;
      spectrumDirty = false;
      console.error("scope: redraw failed:", e);
    }
    stats.drawMs = 0.9 * (stats.drawMs || 0) + 0.1 * (performance.now() - t0);  // per frame
    stats.redraws++;
  }
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
  const r = await fetch("api/reset", { method: "POST", headers: { "X-Fluxdrive-Token": TOKEN } });
  const j = await r.json();
  $("resetmsg").textContent = (j.ok ? "ok: " : "refused: ") + j.message;
  $("resetmsg").className = j.ok ? "ok" : "bad";
});

// ------------------------------------------------------------------ parameters
function valueText(p) {
  if (Array.isArray(p.value)) return "[" + p.value.map((v) => typeof v === "number" ? fmt(v) : JSON.stringify(v)).join(", ") + "]";
  if (p.value === null || p.value === undefined) return "";
  return fmt(p.value);
}

function rangeText(p) {
  if (p.choices.length) return "one of " + p.choices.join(", ");
  if (p.min !== null && p.max !== null) return `[${fmt(p.min)}, ${fmt(p.max)}]`;
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
    const r = await fetch("api/param", { method: "POST", headers: { "Content-Type": "application/json", "X-Fluxdrive-Token": TOKEN },
                                         body: JSON.stringify({ node, name: p.name, value: input.value }) });
    const j = await r.json();
    td3.textContent = j.ok ? "✓ " + (j.reason || "set") : "✗ " + j.reason;
    td3.className = "status " + (j.ok ? "ok" : "bad");
    // the box shows what the node holds now: the new value, or the old one after a refusal
    if (j.value !== null && j.value !== undefined) p.value = j.value;
    input.value = valueText(p);
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
    const r = await fetch("api/nodes", { headers: { "X-Fluxdrive-Token": TOKEN } });
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

// ------------------------------------------------------------------ trigger and capture
let capturePath = null;
function updateTrigger(doc) {
  const st = $("trigstate");
  if (doc.pending) st.textContent = `triggered at t=${fmtR(doc.pending.seq * tsS)} s (${doc.pending.why}); capturing…`;
  else if (doc.armed) st.textContent = "armed";
  const c = doc.capture;
  if (c && c.path !== capturePath) {
    capturePath = c.path;
    if (c.error) { st.textContent = c.error; return; }
    st.textContent = `captured: ${c.why} at t=${fmtR(c.seq * tsS)} s -> ${c.path}; reopening…`;
    setTimeout(loadCapture, 300);
  }
}

async function loadCapture(attempt = 0) {
  const r = await fetch("api/capture", { headers: { "X-Fluxdrive-Token": TOKEN } });
  const j = await r.json();
  if (!j.path || j.path !== capturePath) {  // the server is still reading the bag
    if (attempt < 40) setTimeout(() => loadCapture(attempt + 1), 250);
    return;
  }
  capture = j;
  window.scopeCapture = j;  // read by the browser test
  if (j.error) { $("trigstate").textContent = j.error; return; }
  drawCapture();
}

function drawCapture() {
  const j = capture, host = $("capplot");
  host.innerHTML = "";
  const tTrig = j.seq * j.ts_s;
  const w = Math.max(300, host.clientWidth - 12);
  // two charts on the sample time axis: currents [A], angle errors [deg]
  const groups = [
    Object.keys(j.series).filter((k) => ["i_a", "i_b", "i_c", "i_q"].includes(k)),
    Object.keys(j.series).filter((k) => k.startsWith("err/")),
  ];
  for (const keys of groups) {
    if (!keys.length) continue;
    const ts = [...new Set(keys.flatMap((k) => j.series[k].t))].sort((a, b) => a - b);
    const ix = new Map(ts.map((t, i) => [t, i]));
    const data = [ts, ...keys.map((k) => {
      const out = new Array(ts.length).fill(null), s = j.series[k];
      s.t.forEach((t, i) => { out[ix.get(t)] = s.v[i]; });
      return out;
    })];
    captureChart = new uPlot({
      width: w, height: 170, scales: { x: { time: false } },
      axes: [{ size: 28 }, { size: 52 }],
      cursor: { drag: { x: true, y: false } },
      series: [{ label: "t [s]", value: (u, v) => fmtR(v) },
        ...keys.map((k, i) => ({ label: j.series[k].label, stroke: COLORS[i % COLORS.length], width: 1, spanGaps: true,
                                 value: (u, v) => fmtR(v) }))],
      hooks: { draw: [(u) => {
        const g = u.ctx, x = Math.round(u.valToPos(tTrig, "x", true));
        g.save(); g.strokeStyle = "#c62828"; g.setLineDash([5, 3]);
        g.beginPath(); g.moveTo(x, u.bbox.top); g.lineTo(x, u.bbox.top + u.bbox.height); g.stroke(); g.restore();
      }] },
    }, data, host);
  }
  const n = Object.values(j.messages).reduce((a, b) => a + b, 0);
  const mk = j.markers.map((m) => `${m.node} ${m.name}=${m.value} ${m.successful ? "✓" : "✗"} at t=${fmtR(m.seq * j.ts_s)} s`).join("; ");
  $("capinfo").textContent = `reopened ${j.path}: ${n} messages, samples ${j.seq0}…${j.seq1} ` +
    `(full rate, trigger: ${j.why} at the red line)` + (mk ? `\nmarkers: ${mk}` : "");
  $("trigstate").textContent = `captured: ${j.why}`;
  const a = $("mcap");
  a.hidden = false;
  a.href = `api/capture.mcap?token=${encodeURIComponent(TOKEN)}`;
  a.download = j.path.split("/").pop() + ".mcap";
}

$("arm").addEventListener("click", async () => {
  $("trigstate").textContent = "arming…";
  const body = { trigger: $("trig").value, field: $("trigfield").value, level: $("triglevel").value,
                 pre_s: $("trigpre").value, post_s: $("trigpost").value };
  const r = await fetch("api/trigger", { method: "POST", headers: { "Content-Type": "application/json", "X-Fluxdrive-Token": TOKEN },
                                          body: JSON.stringify(body) });
  const j = await r.json();
  $("trigstate").textContent = j.ok ? j.reason : "refused: " + j.reason;
});

// ------------------------------------------------------------------ export
// the time charts' traces in view (each series' min and max per bucket) as one CSV
function exportCsv() {
  const rows = new Map(), cols = [];
  for (const ch of charts) {
    if (!ch.u || ch.def.kind === "spectrum") continue;
    const d = ch.u.data, [x0, x1] = [ch.u.scales.x.min, ch.u.scales.x.max];
    ch.def.series.forEach((s, j) => {
      const ci = cols.length;
      cols.push(`${ch.def.id}:${s.label}:min`, `${ch.def.id}:${s.label}:max`);
      d[0].forEach((t, i) => {
        if (t < x0 || t > x1) return;
        const key = Number(t.toPrecision(12));
        if (!rows.has(key)) rows.set(key, []);
        const r = rows.get(key);
        r[ci] = d[2 + 2 * j][i]; r[ci + 1] = d[1 + 2 * j][i];
      });
    });
  }
  const lines = ["t_s," + cols.join(",")];
  for (const t of [...rows.keys()].sort((a, b) => a - b)) {
    const r = rows.get(t);
    lines.push(fmt(t) + "," + cols.map((_, i) => (r[i] === null || r[i] === undefined ? "" : fmt(r[i]))).join(","));
  }
  return lines.join("\n") + "\n";
}
window.scopeExportCsv = exportCsv;
$("csv").addEventListener("click", () => {
  const a = document.createElement("a");
  a.href = URL.createObjectURL(new Blob([exportCsv()], { type: "text/csv" }));
  a.download = `scope-${fmtR(stats.simT)}s.csv`;
  document.body.appendChild(a); a.click(); a.remove();
});
$("robust").addEventListener("change", () => { dirty = true; dataDirty = true; for (const c of charts) if (c.u) c.u.redraw(true, true); });

// ------------------------------------------------------------------ instrument
// FFT in Hz, edge trigger and raw export of one trace's full-rate samples: the scope
// server computes (fluxdrive.analysis.instrument); the page asks and draws.
const api = (path, opts = {}) => fetch(path, { ...opts, headers: { "X-Fluxdrive-Token": TOKEN, "Content-Type": "application/json", ...(opts.headers || {}) } });
let traceNames = "";
function updateTraceList() {
  const names = [];
  for (const [s, st] of Object.entries(store)) for (const f of Object.keys(st.f)) names.push(s + ":" + f);
  names.sort();
  const key = names.join(",");
  if (key === traceNames) return;
  traceNames = key;
  const sel = $("itrace"), keep = sel.value;
  sel.innerHTML = names.map((n) => `<option value="${escapeHtml(n)}">${escapeHtml(n)}</option>`).join("");
  if (names.includes(keep)) sel.value = keep;
  else if (names.includes("frame:i_a")) sel.value = "frame:i_a";
}
// the time charts' view [t0, t1] (zoomed, held or scrolling)
function viewSpan() {
  const ch = charts.find((c) => c.u && c.def.kind !== "spectrum" && c.u.scales.x.min !== undefined);
  return ch ? [ch.u.scales.x.min, ch.u.scales.x.max] : null;
}
const spanQuery = (v) => `trace=${encodeURIComponent($("itrace").value)}&t0=${v[0]}&t1=${v[1]}`;

let fft = null, fftChart = null, fftBusy = false, fftView = "";
const fftCur = { a: null, b: null };  // cursor frequencies [Hz]
window.scopeFft = () => fft;          // read by the browser test
window.scopeFftCursors = () => ({ ...fftCur });
window.scopeDebug.view = () => viewSpan();
window.scopeDebug.fftChart = () => fftChart;
function fftAt(f) {  // the nearest bin: [f, amplitude]
  if (!fft) return null;
  const i = Math.max(0, Math.min(fft.f_hz.length - 1, Math.round(f / fft.df_hz)));
  return [fft.f_hz[i], fft.amp[i]];
}
function fftPeak(f0, f1) {  // the highest bin in [f0, f1] (else the nearest): [f, amplitude]
  if (!fft) return null;
  const n = fft.f_hz.length, d = fft.df_hz;
  let lo = Math.max(0, Math.ceil(f0 / d)), hi = Math.min(n - 1, Math.floor(f1 / d));
  if (lo > hi) return fftAt((f0 + f1) / 2);
  let k = lo;
  for (let i = lo + 1; i <= hi; i++) if (fft.amp[i] > fft.amp[k]) k = i;
  return [fft.f_hz[k], fft.amp[k]];
}
function fftReadout() {
  const parts = [];
  const a = fftCur.a !== null ? fftAt(fftCur.a) : null, b = fftCur.b !== null ? fftAt(fftCur.b) : null;
  if (a) parts.push(`A f=${fmtR(a[0])} Hz amp=${fmtR(a[1])}`);
  if (b) parts.push(`B f=${fmtR(b[0])} Hz amp=${fmtR(b[1])}`);
  if (a && b) parts.push(`Δf=${fmtR(b[0] - a[0])} Hz Δamp=${fmtR(b[1] - a[1])}`);
  $("fftcursors").textContent = parts.length ? "FFT: " + parts.join("  ") : "FFT: click: cursor A; shift-click: B";
}
function drawFft() {
  const host = $("fftplot");
  if (!fftChart) {
    fftChart = new uPlot({
      width: Math.max(300, host.clientWidth - 12), height: 180, legend: { show: false },
      scales: { x: { time: false }, y: { range: (u, mn, mx) => [0, (Number.isFinite(mx) ? Math.max(mx, 1e-12) : 1) * 1.1] } },
      axes: [{ size: 28, label: "f [Hz]", labelSize: 14 }, { size: 60 }],
      cursor: { drag: { x: true, y: false } },
      series: [{ label: "f [Hz]" }, { label: "amplitude", stroke: COLORS[0], width: 1, points: { show: false } }],
      hooks: { draw: [(u) => {
        const g = u.ctx, dpr = devicePixelRatio || 1;
        for (const [k, c] of [["a", "#000"], ["b", "#6a1b9a"]]) {
          if (fftCur[k] === null) continue;
          const x = Math.round(u.valToPos(fftCur[k], "x", true));
          g.save(); g.strokeStyle = c; g.lineWidth = dpr;
          g.beginPath(); g.moveTo(x, u.bbox.top); g.lineTo(x, u.bbox.top + u.bbox.height); g.stroke();
          g.fillStyle = c; g.font = `${10 * dpr}px sans-serif`; g.fillText(k.toUpperCase(), x + 3 * dpr, u.bbox.top + 10 * dpr);
          g.restore();
        }
      }] },
    }, [[], []], host);
    fftChart.over.addEventListener("click", (e) => {
      // the highest bin within 3 pixels of the click: a pixel spans several bins
      const f0 = fftChart.posToVal(e.offsetX - 3, "x"), f1 = fftChart.posToVal(e.offsetX + 3, "x");
      const bin = fftPeak(f0, f1);
      if (!bin) return;
      if (e.shiftKey) fftCur.b = bin[0]; else fftCur.a = bin[0];
      fftReadout(); fftChart.redraw(false, false);
    });
  }
  fftChart.setData([fft.f_hz, fft.amp]);
  fftReadout();
}
async function updateFft() {
  if (!$("fften").checked || fftBusy || !$("itrace").value) return;
  const v = viewSpan();
  if (!v || !drawableSpan(v[0], v[1])) return;
  const ac = $("fftac").checked ? 1 : 0;
  const key = `${$("itrace").value} ${$("fftwin").value} ${ac} ${v[0]} ${v[1]}`;
  if (paused() && key === fftView && fft) return;  // a held view: computed once
  fftBusy = true;
  try {
    const r = await api(`api/fft?${spanQuery(v)}&window=${$("fftwin").value}&ac=${ac}`);
    const j = await r.json();
    if (!j.ok) { $("fftinfo").textContent = j.error; return; }
    fft = j; fftView = key;
    let k = 1;
    for (let i = 2; i < j.amp.length; i++) if (j.amp[i] > j.amp[k]) k = i;
    $("fftinfo").textContent = `${j.trace}, ${j.window}${j.ac ? ", AC" : ""}: ${j.n} samples ${fmtR(j.t0_s)}…${fmtR(j.t1_s)} s, ` +
      `bins ${fmtR(j.df_hz)} Hz; peak ${fmtR(j.f_hz[k])} Hz, ${fmtR(j.amp[k])} (${j.scaling})` + (j.gap_cut ? "; cut at a gap" : "");
    drawFft();
  } catch (e) {
    $("fftinfo").textContent = "FFT failed: " + e;
  } finally { fftBusy = false; }
}
setInterval(updateFft, 1000);
$("fften").addEventListener("change", updateFft);
$("fftwin").addEventListener("change", () => { fftView = ""; updateFft(); });
$("fftac").addEventListener("change", () => { fftView = ""; updateFft(); });

let edgeState = null, edgeChart = null, edgeShown = 0, edgeTimer = null;
window.scopeEdge = () => edgeState;  // read by the browser test
$("earm").addEventListener("click", async () => {
  $("estate").textContent = "arming…";
  const body = { trace: $("itrace").value, edge: $("edge").value, level: $("elevel").value,
                 hysteresis: $("ehyst").value, mode: $("emode").value, pre_s: $("epre").value,
                 post_s: $("epost").value, auto_timeout_s: $("eauto").value };
  const r = await api("api/edge", { method: "POST", body: JSON.stringify(body) });
  const j = await r.json();
  $("estate").textContent = j.ok ? j.reason : "refused: " + j.reason;
  edgeShown = 0;
  if (j.ok && !edgeTimer) edgeTimer = setInterval(pollEdge, 500);
});
$("estop").addEventListener("click", async () => {
  await api("api/edge", { method: "POST", body: JSON.stringify({ trace: "" }) });
  clearInterval(edgeTimer); edgeTimer = null;
  await pollEdge();
});
async function pollEdge() {
  const r = await api("api/edge");
  const j = await r.json();
  edgeState = j;
  const c = j.config || {};
  const last = j.events.length ? j.events[j.events.length - 1] : null;
  $("estate").textContent = !j.set ? "not set" :
    `${j.stopped ? "stopped" : j.armed ? "armed" : "done"} (${c.mode}, ${c.edge} ${c.trace} through ${c.level} ± ${c.hysteresis}): fired ${j.fired}` +
    (last ? `; #${last.n} at t=${fmtR(last.t_s)} s (${last.auto ? "auto: no edge within the timeout" : "edge"})` : "");
  if (last && last.n !== edgeShown) { edgeShown = last.n; drawEdge(last, c); }
}
function drawEdge(ev, c) {
  const host = $("edgeplot");
  host.innerHTML = "";
  edgeChart = new uPlot({
    width: Math.max(300, host.clientWidth - 12), height: 150, legend: { show: false },
    scales: { x: { time: false } }, axes: [{ size: 28, values: (u, vs) => vs.map((v) => v.toFixed(4)) }, { size: 52 }],
    series: [{ label: "t [s]" }, { label: c.trace, stroke: COLORS[0], width: 1, points: { show: ev.t.length < 200 } }],
    hooks: { draw: [(u) => {
      const g = u.ctx, x = Math.round(u.valToPos(ev.t_s, "x", true)), y = Math.round(u.valToPos(c.level, "y", true));
      g.save(); g.strokeStyle = "#c62828"; g.setLineDash([5, 3]);
      g.beginPath(); g.moveTo(x, u.bbox.top); g.lineTo(x, u.bbox.top + u.bbox.height);
      g.moveTo(u.bbox.left, y); g.lineTo(u.bbox.left + u.bbox.width, y); g.stroke(); g.restore();
    }] },
  }, [ev.t, ev.v], host);
}

async function rawExport(kind) {
  const v = viewSpan();
  if (!v || !$("itrace").value) return;
  window.scopeRawView = v;  // read by the browser test
  $("rawmsg").textContent = `waiting for every sample of ${fmtR(v[0])}…${fmtR(v[1])} s…`;
  const r = await fetch(`api/raw.${kind}?${spanQuery(v)}`, { headers: { "X-Fluxdrive-Token": TOKEN } });
  if (!r.ok) {
    const j = await r.json().catch(() => ({ error: r.statusText }));
    $("rawmsg").textContent = j.error || j.reason || r.statusText;
    return;
  }
  const blob = await r.blob();
  const name = (r.headers.get("Content-Disposition") || "").match(/filename="([^"]+)"/);
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = name ? name[1] : `scope-raw.${kind}`;
  document.body.appendChild(a); a.click(); a.remove();
  $("rawmsg").textContent = `${a.download}: the view ${fmtR(v[0])}…${fmtR(v[1])} s, ${blob.size} bytes`;
}
$("rawcsv").addEventListener("click", () => rawExport("csv"));
$("rawmcap").addEventListener("click", () => rawExport("mcap"));

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
