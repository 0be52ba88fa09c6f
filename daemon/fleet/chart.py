"""The fleet pages' inline SVG chart frame (no I/O): padded value range, round ticks, the y scale,
the <svg> element, the y grid with its tick labels and the rotated y-axis label."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from html import escape

WIDTH_PX, LEFT_PX, RIGHT_PX = 560, 64, 12  # every fleet chart: width, left and right margins


def _e(x: str) -> str:
    return escape(x, quote=True)


def ticks(lo: float, hi: float, n: int = 4) -> list[float]:
    """About ``n`` steps of 1, 2, 2.5 or 5 × 10^k inside [lo, hi] (none if either is not a
    finite number)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return []
    step = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(step)) if step > 0 else 1.0
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= step)
    first = math.ceil(lo / step) * step
    return [first + i * step for i in range(int((hi - first) / step + 1e-9) + 1)]


def padded(lo: float, hi: float) -> tuple[float, float]:
    """[lo, hi] widened by 6 % each side (±1 around a single value), so no point sits on the
    frame."""
    if hi - lo < 1e-9:
        lo, hi = lo - 1.0, hi + 1.0
    pad = 0.06 * (hi - lo)
    return lo - pad, hi + pad


@dataclass(frozen=True)
class Frame:
    """A chart of ``height_px`` with top and bottom margins, values ``lo``…``hi`` upwards."""

    height_px: int
    top_px: int
    bottom_px: int
    lo: float
    hi: float

    def y(self, v: float) -> float:
        t, h, b = self.top_px, self.height_px, self.bottom_px
        return t + (h - t - b) * (self.hi - v) / (self.hi - self.lo)

    def open(self, attrs: Mapping[str, str], aria: str) -> str:
        """The <svg> element: ``attrs`` (class, data-*) then the size, ``aria`` its label."""
        w, h = WIDTH_PX, self.height_px
        head = " ".join(f'{k}="{_e(v)}"' for k, v in attrs.items())
        return (f'<svg {head} viewBox="0 0 {w} {h}" width="{w}" height="{h}" role="img" '
                f'aria-label="{_e(aria)}">')

    def y_grid(self) -> list[str]:
        """A grid line across the plot and its value left of it, at each tick."""
        y, x1 = self.y, WIDTH_PX - RIGHT_PX
        return [f'<line class="grid" x1="{LEFT_PX}" x2="{x1}" y1="{y(tv):.1f}" '
                f'y2="{y(tv):.1f}"/><text class="tick" x="{LEFT_PX - 4}" y="{y(tv) + 4:.1f}" '
                f'text-anchor="end">{tv:g}</text>' for tv in ticks(self.lo, self.hi)]

    def y_label(self, text: str) -> str:
        """``text`` along the y axis, turned a quarter left, centred on the plot."""
        mid = (self.top_px + self.height_px - self.bottom_px) / 2
        return (f'<text class="axis-label" x="12" y="{mid:.0f}" '
                f'transform="rotate(-90 12 {mid:.0f})" text-anchor="middle">{_e(text)}</text>')
