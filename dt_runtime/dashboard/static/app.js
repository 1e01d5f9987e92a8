"use strict";
// The dashboard page: one EventSource on /api/events (a snapshot, then batches of what is new),
// the panels drawn from it, the 3D view (view3d.js) and the operators' actions. Numbers arrive
// in SI (m, s) and are shown in mm. window.dtStats keeps what the tests and benchmarks read:
// batches and messages received, latencies (ms) from the daemon's time stamp t and from the
// server's receipt rx to the frame that showed them (bounded arrays).
const MAX_TEL = 400;        // telemetry samples kept for the plot and the points in the view
const MAX_LAT = 5000;       // latency samples kept
const S = { scene: null, health: null, timeline: [], requests: new Map(), tel: [], last: null,
            token: null, operator: null, readOnly: true, group: null, bus: null, arrivals: [] };
const stats = window.dtStats = { batches: 0, messages: 0, skipped: 0, frames: 0, latT: [], latRx: [], connected: false,
                                 firstDataMs: null };  // performance.now() of the first frame that showed telemetry
const $ = (id) => document.getElementById(id);
const mm = (v) => (v == null ? "–" : (v * 1e3).toFixed(3));
const ago = (t) => (t == null ? "–" : `${Math.max(0, Date.now() / 1e3 - t).toFixed(1)} s ago`);
const clock = (t) => (t == null ? "–" : new Date(t * 1e3).toLocaleTimeString());
function el(tag, attrs = {}, ...kids) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) { if (k === "class") e.className = v; else e.setAttribute(k, v); }
  for (const k of kids) e.append(k instanceof Node ? k : document.createTextNode(String(k)));
  return e;
}
function pushBounded(arr, v, n) { arr.push(v); if (arr.length > n) arr.splice(0, arr.length - n); }

// --- the feed ---------------------------------------------------------------------------------
function connect() {
  const es = new EventSource("/api/events");
  es.addEventListener("snapshot", (e) => applySnapshot(JSON.parse(e.data)));
  es.onmessage = (e) => applyBatch(JSON.parse(e.data));
  es.onopen = () => setLink(true);
  es.onerror = () => {  // EventSource reconnects by itself and gets a new snapshot,
    setLink(false);
    // except after a reply that is not a stream (the server's 503 when too many pages are open: Retry-After 10 s)
    if (es.readyState === EventSource.CLOSED) setTimeout(connect, 10000);
  };
}
function setLink(on) {
  stats.connected = on;
  $("link").textContent = on ? "live" : "reconnecting";
  $("link").className = "badge " + (on ? "on" : "off");
}
function applySnapshot(s) {
  S.readOnly = s.read_only; S.bus = s.bus; S.group = s.bus && s.bus.group;
  $("prefix").textContent = s.bus ? s.bus.prefix : "";
  S.tel = s.telemetry.slice(-MAX_TEL); S.last = S.tel.length ? S.tel[S.tel.length - 1] : null;
  S.timeline = s.timeline; S.requests = new Map(s.requests.map((r) => [r.uid, r]));
  S.health = s.health;
  renderHealth(); renderEscalation(); renderTimeline(); renderRequests(); renderT(); scheduleDraw([]);
}
function applyBatch(b) {
  stats.batches++; stats.messages += b.telemetry.length; stats.skipped += b.skipped;
  for (const m of b.telemetry) pushBounded(S.tel, m, MAX_TEL);
  if (b.telemetry.length) {
    S.last = b.telemetry[b.telemetry.length - 1];
    pushBounded(S.arrivals, [performance.now(), b.telemetry.length], 200);
  }
  for (const { kind, msg } of b.events) {
    if (kind === "health") { S.health = msg; renderHealth(); }
    else if (kind === "state") { pushBounded(S.timeline, msg, 200); renderEscalation(); renderTimeline(); }
    else if (kind === "request") { S.requests.set(msg.uid, msg); renderRequests(); }
  }
  if (b.telemetry.length) { renderT(); renderEscalation(); }
  scheduleDraw(b.telemetry);
}

