"""The linuxcnc programs run through LinuxCNC's own interpreter (``rs274``, Debian package
linuxcnc-uspace, installed by .ci/install-peers.sh): accepted, one STRAIGHT_PROBE per touch at
the intended end point, and a preview that never trips the miss check (#5070 = 0, #<_task> = 0)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from contracts.setup_files import load_artefact, load_machine, plan_from_dict
from programs.dialects import get_dialect
from programs.toolpath import build_program
from tests.regen_golden import golden_program

RS274 = shutil.which("rs274")
pytestmark = [pytest.mark.peer,
              pytest.mark.skipif(RS274 is None, reason="rs274 not installed (LinuxCNC peer: "
                                 "`make peers` installs linuxcnc-uspace)")]
CONFIG = Path(__file__).resolve().parent.parent / "config"
_CALL = re.compile(r"^\s*\d+\s+N\S*\s+(\w+)\((.*)\)\s*$")


def run_rs274(text: str, tmp_path: Path) -> tuple[int, str, list[tuple[str, str]]]:
    src, out = tmp_path / "p.ngc", tmp_path / "canon.txt"
    src.write_text(text)
    r = subprocess.run([RS274, "-g", str(src), str(out)], stdin=subprocess.DEVNULL,
                       capture_output=True, text=True, timeout=60, cwd=tmp_path)
    canon = out.read_text() if out.exists() else ""
    calls = [(m.group(1), m.group(2)) for m in map(_CALL.match, canon.splitlines()) if m]
    return r.returncode, r.stdout + r.stderr, calls


def _vertical():
    machine, mf = load_machine(CONFIG / "machines" / "vertical_wcayfxzt.yaml")
    art = load_artefact(CONFIG / "artefacts" / "vertical_4ball.yaml")
    plan = plan_from_dict({"name": "v", "stylus_diameter_mm": 6, "poses": [[-30, 60], [0, 0]]})
    return build_program(machine, mf, art, plan)


@pytest.mark.parametrize("make", [golden_program, _vertical], ids=["thesis-BC", "vertical-AC"])
def test_rs274_accepts_program_with_one_probe_per_touch_at_its_end_point(make, tmp_path):
    prog = make()
    d = get_dialect("linuxcnc")
    rc, output, calls = run_rs274(d.render(prog), tmp_path)
    assert rc == 0, output
    probes = [np.array([float(x) for x in args.split(",")]) for name, args in calls
              if name == "STRAIGHT_PROBE"]
    assert len(probes) == len(prog.touches)
    letters = "XYZABC"
    for p, t in zip(probes, prog.touches, strict=True):
        assert p[:3] == pytest.approx(t.end, abs=1e-4)
        assert p[letters.index(prog.rotary[0])] == pytest.approx(t.b_deg, abs=1e-4)
        assert p[letters.index(prog.rotary[1])] == pytest.approx(t.c_deg, abs=1e-4)
    # the preview ran to the end: every result line logged (trig 0 in a preview), no abort
    logs = [args.strip('"') for name, args in calls if name == "LOG"]
    hits = [d.parse_result(x) for x in logs]
    assert [h.seq for h in hits] == [t.id.seq for t in prog.touches]
    assert not any(h.triggered for h in hits)
    assert calls[-1][0] in ("PROGRAM_END", "ON_RESET")
    assert "abort" not in output.lower()


def test_without_the_task_guard_a_preview_would_abort(tmp_path):
    """Why the guard exists: in a preview #5070 is 0, so an unguarded check aborts."""
    text = get_dialect("linuxcnc").render(golden_program())
    unguarded = text.replace(" AND [#<_task> EQ 1]", "")
    _rc, output, calls = run_rs274(unguarded, tmp_path)
    assert sum(name == "STRAIGHT_PROBE" for name, _ in calls) == 1
    assert "RUMBA probe miss seq 1" in output + str(calls)
