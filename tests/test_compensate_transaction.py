"""A compensation is one guarded transaction per machine: concurrent confirms in
real processes, the machine lock shared by runs and confirms across processes, the journal's
own one-applied-row rule, confirm after rollback only with --again, the cumulative guard, and
validated names. Real SQLite files, real processes; the LinuxCNC on this PC is a fake HAL (pins
in a shared file, setp/getp monkeypatched before the fork) over a real HAL file."""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import io
import json
import multiprocessing
import re
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from contracts.probing_log import write_log
from daemon.analysis.replay_link import ReplayLink
from daemon.compensation import journal as cj
from daemon.compensation.names import BadName, validate_by
from daemon.config import load_daemon_config
from daemon.run.session import Refused, Session
from daemon.store import machine_lock
from daemon.store.journal import Store
from drivers.linuxcnc import halkins
from simulators.exact_log import shipped_run_rows
from tests.cli_helpers import run_cli
from tests.test_compensate import LINKS, MACHINE, PLAN, _journal, _world

PINS = {"xyzbc-trt-kins.x-rot-point": 0.0, "xyzbc-trt-kins.y-rot-point": 0.0,
        "xyzbc-trt-kins.z-rot-point": 0.0, "xyzbc-trt-kins.x-offset": 12.5,
        "xyzbc-trt-kins.z-offset": -40.0}
X = "xyzbc-trt-kins.x-offset"
PY = sys.executable


def fake_linuxcnc(tmp: Path, monkeypatch) -> tuple[Path, Path]:
    """A LinuxCNC on this PC as far as rumba can tell: pins in ``pins.json`` (shared by forked
    processes, setp counted), the running INI and its real HAL file. (pins file, HAL file)."""
    pins, hal, ini = tmp / "pins.json", tmp / "machine.hal", tmp / "machine.ini"
    pins.write_text(json.dumps({"pins": PINS, "setp": 0}))
    hal.write_text("loadrt xyzbc-trt-kins\n" + "".join(f"setp {p} {v}\n"
                                                       for p, v in PINS.items()))
    ini.write_text("[HAL]\nHALFILE = machine.hal\n")

    @contextlib.contextmanager
    def locked():
        with open(tmp / "pins.lock", "a") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            yield

    def setp(pin: str, value: float) -> None:
        with locked():
            d = json.loads(pins.read_text())
            d["pins"][pin], d["setp"] = float(value), d["setp"] + 1
            pins.write_text(json.dumps(d))

    def read_pins(names: list[str]) -> dict[str, float]:
        with locked():
            return {n: json.loads(pins.read_text())["pins"][n] for n in names}

    monkeypatch.setattr(halkins, "setp", setp)
    monkeypatch.setattr(halkins, "read_pins", read_pins)
    monkeypatch.setattr(halkins, "running_ini", lambda: ini)
    return pins, hal


def _confirm_in_child(cfg: str, barrier, out) -> None:
    from daemon.cli.main import main

    buf = io.StringIO()
    barrier.wait()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        code = main(["compensate", "--config", cfg, "--confirm", "synth", "--by", "alice"])
    out.put((code, buf.getvalue()))


def test_four_concurrent_confirms_apply_once(tmp_path, capsys, monkeypatch):
    cfg = _world(tmp_path, capsys, host="127.0.0.1")  # loopback: LinuxCNC on this PC
    pins, hal = fake_linuxcnc(tmp_path, monkeypatch)
    ctx = multiprocessing.get_context("fork")  # the children inherit the fake HAL
    barrier, out = ctx.Barrier(4), ctx.Queue()
    procs = [ctx.Process(target=_confirm_in_child, args=(cfg, barrier, out)) for _ in range(4)]
    for p in procs:
        p.start()
    results = [out.get(timeout=240) for _ in procs]
    for p in procs:
        p.join(30)
    codes = sorted(c for c, _ in results)
    assert codes == [0, 2, 2, 2], results
    for code, text in results:
        if code == 2:
            assert "refused" in text and ("busy" in text or "already applied" in text
                                          or "changed after run synth" in text), text
    rows = _journal(cfg)
    applied = [r for r in rows if r.state == "applied"]
    assert len(applied) == 1 and applied[0].decision == 1, [(r.state, r.reason) for r in rows]
    (v,) = applied[0].values
    state = json.loads(pins.read_text())
    assert state["setp"] == 1  # one write to the controller
    assert state["pins"][X] == v.new  # journal == live value
    assert f"setp {X} {v.new:.6f}" in hal.read_text() or f"setp {X} {v.new}" in hal.read_text()
    assert len(list(tmp_path.glob("machine.hal.rumba-*.bak"))) == 1
    assert not list(tmp_path.glob(".machine.hal.rumba-*.tmp"))


