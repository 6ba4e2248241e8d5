// arlight's browser display: numbers from /events (Server-Sent Events), the composite from
// /stream.mjpeg (an <img>), a sphere lit by the estimated light as an engine would shade it,
// the confidence with its reason, and small plots of figures that need no ground truth
// (latency, confidence, light direction) over the last HISTORY Results. Every update is also
// written into <body data-*> so that tests (headless Chromium) can read the page's state.
"use strict";

const HISTORY = 120;  // Results kept for the plots

// Real SH without the Condon-Shortley phase, index l(l+1)+m (pipeline/sh.py), bands 0..2,
// convolved with the clamped cosine (Ramamoorthi-Hanrahan: A0 = pi, A1 = 2pi/3, A2 = pi/4):
// E(n), the irradiance on a surface facing n.
function irradiance(sh, x, y, z) {
  const c = (i) => (i < sh.length ? sh[i] : 0);
  const a0 = Math.PI, a1 = 2 * Math.PI / 3, a2 = Math.PI / 4;
  return a0 * 0.282095 * c(0)
    + a1 * 0.488603 * (y * c(1) + z * c(2) + x * c(3))
    + a2 * (1.092548 * (x * y * c(4) + y * z * c(5) + x * z * c(7))
            + 0.315392 * (3 * z * z - 1) * c(6) + 0.546274 * (x * x - y * y) * c(8));
}

// Linear [0, 1] -> 8-bit sRGB (IEC 61966-2-1), clipped: the camera image's own encoding.
function srgb8(v) {
  const x = Math.min(Math.max(v, 0), 1);
  const e = x <= 0.0031308 ? 12.92 * x : 1.055 * Math.pow(x, 1 / 2.4) - 0.055;
  return Math.round(255 * e);
}

// The sphere as the camera would see a surface of the scene's albedo under the light: the
// estimate absorbs the albedo (I = a T l), so a pixel's linear value is E(n) in the units
// of the camera's linear image; no normalisation to the peak (a dim light looks dim, a
// bright one clips). Returns the peak linear value drawn.
function drawSphere(canvas, sh, dir) {
  const g = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, r = Math.min(w, h) / 2 - 14;
  const cx = w / 2, cy = h / 2;
  const img = g.createImageData(w, h);
  let peak = 0;
  for (let py = 0; py < h; py++) {
    for (let px = 0; px < w; px++) {
      const x = (px - cx) / r, y = (py - cy) / r, q = 1 - x * x - y * y;
      const k = (py * w + px) * 4;
      if (q < 0) { img.data[k + 3] = 0; continue; }
      // camera axes: x right, y down; the sphere's visible side faces the camera (-z)
      const e = Math.max(irradiance(sh, x, y, -Math.sqrt(q)), 0);
      peak = Math.max(peak, e);
      const s = srgb8(e);
      img.data[k] = s; img.data[k + 1] = s; img.data[k + 2] = s; img.data[k + 3] = 255;
    }
  }
  g.clearRect(0, 0, w, h);
  g.putImageData(img, 0, 0);
  g.strokeStyle = "#555"; g.lineWidth = 1;
  g.beginPath(); g.arc(cx, cy, r, 0, 2 * Math.PI); g.stroke();  // the outline, even if black
  if (!dir) return peak;
  // the dominant direction seen from the camera: solid towards the viewer, dashed behind
  const ex = cx + dir[0] * (r + 10), ey = cy + dir[1] * (r + 10);
  g.strokeStyle = "#ffd166"; g.fillStyle = "#ffd166"; g.lineWidth = 3;
  g.setLineDash(dir[2] > 0 ? [6, 4] : []);
  g.beginPath(); g.moveTo(cx, cy); g.lineTo(ex, ey); g.stroke();
  g.setLineDash([]);
  g.beginPath(); g.arc(ex, ey, 6, 0, 2 * Math.PI); g.fill();
  return peak;
}

