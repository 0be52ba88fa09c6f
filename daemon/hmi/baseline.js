// rumba operator page, drift baseline: "Accept this run as the drift baseline" on each machine
// card. Its state is known before anyone clicks: an operator sees it disabled with the reason
// (an engineer or admin decides); a run that FAILed, predates a compensation or was identified
// against a model the controller no longer runs is disabled with the daemon's objections, and
// an engineer or admin may override it with a reason (journaled with the objections).
"use strict";
window.rumbaBaseline = (() => {
  const csrfToken = document.querySelector('meta[name="csrf-token"]').content;
  const checked = {};  // machine → {run, objections} of the last run looked up

  async function postJson(url, body) {
    let r, text;
    try {
      r = await fetch(url, {method: "POST", credentials: "same-origin", body: JSON.stringify(body),
                            headers: {"X-CSRF-Token": csrfToken, "Content-Type": "application/json"}});
      text = await r.text();
    } catch (e) { return {ok: false, body: {error: "daemon not reachable"}}; }
    try { return {ok: r.ok, body: JSON.parse(text)}; } catch (e) {
      return {ok: r.ok, body: {error: text || `HTTP ${r.status}`}};
    }
  }

  function parts(el) {
    let box = el.querySelector(".set-baseline-box");
    if (!box) {
      box = document.createElement("div");
      box.className = "set-baseline-box";
      box.hidden = true;  // until the run's objections are known
      const btn = document.createElement("button");
      btn.className = "btn set-baseline";
      btn.textContent = "Accept this run as the drift baseline";
      btn.disabled = true;
      const over = document.createElement("button");
      over.className = "btn set-baseline-override";
      over.textContent = "Override…";
      const why = document.createElement("p");
      why.className = "set-baseline-why";
      box.append(btn, over, why);
      el.querySelector(".baseline").after(box);
      btn.addEventListener("click", () => decide(el, false));
      over.addEventListener("click", () => decide(el, true));
    }
    return {box, btn: box.querySelector(".set-baseline"),
            over: box.querySelector(".set-baseline-override"),
            why: box.querySelector(".set-baseline-why")};
  }

  async function decide(el, override) {
    const me = window.rumbaMe || {}, name = el.dataset.machine;
    const {btn} = parts(el);
    const run = btn.dataset.run;
    const found = (checked[name] && checked[name].run === run) ? checked[name].objections : [];
    const body = {run_id: run};
    if (override) {
      const reason = prompt(`Run ${run} should not be the drift baseline of ${name}:\n\n` +
                            found.map(o => `• ${o}`).join("\n") +
                            "\n\nOverride anyway? The reason is journaled with the baseline:");
      if (!reason) return;
      body.override = reason;
    } else if (!confirm(`Make run ${run} the drift baseline of ${name}? Later runs' drift is ` +
                        "judged against it.")) return;
    if (me.via !== "password") {
      body.by = prompt("Your name (journaled with the baseline):") || "";
      if (!body.by) return;
    }
    const r = await postJson(`/api/machines/${encodeURIComponent(name)}/baseline`, body);
    el.querySelector(".message").textContent = r.ok ? `Baseline now: ${r.body.baseline.text}.`
      : (r.body.error || "refused");
    if (r.ok) { btn.dataset.done = run; show(el, run, []); }
  }

  function show(el, run, objections) {
    const me = window.rumbaMe;
    const {box, btn, over, why} = parts(el);
    const done = btn.dataset.done === run;
    box.hidden = btn.hidden = !run || done;
    const engineer = !!(me && me.may_compensate);
    btn.disabled = !engineer || objections.length > 0;
    over.hidden = !engineer || objections.length === 0;
    let text = "";
    if (me && !engineer) {
      text = `Signed in as ${me.name} (${me.role}): an engineer or admin sets the baseline.`;
    } else if (objections.length) {
      text = `Not a baseline without an override: ${objections.join("; ")}.`;
    }
    btn.title = text;
    why.textContent = text;
  }

  return {
    // a card's verdict shown: ``st`` the status, ``v`` the verdict on the card
    async button(el, st, v) {
      await window.rumbaMeReady;  // who is signed in decides what the button offers
      const name = el.dataset.machine;
      const run = (st.verdict && v.status !== "ERROR" && st.run_id) || "";
      const {btn} = parts(el);
      btn.dataset.run = run;
      if (!run || (v.baseline && v.baseline.run_id === run)) { show(el, "", []); return; }
      if (!checked[name] || checked[name].run !== run) {
        checked[name] = {run, objections: []};
        try {
          const r = await fetch(`/api/machines/${encodeURIComponent(name)}/baseline?run_id=` +
                                encodeURIComponent(run), {credentials: "same-origin"});
          if (r.ok) checked[name].objections = (await r.json()).objections || [];
        } catch (e) { /* shown without objections; the daemon checks again on POST */ }
      }
      if (btn.dataset.run === run) show(el, run, checked[name].objections);
    },
  };
})();
