// agos human console: draws the board's state (server-sent events from /api/events) and sends the
// person's decision to /api/act. Play mode shows, for one role at a time, what that role's agent
// receives; spectate mode shows the visualisation stream, read-only. No framework, no build step.
"use strict";

const $ = (id) => document.getElementById(id);
const esc = (s) => String(s ?? "").replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
const params = new URLSearchParams(location.search);
const S = {
  snap: null, at: 0, role: params.get("role"), shownKey: null, selected: null, rowKey: null, annotating: false,
  sending: false, feedback: [],
};

// ----- connection ----------------------------------------------------------------------------------
function connect() {
  const es = new EventSource("/api/events");
  es.onopen = () => { $("link").textContent = "connected"; $("link").classList.remove("down"); };
  es.onerror = () => { $("link").textContent = "reconnecting…"; $("link").classList.add("down"); };
  es.onmessage = (e) => { S.snap = JSON.parse(e.data); S.at = performance.now(); render(); };
}

function say(kind, text) {
  S.feedback.unshift({ kind, text, t: new Date().toLocaleTimeString() });
  S.feedback = S.feedback.slice(0, 3);
  $("feedback").innerHTML = S.feedback.map((f, k) =>
    `<div class="${f.kind}${k ? " old" : ""}" data-kind="${f.kind}">${esc(f.t)} · ${esc(f.text)}</div>`).join("");
}

const fmtS = (s) => {
  s = Math.max(0, Math.floor(s));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), x = s % 60;
  return (h ? `${h}:${String(m).padStart(2, "0")}` : `${m}`) + `:${String(x).padStart(2, "0")}`;
};

// ----- play --------------------------------------------------------------------------------------
function render() {
  const snap = S.snap;
  if (snap.mode === "spectate") { renderSpectate(snap); return; }
  $("play").hidden = false;
  if (!S.role || !snap.roles.includes(S.role)) S.role = snap.roles[0];
  const mine = snap.by_role[S.role];
  if (!mine.asked && !params.get("role")) {  // playing both: go where a decision waits
    const other = snap.roles.find((r) => snap.by_role[r].asked);
    if (other) S.role = other;
  }
  $("tabs").innerHTML = snap.roles.length > 1 ? snap.roles.map((r) =>
    `<button data-role="${r}" class="${r === S.role ? "on" : ""} ${snap.by_role[r].asked ? "asks" : ""}">${r.toUpperCase()}</button>`).join("") : "";
  for (const b of $("tabs").querySelectorAll("button")) b.onclick = () => { S.role = b.dataset.role; S.shownKey = null; render(); };
  const slot = snap.by_role[S.role];
  const view = slot.asked || slot.last;
  const key = view ? `${view.state.episode_id}/${view.state.attempt}/${S.role}/${view.state.decision_index}/${!!slot.asked}` : null;
  if (key !== S.shownKey) {
    S.shownKey = key; S.selected = null; S.annotating = false; S.rowKey = null;
    drawDecision(view, !!slot.asked);
  }
  drawLists(snap, view);
  tick();
  document.body.dataset.asked = slot.asked ? "yes" : "no";
  document.body.dataset.role = S.role;
  document.body.dataset.mode = view ? view.state.mode : "";
  document.body.dataset.decision = view ? view.state.decision_index : "";
}

function current() {
  const slot = S.snap && S.snap.by_role[S.role];
  return slot && slot.asked;
}

