// OBU live view: draws each tick's state (GET /api/state, pushed over /ws) on a canvas.
// Live: follows the OBU.  Replay (captures view): play, pause, speed, slider, warnings.
"use strict";

const MODE = document.body.dataset.mode;
const canvas = document.getElementById("map");
const ctx = canvas.getContext("2d");
const LANE = 3.6;
const COLORS = { centre: "#d62728", left: "#1f77b4", right: "#2ca02c", behind: "#9da5ad",
                 oncoming: "#9467bd", other: "#8c8c8c" };
// a track whose latest message is not verified (verify on demand): hollow, dashed, amber
const UNVERIFIED = "#ff7f0e";
let state = null;
let scale = 7;            // px per metre
let pan = { x: 0, y: 0 }; // screen offset, px
let fps = 0, lastT = null, frames = 0, fpsT = performance.now();

function zoneColor(z) {
  const [ahead, lateral, direction] = z;
  if (direction === 1) return COLORS.oncoming;
  if (!ahead) return COLORS.behind;
  if (lateral === 2) return COLORS.centre;
  if (lateral < 2) return COLORS.left;
  if (lateral > 2) return COLORS.right;
  return COLORS.other;
}

function resize() {
  const r = canvas.getBoundingClientRect();
  canvas.width = Math.max(1, Math.round(r.width * devicePixelRatio));
  canvas.height = Math.max(1, Math.round(r.height * devicePixelRatio));
  draw();
}

// world (ENU m) -> screen px: centred on the host, host heading up in the host frame
function view() {
  const hf = document.getElementById("hostframe").checked;
  const h = state && state.host ? state.host : { x: 0, y: 0, heading: 0 };
  const a = hf ? h.heading * Math.PI / 180 : 0;
  const c = Math.cos(a), s = Math.sin(a);
  const k = scale * devicePixelRatio;
  const W = canvas.width, H = canvas.height;
  const ox = W / 2 + pan.x * devicePixelRatio, oy = H * 0.62 + pan.y * devicePixelRatio;
  return {
    a, k, ox, oy, hx: h.x, hy: h.y,
    p(x, y) {
      const dx = x - h.x, dy = y - h.y;
      return [ox + k * (dx * c - dy * s), oy - k * (dx * s + dy * c)];
    },
  };
}

function box(v, x, y, headingDeg, len, wid, fill, stroke, lw) {
  const [sx, sy] = v.p(x, y);
  ctx.save();
  ctx.translate(sx, sy);
  ctx.rotate(headingDeg * Math.PI / 180 - v.a);
  const L = len * v.k, Wd = wid * v.k;
  ctx.beginPath();
  ctx.roundRect ? ctx.roundRect(-Wd / 2, -L / 2, Wd, L, Math.min(Wd, L) * 0.2)
                : ctx.rect(-Wd / 2, -L / 2, Wd, L);
  if (fill) { ctx.fillStyle = fill; ctx.fill(); }
  if (stroke) { ctx.strokeStyle = stroke; ctx.lineWidth = lw || 2; ctx.stroke(); }
  ctx.restore();
  return [sx, sy];
}

// points of the host path (arc of the host's radius), at lateral offset d (m, right +)
function pathPoints(h, d, from, to) {
  const pts = [];
  const R = h.radius;
  for (let s = from; s <= to; s += 4) {
    let hd = h.heading * Math.PI / 180, x = h.x, y = h.y;
    if (R && isFinite(R)) {
      const a = s / R;   // clockwise turn for R > 0
      x = h.x + R * (Math.cos(hd) - Math.cos(hd + a)) ;
      y = h.y + R * (Math.sin(hd + a) - Math.sin(hd));
      hd += a;
    } else {
      x = h.x + s * Math.sin(hd);
      y = h.y + s * Math.cos(hd);
    }
    pts.push([x + d * Math.cos(hd), y - d * Math.sin(hd)]);
  }
  return pts;
}

function polyline(v, pts, color, width, dash) {
  ctx.beginPath();
  pts.forEach(([x, y], i) => { const [sx, sy] = v.p(x, y); i ? ctx.lineTo(sx, sy) : ctx.moveTo(sx, sy); });
  ctx.strokeStyle = color; ctx.lineWidth = width; ctx.setLineDash(dash || []);
  ctx.stroke(); ctx.setLineDash([]);
}

