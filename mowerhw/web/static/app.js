// mowerhw status page: a plan view of the map with the live pose, and the daemon's decision.
// Plain JavaScript, no build step, no library: the mower serves it as it is.
"use strict";

const $ = (id) => document.getElementById(id);
const state = {
  map: null, mapVersion: "", traj: [], session: "", landmarks: [], live: null,
  updates: 0, ws: null, retry: 1000,
};

// ------------------------------------------------------------------------- the stream

function connect() {
  const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
  const ws = new WebSocket(url);
  state.ws = ws;
  ws.onopen = () => {
    state.retry = 1000;
    state.traj = []; // the server sends the whole trajectory to every new connection
    setConnection(true, "live");
  };
  ws.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.type === "live") onLive(msg);
  };
  ws.onclose = () => {
    setConnection(false, "reconnecting…");
    setTimeout(connect, state.retry);
    state.retry = Math.min(5000, state.retry * 2);
  };
}

function setConnection(on, text) {
  const el = $("connection");
  el.textContent = text;
  el.className = "badge " + (on ? "on" : "off");
  document.body.dataset.connected = on ? "true" : "false";
}

function onLive(msg) {
  if (msg.session !== state.session) { state.session = msg.session; state.traj = []; state.landmarks = []; }
  const tr = msg.trajectory;
  if (tr) {
    state.traj.push(...tr.points);
    if (state.traj.length > 40000) state.traj.splice(0, state.traj.length - 40000);
  }
  if (msg.landmarks) state.landmarks = msg.landmarks;
  if (msg.map_version !== state.mapVersion) {
    state.mapVersion = msg.map_version;
    loadMap();
  }
  state.live = msg;
  state.updates += 1;
  document.body.dataset.points = state.traj.length;
  $("updates").textContent = state.updates;
  $("error").hidden = !msg.error;
  $("error").textContent = msg.error || "";
  const d = msg.daemon;
  if (d) showDaemon(d);
  draw();
}

async function loadMap() {
  try {
    const r = await fetch("/api/map", { cache: "no-store" });
    const body = await r.json();
    state.map = r.ok ? body : null;
    $("map-info").textContent = r.ok
      ? `${body.area_m2} m², ${body.landmarks.length} landmarks` : body.error;
    showAreas();
  } catch (e) {
    $("map-info").textContent = "unreadable (" + e + ")";
  }
  draw();
}

// ------------------------------------------------------------------------------ panel

const fmt = (v, n) => (v === null || v === undefined ? "–" : Number(v).toFixed(n));

function showDaemon(d) {
  document.body.dataset.now = d.now;
  document.body.dataset.state = d.state;
  // the permit supervisor sends the frames: its own halt (tilt, a bump, a late estimator,
  // its CAN address) stops the deck whatever the estimation side decided
  const sup = d.supervisor;
  const supHalt = Boolean(d.permit && sup && sup.permit === false);
  const permit = Boolean(d.permit) && !supHalt;
  document.body.dataset.permit = permit;
  $("mode").textContent = d.mode;
  const p = $("permit");
  p.textContent = permit ? "MOWING PERMITTED" : "HALT";
  p.className = "badge " + (permit ? "permit" : "halt");
  $("state").textContent = d.state;
  $("reason").textContent = permit ? "–" : supHalt ? sup.reason : d.reason;
  $("detail").textContent = supHalt ? `permit supervisor: ${sup.detail || sup.reason}` : d.detail || "–";
  $("distance").textContent = d.signed_distance_m === null ? "–" : fmt(d.signed_distance_m, 2) + " m inside";
  const pose = d.pose;
  $("pose-x").textContent = pose ? fmt(pose.x, 3) : "–";
  $("pose-y").textContent = pose ? fmt(pose.y, 3) : "–";
  $("pose-heading").textContent = pose ? fmt((pose.heading * 180) / Math.PI, 1) : "–";
  $("sigma").textContent = pose && pose.sigma_xy_m !== null ? fmt(pose.sigma_xy_m * 100, 1) + " cm" : "–";
  $("sigma-heading").textContent =
    pose && pose.sigma_heading !== null ? fmt((pose.sigma_heading * 180) / Math.PI, 2) + "°" : "–";
  const loc = d.localizer;
  $("localizer").textContent = loc
    ? `${loc.localized ? "localized" : "not localized"} · searches ${loc.searches} · found ${loc.relocalizations}` +
      (loc.compass_deg === undefined ? "" : " · compass " +
        (loc.compass_deg === null ? "–" : `${fmt(loc.compass_deg[0], 0)}° ± ${fmt(loc.compass_deg[1], 0)}°`))
    : "–";
  const rows = Object.entries(d.sensors || {}).map(([name, s]) => {
    const late = s.late; // as the permit gate judges it (its limit: s.limit_s)
    return `<tr><td>${name}</td><td>${s.rate_hz === null ? "–" : fmt(s.rate_hz, 1) + " Hz"}</td>` +
      `<td class="${late ? "late" : ""}" title="limit ${s.limit_s} s">${s.age_s === null ? "never" : fmt(s.age_s * 1000, 0) + " ms"}</td></tr>`;
  });
  $("sensors").tBodies[0].innerHTML = rows.join("");
  const t = d.teach;
  $("teach-panel").hidden = !t;
  if (t) {
    $("teach-state").textContent = t.phase ? `${t.state} (${t.phase})` : t.state || "–";
    $("teach-distance").textContent = t.distance_m === undefined ? "–" : fmt(t.distance_m, 1) + " m";
    $("teach-landmarks").textContent = t.landmarks === undefined ? (t.landmarks_kept ?? "–") : t.landmarks;
    $("teach-loop").textContent = loopText(t);
  }
}

