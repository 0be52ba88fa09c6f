"""Controller side of Modbus TCP: a pymodbus server holding the rumba register map
(contracts/modbus_map.py) for one VirtualController: handshake, command register, block mailbox
(payload, then sequence, then ready; acknowledged by the controller) and the result ring.

The map lives in ``self.regs``; pymodbus's access hook copies it into every read and checks every
write (a write to a CNC-owned register is refused with exception 02, illegal data address).
"""

from __future__ import annotations

import asyncio
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from contracts.modbus_map import (
    ALARM_TEXT_WORDS,
    COMMANDS,
    MAP_ID,
    MAP_VERSION,
    MAP_WORDS,
    MBX_DATA_WORDS,
    REGISTERS,
    RING_SLOTS,
    SLOT_WORDS,
    STATE_CODES,
    addr,
    encode_slot,
    slot_address,
    text_words,
    u32_words,
    words_text,
)
from simulators import thermal
from simulators.frontends import cancel_tasks
from simulators.frontends.lookahead import Lookahead

WRITABLE = frozenset(a for r in REGISTERS if r.writer == "daemon"
                     for a in range(r.address, r.address + r.words))
HANDSHAKE = {"REQUEST": "request", "BUSY": "busy", "DONE": "done", "VERDICT": "verdict"}


