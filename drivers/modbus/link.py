"""Modbus TCP link (pymodbus client) for the rumba register map (contracts/modbus_map.py):
request/busy/done/verdict handshake, block streaming through the mailbox, results from the ring.

Modbus has no notifications, so the link polls one 17-register status block (state, handshake,
counter, mailbox); it re-polls at once after a write and backs off to ``poll_interval_s`` while
nothing changes. Every slot between the last seen counter and the current one is read, so no touch
is lost between polls (ring of 16).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from contracts.jobs import ProgramJob, Verdict
from contracts.messages import ProbeHit
from contracts.modbus_map import (
    ALARM_CODES,
    ALARM_TEXT_WORDS,
    COMMANDS,
    MAP_ID,
    MAP_VERSION,
    MBX_DATA_WORDS,
    RING_SLOTS,
    SLOT_WORDS,
    STATE_CODES,
    STATUS_WORDS,
    addr,
    decode_slot,
    slot_address,
    text_words,
    words_text,
)
from contracts.temperatures import TemperatureChannel
from drivers.base import (
    Capabilities,
    CncLink,
    LinkError,
    StartRequest,
)
from drivers.hits import HitFactory, MalformedResult
from drivers.modbus.registers import keep_cancel, read_channel
from drivers.modbus.schema import ModbusLinkConfig
from drivers.result_ring import Feed, ResultRingReader, RingPoll
from drivers.retry import Refused, with_backoff

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
STATE_NAMES = {v: k for k, v in STATE_CODES.items()}
FLAGS_OFFSET = 12
RESERVED_OFFSETS = range(13, SLOT_WORDS)
# Status registers whose value must lie in a documented set (drivers/README.md); anything else
# is a corrupted map, which would otherwise stall the stream until a timeout.
STATUS_VALUES: dict[str, frozenset[int]] = {
    "MAP_ID": frozenset({MAP_ID}),
    "MAP_VERSION": frozenset({MAP_VERSION}),
    "STATE": frozenset(STATE_CODES.values()),
    "ALARM_CODE": frozenset(ALARM_CODES),
    "REQUEST": frozenset({0, 1}),
    "BUSY": frozenset({0, 1}),
    "DONE": frozenset({0, 1}),
    "VERDICT": frozenset(range(5)),
    "COMMAND": frozenset({0, *COMMANDS.values()}),
    "RING_SLOTS": frozenset({RING_SLOTS}),
    "MBX_READY": frozenset({0, 1}),
}


def check_status(regs: list[int]) -> dict[str, int]:
    """The status block (registers 0..16) as named values; ``MalformedResult`` naming the
    register, its value and the allowed values when one holds something the map never does."""
    if len(regs) != STATUS_WORDS:
        raise MalformedResult(f"malformed status block: {len(regs)} registers, expected "
                              f"{STATUS_WORDS}")
    for name, allowed in STATUS_VALUES.items():
        value = regs[addr(name)]
        if value not in allowed:
            raise MalformedResult(f"malformed status block: {name} (register {addr(name)}) = "
                                  f"{value}, expected one of {sorted(allowed)}")
    return {"state": regs[addr("STATE")], "alarm": regs[addr("ALARM_CODE")],
            "request": regs[addr("REQUEST")], "done": regs[addr("DONE")],
            "command": regs[addr("COMMAND")], "counter": regs[addr("RESULT_COUNTER")],
            "ready": regs[addr("MBX_READY")], "ack": regs[addr("MBX_ACK")],
            "seq": regs[addr("MBX_SEQ")]}


def check_mailbox(st: dict[str, int], seq: int, prev_seq: int) -> None:
    """The mailbox registers against what this run wrote: MBX_SEQ is the last block sent and
    MBX_ACK that block or the one before (the CNC has not taken it yet)."""
    if seq and st["seq"] != seq:
        raise MalformedResult(f"malformed mailbox: MBX_SEQ (register {addr('MBX_SEQ')}) = "
                              f"{st['seq']}, expected {seq} (the last block sent)")
    if st["ack"] not in (prev_seq, seq):
        expected = f"{prev_seq} or {seq}" if seq else "0 (reset by BEGIN)"
        raise MalformedResult(f"malformed mailbox: MBX_ACK (register {addr('MBX_ACK')}) = "
                              f"{st['ack']}, expected {expected}")


def slot_hit(hits: HitFactory, regs: list[int], slot: int) -> ProbeHit:
    """Decode and validate one result slot: the next touch in program order, FLAGS 0 or 1,
    reserved registers 0, plausible positions; ``MalformedResult`` otherwise."""
    where = f"result slot {slot}, registers {slot_address(slot)}..+{SLOT_WORDS - 1}"
    if len(regs) != SLOT_WORDS or any(not 0 <= r <= 0xFFFF for r in regs):
        raise MalformedResult(f"malformed result ({where}): {regs!r} is not {SLOT_WORDS} "
                              "16-bit registers")
    flags = regs[FLAGS_OFFSET]
    if flags not in (0, 1):
        raise MalformedResult(f"malformed result ({where}): FLAGS (+{FLAGS_OFFSET}) = "
                              f"{flags:#06x}, expected 0 or 1 (bit 0 triggered, others reserved)")
    for off in RESERVED_OFFSETS:
        if regs[off]:
            raise MalformedResult(f"malformed result ({where}): reserved register +{off} = "
                                  f"{regs[off]:#06x}, expected 0")
    tseq, axes, triggered = decode_slot(regs)
    return hits.make(tseq, axes, triggered, f"slot={slot} regs={regs[:13]}", where=where)


def program_blocks(text: str) -> list[str]:
    """The blocks to stream: no ``%`` framing, no empty lines, each ≤ 160 ASCII characters."""
    blocks = []
    for n, line in enumerate(text.replace("\r\n", "\n").split("\n"), 1):
        block = line.strip()
        if not block or block == "%":
            continue
        if len(block) > 2 * MBX_DATA_WORDS or not block.isascii():
            raise LinkError(f"program line {n}: a mailbox block holds at most "
                            f"{2 * MBX_DATA_WORDS} ASCII characters")
        blocks.append(block)
    return blocks


class ModbusLink(ResultRingReader, CncLink):
    ring_slots = RING_SLOTS
    overrun_since = "the last poll"
    capabilities = Capabilities(start_request=True, streams_blocks=True, loads_program=False,
                                writes_verdict=True, can_abort=True)

    def __init__(self, cfg: ModbusLinkConfig) -> None:
        self.cfg = cfg
        self._client: AsyncModbusTcpClient | None = None
        self.blocks_sent = 0
        self._connected_once = False

    # ------------------------------------------------------------------ register I/O

    async def _connect_once(self) -> AsyncModbusTcpClient:
        client = AsyncModbusTcpClient(self.cfg.host, port=self.cfg.port, retries=1,
                                      timeout=self.cfg.request_timeout_s, reconnect_delay=0)
        if not await client.connect():
            client.close()
            raise await self._why_not()
        return client

    async def _why_not(self) -> LinkError:
        """pymodbus only says "not connected": one plain TCP attempt tells a refused port
        (nothing listens: fail fast at start-up) from a host that does not answer."""
        try:
            async with asyncio.timeout(self.cfg.request_timeout_s):
                _, writer = await asyncio.open_connection(self.cfg.host, self.cfg.port)
        except ConnectionRefusedError as e:
            return Refused(str(e))
        except (OSError, TimeoutError) as e:
            return LinkError(f"no connection: {str(e) or type(e).__name__}")
        writer.close()
        with contextlib.suppress(Exception):
            await writer.wait_closed()
        return LinkError("connection refused or timed out")

    async def connect(self) -> None:
        if self._client is not None:
            return
        # refused fails at once only before the first success (start-up, rumba verify)
        self._client = await with_backoff(
            self._connect_once, what=f"modbus {self.cfg.host}:{self.cfg.port}",
            timeout_s=self.cfg.connect_timeout_s, refused_is_final=not self._connected_once)
        self._connected_once = True
        head = await self._read(addr("MAP_ID"), 2)
        if head != [MAP_ID, MAP_VERSION]:
            await self.close()
            raise LinkError(f"modbus {self.cfg.host}:{self.cfg.port}: registers "
                            f"{self.cfg.base_address}..+1 hold {head}, expected the rumba map "
                            f"[{MAP_ID:#06x}, {MAP_VERSION}] (check base_address / device_id)")

    async def _reconnect(self) -> None:
        if self._client is not None:
            self._client.close()
        self._client = None
        self._client = await with_backoff(
            self._connect_once, what=f"modbus {self.cfg.host}:{self.cfg.port}",
            timeout_s=self.cfg.connect_timeout_s)

    async def _read(self, address: int, count: int) -> list[int]:
        if self._client is None:
            raise LinkError("modbus link not connected")
        try:
            rr = await keep_cancel(self._client.read_holding_registers(
                self.cfg.base_address + address, count=count, device_id=self.cfg.device_id))
        except (TimeoutError, ModbusException, OSError) as e:
            raise LinkError(f"modbus read {address}+{count}: {e}") from None
        if rr.isError():
            raise LinkError(f"modbus read {address}+{count}: exception response {rr}")
        return list(rr.registers)

    async def read_temperature(self, channel: TemperatureChannel) -> float:
        if self._client is None:
            raise LinkError("modbus link not connected")
        return await read_channel(self._client, channel, self.cfg.device_id,
                                  f"modbus {self.cfg.host}:{self.cfg.port}")

    async def _write(self, address: int, values: list[int]) -> None:
        if self._client is None:
            raise LinkError("modbus link not connected")
        try:
            rr = await keep_cancel(self._client.write_registers(
                self.cfg.base_address + address, values, device_id=self.cfg.device_id))
        except (TimeoutError, ModbusException, OSError) as e:
            raise LinkError(f"modbus write {address}: {e}") from None
        if rr.isError():
            raise LinkError(f"modbus write {address}: refused by the controller ({rr})")

    async def _status(self) -> dict[str, int]:
        return check_status(await self._read(0, STATUS_WORDS))

    async def _handshake(self) -> tuple[int, int]:
        """REQUEST and DONE only: waiting for a request does not judge the rest of the map
        (a run does, at its first poll), so a PLC still booting is simply waited for."""
        r = await self._read(addr("REQUEST"), 3)
        return r[0], r[2]

    # ------------------------------------------------------------------ handshake

    async def wait_start_request(self) -> StartRequest:
        while True:
            try:
                request, done = await self._handshake()
            except LinkError:
                await self._reconnect()  # controller restarted or cable pulled: back off, retry
                continue
            if done and not request:
                await self._write(addr("DONE"), [0])
                await self._write(addr("VERDICT"), [0])
                continue
            if request and not done:
                await self._write(addr("BUSY"), [1])
                return StartRequest(source="cnc", detail="REQUEST register = 1")
            await asyncio.sleep(max(self.cfg.poll_interval_s, 0.05))

    async def write_verdict(self, verdict: Verdict) -> None:
        await self._write(addr("VERDICT"), [verdict.code])  # verdict first, then DONE
        await self._write(addr("BUSY"), [0, 1])  # BUSY=0, DONE=1 (adjacent registers)

    # ------------------------------------------------------------------ program

    async def _command(self, name: str) -> None:
        await self._write(addr("COMMAND"), [COMMANDS[name]])
        deadline = time.monotonic() + self.cfg.block_timeout_s
        while (value := (await self._read(addr("COMMAND"), 1))[0]) != 0:
            if value not in COMMANDS.values():  # garbage would only end at the timeout
                raise MalformedResult(f"malformed status block: COMMAND (register "
                                      f"{addr('COMMAND')}) = {value} while waiting for "
                                      f"{name} to be executed, expected {COMMANDS[name]} or 0")
            if time.monotonic() > deadline:
                raise LinkError(f"controller did not execute command {name} within "
                                f"{self.cfg.block_timeout_s:g} s")
            await asyncio.sleep(0.001)

    async def _send_block(self, seq: int, block: str) -> None:
        data = text_words(block, (len(block) + 1) // 2) if block else []
        await self._write(addr("MBX_LEN"), [len(block), *data])  # payload (with its length)
        await self._write(addr("MBX_SEQ"), [seq])  # then the sequence number
        await self._write(addr("MBX_READY"), [1])  # then the ready flag, last

    async def _alarm_text(self, code: int) -> str:
        text = words_text(await self._read(addr("ALARM_TEXT"), ALARM_TEXT_WORDS))
        return text or ALARM_CODES.get(code, f"code {code}")

    async def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        try:
            async with contextlib.aclosing(self._run(job)) as agen:
                async for hit in agen:
                    yield hit
        except MalformedResult:
            # The connection works but the map holds garbage: stop the program (the CNC would
            # otherwise starve mid-stream) and fail with what was wrong.
            with contextlib.suppress(LinkError):
                await self.abort()
            raise

    async def _run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        self._blocks = program_blocks(job.text)
        self._hits = HitFactory(job)
        await self._command("BEGIN")
        self._last = 0
        self._next_block, self._seq, self._prev_seq, self._end_sent = 0, 0, 0, False
        self._poll_s = 0.0
        self.blocks_sent = 0
        async for hit in self._ring_results(job):
            yield hit

    # ------------------------------------------------------------------ the ring's reads

    async def _poll_ring(self, job: ProgramJob, got: int) -> RingPoll:
        st = await self._status()
        check_mailbox(st, self._seq, self._prev_seq)
        self._st = st
        new = (st["counter"] - self._last) & 0xFFFF
        if new and job.touch_count and got + new > job.touch_count:
            raise MalformedResult(
                f"malformed status block: RESULT_COUNTER (register "
                f"{addr('RESULT_COUNTER')}) = {st['counter']}, expected at most "
                f"{(self._last + job.touch_count - got) & 0xFFFF} (the program has "
                f"{job.touch_count} touches, {got} read)")
        return RingPoll(new, STATE_NAMES[st["state"]], st["alarm"])

    async def _read_results(self, new: int) -> AsyncIterator[ProbeHit]:
        first = self._last
        for n in range(first + 1, first + new + 1):
            slot = (n - 1) % RING_SLOTS
            hit = slot_hit(self._hits, await self._read(slot_address(slot), SLOT_WORDS), slot)
            self._last = n & 0xFFFF
            yield hit

    async def _alarm_message(self, poll: RingPoll) -> str:
        return f"controller alarm {poll.alarm}: {await self._alarm_text(int(poll.alarm))}"

    async def _feed(self, poll: RingPoll) -> Feed:
        """The next program block into the mailbox once the CNC took the last one, then END."""
        st = self._st
        if self._next_block < len(self._blocks):
            if st["ready"] == 0 and st["ack"] == self._seq:
                self._prev_seq, self._seq = self._seq, self._seq % 65535 + 1
                await self._send_block(self._seq, self._blocks[self._next_block])
                self._next_block += 1
                self.blocks_sent = self._next_block
                return Feed.SENT
            if time.monotonic() - self._progress_t > self.cfg.block_timeout_s:
                raise LinkError(f"controller did not take block {self._seq} within "
                                f"{self.cfg.block_timeout_s:g} s")
            return Feed.WAITING
        if not self._end_sent:
            await self._command("END")
            self._end_sent = True
            return Feed.AGAIN
        return Feed.DONE

    def _result_timeout_s(self) -> float:
        return self.cfg.result_timeout_s

    def _timeout_message(self, poll: RingPoll, got: int, job: ProgramJob) -> str:
        return f"no touch result for {self.cfg.result_timeout_s:g} s (state {poll.state})"

    async def _wait(self, progressed: bool) -> None:
        # Nothing changed: poll again soon, backing off to the configured interval.
        if progressed:
            self._poll_s = 0.0
        await asyncio.sleep(self._poll_s)
        self._poll_s = min(max(self._poll_s * 2, 0.0005), self.cfg.poll_interval_s)

    async def abort(self) -> None:
        if self._client is None or not self._client.connected:
            raise LinkError("modbus link not connected: the controller was not reset")
        await self._write(addr("COMMAND"), [COMMANDS["ABORT"]])

    async def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()
