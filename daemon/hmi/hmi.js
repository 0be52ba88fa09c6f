// rumba operator page: renders one card per machine from server-sent status events.
"use strict";
const csrf = document.querySelector('meta[name="csrf-token"]').content;
const cfg = JSON.parse(document.querySelector('meta[name="rumba-config"]').content);
const RUNNING = new Set(["PREPARE", "STREAM", "CAPTURE", "IDENTIFY", "JUDGE", "WRITE-BACK"]);
const cards = {};
const live = {};  // machine → its latest status event (the run in progress overrides the table)
const journaled = {};  // machine → the last verdict in its history (shown while the daemon has none)
const MEANING = {
  "IDLE": "ready", "PREPARE": "generating the program and checking it against limits",
  "STREAM": "sending the program, waiting for the first touch", "CAPTURE": "probing",
  "IDENTIFY": "identifying setup and link errors", "JUDGE": "comparing with the tolerances",
  "WRITE-BACK": "sending the verdict to the CNC",
  "ABORTED": "run aborted", "FAILED": "run failed",
  "INTERRUPTED": "run interrupted (link lost, controller silent or daemon stopped)",
};
const COLUMNS = ["Started", "Machine", "Trigger", "State", "Verdict", "Touches", "Details", "Report"];
const SVG = "http://www.w3.org/2000/svg";

function fmtDuration(s) {
  if (s === null || s === undefined) return "";
  s = Math.round(s);
  const m = Math.floor(s / 60), r = s % 60;
  return m > 0 ? `${m} min ${String(r).padStart(2, "0")} s` : `${r} s`;
}

