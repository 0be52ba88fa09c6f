"""The rumba Modbus TCP register map, as data: addresses, types, who writes, meaning, and the
word/byte order helpers. Shared by the daemon's client and the simulator's server; rendered as the
table in drivers/README.md.

All data are holding registers (function codes 3 read, 6/16 write), protocol addresses 0-based
(Modicon reference = address + 40001), relative to the link's ``base_address``.
Byte order: big-endian inside a register (Modbus standard). Word order for 32-bit values: high
word first ("ABCD", big-endian; mbpoll ``-B``). Positions are int32 fixed point: linear axes in
0.1 µm (10 000 counts/mm, range ±214 748 mm), rotary axes in µdeg (range ±2 147 deg) - exact
decimal values a CNC macro can produce with ROUND(), finer than float32 (0.06 µm at 1 m).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

MAP_ID = 0x5242  # "RB"
MAP_VERSION = 1
LINEAR_COUNTS_PER_MM = 10_000
ROTARY_COUNTS_PER_DEG = 1_000_000
RING_SLOTS = 16
SLOT_WORDS = 16
MBX_DATA_WORDS = 80  # 160 ASCII characters per block
ALARM_TEXT_WORDS = 32


@dataclass(frozen=True)
class Reg:
    name: str
    address: int
    words: int
    type: Literal["u16", "u32", "i32", "ascii"]
    writer: Literal["cnc", "daemon"]
    doc: str


STATE_CODES = {"idle": 0, "running": 1, "hold": 2, "alarm": 3, "done": 4}
COMMANDS = {"BEGIN": 1, "END": 2, "ABORT": 3}
ALARM_CODES = {0: "none", 1: "probe did not trigger", 2: "mailbox sequence error",
               3: "invalid mailbox payload", 9: "other (see ALARM_TEXT)"}

REGISTERS: tuple[Reg, ...] = (
    Reg("MAP_ID", 0, 1, "u16", "cnc", "0x5242 ('RB'): this is a rumba map"),
    Reg("MAP_VERSION", 1, 1, "u16", "cnc", "map version, 1"),
    Reg("HEARTBEAT", 2, 1, "u16", "cnc", "incremented by the CNC at least every 100 ms"),
    Reg("STATE", 3, 1, "u16", "cnc", "0 idle, 1 running, 2 hold, 3 alarm, 4 done"),
    Reg("ALARM_CODE", 4, 1, "u16", "cnc", "0 none, 1 probe miss, 2 mailbox sequence, "
        "3 bad payload, 9 other"),
    Reg("REQUEST", 5, 1, "u16", "cnc", "start-of-shift request: 1 until DONE is seen"),
    Reg("BUSY", 6, 1, "u16", "daemon", "1 while the daemon runs the verification"),
    Reg("DONE", 7, 1, "u16", "daemon", "1 when VERDICT is valid; 0 after REQUEST drops"),
    Reg("VERDICT", 8, 1, "u16", "daemon", "0 none, 1 PASS, 2 WARN, 3 FAIL, 4 ERROR"),
    Reg("COMMAND", 9, 1, "u16", "daemon", "1 BEGIN (reset mailbox + results), 2 END of "
        "stream, 3 ABORT; the CNC sets it back to 0 once executed"),
    Reg("RESULT_COUNTER", 10, 1, "u16", "cnc", "touches stored since BEGIN (wraps at 65536); "
        "touch n is in slot (n-1) mod 16"),
    Reg("RING_SLOTS", 11, 1, "u16", "cnc", "16"),
    Reg("MACHINE_TIME_MS", 12, 2, "u32", "cnc", "machine time of the program, ms"),
    Reg("MBX_READY", 14, 1, "u16", "daemon", "mailbox: daemon sets 1 last; CNC sets 0 when the "
        "block is taken"),
    Reg("MBX_SEQ", 15, 1, "u16", "daemon", "mailbox: block number 1, 2, … (65535 → 1)"),
    Reg("MBX_ACK", 16, 1, "u16", "cnc", "mailbox: number of the last block taken"),
    Reg("ALARM_TEXT", 20, ALARM_TEXT_WORDS, "ascii", "cnc", "alarm text, 64 chars, NUL padded"),
    Reg("MBX_LEN", 60, 1, "u16", "daemon", "mailbox: block length in characters (≤ 160)"),
    Reg("MBX_DATA", 61, MBX_DATA_WORDS, "ascii", "daemon", "mailbox: block text, 2 chars per "
        "register, first char in the high byte, no end-of-block character"),
    Reg("RESULT_RING", 200, RING_SLOTS * SLOT_WORDS, "u16", "cnc", "16 slots of 16 registers, "
        "slot k at 200 + 16 k (layout below)"),
)
BY_NAME = {r.name: r for r in REGISTERS}
MAP_WORDS = 200 + RING_SLOTS * SLOT_WORDS
STATUS_WORDS = 17  # one read of 0..16 gives state, handshake, counter and mailbox status

SLOT_LAYOUT: tuple[tuple[str, int, str, str], ...] = (
    ("SEQ", 0, "u32", "touch sequence number in the program (1-based)"),
    ("X", 2, "i32", "latched X, 0.1 µm"),
    ("Y", 4, "i32", "latched Y, 0.1 µm"),
    ("Z", 6, "i32", "latched Z, 0.1 µm"),
    ("B", 8, "i32", "first rotary axis (alphabetical), µdeg"),
    ("C", 10, "i32", "second rotary axis, µdeg"),
    ("FLAGS", 12, "u16", "bit 0: probe triggered"),
)


def addr(name: str) -> int:
    return BY_NAME[name].address


def slot_address(slot: int) -> int:
    return addr("RESULT_RING") + slot * SLOT_WORDS


def u32_words(value: int) -> list[int]:
    if not 0 <= value <= 0xFFFFFFFF:
        raise ValueError(f"{value} does not fit an unsigned 32-bit register pair")
    return [value >> 16, value & 0xFFFF]


def i32_words(value: int) -> list[int]:
    if not -(2**31) <= value < 2**31:
        raise ValueError(f"{value} does not fit a signed 32-bit register pair")
    return u32_words(value & 0xFFFFFFFF)


def words_u32(hi: int, lo: int) -> int:
    return (hi << 16) | lo


def words_i32(hi: int, lo: int) -> int:
    v = words_u32(hi, lo)
    return v - (1 << 32) if v >= 1 << 31 else v


def text_words(text: str, words: int) -> list[int]:
    """ASCII text, first character in the high byte, NUL padded to ``words`` registers."""
    data = text.encode("ascii")
    if len(data) > 2 * words:
        raise ValueError(f"text of {len(data)} characters exceeds {2 * words}")
    data = data.ljust(2 * words, b"\0")
    return [(data[i] << 8) | data[i + 1] for i in range(0, len(data), 2)]


def words_text(regs: list[int], length: int | None = None) -> str:
    data = b"".join(bytes([r >> 8, r & 0xFF]) for r in regs)
    data = data[:length] if length is not None else data.split(b"\0", 1)[0]
    return data.decode("ascii", "replace")


def encode_slot(seq: int, values: dict[str, float]) -> list[int]:
    """One result slot: SEQ, X, Y, Z (0.1 µm), B, C (µdeg), FLAGS, padding."""
    regs = u32_words(seq)
    for key in ("X", "Y", "Z"):
        regs += i32_words(round(values.get(key, 0.0) * LINEAR_COUNTS_PER_MM))
    for key in ("b", "c"):
        regs += i32_words(round(values.get(key, 0.0) * ROTARY_COUNTS_PER_DEG))
    regs.append(1 if values.get("triggered", 1.0) else 0)
    return regs + [0] * (SLOT_WORDS - len(regs))


def decode_slot(regs: list[int]) -> tuple[int, dict[str, float], bool]:
    seq = words_u32(regs[0], regs[1])
    axes = {k: words_i32(regs[o], regs[o + 1]) / LINEAR_COUNTS_PER_MM
            for k, o in (("X", 2), ("Y", 4), ("Z", 6))}
    axes.update({k: words_i32(regs[o], regs[o + 1]) / ROTARY_COUNTS_PER_DEG
                 for k, o in (("b", 8), ("c", 10))})
    return seq, axes, bool(regs[12] & 1)
