// awaremw web dashboard: plain browser JavaScript, no build step, no libraries.
"use strict";
const SVGNS = "http://www.w3.org/2000/svg";
const MAX_POINTS = 300;  // per channel, as the server keeps
const COLOURS = ["#e6194b", "#3cb44b", "#4363d8", "#f58231", "#911eb4", "#46c0c0",
                 "#f032e6", "#9a9a00", "#008080", "#9a6324", "#800000", "#000075"];
const LED_COLOURS = {red: "#f00", green: "#0c0", blue: "#06f", yellow: "#fd0"};
const TOKEN = document.querySelector('meta[name="awaremw-token"]').content;
let state = null;      // the state events: everything but the motes and the definitions
let definitions = {group: {}, channel: {}};
const motes = new Map(); // id -> {id, kind, x, y, alive, parent, leds, groups: {type: [gid, leader]}}
let series = {};       // channel -> [[t, value, gid], ...]
let chosenType = null; // group type chosen by the user (null: the server's default)
let dirty = new Set();
// What the page drew last (read by the tests): counts and ids.
window.awaremw = {drawn: {motes: 0, leaders: [], links: 0, lit: []}, fieldEvents: 0,
                  lastField: 0, stateEvents: 0};

const $ = (id) => document.getElementById(id);
function el(tag, attrs, parent) {
  const e = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}
function colour(gid) { return gid == null ? "#bbb" : COLOURS[gid % COLOURS.length]; }

function applyRows(rows) {
  for (const [id, kind, x, y, alive, parent, leds, groups] of rows) {
    const g = {};
    for (const [t, gid, lead] of groups) g[t] = [gid, !!lead];
    motes.set(id, {id, kind, x, y, alive: !!alive, parent, leds, groups: g});
  }
}

// ---------------------------------------------------------------- the field (canvas)
// view: screen = (ox + x * scale, oy - y * scale) in CSS pixels; null until fitted.
let view = null;
function fit() {
  const c = $("field"), [w, h] = state.area, pad = Math.max(w, h) * 0.03 + 0.6;
  const cw = c.clientWidth, ch = c.clientHeight;
  const scale = Math.min(cw / (w + 2 * pad), ch / (h + 2 * pad));
  view = {scale, ox: (cw - w * scale) / 2, oy: (ch + h * scale) / 2};
}
let fieldFrame = false;
function scheduleField() {
  if (!fieldFrame) { fieldFrame = true; requestAnimationFrame(() => { fieldFrame = false; drawField(); }); }
}

