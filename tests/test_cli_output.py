"""What the CLI prints for people: the first tutorial's `rumba verify` example runs as shipped
(against `rumba sim --serve`), `rumba gcode` reports a real safety margin, the demo gives every
value its unit, the self-check table names its columns in full, spans read the same everywhere."""

from __future__ import annotations

import asyncio
import os
import re
import sys

import pytest

from benchmarks.rigs.daemon_helpers import CONFIG, ROOT, TOLERANCES
from daemon.analysis.judge import judge
from daemon.analysis.result import Analysis, Stability, Where
from daemon.cli.main import main as cli_main
from demos.e2e import links_line
from identification.gap.selfcheck import SCENARIOS, Case, Summary

EXAMPLE = CONFIG / "examples/daemon_sim.yaml"


FIRST_CHECK = ROOT / "docs/tutorials/first-check.md"  # the manual's first tutorial


def readme_block(containing: str) -> list[str]:
    """The commands of the first tutorial's shell blocks that contain ``containing``
    (continuations joined)."""
    found = []
    for block in re.findall(r"```sh\n(.*?)```", FIRST_CHECK.read_text(), re.S):
        if any(c in block for c in containing.split("|")):
            found += [" ".join(c.split()) for c in block.replace("\\\n", " ").splitlines()
                      if c.strip()]
    if not found:
        raise AssertionError(f"no block of {FIRST_CHECK.name} with {containing!r}")
    return found


def test_shipped_example_config_is_valid_as_is(capsys):
    assert cli_main(["run", "--config", str(EXAMPLE), "--check"]) == 0
    assert "OK (1 machines: sim-hmc)" in capsys.readouterr().out


@pytest.mark.slow
async def test_readme_verify_example_runs(tmp_path):
    """The first tutorial's two commands, run from the repository as a new user would; only
    the port is a free one instead of 4841 (the shipped config's, checked to match the page)."""
    sim_cmd, verify_cmd = readme_block("rumba sim --machine|rumba verify --config config/examples/")
    assert sim_cmd.startswith(".venv/bin/rumba sim ") and "--port 4841" in sim_cmd
    assert verify_cmd == (".venv/bin/rumba verify --config config/examples/daemon_sim.yaml "
                          "--machine sim-hmc")
    assert "url: 'opc.tcp://127.0.0.1:4841'" in EXAMPLE.read_text()
    rumba = [sys.executable, "-m", "daemon.cli"]
    sim = await asyncio.create_subprocess_exec(
        *rumba, *sim_cmd.split()[1:-1], "0", cwd=ROOT, stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
    try:
        async with asyncio.timeout(60):
            line = (await sim.stdout.readline()).decode()
        assert line.startswith("listening: opc.tcp://127.0.0.1:"), line
        port = line.split("127.0.0.1:")[1].split("/")[0]
        # the shipped config with the free port; relative paths made absolute for the copy
        cfg = tmp_path / "daemon_sim.yaml"
        cfg.write_text(EXAMPLE.read_text().replace(":4841'", f":{port}'")
                       .replace("../", f"{CONFIG}/"))
        env = {**os.environ, "HOME": str(tmp_path)}  # ~/.local/state/rumba-sim goes here
        verify = await asyncio.create_subprocess_exec(
            *rumba, "verify", "--config", str(cfg), *verify_cmd.split()[4:],
            cwd=ROOT, env=env, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        async with asyncio.timeout(120):
            out, err = await verify.communicate()
        # the thesis errors (EX0C −106 µm) against the example's shop limits (a
        # 0.1 mm pivot error is not fit for 0.1 mm parts): FAIL, exit 1
        assert verify.returncode == 1, err.decode()
    finally:
        if sim.returncode is None:
            sim.terminate()
        await sim.wait()
    assert re.search(r"FAIL\s+run \S+: FAIL: \d+ checks, [1-9]\d* outside limits", err.decode())
    assert "EX0C" in err.decode() + out.decode()
    report = out.decode().split("report: ")[1].strip()
    assert report.startswith(str(tmp_path / ".local/state/rumba-sim/reports/"))
    assert os.path.isfile(report) and os.path.isfile(report.replace(".html", ".pdf"))


def test_gcode_reports_a_real_safety_margin(capsys):
    """The approach to a probing line ends on its ball's standoff by design: the margin
    reported is the closest pass to what a move does not probe (was 0.000 for every program)."""
    code = cli_main(["gcode", "--machine", str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
                     "--artefact", str(CONFIG / "artefacts/thesis_4ball.yaml"),
                     "--plan", str(CONFIG / "plans/thesis_ch3_7poses.yaml"),
                     "--dialect", "fanuc", "-o", os.devnull])
    out = capsys.readouterr().out
    assert code == 0
    margin = float(re.search(r"the closest non-probing move passes (\d+\.\d+) mm beyond the "
                             r"required standoff/clearance", out).group(1))
    assert margin > 0.01, out


def test_demo_gives_every_link_error_its_unit():
    line = links_line({"EX0C": {"value": -106.14, "std": 0.21, "unit": "um"},
                       "EA0C": {"value": -19.1, "std": 1.9, "unit": "urad"}})
    assert line.endswith("EA0C -19.1 ± 1.9 µrad, EX0C -106.1 ± 0.2 µm")


def test_selfcheck_table_names_every_column_in_full():
    cases = [Case(s, None, "p", 0, s if s != "null" else "none", None, None, None, 1.0,
                  False, True) for s in SCENARIOS]
    cases.append(Case("null", None, "p", 1, "linear_scale", "Y", None, None, 1.0, False, False))
    table = Summary(cases).table()
    head = table.splitlines()[0]
    assert head.split() == ["injected", "cases", "ok", "diagnosed", "as", "(cases)"]
    assert "rotary_error_motion 1" in table and "artefact_instability 1" in table
    assert re.search(r"\nnull +2 +50 %  none 1, linear_scale 1\n", table + "\n"), table


def test_short_revisit_span_is_not_zero_minutes():
    """The drift check's span, 7 s at a fast simulator, read "over 0 min" in the verdict."""
    a = Analysis(stability=Stability("c", 1.9, Where(0, "B3"), span_min=0.118))
    tol = TOLERANCES.__class__(**{**TOLERANCES.__dict__, "run_drift_um": 8.0})
    check = next(c for c in judge(a, tol).checks if c.quantity.startswith("revisit"))
    assert check.limit == "health limit 8 µm over 7 s"