// --- drawing, once a frame --------------------------------------------------------------------
let pending = null;
function scheduleDraw(tel) {
  if (pending) { pending.push(...tel); return; }
  pending = tel.slice();
  requestAnimationFrame(() => {
    const shown = pending; pending = null;
    drawViews(); drawT(); drawStrip(); renderRate();
    stats.frames++;
    if (stats.firstDataMs == null && S.last) stats.firstDataMs = performance.now();
    const now = Date.now();  // the frame that shows them: bus-to-screen latency
    for (const m of shown) {
      if (m.t != null) pushBounded(stats.latT, now - m.t * 1e3, MAX_LAT);
      pushBounded(stats.latRx, now - m.rx * 1e3, MAX_LAT);
    }
  });
}
function renderRate() {
  const now = performance.now(), recent = S.arrivals.filter(([t]) => now - t < 2000);
  const n = recent.reduce((a, [, k]) => a + k, 0);
  $("rate").textContent = `${(n / 2).toFixed(0)} Hz`;
}

// --- the 3D view ------------------------------------------------------------------------------
let main = null, detail = null;
function setupViews() {
  const reach = S.scene.robot ? S.scene.robot.reach_m : 1.5;
  const c = S.scene.volume.corners;  // the middle of the calibrated volume (or of the reach) at the centre
  const mid = c.length ? [0, 1, 2].map((i) => c.reduce((a, p) => a + p[i], 0) / c.length) : [0.5 * reach, 0, 0.4 * reach];
  main = new View3D($("view3d"), { scale: $("view3d").height / (1.1 * reach), center: [mid[0] / 2, mid[1] / 2, mid[2]] });
  detail = new View3D($("detail"), { interactive: false });
  main.onchange = () => scheduleDraw([]);
}
function tRatio(m) {  // max |t| / t_crit over the axes: 1 is Eq. 17's threshold
  if (!m.t_stat || !S.scene) return null;
  return Math.max(...m.t_stat.map((t, i) => Math.abs(t) / S.scene.t_crit[i]));
}
function tColor(r) {
  if (r == null) return "#999";
  const hue = r > 1 ? 0 : 120 - 70 * Math.max(0, (r - 0.5) / 0.5);
  return `hsl(${hue} ${r > 1 ? 70 : 60}% ${r > 1 ? 48 : 40}%)`;
}
function drawViews() {
  if (!main) return;
  const v = main;
  v.clear();
  for (let g = -1; g <= 1.0001; g += 0.25) {  // the floor, z = 0, a 0.25 m grid
    v.line([-0.5, g, 0], [1.75, g, 0], "#e3e7ea");
  }
  for (let g = -0.5; g <= 1.7501; g += 0.25) v.line([g, -1, 0], [g, 1, 0], "#e3e7ea");
  v.line([0, 0, 0], [0.2, 0, 0], "#d33", 2); v.line([0, 0, 0], [0, 0.2, 0], "#3a3", 2);
  v.line([0, 0, 0], [0, 0, 0.2], "#36c", 2);
  const vol = S.scene && S.scene.volume;
  if (vol) for (const [a, b] of vol.edges) v.line(vol.corners[a], vol.corners[b], "#5b7fa8", 1, [5, 4]);
  if ($("arrows").checked) drawErrorMap(v, S.scene && S.scene.error_map);
  for (const m of S.tel) if (m.measured) v.dot(m.measured, 3, tColor(tRatio(m)));
  const last = S.last;
  if (last && last.arm) {
    v.polyline(last.arm, "#56606a", 9);
    v.polyline(last.arm, "#9aa5ae", 5);
    for (const p of last.arm.slice(1, -1)) v.dot(p, 5, "#3d454c");
    v.dot(last.arm[0], 9, "#3d454c");
  }
  if (last) {
    if (last.target) v.marker(last.target, "cross", 7, "#222");
    if (last.command) v.marker(last.command, "circle", 6, "#1565c0");
    if (last.measured) v.marker(last.measured, "diamond", 5, "#8e24aa");
  }
  drawDetail(last);
}
// The twin's e_LT_hat at its campaign's points (scene.error_map), scale times its length: from the
// commanded point to where the twin says the arm really goes, c - N ê (e = commanded - measured, Eq. 8).
function drawErrorMap(v, em) {
  if (!em || !em.points) return;
  em.points.forEach((c, i) => {
    const e = em.e_hat[i];
    v.arrow(c, c.map((x, k) => x - em.scale * e[k]), "#00897b", 2, 6);
  });
}
function renderErrorMapLegend() {
  const em = S.scene.error_map, key = $("arrows-key");
  if (!em || !em.points) { $("arrows").disabled = true; key.textContent = `error map: none (${em ? em.why : "no twin"})`; return; }
  key.textContent = `error map: ê_LT at the campaign's ${em.points.length} points (${em.rows} rows), drawn × ${em.scale} ` +
    `(longest ${(em.max_m * 1e3).toFixed(3)} mm, RMS ${(em.rms_m * 1e3).toFixed(3)} mm), pointing to where the arm goes`;
}
function drawDetail(last) {
  const d = detail;
  d.yaw = main.yaw; d.pitch = main.pitch;
  d.clear();
  if (!last || !last.target) { d.text([0, 0, 0], "no telemetry yet"); return; }
  const t = last.target, sub = (a, b) => a.map((x, i) => x - b[i]);
  const norm = (a) => Math.hypot(...a);
  const U = last.U && last.U.every((u) => u != null) ? last.U : null;
  const extent = Math.max(1e-4, last.command ? norm(sub(last.command, t)) : 0,
                          last.measured ? norm(sub(last.measured, t)) : 0, U ? Math.max(...U) : 0) * 1.25;
  d.center = t; d.scale = (d.canvas.width * 0.42) / extent;
  const ax = extent * 0.9;
  d.line(t, [t[0] + ax, t[1], t[2]], "#e5a0a0"); d.line(t, [t[0], t[1] + ax, t[2]], "#a0d0a0");
  d.line(t, [t[0], t[1], t[2] + ax], "#a0b5e5");
  d.text([t[0] + ax, t[1], t[2]], "x", "#c33", 2, 4); d.text([t[0], t[1] + ax, t[2]], "y", "#393", 2, 4);
  d.text([t[0], t[1], t[2] + ax], "z", "#36c", 2, 4);
  if (U) d.ellipsoid(t, U, "#ef6c00");
  d.marker(t, "cross", 8, "#222");
  if (last.command) { d.line(t, last.command, "#1565c0", 1, [3, 3]); d.marker(last.command, "circle", 6, "#1565c0"); }
  if (last.measured) d.marker(last.measured, "diamond", 6, "#8e24aa");
  $("scale").textContent = `view ±${(extent * 1e3).toFixed(3)} mm about the target`;
  const e = last.measured ? sub(last.measured, t).map((x) => (x * 1e3).toFixed(3)) : null;
  $("errors").textContent = (e ? `measured − target ${e.join(" / ")} mm` : "") +
    (U ? `; U95 ${U.map((u) => (u * 1e3).toFixed(3)).join(" / ")} mm` : "; U: none (sent uncorrected)") +
    (last.inside === false ? "; OUTSIDE the calibrated volume" : "");
}