function drawDecision(view, asked) {
  if (!view) {
    $("where").textContent = `you play the ${S.snap.roles.map((r) => r.toUpperCase()).join(" and ")} · waiting for an episode`;
    for (const id of ["camera", "refs", "map", "status", "choices", "hint"]) $(id).innerHTML = "";
    $("camera").innerHTML = `<div class="empty">No decision yet: the console waits for the world to ask.</div>`;
    updateSelected();
    return;
  }
  const st = view.state;
  $("where").textContent = `run ${st.run_id} · ${st.episode_id}${st.attempt > 1 ? ` (attempt ${st.attempt})` : ""} · ${S.role.toUpperCase()} decision ${st.decision_index}`;
  const img = (label) => view.images.find((i) => i.label === label);
  const fig = (i, extra = "") => i ? `<figure data-label="${i.label}"><img src="${i.url}" alt="${esc(i.label)}">${extra}<figcaption>${esc(i.caption)}</figcaption></figure>` : "";
  let cam = "";
  if (st.role === "uav") {
    const rows = st.grid.rows, cols = st.grid.cols;
    let cells = "";
    for (const r of rows) for (let c = 1; c <= cols; c++) cells += `<div data-cell="${r}${c}" title="${r}${c}"></div>`;
    const canAnnotate = asked && st.legal_actions.includes("ANNOTATE_CANDIDATE");
    cam = fig(img("aerial_grid"), `<div class="grid${canAnnotate ? "" : " off"}" style="grid-template-columns:repeat(${cols},1fr);grid-template-rows:repeat(${rows.length},1fr)">${cells}</div>`);
  } else if (st.mode === "stop_6view") {
    cam = `<div class="six">${view.images.filter((i) => !i.label.startsWith("target_ref_") && i.label !== "topdown_map").map((i) => fig(i)).join("")}</div>`;
  } else {
    cam = fig(img("forward"));
  }
  $("camera").innerHTML = cam;
  for (const d of $("camera").querySelectorAll(".grid div")) d.onclick = () => pickCell(d.dataset.cell, "mouse");
  $("refs").innerHTML = view.images.filter((i) => i.label.startsWith("target_ref_")).map((i) => fig(i)).join("");
  drawMap(view, asked);
  const b = st.budget;
  const mate = st.teammate;
  $("status").innerHTML = `<table>
    <tr><td>role · mode</td><td><span class="role-${st.role}">${st.role.toUpperCase()}</span> · ${esc(st.mode.replace("_", " "))}${st.fresh_stop_observe ? " (fresh)" : ""}</td></tr>
    <tr><td>decision</td><td>${st.decision_index} · sim time ${st.sim_time_s.toFixed(1)} s</td></tr>
    <tr><td>shared budget</td><td>${b.used} of ${b.total} used, <b>${b.left} left</b><div class="bar"><i style="width:${Math.min(100, 100 * b.used / Math.max(1, b.total))}%"></i></div></td></tr>
    <tr><td>annotations</td><td>${st.annotations.used} of ${st.annotations.max}</td></tr>
    <tr><td>you are at</td><td>(${st.pose.position_m.join(", ")}) m, heading ${st.pose.heading_deg}°${st.role === "uav" ? `, ${st.pose.altitude_m} m up` : ""}</td></tr>
    <tr><td>${mate ? mate.role.toUpperCase() : "teammate"}</td><td>${mate ? `last reported at (${mate.position_m.join(", ")}) m` : "no report received yet"}</td></tr>
  </table>`;
  $("hint").textContent = st.hint;
  $("choices").innerHTML = asked ? view.choices.map((c, k) =>
    `<button class="choice ${c.action === "CONFIRM" ? "confirm" : ""} ${c.action === "REJECT" ? "reject" : ""}" data-k="${k}" data-action="${c.action}"${c.waypoint_id ? ` data-waypoint="${esc(c.waypoint_id)}"` : ""}>${c.key ? `<kbd>${c.key.toUpperCase()}</kbd>` : ""}${esc(c.label)}</button>`).join("")
    : `<div class="list"><div class="none">${view.decided ? `Sent: ${esc(view.decided)}.` : "Not answered."} Nothing is asked of the ${S.role.toUpperCase()} now.</div></div>`;
  for (const btn of $("choices").querySelectorAll(".choice")) btn.onclick = () => choose(view.choices[+btn.dataset.k], "mouse");
  updateSelected();
}

