"""Wrong inputs through the commands and the daemon: a log analysed against the wrong machine
file is refused (identification's plausibility rule, reported by `rumba analyze` and the run
pipeline), special and over-long files end as one ``error:`` line, a zero spindle axis stops
`rumba gcode`, and every schema's booleans are strict."""

from __future__ import annotations

import importlib
import os
import signal
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks.rigs.daemon_helpers import thesis_setup
from contracts.probing_log import MAX_LOG_ROWS, read_log
from contracts.setup_files import load_artefact, load_machine
from contracts.yaml_files import ConfigError, StrictModel, _is_bool_field
from daemon.analysis.pipeline import PipelineError, analyse, row_to_hit
from daemon.cli.main import main
from identification.estimate import estimate
from identification.model import Centres
from identification.plausibility import (
    MAX_LINK_ROTATION_RAD,
    MAX_LINK_TRANSLATION_MM,
    MAX_RESIDUAL_UM,
    implausible,
    setup_limit_mm,
)
from simulators.exact_log import Truth, true_centres

ROOT = Path(__file__).resolve().parents[1]
CFG = ROOT / "config"
LOG = CFG / "examples/thesis_annexB_14poses.csv"
THESIS = CFG / "machines/thesis_wcbxfzyt.yaml"
ARTEFACT_FILE = CFG / "artefacts/thesis_4ball.yaml"
ARTEFACT = load_artefact(ARTEFACT_FILE)


def _cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """``rumba argv`` in-process, stopped by SIGALRM after 60 s (a hang is a failure, not a
    stuck test run)."""
    def fire(signum: int, frame: Any) -> None:
        raise TimeoutError("rumba did not answer within 60 s")

    old = signal.signal(signal.SIGALRM, fire)
    signal.alarm(60)
    try:
        code = main(argv)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    out, err = capsys.readouterr()
    return code, out, err


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    return lines[0]


def _analyze(log: Path | str, machine: Path, capsys) -> tuple[int, str, str]:
    return _cli(["analyze", "--log", str(log), "--machine", str(machine), "--artefact",
                 str(ARTEFACT_FILE)], capsys)


# ------------------------------------------------------------------ a. wrong machine file


@pytest.mark.parametrize(("machine", "shows"), [
    ("vertical_wcayfxzt", "link EC0A 1571 mrad (90°)"),
    ("linuxcnc_xyzbc", "setup of the stylus tip 41.79 mm")])
def test_the_example_log_against_another_machine_file_is_refused(machine: str, shows: str,
                                                                 capsys) -> None:
    code, out, err = _analyze(LOG, CFG / f"machines/{machine}.yaml", capsys)
    assert code == 2 and out == ""
    line = _one_error_line(err)
    assert line.startswith(f"error: {LOG}: implausible fit for machine "), line
    assert shows in line and "wrong machine file" in line, line
    # the log was taken on the thesis machine, which the message names
    assert f"fits {THESIS}" in line, line


def test_the_example_log_against_its_own_machine_file_passes(capsys) -> None:
    code, out, err = _analyze(LOG, THESIS, capsys)
    assert code == 0 and "Link errors" in out and "error" not in err


def test_the_run_pipeline_reports_the_implausible_fit() -> None:
    setup = thesis_setup(plan="thesis_annexB_14poses")
    hits = [row_to_hit(r, setup.machine) for r in read_log(LOG, ARTEFACT)]
    assert analyse(setup, hits, "ok-run").data.links  # the right machine: identified
    vm, vmf = load_machine(CFG / "machines/vertical_wcayfxzt.yaml")
    wrong = replace(setup, machine=vm, machine_file=vmf)
    with pytest.raises(PipelineError, match=r"^identification impossible: run wrong-run: "
                       r"implausible fit for machine vertical-wcayfxzt \(WCAYFXZT\)"):
        analyse(wrong, [row_to_hit(r, vm) for r in read_log(LOG, ARTEFACT)], "wrong-run")


