"""The moves of a tool path: a builder that appends them, and the small helpers the path uses."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from programs.model import Move, Program


class MoveBuilder:
    """Appends moves to a program from the last position, leaving out a move that moves
    nothing (a linear axis within 1e-12 mm of where it is)."""

    def __init__(self, prog: Program, start: tuple[float, ...]) -> None:
        self.p = prog
        self.pos = list(start)
        self.block = 0

    def emit(self, kind: str, target: Sequence[float | None], **kw: object) -> None:
        new = [self.pos[i] if v is None else float(v) for i, v in enumerate(target)]
        letters = self.p.axis_letters
        words = tuple(letters[i] for i in range(5)
                      if target[i] is not None and (kind in ("probe", "feed") or i >= 3
                                                    or not abs(new[i] - self.pos[i]) <= 1e-12))
        if not words and kind not in ("dwell",):
            return
        self.block += 1
        self.pos = new
        self.p.moves.append(Move(self.block, kind, tuple(new), words, **kw))  # type: ignore[arg-type]


def seg_length(seg: tuple[np.ndarray, np.ndarray], known: dict[int, float]) -> float:
    """|seg|, computed once per segment object (``known``: by its id, the segments alive)."""
    if id(seg) not in known:
        known[id(seg)] = float(np.linalg.norm(seg[1] - seg[0]))
    return known[id(seg)]


def axes_only(values: Mapping[int, float]) -> list[float | None]:
    """A five-axis target that moves only the given axes (index → value)."""
    out: list[float | None] = [None] * 5
    for i, v in values.items():
        out[i] = float(v)
    return out


def t3(v: np.ndarray) -> tuple[float, float, float]:
    """A 3-vector as a tuple of Python floats."""
    return (float(v[0]), float(v[1]), float(v[2]))