function drawField() {
  if (!state) return;
  const t0 = performance.now();
  const c = $("field");
  const dpr = window.devicePixelRatio || 1;
  const cw = c.clientWidth, ch = c.clientHeight;
  if (c.width !== Math.round(cw * dpr) || c.height !== Math.round(ch * dpr)) {
    c.width = Math.round(cw * dpr); c.height = Math.round(ch * dpr);
  }
  if (!view) fit();
  const ctx = c.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, cw, ch);
  const {scale, ox, oy} = view;
  const X = (x) => ox + x * scale, Y = (y) => oy - y * scale;
  const [w, h] = state.area;
  ctx.strokeStyle = "#ccc"; ctx.lineWidth = 1;
  ctx.strokeRect(X(0), Y(h), w * scale, h * scale);
  for (const f of state.fires) {
    ctx.beginPath(); ctx.arc(X(f.x), Y(f.y), Math.max(f.radius * scale, 4), 0, 2 * Math.PI);
    ctx.fillStyle = "rgba(255,90,0,.25)"; ctx.fill(); ctx.strokeStyle = "#f50"; ctx.stroke();
  }
  const gtype = chosenType ?? state.group_type;
  let links = 0;
  if ($("show-tree").checked && state.tree_known) {
    ctx.beginPath();
    for (const m of motes.values()) {
      const p = motes.get(m.parent);
      if (p) { ctx.moveTo(X(m.x), Y(m.y)); ctx.lineTo(X(p.x), Y(p.y)); links++; }
    }
    ctx.strokeStyle = "#6a8"; ctx.lineWidth = 1; ctx.stroke();
  }
  ctx.setLineDash([4, 3]); ctx.strokeStyle = "#888";
  for (const pts of Object.values(state.trails)) {
    if (pts.length < 2) continue;
    ctx.beginPath(); ctx.moveTo(X(pts[0][0]), Y(pts[0][1]));
    for (const [x, y] of pts.slice(1)) ctx.lineTo(X(x), Y(y));
    ctx.stroke();
  }
  ctx.setLineDash([]);
  // Motes batched by fill colour: one path per colour, whatever the field's size.
  const r = Math.max(1.5, Math.min(0.22 * scale, 8));
  const byFill = new Map(), leaders = [], lit = [], special = [];
  let n = 0;
  const inView = (sx, sy) => sx > -20 && sy > -20 && sx < cw + 20 && sy < ch + 20;
  for (const m of motes.values()) {
    n++;
    const g = gtype == null ? null : (m.groups[gtype] || null);
    if (g && g[1]) leaders.push(m);
    if (m.leds.length) lit.push(m);
    const sx = X(m.x), sy = Y(m.y);
    if (!inView(sx, sy)) continue;
    if (m.kind === "robot" || m.kind === "gateway") { special.push(m); continue; }
    const fill = m.alive ? colour(g ? g[0] : null) : "#fff";
    let p = byFill.get(fill);
    if (!p) byFill.set(fill, p = new Path2D());
    p.moveTo(sx + r, sy); p.arc(sx, sy, r, 0, 2 * Math.PI);
  }
  for (const [fill, p] of byFill) {
    ctx.fillStyle = fill; ctx.fill(p);
    if (r >= 3) { ctx.strokeStyle = fill === "#fff" ? "#c00" : "#333"; ctx.lineWidth = 0.7; ctx.stroke(p); }
  }
  const ring = Math.max(r * 1.8, 5);
  ctx.lineWidth = Math.max(2, r * 0.45);
  for (const m of leaders) {
    ctx.beginPath(); ctx.arc(X(m.x), Y(m.y), ring, 0, 2 * Math.PI);
    ctx.strokeStyle = colour(m.groups[gtype][0]); ctx.stroke();
    ctx.lineWidth = 1; ctx.strokeStyle = "#000";
    ctx.beginPath(); ctx.arc(X(m.x), Y(m.y), ring + 1.5, 0, 2 * Math.PI); ctx.stroke();
    ctx.lineWidth = Math.max(2, r * 0.45);
  }
  for (const m of lit) {  // the led command's effect: one dot per lit LED, above the mote
    m.leds.forEach((c, i) => {
      ctx.beginPath(); ctx.arc(X(m.x) - r + i * (r + 2), Y(m.y) - r - 4, Math.max(2.5, r * 0.5), 0, 2 * Math.PI);
      ctx.fillStyle = LED_COLOURS[c] || "#fff"; ctx.fill(); ctx.strokeStyle = "#000"; ctx.lineWidth = 0.6; ctx.stroke();
    });
  }
  const big = Math.max(5, Math.min(0.35 * scale, 12));
  for (const m of special) {
    const sx = X(m.x), sy = Y(m.y);
    ctx.beginPath();
    if (m.kind === "robot") ctx.rect(sx - big, sy - big, 2 * big, 2 * big);
    else { ctx.moveTo(sx, sy - big); ctx.lineTo(sx - big, sy + big * 0.7); ctx.lineTo(sx + big, sy + big * 0.7); ctx.closePath(); }
    ctx.fillStyle = m.kind === "robot" ? "#333" : "#235"; ctx.fill();
  }
  if (scale >= 12 && n <= 3000) {  // ids when they can be read
    ctx.fillStyle = "#444"; ctx.font = `${Math.min(0.38 * scale, 13)}px system-ui`;
    for (const m of motes.values()) {
      const sx = X(m.x), sy = Y(m.y);
      if (inView(sx, sy)) ctx.fillText(String(m.id), sx + r + 2, sy - r);
    }
  }
  const drawn = window.awaremw.drawn;
  drawn.motes = n; drawn.links = links;
  drawn.leaders = leaders.map((m) => m.id).sort((a, b) => a - b);
  drawn.lit = lit.map((m) => m.id).sort((a, b) => a - b);
  drawn.ms = Math.round((performance.now() - t0) * 10) / 10;  // this draw's duration
  c.dataset.motes = n; c.dataset.leaders = leaders.length; c.dataset.links = links; c.dataset.lit = lit.length;
  $("legend").textContent = (state.members_known
    ? "colour: group in the chosen type; ring: leader; square: robot; triangle: gateway; dots above: lit LEDs"
    : "groups from aware/groups: leaders only (the public contract does not list members)")
    + " — wheel: zoom, drag: pan, double-click: whole field";
  $("tree-note").textContent = state.tree_known ? "" : "(tree not available in this view)";
  $("show-tree").disabled = !state.tree_known;
}

