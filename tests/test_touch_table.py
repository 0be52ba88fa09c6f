"""The one touch table: naming a (seq, axes) result, filling what a transport lacks, completing a
result line from the program, refusing a result that is not the program's touch."""

from __future__ import annotations

import pytest

from contracts.jobs import ProgramJob
from contracts.messages import TOUCH_DIRECTIONS, ProbeHit, TouchId
from contracts.touch_table import TouchInfo, TouchTable
from drivers.hits import HitFactory, MalformedResult

DIR = (0.0, 0.6, -0.8)  # the program's approach, not the touch's nominal one
TABLE = TouchTable(TouchInfo(TouchId(k, 0, "B1", k, 0), 30.0, 45.0, DIR, 500.0)
                   for k in (2, 1, 3))  # any order in, by seq out
AXES = {"X": 1.0, "Y": 2.0, "Z": 3.0}


def test_table_by_seq_and_no_duplicate() -> None:
    assert [t.id.seq for t in TABLE] == [1, 2, 3] and len(TABLE) == 3 and 2 in TABLE
    assert TABLE.ids()[0] == TouchId(1, 0, "B1", 1, 0) and TABLE.get(9) is None
    with pytest.raises(ValueError, match="twice"):
        TouchTable([TouchId(1, 0, "B1", 1), TouchId(1, 0, "B2", 1)])


def test_named_gives_identity_and_the_programs_direction() -> None:
    # the program's approach (a tilted touch's is in the tool frame), not the
    # touch number's nominal diagonal; that only when the program gives none
    hit = TABLE.named(2, AXES, True, t_s=1.5, raw="slot 1")
    assert (hit.pose, hit.ball, hit.touch, hit.repeat, hit.t_s) == (0, "B1", 2, 0, 1.5)
    assert hit.direction == DIR and hit.feed_mm_min == 0.0
    bare = TouchTable([TouchId(1, 0, "B1", 2, 0)]).named(1, AXES, True)
    assert bare.direction == TOUCH_DIRECTIONS[2]
    stray = TABLE.named(7, AXES, True)
    assert (stray.pose, stray.ball, stray.touch, stray.direction) == (-1, "", 0, (0.0, 0.0, 0.0))


def test_fill_keeps_what_was_reported_and_is_idempotent() -> None:
    bare = ProbeHit(seq=1, pose=-1, ball="", touch=0, axes=AXES, triggered=True)
    full = TABLE.fill(bare, t_s=2.0)
    assert (full.ball, full.touch, full.direction, full.feed_mm_min) == ("B1", 1, DIR, 500.0)
    assert (full.b_cmd_deg, full.c_cmd_deg, full.t_s) == (30.0, 45.0, 2.0)
    assert TABLE.fill(full) == full
    printed = ProbeHit(seq=1, pose=0, ball="B1", touch=1, axes=AXES, triggered=True,
                       b_cmd_deg=29.9, c_cmd_deg=45.1, direction=TOUCH_DIRECTIONS[1])
    kept = TABLE.fill(printed)  # the line's nominal diagonal is not what the program did
    assert (kept.b_cmd_deg, kept.direction, kept.feed_mm_min) == (29.9, DIR, 500.0)
    assert TABLE.fill(kept) == kept


def test_complete_takes_the_program_side_and_mismatch_names_the_difference() -> None:
    printed = ProbeHit(seq=3, pose=0, ball="B1", touch=3, axes=AXES, triggered=True,
                       b_cmd_deg=29.9, direction=TOUCH_DIRECTIONS[3])
    done = TABLE.complete(printed, raw="line")
    assert (done.b_cmd_deg, done.direction, done.raw) == (30.0, DIR, "line")
    assert TABLE.mismatch(done) == ""
    assert "pose 0 ball B2" in TABLE.mismatch(ProbeHit(3, 0, "B2", 3, AXES, True))
    assert "not in the program" in TABLE.mismatch(ProbeHit(4, 0, "B1", 4, AXES, True))


def test_hit_factory_names_through_the_job_table_in_program_order() -> None:
    hits = HitFactory(ProgramJob("r", "", "fanuc", len(TABLE), touches=TABLE))
    assert hits.make(1, AXES, True, "slot 0").ball == "B1"
    with pytest.raises(MalformedResult, match="expected 2"):
        hits.make(3, AXES, True, "slot 2")
    short = HitFactory(ProgramJob("r", "", "fanuc", 2))  # no table: only the count bounds seq
    short.made = 2
    with pytest.raises(MalformedResult, match="not in the program"):
        short.make(3, AXES, True, "slot 2")
