// awaremw web dashboard: plain browser JavaScript, no build step, no libraries.
"use strict";
const SVGNS = "http://www.w3.org/2000/svg";
const MAX_POINTS = 300;  // per channel, as the server keeps
const COLOURS = ["#e6194b", "#3cb44b", "#4363d8", "#f58231", "#911eb4", "#46c0c0",
                 "#f032e6", "#9a9a00", "#008080", "#9a6324", "#800000", "#000075"];
let state = null;
let series = {};       // channel -> [[t, value, gid], ...]
let chosenType = null; // group type chosen by the user (null: the server's default)
let dirty = new Set();

const $ = (id) => document.getElementById(id);
function el(tag, attrs, parent) {
  const e = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}
function colour(gid) { return gid == null ? "#bbb" : COLOURS[gid % COLOURS.length]; }

function drawField() {
  const svg = $("field");
  const [w, h] = state.area;
  const pad = 0.6;
  svg.setAttribute("viewBox", `${-pad} ${-pad} ${w + 2 * pad} ${h + 2 * pad}`);
  svg.replaceChildren();
  const fy = (y) => h - y;  // north up
  el("rect", {x: 0, y: 0, width: w, height: h, fill: "none", stroke: "#ccc", "stroke-width": 0.04}, svg);
  for (const f of state.fires) {
    el("circle", {cx: f.x, cy: fy(f.y), r: Math.max(f.radius, 0.3), fill: "rgba(255,90,0,.25)",
                  stroke: "#f50", "stroke-width": 0.05, "data-fire": f.name}, svg);
  }
  const gtype = chosenType ?? state.group_type;
  const byId = {};
  for (const m of state.motes) byId[m.id] = m;
  if ($("show-tree").checked && state.tree_known) {
    const g = el("g", {"data-layer": "tree"}, svg);
    for (const m of state.motes) {
      const p = byId[m.parent];
      if (p) el("line", {x1: m.x, y1: fy(m.y), x2: p.x, y2: fy(p.y), stroke: "#6a8",
                         "stroke-width": 0.05, "data-link": `${m.id}-${p.id}`}, g);
    }
  }
  for (const [id, pts] of Object.entries(state.trails)) {
    if (pts.length > 1) el("polyline", {points: pts.map(([x, y]) => `${x},${fy(y)}`).join(" "),
      fill: "none", stroke: "#888", "stroke-dasharray": "0.15 0.1", "stroke-width": 0.05, "data-trail": id}, svg);
  }
  for (const m of state.motes) {
    const g = gtype == null ? null : (m.groups[String(gtype)] || null);
    const gid = g ? g.id : null;
    const attrs = {"data-mote": m.id, "data-kind": m.kind};
    if (gid != null) attrs["data-group"] = gid;
    if (g && g.leader) attrs["data-leader"] = "";
    const node = el("g", attrs, svg);
    const fill = m.alive ? colour(gid) : "#fff";
    if (m.kind === "robot") {
      el("rect", {x: m.x - 0.3, y: fy(m.y) - 0.3, width: 0.6, height: 0.6, fill: "#333"}, node);
    } else if (m.kind === "gateway") {
      el("polygon", {points: `${m.x},${fy(m.y) - 0.35} ${m.x - 0.3},${fy(m.y) + 0.25} ${m.x + 0.3},${fy(m.y) + 0.25}`,
                     fill: "#235"}, node);
    } else {
      el("circle", {cx: m.x, cy: fy(m.y), r: 0.22, fill, stroke: m.alive ? "#333" : "#c00",
                    "stroke-width": 0.03}, node);
    }
    if (g && g.leader) el("circle", {cx: m.x, cy: fy(m.y), r: 0.38, fill: "none", stroke: colour(gid),
                                     "stroke-width": 0.09}, node);
    const label = el("text", {x: m.x + 0.3, y: fy(m.y) - 0.25, "font-size": 0.38, fill: "#444"}, node);
    label.textContent = m.id;
    const title = el("title", {}, node);
    title.textContent = `mote ${m.id} (${m.kind})` + (gid != null ? `, group ${gid}${g.leader ? " leader" : ""}` : "");
  }
  $("legend").textContent = state.members_known
    ? "colour: group in the chosen type; ring: leader; square: robot; triangle: gateway"
    : "groups from aware/groups: leaders only (the public contract does not list members)";
  $("tree-note").textContent = state.tree_known ? "" : "(tree not available in this view)";
  $("show-tree").disabled = !state.tree_known;
}

function drawGroups() {
  const body = $("groups").tBodies[0];
  body.replaceChildren();
  for (const g of state.groups) {
    const tr = body.insertRow();
    const members = g.members == null ? "?" : `${g.members.length}: ${g.members.join(" ")}`;
    for (const v of [g.type, g.id, g.leader ?? "-", members, g.weight ?? "-"]) tr.insertCell().textContent = v;
    tr.dataset.group = `${g.type}/${g.id}`;
    tr.style.color = colour(g.id);
  }
  const sel = $("gtype");
  const types = [...new Set([...state.groups.map((g) => g.type),
                             ...Object.keys(state.definitions.group).map(Number)])].sort((a, b) => a - b);
  const want = String(chosenType ?? state.group_type ?? "");
  if (sel.options.length !== types.length || [...sel.options].some((o, i) => o.value !== String(types[i]))) {
    sel.replaceChildren(...types.map((t) => new Option(`type ${t}`, String(t))));
  }
  sel.value = want;
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
  $("definitions").textContent = JSON.stringify(state.definitions, null, 1);
}

function render() {
  if (!state) return;
  drawField(); drawGroups(); drawSide();
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
    state = d.state; series = d.series;
    $("live").textContent = "live"; $("live").className = "on";
    render();
  });
  es.addEventListener("state", (ev) => { state = JSON.parse(ev.data); render(); });
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
    const r = await fetch(url, {method, headers: {"Content-Type": "application/json"},
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
$("show-tree").addEventListener("change", render);
connect();
