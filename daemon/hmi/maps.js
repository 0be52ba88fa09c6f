// rumba operator page, maps of the linear axes: the journaled map results (rumba map --store,
// or a map job of the daemon) with their figures over the covered volume, the verdict against
// the volumetric limit, what is not observable, and their report. Same table style as the runs.
"use strict";
window.rumbaMaps = (() => {
  const COLUMNS = ["Recorded", "Machine", "Map", "Placements", "Covered (mm)",
                   "Volumetric max ± u (µm)", "RMS (µm)", "Verdict", "Not observable", "Report"];
  let gen = 0;

  function when(t) {
    const d = new Date(t * 1000), p = n => String(n).padStart(2, "0");
    return `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())} ` +
           `${p(d.getHours())}:${p(d.getMinutes())}`;
  }

  function covered(c) {
    return Object.entries(c || {}).map(([a, r]) => `${a} ${r[0]}..${r[1]}`).join(", ");
  }

  function row(m) {
    const tr = document.createElement("tr");
    tr.dataset.map = m.id;
    tr.title = `map ${m.id}` + (m.limit ? ` — limit: ${m.limit}` : "");
    const u = m.volumetric_max_u_um == null ? "" : ` ± ${m.volumetric_max_u_um.toFixed(1)}`;
    const cells = [when(m.created_at), m.machine, m.id, String(m.placements),
                   covered(m.covered_mm), `${m.volumetric_max_um.toFixed(1)}${u}`,
                   m.volumetric_rms_um.toFixed(1), m.verdict || "not judged (no limit)",
                   Object.keys(m.unobservable || {}).join(", ") || "—"];
    cells.forEach((c, i) => {
      const td = document.createElement("td");
      td.textContent = c;  // text only: names and ids never become markup
      td.dataset.label = COLUMNS[i];
      if (i === 5) td.className = "map-vmax";
      if (i === 6) td.className = "map-vrms";
      if (i === 7 && m.verdict) td.className = "v-" + m.verdict;
      tr.appendChild(td);
    });
    const td = document.createElement("td");
    td.dataset.label = COLUMNS[9];
    for (const [href, label] of [[m.report, "report"], [m.pdf, "PDF"], [m.json, "map file"]]) {
      if (!href) continue;
      const a = document.createElement("a");
      a.href = href; a.textContent = label; a.target = "_blank"; a.rel = "noopener";
      td.append(a, " ");
    }
    tr.appendChild(td);
    return tr;
  }

  async function load() {
    const mine = ++gen;  // only the newest answer fills the table
    let maps;
    try {
      const r = await fetch("/api/maps?limit=10", {credentials: "same-origin"});
      if (!r.ok) return;
      maps = await r.json();
    } catch (e) { return; }  // daemon restarting: the next refresh asks again
    if (mine !== gen) return;
    const box = document.getElementById("maps");
    box.hidden = maps.length === 0;  // no map journaled: the page stays as it was
    box.querySelector("tbody").replaceChildren(...maps.map(row));
  }

  document.addEventListener("DOMContentLoaded", () => {
    load();
    setInterval(load, 60000);  // a map journaled by `rumba map --store` beside the daemon
  });
  return {load};
})();