function drawMap(view, asked) {
  const st = view.state, m = view.images.find((i) => i.label === "topdown_map");
  if (!m || !st.map) { $("map").innerHTML = ""; return; }
  const n = st.map.side_px;
  let svg = "";
  for (const p of st.searchable_px) svg += `<circle cx="${p[0]}" cy="${p[1]}" r="2.2" fill="#8a94a6" opacity=".8"/>`;
  for (const c of st.candidates) {
    if (c.polygon_px.length) svg += `<polygon points="${c.polygon_px.map((p) => p.join(",")).join(" ")}" fill="rgba(255,123,0,.15)" stroke="#ff7b00" stroke-width="2"/>`;
    const top = c.polygon_px.length ? Math.min(...c.polygon_px.map((p) => p[1])) : c.map_px && c.map_px[1];
    if (c.map_px) svg += `<text x="${c.map_px[0]}" y="${top - 5}" font-size="12" font-weight="700" fill="#b35400" stroke="#fff" stroke-width="3" paint-order="stroke" text-anchor="middle">${esc(c.id)} ${esc(c.status)}</text>`;
  }
  if (asked && (st.legal_actions.includes("MOVE_TO_UAV_WAYPOINT") || st.legal_actions.includes("MOVE_TO_ROAD_WAYPOINT"))) {
    for (const o of st.options) if (o.map_px) {
      svg += `<g class="opt" data-waypoint="${esc(o.id)}"><circle cx="${o.map_px[0]}" cy="${o.map_px[1]}" r="8"/><text x="${o.map_px[0]}" y="${o.map_px[1]}">${o.n <= 9 ? o.n : "·"}</text><title>${esc(o.id)} (${esc(o.option || o.kind)})</title></g>`;
    }
  }
  $("map").innerHTML = `<figure data-label="topdown_map"><img src="${m.url}" alt="map"><figcaption>${esc(m.caption)}</figcaption></figure><svg viewBox="0 0 ${n} ${n}" preserveAspectRatio="none">${svg}</svg>`;
  for (const g of $("map").querySelectorAll(".opt")) {
    g.onclick = () => {
      const c = view.choices.find((x) => x.waypoint_id === g.dataset.waypoint);
      if (c) choose(c, "mouse");
    };
  }
}

function drawLists(snap, view) {
  const st = view && view.state;
  $("candidates").innerHTML = st && st.candidates.length ? st.candidates.map((c) =>
    `<div><b>${esc(c.id)}</b> cell ${esc(c.cell)} <span class="st ${c.status}">${esc(c.status)}</span> · ${c.distance_m} m away${c.approach ? ` · via ${esc(c.approach)}` : ""}</div>`).join("")
    : `<div class="none">none known to the ${S.role.toUpperCase()}</div>`;
  $("messages").innerHTML = st && st.messages.length ? st.messages.slice().reverse().map((m) =>
    `<div><span class="role-${m.from}">${m.from.toUpperCase()}</span> (t ${m.delivered_s} s): ${esc(m.text)}</div>`).join("")
    : `<div class="none">no message delivered</div>`;
  const mine = snap.history.filter((h) => h.role === S.role);
  $("history").innerHTML = mine.length ? mine.map((h) =>
    `<div>#${h.decision_index} ${h.action ? esc(h.action) : "<i>not answered (the world applied WAIT)</i>"} · ${h.waited_s} s${h.message ? ` · “${esc(h.message)}”` : ""}</div>`).join("")
    : `<div class="none">none yet</div>`;
  const fresh = snap.notices.filter((n) => !S.seenNotices || !S.seenNotices.has(n.utc + n.text));
  S.seenNotices = new Set(snap.notices.map((n) => n.utc + n.text));
  if (S.noticesPrimed) for (const n of fresh.reverse()) say(n.level === "warning" ? "warn" : "info", n.text);
  S.noticesPrimed = true;
}

function tick() {
  const slot = S.snap && S.snap.mode === "play" ? S.snap.by_role[S.role] : null;
  if (!slot) return;
  const clock = $("clock");
  if (!slot.asked) {
    clock.className = "clock idle";
    clock.textContent = `Nothing is asked of the ${S.role.toUpperCase()} now: the world is simulating, or waiting for your teammate.`;
    document.title = "agos human console";
    return;
  }
  const st = slot.asked.state;
  const waited = slot.asked.waited_s + (performance.now() - S.at) / 1000;
  const limit = st.decision_timeout_s;
  clock.className = "clock";
  clock.innerHTML = `The world waits for you: <b>${fmtS(waited)}</b> so far` + (limit ?
    ` · it waits up to ${fmtS(limit)} (<span id="left">${fmtS(limit - waited)}</span> left), then applies WAIT` : "") +
    (slot.queued ? ` · ${slot.queued} more decision(s) queued` : "");
  document.title = `● ${S.role.toUpperCase()} decision ${st.decision_index} · agos`;
}

function choose(choice, input) {
  if (!current()) return;
  if (choice.needs === "cell") {
    S.selected = { ...choice, cell: S.selected && S.selected.cell, input };
    S.annotating = true;
  } else {
    S.selected = { ...choice, input };
    S.annotating = false;
  }
  updateSelected();
}

