// rumba operator page: renders one card per machine from server-sent status events.
"use strict";
const csrf = document.querySelector('meta[name="csrf-token"]').content;
const RUNNING = new Set(["PREPARE", "STREAM", "CAPTURE", "IDENTIFY", "JUDGE", "REPORT", "WRITE-BACK"]);
const cards = {};
const MEANING = {
  "IDLE": "ready", "PREPARE": "generating the program and checking it against limits",
  "STREAM": "sending the program, waiting for the first touch", "CAPTURE": "probing",
  "IDENTIFY": "identifying setup and link errors", "JUDGE": "comparing with the tolerances",
  "REPORT": "writing the report", "WRITE-BACK": "sending the verdict to the CNC",
  "ABORTED": "run aborted", "FAILED": "run failed",
};

function fmtDuration(s) {
  if (s === null || s === undefined) return "";
  s = Math.round(s);
  const m = Math.floor(s / 60), r = s % 60;
  return m > 0 ? `${m} min ${String(r).padStart(2, "0")} s` : `${r} s`;
}

async function post(url) {
  const r = await fetch(url, {method: "POST", headers: {"X-CSRF-Token": csrf}, credentials: "same-origin"});
  let body = {};
  try { body = await r.json(); } catch (e) { body = {error: await r.text()}; }
  return {ok: r.ok, body};
}

function card(name) {
  if (cards[name]) return cards[name];
  const el = document.getElementById("machine-tpl").content.firstElementChild.cloneNode(true);
  el.dataset.machine = name;
  el.querySelector(".name").textContent = name;
  el.querySelector(".start").addEventListener("click", async () => {
    el.querySelector(".message").textContent = "";
    const r = await post(`/api/machines/${encodeURIComponent(name)}/start`);
    if (!r.ok) el.querySelector(".message").textContent = r.body.error || "start refused";
  });
  el.querySelector(".abort").addEventListener("click", async () => {
    if (!confirm(`Abort the run on ${name}? The machine stops.`)) return;
    const r = await post(`/api/machines/${encodeURIComponent(name)}/abort`);
    if (!r.ok) el.querySelector(".message").textContent = r.body.error || "abort failed";
  });
  document.getElementById("machines").appendChild(el);
  cards[name] = el;
  return el;
}

function render(st) {
  const el = card(st.machine);
  const running = RUNNING.has(st.state);
  const state = el.querySelector(".state");
  state.textContent = st.state;
  state.className = "state " + (running ? "running" : st.state);
  el.querySelector(".meaning").textContent = MEANING[st.state] || "";
  el.querySelector(".link-state").textContent = st.link_ok ? "controller connected" : "controller link down";
  el.querySelector(".link-state").classList.toggle("down", !st.link_ok);
  const pct = st.total ? Math.round(100 * st.done / st.total) : 0;
  el.querySelector(".bar").style.width = pct + "%";
  let text = "";
  if (st.run_id) {
    text = `${st.done} / ${st.total || "?"} touches`;
    if (running && st.eta_s !== null) text += ` — ${fmtDuration(st.eta_s)} left`;
    if (running) text += ` — run ${st.run_id} (${st.trigger})`;
  }
  if (!running && st.reason) text = st.reason;
  el.querySelector(".progress-text").textContent = text;
  el.querySelector(".start").disabled = running;
  el.querySelector(".abort").disabled = !running;
  const v = st.verdict;
  if (v) {
    const badge = el.querySelector(".badge");
    badge.textContent = v.status;
    badge.className = "badge " + v.status;
    el.querySelector(".summary").textContent = v.summary || "";
    const ul = el.querySelector(".reasons");
    ul.replaceChildren(...(v.reasons || []).slice(0, 6).map(r => {
      const li = document.createElement("li"); li.textContent = r; return li; }));
    const a = el.querySelector(".report");
    if (v.report) { a.href = `/reports/${encodeURIComponent(st.run_id)}.html`; a.hidden = false; }
    else a.hidden = true;
  } else if (!running && !st.run_id) {
    el.querySelector(".badge").textContent = "none yet";
    el.querySelector(".badge").className = "badge none";
    el.querySelector(".report").hidden = true;
  }
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
    const cells = [new Date(run.started_at * 1000).toLocaleString(), run.machine, run.trigger,
                   run.state, run.verdict || "—", `${run.hits} / ${run.touch_total}`,
                   run.reason || run.summary || ""];
    cells.forEach((c, i) => {
      const td = document.createElement("td"); td.textContent = c;
      if (i === 4 && run.verdict) td.className = "v-" + run.verdict;
      tr.appendChild(td);
    });
    const td = document.createElement("td");
    if (run.report) { const a = document.createElement("a"); a.href = run.report; a.textContent = "report";
                      a.target = "_blank"; a.rel = "noopener"; td.appendChild(a); }
    tr.appendChild(td);
    return tr;
  }));
  // Cards of idle machines show the last verdict of their history.
  for (const run of runs) {
    const el = cards[run.machine];
    if (el && el.querySelector(".badge").textContent === "none yet" && run.verdict) {
      render({machine: run.machine, state: "IDLE", run_id: run.id, done: run.hits, total: run.touch_total,
              reason: "", link_ok: true, eta_s: null,
              verdict: {status: run.verdict, summary: run.summary, reasons: [], report: run.report}});
    }
  }
}

document.getElementById("logout").addEventListener("click", async () => {
  await post("/logout");
  location.href = "/login";
});

// The history reloads whenever a machine's run, state or verdict changes (a run started,
// moved on or ended — also one that ended while the event stream was reconnecting) and every
// 2 s while a run captures (its touch count).
const lastKeys = {};
let lastHistory = 0;
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
    render(st);
    const now = Date.now(), key = historyKey(st);
    if (lastKeys[st.machine] !== key || (st.busy && now - lastHistory > 2000)) {
      lastKeys[st.machine] = key;
      lastHistory = now;
      loadLastVerdicts();
    }
  });
}

fetch("/api/status", {credentials: "same-origin"}).then(r => r.json()).then(all => {
  Object.values(all).forEach(st => { render(st); lastKeys[st.machine] = historyKey(st); });
  loadLastVerdicts();
  connect();
});