// One small line plot: series = [{values, color}], y from lo to hi (null: the data's range).
function drawPlot(canvas, series, lo, hi) {
  const rect = canvas.getBoundingClientRect();
  if (rect.width > 0) canvas.width = Math.round(rect.width);  // crisp at the panel's width
  const g = canvas.getContext("2d"), w = canvas.width, h = canvas.height, pad = 4;
  g.clearRect(0, 0, w, h);
  g.fillStyle = "#1b1d21"; g.fillRect(0, 0, w, h);
  const all = series.flatMap((s) => s.values);
  if (!all.length) return [0, 0];
  let a = lo === null ? Math.min(...all) : lo, b = hi === null ? Math.max(...all) : hi;
  if (b - a < 1e-9) { a -= 1; b += 1; }
  g.strokeStyle = "#333"; g.lineWidth = 1;
  if (a < 0 && b > 0) {  // the zero line
    const y0 = h - pad - (0 - a) / (b - a) * (h - 2 * pad);
    g.beginPath(); g.moveTo(0, y0); g.lineTo(w, y0); g.stroke();
  }
  for (const s of series) {
    g.strokeStyle = s.color; g.lineWidth = 2; g.beginPath();
    s.values.forEach((v, i) => {
      const x = pad + (i / Math.max(HISTORY - 1, 1)) * (w - 2 * pad);
      const y = h - pad - (v - a) / (b - a) * (h - 2 * pad);
      if (i === 0) g.moveTo(x, y); else g.lineTo(x, y);
    });
    g.stroke();
  }
  return [a, b];
}

function text(id, value) { document.getElementById(id).textContent = value; }

const history = [];  // {latency, confidence, direction} of the last HISTORY Results

function remember(state) {
  const last = history[history.length - 1];
  if (last && last.frame === state.frame) return;  // the same Result again (a reconnect)
  history.push({
    frame: state.frame,
    latency: state.latency_ms,
    confidence: state.confidence,
    direction: state.dominant_direction_camera,
  });
  if (history.length > HISTORY) history.shift();
}

function drawPlots() {
  const [a, b] = drawPlot(document.getElementById("plot-latency"),
    [{ values: history.map((s) => s.latency), color: "#ffd166" }], 0, null);
  text("latency-range", a.toFixed(0) + ".." + b.toFixed(0) + " ms");
  drawPlot(document.getElementById("plot-confidence"),
    [{ values: history.map((s) => s.confidence), color: "#06d6a0" }], 0, 1);
  drawPlot(document.getElementById("plot-direction"), ["#ef476f", "#06d6a0", "#118ab2"].map(
    (color, k) => ({ values: history.map((s) => s.direction[k]), color })), -1, 1);
  text("history", String(history.length));
  document.body.dataset.plotPoints = String(history.length);
}

function show(state) {
  const body = document.body;
  body.dataset.updates = String(Number(body.dataset.updates) + 1);
  body.dataset.results = String(state.results);
  if (!state.results) { text("status", "waiting for results"); return; }
  text("status", "live");
  text("session", state.session);
  text("fps", state.fps.toFixed(1));
  text("latency", state.latency_ms.toFixed(0));
  text("latency-kind", state.latency_kind === "end_to_end" ? "(end to end)"
                                                           : "(server receive to display)");
  text("confidence", state.confidence.toFixed(2));
  text("confidence-value", state.confidence.toFixed(2));
  const reason = (state.confidence_detail && state.confidence_detail.reason) || "";
  const why = document.getElementById("confidence-reason");
  why.textContent = reason || "no reason given (not low)";
  why.className = reason ? "low" : "muted";
  body.dataset.reason = reason;
  text("frame", state.frame);
  text("results", state.results);
  text("dropped", state.frames_dropped);
  text("pipeline", state.pipeline_ms === null ? "-" : state.pipeline_ms.toFixed(1));
  const d = state.dominant_direction_camera;
  text("direction", "(" + d.map((v) => v.toFixed(2)).join(", ") + ")");
  const table = document.getElementById("timings");
  table.replaceChildren(...Object.entries(state.timings_ms).map(([k, v]) => {
    const row = document.createElement("tr");
    row.innerHTML = "<td></td><td class='n'></td>";
    row.cells[0].textContent = k; row.cells[1].textContent = v.toFixed(1);
    return row;
  }));
  const peak = drawSphere(document.getElementById("sphere"), state.sh_camera, d);
  text("peak", peak.toFixed(3));
  body.dataset.spherePeak = String(peak);
  remember(state);
  drawPlots();
  body.dataset.frame = String(state.frame);
  body.dataset.fps = String(state.fps);
  body.dataset.latency = String(state.latency_ms);
  const seen = (body.dataset.framesSeen || "").split(",").filter(Boolean);
  if (seen[seen.length - 1] !== String(state.frame)) seen.push(String(state.frame));
  body.dataset.framesSeen = seen.slice(-50).join(",");
}

const composite = document.getElementById("composite");
composite.addEventListener("load", () => {
  document.body.dataset.imageWidth = String(composite.naturalWidth);
});
const events = new EventSource("/events");
events.onmessage = (e) => show(JSON.parse(e.data));
events.onerror = () => text("status", "reconnecting");