def _centres(machine: Any, truth: Truth, noise_um: float = 0.0) -> Centres:
    poses = [(b, c) for b in (-60.0, 0.0, 45.0, 90.0) for c in (0.0, 120.0, 240.0)]
    xyz = true_centres(machine, ARTEFACT, poses, truth).reshape(-1, 3)
    xyz = xyz + np.random.default_rng(3).normal(0.0, noise_um * 1e-3, xyz.shape)
    n = len(ARTEFACT.balls)
    return Centres(np.repeat(np.arange(len(poses)), n), np.tile(np.arange(n), len(poses)),
                   np.repeat([p[0] for p in poses], n), np.repeat([p[1] for p in poses], n),
                   xyz)


@pytest.mark.parametrize(("truth", "noise_um", "flagged"), [
    (Truth({"EB0Z": 0.8 * MAX_LINK_ROTATION_RAD}), 0.0, None),
    (Truth({"EB0Z": 1.2 * MAX_LINK_ROTATION_RAD}), 0.0, "link EB0Z"),
    (Truth({"EX0C": 0.8 * MAX_LINK_TRANSLATION_MM}), 0.0, None),
    (Truth({"EX0C": -1.2 * MAX_LINK_TRANSLATION_MM}), 0.0, "link EX0C"),
    (Truth(balls_mm=np.array([[0, 0, 12.0]] + [[0, 0, 0]] * 3)), 0.0, None),
    (Truth(balls_mm=np.array([[0, 0, 0]] * 3 + [[0, 13.0, 0]])), 0.0, "setup of ball B4"),
    (Truth(tip_mm=np.array([13.0, 0, 0])), 0.0, "setup of the stylus tip"),
    (Truth(), 0.5 * MAX_RESIDUAL_UM, None),
    (Truth(), 3.0 * MAX_RESIDUAL_UM, "residual RMS"),
])
def test_the_plausibility_thresholds(truth: Truth, noise_um: float, flagged: str | None) -> None:
    m, _ = load_machine(THESIS)
    assert setup_limit_mm(ARTEFACT) == 12.7  # the 25.4 mm balls' radius
    est = estimate(m, ARTEFACT, _centres(m, truth, noise_um))
    found = implausible(m, ARTEFACT, est)
    assert [f.what for f in found][:1] == ([flagged] if flagged else []), found


def test_the_residual_limit_follows_a_stated_noise() -> None:
    m, _ = load_machine(THESIS)
    c = _centres(m, Truth(), 5 * MAX_RESIDUAL_UM)  # residual RMS about 450 µm
    found = implausible(m, ARTEFACT, estimate(m, ARTEFACT, c, sigma_um=20.0))
    assert "residual RMS" not in [f.what for f in found]
    found = implausible(m, ARTEFACT, estimate(m, ARTEFACT, c, sigma_um=2.5))
    assert "(plausible: ≤ 125 µm, 50 × the noise 2.5 µm)" in "; ".join(map(str, found))
    found = implausible(m, ARTEFACT, estimate(m, ARTEFACT, c))  # σ from the residuals
    assert "(plausible: ≤ 100 µm)" in "; ".join(map(str, found))


# ------------------------------------------------------------------ b. special, long files


def test_analyze_refuses_special_files_at_once(tmp_path: Path, capsys) -> None:
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    for path in ("/dev/zero", str(fifo), str(tmp_path)):
        code, _, err = _analyze(path, THESIS, capsys)
        assert code == 2, err
        assert _one_error_line(err).endswith("expected a regular file")
        code, _, err = _cli(["analyze", "--centres", path, "--machine", str(THESIS),
                             "--artefact", str(ARTEFACT_FILE)], capsys)
        assert code == 2 and _one_error_line(err).endswith("expected a regular file")


def test_other_files_the_daemon_reads_refuse_a_fifo(tmp_path: Path, capsys) -> None:
    from daemon.config import read_token_file
    from daemon.hmi.auth import SecretError, load_or_create_secret

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo, 0o600)
    with pytest.raises(ConfigError, match=rf"^hmi.token_file: token file {fifo}: is a FIFO"):
        read_token_file(fifo, "hmi.token_file")
    with pytest.raises(SecretError, match=rf"^{fifo}: is a FIFO"):
        load_or_create_secret(fifo)
    code, _, err = _cli(["sim", "--machine", str(THESIS), "--artefact", str(ARTEFACT_FILE),
                         "--run", str(fifo), "--dialect", "fanuc", "--log",
                         str(tmp_path / "out.csv")], capsys)
    assert code == 2 and _one_error_line(err) == f"error: {fifo}: is a FIFO (named pipe): " \
        "expected a regular file"
    (tmp_path / "token").write_bytes(b"\xff" * 20)
    (tmp_path / "token").chmod(0o600)
    with pytest.raises(ConfigError, match="not UTF-8"):
        read_token_file(tmp_path / "token", "hmi.token_file")


