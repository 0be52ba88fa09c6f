"""A synthetic probe hit for the journal tests (importable by their kill -9 writer subprocess)."""

from __future__ import annotations

from contracts.messages import ProbeHit


def hit(seq: int, triggered: bool = True) -> ProbeHit:
    return ProbeHit(seq=seq, pose=seq // 20, ball="B1", touch=1 + seq % 5,
                    axes={"X": 1.5 * seq, "Y": -2.0, "Z": 3.25, "B": 30.0, "C": 60.0},
                    triggered=triggered, t_s=0.1 * seq, raw=f"#{seq}", direction=(1.0, 0, 0),
                    feed_mm_min=300.0, extra={"q": 1.0})