function pickCell(cell, input) {
  const asked = current();
  if (!asked || !asked.state.legal_actions.includes("ANNOTATE_CANDIDATE")) return;
  const annotate = asked.choices.find((c) => c.action === "ANNOTATE_CANDIDATE");
  S.selected = { ...annotate, cell, input };
  S.annotating = false;
  updateSelected();
}

function updateSelected() {
  const s = S.selected, el = $("selected");
  for (const b of document.querySelectorAll(".choice")) {
    const c = current() && current().choices[+b.dataset.k];
    b.classList.toggle("sel", !!(s && c && c.action === s.action && (c.waypoint_id || null) === (s.waypoint_id || null) && (c.candidate_id || null) === (s.candidate_id || null)));
  }
  for (const d of document.querySelectorAll(".grid div")) d.classList.toggle("sel", !!(s && s.cell === d.dataset.cell));
  for (const g of document.querySelectorAll(".mapwrap .opt")) g.classList.toggle("sel", !!(s && s.waypoint_id === g.dataset.waypoint));
  const ready = !!(current() && s && (!s.needs || s.cell));
  $("send").disabled = !ready;
  el.classList.toggle("on", ready);
  el.textContent = !current() ? "Nothing to decide now." : !s ? "Nothing selected." :
    s.needs && !s.cell ? "Annotate: click a cell on the grid, or type it (row A-E, then column 1-5)." :
    `Selected: ${s.action}${s.waypoint_id ? " " + s.waypoint_id : ""}${s.cell ? " " + s.cell : ""}${s.candidate_id ? " " + s.candidate_id : ""}`;
}

