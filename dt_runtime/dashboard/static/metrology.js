"use strict";
// The metrologist's view: a result of dt compare / dt diagnose or a twin (/api/results, /api/result),
// its residual map per commanded point in 3D (residuals.csv: compare's models, or diagnose's first and
// final model held out; rows filtered, then aggregated per point: mean residual and row count,
// coloured by |mean r|), the diagnose steps and the report's own figures. Files hold
// mm; the 3D view draws m. window.dtMetro keeps what the tests read.
const R = { res: null, rows: null, models: [], view: null, points: [], vmax: 1, floor: null };
const stats = window.dtMetro = { loaded: null, kind: null, points: 0, rows: 0, rms: null, draws: 0 };
const $ = (id) => document.getElementById(id);
const fx = (v, d = 4) => (v == null || !isFinite(v) ? "–" : Number(v).toFixed(d));
function el(tag, attrs = {}, ...kids) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) { if (k === "class") e.className = v; else e.setAttribute(k, v); }
  for (const k of kids) e.append(k instanceof Node ? k : document.createTextNode(String(k)));
  return e;
}
function options(sel, items) {  // items: [value, label]
  sel.replaceChildren(...items.map(([v, l]) => el("option", { value: v }, l)));
}

// --- the list and one result -------------------------------------------------------------------
async function start() {
  const r = await fetch("/api/results"), body = await r.json();
  $("root").textContent = body.root;
  $("live").hidden = !body.live;
  options($("result"), body.results.map((x) => [x.name, `${x.name} (${x.kind})`]));
  if (!body.results.length) { $("status").textContent = `no result under ${body.root}`; return; }
  const wanted = new URLSearchParams(location.search).get("name");
  const first = body.results.find((x) => x.name === wanted) || body.results.find((x) => x.kind === "compare") || body.results[0];
  $("result").value = first.name;
  $("result").addEventListener("change", () => open($("result").value));
  for (const id of ["f-model", "f-session", "f-speed", "f-joint", "f-dir"]) $(id).addEventListener("change", () => redraw());
  R.view = new View3D($("map3d"), {});
  R.view.onchange = () => draw();
  await open(first.name);
}
async function open(name) {
  $("status").textContent = `loading ${name}…`;
  const r = await fetch(`/api/result?name=${encodeURIComponent(name)}`), res = await r.json();
  if (!r.ok) { $("status").textContent = `${name}: ${res.error}`; $("status").className = "error"; return; }
  R.res = res; $("status").className = ""; $("status").textContent = "";
  history.replaceState(null, "", `?name=${encodeURIComponent(name)}`);
  R.rows = res.rows ? columns(res.rows) : null;
  R.floor = res.noise_floor_mm > 0 ? res.noise_floor_mm : null;  // mm, 3D RMS: where the colour scale starts
  renderAbout(); renderSteps(); renderFigures(); setupFilters(); fitView(); redraw();
  stats.loaded = name; stats.kind = res.kind;
}
function columns(rows) {  // text columns of residuals.csv -> numbers (NaN for an empty cell)
  const out = {};
  for (const [k, v] of Object.entries(rows)) out[k] = (k === "session" || k === "point_id") ? v : v.map((s) => (s === "" ? NaN : Number(s)));
  return out;
}