def test_the_journal_itself_refuses_a_second_applied_row(tmp_path, capsys):
    cfg = _world(tmp_path, capsys)
    store = Store(load_daemon_config(cfg).store_path)
    try:
        cj.record(store, "lcnc", "synth", "linuxcnc", "applied", [], applied_at=time.time())
        with pytest.raises(sqlite3.IntegrityError):
            cj.record(store, "lcnc", "synth", "linuxcnc", "applied", [],
                      applied_at=time.time())
        with pytest.raises(cj.DecisionTaken):
            cj.begin_apply(store, "lcnc", "synth", "linuxcnc", [], confirmed_by="bob",
                           decision=1)
    finally:
        store.close()


def _slow_session(cfg: str, rows) -> tuple[Session, Store]:
    conf = load_daemon_config(cfg)
    setup = conf.machines["lcnc"]
    store = Store(conf.store_path)
    from daemon.analysis.replay_link import prepare_from_rows

    link = ReplayLink(rows, setup.machine, delay_s=0.5)
    return Session(setup, link, store, conf.reports_dir, prepare=prepare_from_rows(rows)), store


def _rows(links: dict[str, float], run_id: str = "synth"):
    return shipped_run_rows(MACHINE, Path(MACHINE).parents[1] / "artefacts/thesis_4ball.yaml",
                            PLAN, links, run_id=run_id)


def _cli(cfg: str, *args: str) -> subprocess.CompletedProcess:
    """`rumba compensate` in a process of its own (as an operator at a terminal)."""
    return subprocess.run([PY, "-m", "daemon.cli.main", "compensate", "--config", cfg, *args],
                          capture_output=True, text=True, timeout=240, check=False)