function loopText(t) {
  if (t.loop_closure) {
    const area = t.area_m2 === undefined ? "" : ` — ${fmt(t.area_m2, 1)} m²`;
    return t.loop_closure + area;
  }
  if (t.state && t.state.startsWith("failed")) return t.state;
  return t.state === "recording" ? "after the drive" : "–";
}

function showAreas() {
  const box = $("areas");
  box.innerHTML = "";
  if (!state.map) return;
  for (const name of state.map.mow_areas) {
    const label = document.createElement("label");
    const input = document.createElement("input");
    input.type = "checkbox"; input.value = name; input.checked = true;
    label.append(input, " " + name + " ");
    box.append(label);
  }
}

// --------------------------------------------------------------------------- controls

async function send(cmd) {
  const body = { cmd };
  if (cmd === "mow" && state.map) {
    const boxes = [...document.querySelectorAll("#areas input")];
    const chosen = boxes.filter((b) => b.checked).map((b) => b.value);
    if (chosen.length && chosen.length < boxes.length) body.areas = chosen;
  }
  const token = $("token").value.trim();
  sessionStorage.setItem("mowerhw-token", token);
  const headers = { "Content-Type": "application/json" };
  if (token) headers.Authorization = "Bearer " + token;
  try {
    const r = await fetch("/api/command", { method: "POST", headers, body: JSON.stringify(body) });
    const reply = await r.json();
    $("reply").textContent = `${cmd}: ${r.status} ${reply.ok ? "done" : reply.error}`;
  } catch (e) {
    $("reply").textContent = `${cmd}: ${e}`;
  }
}

// ---------------------------------------------------------------------------- drawing

function bounds() {
  const xs = [], ys = [];
  const add = (x, y) => { xs.push(x); ys.push(y); };
  if (state.map) {
    for (const a of state.map.areas) for (const [x, y] of a.polygon) add(x, y);
    add(state.map.dock.x, state.map.dock.y);
    for (const l of state.map.landmarks) add(l[1], l[2]);
  }
  for (const [, x, y] of state.traj) add(x, y);
  for (const l of state.landmarks) add(l[1], l[2]);
  const pose = state.live && state.live.daemon && state.live.daemon.pose;
  if (pose) add(pose.x, pose.y);
  if (!xs.length) return { x0: -5, x1: 5, y0: -5, y1: 5 };
  return { x0: Math.min(...xs) - 1, x1: Math.max(...xs) + 1, y0: Math.min(...ys) - 1, y1: Math.max(...ys) + 1 };
}