// --- Eq. 17 -----------------------------------------------------------------------------------
function renderT() {
  const m = S.last;
  if (!m || !m.t_stat || !S.scene) return;
  $("tlast").textContent = `last t (x/y/z) ${m.t_stat.map((t) => t.toFixed(2)).join(" / ")}; t_crit ` +
    `${S.scene.t_crit.map((t) => t.toFixed(2)).join(" / ")} (α = ${S.scene.alpha}); ${m.passed ? "passed" : "FAILED"}`;
}
const T_MARGIN = { left: 40, bottom: 16, top: 4, right: 4 };  // the axes' labels live here, never on the traces
function niceStep(span) {  // 1, 2 or 5 times a power of ten, about 4 ticks over the span
  const raw = span / 4, p = 10 ** Math.floor(Math.log10(raw));
  return [1, 2, 5, 10].map((m) => m * p).find((s) => s >= raw);
}
function drawT() {
  const c = $("tplot"), g = c.getContext("2d"), W = c.width, H = c.height, M = T_MARGIN;
  g.fillStyle = "#fff"; g.fillRect(0, 0, W, H);
  const x0 = M.left, x1 = W - M.right, y0 = M.top, y1 = H - M.bottom;
  g.fillStyle = "#fbfcfd"; g.fillRect(x0, y0, x1 - x0, y1 - y0);
  if (!S.scene) return;
  const tc = Math.max(...S.scene.t_crit);
  const pts = S.tel.filter((m) => m.t_stat);
  const top = Math.max(2 * tc, ...pts.map((m) => Math.max(...m.t_stat.map(Math.abs)))) * 1.05;
  const y = (t) => (y0 + y1) / 2 - (t / top) * ((y1 - y0) / 2);
  g.font = "10px system-ui"; g.textAlign = "right"; g.textBaseline = "middle";
  const step = niceStep(2 * top);
  for (let t = -Math.floor(top / step) * step; t <= top + 1e-9; t += step) {  // the t axis: grid and labels
    g.strokeStyle = t === 0 ? "#bbb" : "#e6e9ec"; g.beginPath(); g.moveTo(x0, y(t)); g.lineTo(x1, y(t)); g.stroke();
    g.fillStyle = "#555"; g.fillText(`${+t.toFixed(6)}`, x0 - 4, y(t));
  }
  g.strokeStyle = "#c8323c"; g.setLineDash([6, 4]); g.lineWidth = 1;
  for (const s of [1, -1]) { g.beginPath(); g.moveTo(x0, y(s * tc)); g.lineTo(x1, y(s * tc)); g.stroke(); }
  g.setLineDash([]);
  g.fillStyle = "#c8323c"; g.fillText("t_crit", x0 - 4, Math.max(y0 + 5, y(tc) - 9));
  ["#d33", "#3a3", "#36c"].forEach((color, i) => {
    g.strokeStyle = color; g.beginPath();
    pts.forEach((m, k) => { const x = x0 + (k / Math.max(1, MAX_TEL - 1)) * (x1 - x0); if (k) g.lineTo(x, y(m.t_stat[i])); else g.moveTo(x, y(m.t_stat[i])); });
    g.stroke();
  });
  g.strokeStyle = "#888"; g.strokeRect(x0, y0, x1 - x0, y1 - y0);
  g.fillStyle = "#555"; g.textBaseline = "top"; g.textAlign = "left";
  g.fillText(`left axis: t; across: the last ${MAX_TEL} tests, oldest left (x red, y green, z blue)`, x0, y1 + 3);
}

