"""The one touch table of a program: what identifies a touch (seq → pose, ball, touch, repeat)
and what the program says about it (commanded pose, approach, feed). Links, the session and the
dialect parsers name and complete every hit here, and nowhere else."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from typing import Any

from contracts.messages import TOUCH_DIRECTIONS, ProbeHit, TouchId

_NONE = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class TouchInfo:
    """What the program says about one touch: identity, commanded pose, approach, feed."""

    id: TouchId
    b_cmd_deg: float = 0.0
    c_cmd_deg: float = 0.0
    direction: tuple[float, float, float] = _NONE
    feed_mm_min: float = 0.0


class TouchTable:
    """The touches of one program by sequence number (seq k is the k-th touch, 1-based)."""

    def __init__(self, touches: Iterable[TouchInfo | TouchId] = ()) -> None:
        infos = [t if isinstance(t, TouchInfo) else TouchInfo(t) for t in touches]
        self._by_seq = {t.id.seq: t for t in infos}
        if len(self._by_seq) != len(infos):
            raise ValueError("touch table: a sequence number appears twice")

    def __len__(self) -> int:
        return len(self._by_seq)

    def __iter__(self) -> Iterator[TouchInfo]:
        return iter(self._by_seq[k] for k in sorted(self._by_seq))

    def __contains__(self, seq: object) -> bool:
        return seq in self._by_seq

    def get(self, seq: int) -> TouchInfo | None:
        return self._by_seq.get(seq)

    def ids(self) -> tuple[TouchId, ...]:
        return tuple(t.id for t in self)

    def mismatch(self, hit: ProbeHit) -> str:
        """Why ``hit`` does not belong to this program ('' when it does): identities are
        carried through the program into its results, never guessed."""
        info = self._by_seq.get(hit.seq)
        if info is None:
            return f"controller reported touch seq {hit.seq}, not in the program"
        t = info.id
        if hit.ball and (hit.pose, hit.ball, hit.touch, hit.repeat) != (t.pose, t.ball, t.touch,
                                                                        t.repeat):
            return (f"touch seq {hit.seq} reported as pose {hit.pose} ball {hit.ball} touch "
                    f"{hit.touch} rep {hit.repeat}, the program has pose {t.pose} ball {t.ball} "
                    f"touch {t.touch} rep {t.repeat}")
        return ""

    def named(self, seq: int, axes: dict[str, float], triggered: bool, **fields: Any) -> ProbeHit:
        """The hit of touch ``seq`` as a transport reporting only (seq, axes) delivers it (OPC UA,
        Modbus): identity and approach direction from the program (a tilted touch's direction
        is in the tool frame: the log is true), the nominal direction of its touch
        number when the program gives none; pose -1 and no ball for a seq not in the table.
        ``fields`` (``t_s=…``, ``raw=…``) are passed to ``ProbeHit``."""
        info = self._by_seq.get(seq)
        if info is None:
            return ProbeHit(seq=seq, pose=-1, ball="", touch=0, axes=axes, triggered=triggered,
                            **fields)
        t = info.id
        direction = info.direction if info.direction != _NONE else \
            TOUCH_DIRECTIONS.get(t.touch, _NONE)
        return ProbeHit(seq=seq, pose=t.pose, ball=t.ball, touch=t.touch, repeat=t.repeat,
                        axes=axes, triggered=triggered, direction=direction, **fields)

    def fill(self, hit: ProbeHit, **changes: Any) -> ProbeHit:
        """``hit`` with only what it lacks taken from the program: identity when it has no ball,
        commanded pose when both rotary values are zero, feed when zero (what the transport or
        result line reported is kept); the approach direction is the program's whenever it has
        one — no transport reports a direction, a result line only implies its touch number's
        nominal diagonal, which a tilted touch is not. ``changes`` are applied as
        given. Filling twice changes nothing."""
        info = self._by_seq.get(hit.seq)
        if info is not None:
            t = info.id
            if not hit.ball:
                changes.setdefault("pose", t.pose)
                changes.setdefault("ball", t.ball)
                changes.setdefault("touch", t.touch)
                changes.setdefault("repeat", t.repeat)
            if info.direction != _NONE and hit.direction != info.direction:
                changes.setdefault("direction", info.direction)
            if hit.b_cmd_deg == 0.0 and hit.c_cmd_deg == 0.0:
                changes.setdefault("b_cmd_deg", info.b_cmd_deg)
                changes.setdefault("c_cmd_deg", info.c_cmd_deg)
            if hit.feed_mm_min == 0.0:
                changes.setdefault("feed_mm_min", info.feed_mm_min)
        return replace(hit, **changes) if changes else hit

    def complete(self, hit: ProbeHit, **changes: Any) -> ProbeHit:
        """``hit`` with what a transport cannot know filled from the program: identity (when the
        transport reported only seq), commanded pose, approach direction and feed; ``changes``
        (``t_s=…``, ``raw=…``, ``axes=…``) are applied as given."""
        info = self._by_seq.get(hit.seq)
        if info is not None:
            t = info.id
            changes.setdefault("pose", t.pose)
            changes.setdefault("ball", t.ball)
            changes.setdefault("touch", t.touch)
            changes.setdefault("repeat", t.repeat)
            changes.setdefault("b_cmd_deg", info.b_cmd_deg)
            changes.setdefault("c_cmd_deg", info.c_cmd_deg)
            changes.setdefault("direction", info.direction)
            changes.setdefault("feed_mm_min", info.feed_mm_min)
        return replace(hit, **changes) if changes else hit
