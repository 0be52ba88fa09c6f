"""The OPC UA link's result ring, read back: the touch counter and state checked, one slot of
the result arrays decoded into a hit (contracts/opcua_space.py), anything malformed a
``MalformedResult`` naming the node and slot."""

from __future__ import annotations

import math
from typing import Any

from contracts.messages import ProbeHit
from contracts.opcua_space import BY_ROLE, RESULT_ROLES, RING_SLOTS, STATES
from drivers.hits import HitFactory, MalformedResult


def _number(value: Any, role: str, where: str, integer: bool) -> float:
    """``value`` as a finite number (an integer when ``integer``), else ``MalformedResult``."""
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if ok:
        try:
            ok = math.isfinite(value) and (not integer or float(value).is_integer())
        except OverflowError:  # an int too large for a float
            ok = False
    if not ok:
        kind = "an integer" if integer else "a finite number"
        raise MalformedResult(f"malformed result ({where}): {BY_ROLE[role].path} = "
                              f"{value!r}, expected {kind}")
    return value


def check_counter(counter: Any, state: Any, last: int, high: int | None) -> int:
    """The touch counter and state as read during a run; ``MalformedResult`` when the counter
    is not a whole number between the last one read and ``high`` (the counter after the
    program's last touch; None: unknown), or the state is not one of the address space's
    states (either would stall the run silently or crash it)."""
    where = "status"
    if state not in STATES:
        raise MalformedResult(f"malformed result ({where}): {BY_ROLE['state'].path} = "
                              f"{state!r}, expected one of {', '.join(STATES)}")
    n = int(_number(counter, "touch_counter", where, integer=True))
    if n < last or (high is not None and n > high):
        raise MalformedResult(f"malformed result ({where}): {BY_ROLE['touch_counter'].path} = "
                              f"{counter!r}, expected {last}..{'' if high is None else high} "
                              "(from the last one read to the program's last touch)")
    return n


def ring_hit(hits: HitFactory, rows: list[Any], n: int) -> ProbeHit:
    """Decode and validate result ``n`` from the ring arrays (``RESULT_ROLES`` order): arrays of
    ``RING_SLOTS`` elements, a whole seq (the next in program order), finite plausible
    positions, a trigger flag 0 or 1; ``MalformedResult`` otherwise."""
    slot = (n - 1) % RING_SLOTS
    where = f"ring slot {slot}, touch counter {n}"
    if len(rows) != len(RESULT_ROLES):
        raise MalformedResult(f"malformed result ({where}): {len(rows)} result arrays, "
                              f"expected {len(RESULT_ROLES)}")
    values = []
    for role, row in zip(RESULT_ROLES, rows, strict=True):
        if not isinstance(row, list | tuple) or len(row) != RING_SLOTS:
            size = len(row) if isinstance(row, list | tuple) else type(row).__name__
            raise MalformedResult(f"malformed result ({where}): {BY_ROLE[role].path} holds "
                                  f"{size}, expected an array of {RING_SLOTS}")
        integer = role in ("result_seq", "result_triggered")
        values.append(_number(row[slot], role, where, integer))
    seq, x, y, z, b, c, trig = values
    if trig not in (0, 1):
        raise MalformedResult(f"malformed result ({where}): {BY_ROLE['result_triggered'].path}"
                              f" = {trig!r}, expected 0 or 1")
    axes = {"X": float(x), "Y": float(y), "Z": float(z), "b": float(b), "c": float(c)}
    raw = (f"slot={slot} counter={n} seq={seq} X={x!r} Y={y!r} Z={z!r} b={b!r} c={c!r} "
           f"trig={trig}")
    return hits.make(int(seq), axes, bool(trig), raw, where=where)