function draw() {
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#fbfbfc";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  if (!state || !state.host) return;
  const v = view();
  const h = state.host;
  // road: five lanes around the host's path, the host's lane shaded
  const reach = Math.max(canvas.width, canvas.height) / v.k;
  const from = -reach * 0.6, to = reach;
  ctx.globalAlpha = 0.35;
  polyline(v, pathPoints(h, 0, from, to), "#e9ecef", LANE * v.k);
  ctx.globalAlpha = 1;
  for (const d of [-2.5, -1.5, -0.5, 0.5, 1.5, 2.5]) {
    polyline(v, pathPoints(h, d * LANE, from, to), Math.abs(d) === 2.5 ? "#9aa3ab" : "#c3c9cf",
             1.2, Math.abs(d) === 2.5 ? [] : [8, 8]);
  }
  // the host's predicted path to its pose at the horizon
  if (h.pred) {
    polyline(v, [[h.x, h.y], h.pred], "#333", 1.5, [4, 4]);
    const [px, py] = v.p(h.pred[0], h.pred[1]);
    ctx.strokeStyle = "#333"; ctx.lineWidth = 1.5;
    ctx.beginPath(); ctx.arc(px, py, 4, 0, 2 * Math.PI); ctx.stroke();
  }
  const warned = new Map(state.warnings.map(w => [w[1], w]));
  // true positions (replay with the RVE's ground truth)
  if (document.getElementById("showtruth").checked) {
    for (const tr of state.truth || []) {
      const [sx, sy] = v.p(tr.x, tr.y);
      ctx.setLineDash([3, 3]); ctx.strokeStyle = "#444"; ctx.lineWidth = 1;
      ctx.beginPath(); ctx.arc(sx, sy, Math.max(4, 1.2 * v.k), 0, 2 * Math.PI); ctx.stroke();
      ctx.setLineDash([]);
    }
  }
  let drawn = 0, doubtful = 0;
  const unverified = new Set(state.unverified || []);
  ctx.font = `${11 * devicePixelRatio}px system-ui, sans-serif`;
  for (const r of state.rvs) {
    const color = zoneColor(r.zone);
    // predicted position at the horizon
    const [cx, cy] = v.p(r.x, r.y);
    const [qx, qy] = v.p(r.px, r.py);
    ctx.strokeStyle = color; ctx.lineWidth = 1; ctx.globalAlpha = 0.6;
    ctx.beginPath(); ctx.moveTo(cx, cy); ctx.lineTo(qx, qy); ctx.stroke();
    ctx.beginPath(); ctx.arc(qx, qy, 3 * devicePixelRatio, 0, 2 * Math.PI);
    ctx.fillStyle = zoneColor(r.pzone); ctx.fill();
    ctx.globalAlpha = 1;
    if (unverified.has(r.id)) {  // no application sees it: never filled
      ctx.setLineDash([4, 3]);
      box(v, r.x, r.y, r.heading, 4.8, 1.9, null, UNVERIFIED, 2.5);
      ctx.setLineDash([]);
      doubtful++;
    } else {
      box(v, r.x, r.y, r.heading, 4.8, 1.9, r.fresh ? color : null, r.fresh ? null : color,
          2.5);
    }
    if (warned.has(r.id)) {
      ctx.strokeStyle = "#d62728"; ctx.lineWidth = 3 * devicePixelRatio;
      ctx.beginPath(); ctx.arc(cx, cy, Math.max(14, 4 * v.k), 0, 2 * Math.PI); ctx.stroke();
    }
    ctx.fillStyle = "#333";
    const label = r.id.slice(-4) + (r.fresh ? "" : ` +${r.age.toFixed(1)}s`) +
      (unverified.has(r.id) ? " unverified" : "");
    ctx.fillText(label, cx + 8 * devicePixelRatio, cy - 8 * devicePixelRatio);
    drawn++;
  }
  box(v, h.x, h.y, h.heading, h.length || 4.8, h.width || 1.9, "#1d2733", null);
  canvas.dataset.rvs = String(drawn);
  canvas.dataset.unverified = String(doubtful);
  canvas.dataset.t = state.t == null ? "" : String(state.t);
  // scale bar
  const m = [5, 10, 20, 50, 100, 200].find(x => x * v.k > 80) || 200;
  ctx.fillStyle = "#333"; ctx.fillRect(16, canvas.height - 24, m * v.k, 3);
  ctx.fillText(`${m} m`, 16, canvas.height - 30);
}