// --- filters and the per-point aggregation -----------------------------------------------------
function setupFilters() {
  const c = R.rows;
  $("filters").hidden = !c;
  if (!c) return;
  R.models = Object.keys(c).filter((k) => k.startsWith("r_x:")).map((k) => k.slice(4));
  options($("f-model"), R.models.map((m) => [m, m]));
  $("f-model").value = R.models[R.models.length - 1];  // the primary model, as the report's map
  const sessions = c.session ? [...new Set(c.session)].sort() : [];
  $("l-session").hidden = sessions.length < 2;
  options($("f-session"), [["", "all"], ...sessions.map((s) => [s, (R.res.sessions || {})[s] || `session ${s}`])]);
  const speeds = c.speed ? [...new Set(c.speed.filter(isFinite))].sort((a, b) => a - b) : [];
  $("l-speed").hidden = speeds.length < 2;
  options($("f-speed"), [["", "all"], ...speeds.map((v) => [String(v), `${v} mm/s`])]);
  const joints = Object.keys(c).filter((k) => k.startsWith("approach_q") && c[k].some((d) => d !== c[k][0]));
  $("l-dir").hidden = !joints.length;
  options($("f-joint"), [["", "any joint"], ...joints.map((k) => [k, k.slice(9)])]);
  options($("f-dir"), [["1", "+ (angle rose)"], ["-1", "− (angle fell)"], ["0", "still"]]);
}
function selectedRows() {
  const c = R.rows, n = c.x.length, keep = [];
  const s = $("f-session").value, v = $("f-speed").value, j = $("f-joint").value, d = Number($("f-dir").value);
  for (let i = 0; i < n; i++) {
    if (s && c.session && c.session[i] !== s) continue;
    if (v && c.speed && c.speed[i] !== Number(v)) continue;
    if (j && c[j][i] !== d) continue;
    keep.push(i);
  }
  return keep;
}
function aggregate(rows, model) {  // per commanded point (1 um, as analysis.points.per_point)
  const c = R.rows, rx = c[`r_x:${model}`], ry = c[`r_y:${model}`], rz = c[`r_z:${model}`], f = c[`fails:${model}`];
  const pts = new Map();
  for (const i of rows) {
    const key = `${Math.round(c.x[i] * 1e3)},${Math.round(c.y[i] * 1e3)},${Math.round(c.z[i] * 1e3)}`;
    let p = pts.get(key);
    if (!p) { p = { at: [c.x[i], c.y[i], c.z[i]], r: [0, 0, 0], n: 0, fails: 0 }; pts.set(key, p); }
    p.r[0] += rx[i]; p.r[1] += ry[i]; p.r[2] += rz[i]; p.n++; if (f && f[i] === 1) p.fails++;
  }
  const out = [...pts.values()];
  for (const p of out) { p.r = p.r.map((v) => v / p.n); p.norm = Math.hypot(...p.r); }
  return out;
}
function rms3(rows, model) {  // the 3D RMS of the rows' residuals (mm), as the results' figures (rows, not points)
  const c = R.rows, rx = c[`r_x:${model}`], ry = c[`r_y:${model}`], rz = c[`r_z:${model}`];
  let sum = 0, n = 0;
  for (const i of rows) { const q = rx[i] ** 2 + ry[i] ** 2 + rz[i] ** 2; if (isFinite(q)) { sum += q; n++; } }
  return n ? Math.sqrt(sum / n) : null;
}
function percentile(values, q) {
  const s = values.filter(isFinite).sort((a, b) => a - b);
  return s.length ? s[Math.min(s.length - 1, Math.floor(q * (s.length - 1)))] : 0;
}
function redraw() {
  const res = R.res;
  if (R.rows) {
    const model = $("f-model").value, rows = selectedRows();
    // the scale of the whole result for this model (95th percentile, as the report's map): a filter does not rescale;
    // a diagnose result's first and final model share one (the larger), so the map shows where the error went
    const all = R.rows.x.map((_, i) => i);
    R.vmax = scaleTop(Math.max(...(res.kind === "diagnose" ? R.models : [model]).map((m) =>
      percentile(aggregate(all, m).map((p) => p.norm), 0.95))));
    R.points = aggregate(rows, model);
    stats.rows = rows.length;
    stats.rms = rms3(rows, model);
    $("map-why").textContent = "";
    $("map-what").textContent = `r = e − ê of ${model} per commanded point (replicates aggregated: mean and count)` +
      (res.kind === "diagnose" ? ", each row held out (predicted by the model fitted without its point)" : "") +
      "; drag to turn, wheel to zoom; robot frame";
  } else if (res.kind === "twin" && res.error_map && res.error_map.points) {
    const em = res.error_map;
    R.points = em.points.map((p, i) => { const r = em.e_hat[i].map((v) => v * 1e3);
      return { at: p.map((v) => v * 1e3), r, n: em.count[i], fails: 0, norm: Math.hypot(...r) }; });
    R.vmax = scaleTop(percentile(R.points.map((p) => p.norm), 0.95));
    stats.rows = em.rows; stats.rms = null;
    $("map-why").textContent = `the twin's predicted error ê_LT at its campaign's points (${em.campaign}); arrows × ${em.scale}, ` +
      "pointing to where the arm goes";
    $("map-what").textContent = "ê_LT per DOE point (its rows averaged); drag to turn, wheel to zoom; robot frame";
  } else {
    R.points = []; stats.rows = 0; stats.rms = null;
    $("map-why").textContent = res.rows_why || (res.error_map && res.error_map.why) || "no residuals in this result";
  }
  stats.points = R.points.length;
  document.querySelector("#map-panel .views").hidden = !R.points.length && !R.rows;
  $("shown").textContent = `${R.points.length} points (${stats.rows} rows) shown` +
    (R.rows && stats.rms != null ? `, 3D RMS ${fx(stats.rms)} mm` : "");
  renderScale(); renderWorst(); draw();
}