def test_analyze_refuses_an_over_long_log_in_well_under_a_few_seconds(tmp_path: Path,
                                                                      capsys) -> None:
    head, row = LOG.read_text().splitlines()[:2], LOG.read_text().split("\n")[2].split(",")
    path = tmp_path / "long.csv"
    with path.open("w") as f:
        f.write("\n".join(head) + "\n")
        for k in range(MAX_LOG_ROWS + 1):
            row[1], row[3] = str(k + 1), str(k // 56)
            f.write(",".join(row) + "\n")
    t0 = time.process_time()  # CPU seconds: the work, whatever else the box runs
    code, _, err = _analyze(path, THESIS, capsys)
    took = time.process_time() - t0
    assert code == 2 and f"more than {MAX_LOG_ROWS} touch rows" in _one_error_line(err)
    assert took < 2.0, f"{took:.1f} CPU s"


# ------------------------------------------------------------------ c. directions


def test_gcode_refuses_a_zero_spindle_axis(tmp_path: Path, capsys) -> None:
    text = THESIS.read_text()
    bad = tmp_path / "m.yaml"
    bad.write_text(text.replace("spindle_axis: [0, 0, 1]", "spindle_axis: [0, 0, 0]"))
    code, out, err = _cli(["gcode", "--machine", str(bad), "--artefact", str(ARTEFACT_FILE),
                           "--plan", str(CFG / "plans/thesis_ch3_7poses.yaml"), "--dialect",
                           "fanuc"], capsys)
    assert code == 2 and out == ""
    assert _one_error_line(err).startswith(
        f"error: {bad}: tool.spindle_axis: must be a non-zero direction"), err


# ------------------------------------------------------------------ d. strict booleans


SCHEMA_MODULES = [
    "contracts.setup_files", "contracts.plan_targets", "contracts.controller_kinematics",
    "daemon.config", "daemon.mqtt.config", "daemon.notify.config", "simulators.errors_schema",
    "simulators.faults", "drivers.can.schema", "drivers.modbus.schema",
    "drivers.linuxcnc.schema", "drivers.opcua.schema", "drivers.serial.schema"]


def _schemas() -> list[type[StrictModel]]:
    for name in SCHEMA_MODULES:
        importlib.import_module(name)
    out, todo = [], list(StrictModel.__subclasses__())
    while todo:
        cls = todo.pop()
        out.append(cls)
        todo += cls.__subclasses__()
    return sorted(set(out), key=lambda c: f"{c.__module__}.{c.__qualname__}")


def test_every_boolean_of_every_schema_is_strict() -> None:
    fields = [(cls, name) for cls in _schemas() for name, f in cls.model_fields.items()
              if _is_bool_field(f.annotation)]
    names = {f"{c.__name__}.{n}" for c, n in fields}
    assert {"GuardsFile.unattended", "PlanFile.drift_check", "HmiFile.enabled",
            "SerialLinkConfig.xonxoff"} <= names, names
    assert len(fields) >= 12, names
    for cls, name in fields:
        for bad in ("yes", "true", "on", 1, 0, 1.0, "1", "", [True]):
            try:
                cls.model_validate({name: bad})
                raise AssertionError(f"{cls.__name__}.{name} = {bad!r} accepted")
            except ValueError as e:  # pydantic's ValidationError
                errs = [x for x in e.errors() if x["loc"] == (name,)]  # type: ignore[attr-defined]
                assert errs and "expected true or false" in errs[0]["msg"], (cls, name, bad)
        for good in (True, False):
            try:
                cls.model_validate({name: good})
            except ValueError as e:
                assert not [x for x in e.errors() if x["loc"] == (name,)], (cls, name)  # type: ignore[attr-defined]