// Send a decision. ``fields`` overrides what is selected (scripts and tests use window.agos.send).
async function send(fields, input) {
  const asked = current();
  const base = asked ? { episode_id: asked.state.episode_id, attempt: asked.state.attempt, decision_index: asked.state.decision_index } : {};
  const choice = fields || S.selected;
  if (!choice) { say("warn", "Select a choice first."); return null; }
  if (S.sending && !fields) { say("warn", "Your decision is being sent; the repeated click was ignored."); return null; }
  const body = { role: S.role, ...base, action: choice.action, waypoint_id: choice.waypoint_id, cell: choice.cell,
    candidate_id: choice.candidate_id, message: $("message").value || null, input: input || choice.input || "script", ...fields };
  S.sending = true;
  try {
    const r = await fetch("/api/act", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
    const answer = await r.json();
    say(answer.ok ? "ok" : r.status === 409 ? "warn" : "bad", answer.message);
    if (answer.ok) { $("message").value = ""; S.selected = null; updateSelected(); }
    return answer;
  } catch (e) {
    say("bad", `Could not reach the console server (${e}); nothing was sent.`);
    return null;
  } finally {
    S.sending = false;
  }
}

function onKey(e) {
  if (!S.snap || S.snap.mode !== "play") return;
  const typing = document.activeElement === $("message");
  if (e.key === "Enter") { e.preventDefault(); if (!$("send").disabled) send(null, "keyboard"); return; }
  if (e.key === "Escape") { if (typing) $("message").blur(); S.selected = null; S.annotating = false; S.rowKey = null; updateSelected(); return; }
  if (typing || e.ctrlKey || e.metaKey || e.altKey) return;
  const asked = current();
  if (!asked) return;
  const k = e.key.toLowerCase();
  if (k === "m") { e.preventDefault(); $("message").focus(); return; }
  if (S.annotating) {  // a cell: row letter, then column digit
    const rows = asked.state.grid.rows.toLowerCase();
    if (!S.rowKey && rows.includes(k)) { S.rowKey = k.toUpperCase(); $("selected").textContent = `Annotate: row ${S.rowKey}, now the column (1-${asked.state.grid.cols})`; return; }
    if (S.rowKey && /^[1-9]$/.test(k) && +k <= asked.state.grid.cols) { pickCell(S.rowKey + k, "keyboard"); S.rowKey = null; return; }
  }
  const c = asked.choices.find((x) => x.key === k);
  if (c) { e.preventDefault(); choose(c, "keyboard"); }
}

// ----- spectate ----------------------------------------------------------------------------------
function renderSpectate(snap) {
  $("spectate").hidden = false;
  $("where").textContent = `spectating ${snap.run_id ? "run " + snap.run_id : "every run"} · read-only`;
  if (!snap.episodes.length) { $("spectate").innerHTML = `<div class="empty">No episode seen yet on the visualisation stream.</div>`; return; }
  $("spectate").innerHTML = snap.episodes.slice(0, 3).map(episodeCard).join("");
}

function episodeCard(ep) {
  const views = (role) => {
    const f = ep.frames[role];
    if (!f) return `<div class="none">no view yet</div>`;
    const names = Object.keys(f.views);
    return `<div class="${names.length > 1 ? "thumbs" : ""}">${names.map((n) => `<figure><img src="${f.views[n]}" alt="${esc(n)}"><figcaption>${esc(n)}</figcaption></figure>`).join("")}</div>
      <figcaption>decision ${f.decision_index} · t ${f.sim_time_s} s</figcaption>`;
  };
  const out = ep.outcome ? ` · <b>${esc(ep.outcome.termination)}</b>${ep.outcome.success ? " (success)" : ""}` : "";
  const steps = ep.steps.map((s) => `<div><span class="role-${s.role}">${s.role.toUpperCase()}</span> #${s.decision_index} ${esc(s.applied)}${s.argument ? " " + esc(s.argument) : ""}${s.fallback_reason ? ` <i>(fallback: ${esc(s.fallback_reason)})</i>` : ""}${s.message ? ` · “${esc(s.message)}”` : ""}</div>`).join("");
  return `<div class="episode" data-episode="${esc(ep.episode_id)}">
    <h2>${esc(ep.run_id)} / ${esc(ep.episode_id)} · ${esc(ep.difficulty || "")} · ${esc(ep.town_id || "")} · t ${ep.sim_time_s ?? 0} s${ep.budget ? ` · ${ep.budget.used}/${ep.budget.total} decisions` : ""}${out}</h2>
    <div class="views"><div><h3>UAV view</h3>${views("uav")}</div><div><h3>UGV view</h3>${views("ugv")}</div></div>
    <div><h3>Paths and candidates</h3>${miniMap(ep)}<h3>Candidates</h3><div class="list">${ep.candidates.map((c) => `<div><b>${esc(c.id)}</b> ${esc(c.cell)} <span class="st ${c.status}">${esc(c.status)}</span></div>`).join("") || `<div class="none">none</div>`}</div></div>
    <div><h3>Decisions, newest first</h3><div class="list steps" style="max-height:420px">${steps || `<div class="none">none yet</div>`}</div>
      <h3>Messages</h3><div class="list">${ep.messages.map((m) => `<div><span class="role-${m.from}">${m.from.toUpperCase()}</span>: ${esc(m.text)}</div>`).join("") || `<div class="none">none</div>`}</div></div>
  </div>`;
}

function miniMap(ep) {
  const pts = [...ep.paths.uav, ...ep.paths.ugv, ...ep.candidates.flatMap((c) => c.polygon_m)];
  let [x0, y0, x1, y1] = ep.region_m || [0, 0, 0, 0];
  if (!ep.region_m) {
    if (!pts.length) return `<div class="none">no positions yet</div>`;
    x0 = Math.min(...pts.map((p) => p[0])) - 20; x1 = Math.max(...pts.map((p) => p[0])) + 20;
    y0 = Math.min(...pts.map((p) => p[1])) - 20; y1 = Math.max(...pts.map((p) => p[1])) + 20;
  }
  const side = Math.max(x1 - x0, y1 - y0, 1), P = (p) => `${(p[0] - x0) / side * 300},${300 - (p[1] - y0) / side * 300}`;
  const line = (path, colour) => path.length ? `<polyline points="${path.map(P).join(" ")}" fill="none" stroke="${colour}" stroke-width="2"/><circle cx="${P(path[path.length - 1]).split(",")[0]}" cy="${P(path[path.length - 1]).split(",")[1]}" r="4" fill="${colour}"/>` : "";
  const cands = ep.candidates.map((c) => c.polygon_m.length ? `<polygon points="${c.polygon_m.map(P).join(" ")}" fill="rgba(255,123,0,.15)" stroke="#ff7b00"/>` : "").join("");
  return `<svg class="minimap" viewBox="0 0 300 300">${cands}${line(ep.paths.uav, "#0aa5c0")}${line(ep.paths.ugv, "#c0267f")}</svg>`;
}

// ----- start -------------------------------------------------------------------------------------
$("send").onclick = () => send(null, "mouse");
document.addEventListener("keydown", onKey);
setInterval(tick, 250);
window.agos = { send: (fields) => send(fields, "script"), state: () => S.snap, role: () => S.role, choose, pickCell };
connect();
