"""The fleet charts' shared frame (daemon/fleet/chart.py): padded range, round ticks inside it,
the y scale top-down, attributes and labels escaped."""

from __future__ import annotations

import pytest

from daemon.fleet.chart import Frame, padded, ticks


def test_padded_widens_by_six_percent_and_a_single_value_by_one():
    assert padded(0.0, 10.0) == pytest.approx((-0.6, 10.6))
    assert padded(5.0, 5.0) == pytest.approx((5.0 - 1.12, 5.0 + 1.12))


@pytest.mark.parametrize(("lo", "hi", "want"), [
    (-0.6, 10.6, [0.0, 5.0, 10.0]),
    (-13.0, 13.0, [-10.0, 0.0, 10.0]),  # a step of 6.5 rounds up to 10
    (19.4, 24.6, [20.0, 22.0, 24.0]),
])
def test_ticks_are_round_and_inside_the_range(lo, hi, want):
    assert ticks(lo, hi) == pytest.approx(want)


def test_y_runs_from_the_top_margin_down_to_the_bottom_one():
    f = Frame(150, 10, 26, -1.0, 3.0)
    assert (f.y(3.0), f.y(-1.0), f.y(1.0)) == pytest.approx((10.0, 124.0, 67.0))
    grid = f.y_grid()
    assert len(grid) == len(ticks(-1.0, 3.0)) and 'y1="124.0"' in grid[0]


def test_names_in_attributes_and_labels_are_escaped():
    f = Frame(320, 12, 40, 0.0, 1.0)
    head = f.open({"class": "chart", "data-link": 'E"X<0>C'}, "a & b")
    assert head.startswith('<svg class="chart" data-link="E&quot;X&lt;0&gt;C" '
                           'viewBox="0 0 560 320"')
    assert head.endswith('aria-label="a &amp; b">')
    assert ">E&lt;X&gt; (µm)</text>" in f.y_label("E<X> (µm)")
    assert 'y="146"' in f.y_label("x")  # centred between the margins: (12 + 320 - 40) / 2
