// The engineer's page: measurements with state and decision, one measurement's detail, start a
// measurement (free form, or a part of a recipe), recipes with their control chart (I-MR, drawn
// here as inline SVG from /recipes/{name}/spc and /history), live progress from /api/v1/measurements/{id}/events (read with fetch streaming, so
// the token goes in an Authorization header). The token is held in this page's memory only.
"use strict";

const API = "/api/v1";
const FINAL = new Set(["done", "failed", "cancelled"]);
let selected = null; // id of the measurement shown in the detail panel
const following = new Set(); // ids whose event streams are open

const $ = (id) => document.getElementById(id);

function authHeaders() {
  const token = $("token").value.trim();
  return token ? { Authorization: `Bearer ${token}` } : {};
}

async function api(path, options = {}) {
  const res = await fetch(API + path, { ...options, headers: { ...authHeaders(), ...(options.headers || {}) } });
  const text = await res.text();
  let body = null;
  try { body = text ? JSON.parse(text) : null; } catch { body = text; }
  if (!res.ok) {
    const msg = body && (body.message || body.detail) ? (body.message || body.detail) : `HTTP ${res.status}`;
    throw new Error(typeof msg === "string" ? msg : JSON.stringify(msg));
  }
  return body;
}

function mm(v, digits = 3) {
  return typeof v === "number" && isFinite(v) ? `${(v * 1e3).toFixed(digits)} mm` : "-";
}

function utc(t) {
  return t ? new Date(t * 1000).toISOString().replace("T", " ").slice(0, 19) : "-";
}

function cell(tr, text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  tr.appendChild(td);
  return td;
}

function outcomeOf(m) {
  return (m.result && m.result.decision && m.result.decision.outcome) || "";
}

function showError(id, err) {
  const el = $(id);
  el.textContent = err ? String(err.message || err) : "";
  el.hidden = !err;
}

async function loadList() {
  try {
    const ms = await api("/measurements?limit=50");
    const tbody = $("measurements").querySelector("tbody");
    tbody.replaceChildren();
    for (const m of ms) {
      const tr = document.createElement("tr");
      tr.dataset.id = m.id;
      cell(tr, m.id, "mono");
      cell(tr, utc(m.created_at));
      cell(tr, m.state, `state state-${m.state}`);
      const part = m.result && m.result.part;
      const calSweep = m.request && m.request.target === "calibration";
      cell(tr, part ? `${part.part_id} (${part.recipe} v${part.recipe_version})` : calSweep ? "calibration sweep" : "-");
      cell(tr, mm(m.result && m.result.diameter_m), "n");
      const outcome = outcomeOf(m);
      const td = cell(tr, "");
      if (outcome) {
        const span = document.createElement("span");
        span.className = `outcome ${outcome}`;
        span.textContent = outcome.replaceAll("_", " ");
        td.appendChild(span);
      }
      tr.addEventListener("click", () => select(m.id));
      tbody.appendChild(tr);
      if (!FINAL.has(m.state)) follow(m.id);
    }
    showError("list-error", null);
  } catch (err) {
    showError("list-error", err);
  }
}

function setProgress(p, message) {
  $("progress").value = p;
  $("progress-text").textContent = `${Math.round(p * 100)} %`;
  $("detail-message").textContent = message || "";
}

function link(parent, href, text) {
  const a = document.createElement("a");
  a.href = href;
  a.textContent = text;
  a.target = "_blank";
  a.addEventListener("click", (ev) => {
    // reads that need a token: fetch with the header and open the file from memory
    if (!authHeaders().Authorization) return;
    ev.preventDefault();
    fetch(href, { headers: authHeaders() })
      .then((r) => (r.ok ? r.blob() : Promise.reject(new Error(`HTTP ${r.status}`))))
      .then((b) => window.open(URL.createObjectURL(b), "_blank"))
      .catch((err) => showError("detail-error", err));
  });
  parent.appendChild(a);
  parent.appendChild(document.createTextNode(" "));
}