function panel() {
  const p = state.panel || {};
  const rows = [
    ["time", state.t == null ? "–" : `${state.t.toFixed(1)} s`],
    ["tracked RVs", state.rvs.length],
    ["predicted now", state.rvs.filter(r => !r.fresh).length],
    ["unverified tracks", (state.unverified || []).length],
    ["frames/s", p.frames_per_s ?? "–"],
    ["decode errors", p.decode_errors ?? 0],
    ["security rejections", p.rejected ?? 0],
    ["tick p50 ms", p.tick_p50 ?? p.tick_ms ?? "–"],
    ["tick p99 ms", p.tick_p99 ?? "–"],
    ["deadline misses", p.deadline_misses ?? 0],
    ["views pushed/s", fps.toFixed(0)],
  ];
  // as text: a capture's strings (captures view) are data, never HTML
  document.getElementById("panel").replaceChildren(...rows.map(([k, val]) => {
    const tr = document.createElement("tr");
    for (const cell of [k, val]) {
      const td = document.createElement("td");
      td.textContent = String(cell);
      tr.appendChild(td);
    }
    return tr;
  }));
  const b = document.getElementById("banner");
  if (state.warnings.length) {
    b.textContent = state.warnings.map(([app, id, range, thr]) =>
      `${app.toUpperCase()} · RV ${id} · range ${range} m` +
      (thr == null ? "" : ` (threshold ${thr} m)`)).join("   |   ");
    b.classList.remove("hidden");
  } else {
    b.classList.add("hidden");
  }
  document.getElementById("clock").textContent =
    state.t == null ? "t = –" : `t = ${state.t.toFixed(1)} s`;
}

function show(s) {
  state = s;
  frames++;
  const now = performance.now();
  if (now - fpsT > 1000) { fps = frames * 1000 / (now - fpsT); frames = 0; fpsT = now; }
  draw();
  panel();
}

// mouse: drag to pan, wheel to zoom
let drag = null;
canvas.addEventListener("mousedown", e => { drag = [e.clientX, e.clientY]; canvas.style.cursor = "grabbing"; });
window.addEventListener("mouseup", () => { drag = null; canvas.style.cursor = "grab"; });
window.addEventListener("mousemove", e => {
  if (!drag) return;
  pan.x += e.clientX - drag[0]; pan.y += e.clientY - drag[1];
  drag = [e.clientX, e.clientY]; draw();
});
canvas.addEventListener("wheel", e => {
  e.preventDefault();
  scale = Math.min(60, Math.max(0.2, scale * Math.exp(-e.deltaY * 0.0015)));
  draw();
}, { passive: false });
document.getElementById("fit").onclick = () => { pan = { x: 0, y: 0 }; scale = 7; draw(); };
document.getElementById("hostframe").onchange = draw;
document.getElementById("showtruth").onchange = draw;
window.addEventListener("resize", resize);

function live() {
  const status = document.getElementById("status");
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const ws = new WebSocket(`${proto}://${location.host}/ws`);
  ws.onopen = () => { status.textContent = "live"; };
  ws.onmessage = ev => show(JSON.parse(ev.data));
  ws.onclose = () => { status.textContent = "disconnected, retrying…"; setTimeout(live, 1000); };
}

async function replay() {
  document.getElementById("replay").classList.remove("hidden");
  const status = document.getElementById("status");
  const index = await (await fetch("api/ticks")).json();
  const slider = document.getElementById("slider");
  slider.max = Math.max(0, index.ticks - 1);
  status.textContent = `replay: ${index.ticks} ticks`;
  let playing = false, timer = null;
  const go = async i => {
    slider.value = i;
    document.getElementById("tickno").textContent = `tick ${i} of ${index.ticks}`;
    show(await (await fetch(`api/state?tick=${i}`)).json());
  };
  slider.oninput = () => go(+slider.value);
  const list = document.getElementById("warnlist");
  for (const e of index.events) {
    const li = document.createElement("li");
    li.textContent = `${e.app.toUpperCase()} RV ${e.rv} at ${e.t.toFixed(1)} s`;
    li.onclick = () => {
      let best = 0;
      index.t.forEach((t, i) => { if (Math.abs(t - e.t) < Math.abs(index.t[best] - e.t)) best = i; });
      go(best);
    };
    list.appendChild(li);
  }
  const step = () => {
    if (!playing) return;
    const i = +slider.value + 1;
    if (i >= index.ticks) { playing = false; document.getElementById("play").textContent = "play"; return; }
    go(i).then(() => { timer = setTimeout(step, 100 / +document.getElementById("speed").value); });
  };
  document.getElementById("play").onclick = () => {
    playing = !playing;
    document.getElementById("play").textContent = playing ? "pause" : "play";
    clearTimeout(timer); step();
  };
  go(0);
}

// for tests: the transform's parameters (the pixels are checked against them)
window.liveView = { view };

resize();
if (MODE === "replay") replay(); else live();
