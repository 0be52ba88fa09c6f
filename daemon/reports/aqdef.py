"""SPC export: a machine's runs as a Q-DAS ASCII transfer file (AQDEF, ``.dfq``).

One part per machine (K1001 = machine name), one characteristic per identified ISO 230-1 link
error plus the volumetric indicators, one value record per completed run; with map results of
the linear axes, their characteristics (volumetric max and RMS over the covered box, the
positioning errors' max) follow, one value record per map. Written in the K-field
form of the description and value parts (description part first, then the values), each line
``Kxxxx[/i] value``, Windows-1252 text with CR LF line ends as the Q-DAS tools read it. Field by
field in README "SPC export (AQDEF)".

Text from configuration or the journal (machine, operator, run ids, descriptions) is sanitised:
control characters (line breaks, the DFX separators 0x0F and 0x14) become spaces and characters
outside Windows-1252 become '?', so no value can start a line of its own and pass for a K-field.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from daemon.analysis import figures
from daemon.analysis.judge import volumetric_max_um
from daemon.analysis.result import Analysis
from daemon.machines.tolerances import Limit, Tolerances
from daemon.store.journal import TrendPoint
from daemon.store.map_results import MapResult

AQDEF_VERSION = "Q-DAS ASCII transfer format (AQDEF), K-field form, field numbers of AQDEF V12"
ENCODING = "cp1252"
UNITS = {"um": "µm", "urad": "µrad"}
DECIMALS = 3  # K2022: µm / µrad to the nanometre / nanoradian, below any probe's resolution
VOLUMETRIC = ("VD_MAX", "VD_MAX_RESIDUAL")  # K2001 of the volumetric indicators (≤ 20 chars)
# a map of the linear axes (daemon/store/map_results.py): its volumetric error over the
# covered box (max, with its u; RMS) and each positioning error's largest |e| over its stroke
MAP_VD_MAX, MAP_VD_RMS = "MAP_VD_MAX", "MAP_VD_RMS"
MAP_POSITIONING = ("EXX", "EYY", "EZZ")
NORMS = (*VOLUMETRIC, MAP_VD_MAX, MAP_VD_RMS, *(f"MAP_{n}_MAX" for n in MAP_POSITIONING))
"""Characteristics that are magnitudes (never negative): lower limit 0."""
MAX_TEXT = 80  # no description or name field of the format is longer than this

_CTRL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def text(value: object, limit: int = MAX_TEXT) -> str:
    """One field's text: no control character (a line break would start a line of its own,
    e.g. a forged ``K0001/1``), nothing the file's code page cannot hold, at most ``limit``."""
    s = _CTRL.sub(" ", str(value)).strip()
    s = s.encode(ENCODING, errors="replace").decode(ENCODING)
    return s[:limit]


@dataclass(frozen=True)
class Characteristic:
    key: str  # the link's ISO 230-1 name, or one of VOLUMETRIC
    description: str
    unit: str  # "um" | "urad"
    limit: Limit | None


def characteristics(runs: Sequence[TrendPoint], tol: Tolerances) -> list[Characteristic]:
    """Every link identified in any of ``runs`` (sorted by name), then the volumetric
    indicators; limits from the machine's tolerances (a link's own, else its unit's default)."""
    units: dict[str, str] = {}
    for r in runs:
        for name, e in r.analysis.links.items():
            units.setdefault(name, e.unit or ("urad" if name[1:2] in "ABC" else "um"))
    out = []
    for name in sorted(units):
        u = units[name]
        lim = tol.links.get(name) or (tol.default_rotation_urad if u == "urad"
                                      else tol.default_translation_um)
        kind = "orientation" if u == "urad" else "position"
        out.append(Characteristic(name, f"{name}: ISO 230-1 location error ({kind})", u, lim))
    # the report's own names of these figures (daemon/analysis/figures.py)
    out.append(Characteristic(VOLUMETRIC[0], figures.LABELS[figures.VOLUMETRIC], "um",
                              tol.volumetric_max_um))
    out.append(Characteristic(VOLUMETRIC[1], figures.LABELS[figures.AFTER_LINKS], "um", None))
    return out


def map_characteristics(maps: Sequence[MapResult], tol: Tolerances) -> list[Characteristic]:
    """The map figures (only when there are maps): the volumetric max judged against the
    machine's volumetric limit as the map was, the RMS and each positioning error's max
    reported without one (no tolerance of the machine applies to them)."""
    if not maps:
        return []
    out = [Characteristic(MAP_VD_MAX, "map: volumetric error max over the covered box", "um",
                          tol.volumetric_max_um),
           Characteristic(MAP_VD_RMS, "map: volumetric error RMS over the covered box", "um",
                          None)]
    seen = {n for m in maps for n in m.figures.get("positioning_max_um", {})}
    out += [Characteristic(f"MAP_{n}_MAX", f"map: {n} positioning error max |e| (ISO 230-1)",
                           "um", None) for n in MAP_POSITIONING if n in seen]
    return out


