"""Temperature channels end to end: daemon.yaml → Service against the simulated
CNC with a warm-up (simulators/thermal.py) behind its real front-end (an asyncua server, a pymodbus
server) and a simulated Modbus TCP transmitter beside it; the readings at the start, at every pose
and at the end are journaled, agree with the thermal state the touches drift with, reach the
analysis JSON and the verdict (a change limit → WARN with the reason, never FAIL); a channel that
cannot be read is journaled with the reason and the run goes on."""

from __future__ import annotations

import contextlib
import json

import pytest
import pytest_asyncio

from benchmarks.rigs.rig_helpers import start_rig
from benchmarks.rigs.temperature_helpers import run_from_cnc
from benchmarks.rigs.warm_cnc import (
    SPINDLE,
    machine_entry,
    sensor,
    warm_truth,
    write_config,
)
from contracts.yaml_files import ConfigError
from daemon.config import load_daemon_config
from daemon.run.session import State
from simulators.controller import VirtualController
from simulators.frontends.transmitter import TransmitterFrontend

UNREADABLE = {"opcua": "/Channel/Temperatures/none", "modbus": "input:4000",
              "sinumerik": "/Channel/Parameter/R[u1,999]"}


@pytest_asyncio.fixture
async def cnc(request):
    """The warming CNC behind the transport's front-end and a transmitter beside it."""
    ctrl = VirtualController(warm_truth())
    rig = await start_rig(request.param, ctrl)
    tx = TransmitterFrontend(ctrl)
    port = await tx.start()
    try:
        yield rig, tx, port
    finally:
        with contextlib.suppress(Exception):
            await tx.stop()
        await rig.close()


@pytest.mark.asyncio
@pytest.mark.parametrize("cnc", ["opcua", "modbus", "sinumerik"], indirect=True)
async def test_channels_read_at_start_every_pose_and_end_agree_with_the_warmup(cnc, tmp_path):
    rig, tx, port = cnc
    channels = [
        {"name": "spindle", "source": "controller", **SPINDLE[rig.transport]},
        {"name": "column", "source": "transmitter", "address": "input:0", "scale": 0.1,
         "transmitter": {"host": "127.0.0.1", "port": port, "device_id": 1}},
        {"name": "broken", "source": "controller", "address": UNREADABLE[rig.transport]},
    ]
    cfg = load_daemon_config(write_config(tmp_path, machine_entry(
        rig.link, channels, {"spindle": {"change_c": 0.5, "min_c": 15, "max_c": 35}})))
    run = await run_from_cnc(cfg, rig.ctrl)
    assert run.session.state == State.IDLE, run.session.reason
    readings, analysis, verdict = run.readings, run.analysis, run.verdict
    assert run.report is not None, run.run_id
    html_path, json_path = run.report
    t_end = rig.ctrl.machine_time_s  # the program's end: nothing ran after it on this link
    plan_poses = list(range(7))
    for name in ("spindle", "column", "broken"):
        mine = [r for r in readings if r.channel == name]
        assert [r.at for r in mine] == ["start", *["pose"] * 7, "end"], (name, mine)
        assert [r.pose for r in mine if r.at == "pose"] == plan_poses
    ok = [r for r in readings if r.channel != "broken"]
    assert all(r.value_c is not None and not r.error for r in ok), ok
    broken = [r for r in readings if r.channel == "broken"]
    assert all(r.value_c is None and "broken" in r.error for r in broken), broken
    # the values come from the thermal state the touches drift with: cold at the start (machine
    # time 0), warming monotonically, the live transmitter exactly the state at the end
    spindle = [r.value_c for r in readings if r.channel == "spindle"]
    column = [r.value_c for r in readings if r.channel == "column"]
    assert spindle[0] == pytest.approx(sensor("Z", 0.0), abs=0.01)
    assert column[0] == pytest.approx(sensor("X", 0.0), abs=0.05)
    assert spindle == sorted(spindle) and column == sorted(column)
    assert column[-1] == pytest.approx(round(sensor("X", t_end) / 0.1) * 0.1, abs=1e-9)
    assert spindle[-1] <= sensor("Z", t_end) + 0.01
    assert spindle[-1] - spindle[0] > 1.0  # 8 °C rise, τ 5 min over a program of minutes
    # summary in the analysis JSON, the change limit turns the verdict to WARN with the reason
    t = analysis.temperatures
    assert t["spindle"]["change_c"] == pytest.approx(spindle[-1] - spindle[0])
    assert t["spindle"]["source"].startswith(f"spindle: {rig.transport}")
    assert t["column"]["source"].startswith("column: modbus-tcp 127.0.0.1")
    assert t["broken"]["unread"] == 9 and t["broken"]["min_c"] is None
    assert len(t["spindle"]["per_pose"]) == 7
    assert verdict["status"] == "WARN", verdict
    why = [r for r in verdict["reasons"] if "temperature change spindle" in r]
    assert why and "machine not thermally stable: |change| > 0.5 °C" in why[0], verdict
    assert not any("temperature spindle" in r and "range" in r for r in verdict["reasons"])
    assert tx.reads >= 9
    # the report: HTML table, audit row naming the sources, JSON summary
    html = html_path.read_text(encoding="utf-8")
    assert "Temperatures during the run" in html and "no temperature sensor" not in html
    assert f"spindle {spindle[0]:.1f} → {spindle[-1]:.1f} °C" in html  # the audit row
    assert "column: modbus-tcp 127.0.0.1" in html
    assert "9 of 9 readings failed" in html  # the broken channel, with its reason
    doc = json.loads(json_path.read_text(encoding="utf-8"))
    assert doc["analysis"]["temperatures"]["column"]["end_c"] == column[-1]


