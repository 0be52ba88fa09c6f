"""Temperature channels of a machine: their config schema, a reading and the
run's summary (start, end, change, per pose) that the report, the HMI, the fleet and the judge use.

A channel is read from the controller over the run's own link (an OPC UA node, a Modbus register,
a LinuxCNC HAL pin, a macro variable the DNC program prints) or from a Modbus TCP/RTU temperature
transmitter of its own. Values are °C; Modbus registers carry a stated scale and offset
(°C = raw × scale + offset_c), e.g. a transmitter giving 0.1 °C per count: scale 0.1.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from contracts.dialects import dialect
from contracts.setup_types import safe_name
from contracts.yaml_files import StrictModel

MODBUS_ADDRESS = re.compile(r"^(input|holding):([0-9]{1,5})$")
OPCUA_ADDRESS = re.compile(r"^(ns=[0-9]{1,5};[isgb]=[^\x00-\x1f]{1,200}|/[^\x00-\x1f]{1,200})$")
HAL_PIN = re.compile(r"^[A-Za-z0-9_.-]{1,100}$")
# the macro variable a DNC program prints is the dialect's (contracts.dialects:
# DialectRecord.temperature_variable). LinuxCNC has no print to a serial line: its channels are
# HAL pins over the linuxcnc transport (check_address says so)
# what the program prints: RTEMP S|P<pose>|E <channel number> <°C> (gcode_templates/*/README.md);
# the value as each control formats it: Fanuc DPRNT [53] 3 decimals, Sinumerik a REAL rounded to
# 3 decimals in a string chain (no decimal point when whole), Heidenhain %.3LF
PRINTED_LINE = re.compile(
    r"^RTEMP +(S|E|P[0-9]{1,4}) +([0-9]{1,2}) +(-?[0-9]{1,5}(?:\.[0-9]{1,6})?)$", re.ASCII)
# a printed value outside this is a sensor fault code (an open Pt100 reads 850 °C or −200 °C on
# many transmitters, 3276.7 is int16's end at 0.1 °C), not a structure temperature
PRINTED_RANGE_C = (-60.0, 200.0)
WORDS = {"int16": 1, "uint16": 1, "int32": 2, "float32": 2}


class TransmitterFile(StrictModel):
    """A Modbus temperature transmitter of its own: TCP (``host``) or RTU (``serial`` port)."""

    host: str | None = None
    port: int = Field(502, ge=1, le=65535)
    serial: str | None = Field(None, pattern=r"^/[^\x00-\x1f ]{1,200}$")
    baudrate: int = Field(9600, ge=1200, le=115200)
    parity: Literal["N", "E", "O"] = "N"
    device_id: int = Field(1, ge=0, le=247)
    timeout_s: float = Field(1.0, gt=0, le=30)

    @model_validator(mode="after")
    def _one(self) -> TransmitterFile:
        if (self.host is None) == (self.serial is None):
            raise ValueError("give exactly one of 'host' (Modbus TCP) or 'serial' (Modbus RTU)")
        return self

    def describe(self) -> str:
        return (f"modbus-tcp {self.host}:{self.port} unit {self.device_id}" if self.host
                else f"modbus-rtu {self.serial} {self.baudrate} 8{self.parity}1 unit "
                     f"{self.device_id}")


class TemperatureChannel(StrictModel):
    """One temperature channel (machines.N.temperatures in daemon.yaml)."""

    name: str
    unit: Literal["°C", "degC"] = "°C"
    source: Literal["controller", "transmitter"] = "controller"
    # OPC UA node id (ns=2;s=… or a /path in the link's namespace), Modbus input:N/holding:N,
    # a HAL pin, or the macro variable the DNC program prints (#5021, R21, Q1600, #<_t_spindle>)
    address: str = Field(min_length=1, max_length=200)
    transmitter: TransmitterFile | None = None
    format: Literal["int16", "uint16", "int32", "float32"] = "int16"  # Modbus registers
    scale: float = 1.0  # Modbus: °C per count
    offset_c: float = 0.0
    _n = field_validator("name")(safe_name)

    @model_validator(mode="after")
    def _source(self) -> TemperatureChannel:
        if (self.source == "transmitter") != (self.transmitter is not None):
            raise ValueError("source: transmitter needs a 'transmitter' section (and only it)")
        if self.source == "transmitter":
            modbus_address(self.address)
        if self.scale == 0:
            raise ValueError("scale must not be 0")
        return self

    def describe(self, link: str) -> str:
        """Where the value comes from, for the audit record."""
        if self.transmitter is not None:
            return f"{self.name}: {self.transmitter.describe()} {self.address}"
        return f"{self.name}: {link} {self.address}"


def modbus_address(address: str) -> tuple[str, int]:
    """``input:30`` → ("input", 30); ValueError naming the expected form."""
    m = MODBUS_ADDRESS.fullmatch(address)
    if not m or int(m.group(2)) > 65535:
        raise ValueError(f"address {address!r}: a Modbus register is input:N or holding:N "
                         "(protocol address, 0-65535)")
    return m.group(1), int(m.group(2))


def check_address(ch: TemperatureChannel, transport: str, dialect_name: str) -> None:
    """A controller channel's address must suit the run's transport and dialect (ValueError
    otherwise)."""
    if ch.source == "transmitter":
        return
    if transport in ("opcua", "sinumerik"):  # sinumerik: an R parameter's node, a GUD's …
        ok, form = OPCUA_ADDRESS.fullmatch(ch.address), "an OPC UA node id (ns=2;s=…) or /path"
    elif transport == "modbus":
        modbus_address(ch.address)
        return
    elif transport == "linuxcnc":
        ok, form = HAL_PIN.fullmatch(ch.address), "a HAL pin name"
    elif transport == "haas":  # a macro variable read over the data port (?Q600)
        rec = dialect("haas")
        ok, form = rec.prints_temperature(ch.address), rec.temperature_form
    elif transport == "serial":
        rec = dialect(dialect_name)
        if rec.temperature_variable is None:
            raise ValueError(rec.temperature_refusal or f"the {rec.family} programs print no "
                             "temperature over DNC; use source: transmitter")
        ok, form = rec.prints_temperature(ch.address), rec.temperature_form
    else:
        raise ValueError(f"the {transport} link cannot read temperatures; use source: "
                         "transmitter")
    if not ok:
        raise ValueError(f"address {ch.address!r} is not {form}")


def parse_printed(line: str) -> tuple[int, str, float]:
    """An ``RTEMP`` line → (channel number, marker S/E/P<pose>, °C); ValueError when broken."""
    m = PRINTED_LINE.fullmatch(line.strip(" \t\r\n"))
    if not m:
        raise ValueError(f"temperature line {line.strip()[:60]!r} does not match "
                         "'RTEMP S|E|P<pose> <channel> <value>'")
    k, value = int(m.group(2)), float(m.group(3))
    lo, hi = PRINTED_RANGE_C
    if k == 0:
        raise ValueError(f"temperature line {line.strip()[:60]!r}: channel 0 (they count "
                         "from 1)")
    if not lo <= value <= hi:
        raise ValueError(f"temperature line {line.strip()[:60]!r}: {m.group(3)} °C is outside "
                         f"{lo:g}…{hi:g} °C (a sensor fault code, not a temperature)")
    return k, m.group(1), value


def decode_registers(regs: list[int], ch: TemperatureChannel) -> float:
    """°C from the registers of a channel (high word first for 32-bit values)."""
    raw: float
    if ch.format == "uint16":
        raw = regs[0]
    elif ch.format == "int16":
        raw = regs[0] - 0x10000 if regs[0] >= 0x8000 else regs[0]
    else:
        data = struct.pack(">HH", regs[0], regs[1])
        raw = struct.unpack(">i" if ch.format == "int32" else ">f", data)[0]
    return raw * ch.scale + ch.offset_c


@dataclass(frozen=True)
class TemperatureReading:
    """One channel read at one instant of a run (``value_c`` None: not read, ``error`` why)."""

    channel: str
    at: Literal["start", "pose", "end"]
    pose: int | None  # the plan pose being probed (at == "pose")
    t_s: float  # on the touches' clock (contracts.jobs.RunClock): 0 before the first program
    value_c: float | None
    error: str = ""
    # the program it came from: 0 the plan's, k the k-th re-probe round's (daemon/run/reprobe.py),
    # which prints a start and an end line of its own and probes again a pose of the plan
    reprobe_round: int = 0


def _where(r: TemperatureReading, start: TemperatureReading | None,
           end: TemperatureReading | None) -> str:
    """Where a reading was taken, as the summary names it: the run's own start and end plain,
    a re-probe round's pose, start or end with its round."""
    if r is start or r is end:
        return r.at
    k = r.reprobe_round
    if r.at == "pose":
        return f"pose {r.pose}" + (f" of re-probe {k}" if k else "")
    return f"{r.at} of " + (f"re-probe {k}" if k else "the plan's program")