const pad = n => String(n).padStart(2, "0");
// Local time, ISO-like (the operator's clock, no ambiguity about day and month order).
function localIso(t) {
  const d = new Date(t * 1000);
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ` +
         `${pad(d.getHours())}:${pad(d.getMinutes())}`;
}
function ageText(s) {
  if (s < 60) return "just now";
  if (s < 3600) return `${Math.floor(s / 60)} min ago`;
  if (s < 48 * 3600) return `${Math.floor(s / 3600)} h ago`;
  return `${Math.floor(s / 86400)} days ago`;
}

// The verdict's date and age; a verdict older than hmi.stale_after_h is flagged stale.
function showWhen(el, at) {
  const when = el.querySelector(".when"), verdict = el.querySelector(".verdict");
  when.dataset.at = at || "";
  if (!at) {
    when.querySelector("time").textContent = "";
    when.querySelector(".age").textContent = "";
    when.querySelector(".stale-note").hidden = true;
    verdict.classList.remove("stale");
    return;
  }
  const t = when.querySelector("time");
  t.textContent = localIso(at);
  t.dateTime = new Date(at * 1000).toISOString();
  const age = Date.now() / 1000 - at;
  when.querySelector(".age").textContent = `(${ageText(age)})`;
  const stale = age > cfg.stale_after_h * 3600;
  verdict.classList.toggle("stale", stale);
  const note = when.querySelector(".stale-note");
  note.hidden = !stale;
  note.textContent = stale ? `stale: older than ${cfg.stale_after_h} h — run a check before ` +
                             "relying on it" : "";
}
setInterval(() => {
  for (const el of Object.values(cards)) {
    const at = Number(el.querySelector(".when").dataset.at);
    if (at) showWhen(el, at);
  }
}, 30000);

async function post(url, body) {
  // the body is read once, as text: an answer that is not JSON (a proxy's error page) is shown
  let r, text;
  const headers = {"X-CSRF-Token": csrf};
  if (body !== undefined) headers["Content-Type"] = "application/json";
  try {
    r = await fetch(url, {method: "POST", headers, credentials: "same-origin",
                          body: body === undefined ? undefined : JSON.stringify(body)});
    text = await r.text();
  } catch (e) { return {ok: false, body: {error: "daemon not reachable"}}; }
  try { return {ok: r.ok, body: JSON.parse(text)}; } catch (e) {
    return {ok: r.ok, body: {error: text || `HTTP ${r.status}`}};
  }
}

// the drift baseline's button (baseline.js): its state known before a click
function baselineButton(el, st, v) { window.rumbaBaseline.button(el, st, v); }

function card(name) {
  if (cards[name]) return cards[name];
  const el = document.getElementById("machine-tpl").content.firstElementChild.cloneNode(true);
  el.dataset.machine = name;
  el.querySelector(".name").textContent = name;
  el.querySelector(".start").addEventListener("click", () => {
    el.querySelector(".message").textContent = "";
    preflight(name, async ticked => {
      const r = await post(`/api/machines/${encodeURIComponent(name)}/start`, {preflight: ticked});
      if (!r.ok) el.querySelector(".message").textContent = r.body.error || "start refused";
    });
  });
  el.querySelector(".abort").addEventListener("click", async () => {
    if (!confirm(`Abort the run on ${name}? The machine stops.`)) return;
    const r = await post(`/api/machines/${encodeURIComponent(name)}/abort`);
    if (!r.ok) el.querySelector(".message").textContent = r.body.error || "abort failed";
  });
  document.getElementById("machines").appendChild(el);
  cards[name] = el;
  loadTrend(name);
  window.rumbaComp.attach(name, el);  // compensation.js: the compensation panel
  return el;
}

function link(a, href) {
  if (href) { a.href = href; a.hidden = false; } else a.hidden = true;
}

function render(st) {
  const el = card(st.machine);
  const running = RUNNING.has(st.state);
  const state = el.querySelector(".state");
  state.textContent = st.state;
  state.className = "state " + (running ? "running" : st.state);
  // the step within the state, the daemon's own words (the start's or the end's temperature
  // reads: CAPTURE with every touch done would say the probe still works)
  el.querySelector(".meaning").textContent = (running && st.step) || MEANING[st.state] || "";
  el.querySelector(".meaning").dataset.step = (running && st.step) || "";
  el.querySelector(".link-state").textContent = st.link_ok ? "controller connected" : "controller link down";
  el.querySelector(".link-state").classList.toggle("down", !st.link_ok);
  const pct = st.total ? Math.round(100 * st.done / st.total) : 0;
  el.querySelector(".bar").style.width = pct + "%";
  let text = "";
  if (st.run_id) {
    text = `${st.done} / ${st.total || "?"} touches`;
    if (running && st.eta_s !== null) text += ` — ${fmtDuration(st.eta_s)} left`;
    if (running) text += ` — run ${st.run_id} (${st.started_by || st.trigger})`;
  }
  if (!running && st.reason) text = st.reason;
  el.querySelector(".progress-text").textContent = text;
  // which pose and ball the probe is on, live
  const p = running && st.probing;
  const probing = el.querySelector(".probing");
  probing.hidden = !p;
  probing.textContent = p ? `Probing pose ${p.pose}, ball ${p.ball}, touch ${p.touch}` : "";
  if (p) Object.assign(probing.dataset, {pose: p.pose, ball: p.ball, touch: p.touch});
  el.querySelector(".start").disabled = running;
  el.querySelector(".abort").disabled = !running;
  // The daemon's own verdict; when it has none (just started, or the last run failed) the
  // last one of the history, with its date and age.
  const v = st.verdict || (!running ? journaled[st.machine] : null);
  if (v) {
    const badge = el.querySelector(".badge");
    badge.textContent = v.status;
    badge.className = "badge " + v.status;
    showWhen(el, v.at);
    el.querySelector(".summary").textContent = v.summary || "";
    // each figure's one-sentence definition beside it, and the drift baseline
    el.querySelector(".definition").textContent = (v.figures || []).slice(0, 1).map(
      f => `${f.label}: ${f.definition}.`).join(" ");
    el.querySelector(".baseline").textContent = v.figures ? (v.baseline ?
      `Drift judged against baseline ${v.baseline.text}.` : "Drift not checked: no baseline.") : "";
    baselineButton(el, st, v);
    // the temperature channels read during the run, start → end
    let temps = el.querySelector(".temperatures");
    if (!temps) {
      temps = document.createElement("div");
      temps.className = "temperatures";
      el.querySelector(".baseline").after(temps);
    }
    temps.textContent = (v.temperatures || []).length ? `Temperatures: ${v.temperatures.join("; ")}.` : "";
    // the rotary axes' indexing repeatability the link u rest on (the report's text)
    let ix = el.querySelector(".index-scatter");
    if (!ix) {
      ix = document.createElement("ul");
      ix.className = "index-scatter";
      temps.after(ix);
    }
    ix.replaceChildren(...(v.index_scatter || []).map(t => {
      const li = document.createElement("li"); li.textContent = t; return li; }));
    const todo = el.querySelector(".todo");
    todo.textContent = cfg.advice[v.status] ? `What to do: ${cfg.advice[v.status]}` : "";
    todo.hidden = !cfg.advice[v.status];
    todo.className = "todo " + v.status;
    const ul = el.querySelector(".reasons");
    ul.replaceChildren(...(v.reasons || []).slice(0, 6).map(r => {
      const li = document.createElement("li"); li.textContent = r; return li; }));
    const run = encodeURIComponent(st.verdict ? st.run_id : v.run_id);
    link(el.querySelector(".report"), v.report ? `/reports/${run}.html` : null);
    link(el.querySelector(".pdf"), v.pdf ? `/reports/${run}.pdf` : null);
    // the report is written after the run's end; say so until its links appear
    reportState(el, v.report ? "" : reportText(v.report_state, v.report_error));
  } else if (!running) {
    el.querySelector(".badge").textContent = "none yet";
    el.querySelector(".badge").className = "badge none";
    showWhen(el, null);
    el.querySelector(".todo").hidden = true;
    link(el.querySelector(".report"), null);
    link(el.querySelector(".pdf"), null);
    reportState(el, "");
  }
}

function reportText(state, error) {
  return state === "writing" ? "report being written…"
    : state === "failed" ? `report not written: ${error || "see the log"}` : "";
}

function reportState(el, text) {
  const rs = el.querySelector(".report-state");
  rs.textContent = text;
  rs.hidden = !text;
}

// The row of a run in progress shows what its progress bar shows, from the same event.
function liveRow(st) {
  if (!st.run_id || !st.busy) return;
  const tr = [...document.querySelectorAll("#history tbody tr")].find(r => r.dataset.run === st.run_id);
  if (!tr) return;
  tr.cells[3].textContent = st.state;
  tr.cells[5].textContent = `${st.done} / ${st.total || "?"}`;
}

let historyGen = 0;
async function loadLastVerdicts() {
  // Refreshes overlap when states change fast: only the newest request may fill the table.
  const gen = ++historyGen;
  let runs;
  try {
    const r = await fetch("/api/runs?limit=25", {credentials: "same-origin"});
    if (!r.ok) return;
    runs = await r.json();
  } catch (e) { return; }  // daemon restarting: the next status event refreshes again
  if (gen !== historyGen) return;
  const tbody = document.querySelector("#history tbody");
  tbody.replaceChildren(...runs.map(run => {
    const tr = document.createElement("tr");
    tr.dataset.run = run.id;
    tr.title = `run ${run.id}`;
    // the person who started it beside how (hmi, cnc, can, cli)
    const cells = [localIso(run.started_at), run.machine,
                   run.started_by ? `${run.started_by} (${run.trigger})` : run.trigger,
                   run.state, run.verdict || "—", `${run.hits} / ${run.touch_total}`,
                   run.reason || run.summary || ""];
    cells.forEach((c, i) => {
      const td = document.createElement("td"); td.textContent = c;
      td.dataset.label = COLUMNS[i];
      if (i === 4 && run.verdict) td.className = "v-" + run.verdict;
      if (i === 6) td.className = "details";
      tr.appendChild(td);
    });
    const td = document.createElement("td");
    td.dataset.label = COLUMNS[7];
    for (const [href, label] of [[run.report, "report"], [run.pdf, "PDF"]]) {
      if (!href) continue;
      const a = document.createElement("a"); a.href = href; a.textContent = label;
      a.target = "_blank"; a.rel = "noopener"; td.appendChild(a);
    }
    // the run's report job (its own record, not the run's reason): being written, or why not
    if (!run.report) td.textContent = reportText(run.report_state, run.report_error);
    tr.appendChild(td);
    return tr;
  }));
  // The fetch answered a moment ago: the live events since then are newer.
  Object.values(live).forEach(liveRow);
  if (window.rumbaMaps) window.rumbaMaps.load();  // maps.js: a map job is a run too
  // The last verdict of each machine's history, for a card whose daemon has none yet.
  for (const run of [...runs].reverse()) {
    if (run.verdict) {
      journaled[run.machine] = {status: run.verdict, summary: run.summary, reasons: [],
                                report: run.report, pdf: run.pdf, run_id: run.id,
                                report_state: run.report_state, report_error: run.report_error,
                                at: run.ended_at || run.started_at};
    }
  }
  Object.values(live).forEach(st => { if (!st.verdict && !st.busy) render(st); });
  // what the runs list does not carry: the run API's sections of each journaled verdict
  for (const [machine, v] of Object.entries(journaled)) {
    if (v.index_scatter) continue;
    fetch(`/api/runs/${encodeURIComponent(v.run_id)}`, {credentials: "same-origin"})
      .then(r => r.ok ? r.json() : null).then(d => {
        if (!d || journaled[machine] !== v) return;
        v.index_scatter = d.index_scatter ? d.index_scatter.lines : [];
        v.temperatures = d.temperatures;
        const st = live[machine];
        if (st && !st.verdict && !st.busy) render(st);
      }).catch(() => {});  // daemon restarting: the next refresh asks again
  }
}

// ------------------------------------------------------------------------------- trend chart

function svgEl(tag, attrs, text) {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}
function niceStep(span) {
  const raw = span / 4, p = Math.pow(10, Math.floor(Math.log10(raw)));
  return [1, 2, 5, 10].map(m => m * p).find(s => s >= raw) || raw;
}

// One small chart per link error: its own axis in its own unit (µm or µrad), its warn and fail
// limits (±, the judge bounds |value|), one dot per run coloured by the run's verdict.
function chart(s, runs) {
  // large enough to read, runs placed by their date, date and time on the axis
  const W = 380, H = 210, L = 52, R = 10, T = 24, B = 34;
  const vals = s.values.filter(v => v !== null);
  const lim = s.fail || s.warn || 0;
  const top = 1.12 * Math.max(lim, ...vals.map(Math.abs), 1e-9);
  const lo = s.two_sided ? -top : 0;
  const y = v => T + (H - T - B) * (top - v) / (top - lo);
  const t0 = runs.length ? runs[0].started_at : 0;
  const span = runs.length > 1 ? runs[runs.length - 1].started_at - t0 : 0;
  const x = i => L + (W - L - R) * (span > 0 ? (runs[i].started_at - t0) / span : 0.5);
  const svg = svgEl("svg", {viewBox: `0 0 ${W} ${H}`, class: "chart", role: "img",
                         "aria-label": `${s.name} trend in ${s.unit}`});
  svg.appendChild(svgEl("text", {x: L, y: 14, class: "title"}, s.name));
  const last = vals.length ? vals[vals.length - 1] : null;
  if (last !== null) svg.appendChild(svgEl("text", {x: W - R, y: 14, class: "last", "text-anchor": "end"},
                                        `${last >= 0 ? "+" : ""}${last.toFixed(1)} ${s.unit}`));
  const step = niceStep(top - lo);
  for (let v = Math.ceil(lo / step) * step; v <= top + 1e-9; v += step) {
    svg.appendChild(svgEl("line", {x1: L, x2: W - R, y1: y(v), y2: y(v), class: "grid"}));
    svg.appendChild(svgEl("text", {x: L - 3, y: y(v) + 3, class: "tick", "text-anchor": "end"},
                       String(Math.round(v * 100) / 100)));
  }
  svg.appendChild(svgEl("text", {x: 11, y: (T + H - B) / 2, class: "unit", "text-anchor": "middle",
                              transform: `rotate(-90 11 ${(T + H - B) / 2})`}, s.unit));
  svg.appendChild(svgEl("line", {x1: L, x2: L, y1: T, y2: H - B, class: "axis"}));
  for (const [kind, v] of [["warn", s.warn], ["fail", s.fail]]) {
    if (v === null || v === undefined) continue;
    for (const w of s.two_sided ? [v, -v] : [v]) {
      svg.appendChild(svgEl("line", {x1: L, x2: W - R, y1: y(w), y2: y(w), class: `limit ${kind}`}));
    }
  }
  const pts = s.values.map((v, i) => [i, v]).filter(([, v]) => v !== null);
  svg.appendChild(svgEl("polyline", {points: pts.map(([i, v]) => `${x(i)},${y(v)}`).join(" "), class: "line"}));
  for (const [i, v] of pts) {
    const c = svgEl("circle", {cx: x(i), cy: y(v), r: 4, class: `pt v-${runs[i].verdict}`});
    c.appendChild(svgEl("title", {}, `${localIso(runs[i].started_at)}: ${v.toFixed(2)} ${s.unit} (${runs[i].verdict})`));
    svg.appendChild(c);
  }
  // time axis: first, middle and last run's date (MM-DD) over its time (HH:MM)
  svg.appendChild(svgEl("line", {x1: L, x2: W - R, y1: H - B, y2: H - B, class: "axis"}));
  const marks = runs.length > 2 ? [0, Math.floor((runs.length - 1) / 2), runs.length - 1] :
    [...runs.keys()];
  for (const i of marks) {
    const iso = localIso(runs[i].started_at), anchor = i === 0 ? "start" :
      i === runs.length - 1 ? "end" : "middle";
    const g = svgEl("g", {class: "xtick"});
    g.appendChild(svgEl("line", {x1: x(i), x2: x(i), y1: H - B, y2: H - B + 4, class: "axis"}));
    g.appendChild(svgEl("text", {x: x(i), y: H - B + 14, class: "tick date", "text-anchor": anchor},
                        iso.slice(5, 10)));
    g.appendChild(svgEl("text", {x: x(i), y: H - B + 26, class: "tick time", "text-anchor": anchor},
                        iso.slice(11, 16)));
    svg.appendChild(g);
  }
  svg.dataset.name = s.name;
  return svg;
}

async function loadTrend(name) {
  let t;
  try {
    const r = await fetch(`/api/machines/${encodeURIComponent(name)}/trend?limit=30`,
                          {credentials: "same-origin"});
    if (!r.ok) return;
    t = await r.json();
  } catch (e) { return; }
  const box = cards[name].querySelector(".trend");
  const enough = t.runs.length >= 2;
  box.querySelector(".trend-note").textContent = enough ? `(last ${t.runs.length} runs)` :
    "(shown from the second run with a verdict on)";
  box.querySelector(".charts").replaceChildren(...(enough ? t.series.map(s => chart(s, t.runs)) : []));
  pickControls(box, enough ? t.series.map(s => s.name) : []);
  if ((t.channels || []).length) againstControls(name, box, t);
}

// A link error against a recorded temperature channel, one dot per run
// (the channel's mean over the run), the least-squares line, r and the slope ± u.
function againstControls(name, box, t) {
  // beside the trend box, not in it: the trend's charts stay one per link error
  let div = box.nextElementSibling && box.nextElementSibling.classList.contains("against") ?
    box.nextElementSibling : null;
  if (!div) {
    div = document.createElement("div");
    div.className = "against";
    const ch = document.createElement("select"), ln = document.createElement("select");
    ch.className = "against-channel"; ln.className = "against-link";
    ch.setAttribute("aria-label", "temperature channel");
    ln.setAttribute("aria-label", "link error");
    const label = document.createElement("span");
    label.textContent = "Link error against temperature: ";
    const out = document.createElement("div"); out.className = "against-chart";
    const note = document.createElement("p"); note.className = "against-text";
    div.append(label, ln, document.createTextNode(" vs "), ch, out, note);
    box.after(div);
    ch.addEventListener("change", () => loadAgainst(name, div));
    ln.addEventListener("change", () => loadAgainst(name, div));
  }
  const fill = (sel, names) => {
    const keep = sel.value;
    sel.replaceChildren(...names.map(n => { const o = document.createElement("option");
                                             o.value = o.textContent = n; return o; }));
    if (names.includes(keep)) sel.value = keep;
  };
  fill(div.querySelector(".against-channel"), t.channels);
  fill(div.querySelector(".against-link"), t.series.map(s => s.name).filter(n => /^E[A-Z]/.test(n)));
  loadAgainst(name, div);
}

async function loadAgainst(name, div) {
  const ch = div.querySelector(".against-channel").value, ln = div.querySelector(".against-link").value;
  if (!ch || !ln) return;
  let a;
  try {
    const r = await fetch(`/api/machines/${encodeURIComponent(name)}/trend?limit=200&against=` +
                          `${encodeURIComponent(ch)}&link=${encodeURIComponent(ln)}`,
                          {credentials: "same-origin"});
    if (!r.ok) return;
    a = (await r.json()).against;
  } catch (e) { return; }
  div.querySelector(".against-text").textContent = a.text;
  div.querySelector(".against-chart").replaceChildren(...(a.points.length ? [scatter(a)] : []));
}

function scatter(a) {
  const W = 300, H = 150, L = 44, R = 8, T = 8, B = 24;
  const xs = a.points.map(p => p.temperature_c), ys = a.points.map(p => p.value);
  let x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  if (x1 - x0 < 1e-9) { x0 -= 0.5; x1 += 0.5; }
  if (y1 - y0 < 1e-9) { y0 -= 0.5; y1 += 0.5; }
  const px = v => L + (W - L - R) * (v - x0) / (x1 - x0), py = v => T + (H - T - B) * (y1 - v) / (y1 - y0);
  const svg = svgEl("svg", {viewBox: `0 0 ${W} ${H}`, class: "chart scatter", role: "img",
                         "aria-label": `${a.link} against ${a.channel}`});
  svg.appendChild(svgEl("line", {x1: L, x2: L, y1: T, y2: H - B, class: "axis"}));
  svg.appendChild(svgEl("line", {x1: L, x2: W - R, y1: H - B, y2: H - B, class: "axis"}));
  for (const [v, y] of [[y0, py(y0)], [y1, py(y1)]]) {
    svg.appendChild(svgEl("text", {x: L - 3, y: y + 3, class: "tick", "text-anchor": "end"}, v.toFixed(1)));
  }
  for (const [v, anchor] of [[x0, "start"], [x1, "end"]]) {
    svg.appendChild(svgEl("text", {x: px(v), y: H - B + 12, class: "tick", "text-anchor": anchor},
                       `${v.toFixed(1)} °C`));
  }
  svg.appendChild(svgEl("text", {x: (L + W) / 2, y: H - 2, class: "unit", "text-anchor": "middle"},
                     `${a.channel} (°C), ${a.link} (${a.unit})`));
  if (a.slope !== null) {
    const mx = xs.reduce((s, v) => s + v, 0) / xs.length, my = ys.reduce((s, v) => s + v, 0) / ys.length;
    const f = v => my + a.slope * (v - mx);
    svg.appendChild(svgEl("line", {x1: px(x0), x2: px(x1), y1: py(f(x0)), y2: py(f(x1)), class: "line"}));
  }
  for (const p of a.points) {
    const c = svgEl("circle", {cx: px(p.temperature_c), cy: py(p.value), r: 3, class: "pt"});
    c.appendChild(svgEl("title", {}, `${p.run_id}: ${p.temperature_c.toFixed(2)} °C, ${p.value.toFixed(2)} ${a.unit}`));
    svg.appendChild(c);
  }
  return svg;
}

// On a phone one chart at a time: the picker chooses which link error is shown.
function pickControls(box, names) {
  const pick = box.querySelector(".trend-pick");
  const keep = pick.value;
  pick.replaceChildren(...names.map(n => { const o = document.createElement("option");
                                           o.value = o.textContent = n; return o; }));
  pick.hidden = !names.length;
  if (names.includes(keep)) pick.value = keep;
  const show = () => box.querySelectorAll(".charts svg.chart").forEach(
    svg => svg.classList.toggle("picked", svg.dataset.name === pick.value));
  pick.onchange = show;
  show();
}

// Start asks first: every item of the pre-flight list ticked, then the run starts.
function preflight(name, go) {
  const dlg = document.getElementById("preflight");
  dlg.querySelector(".pf-machine").textContent = name;
  const list = dlg.querySelector(".pf-items"), ok = dlg.querySelector(".pf-start");
  list.replaceChildren(...cfg.preflight.map(([key, text]) => {
    const li = document.createElement("li"), label = document.createElement("label");
    const box = document.createElement("input");
    box.type = "checkbox"; box.value = key; box.className = "pf-" + key;
    label.append(box, " ", text); li.appendChild(label); return li;
  }));
  const boxes = [...list.querySelectorAll("input")];
  const update = () => { ok.disabled = !boxes.every(b => b.checked); };
  boxes.forEach(b => b.addEventListener("change", update));
  update();
  ok.onclick = () => { dlg.close(); go(boxes.map(b => b.value)); };
  dlg.querySelector(".pf-cancel").onclick = () => dlg.close();
  dlg.showModal();
}

// Who is signed in: the header names the person and role; the compensation
// buttons say when the role may not use them (the daemon refuses anyway).
window.rumbaMe = null;
window.rumbaMeReady = fetch("/api/me", {credentials: "same-origin"}).then(r => r.json()).then(me => {
  window.rumbaMe = me;
  document.body.dataset.role = me.role;
  document.getElementById("who").textContent = `${me.name} · ${me.role}`;
}).catch(() => {});

document.getElementById("logout").addEventListener("click", async () => {
  await post("/logout");
  location.href = "/login";
});

// The history reloads whenever a machine's run, state or verdict changes (a run started,
// moved on or ended — also one that ended while the event stream was reconnecting); in between
// the row of the running run follows its progress events (liveRow). A finished run with a
// verdict also refreshes its machine's trend.
const lastKeys = {};
function historyKey(st) {
  return [st.run_id, st.state, st.verdict ? st.verdict.status : ""].join("|");
}
function connect() {
  const es = new EventSource("/api/events");
  const conn = document.getElementById("conn");
  es.addEventListener("open", () => { conn.textContent = "live"; });
  es.addEventListener("error", () => { conn.textContent = "reconnecting…"; });
  es.addEventListener("status", ev => {
    const st = JSON.parse(ev.data);
    live[st.machine] = st;
    render(st);
    liveRow(st);
    const key = historyKey(st);
    const changed = lastKeys[st.machine] !== key;
    if (changed) {
      lastKeys[st.machine] = key;
      loadLastVerdicts();
      if (!st.busy && st.verdict) loadTrend(st.machine);
    }
    window.rumbaComp.status(st, changed);
  });
}

fetch("/api/status", {credentials: "same-origin"}).then(r => r.json()).then(all => {
  Object.values(all).forEach(st => {
    live[st.machine] = st; render(st); lastKeys[st.machine] = historyKey(st);
    window.rumbaComp.status(st, false);
  });
  loadLastVerdicts();
  connect();
});
