"""`rumba verify` / `rumba history`, and runs triggered by CLI, CAN panel and two machines."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from daemon.analysis.replay_link import Faults, ReplayLink, prepare_from_rows
from daemon.cli.commands.verify import verify
from tests.cli_helpers import free_port, run_cli
from tests.waiting import until

# --------------------------------------------------------------------------------- verify


@pytest.mark.parametrize(("faults", "tol", "code", "word"), [
    (Faults(), "", 0, "PASS"),
    (Faults(), "links: {EX0C: {warn: 50, fail: 100}}", 1, "FAIL"),
    (Faults(no_trigger_at=12), "", 2, "ERROR"),
])
async def test_verify_exit_codes(tmp_path, capsys, faults, tol, code, word):
    path = write_daemon_yaml(tmp_path)
    if tol:
        path.write_text(path.read_text().replace("default_rotation_urad:",
                                                 f"{tol}\n      default_rotation_urad:"))
    setup = thesis_setup()
    rows = thesis_rows(setup)
    got = await verify(str(path), "mill1", quiet=True,
                       link_factory=lambda s: ReplayLink(rows, s.machine, faults=faults),
                       prepare=prepare_from_rows(rows))
    out, err = capsys.readouterr()
    assert got == code and word in err
    if code < 2:
        report = out.strip().split("report: ")[1]
        assert Path(report).is_file()
        for written in (Path(report).with_suffix(".pdf"), Path(report).with_suffix(".json")):
            assert written.is_file() and str(written) in out  # every file written is named


def test_verify_unknown_machine(tmp_path, capsys):
    path = write_daemon_yaml(tmp_path)
    code, _, err = run_cli(["verify", "--config", str(path), "--machine", "mill9"], capsys)
    assert code == 2 and "no machine 'mill9' (configured: mill1)" in err


# -------------------------------------------------------------------------------- history


def test_history_import_list_export(tmp_path, capsys):
    from contracts.probing_log import write_log
    path = write_daemon_yaml(tmp_path)
    setup = thesis_setup()
    rows = thesis_rows(setup)
    log = tmp_path / "in.csv"
    write_log(log, rows)
    code, out, _ = run_cli(["history", "--config", str(path), "--import", str(log),
                            "--machine", "mill1"], capsys)
    assert code == 0 and "imported run synth: 140 touches" in out and "report: " in out
    code, out, _ = run_cli(["history", "--config", str(path)], capsys)
    assert code == 0 and "synth" in out and "PASS" in out and "140/140" in out
    exported = tmp_path / "out.csv"
    code, out, _ = run_cli(["history", "--config", str(path), "--export", "synth", "--csv",
                            str(exported)], capsys)
    assert code == 0 and exported.read_text() == log.read_text()
    code, _, err = run_cli(["history", "--config", str(path), "--export", "nope", "--csv",
                            str(exported)], capsys)
    assert code == 2 and "no run 'nope'" in err
    code, _, err = run_cli(["history", "--config", str(path), "--import", str(log),
                            "--machine", "mill1"], capsys)
    assert code == 2 and "already in the journal" in err


# ---------------------------------------------------------------------------- CAN panel


async def test_can_panel_start_abort_and_lamps(tmp_path):
    """The panel on python-can's virtual bus: START starts a run (trigger can), ABORT aborts
    it, lamps follow the state and end on the verdict."""
    import asyncio

    import can

    from contracts.can_frames import LAMP_NAMES, button_frame
    from daemon.config import load_daemon_config
    from daemon.service.service import Service

    channel = f"rumba-test-{os.getpid()}-{time.monotonic_ns()}"
    path = write_daemon_yaml(tmp_path, extra_top=f"can_panel: {{interface: virtual, channel: "
                                                  f"{channel}, machine: mill1, heartbeat_s: 0.2}}")
    setup = thesis_setup()
    rows = thesis_rows(setup)
    svc = Service(load_daemon_config(path),
                  lambda s: ReplayLink(rows, s.machine, delay_s=0.01),
                  prepare=prepare_from_rows(rows))
    panel = can.Bus(interface="virtual", channel=channel)  # the panel is on the bus first
    await svc.start()
    lamps: list[str] = []

    async def read_lamps():
        while True:
            msg = await asyncio.to_thread(panel.recv, 0.1)
            if msg is not None and msg.arbitration_id == 0x641:
                name = LAMP_NAMES[msg.data[0]]
                if not lamps or lamps[-1] != name:
                    lamps.append(name)

    reader = asyncio.create_task(read_lamps())
    session = svc.sessions["mill1"]
    try:
        await until(lambda: lamps == ["idle"], 10, "one heartbeat: the idle lamp")
        panel.send(button_frame(0x640, "start", 1))
        async with asyncio.timeout(10):
            while session.done < 5:
                await asyncio.sleep(0.01)
        assert session.trigger == "can" and session.busy
        panel.send(button_frame(0x640, "start", 1))  # the same press repeated: ignored
        panel.send(button_frame(0x640, "abort", 2))
        async with asyncio.timeout(10):
            while session.busy:
                await asyncio.sleep(0.01)
        assert session.state == "ABORTED"
        assert session.reason.startswith("aborted by CAN panel during "), session.reason
        panel.send(button_frame(0x640, "start", 3))
        async with asyncio.timeout(60):
            while session.state != "IDLE" or session.busy:
                await asyncio.sleep(0.02)
        assert session.verdict["status"] == "PASS"
        await until(lambda: lamps[-1:] == ["pass"], 10, "the pass lamp")
        assert lamps == ["idle", "running", "error", "running", "pass"], lamps
        assert [r.trigger for r in svc.store.runs()] == ["can", "can"]
    finally:
        reader.cancel()
        await svc.stop()
        panel.shutdown()


async def test_verify_through_the_running_daemon(tmp_path, capsys):
    """`rumba verify --daemon`: the CLI trigger of a running service, over its HMI API."""
    from daemon.cli.commands.verify import verify_via_daemon
    from daemon.config import load_daemon_config
    from daemon.service.service import Service

    path = write_daemon_yaml(tmp_path)
    path.write_text(path.read_text().replace("port: 0", f"port: {free_port()}"))
    setup = thesis_setup()
    rows = thesis_rows(setup)
    svc = Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine, delay_s=0.002),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        assert await verify_via_daemon(str(path), "mill1", quiet=True) == 0
        out, err = capsys.readouterr()
        assert "PASS" in err and Path(out.split("report: ")[1].strip()).is_file()
        assert svc.store.runs()[0].trigger == "cli"
        # --operator names the person; journaled with the run and the start action
        assert await verify_via_daemon(str(path), "mill1", quiet=True,
                                       operator="Anna Berg") == 0
        out, _ = capsys.readouterr()
        assert Path(out.split("report: ")[1].strip()).is_file()  # waited for the report
        run = svc.store.runs()[0]
        assert (run.started_by, run.trigger) == ("Anna Berg", "cli")
        from daemon.store.actions import actions
        act = actions(svc.store, "mill1")[0]
        assert (act.action, act.run_id, act.outcome) == ("start", run.id, "ok")
        assert act.detail == "operator named by the script: Anna Berg"
        svc.sessions["mill1"].start("hmi")  # busy: the CLI request is refused with the reason
        with pytest.raises(Exception, match=r"in progress .*started by hmi.*cli request refused"):
            await verify_via_daemon(str(path), "mill1", quiet=True)
    finally:
        await svc.stop()


async def test_two_machines_run_concurrently_with_one_session_each(tmp_path):
    import asyncio

    from daemon.config import load_daemon_config
    from daemon.run.session import Refused
    from daemon.service.service import Service

    path = write_daemon_yaml(tmp_path)
    text = path.read_text()
    second = text[text.index("  - name: mill1"):].replace("name: mill1", "name: mill2")
    path.write_text(text + second)
    setup = thesis_setup()
    rows = thesis_rows(setup)
    svc = Service(load_daemon_config(path),
                  lambda s: ReplayLink(rows, s.machine, delay_s=0.003),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        a, b = svc.trigger("mill1", "hmi"), svc.trigger("mill2", "cli")
        with pytest.raises(Refused, match=r"mill1: run .* in progress"):
            svc.trigger("mill1", "can")
        with pytest.raises(Refused, match="no machine 'mill3'"):
            svc.trigger("mill3", "hmi")
        await asyncio.gather(*(s.wait() for s in svc.sessions.values()))
        runs = {r.id: r for r in svc.store.runs()}
        assert {runs[a].machine, runs[b].machine} == {"mill1", "mill2"}
        assert runs[a].hits == runs[b].hits == 140
        assert runs[a].verdict == runs[b].verdict == "PASS"
    finally:
        await svc.stop()


async def test_verify_operator_is_on_the_report_as_who_started_and_prepared(tmp_path, capsys):
    """A person, not "cli", started the run: `--operator` goes to the
    journal's run row and the report's Started by / Prepared by; a bad name is one line."""
    import json

    from daemon.store.journal import Store

    path = write_daemon_yaml(tmp_path)
    setup = thesis_setup()
    rows = thesis_rows(setup)
    got = await verify(str(path), "mill1", quiet=True, operator="Anna Berg",
                       link_factory=lambda s: ReplayLink(rows, s.machine),
                       prepare=prepare_from_rows(rows))
    out, _ = capsys.readouterr()
    assert got == 0
    report = Path(out.strip().split("report: ")[1])
    store = Store(tmp_path / "journal.sqlite")
    try:
        (run,) = store.runs("mill1")
        assert run.started_by == "Anna Berg" and run.trigger == "cli"
    finally:
        store.close()
    html = " ".join(report.read_text().split())
    assert "Started by</th><td>Anna Berg (CLI)" in html
    assert "Prepared by</td><td class=\"l\">Anna Berg</td>" in html
    assert json.loads(report.with_suffix(".json").read_text())["run"]["id"] == run.id
    for bad, why in (("a\x1bb", "not allowed"), ("unattended", "reserved")):
        code, _, err = run_cli(["verify", "--config", str(path), "--machine", "mill1",
                                "--operator", bad], capsys)
        assert code == 2 and err.startswith("error: --operator: ") and why in err, err
