"""A simulated Modbus temperature transmitter beside the controller, on TCP or
on an RTU serial line: input registers 0, 1, 2 carry the X, Y, Z structure sensors of the
controller's thermal state (int16, 0.1 °C per count, as a common RTD transmitter does), read
live at every request."""

from __future__ import annotations

from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from simulators import thermal

WORDS = 8


class TransmitterFrontend:
    """``await start()`` returns the bound TCP port (loopback, port 0 = a free one)."""

    def __init__(self, controller: Any, *, device_id: int = 1) -> None:
        self.ctrl = controller
        self.device_id = device_id
        self.reads = 0
        self._server: ModbusTcpServer | ModbusSerialServer | None = None

    def _device(self) -> SimDevice:
        return SimDevice(id=self.device_id, action=self._access, simdata=[
            SimData(0, count=WORDS, values=0, datatype=DataType.REGISTERS)])

    async def start_rtu(self, device: str, baudrate: int = 9600) -> None:
        """Modbus RTU on the serial ``device`` (8N1), e.g. one end of a pty pair."""
        self._server = ModbusSerialServer(self._device(), port=device, baudrate=baudrate)
        await self._server.serve_forever(background=True)

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        self._server = ModbusTcpServer(self._device(), address=(host, port))
        try:
            await self._server.serve_forever(background=True)
        except RuntimeError:
            self._server = None
            raise OSError(f"cannot listen on {host}:{port}") from None
        return self._server.transport.sockets[0].getsockname()[1]  # type: ignore[union-attr]

    async def stop(self) -> None:
        if self._server is not None:
            await self._server.shutdown()
            self._server = None

    async def _access(self, fc: int, start: int, address: int, count: int,
                      registers: list[int], values: list[int] | None) -> ExcCodes | None:
        if values is not None:
            return ExcCodes.ILLEGAL_FUNCTION  # a transmitter is read-only
        regs = [0] * WORDS
        for axis, value in self.ctrl.sensor_temperatures().items():
            regs[thermal.TRANSMITTER_ADDRESS[axis]] = thermal.counts(
                value, thermal.TRANSMITTER_SCALE_C)
        registers[address - start:address - start + count] = regs[address:address + count]
        self.reads += 1
        return None