// --- health and escalation --------------------------------------------------------------------
function renderHealth() {
  const h = S.health;
  if (!h) return;
  $("health-status").textContent = h.status; $("health-status").className = "status " + h.status;
  $("health-reason").textContent = h.reason || "";
  const rows = [["ticks", h.ticks], ["last tick", ago(h.last_tick)], ["commands refused in a row", h.refused_in_row],
    ["driver faults in a row", h.driver_faults_in_row], ["stale MVS readings", h.stale_measurements],
    ["MVS readings refused", h.mvs_refused], ["untested for", h.camera_untested_s == null ? "–" : `${h.camera_untested_s} s`],
    ["requests not acknowledged", h.outbox_pending], ["bus messages refused", h.bus_refused + (h.bus_last_refused ? ` (${h.bus_last_refused})` : "")],
    ["health sent", clock(h.t)]];
  $("counters").replaceChildren(...rows.map(([k, v]) => el("tr", {}, el("td", {}, k), el("td", {}, v == null ? "–" : v))));
}
function currentState() {
  const lastT = S.last ? S.last : null, lastS = S.timeline.length ? S.timeline[S.timeline.length - 1] : null;
  if (lastS && (!lastT || lastS.rx >= lastT.rx)) return lastS.dst;
  return lastT ? lastT.state : (S.health ? S.health.escalation : null);
}
function renderEscalation() {
  const st = currentState();
  if (st && $("esc-state").textContent !== st) { $("esc-state").textContent = st; $("esc-state").className = "status " + st; }
  renderValidityNow();
}
function renderTimeline() {
  const items = S.timeline.slice(-30).reverse().map((m) => {
    const ev = m.evidence || {};
    const why = ev.reason || ev.rule || (ev.by ? `by ${ev.by}: ${ev.note || ""}` : "");
    return el("li", { "data-dst": m.dst }, `${clock(m.rx)} ${m.src} → ${m.dst}${why ? " (" + why + ")" : ""}`);
  });
  $("timeline").replaceChildren(...(items.length ? items : [el("li", { class: "none" }, "no transition since this page joined")]));
}
const STATE_COLOR = { nominal: "#2e9d4f", suspect: "#d99a00", out_of_control: "#e0531f", rereference_offered: "#b36ae2",
                      maintenance_requested: "#c8323c",
                      halted: "#7a1020" };
