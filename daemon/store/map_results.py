"""Map results in the journal: the figures of a map of the linear axes (``rumba map``, or the
daemon's multi-placement job) with the path and SHA-256 of its map file and report.

A map is not a probing run (it has no touches of its own: its placements are runs or logs), so
it has a row of its own in ``map_results`` (migration 12), numbered by the run of the daemon's
job, or by a ``map-…`` id when ``rumba map --store`` made it. The row holds what every surface
shows (history, HMI, fleet store, OPC UA, AQDEF): the volumetric error max ± u and RMS over the
covered box, the verdict against the limit, the covered strokes, the positioning errors' max,
what is not observable. The map file itself stays a file (its covariance is megabytes); its
hash says whether the file read back later is the one journaled.
"""

from __future__ import annotations

import hashlib
import json
import secrets
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from contracts.linear_map import LinearMapFile, load_map
from daemon.store.journal import Store, StoreError, validate_run_id

KIND = "map"
REPORT_NAMES = {"html": "map.html", "pdf": "map.pdf", "json": "map.json"}
COLS = ("id", "machine", "run_id", "created_at", "verdict", "volumetric_max_um",
        "volumetric_max_u_um", "volumetric_rms_um", "limit_text", "placements", "figures",
        "json_path", "json_sha256", "report_html", "report_sha256", "recorded_by")
"""Columns copied to the fleet store (``fleet_copied`` is the local journal's own flag)."""
POSITIONING = ("EXX", "EYY", "EZZ")
NOT_COPIED, COPIED, REFUSED = 0, 1, 2


class MapResultError(StoreError):
    """A map result cannot be recorded or read back; one line naming the file or id."""


@dataclass(frozen=True)
class MapResult:
    """One row of ``map_results``; ``figures`` is the JSON object of ``figures_of``."""

    id: str
    machine: str
    run_id: str  # the daemon job's run ('' : made by ``rumba map --store``)
    created_at: float
    verdict: str | None  # PASS / WARN / FAIL against the limit; None: no limit, not judged
    volumetric_max_um: float
    volumetric_max_u_um: float | None
    volumetric_rms_um: float
    limit_text: str
    placements: int
    figures: dict[str, Any]
    json_path: str
    json_sha256: str
    report_html: str
    report_sha256: str
    recorded_by: str

    @property
    def kind(self) -> str:
        return KIND

    @property
    def report_pdf(self) -> str:
        return str(Path(self.report_html).with_suffix(".pdf")) if self.report_html else ""

    def describe(self) -> str:
        """"map volumetric max 12.3 ± 0.8 µm, RMS 5.1 µm — PASS (…)" (one line)."""
        u = f" ± {self.volumetric_max_u_um:.1f}" if self.volumetric_max_u_um is not None else ""
        judged = (f" — {self.verdict} ({self.limit_text})" if self.verdict
                  else " — not judged (no limit)")
        return (f"map volumetric max {self.volumetric_max_um:.1f}{u} µm, RMS "
                f"{self.volumetric_rms_um:.1f} µm{judged}")

    def as_dict(self) -> dict[str, Any]:
        d = {c: getattr(self, c) for c in COLS}
        d.update(kind=KIND, report_pdf=self.report_pdf)
        return d


