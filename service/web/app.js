// The engineer's page: measurements with state and decision, one measurement's detail, start a
// measurement, live progress from /api/v1/measurements/{id}/events (read with fetch streaming, so
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
      cell(tr, part ? `${part.part_id} (${part.recipe} v${part.recipe_version})` : "-");
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
  if (r.diameter_m !== undefined) rows.push(["diameter (measured)", mm(r.diameter_m)]);
  if (r.thermal) rows.push(["diameter at 20 C", mm(r.thermal.diameter_20c_m)]);
  if (u.expanded_m !== undefined) rows.push([`U (k = ${u.k})`, mm(u.expanded_m, 4)]);
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
  if (m.state === "done" || m.state === "failed") {
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
}

function onProgress(ev) {
  const row = document.querySelector(`#measurements tr[data-id="${ev.id}"] td.state`);
  if (row) row.textContent = ev.state;
  if (selected === ev.id) {
    $("detail-state").textContent = ev.state;
    setProgress(ev.progress, ev.message);
  }
}

async function start(ev) {
  ev.preventDefault();
  const body = { target: $("target").value };
  const speed = $("speed").value;
  if (speed) body.sweep = { speed_deg_s: Number(speed) };
  if ($("recipe").value.trim()) body.recipe = $("recipe").value.trim();
  if ($("part-id").value.trim()) body.part_id = $("part-id").value.trim();
  if ($("part-temp").value) body.part_temperature_c = Number($("part-temp").value);
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

document.addEventListener("DOMContentLoaded", () => {
  $("start-form").addEventListener("submit", start);
  $("refresh").addEventListener("click", loadList);
  $("token").addEventListener("change", loadList);
  health();
  loadList();
  setInterval(health, 5000);
  setInterval(loadList, 10000);
});