def run_ends(mine: Sequence[TemperatureReading]
             ) -> tuple[TemperatureReading | None, TemperatureReading | None]:
    """A channel's start and end reading of the run (``mine`` in journal order): the start the
    plan's program began with (the first read, else its row saying why not) — never a re-probe
    round's — and the end of the last program that ran (the highest round's end, read or
    not: a re-probe's end line that never came leaves the run's end unread rather than the
    plan program's end standing in for it). The fleet store's query picks the same
    (daemon/store/pg_temperatures.readings)."""
    starts = [r for r in mine if r.at == "start" and r.reprobe_round == 0]
    start = next((r for r in starts if r.value_c is not None), starts[0] if starts else None)
    ends = [(r.reprobe_round, i, r) for i, r in enumerate(mine) if r.at == "end"]
    return start, max(ends, key=lambda e: e[:2])[2] if ends else None


def run_mean_c(pose_c: Sequence[float | None], start_c: float | None,
               end_c: float | None) -> float | None:
    """A run's temperature on one channel, the one definition the report, the CLI, the HMI and
    the fleet page use: the mean of the values read at the poses — the
    instants the geometry was measured — else of the start and end values that were read. A
    reading that is missing (or not a finite number: a store written by hand) is left out,
    never stood in for by another one."""
    def read(vs: Sequence[float | None]) -> list[float]:
        return [float(v) for v in vs if v is not None and math.isfinite(v)]

    values = read(pose_c) or read((start_c, end_c))
    return sum(values) / len(values) if values else None