function moteAt(px, py) {
  if (!view) return null;
  let best = null, bd = 64;
  for (const m of motes.values()) {
    const dx = view.ox + m.x * view.scale - px, dy = view.oy - m.y * view.scale - py;
    const d = dx * dx + dy * dy;
    if (d < bd) { bd = d; best = m; }
  }
  return best;
}
(function interact() {
  const c = $("field");
  let drag = null;
  c.addEventListener("wheel", (ev) => {
    ev.preventDefault();
    if (!view) return;
    const k = Math.exp(-ev.deltaY * 0.0015), rect = c.getBoundingClientRect();
    const px = ev.clientX - rect.left, py = ev.clientY - rect.top;
    view.ox = px - (px - view.ox) * k; view.oy = py - (py - view.oy) * k; view.scale *= k;
    scheduleField();
  }, {passive: false});
  c.addEventListener("mousedown", (ev) => { drag = [ev.clientX, ev.clientY]; });
  window.addEventListener("mouseup", () => { drag = null; });
  c.addEventListener("mousemove", (ev) => {
    const rect = c.getBoundingClientRect();
    if (drag && view) {
      view.ox += ev.clientX - drag[0]; view.oy += ev.clientY - drag[1];
      drag = [ev.clientX, ev.clientY]; scheduleField(); return;
    }
    const m = moteAt(ev.clientX - rect.left, ev.clientY - rect.top);
    const gtype = chosenType ?? (state && state.group_type);
    const g = m && gtype != null ? m.groups[gtype] : null;
    c.title = m ? `mote ${m.id} (${m.kind})` + (g ? `, group ${g[0]}${g[1] ? " leader" : ""}` : "")
      + (m.leds.length ? `, LEDs ${m.leds.join(",")}` : "") : "";
  });
  c.addEventListener("dblclick", () => { view = null; scheduleField(); });
  window.addEventListener("resize", () => { view = null; scheduleField(); });
})();

function drawGroups() {
  const body = $("groups").tBodies[0];
  body.replaceChildren();
  for (const g of state.groups) {
    const tr = body.insertRow();
    const members = g.size == null ? "?" : g.size;
    for (const v of [g.type, g.id, g.leader ?? "-", members, g.weight ?? "-"]) tr.insertCell().textContent = v;
    tr.dataset.group = `${g.type}/${g.id}`;
    tr.style.color = colour(g.id);
  }
  const sel = $("gtype");
  const types = [...new Set([...state.groups.map((g) => g.type),
                             ...Object.keys(definitions.group).map(Number)])].sort((a, b) => a - b);
  const want = String(chosenType ?? state.group_type ?? "");
  if (sel.options.length !== types.length || [...sel.options].some((o, i) => o.value !== String(types[i]))) {
    sel.replaceChildren(...types.map((t) => new Option(`type ${t}`, String(t))));
  }
  sel.value = want;
}

function drawEnergy() {
  // Mean radio energy and frames per hour of the motes in each role (docs/energy.md).
  const rows = Object.entries(state.energy || {});
  $("no-energy").hidden = rows.length > 0;
  const body = $("energy").tBodies[0];
  body.replaceChildren();
  for (const [role, e] of rows) {
    const tr = body.insertRow();
    tr.dataset.role = role;
    for (const v of [role, e.motes, e.mj_per_hour.toFixed(1), e.frames_per_hour.toFixed(1)]) {
      tr.insertCell().textContent = v;
    }
  }
}

