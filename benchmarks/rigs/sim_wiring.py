"""Wire the simulated CNC to a daemon link over a real transport, in a few lines (for the
end-to-end suite, benchmarks and demos):

    ctrl = VirtualController(truth, time_scale=0.02, dialect="fanuc")
    cfg, stop = await sim_link("modbus", ctrl)          # front-end listening on loopback
    session = Session(replace(setup, link=cfg), make_link(replace(setup, link=cfg)), store, dir)
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any


async def sim_link(transport: str, ctrl: Any, **kw: Any
                   ) -> tuple[Any, Callable[[], Awaitable[None]]]:
    """Start the simulator front-end of ``transport`` for ``ctrl`` on a free loopback port;
    return the matching daemon link config and the front-end's stop coroutine function.
    ``kw`` goes to the link config (e.g. baudrate for serial)."""
    from drivers.modbus.schema import ModbusLinkConfig
    from drivers.opcua.schema import OpcUaLinkConfig
    from drivers.serial.schema import SerialLinkConfig

    if transport == "opcua":
        from simulators.frontends.opcua import OpcUaFrontend

        fe = OpcUaFrontend(ctrl, security="none")
        url = await fe.start()
        return OpcUaLinkConfig(transport="opcua", url=url, security="none", **kw), fe.stop
    if transport == "modbus":
        from simulators.frontends.modbus import ModbusFrontend

        fe = ModbusFrontend(ctrl)
        port = await fe.start()
        return ModbusLinkConfig(transport="modbus", host="127.0.0.1", port=port, **kw), fe.stop
    if transport == "serial":
        from simulators.frontends.serial import SerialFrontend, SerialSettings

        baud = kw.pop("baudrate", 115200)
        fe = SerialFrontend(ctrl, SerialSettings(baudrate=baud, framing="8N1", eol="LF"))
        port = await fe.open_tcp()
        return SerialLinkConfig(transport="serial", url=f"socket://127.0.0.1:{port}",
                                baudrate=baud, framing="8N1", **kw), fe.close
    raise ValueError(f"transport {transport!r}: expected opcua, modbus or serial")