function drawStrip() {  // the escalation states over the timeline's span, left to right
  const c = $("strip"), g = c.getContext("2d"), W = c.width, H = c.height;
  g.fillStyle = "#eef1f3"; g.fillRect(0, 0, W, H);
  const tl = S.timeline.slice(-50);
  if (!tl.length) return;
  const t0 = tl[0].rx, t1 = Date.now() / 1e3, span = Math.max(1, t1 - t0);
  tl.forEach((m, i) => {
    const a = ((m.rx - t0) / span) * W, b = i + 1 < tl.length ? ((tl[i + 1].rx - t0) / span) * W : W;
    g.fillStyle = STATE_COLOR[m.dst] || "#888"; g.fillRect(a, 0, Math.max(1, b - a), H);
  });
}

// --- maintenance requests and the operator ----------------------------------------------------
function renderRequests() {
  const rows = [...S.requests.values()].reverse().map((r) => {
    const state = r.done_by ? `done by ${r.done_by}: ${r.done_note}` :
      r.acked_by ? `acknowledged by ${r.acked_by}` : `waiting (sent ${r.attempt || 1}×)`;
    const note = el("input", { class: "note", placeholder: "what was done", "aria-label": "note" });
    const ack = el("button", { class: "ack" }, "acknowledge"), done = el("button", { class: "done" }, "done");
    ack.onclick = () => act("ack", r.uid, null);
    done.onclick = () => act("done", r.uid, note.value);
    for (const b of [ack, done]) if (!S.token) b.disabled = true;
    return el("tr", { "data-uid": r.uid }, el("td", {}, clock(r.created)), el("td", {}, r.kind || "–"),
              el("td", {}, r.reason || (r.evidence && r.evidence.rule) || "–"), el("td", { class: "state" }, state),
              el("td", {}, ack, note, done));
  });
  $("requests").tBodies[0].replaceChildren(...(rows.length ? rows : [el("tr", { class: "none" }, el("td", { colspan: "5" }, "none"))]));
}
async function act(action, uid, note) {
  const status = $("act-status");
  const res = await fetch(`/api/requests/${action}`, {
    method: "POST", headers: { "Content-Type": "application/json", Authorization: `Bearer ${S.token || ""}` },
    body: JSON.stringify(note == null ? { uid } : { uid, note }) });
  const body = await res.json().catch(() => ({}));
  status.className = res.ok ? "" : "error";
  status.textContent = res.ok ? `${action} by ${body.by}: published on ${body.published}`
                              : `refused (${res.status}): ${body.error || res.statusText}`;
}
$("login").addEventListener("submit", async (e) => {
  e.preventDefault();
  const token = $("token").value.trim();
  const res = await fetch("/api/whoami", { headers: { Authorization: `Bearer ${token}` } });
  const body = await res.json().catch(() => ({}));
  if (res.ok) { S.token = token; S.operator = body.operator; $("operator").textContent = `operator ${body.operator}`; }
  else { S.token = null; S.operator = null; $("operator").textContent = `not signed in (${res.status}): ${body.error || ""}`; }
  $("token").value = "";
  renderRequests();
});