function renderDetail(m) {
  $("detail-section").hidden = false;
  $("detail-id").textContent = m.id;
  $("detail-state").textContent = m.state;
  $("detail-state").className = `state-${m.state}`;
  const outcome = outcomeOf(m);
  $("detail-decision").textContent = outcome.replaceAll("_", " ");
  $("detail-decision").className = `outcome ${outcome}`;
  setProgress(m.progress, m.message);
  $("detail-error").textContent = m.error || "";
  $("detail-error").hidden = !m.error;
  const values = $("detail-values");
  values.replaceChildren();
  const r = m.result || {};
  const u = r.uncertainty || {};
  const rows = [];
  if (r.part) rows.push(["part", `${r.part.part_id}, recipe ${r.part.recipe} v${r.part.recipe_version}`]);
  if (r.model) rows.push(["model", r.model]);
  if (r.calibration_id) rows.push(["calibration made", `${r.calibration_id}${r.calibration_active ? " (active)" : ""}`]);
  if (r.diameter_m !== undefined) rows.push(["diameter (measured)", mm(r.diameter_m)]);
  if (r.thermal) rows.push(["diameter at 20 C", mm(r.thermal.diameter_20c_m)]);
  if (u.expanded_m !== undefined) rows.push([`U (k = ${u.k})`, mm(u.expanded_m, 4)]);
  if (typeof r.diameter_range_excess_m === "number" && Array.isArray(r.diameter_range_m)) {
    // a fit outside the request's nominal diameter range within 3 of its u (docs/service.md)
    const [lo, hi] = r.diameter_range_m;
    const by = `${r.diameter_range_excess_m >= 0 ? "+" : ""}${(r.diameter_range_excess_m * 1e3).toFixed(2)} mm`;
    rows.push([
      "warning",
      `outside the nominal range ${mm(lo, 1)} .. ${mm(hi, 1)} by ${by} (${Number(r.diameter_range_excess_u).toFixed(2)} u of the fit)`,
    ]);
  }
  if (r.decision) rows.push(["decision", `${r.decision.outcome} (${r.decision.rule})`]);
  for (const [k, v] of rows) {
    const tr = document.createElement("tr");
    const th = document.createElement("th");
    th.textContent = k;
    tr.appendChild(th);
    cell(tr, v);
    values.appendChild(tr);
  }
  const budget = $("detail-budget");
  budget.replaceChildren();
  const brows = [...(u.budget || []), ...((r.thermal && r.thermal.budget) || [])];
  $("budget-title").hidden = brows.length === 0;
  if (brows.length) {
    const head = document.createElement("tr");
    for (const h of ["source", "type", "u(x)", "unit", "c", "u (um)"]) {
      const th = document.createElement("th");
      th.textContent = h;
      head.appendChild(th);
    }
    budget.appendChild(head);
    for (const b of brows) {
      const tr = document.createElement("tr");
      cell(tr, b.source);
      cell(tr, b.type);
      cell(tr, Number(b.u_x).toPrecision(4), "n");
      cell(tr, b.unit || "");
      cell(tr, Number(b.c).toPrecision(4), "n");
      cell(tr, (b.u_m * 1e6).toFixed(1), "n");
      budget.appendChild(tr);
    }
  }
  const links = $("detail-links");
  links.replaceChildren();
  // a calibration sweep (POST /api/v1/calibrations) measured no part: its calibration, no report
  if (r.calibration_id) link(links, `${API}/calibrations/${r.calibration_id}`, "calibration (JSON)");
  if (m.request && m.request.target === "calibration") {
    // nothing more
  } else if (m.state === "done" || m.state === "failed") {
    link(links, `${API}/measurements/${m.id}/report.html`, "report (HTML)");
    link(links, `${API}/measurements/${m.id}/report.pdf`, "report (PDF)");
  }
  if (m.has_raw && FINAL.has(m.state)) link(links, `${API}/measurements/${m.id}/raw`, "raw log (MCAP)");
}

async function select(id) {
  selected = id;
  try {
    renderDetail(await api(`/measurements/${id}`));
    if (!FINAL.has($("detail-state").textContent)) follow(id);
  } catch (err) {
    showError("detail-error", err);
  }
}

// Server-sent events read with fetch streaming: "event: progress\ndata: {...}\n\n" blocks.
async function follow(id) {
  if (following.has(id)) return;
  following.add(id);
  try {
    const res = await fetch(`${API}/measurements/${id}/events`, { headers: authHeaders() });
    if (!res.ok || !res.body) throw new Error(`events: HTTP ${res.status}`);
    const reader = res.body.pipeThrough(new TextDecoderStream()).getReader();
    let buf = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buf += value;
      let cut;
      while ((cut = buf.indexOf("\n\n")) >= 0) {
        const block = buf.slice(0, cut);
        buf = buf.slice(cut + 2);
        const data = block.split("\n").filter((l) => l.startsWith("data:")).map((l) => l.slice(5)).join("\n");
        if (data) onProgress(JSON.parse(data));
      }
    }
  } catch (err) {
    showError("list-error", err);
  } finally {
    following.delete(id);
  }
  await loadList();
  if (selected === id) await select(id);
  if (shownRecipe) await showRecipe(shownRecipe);
}