@pytest.mark.parametrize(("channel", "limits", "message"), [
    ({"name": "s", "address": "ns=2;s=/T", "colour": "red"}, {},
     "machines.0.temperatures.0.colour"),
    ({"name": "s", "address": "#5021"}, {}, "machines.0.temperatures.0.address: address "
     "'#5021' is not an OPC UA node id"),
    ({"name": "s", "source": "transmitter", "address": "input:1"}, {},
     "needs a 'transmitter' section"),
    ({"name": "s", "source": "transmitter", "address": "coil:1",
      "transmitter": {"host": "127.0.0.1"}}, {}, "input:N or holding:N"),
    ({"name": "s", "address": "/T"}, {"spindel": {"change_c": 1}},
     "tolerances.temperatures.spindel: no temperature channel of that name"),
    ({"name": "s", "address": "/T"}, {"s": {"min_c": 30, "max_c": 20}},
     "min_c 30.0 must be below max_c 20.0"),
    ({"name": "s x", "address": "/T"}, {}, "machines.0.temperatures.0.name"),
])
def test_bad_channel_config_is_one_line_naming_the_key(tmp_path, channel, limits, message):
    link = {"transport": "opcua", "url": "opc.tcp://127.0.0.1:4840", "security": "none"}
    path = write_config(tmp_path, machine_entry(link, [channel], limits))
    with pytest.raises(ConfigError) as e:
        load_daemon_config(path)
    assert message in str(e.value) and "\n" not in str(e.value).strip(), str(e.value)


@pytest.mark.peer
@pytest.mark.asyncio
async def test_modbus_rtu_transmitter_over_a_pty_pair(tmp_path):
    """The transmitter on an RTU line (socat's pty pair, as a USB-RS485 adapter would be): the
    daemon's reader gets the thermal state's reading, and a silent line is a clear error."""
    import asyncio
    import os
    import shutil
    import signal
    import subprocess
    import time

    from contracts.temperatures import TemperatureChannel, TransmitterFile
    from drivers.base import LinkError
    from drivers.modbus.transmitter import Transmitter

    socat = shutil.which("socat")
    if socat is None:
        pytest.skip("socat not installed (.ci/install-peers.sh installs it)")
    a, b = tmp_path / "ttyA", tmp_path / "ttyB"
    proc = subprocess.Popen([socat, f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                            stderr=subprocess.DEVNULL, start_new_session=True)
    ctrl = VirtualController(warm_truth())
    ctrl.machine_time_s = 240.0  # four minutes into a program
    fe = TransmitterFrontend(ctrl, device_id=7)
    tx = None
    try:
        deadline = time.monotonic() + 5
        while not (a.exists() and b.exists()):
            assert time.monotonic() < deadline, "socat did not create its ptys"
            await asyncio.sleep(0.02)
        await fe.start_rtu(str(b), baudrate=19200)
        ch = TemperatureChannel(name="column", source="transmitter", address="input:2",
                                scale=0.1, transmitter=TransmitterFile(
                                    serial=str(a), baudrate=19200, device_id=7))
        tx = Transmitter(ch.transmitter)
        value = await tx.read(ch)
        assert value == pytest.approx(round(sensor("Z", 240.0) / 0.1) * 0.1, abs=1e-9)
        assert value > sensor("Z", 0.0) + 1.0  # warmed since the start
        await tx.close()  # one user of the line at a time (pymodbus locks the port)
        wrong = ch.model_copy(update={"transmitter": TransmitterFile(
            serial=str(a), baudrate=19200, device_id=9, timeout_s=0.3)})
        with pytest.raises(LinkError, match=r"modbus-rtu .* unit 9: temperature column"):
            await Transmitter(wrong.transmitter).read(wrong)  # nobody answers unit 9
    finally:
        if tx is not None:
            await tx.close()
        await fe.stop()
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(5)


def test_dnc_temperature_variable_cannot_inject_gcode():
    """Only a Fanuc common variable outside rumba's own reaches the program text; anything else
    is refused when the program is generated (and by the config before that)."""
    from programs.dialects import get_dialect
    from programs.geometry import ProgramError
    from programs.model import Program

    prog = Program.__new__(Program)
    for bad in ("#593]M30", "#599", "#600", "#5021", "R21", "#1\nM30", "#<_t>"):
        prog.temperature_vars = (bad,)
        with pytest.raises(ProgramError, match="is not a fanuc variable"):
            get_dialect("fanuc").temperature_prints(prog)
    prog.temperature_vars = ("#593", "#100", "#750")
    assert [t["var"] for t in get_dialect("haas").temperature_prints(prog)] == [
        "#593", "#100", "#750"]
    for other in ("siemens", "heidenhain"):  # R / Q parameters (test_temperature_dnc_dialects)
        with pytest.raises(ProgramError, match=f"is not a {other} variable"):
            get_dialect(other).temperature_prints(prog)
    with pytest.raises(ProgramError, match="prints no temperature lines"):
        get_dialect("linuxcnc").temperature_prints(prog)
