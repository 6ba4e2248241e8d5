// arlight's browser display: numbers from /events (Server-Sent Events), the composite from
// /stream.mjpeg (an <img>), and a sphere shaded by the estimated light. Every update is also
// written into <body data-*> so that tests (headless Chromium) can read the page's state.
"use strict";

// Real SH without the Condon-Shortley phase, index l(l+1)+m (pipeline/sh.py), bands 0..2,
// convolved with the clamped cosine (Ramamoorthi-Hanrahan: A0 = pi, A1 = 2pi/3, A2 = pi/4).
function irradiance(sh, x, y, z) {
  const c = (i) => (i < sh.length ? sh[i] : 0);
  const a0 = Math.PI, a1 = 2 * Math.PI / 3, a2 = Math.PI / 4;
  return a0 * 0.282095 * c(0)
    + a1 * 0.488603 * (y * c(1) + z * c(2) + x * c(3))
    + a2 * (1.092548 * (x * y * c(4) + y * z * c(5) + x * z * c(7))
            + 0.315392 * (3 * z * z - 1) * c(6) + 0.546274 * (x * x - y * y) * c(8));
}

function drawSphere(canvas, sh, dir) {
  const g = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, r = Math.min(w, h) / 2 - 14;
  const cx = w / 2, cy = h / 2;
  const img = g.createImageData(w, h);
  const values = new Float32Array(w * h);
  let peak = 1e-9;
  for (let py = 0; py < h; py++) {
    for (let px = 0; px < w; px++) {
      const x = (px - cx) / r, y = (py - cy) / r, q = 1 - x * x - y * y;
      if (q < 0) { values[py * w + px] = -1; continue; }
      // camera axes: x right, y down; the sphere's visible side faces the camera (-z)
      const e = Math.max(irradiance(sh, x, y, -Math.sqrt(q)), 0);
      values[py * w + px] = e;
      peak = Math.max(peak, e);
    }
  }
  for (let i = 0; i < w * h; i++) {
    const v = values[i];
    const k = i * 4;
    if (v < 0) { img.data[k + 3] = 0; continue; }
    const s = Math.round(255 * Math.pow(v / peak, 1 / 2.2));  // white Lambertian, display gamma
    img.data[k] = s; img.data[k + 1] = s; img.data[k + 2] = s; img.data[k + 3] = 255;
  }
  g.clearRect(0, 0, w, h);
  g.putImageData(img, 0, 0);
  if (!dir) return;
  // the dominant direction seen from the camera: solid towards the viewer, dashed behind
  const ex = cx + dir[0] * (r + 10), ey = cy + dir[1] * (r + 10);
  g.strokeStyle = "#ffd166"; g.fillStyle = "#ffd166"; g.lineWidth = 3;
  g.setLineDash(dir[2] > 0 ? [6, 4] : []);
  g.beginPath(); g.moveTo(cx, cy); g.lineTo(ex, ey); g.stroke();
  g.setLineDash([]);
  g.beginPath(); g.arc(ex, ey, 6, 0, 2 * Math.PI); g.fill();
}

function text(id, value) { document.getElementById(id).textContent = value; }

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
  drawSphere(document.getElementById("sphere"), state.sh_camera, d);
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
