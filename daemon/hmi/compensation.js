// rumba operator page, compensation panel: the proposal of each machine's last
// finished run, Confirm (a second, explicit confirmation naming the values) and Rollback.
"use strict";
window.rumbaComp = (() => {
  const csrfToken = document.querySelector('meta[name="csrf-token"]').content;
  const panels = {};  // machine → {el, data, busy}
  // signed, with a zero never negative ("-0.00" is "0.00")
  const fmt = (v, d = 2) => {
    if (v === null || v === undefined) return "—";
    const s = v.toFixed(d);
    return Number(s) === 0 ? (0).toFixed(d) : `${v > 0 ? "+" : ""}${s}`;
  };
  const unitNames = {mm: "mm", deg: "deg", "1": "axis-vector component, no unit"};

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

  function cells(tr, values, labels) {
    values.forEach((v, i) => {
      const td = document.createElement("td");
      td.textContent = v;
      td.dataset.label = labels[i];
      tr.appendChild(td);
    });
  }

  function buttons(name) {
    const p = panels[name];
    if (!p) return;
    const d = p.data;
    // disabled with the reason stated beside it (.comp-why: "Nothing to confirm: …")
    p.el.querySelector(".comp-confirm").disabled =
      p.busy || !d || !d.proposal || !d.proposal.applicable;
    p.el.querySelector(".comp-rollback").disabled = p.busy || !d || !d.last_applied;
    // only an engineer or admin confirms or rolls back; say so on the buttons
    const me = window.rumbaMe;
    if (me && !me.may_compensate) {
      for (const b of p.el.querySelectorAll(".comp-confirm, .comp-rollback")) {
        b.disabled = true;
        b.title = `signed in as ${me.name} (${me.role}): an engineer or admin confirms`;
      }
    }
  }

  function render(name) {
    const {el, data: d} = panels[name];
    const body = el.querySelector(".comp-body");
    const run = d.run ? `run ${d.run.id}` : "";
    el.querySelector(".comp-note").textContent = run ? `(${run})` : "";
    el.querySelector(".comp-why").textContent = d.why ? `Nothing to confirm: ${d.why}` : "";
    body.hidden = !d.proposal;
    if (d.proposal) {
      const p = d.proposal, k = p.coverage_k;
      el.querySelector(".comp-state").textContent = `State: ${p.state_text}.`;
      // each controller value's change in µm / µrad of what it holds; the addresses and what
      // is written there are the table below (a tilt is not written in µrad)
      const vl = ["Value", "Δ", `U (k=${k})`, "Effect", "Status"];
      el.querySelector(".comp-values thead tr").replaceChildren(...vl.map(h => {
        const th = document.createElement("th"); th.textContent = h; return th; }));
      el.querySelector(".comp-values tbody").replaceChildren(...p.values.map(v => {
        const tr = document.createElement("tr");
        tr.dataset.name = v.name;
        tr.className = "st-" + v.status;
        cells(tr, [v.name, v.delta_text, v.u_text,
                   v.effect_um === null ? "—" : `${v.effect_um.toFixed(1)} µm`,
                   v.status === "apply" ? "apply" : `${v.status}: ${v.reason}`], vl);
        return tr;
      }));
      // what a confirmation writes: every address, the value exactly as the program holds it
      const writes = p.writes || [];
      el.querySelector(".comp-writes-head").textContent = writes.length ?
        `A confirmation writes ${p.program_name}, these ${writes.length} addresses ` +
        "(the controller's own unit and sign):" : "";
      el.querySelector(".comp-writes").hidden = !writes.length;
      const wl = ["Address", "Written", "Was", "Unit", "Value"];
      el.querySelector(".comp-writes tbody").replaceChildren(...writes.map(w => {
        const tr = document.createElement("tr");
        tr.dataset.address = w.address;
        cells(tr, [w.address, w.written, w.was, unitNames[w.unit] || w.unit, w.name], wl);
        return tr;
      }));
      const ll = ["Link", "Run estimate", "Held by the changes", "Residual"];
      el.querySelector(".comp-links tbody").replaceChildren(...p.links.map(l => {
        const tr = document.createElement("tr");
        cells(tr, [l.name, ...[l.identified, l.compensable, l.residual].map(
          v => `${fmt(v)} ${l.unit}`)], ll);
        return tr;
      }));
      // each figure named and defined as on the report (one truth per run)
      el.querySelector(".comp-dist").replaceChildren(...(p.figures || []).map(f => {
        const div = document.createElement("div");
        const b = document.createElement("b");
        b.textContent = `${f.label} ${f.value === null ? "—" : f.value.toFixed(1) + " " + f.unit}`;
        const small = document.createElement("small");
        small.textContent = ` — ${f.definition}`;
        div.append(b, small);
        return div;
      }), Object.assign(document.createElement("small"), {textContent: p.links_text || ""}));
      el.querySelector(".comp-refusals").replaceChildren(...p.refusals.map(r => {
        const li = document.createElement("li"); li.textContent = r; return li; }));
    }
    el.querySelector(".comp-journal").replaceChildren(...(d.journal || []).map(r => {
      const li = document.createElement("li");
      li.textContent = `#${r.id} ${r.state}${r.rollback ? " (rollback)" : ""} — run ${r.run_id}` +
        `${r.by ? `, by ${r.by}` : ""}`;
      return li;
    }));
    buttons(name);
  }

  async function load(name) {
    let r;
    try {
      r = await fetch(`/api/compensation?machine=${encodeURIComponent(name)}`,
                      {credentials: "same-origin"});
      if (!r.ok) return;
      panels[name].data = await r.json();
    } catch (e) { return; }
    render(name);
  }

  function result(name, text, ok) {
    const out = panels[name].el.querySelector(".comp-result");
    out.textContent = text;
    out.className = "comp-result " + (ok ? "ok" : "refused");
  }

  async function doConfirm(name) {
    const d = panels[name].data;
    if (!d || !d.proposal || !d.run) return;
    // every address the program writes, the value as written (the controller's unit and
    // sign), then what each change is in µm / µrad: what the person confirms
    const writes = (d.proposal.writes || []).map(w => `  ${w.text}`);
    const changes = d.proposal.values.filter(v => v.status === "apply").map(v =>
      `  ${v.name}: Δ ${v.delta_text} (U ${v.u_text})`);
    const ask = `Write ${d.proposal.program_name} for ${name} (${d.proposal.family}), ` +
      `from run ${d.run.id}? It writes these ${writes.length} addresses:\n\n` +
      `${writes.join("\n")}\n\nThe changes they hold:\n${changes.join("\n")}\n\n` +
      `Listing ${d.proposal.listing_fingerprint}. Your session is recorded in the ` +
      "compensation journal as the one who confirmed.";
    if (!confirm(ask)) { result(name, "Not confirmed: nothing written.", false); return; }
    const listing = d.proposal.listing_fingerprint;
    let r = await postJson("/api/compensation/confirm",
                           {machine: name, run_id: d.run.id, listing});
    if (!r.ok && r.body && r.body.again) {
      // this run was applied and rolled back: applying it again is a new decision, asked anew
      if (!confirm(`${r.body.error}\n\nApply run ${d.run.id} again, as a new decision?`)) {
        result(name, "Not confirmed again: nothing written.", false); load(name); return;
      }
      r = await postJson("/api/compensation/confirm",
                         {machine: name, run_id: d.run.id, listing, again: true});
    }
    if (r.ok) {
      result(name, `Applied (journal #${r.body.journal}, by ${r.body.by}): ${r.body.note}` +
             (r.body.path ? ` — written to file ${r.body.path}` : ""), true);
    } else result(name, `Refused: ${r.body.error}`, false);
    load(name);
  }

  async function doRollback(name) {
    const last = panels[name].data && panels[name].data.last_applied;
    if (!last) return;
    const values = (last.undo || []).map(w => `  ${w.text}`);
    if (!confirm(`Roll back compensation #${last.id} on ${name}, restoring:\n\n` +
                 `${values.join("\n")}`)) return;
    const r = await postJson("/api/compensation/rollback", {machine: name});
    if (r.ok) {
      result(name, `Rolled back (journal #${r.body.journal}, by ${r.body.by}): ${r.body.note}` +
             (r.body.path ? ` — written to file ${r.body.path}` : ""), true);
    } else result(name, `Refused: ${r.body.error}`, false);
    load(name);
  }

  return {
    attach(name, el) {  // a new machine card
      panels[name] = {el, data: null, busy: false};
      el.querySelector(".comp-confirm").addEventListener("click", () => doConfirm(name));
      el.querySelector(".comp-rollback").addEventListener("click", () => doRollback(name));
      load(name);
    },
    status(st, changed) {  // a status event; ``changed``: its run, state or verdict changed
      const p = panels[st.machine];
      if (!p) return;
      p.busy = !!st.busy;
      buttons(st.machine);
      if (changed && !st.busy) load(st.machine);
    },
  };
})();