function onProgress(ev) {
  const row = document.querySelector(`#measurements tr[data-id="${ev.id}"] td.state`);
  if (row) row.textContent = ev.state;
  if (selected === ev.id) {
    $("detail-state").textContent = ev.state;
    setProgress(ev.progress, ev.message);
  }
}

// A part of a recipe (the recipe supplies target and sweep), or a free-form measurement.
function startBody() {
  const recipe = $("recipe").value;
  if (recipe) {
    const body = { recipe, part_id: $("part-id").value.trim() };
    if ($("part-temp").value !== "") body.part_temperature_c = Number($("part-temp").value);
    if ($("part-temp-u").value !== "") body.temperature_uncertainty_c = Number($("part-temp-u").value);
    return body;
  }
  const body = { target: $("target").value };
  const speed = $("speed").value;
  if (speed) body.sweep = { speed_deg_s: Number(speed) };
  return body;
}

function recipeChosen() {
  const chosen = $("recipe").value !== "";
  $("free-form").hidden = chosen;
  $("part-fields").hidden = !chosen;
}

async function start(ev) {
  ev.preventDefault();
  const body = startBody();
  try {
    const m = await api("/measurements", {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify(body),
    });
    showError("start-error", null);
    selected = m.id;
    renderDetail(m);
    follow(m.id);
    loadList();
  } catch (err) {
    showError("start-error", err);
  }
}

async function health() {
  try {
    const res = await fetch("/healthz");
    const h = await res.json();
    $("health").textContent = `rig: ${h.status}` + (h.running ? ` (running ${h.running})` : "");
    $("health").className = `badge ${h.status}`;
    $("health").title = (h.reasons || []).join("; ");
  } catch {
    $("health").textContent = "rig: unreachable";
    $("health").className = "badge degraded";
  }
}

// ------------------------------------------------------------------------------------ recipes

let shownRecipe = null; // name of the recipe whose chart is shown
const SVG_NS = "http://www.w3.org/2000/svg";
const COLOURS = { conforms: "#1b7f3a", does_not_conform: "#b3261e", cannot_decide: "#b26a00" };

function tolText(t) {
  if (!t) return "-";
  const dev = (v) => (v === null || v === undefined ? "open" : `${v >= 0 ? "+" : ""}${(v * 1e3).toFixed(3)}`);
  return `${(t.nominal_m * 1e3).toFixed(3)} mm ${dev(t.upper_m)} / ${dev(t.lower_m)}`;
}

async function loadRecipes() {
  try {
    const rs = await api("/recipes");
    const tbody = $("recipes").querySelector("tbody");
    tbody.replaceChildren();
    const select = $("recipe");
    const keep = select.value;
    select.replaceChildren(new Option("none (free form)", ""));
    for (const r of rs) {
      const tr = document.createElement("tr");
      tr.dataset.name = r.name;
      cell(tr, r.name, "mono");
      cell(tr, String(r.version), "n");
      cell(tr, r.target);
      cell(tr, tolText(r.tolerances.diameter));
      cell(tr, r.material || "-");
      cell(tr, r.decision_rule);
      tr.addEventListener("click", () => showRecipe(r.name));
      tbody.appendChild(tr);
      select.appendChild(new Option(`${r.name} (v${r.version}, ${r.target})`, r.name));
    }
    if (rs.some((r) => r.name === keep)) select.value = keep;
    recipeChosen();
    showError("recipes-error", null);
  } catch (err) {
    showError("recipes-error", err);
  }
}

function svg(parent, tag, attrs, text) {
  const el = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, String(v));
  if (text !== undefined) el.textContent = text;
  parent.appendChild(el);
  return el;
}

