"""Results a program leaves in the controller's own variables (gcode_templates/README.md "Result
slots": a counter and a ring of ``RING_SLOTS`` slots of ``RESULT_FIELDS``), read by a link that
reads the controller's variables — R parameters on a SINUMERIK OPC UA server, macro variables on
a Haas data port — and checked before anything is journaled.

Per touch the program writes its slot, then the counter = seq, then waits before the next probing
move while counter − ack = ``RING_SLOTS`` (ack: the link's, ``HANDSHAKE_VARIABLES``). A link reads
every slot from the last counter read up to the counter, writes ack, and never trusts a value it
has not checked: the counter must be a whole number between the last one read and the program's
last touch, a slot's seq the next touch, its rep / pose / touch those of the program's touch
table, the trigger flag 0 or 1, every position finite and plausible (``drivers.hits``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from contracts.messages import ProbeHit
from contracts.result_lines import RESULT_FIELDS, RING_SLOTS, SLOT_FIELDS
from drivers.hits import HitFactory, MalformedResult


def slot_numbers(base: int, n: int) -> list[int]:
    """The variable numbers of touch ``n``'s slot (``base``: the ring's first variable)."""
    first = base + SLOT_FIELDS * ((n - 1) % RING_SLOTS)
    return list(range(first, first + SLOT_FIELDS))


def number(value: Any, name: str, where: str, integer: bool = False) -> float:
    """``value`` as a finite number (whole when ``integer``), else ``MalformedResult`` naming
    the variable (a bool, a string, NaN, an int beyond a float are never a result)."""
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if ok:
        try:
            ok = math.isfinite(value) and (not integer or float(value).is_integer())
        except OverflowError:
            ok = False
    if not ok:
        kind = "a whole number" if integer else "a finite number"
        raise MalformedResult(f"malformed result ({where}): {name} = {value!r}, expected {kind}")
    return float(value)


def check_counter(value: Any, name: str, last: int, high: int | None) -> int:
    """The counter as read during a run: a whole number from ``last`` (the last one read) to
    ``high`` (the program's last touch; None: unknown), else ``MalformedResult``."""
    n = int(number(value, name, "counter", integer=True))
    if n < last or (high is not None and n > high):
        raise MalformedResult(f"malformed result (counter): {name} = {value!r}, expected "
                              f"{last}..{'' if high is None else high} (from the last one read "
                              "to the program's last touch)")
    return n


def decode(hits: HitFactory, values: Sequence[Any], names: Sequence[str], n: int,
           where: str) -> ProbeHit:
    """Touch ``n``'s hit from its slot's ``values`` (``RESULT_FIELDS`` order; ``names``: the
    variables they were read from, for the messages); ``MalformedResult`` when anything is
    off."""
    if len(values) != SLOT_FIELDS or len(names) != SLOT_FIELDS:
        raise MalformedResult(f"malformed result ({where}): {len(values)} values, expected "
                              f"{SLOT_FIELDS}")
    whole = {"seq", "rep", "pose", "ball", "touch", "trig"}
    v = {f: number(x, name, where, integer=f in whole)
         for f, x, name in zip(RESULT_FIELDS, values, names, strict=True)}
    if v["trig"] not in (0.0, 1.0):
        raise MalformedResult(f"malformed result ({where}): {names[5]} = {values[5]!r}, "
                              "expected 0 or 1 (trigger flag)")
    info = hits.job.touches.get(int(v["seq"]))
    if info is not None:
        t = info.id
        for field, want in (("rep", t.repeat), ("pose", t.pose), ("touch", t.touch)):
            if int(v[field]) != want:
                i = RESULT_FIELDS.index(field)
                raise MalformedResult(f"malformed result ({where}): {names[i]} = {values[i]!r}"
                                      f", the program's touch seq {t.seq} has {field} {want}")
    axes = {"X": v["x"], "Y": v["y"], "Z": v["z"], "b": v["r1"], "c": v["r2"]}
    raw = f"{where}: " + " ".join(f"{f}={values[i]!r}" for i, f in enumerate(RESULT_FIELDS))
    return hits.make(int(v["seq"]), axes, v["trig"] == 1.0, raw, where=where)