function drawPlot(ch) {
  const pts = series[ch] || [];
  const info = (state && state.channels[ch]) || {};
  let box = document.querySelector(`.plot-box[data-channel="${ch}"]`);
  if (!box) {
    box = document.createElement("div");
    box.className = "plot-box";
    box.dataset.channel = ch;
    box.innerHTML = `<div class="plot-title"></div>`;
    el("svg", {class: "plot", viewBox: "0 0 400 130", preserveAspectRatio: "none"}, box);
    const boxes = [...document.querySelectorAll(".plot-box")];
    const after = boxes.find((b) => Number(b.dataset.channel) > Number(ch));
    $("plots").insertBefore(box, after || null);
    $("no-plots").hidden = true;
  }
  const unit = info.unit || "";
  const svg = box.querySelector("svg");
  svg.setAttribute("data-channel", ch);
  svg.setAttribute("data-points", pts.length);
  svg.replaceChildren();
  const last = pts.length ? pts[pts.length - 1] : null;
  box.querySelector(".plot-title").textContent =
    `channel ${ch}: ${info.agg || "?"} of ${info.attr || "?"}` + (unit ? ` (${unit})` : "") +
    (info.group_type != null ? `, group type ${info.group_type}` : "") +
    (last ? ` — last ${last[1].toFixed(2)} ${unit} at t=${last[0].toFixed(1)} s (group ${last[2]})` : "");
  if (!pts.length) return;
  const L = 72, R = 396, T = 8, B = 112;
  let t0 = pts[0][0], t1 = pts[pts.length - 1][0];
  let v0 = Math.min(...pts.map((p) => p[1])), v1 = Math.max(...pts.map((p) => p[1]));
  if (t1 - t0 < 1e-6) t1 = t0 + 1;
  if (v1 - v0 < 1e-6) { v0 -= 0.5; v1 += 0.5; }
  const X = (t) => L + (t - t0) / (t1 - t0) * (R - L);
  const Y = (v) => B - (v - v0) / (v1 - v0) * (B - T);
  el("line", {x1: L, y1: B, x2: R, y2: B, stroke: "#999"}, svg);
  el("line", {x1: L, y1: T, x2: L, y2: B, stroke: "#999"}, svg);
  const text = (x, y, s, anchor) => {
    const e = el("text", {x, y, "font-size": 10, fill: "#555", "text-anchor": anchor || "start"}, svg);
    e.textContent = s;
  };
  text(L - 3, T + 8, `${v1.toFixed(1)} ${unit}`, "end");
  text(L - 3, B, `${v0.toFixed(1)} ${unit}`, "end");
  text(L, B + 13, `${t0.toFixed(0)} s`);
  text(R, B + 13, `${t1.toFixed(0)} s (emulated time)`, "end");
  const byGroup = {};
  for (const p of pts) (byGroup[p[2]] = byGroup[p[2]] || []).push(p);
  for (const [gid, gp] of Object.entries(byGroup)) {
    el("polyline", {points: gp.map((p) => `${X(p[0]).toFixed(1)},${Y(p[1]).toFixed(1)}`).join(" "),
                    fill: "none", stroke: colour(Number(gid)), "stroke-width": 1.5, "data-group": gid}, svg);
    for (const p of gp) el("circle", {cx: X(p[0]).toFixed(1), cy: Y(p[1]).toFixed(1), r: 2,
                                      fill: colour(Number(gid)), "data-point": ""}, svg);
  }
}

function countPoints() {
  const n = Object.values(series).reduce((a, s) => a + s.length, 0);
  $("points-total").textContent = n;
  $("points-total").dataset.points = n;
}

function drawSide() {
  $("title").textContent = state.title;
  $("clock").textContent = state.t.toFixed(1);
  $("gateway").textContent = state.gateway;
  $("mqtt").textContent = state.mqtt ? "connected" : "disconnected";
  $("records").textContent = state.records;
  const errs = $("errors");
  errs.replaceChildren(...state.errors.slice().reverse().map((e) => {
    const li = document.createElement("li");
    li.textContent = `${e.code || "error"}: ${e.error || ""}` + (e.topic ? ` (${e.topic})` : "");
    return li;
  }));
  $("definitions").textContent = JSON.stringify(definitions, null, 1);
  $("n-motes").textContent = state.n_motes;
}

function render() {
  if (!state) return;
  scheduleField(); drawGroups(); drawEnergy(); drawSide();
  for (const ch of Object.keys(state.channels)) dirty.add(ch);
  flushPlots();
}
function flushPlots() {
  for (const ch of dirty) drawPlot(ch);
  dirty.clear();
  countPoints();
}
let frame = false;
function schedule() {
  if (!frame) { frame = true; requestAnimationFrame(() => { frame = false; flushPlots(); }); }
}