def sha256_of(path: Path | str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _max_of(f: Any) -> dict[str, Any] | None:
    if not f.terms or not f.value:
        return None
    if not len(f.value) == len(f.u) == len(f.x_mm):
        raise MapResultError(f"functions: {f.name}: value, u and x_mm differ in length "
                             f"({len(f.value)}, {len(f.u)}, {len(f.x_mm)})")
    v = np.abs(np.asarray(f.value, float))
    i = int(np.argmax(v))
    return {"value_um": float(v[i]), "u_um": float(f.u[i]), "at_mm": float(f.x_mm[i])}


def figures_of(doc: LinearMapFile) -> dict[str, Any]:
    """What the surfaces show of a map: its figures, covered strokes, positioning errors' max
    over them (|e| ± u where it is largest; absent when the function has no term), what is
    not observable, the fit's residual and the held-out check."""
    fig = doc.figures.volumetric_max_um
    fns = {f.name: f for f in doc.functions}
    return {
        "volumetric_max_um": fig.value_um, "volumetric_max_u_um": fig.u_um,
        "volumetric_max_at_mm": fig.at_mm, "volumetric_rms_um": doc.figures.volumetric_rms_um,
        "status": fig.status, "limit": fig.limit, "limit_source": fig.source,
        "points": doc.figures.points, "grid": doc.figures.grid,
        "covered_mm": {a.axis: list(a.range_mm) for a in doc.basis.axes},
        "degrees": {a.axis: a.degree for a in doc.basis.axes},
        "positioning_max_um": {n: m for n in POSITIONING
                               if n in fns and (m := _max_of(fns[n])) is not None},
        "unobservable": dict(doc.observability.unobservable),
        "scale_observable": doc.observability.scale_observable,
        "placements": [p.name for p in doc.placements],
        "residual_rms_um": doc.fit.residual_rms_um,
        "holdout": None if doc.holdout is None else {
            "rms_before_um": doc.holdout.rms_before_um,
            "rms_after_um": doc.holdout.rms_after_um},
        "created_utc": doc.created_utc, "map_machine": doc.machine.get("name"),
        "warnings": list(doc.warnings),
    }


def new_map_id(now: float | None = None) -> str:
    """``map-20261129-031502-3fa1``: a run-id-safe name (file names, URLs) of a map made
    outside a run; UTC; the random tail tells two maps of the same second apart."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(time.time() if now is None else now))
    return f"map-{stamp}-{secrets.token_hex(2)}"


def _report_html(report_dir: Path | str | None) -> Path | None:
    if report_dir is None:
        return None
    html = Path(report_dir) / REPORT_NAMES["html"]
    if not html.is_file():
        raise MapResultError(f"{report_dir}: no map report there (expected "
                             f"{REPORT_NAMES['html']}, written by rumba map --report)")
    return html


def record_map_result(store: Store, run_id: str | None, map_json_path: Path | str,
                      report_dir: Path | str | None = None, *, machine: str | None = None,
                      recorded_by: str = "") -> MapResult:
    """Journal one map: its file is read and checked (``contracts.linear_map``), its figures
    and the SHA-256 of the file and of the report's HTML are committed in one row.

    ``run_id``: the daemon job's run (it must be in the journal; the map's id is the run's and
    ``machine`` defaults to the run's), or None for a map made outside a run (a new ``map-…``
    id; ``machine`` then required: the daemon.yaml entry's name). Recording the same run's map
    again replaces its row (a map fitted again). ``MapResultError`` (one line) on a file that
    is not a map, a missing report, an unknown run or a machine that does not match."""
    from contracts.yaml_files import ConfigError

    try:
        doc = load_map(map_json_path)
    except ConfigError as e:
        raise MapResultError(str(e)) from None
    html = _report_html(report_dir)
    try:
        figs = figures_of(doc)
    except MapResultError as e:
        raise MapResultError(f"{map_json_path}: {e}") from None
    if run_id is not None:
        validate_run_id(run_id)
        run = store.run(run_id)  # StoreError: not in this journal
        if machine is not None and machine != run.machine:
            raise MapResultError(f"run {run_id} is of machine {run.machine!r}, not {machine!r}")
        machine, map_id = run.machine, run_id
    elif not machine:
        raise MapResultError("a map made outside a run needs the machine's name")
    else:
        map_id = new_map_id()
    try:  # JSON's NaN / Infinity literals parse; a figure that is one is not a figure
        text = json.dumps(figs, allow_nan=False)
    except ValueError:
        raise MapResultError(f"{map_json_path}: figures: a figure that is not a finite number "
                             "(NaN or infinite): not journaled") from None
    if figs["volumetric_max_um"] < 0 or figs["volumetric_rms_um"] < 0 or (
            figs["volumetric_max_u_um"] or 0) < 0:
        raise MapResultError(f"{map_json_path}: figures: a negative volumetric error or u: "
                             "not journaled")
    if figs["status"] not in (None, "PASS", "WARN", "FAIL"):
        raise MapResultError(f"{map_json_path}: figures.volumetric_max_um.status: expected "
                             f"PASS, WARN, FAIL or null, got {figs['status']!r}")
    row = (map_id, machine, run_id or "", time.time(), figs["status"],
           figs["volumetric_max_um"], figs["volumetric_max_u_um"], figs["volumetric_rms_um"],
           figs["limit"] or "", len(doc.placements), text,
           str(Path(map_json_path).resolve()), sha256_of(map_json_path),
           str(html.resolve()) if html else "", sha256_of(html) if html else "", recorded_by)
    with store.transaction():
        store.db.execute(f"INSERT OR REPLACE INTO map_results ({', '.join(COLS)}, fleet_copied)"
                         f" VALUES ({', '.join('?' * len(COLS))}, {NOT_COPIED})", row)
    return get(store, map_id)


def _row(r: tuple) -> MapResult:
    d = dict(zip(COLS, r, strict=True))
    d["figures"] = json.loads(d["figures"])
    return MapResult(**d)


_SELECT = f"SELECT {', '.join(COLS)} FROM map_results "


def get(store: Store, map_id: str) -> MapResult:
    """One map result by id; ``MapResultError`` when the journal has none."""
    validate_run_id(map_id, "map id")
    row = store.db.execute(_SELECT + "WHERE id=?", (map_id,)).fetchone()
    if row is None:
        raise MapResultError(f"no map result {map_id!r} in {store.path}")
    return _row(row)


def find(store: Store, map_id: str) -> MapResult | None:
    """``get`` without the error: None when ``map_id`` is not a map's (a run's, or unknown)."""
    try:
        return get(store, map_id)
    except StoreError:
        return None


def listed(store: Store, machine: str | None = None, limit: int = 20) -> list[MapResult]:
    """Map results, newest first (of ``machine`` only when given)."""
    if machine is None:
        rows = store.db.execute(_SELECT + "ORDER BY created_at DESC LIMIT ?", (limit,))
    else:
        rows = store.db.execute(_SELECT + "WHERE machine=? ORDER BY created_at DESC LIMIT ?",
                                (machine, limit))
    return [_row(r) for r in rows.fetchall()]


def last(store: Store, machine: str) -> MapResult | None:
    got = listed(store, machine, 1)
    return got[0] if got else None


def export_map(store: Store, map_id: str, out: Path | str) -> MapResult:
    """Copy the journaled map file to ``out`` after checking it is the one journaled (its
    SHA-256): a file changed or gone since is refused, naming it."""
    m = get(store, map_id)
    src = Path(m.json_path)
    try:
        data = src.read_bytes()
    except OSError as e:
        raise MapResultError(f"map {map_id}: its file {src} cannot be read: "
                             f"{e.strerror or e}") from None
    if hashlib.sha256(data).hexdigest() != m.json_sha256:
        raise MapResultError(f"map {map_id}: {src} changed since it was journaled (SHA-256 "
                             f"{m.json_sha256[:12]}… expected): not exported")
    try:
        Path(out).write_bytes(data)
    except OSError as e:
        raise MapResultError(f"{out}: cannot write: {e.strerror or e}") from None
    return m


# ----------------------------------------------------------------------- fleet copy (drainer)
def pending(store: Store) -> list[tuple]:
    """Rows (``COLS``) not yet copied to the fleet store: written by this daemon or by a
    ``rumba map --store`` beside it (another connection, no capture trigger), so the drainer
    looks at this flag rather than at the outbox."""
    return store.db.execute(f"SELECT {', '.join(COLS)} FROM map_results WHERE fleet_copied=?"
                            " ORDER BY created_at", (NOT_COPIED,)).fetchall()


def mark_copied(store: Store, map_id: str, created_at: float, refused: bool = False) -> None:
    """Copied (or refused by the fleet store); a row replaced since (newer created_at) stays
    pending."""
    store.db.execute("UPDATE map_results SET fleet_copied=? WHERE id=? AND created_at=?",
                     (REFUSED if refused else COPIED, map_id, created_at))
