"""Switchable faults of the simulated controller, by block number, machine time or touch number.

Machine-side faults are applied by the controller itself (no trigger = ball removed, early
trigger, a chip on a ball, dropped result line, alarm, feed hold, restart); transport faults
(disconnect, late or missing XON, garbled bytes) are raised as flags and events that the protocol
front-ends act on.

A ``chip`` (a swarf chip, a coolant drop or dirt stuck where one touch meets the ball) makes the
probe switch ``size_um`` before the ball surface along the approach: that touch latches
``size_um`` outside the sphere. It fires on the touch ``at_touch`` names (once per fault plan:
a re-probe program numbers its touches from 1 again and must not meet it by number). With
``persist: false`` (default) it is gone afterwards — blown off by the next approach, as a drop
or a loose chip is — so a re-probe of that ball is clean; with ``persist: true`` it stays on
the ball at that spot and every later touch of the same ball, touch direction and indexation
meets it again (a chip stuck fast, a burr, a dent).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator

from contracts.yaml_files import StrictModel, read_yaml, validate_file

FaultKind = Literal[
    "disconnect", "late_xon", "missing_xon", "garbled",  # front-end (transport) faults
    "drop_result_line", "no_trigger", "early_trigger", "chip", "alarm", "feed_hold", "restart",
]
FRONT_END_KINDS = frozenset({"disconnect", "late_xon", "missing_xon", "garbled"})


class Fault(StrictModel):
    """One fault. Exactly one of ``at_block`` (1-based program line), ``at_time_s`` (machine
    time since program start) or ``at_touch`` (touch sequence number) says when it fires;
    ``count`` how many consecutive touches / lines / blocks it affects."""


    kind: FaultKind
    at_block: int | None = Field(None, ge=1)
    at_time_s: float | None = Field(None, ge=0)
    at_touch: int | None = Field(None, ge=1)
    count: int = Field(1, ge=1)
    duration_s: float = Field(0.0, ge=0, le=3600)  # feed hold / late XON / disconnect length
    fraction: float = Field(0.5, gt=0, lt=1)  # early trigger: where along the probing move
    size_um: float = Field(20.0, gt=0, le=5000)  # chip: how far outside the ball it switches
    persist: bool = False  # chip: stays on the ball (every later touch of that spot meets it)
    message: str = "simulated fault"
    params: dict[str, Any] = {}

    @model_validator(mode="after")
    def _one_when(self) -> Fault:
        n = sum(x is not None for x in (self.at_block, self.at_time_s, self.at_touch))
        if n != 1:
            raise ValueError("give exactly one of at_block, at_time_s, at_touch")
        if self.kind == "chip" and self.at_block is not None:
            raise ValueError("a chip sits on a touch: give at_touch or at_time_s, not at_block")
        return self


class FaultsFile(StrictModel):
    faults: list[Fault] = []


@dataclass
class FaultPlan:
    """The faults of one session; each fires once (``count`` touches/blocks from its start)."""

    faults: list[Fault] = field(default_factory=list)
    fired: list[tuple[Fault, str]] = field(default_factory=list)  # (fault, where) for reports
    stuck: list[tuple[Fault, int, int, float, float]] = field(default_factory=list)
    # persistent chips: (fault, ball index, touch number, b, c rounded to 1e-6 deg)
    _used: set[int] = field(default_factory=set)
    _chips_used: set[tuple[int, int]] = field(default_factory=set)  # (fault index, touch)

    @classmethod
    def load(cls, path: Path | str) -> FaultPlan:
        data = read_yaml(path)  # the schemas' one reader: size, UTF-8, depth ceilings
        return cls(list(validate_file(FaultsFile, path, data).faults))

    def reset(self) -> None:
        self.fired.clear()
        self.stuck.clear()
        self._used.clear()
        self._chips_used.clear()

    def _hit(self, f: Fault, block: int | None, t_s: float | None, touch: int | None) -> bool:
        if f.at_block is not None and block is not None:
            return f.at_block <= block < f.at_block + f.count
        if f.at_touch is not None and touch is not None:
            return f.at_touch <= touch < f.at_touch + f.count
        if f.at_time_s is not None and t_s is not None:
            return t_s >= f.at_time_s
        return False

    def due(self, kinds: set[str] | frozenset[str], *, block: int | None = None,
            t_s: float | None = None, touch: int | None = None) -> list[Fault]:
        """Faults of ``kinds`` that fire at this block / time / touch (time faults fire once,
        except ``no_trigger``: a removed ball stays removed; block and touch faults on each of
        their ``count`` blocks or touches)."""
        out = []
        for i, f in enumerate(self.faults):
            if f.kind not in kinds or not self._hit(f, block, t_s, touch):
                continue
            if f.at_time_s is not None and f.kind != "no_trigger":  # a removed ball stays away
                if i in self._used:
                    continue
                self._used.add(i)
            if f.kind == "chip" and f.at_touch is not None:  # once, not again by number
                if (i, touch) in self._chips_used:
                    continue
                self._chips_used.add((i, touch))  # type: ignore[arg-type]
            where = (f"block {block}" if f.at_block is not None else
                     f"touch {touch}" if f.at_touch is not None else f"t={t_s:.1f}s")
            self.fired.append((f, where))
            out.append(f)
        return out

    def chip_mm(self, due: list[Fault], ball: int, touch: int, b_deg: float, c_deg: float,
                seq: int) -> float:
        """How far (mm) outside the ball this touch switches: the chips ``due`` now (a
        persistent one is remembered at this ball, touch direction and indexation) plus those
        stuck there earlier."""
        spot = (ball, touch, round(b_deg, 6), round(c_deg, 6))
        size = 0.0
        for f in due:
            if f.kind != "chip":
                continue
            size += f.size_um
            if f.persist:
                self.stuck.append((f, *spot))
        for f, *where in self.stuck:
            if tuple(where) == spot and all(f is not g for g in due):
                size += f.size_um
                self.fired.append((f, f"touch {seq} (stuck chip)"))
        return size * 1e-3