def _map_value(c: Characteristic, m: MapResult) -> tuple[float, float | None] | None:
    if c.key == MAP_VD_MAX:
        return m.volumetric_max_um, m.volumetric_max_u_um
    if c.key == MAP_VD_RMS:
        return m.volumetric_rms_um, None
    e = m.figures.get("positioning_max_um", {}).get(c.key[4:7])
    return None if e is None else (float(e["value_um"]), e.get("u_um"))


def _value(c: Characteristic, a: Analysis) -> tuple[float, float | None] | None:
    if c.key == VOLUMETRIC[0]:
        v = volumetric_max_um(a)
        return None if v is None else (v, None)
    if c.key == VOLUMETRIC[1]:
        v = volumetric_max_um(a, after_links=True)
        return None if v is None else (v, None)
    e = a.links.get(c.key)
    return None if e is None else (float(e.value), e.std)


def _num(v: float) -> str:
    return f"{v:.{DECIMALS}f}"


def _date(t: float) -> str:
    # K0004: DD.MM.YYYY/HH:MM:SS, the daemon's local time (as its reports print it)
    return time.strftime("%d.%m.%Y/%H:%M:%S", time.localtime(t))


def aqdef_lines(machine: str, runs: Sequence[TrendPoint], tol: Tolerances, *,
                operator: str | None = None, artefact: str = "",
                maps: Sequence[MapResult] = ()) -> list[str]:
    """The file's lines (without line ends): K0100, the part (K1xxx), the characteristics
    (K2xxx/i), then per run (oldest first) and characteristic one value record (K0001/i …),
    then per map result (oldest first) one value record of each map characteristic."""
    # a file of maps only (a map job's drop) has no empty run characteristics
    run_chars = characteristics(runs, tol) if runs or not maps else []
    chars = run_chars + map_characteristics(maps, tol)
    out = [f"K0100 {len(chars)}",
           f"K1001 {text(machine, 30)}",
           f"K1002 {text(f'rumba-cnc kinematic check of {machine}')}"]
    if artefact:
        out.append(f"K1003 {text(artefact, 20)}")
    for i, c in enumerate(chars, start=1):
        out += [f"K2001/{i} {text(c.key, 20)}", f"K2002/{i} {text(c.description)}",
                f"K2004/{i} 0",  # variable characteristic
                f"K2022/{i} {DECIMALS}", f"K2101/{i} {_num(0.0)}"]
        if c.limit is not None and c.limit.fail is not None:
            lower = 0.0 if c.key in NORMS else -c.limit.fail  # a norm is never negative
            out += [f"K2110/{i} {_num(lower)}", f"K2111/{i} {_num(c.limit.fail)}"]
        out.append(f"K2142/{i} {UNITS[c.unit]}")
    def record(i: int, c: Characteristic, got: tuple[float, float | None] | None,
               at: float, ident: str, what: str) -> None:
        if got is None or not math.isfinite(got[0]):
            return  # not identified in this run: no value record (K0006 names the run)
        v, u = got
        note = what + (f"; u {_num(u)} {UNITS[c.unit]}" if u else "")
        out.extend([f"K0001/{i} {_num(v)}", f"K0004/{i} {_date(at)}",
                    f"K0006/{i} {text(ident, 40)}"])
        if operator:
            out.append(f"K0008/{i} {text(operator, 40)}")
        out.extend([f"K0009/{i} {text(note)}", f"K0010/{i} {text(machine, 40)}"])

    for r in runs:
        for i, c in enumerate(run_chars, start=1):
            record(i, c, _value(c, r.analysis), r.started_at, r.run_id, f"verdict {r.verdict}")
    for m in maps:
        for i, c in enumerate(chars[len(run_chars):], start=len(run_chars) + 1):
            record(i, c, _map_value(c, m), m.created_at, m.id,
                   f"map; verdict {m.verdict or 'not judged'}")
    return out


def write_aqdef(path: Path | str, machine: str, runs: Iterable[TrendPoint], tol: Tolerances, *,
                operator: str | None = None, artefact: str = "",
                maps: Sequence[MapResult] = ()) -> int:
    """Write the file atomically (a watched SPC folder never sees half a file); the number of
    runs written (each with its value records; the maps' follow them)."""
    runs = list(runs)
    body = "\r\n".join(aqdef_lines(machine, runs, tol, operator=operator,
                                   artefact=artefact, maps=maps)) + "\r\n"
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(body.encode(ENCODING))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return len(runs)
