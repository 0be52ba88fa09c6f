"""The simulated CNC over OPC UA for the session tests: the thesis truth (Table B.2 errors) and a
connected link to the simulator's asyncua server on a free loopback port."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator

from benchmarks.rigs.daemon_helpers import CONFIG
from drivers.opcua.link import OpcUaLink
from drivers.opcua.schema import OpcUaLinkConfig
from simulators.controller import VirtualController
from simulators.frontends.opcua import OpcUaFrontend
from simulators.truth import TruthModel

ERRORS = CONFIG / "errors/thesis_tableB2.yaml"


def thesis_truth() -> TruthModel:
    """The thesis machine and 4-ball artefact with the errors of ``ERRORS``."""
    return TruthModel.from_files(CONFIG / "machines/thesis_wcbxfzyt.yaml",
                                 CONFIG / "artefacts/thesis_4ball.yaml", ERRORS)


@contextlib.asynccontextmanager
async def opcua_link(ctrl: VirtualController) -> AsyncIterator[OpcUaLink]:
    """``ctrl`` behind its OPC UA server (no security) and a connected driver link to it."""
    sim = OpcUaFrontend(ctrl, security="none")
    url = await sim.start()
    try:
        link = OpcUaLink(OpcUaLinkConfig(transport="opcua", url=url, security="none"))
        await link.connect()
        try:
            yield link
        finally:
            await link.close()
    finally:
        await sim.stop()
