"""pymodbus calls as the Modbus drivers make them: a cancellation kept (``keep_cancel``, from
drivers/cancel.py), and a temperature channel's registers read from the controller's own Modbus
link or from a temperature transmitter (TCP or RTU), decoded as the channel states
(contracts)."""

from __future__ import annotations

from typing import Any

from pymodbus.exceptions import ModbusException

from contracts.temperatures import WORDS, TemperatureChannel, decode_registers, modbus_address
from drivers.base import LinkError
from drivers.cancel import keep_cancel


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