// One panel of the chart: horizontal lines (centre, limits) and the points, on a y scale holding them all.
function panel(root, opts) {
  const { id, top, height, left, width, points, lines } = opts;
  const g = svg(root, "g", { id });
  const ys = [...points.map((p) => p.y), ...lines.map((l) => l.y)].filter((v) => typeof v === "number" && isFinite(v));
  let lo = Math.min(...ys);
  let hi = Math.max(...ys);
  const span = hi - lo || Math.abs(hi) * 1e-3 || 1e-6;
  lo -= 0.08 * span;
  hi += 0.08 * span;
  const y = (v) => top + height - ((v - lo) / (hi - lo)) * height;
  const n = Math.max(points.length, 2);
  const x = (i) => left + ((i + 0.5) / n) * width;
  svg(g, "rect", { x: left, y: top, width, height, fill: "#fcfcfc", stroke: "#bbb" });
  svg(g, "text", { x: 4, y: top + 12, class: "axis" }, opts.title);
  for (const l of lines) {
    if (typeof l.y !== "number" || !isFinite(l.y)) continue;
    const line = svg(g, "line", {
      x1: left, x2: left + width, y1: y(l.y), y2: y(l.y),
      class: `limit ${l.kind}`, "data-kind": l.kind, "data-value-mm": l.y * 1e3,
      stroke: l.colour, "stroke-width": l.kind.endsWith("sl") ? 2 : 1.2,
      "stroke-dasharray": l.kind === "cl" || l.kind === "mr-cl" ? "" : "6 4",
    });
    svg(line, "title", {}, `${l.label} ${(l.y * 1e3).toFixed(3)} mm`);
    svg(g, "text", { x: left + width + 4, y: y(l.y) + 4, class: "axis", fill: l.colour }, `${l.label} ${(l.y * 1e3).toFixed(3)}`);
  }
  const drawn = points.map((p, i) => ({ ...p, i })).filter((p) => typeof p.y === "number");
  if (drawn.length > 1) {
    svg(g, "polyline", {
      points: drawn.map((p) => `${x(p.i)},${y(p.y)}`).join(" "), fill: "none", stroke: "#888", class: "trace",
    });
  }
  for (const p of drawn) {
    const c = svg(g, "circle", {
      cx: x(p.i), cy: y(p.y), r: p.flagged ? 6 : 4.5, class: `${opts.pointClass} ${p.outcome || "undecided"}`,
      fill: COLOURS[p.outcome] || "#777", stroke: p.flagged ? "#000" : "#fff", "stroke-width": p.flagged ? 2 : 1,
      "data-measurement-id": p.id, "data-part-id": p.part, "data-value-mm": p.y * 1e3,
      "data-outcome": p.outcome || "", "data-flagged": p.flagged ? "true" : "false",
    });
    svg(c, "title", {}, `part ${p.part}: ${(p.y * 1e3).toFixed(3)} mm, ${(p.outcome || "no decision").replaceAll("_", " ")}`
      + (p.flagged ? " (flagged)" : ""));
    c.addEventListener("click", () => select(p.id));
  }
}

// The I-MR chart of the recipe's decided values: individuals with centre line, control limits and
// the tolerance (LSL / USL); moving ranges below. Points are coloured by their decision.
function drawChart(spc, history) {
  const outcomes = new Map(history.map((h) => [h.measurement_id, h.outcome]));
  const width = 640;
  const left = 12;
  const root = document.createElementNS(SVG_NS, "svg");
  const h = 420;
  for (const [k, v] of Object.entries({ id: "spc-chart", width: width + 130, height: h, viewBox: `0 0 ${width + 130} ${h}` })) {
    root.setAttribute(k, String(v));
  }
  root.dataset.n = String(spc.n);
  root.setAttribute("role", "img");
  root.setAttribute("aria-label", `individuals and moving-range chart of ${spc.recipe}`);
  const pts = spc.points.map((p) => ({
    id: p.measurement_id, part: p.part_id, outcome: outcomes.get(p.measurement_id), flagged: p.flagged,
  }));
  const cap = spc.capability || {};
  panel(root, {
    id: "i-chart", title: "individuals (mm)", top: 20, height: 250, left, width, pointClass: "point",
    points: spc.points.map((p, i) => ({ ...pts[i], y: p.value_m, flagged: p.beyond_limits || p.run_of_eight })),
    lines: [
      { kind: "usl", label: "USL", y: cap.usl_m, colour: "#b3261e" },
      { kind: "ucl", label: "UCL", y: spc.i_ucl_m, colour: "#1565c0" },
      { kind: "cl", label: "mean", y: spc.mean_m, colour: "#333" },
      { kind: "lcl", label: "LCL", y: spc.i_lcl_m, colour: "#1565c0" },
      { kind: "lsl", label: "LSL", y: cap.lsl_m, colour: "#b3261e" },
    ],
  });
  panel(root, {
    id: "mr-chart", title: "moving range (mm)", top: 295, height: 110, left, width, pointClass: "mr-point",
    points: spc.points.map((p, i) => ({ ...pts[i], y: p.moving_range_m, flagged: p.mr_beyond_limit })),
    lines: [
      { kind: "mr-ucl", label: "UCL", y: spc.mr_ucl_m, colour: "#1565c0" },
      { kind: "mr-cl", label: "MR-bar", y: spc.mr_bar_m, colour: "#333" },
    ],
  });
  return root;
}