class ModbusFrontend:
    """``await start()`` returns the bound TCP port (loopback, port 0 = a free one)."""

    def __init__(self, controller: Any, *, device_id: int = 1, lookahead_blocks: int = 8
                 ) -> None:
        self.ctrl = controller
        self._look = Lookahead(controller, lookahead_blocks)
        self.device_id = device_id
        self.regs = [0] * MAP_WORDS
        self.regs[addr("MAP_ID")] = MAP_ID
        self.regs[addr("MAP_VERSION")] = MAP_VERSION
        self.regs[addr("RING_SLOTS")] = RING_SLOTS
        self.alarms: list[str] = []
        self.blocks_taken = 0
        self._counter = 0
        self._mirror = {k: 0 for k in HANDSHAKE}
        self._mailbox = asyncio.Event()
        self._command = asyncio.Event()
        self._server: ModbusTcpServer | None = None
        self._tasks: list[asyncio.Task] = []

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        device = SimDevice(id=self.device_id, action=self._access, simdata=[
            SimData(0, count=MAP_WORDS, values=0, datatype=DataType.REGISTERS)])
        self._server = ModbusTcpServer(device, address=(host, port))
        try:
            await self._server.serve_forever(background=True)
        except RuntimeError:  # pymodbus logs the bind error and raises a generic one
            self._server = None
            raise OSError(f"cannot listen on {host}:{port} (address in use or not "
                          f"available)") from None
        self._tasks = [asyncio.create_task(c) for c in
                       (self._events(), self._sync(), self._mailbox_loop(), self._command_loop())]
        return self._server.transport.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        await cancel_tasks(self._tasks)
        if self._server is not None:
            await self._server.shutdown()
            self._server = None

    # ------------------------------------------------------------------ register access hook

    async def _access(self, fc: int, start: int, address: int, count: int,
                      registers: list[int], values: list[int] | None) -> ExcCodes | None:
        if values is None:
            registers[address - start:address - start + count] = self.regs[address:address + count]
            return None
        if any(a not in WRITABLE for a in range(address, address + len(values))):
            return ExcCodes.ILLEGAL_ADDRESS
        self.regs[address:address + len(values)] = [int(v) & 0xFFFF for v in values]
        touched = range(address, address + len(values))
        if addr("MBX_READY") in touched and self.regs[addr("MBX_READY")] == 1:
            self._mailbox.set()
        if addr("COMMAND") in touched and self.regs[addr("COMMAND")]:
            self._command.set()
        return None

    # ------------------------------------------------------------------ daemon → controller

    async def _mailbox_loop(self) -> None:
        ready, seq_a, ack_a = addr("MBX_READY"), addr("MBX_SEQ"), addr("MBX_ACK")
        while True:
            await self._mailbox.wait()
            self._mailbox.clear()
            if self.regs[ready] != 1:
                continue
            seq, ack = self.regs[seq_a], self.regs[ack_a]
            expected = ack % 65535 + 1
            if seq != expected:
                await self._alarm(2, f"mailbox sequence error: block {seq}, expected {expected}")
                continue
            length = self.regs[addr("MBX_LEN")]
            if length > 2 * MBX_DATA_WORDS:
                await self._alarm(3, f"mailbox block {seq}: length {length} > "
                                     f"{2 * MBX_DATA_WORDS}")
                continue
            data_a = addr("MBX_DATA")
            text = words_text(self.regs[data_a:data_a + MBX_DATA_WORDS], length)
            await self._look.feed(text)
            self.blocks_taken += 1
            self.regs[ack_a] = seq
            self.regs[ready] = 0  # taken: the daemon may write the next block

    async def _command_loop(self) -> None:
        cmd_a = addr("COMMAND")
        while True:
            await self._command.wait()
            self._command.clear()
            cmd = self.regs[cmd_a]
            if cmd == COMMANDS["BEGIN"]:
                if self.ctrl.state in ("running", "hold"):
                    await self.ctrl.abort()  # a new stream resets a starved, unfinished one
                self._reset_stream()
            elif cmd == COMMANDS["END"]:
                await self.ctrl.end_of_stream()
            elif cmd == COMMANDS["ABORT"]:
                await self.ctrl.abort()
            self.regs[cmd_a] = 0  # executed

    def _reset_stream(self) -> None:
        self._look.reset()
        self._counter = 0
        self.regs[addr("RESULT_COUNTER")] = 0
        self.regs[addr("MBX_ACK")] = 0
        self.regs[addr("MBX_READY")] = 0
        ring = addr("RESULT_RING")
        self.regs[ring:ring + RING_SLOTS * SLOT_WORDS] = [0] * (RING_SLOTS * SLOT_WORDS)
        self._set_state("idle", None)

    # ------------------------------------------------------------------ controller → registers

    def _set_state(self, state: str, alarm: str | None) -> None:
        self.regs[addr("STATE")] = STATE_CODES.get(state, STATE_CODES["alarm"])
        if state != "alarm":
            self.regs[addr("ALARM_CODE")] = 0
            self._alarm_text("")

    def _alarm_text(self, text: str) -> None:
        a = addr("ALARM_TEXT")
        clipped = text.encode("ascii", "replace")[:2 * ALARM_TEXT_WORDS].decode("ascii")
        self.regs[a:a + ALARM_TEXT_WORDS] = text_words(clipped, ALARM_TEXT_WORDS)

    async def _alarm(self, code: int, text: str) -> None:
        self.alarms.append(text)
        raise_alarm = getattr(self.ctrl, "raise_alarm", None)
        if callable(raise_alarm):
            raise_alarm(text)
        else:
            await self.ctrl.abort()
        self.regs[addr("STATE")] = STATE_CODES["alarm"]
        self.regs[addr("ALARM_CODE")] = code
        self._alarm_text(text)

    async def _events(self) -> None:
        async for ev in self._look.events():
            kind = type(ev).__name__
            if kind == "FaultEvent" and ev.kind == "disconnect" and self._server is not None:
                for conn in list(self._server.active_connections.values()):
                    conn.close()  # the cable is pulled: clients must reconnect
            if kind == "TouchResult":
                self._counter += 1
                slot = (self._counter - 1) % RING_SLOTS
                a = slot_address(slot)
                try:
                    values = dict(ev.values)
                    values["triggered"] = float(getattr(ev, "triggered",
                                                        values.get("triggered", 1.0)))
                    self.regs[a:a + SLOT_WORDS] = encode_slot(int(ev.seq), values)
                except ValueError as e:
                    await self._alarm(9, f"result out of register range: {e}")
                    continue
                self.regs[addr("RESULT_COUNTER")] = self._counter & 0xFFFF  # counter last
            elif kind == "StateChange":
                if ev.state == "alarm":
                    text = ev.alarm or "alarm"
                    code = 1 if "trigger" in text.lower() else 9
                    self.regs[addr("ALARM_CODE")] = code
                    self._alarm_text(text)
                    self.regs[addr("STATE")] = STATE_CODES["alarm"]
                else:
                    self._set_state(ev.state, None)

    async def _sync(self) -> None:
        """Heartbeat, machine time, and the handshake mirrored both ways (a write wins)."""
        hb = addr("HEARTBEAT")
        while True:
            self.regs[hb] = (self.regs[hb] + 1) & 0xFFFF
            ms = min(int(float(getattr(self.ctrl, "machine_time_s", 0.0)) * 1000), 0xFFFFFFFF)
            mt = addr("MACHINE_TIME_MS")
            self.regs[mt:mt + 2] = u32_words(ms)
            for axis, value in self.ctrl.sensor_temperatures().items():
                self.regs[thermal.MODBUS_ADDRESS[axis]] = thermal.counts(value,
                                                                         thermal.MODBUS_SCALE_C)
            for name, attr in HANDSHAKE.items():
                reg = self.regs[addr(name)]
                mine = int(getattr(self.ctrl, attr))
                if reg != self._mirror[name]:
                    setattr(self.ctrl, attr, reg if attr == "verdict" else bool(reg))
                    self._mirror[name] = reg
                elif mine != self._mirror[name]:
                    self.regs[addr(name)] = mine
                    self._mirror[name] = mine
            await asyncio.sleep(0.02)