async def test_a_run_and_a_confirm_exclude_each_other_across_processes(tmp_path, capsys):
    cfg = _world(tmp_path, capsys)
    session, store = _slow_session(cfg, _rows(LINKS, "live"))
    try:
        run_id = session.start("cli")
        async with asyncio.timeout(60):
            while session.state.name not in ("CAPTURE",):
                await asyncio.sleep(0.05)
        # a CLI confirm in another process while the run captures: refused, naming the run
        r = await asyncio.to_thread(_cli, cfg, "--confirm", "synth", "--by", "alice")
        assert r.returncode == 2, r.stdout + r.stderr
        assert f"run {run_id}" in r.stdout and "busy" in r.stdout, r.stdout
        await session.abort("test")
    finally:
        store.close()
    states = [x.state for x in _journal(cfg)]
    assert states == ["refused"]
    # a confirm in progress (another process holds the machine) refuses a run start
    holder = subprocess.Popen([PY, "-c", (
        "import sys, time; from daemon.store import machine_lock as m; "
        f"l = m.acquire({str(load_daemon_config(cfg).store_path)!r}, 'lcnc', "
        "'compensation of run synth by alice'); print('held', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        session, store = _slow_session(cfg, _rows(LINKS, "live2"))
        try:
            with pytest.raises(Refused, match="compensation of run synth by alice"):
                session.start("cli")
        finally:
            store.close()
    finally:
        holder.kill()
        holder.wait()
    # once both are over, the confirm goes through
    r = await asyncio.to_thread(_cli, cfg, "--confirm", "synth", "--by", "alice")
    assert r.returncode == 0, r.stdout + r.stderr
    assert machine_lock.lock_path(load_daemon_config(cfg).store_path, "lcnc").exists()


def test_confirm_after_rollback_only_with_again(tmp_path, capsys):
    cfg = _world(tmp_path, capsys)
    confirm = ["compensate", "--config", cfg, "--confirm", "synth", "--by", "alice"]
    assert run_cli(confirm, capsys)[0] == 0
    assert run_cli(["compensate", "--config", cfg, "--rollback", "--machine", "lcnc", "--by",
                    "bob"], capsys)[0] == 0
    code, out, _ = run_cli(confirm, capsys)
    assert code == 2 and "confirming it again is a new decision — give --again" in out, out
    code, _, err = run_cli(["compensate", "--config", cfg, "synth", "--again"], capsys)
    assert code == 2 and "--again is a new decision to apply" in err
    code, out, _ = run_cli([*confirm, "--again"], capsys)
    assert code == 0 and "applied (journal #" in out, out
    rows = _journal(cfg)
    assert [(r.state, r.decision) for r in rows] == [
        ("rolled_back", 1), ("rolled_back", None), ("refused", None), ("applied", 2)]
    code, out, _ = run_cli([*confirm, "--again"], capsys)  # applied: never twice at once
    assert code == 2 and ("already applied" in out or "changed after run synth" in out), out


def _import(cfg: str, tmp: Path, run_id: str, links: dict[str, float], capsys) -> None:
    log = tmp / f"{run_id}.csv"
    write_log(log, _rows(links, run_id))
    code, _, err = run_cli(["history", "--config", cfg, "--import", str(log), "--machine",
                            "lcnc"], capsys)
    assert code == 0, err


def test_cumulative_guard_against_the_last_verified_baseline(tmp_path, capsys):
    cfg = _world(tmp_path, capsys, links={**LINKS, "EX0C": -140},
                 guards={"max_change_um": 150, "max_total_um": 300})
    by = ["--by", "alice"]
    assert run_cli(["compensate", "--config", cfg, "--confirm", "synth", *by], capsys)[0] == 0
    # the next run still sees EX0C −140 µm (the first change did not hold): a second
    # +140 µm would walk x-offset 280 µm from the machine file's value
    _import(cfg, tmp_path, "again", {**LINKS, "EX0C": -280}, capsys)
    # this machine's limits pass it; a PASS verification proposes nothing (the worth rule's
    # rule 5), saying the compensation did not hold
    code, out, _ = run_cli(["compensate", "--config", cfg, "again"], capsys)
    assert code == 0 and "verifies compensation #1 (from run synth) and PASSed" in out, out
    assert "x-offset would move again beyond U (the compensation did not hold" in out
    assert "proposed (journal" not in out and not (tmp_path / "reports" /
                                                  "proposal-lcnc-again.json").exists()
    # had it FAILed (tighter limits), the cumulative guard refuses the walk
    _set_verdict(cfg, "again", "FAIL")
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "again", *by], capsys)
    assert code == 2, out
    assert re.search(r"x-offset: \+2[78]\d\.\d µm since the last verified baseline", out), out
    assert "over the cumulative limit 150.0 µm" in out
    assert "the machine file's values" in out
    assert [r.state for r in _journal(cfg)] == ["applied", "proposed", "refused"]


def _set_verdict(cfg: str, run_id: str, status: str) -> None:
    store = Store(load_daemon_config(cfg).store_path)
    try:
        store.save_verdict(run_id, status, [f"judged {status} here"], [], status)
    finally:
        store.close()


def test_a_verified_compensation_moves_the_baseline(tmp_path, capsys):
    cfg = _world(tmp_path, capsys, links={**LINKS, "EX0C": -140},
                 guards={"max_change_um": 150, "max_total_um": 300})
    by = ["--by", "alice"]
    assert run_cli(["compensate", "--config", cfg, "--confirm", "synth", *by], capsys)[0] == 0
    _import(cfg, tmp_path, "held", {**LINKS, "EX0C": -140}, capsys)  # it held: EX0C ≈ 0
    _import(cfg, tmp_path, "drift", {**LINKS, "EX0C": -240}, capsys)  # later: 100 µm more
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "drift", *by], capsys)
    assert code == 0, out
    assert _journal(cfg)[0].verify_run_id == "held"


@pytest.mark.parametrize("name", [
    "alice\nforged journal line", "a" * 65, "\x1b[31mred", "al\u202eice", "bob\u200b",
    "Unattended", "ｕｎａｔｔｅｎｄｅｄ", "unаttended", "un-attended", " alice", "tab\there"])
def test_by_is_validated(tmp_path, capsys, name):
    cfg = _world(tmp_path, capsys)
    code, out, err = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by",
                              name], capsys)
    assert code == 2 and err.count("\n") == 1 and "--by" in err, (out, err)
    assert _journal(cfg) == []  # nothing journaled under a refused name


def test_by_accepts_ordinary_names():
    for name in ("alice", "Jürgen Müller", "王小明", "shift-2 (night)", "unattended"):
        assert validate_by(name) == name
    with pytest.raises(BadName, match="reserved"):
        validate_by("unattended", "HMI session", allow_unattended=False)