function kvRows(table, rows) {
  table.replaceChildren();
  for (const [k, v] of rows) {
    const tr = document.createElement("tr");
    const th = document.createElement("th");
    th.textContent = k;
    tr.appendChild(th);
    cell(tr, v);
    table.appendChild(tr);
  }
}

async function showRecipe(name) {
  shownRecipe = name;
  $("recipe-section").hidden = false;
  $("recipe-name").textContent = name;
  const enc = encodeURIComponent(name);
  try {
    const [recipe, history] = await Promise.all([api(`/recipes/${enc}`), api(`/recipes/${enc}/history`)]);
    $("recipe-summary").textContent =
      `version ${recipe.version}, ${recipe.target}, diameter ${tolText(recipe.tolerances.diameter)}, ` +
      `${recipe.material || "no material"}, ${recipe.decision_rule}` + (recipe.retired ? " (retired)" : "");
    let spc = null;
    try {
      spc = await api(`/recipes/${enc}/spc`);
    } catch (err) {
      $("chart-note").textContent = String(err.message || err); // fewer than 2 measured parts
    }
    $("chart").replaceChildren(...(spc ? [drawChart(spc, history)] : []));
    $("chart-note").hidden = spc !== null;
    const cap = (spc && spc.capability) || {};
    const num = (v) => (typeof v === "number" && isFinite(v) ? v.toFixed(2) : "-");
    kvRows($("spc-values"), spc ? [
      ["parts charted", String(spc.n)],
      ["mean", mm(spc.mean_m)],
      ["control limits (individuals)", `${mm(spc.i_lcl_m)} .. ${mm(spc.i_ucl_m)}`],
      ["sigma within / overall", `${mm(spc.sigma_within_m, 4)} / ${mm(spc.sigma_overall_m, 4)}`],
      ["Cp / Cpk", `${num(cap.cp)} / ${num(cap.cpk)}`],
      ["Pp / Ppk", `${num(cap.pp)} / ${num(cap.ppk)}`],
      ["flagged points", String(spc.points.filter((p) => p.flagged).length)],
    ] : []);
    const tbody = $("history").querySelector("tbody");
    tbody.replaceChildren();
    for (const r of history) {
      const tr = document.createElement("tr");
      tr.dataset.id = r.measurement_id;
      cell(tr, r.part_id);
      cell(tr, r.measurement_id, "mono");
      cell(tr, utc(r.finished_at));
      cell(tr, r.state, `state state-${r.state}`);
      cell(tr, String(r.recipe_version), "n");
      cell(tr, mm(r.value_m), "n");
      const td = cell(tr, "");
      if (r.outcome) {
        const span = document.createElement("span");
        span.className = `outcome ${r.outcome}`;
        span.textContent = r.outcome.replaceAll("_", " ");
        td.appendChild(span);
      }
      tr.addEventListener("click", () => select(r.measurement_id));
      tbody.appendChild(tr);
    }
    showError("recipe-error", null);
  } catch (err) {
    showError("recipe-error", err);
  }
}

document.addEventListener("DOMContentLoaded", () => {
  $("start-form").addEventListener("submit", start);
  $("refresh").addEventListener("click", loadList);
  $("refresh-recipes").addEventListener("click", loadRecipes);
  $("refresh-chart").addEventListener("click", () => shownRecipe && showRecipe(shownRecipe));
  $("recipe").addEventListener("change", recipeChosen);
  $("token").addEventListener("change", () => { loadList(); loadRecipes(); });
  health();
  loadList();
  loadRecipes();
  setInterval(health, 5000);
  setInterval(loadList, 10000);
});