// --- the twin's provenance --------------------------------------------------------------------
function renderProvenance() {
  const p = S.scene.provenance, rows = [];
  const sw = p.software || {};
  rows.push(["twin", p.twin], ["software", `${sw.name || "?"} ${sw.version || ""} (${(sw.commit || "").slice(0, 10)})`],
            ["calibrated", p.created || "–"], ["robot", `${p.robot || "–"}${S.scene.robot ? ` (${S.scene.robot.name}, ${S.scene.robot.dof} joints)` : ""}`],
            ["campaign", p.campaign || "–"]);
  for (const i of p.instruments || []) {
    rows.push([i.role, [i.kind, i.model, i.serial && `s/n ${i.serial}`, i.certificate && `certificate ${i.certificate}`,
                        i.calibration_date && `calibrated ${i.calibration_date}`, i.valid_until && `valid until ${i.valid_until}`]
                .filter(Boolean).join("; ")]);
  }
  if (p.environment && p.environment.temperature_c) {
    const t = p.environment.temperature_c; rows.push(["temperature", `${t.min}–${t.max} °C over ${t.n} rows`]);
  }
  rows.push(["validity now", validityNow()],
            ["validity at calibration", p.validity ? p.validity.line : "no summary beside the twin"]);
  rows.push(["Eq. 17", `α = ${S.scene.alpha}, t_crit ${S.scene.t_crit.map((t) => t.toFixed(3)).join(" / ")}`]);
  shownValidity = rows[rows.findIndex(([k]) => k === "validity now")][1];
  $("prov").replaceChildren(...rows.flatMap(([k, v]) => [el("dt", {}, k),
    el("dd", k === "validity now" ? { id: "validity-now", class: v.startsWith("NOT VALID") ? "bad" : "" } : {}, v)]));
}

// The calibration's validity line says whether the stated U covered the errors then; the escalation
// says whether the twin holds now: a maintenance request (or a halt) is the worse state and is shown first.
function validityNow() {
  const st = currentState();
  if (st === "maintenance_requested" || st === "halted")
    return `NOT VALID now: ${st} (the in-service Eq. 17 test failed; the calibration's OK below no longer holds)`;
  if (st === "out_of_control" || st === "suspect") return `in doubt now: ${st} (Eq. 17 failures in service)`;
  return st ? `as calibrated: ${st} (Eq. 17 passes in service)` : "no state from the cell yet";
}
let shownValidity = null;
function renderValidityNow() {  // the provenance panel again when the state changes what it says
  if (!S.scene) return;
  const now = validityNow();
  if (now !== shownValidity) { shownValidity = now; renderProvenance(); }
}

fetch("/api/scene").then((r) => r.json()).then((sc) => {
  S.scene = sc; $("metrology").hidden = !sc.metrology; setupViews(); renderProvenance(); renderErrorMapLegend(); renderT(); scheduleDraw([]);
  $("arrows").addEventListener("change", () => scheduleDraw([]));
  connect();
});