function draw() {
  const cv = $("plan");
  const dpr = window.devicePixelRatio || 1;
  const w = cv.clientWidth, h = cv.clientHeight;
  if (cv.width !== w * dpr || cv.height !== h * dpr) { cv.width = w * dpr; cv.height = h * dpr; }
  const g = cv.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  const b = bounds();
  const s = Math.min(w / (b.x1 - b.x0), h / (b.y1 - b.y0));
  const ox = (w - s * (b.x1 - b.x0)) / 2, oy = (h - s * (b.y1 - b.y0)) / 2;
  const X = (x) => ox + s * (x - b.x0), Y = (y) => h - oy - s * (y - b.y0); // y north = up
  const poly = (pts, fill, stroke, dash) => {
    if (!pts.length) return;
    g.beginPath();
    pts.forEach(([x, y], i) => (i ? g.lineTo(X(x), Y(y)) : g.moveTo(X(x), Y(y))));
    g.closePath();
    if (fill) { g.fillStyle = fill; g.fill(); }
    g.setLineDash(dash || []); g.strokeStyle = stroke; g.lineWidth = 1.5; g.stroke(); g.setLineDash([]);
  };
  grid(g, b, X, Y, w, h);
  const m = state.map;
  if (m) {
    for (const a of m.areas) poly(a.polygon, a.kind === "mow" ? "#bfe3b4" : "#dde3e8", a.kind === "mow" ? "#3d7a33" : "#7d8b96");
    for (const k of m.keepouts) poly(k.polygon, "#f3c1bd", "#b3261e");
    for (const p of m.paths) {
      g.beginPath(); p.forEach(([x, y], i) => (i ? g.lineTo(X(x), Y(y)) : g.moveTo(X(x), Y(y))));
      g.setLineDash([6, 4]); g.strokeStyle = "#7d8b96"; g.stroke(); g.setLineDash([]);
    }
    g.fillStyle = "#6a3d9a";
    for (const [, x, y] of m.landmarks) g.fillRect(X(x) - 2.5, Y(y) - 2.5, 5, 5);
    arrow(g, X(m.dock.x), Y(m.dock.y), m.dock.heading, 12, "#444", true);
  }
  g.fillStyle = "#d9822b"; // landmarks being mapped (teach)
  for (const [, x, y] of state.landmarks) { g.beginPath(); g.arc(X(x), Y(y), 3, 0, 2 * Math.PI); g.fill(); }
  if (state.traj.length > 1) {
    g.beginPath();
    state.traj.forEach(([, x, y], i) => (i ? g.lineTo(X(x), Y(y)) : g.moveTo(X(x), Y(y))));
    g.strokeStyle = "#1f5fbf"; g.lineWidth = 1.5; g.stroke();
  }
  const d = state.live && state.live.daemon;
  const pose = d && d.pose;
  if (pose) {
    const px = X(pose.x), py = Y(pose.y);
    ellipse(g, pose, px, py, s);
    arrow(g, px, py, pose.heading, 16, d.permit ? "#1f8a3b" : "#b3261e", false);
  }
}

function grid(g, b, X, Y, w, h) {
  const span = Math.max(b.x1 - b.x0, b.y1 - b.y0);
  const step = span > 60 ? 10 : span > 15 ? 5 : 1;
  g.strokeStyle = "#eef1ec"; g.lineWidth = 1;
  for (let x = Math.ceil(b.x0 / step) * step; x <= b.x1; x += step) { g.beginPath(); g.moveTo(X(x), 0); g.lineTo(X(x), h); g.stroke(); }
  for (let y = Math.ceil(b.y0 / step) * step; y <= b.y1; y += step) { g.beginPath(); g.moveTo(0, Y(y)); g.lineTo(w, Y(y)); g.stroke(); }
  g.fillStyle = "#8a948c"; g.font = "11px system-ui";
  g.fillText(`grid ${step} m`, 6, h - 6);
}

function arrow(g, x, y, heading, len, color, hollow) {
  g.save(); g.translate(x, y); g.rotate(-heading); // map heading: counter-clockwise from east
  g.beginPath(); g.moveTo(len, 0); g.lineTo(-len * 0.5, len * 0.45); g.lineTo(-len * 0.2, 0); g.lineTo(-len * 0.5, -len * 0.45); g.closePath();
  if (hollow) { g.strokeStyle = color; g.lineWidth = 2; g.stroke(); } else { g.fillStyle = color; g.fill(); }
  g.restore();
}

// the 95 % ellipse of the position (χ²₂ 5.99), drawn larger when it would be under 10 px
function ellipse(g, pose, px, py, scale) {
  const note = $("ellipse-note");
  if (!pose.cov_xy) { note.textContent = ""; return; }
  const [[a, bxy], [, c]] = pose.cov_xy;
  const tr = (a + c) / 2, det = Math.sqrt(Math.max(0, ((a - c) / 2) ** 2 + bxy * bxy));
  const l1 = tr + det, l2 = Math.max(0, tr - det);
  const k = Math.sqrt(5.991);
  const r1 = k * Math.sqrt(l1) * scale, r2 = k * Math.sqrt(l2) * scale;
  const angle = 0.5 * Math.atan2(2 * bxy, a - c);
  let zoom = 1; // 1, 2, 5, 10, 20, … until the ellipse is at least 10 px across
  while (r1 > 0 && r1 * zoom < 5 && zoom < 1e4) zoom *= String(zoom)[0] === "2" ? 2.5 : 2;
  note.textContent = zoom > 1 ? `· 95 % ellipse ×${zoom}` : "· 95 % ellipse";
  g.save(); g.translate(px, py); g.rotate(-angle);
  g.beginPath(); g.ellipse(0, 0, r1 * zoom, Math.max(r2 * zoom, 1), 0, 0, 2 * Math.PI);
  g.fillStyle = "rgba(31,95,191,0.15)"; g.fill(); g.strokeStyle = "#1f5fbf"; g.lineWidth = 1; g.stroke();
  g.restore();
}

// -------------------------------------------------------------------------------- start

window.addEventListener("load", () => {
  $("token").value = sessionStorage.getItem("mowerhw-token") || "";
  for (const b of document.querySelectorAll("button[data-cmd]")) b.addEventListener("click", () => send(b.dataset.cmd));
  window.addEventListener("resize", draw);
  loadMap();
  connect();
});
