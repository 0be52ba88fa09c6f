"""One simulated CNC behind one real front-end (a pty, a TCP serial server, an asyncua server, a
pymodbus server; free loopback ports): the rigs of tests/test_e2e_transports.py and the stop
matrix (tests/test_stop_matrix.py)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from benchmarks.rigs.daemon_helpers import CONFIG
from simulators.controller import VirtualController
from simulators.truth import TruthModel

ERRORS = CONFIG / "errors/thesis_tableB2.yaml"
BAUD = 921_600  # the highest rate a DNC link accepts (drivers/serial/schema.py)


@dataclass
class Rig:
    """One simulated CNC behind one front-end; ``link`` is the daemon.yaml link section."""

    transport: str
    ctrl: VirtualController
    link: dict[str, Any]
    close: Any
    extra: dict[str, Any] = field(default_factory=dict)


def make_truth() -> TruthModel:
    """The thesis machine with the annex B table of link errors."""
    return TruthModel.from_files(CONFIG / "machines/thesis_wcbxfzyt.yaml",
                                 CONFIG / "artefacts/thesis_4ball.yaml", ERRORS)


async def start_rig(transport: str, ctrl: VirtualController) -> Rig:
    """``ctrl`` behind the front-end of ``transport`` (serial-pty, serial-socket, opcua,
    modbus, sinumerik, lsv2, haas), started on a free loopback port."""
    if transport.startswith("serial"):
        from simulators.frontends.serial import SerialFrontend, SerialSettings

        fe = SerialFrontend(ctrl, SerialSettings(baudrate=BAUD, framing="7E1"))
        if transport == "serial-pty":
            url = await fe.open_pty()
        else:
            url = f"socket://127.0.0.1:{await fe.open_tcp('127.0.0.1', 0)}"
        link = {"transport": "serial", "url": url, "baudrate": BAUD, "framing": "7E1",
                "request_machine": ctrl.machine_id, "tx_chunk_bytes": 64}
        return Rig(transport, ctrl, link, fe.close, {"frontend": fe})
    if transport == "sinumerik":
        from simulators.frontends.sinumerik import SinumerikFrontend

        ctrl.dialect = "siemens"
        fe = SinumerikFrontend(ctrl, security="none")  # security: tests/test_sinumerik_*.py
        url = await fe.start()
        return Rig(transport, ctrl, {"transport": "sinumerik", "url": url, "security": "none",
                                     "nc_start_timeout_s": 60, "stop_timeout_s": 8}, fe.stop,
                   {"frontend": fe})
    if transport == "lsv2":
        from simulators.frontends.lsv2 import Lsv2Frontend

        ctrl.dialect = "heidenhain"
        fe = Lsv2Frontend(ctrl)  # the operator starts the transferred RUMBA.H at once
        port = await fe.start()
        return Rig(transport, ctrl, {"transport": "lsv2", "host": "127.0.0.1", "port": port,
                                     "poll_interval_s": 0.05, "nc_start_timeout_s": 60,
                                     "stop_timeout_s": 8}, fe.stop, {"frontend": fe})
    if transport == "haas":
        import shutil
        import tempfile
        from pathlib import Path

        from simulators.frontends.haas import HaasFrontend

        ctrl.dialect = "haas"
        share = Path(tempfile.mkdtemp(prefix="rumba-haas-share-"))
        fe = HaasFrontend(ctrl, share)  # the start-of-shift routine runs O09100 on ready
        port = await fe.start()

        async def close() -> None:
            await fe.stop()
            shutil.rmtree(share, ignore_errors=True)
        return Rig(transport, ctrl, {"transport": "haas", "host": "127.0.0.1", "port": port,
                                     "program_dir": str(share), "poll_interval_s": 0.02,
                                     "nc_start_timeout_s": 60}, close, {"frontend": fe})
    if transport == "opcua":
        from simulators.frontends.opcua import OpcUaFrontend

        fe = OpcUaFrontend(ctrl, security="none")  # security: tests/test_transport_opcua.py
        url = await fe.start()
        return Rig(transport, ctrl, {"transport": "opcua", "url": url, "security": "none"},
                   fe.stop)
    from simulators.frontends.modbus import ModbusFrontend

    fe = ModbusFrontend(ctrl)
    port = await fe.start("127.0.0.1", 0)
    return Rig(transport, ctrl, {"transport": "modbus", "host": "127.0.0.1", "port": port},
               fe.stop)