function connect() {
  const es = new EventSource("/api/events");
  es.addEventListener("hello", (ev) => {
    const d = JSON.parse(ev.data);
    state = d.state; series = d.series; definitions = d.definitions;
    motes.clear(); applyRows(d.field.rows);
    $("live").textContent = "live"; $("live").className = "on";
    render();
  });
  es.addEventListener("field", (ev) => {
    const d = JSON.parse(ev.data);
    for (const id of d.gone) motes.delete(id);
    applyRows(d.rows);
    window.awaremw.fieldEvents++; window.awaremw.lastField = Date.now();
    scheduleField();
  });
  es.addEventListener("state", (ev) => {
    state = JSON.parse(ev.data); window.awaremw.stateEvents++; render();
  });
  es.addEventListener("defs", (ev) => { definitions = JSON.parse(ev.data); if (state) { drawGroups(); drawSide(); } });
  es.addEventListener("record", (ev) => {
    const d = JSON.parse(ev.data);
    const s = (series[d.channel] = series[d.channel] || []);
    s.push(d.point);
    if (s.length > MAX_POINTS) s.splice(0, s.length - MAX_POINTS);
    if (state) state.channels[d.channel] = d.info;
    dirty.add(d.channel);
    schedule();
  });
  es.onerror = () => { $("live").textContent = "reconnecting…"; $("live").className = "off"; };
}

// ---------------------------------------------------------------- the forms
function idOrAny(v) { v = v.trim(); return v === "*" || v === "" ? "*" : Number(v); }
function parseConditions(text) {
  return text.split(/,|\band\b/).map((c) => c.trim()).filter(Boolean).map((c) => {
    const m = c.match(/^(\S+?)\s*(<=|>=|==|!=|<|>|=)\s*(-?[\d.eE+-]+)$/);
    if (!m) throw new Error(`condition "${c}": expected e.g. temperature > 45`);
    return {attr: m[1], op: m[2], value: Number(m[3])};
  });
}
function parseArgs(text) {
  const out = {};
  for (const kv of text.split(",").map((s) => s.trim()).filter(Boolean)) {
    const [k, ...rest] = kv.split("=");
    const v = rest.join("=").trim();
    out[k.trim()] = v === "true" ? true : v === "false" ? false : (v !== "" && !isNaN(Number(v)) ? Number(v) : v);
  }
  return out;
}
function parseTarget(text) {
  text = text.trim();
  let m;
  if (text === "" || text === "all") return "all";
  if ((m = text.match(/^node:(\d+)$/))) return {node: Number(m[1])};
  if ((m = text.match(/^group:(\d+)\/(\d+)$/))) return {group_type: Number(m[1]), group_id: Number(m[2])};
  throw new Error("target: all, node:<id> or group:<type>/<id>");
}
async function send(method, url, body) {
  const status = $("form-status");
  try {
    // The server's token and a same-origin request: only this page drives the dashboard.
    const r = await fetch(url, {method, headers: {"Content-Type": "application/json", "X-Awaremw-Token": TOKEN},
                                body: body === undefined ? undefined : JSON.stringify(body)});
    const text = await r.text();
    status.textContent = r.ok ? `published on ${JSON.parse(text).topic}` : `refused (${r.status}): ${text}`;
  } catch (e) { status.textContent = String(e); }
}
function onSubmit(id, fn) {
  $(id).addEventListener("submit", (ev) => {
    ev.preventDefault();
    try { fn(new FormData(ev.target)); } catch (e) { $("form-status").textContent = e.message; }
  });
}
onSubmit("group-form", (f) => send("POST", `/api/def/group/${f.get("type")}`, {
  conditions: parseConditions(f.get("conditions")), hysteresis: Number(f.get("hysteresis") || 0)}));
onSubmit("channel-form", (f) => send("POST", `/api/def/channel/${f.get("id")}`, {
  attr: f.get("attr").trim(), group_type: idOrAny(f.get("group_type")), group_id: idOrAny(f.get("group_id")),
  period_s: Number(f.get("period_s")), agg: f.get("agg")}));
onSubmit("command-form", (f) => send("POST", `/api/cmd/${encodeURIComponent(f.get("name").trim())}`, {
  target: parseTarget(f.get("target")), args: parseArgs(f.get("args"))}));
for (const b of document.querySelectorAll("[data-delete]")) {
  b.addEventListener("click", () => {
    const kind = b.dataset.delete;
    const f = new FormData(b.form);
    send("DELETE", `/api/def/${kind}/${f.get(kind === "group" ? "type" : "id")}`);
  });
}
$("gtype").addEventListener("change", (ev) => { chosenType = Number(ev.target.value); render(); });
$("show-tree").addEventListener("change", scheduleField);
connect();
