"""A Modbus temperature transmitter of its own (not the controller): Modbus TCP or RTU, opened
on the first read and kept open for the run; a failed read drops the connection (the next
read reconnects), so a transmitter switched off mid-run costs readings, never the run."""

from __future__ import annotations

import contextlib
from typing import Any

from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient

from contracts.temperatures import TemperatureChannel, TransmitterFile
from drivers.base import LinkError
from drivers.modbus.registers import read_channel


class Transmitter:
    """One transmitter (one TCP address or one RTU line and unit)."""

    def __init__(self, cfg: TransmitterFile) -> None:
        self.cfg = cfg
        self._client: Any = None

    async def _connect(self) -> Any:
        c = self.cfg
        client: Any
        if c.host is not None:
            client = AsyncModbusTcpClient(c.host, port=c.port, timeout=c.timeout_s, retries=0)
        else:
            client = AsyncModbusSerialClient(c.serial or "", baudrate=c.baudrate, bytesize=8,
                                             parity=c.parity, stopbits=1, timeout=c.timeout_s,
                                             retries=0)
        try:
            ok = await client.connect()
        except OSError as e:
            ok, why = False, str(e)
        except BaseException:  # the caller's timeout: nothing half-open stays behind
            client.close()
            raise
        else:
            why = ("connection refused or host unreachable" if c.host is not None
                   else "serial port missing, in use or not permitted")
        if not ok:
            client.close()
            raise LinkError(f"{c.describe()}: cannot connect: {why}")
        return client

    async def read(self, ch: TemperatureChannel) -> float:
        if self._client is None:
            self._client = await self._connect()
        try:
            return await read_channel(self._client, ch, self.cfg.device_id, self.cfg.describe())
        except BaseException:  # failed, or given up on by the caller's timeout: a request
            await self.close()  # left pending must not answer the next one
            raise

    async def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            with contextlib.suppress(Exception):
                client.close()
