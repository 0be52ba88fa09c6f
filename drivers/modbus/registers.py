"""pymodbus calls as the Modbus drivers make them: a cancellation kept (``keep_cancel``), and a
temperature channel's registers read from the controller's own Modbus link or from a
temperature transmitter (TCP or RTU), decoded as the channel states (contracts)."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable
from typing import Any, TypeVar

from pymodbus.exceptions import ModbusException

from contracts.temperatures import WORDS, TemperatureChannel, decode_registers, modbus_address
from drivers.base import LinkError

T = TypeVar("T")


async def keep_cancel(request: Awaitable[T]) -> T:
    """``await request`` (a pymodbus call), raising the caller's cancellation if one arrived
    meanwhile. pymodbus waits for each response under ``asyncio.wait_for``, which in Python 3.11
    returns the response instead of raising when it arrives in the same loop step as the
    cancellation (CPython gh-86296, fixed in 3.12): a poll loop then carried on polling and the
    daemon's stop never returned (one CI run, a Modbus controller). A cancellation requested
    before the call (a task's cleanup after its own cancel) is not raised again."""
    task = asyncio.current_task()
    before = task.cancelling() if task is not None else 0
    result = await request
    if task is not None and task.cancelling() > before:
        raise asyncio.CancelledError
    return result


async def read_channel(client: Any, ch: TemperatureChannel, device_id: int, where: str) -> float:
    """°C of ``ch`` read with ``client`` (a connected pymodbus async client); ``LinkError``
    naming ``where`` and the register when the read fails or is refused."""
    kind, address = modbus_address(ch.address)
    read = (client.read_input_registers if kind == "input" else client.read_holding_registers)
    what = f"{where}: temperature {ch.name} ({ch.address})"
    try:
        rr = await keep_cancel(read(address, count=WORDS[ch.format], device_id=device_id))
    except (TimeoutError, ModbusException, OSError) as e:
        raise LinkError(f"{what}: {str(e) or type(e).__name__}") from None
    if rr.isError():
        raise LinkError(f"{what}: exception response {rr}")
    return decode_registers(list(rr.registers), ch)