// --- drawing -----------------------------------------------------------------------------------
// |mean r| from the noise floor (blue: at or below it, the residual is noise) to R.vmax (red): a result
// whose residuals all lie below the floor is all blue, not painted red by its own 95th percentile.
// Without a stated floor the scale starts at 0.
function colour(v) {
  const floor = R.floor || 0, x = Math.max(0, Math.min(1, (v - floor) / Math.max(1e-12, R.vmax - floor)));
  return `hsl(${240 - 240 * x} 75% ${45 + 5 * x}%)`;
}
const FLOOR_TIMES = 3;  // red needs at least this many noise floors
function scaleTop(p95) {  // the red end: the result's 95th percentile, never below FLOOR_TIMES noise floors
  return Math.max(p95, FLOOR_TIMES * (R.floor || 0)) || 1e-3;
}
function fitView() {
  R.box = null;
  const v = R.view, P = R.rows ? R.rows.x.map((x, i) => [x, R.rows.y[i], R.rows.z[i]]) :
    (R.res.error_map && R.res.error_map.points ? R.res.error_map.points.map((p) => p.map((x) => x * 1e3)) : []);
  if (!P.length) return;
  const lo = [0, 1, 2].map((k) => Math.min(...P.map((p) => p[k]))), hi = [0, 1, 2].map((k) => Math.max(...P.map((p) => p[k])));
  v.center = lo.map((l, k) => (l + hi[k]) / 2e3);
  v.scale = (0.8 * Math.min(v.canvas.width, v.canvas.height)) / Math.max(1e-3, Math.hypot(...hi.map((h, k) => h - lo[k])) / 1e3);
  R.box = [lo.map((x) => x / 1e3), hi.map((x) => x / 1e3)];
}
function draw() {
  const v = R.view;
  if (!v) return;
  v.clear();
  if (R.box) {  // the points' bounding box and the robot frame's axes at its corner
    const [a, b] = R.box, c = (i, j, k) => [[a, b][i][0], [a, b][j][1], [a, b][k][2]];
    for (const [p, q] of [[[0, 0, 0], [1, 0, 0]], [[0, 0, 0], [0, 1, 0]], [[0, 0, 0], [0, 0, 1]], [[1, 1, 0], [0, 1, 0]],
                          [[1, 1, 0], [1, 0, 0]], [[1, 1, 0], [1, 1, 1]], [[0, 1, 1], [0, 1, 0]], [[0, 1, 1], [0, 0, 1]],
                          [[0, 1, 1], [1, 1, 1]], [[1, 0, 1], [1, 0, 0]], [[1, 0, 1], [0, 0, 1]], [[1, 0, 1], [1, 1, 1]]]) {
      v.line(c(...p), c(...q), "#d5dbe0", 1, [4, 4]);
    }
    const o = a, L = 0.1;
    v.line(o, [o[0] + L, o[1], o[2]], "#d33", 2); v.line(o, [o[0], o[1] + L, o[2]], "#3a3", 2);
    v.line(o, [o[0], o[1], o[2] + L], "#36c", 2);
    v.text([o[0] + L, o[1], o[2]], "x", "#c33"); v.text([o[0], o[1] + L, o[2]], "y", "#393"); v.text([o[0], o[1], o[2] + L], "z", "#36c");
  }
  const pts = R.points.slice().sort((p, q) => v.project(q.at.map((x) => x / 1e3))[2] - v.project(p.at.map((x) => x / 1e3))[2]);
  const em = R.res && R.res.kind === "twin" ? R.res.error_map : null;
  for (const p of pts) {
    const at = p.at.map((x) => x / 1e3);
    if (em) v.arrow(at, at.map((x, k) => x - (em.scale * p.r[k]) / 1e3), colour(p.norm), 1.5, 5);
    v.dot(at, 2.5 + 1.2 * Math.sqrt(p.n), colour(p.norm), p.fails * 2 >= p.n && p.n ? "#7a1020" : "#0003");
  }
  stats.draws++;
}
function renderScale() {
  const c = $("scale-bar"), g = c.getContext("2d");
  for (let x = 0; x < c.width; x++) { g.fillStyle = colour((x / (c.width - 1)) * R.vmax); g.fillRect(x, 0, 1, c.height); }
  const floor = R.floor ? `blue at or below the noise floor ${fx(R.floor)} mm, ` : "blue at 0, ";
  $("scale-text").textContent = R.points.length ? `|mean r| per point: ${floor}red at ${fx(R.vmax)} mm and beyond (the ` +
    `95th percentile of the result's points` + (R.res.kind === "diagnose" && R.rows ? " of the model with the larger error" : "") +
    (R.floor ? `, at least ${FLOOR_TIMES} noise floors` : "") + "); dot size: rows; dark ring: fails Eq. 17 in at least half its rows" : "";
}
function renderWorst() {
  const top = R.points.slice().sort((a, b) => b.norm - a.norm).slice(0, 8);
  $("worst").tBodies[0].replaceChildren(...top.map((p) => el("tr", {}, el("td", {}, p.at.map((x) => x.toFixed(1)).join(", ")),
    el("td", {}, fx(p.norm)), el("td", {}, p.n), el("td", {}, R.res.kind === "compare" ? `${p.fails}/${p.n}` : "–"))));
}