def summarise(readings: list[TemperatureReading], sources: dict[str, str]) -> dict[str, Any]:
    """Per channel: start, end, the first and last values read (and where), the change between
    them, mean, min, max, per-pose values, errors, source (the analysis JSON's
    ``temperatures``; the report, HMI, fleet and judge read it). ``start_c`` / ``end_c`` are the
    readings at the run's start and end (``run_ends``), None where not read; ``change_c`` spans
    ``change_over`` ("start → end", or e.g. "pose 0 → end" when the start was not read), None
    below two readings: one value is no change. A pose probed again by a re-probe round is in
    ``per_pose`` a second time, with its round."""
    out: dict[str, Any] = {}
    for name, source in sources.items():
        mine = [r for r in readings if r.channel == name]
        ok = [r for r in mine if r.value_c is not None]
        start_r, end_r = run_ends(mine)
        start = start_r.value_c if start_r is not None else None
        end = end_r.value_c if end_r is not None else None
        first, last = (ok[0], ok[-1]) if ok else (None, None)
        two = first is not None and last is not None and first is not last
        values = [float(r.value_c) for r in ok]  # type: ignore[arg-type]
        poses = [r for r in ok if r.at == "pose"]
        at_first = _where(first, start_r, end_r) if first else None
        at_last = _where(last, start_r, end_r) if last else None
        out[name] = {
            "source": source, "start_c": start, "end_c": end,
            "first_c": first.value_c if first else None,
            "first_at": at_first,
            "last_c": last.value_c if last else None,
            "last_at": at_last,
            "change_c": (last.value_c - first.value_c) if two else None,  # type: ignore
            "change_over": f"{at_first} → {at_last}" if two else None,
            "mean_c": run_mean_c([r.value_c for r in poses], start, end),
            "min_c": min(values) if values else None, "max_c": max(values) if values else None,
            "per_pose": [{"pose": r.pose, "t_s": round(r.t_s, 3), "value_c": r.value_c,
                          "reprobe_round": r.reprobe_round} for r in poses],
            "readings": len(mine), "unread": len(mine) - len(ok),
            "errors": sorted({r.error for r in mine if r.error})[:5]}
    return out


def _c(v: Any) -> str:
    return f"{v:.1f}"


def _finite(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def channel_text(name: str, t: Any) -> str:
    """One channel of a run's summary as every view prints it (the report's audit row and PDF
    line, the HMI card, the fleet page): "spindle 20.5 → 24.1 °C (+3.6 °C)"; without a start
    reading the span says where it began ("spindle 21.0 (pose 0) → 24.1 °C (+3.1 °C; start
    not read)"), one value is no change ("spindle 24.1 °C (end only; start not read)"), none
    says why. A summary written by another version or by hand costs the cell, never the page."""
    if not isinstance(t, Mapping):
        return f"{name} not read"
    start, end = _finite(t.get("start_c")), _finite(t.get("end_c"))
    new = "first_c" in t  # older summaries put the first reading in start_c
    first = _finite(t.get("first_c")) if new else start
    last = _finite(t.get("last_c")) if new else end
    if first is None or last is None:
        errors = t.get("errors")
        why = "; ".join(str(e) for e in errors) if isinstance(errors, list) and errors else ""
        return f"{name} not read" + (f" ({why})" if why else "")
    change = _finite(t.get("change_c"))
    if not new or (start is not None and end is not None):
        return (f"{name} {_c(first)} → {_c(last)} °C"
                + (f" ({change:+.1f} °C)" if change is not None else ""))
    gap = "start not read" if start is None else "end not read"
    if change is None:
        return f"{name} {_c(first)} °C ({t.get('first_at')} only; {gap})"
    return (f"{name} {_c(first)} ({t.get('first_at')}) → {_c(last)} °C ({t.get('last_at')}) "
            f"({change:+.1f} °C; {gap})")