// --- the result's figures, steps and report ----------------------------------------------------
function renderAbout() {
  const r = R.res, rows = [["kind", r.kind], ["directory", r.path]];
  if (r.dataset) rows.push(["data", r.dataset]);
  if (r.n != null) rows.push(["rows", r.n]);
  if (r.noise_floor_mm != null) rows.push(["noise floor", `${fx(r.noise_floor_mm)} mm`]);
  if (r.heldout) rows.push(["held out", r.heldout.method]);
  if (r.in_sample && r.in_sample.length) rows.push(["in-sample", `${r.in_sample.join(", ")} trained on these data`]);
  if (r.kind === "twin") {
    const p = r.provenance || {};
    rows.push(["calibrated", p.created || "–"], ["campaign", p.campaign || "–"], ["validity", p.validity ? p.validity.line : "–"]);
  }
  $("about").replaceChildren(...rows.flatMap(([k, v]) => [el("dt", {}, k), el("dd", {}, v)]));
  const ms = r.models || [];
  $("models").tHead.replaceChildren(...(ms.length ? [el("tr", {}, ...["model", "3D RMS / mm", "mean", "max", "fails Eq. 17"].map((h) => el("th", {}, h)))] : []));
  $("models").tBodies[0].replaceChildren(...ms.map((m) => el("tr", {}, el("td", {}, m.name),
    el("td", {}, `${fx(m.rmse_mm)}${m.rmse_U95_mm != null ? " ± " + fx(m.rmse_U95_mm) : ""}`), el("td", {}, fx(m.mae_mm)),
    el("td", {}, fx(m.max_mm)), el("td", {}, m.fails == null ? "–" : `${(100 * m.fails).toFixed(1)} %`))));
}
function renderSteps() {
  const r = R.res, steps = r.steps || [];
  $("steps-panel").hidden = r.kind !== "diagnose";
  $("steps").tBodies[0].replaceChildren(...steps.map((s, i) => {
    const next = steps[i + 1];
    const ho = next ? `${fx(s.rmse_mm)} → ${fx(next.rmse_mm)}` : `${fx(s.rmse_mm)} ± ${fx(s.u_rmse_mm)} (final)`;
    const dep = s.change_deploy_rmse_mm ? `${s.change_deploy_kind}: ${fx(s.change_deploy_rmse_mm[0])} → ${fx(s.change_deploy_rmse_mm[1])}`
      : `${s.deploy_kind || ""} ${fx(s.deploy_rmse_mm)}`;
    return el("tr", { "data-change": s.change || "" }, el("td", {}, i + 1), el("td", {}, s.model),
      el("td", {}, s.change ? `${s.change}${s.follows ? " (follows " + s.follows + ")" : ""}` : `stop: ${r.stop_reason || "nothing more passes"}`),
      el("td", {}, ho), el("td", {}, dep), el("td", {}, s.p_value == null ? "–" : `${s.p_value.toExponential(2)} (${s.alpha.toExponential(1)})`),
      el("td", {}, s.explained_fraction == null ? "–" : `${(100 * s.explained_fraction).toFixed(0)} %`));
  }));
  $("verdict").textContent = r.verdict || "";
}
function renderFigures() {
  const figs = R.res.figures || [];
  $("figures-panel").hidden = !figs.length;
  $("figures").replaceChildren(...figs.map((f) => el("figure", {}, el("img", { src: f.src, alt: f.alt }), el("figcaption", {}, f.caption))));
}

start();
