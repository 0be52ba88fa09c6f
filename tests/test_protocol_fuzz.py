"""Protocol garbage fuzz: whatever a controller puts in a Modbus result slot or status block, an
OPC UA result ring or a serial result line, the decoder returns a valid hit or raises the link's
clear error (``MalformedResult`` / the serial ``ValueError``), never another exception, and never
lets an out-of-order, out-of-program or implausible result through."""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from contracts.jobs import ProgramJob
from contracts.messages import ProbeHit, TouchId
from contracts.modbus_map import (
    COMMANDS,
    MAP_ID,
    MAP_VERSION,
    RING_SLOTS,
    SLOT_WORDS,
    STATE_CODES,
    STATUS_WORDS,
    addr,
    encode_slot,
)
from contracts.opcua_space import RESULT_ROLES, STATES
from contracts.opcua_space import RING_SLOTS as UA_RING_SLOTS
from contracts.result_lines import MAX_RESULT_DEG, MAX_RESULT_MM
from contracts.touch_table import TouchTable
from drivers.hits import HitFactory, MalformedResult
from drivers.modbus.link import check_mailbox, check_status, slot_hit
from drivers.opcua.link import check_counter, ring_hit
from programs.dialects import DIALECTS

FUZZ = settings(max_examples=150, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])
TOUCHES = 20
JOB = ProgramJob(run_id="fuzz", text="", dialect="fanuc", touch_count=TOUCHES,
                 touches=TouchTable(TouchId(seq=k, pose=(k - 1) // 5, ball="B1",
                                            touch=(k - 1) % 5 + 1)
                                    for k in range(1, TOUCHES + 1)))


def valid_hit(hit: ProbeHit, seq: int) -> None:
    """What every decoded hit must be: the expected touch, plausible finite positions."""
    assert hit.seq == seq and (hit.pose, hit.touch) == ((seq - 1) // 5, (seq - 1) % 5 + 1)
    assert isinstance(hit.triggered, bool)
    for key, v in hit.axes.items():
        limit = MAX_RESULT_MM if key in "XYZ" else MAX_RESULT_DEG
        assert math.isfinite(v) and abs(v) <= limit, (key, v)


# ---------------------------------------------------------------------------- Modbus

u16 = st.integers(0, 0xFFFF)
good_slot = st.builds(
    lambda x, y, trig: encode_slot(1, {"X": x, "Y": y, "Z": -x, "b": 10.0, "c": -5.0,
                                      "triggered": float(trig)}),
    st.floats(-2e5, 2e5), st.floats(-500, 500), st.booleans())


@st.composite
def slots(draw: st.DrawFn) -> list[int]:
    """Pure garbage, or a valid slot of touch 1 with some registers overwritten."""
    if draw(st.booleans()):
        return draw(st.lists(u16, min_size=SLOT_WORDS, max_size=SLOT_WORDS))
    regs = draw(good_slot)
    for i in draw(st.lists(st.integers(0, SLOT_WORDS - 1), max_size=3)):
        regs[i] = draw(u16)
    return regs


@FUZZ
@given(slots(), st.integers(0, RING_SLOTS - 1))
@example([0, 1, 0x7FFF, 0xFFFF, *[0] * 8, 1, 0, 0, 0], 0)  # X = 214 748 mm: int32 max
@example([0, 1, *[0] * 10, 1, 0, 0, 0], 3)  # all zero positions, triggered: valid
def test_modbus_slot_garbage_is_a_hit_or_a_clear_error(regs, slot):
    try:
        hit = slot_hit(HitFactory(JOB), regs, slot)
    except MalformedResult as e:
        assert f"slot {slot}" in str(e)
        return
    valid_hit(hit, 1)
    assert regs[12] in (0, 1) and regs[13:] == [0, 0, 0]


@st.composite
def status_blocks(draw: st.DrawFn) -> list[int]:
    regs = draw(st.lists(u16, min_size=STATUS_WORDS, max_size=STATUS_WORDS))
    if draw(st.booleans()):  # mostly plausible, so the valid path is exercised too
        regs[addr("MAP_ID")], regs[addr("MAP_VERSION")] = MAP_ID, MAP_VERSION
        regs[addr("RING_SLOTS")] = RING_SLOTS
        for name, hi in (("STATE", 4), ("REQUEST", 1), ("BUSY", 1), ("DONE", 1),
                         ("VERDICT", 4), ("COMMAND", 3), ("MBX_READY", 1)):
            regs[addr(name)] = draw(st.integers(0, hi + draw(st.sampled_from([0, 0, 0, 1]))))
        regs[addr("ALARM_CODE")] = draw(st.sampled_from([0, 1, 2, 3, 9, 4]))
    return regs


@FUZZ
@given(status_blocks(), st.integers(0, 0xFFFF), st.integers(0, 0xFFFF))
def test_modbus_status_garbage_is_named_or_accepted(regs, seq, prev_seq):
    try:
        st_ = check_status(regs)
        check_mailbox(st_, seq, prev_seq)
    except MalformedResult as e:
        assert "register" in str(e) and "expected" in str(e)
        return
    assert st_["state"] in STATE_CODES.values() and st_["ready"] in (0, 1)
    assert st_["command"] in (0, *COMMANDS.values())
    assert st_["ack"] in (prev_seq, seq) and (not seq or st_["seq"] == seq)


def test_modbus_slot_must_be_the_next_touch():
    hits = HitFactory(JOB)
    valid_hit(slot_hit(hits, encode_slot(1, {}), 0), 1)
    with pytest.raises(MalformedResult, match="touch seq 1, expected 2"):
        slot_hit(hits, encode_slot(1, {}), 1)  # a stale slot read again
    with pytest.raises(MalformedResult, match="touch seq 3, expected 2"):
        slot_hit(hits, encode_slot(3, {}), 1)  # a touch skipped


# ---------------------------------------------------------------------------- OPC UA

ua_value = st.one_of(
    st.integers(-(2**31), 2**31 - 1), st.integers(), st.floats(allow_nan=True),
    st.booleans(), st.none(), st.text(max_size=5), st.sampled_from([0, 1, 1.0, 2.5]))


@st.composite
def ua_rows(draw: st.DrawFn) -> list:
    """The seven result arrays: plausible ones with garbage elements, or garbage structure."""
    if draw(st.integers(0, 4)) == 0:
        return draw(st.lists(st.one_of(st.none(), st.lists(ua_value, max_size=UA_RING_SLOTS + 1)),
                             min_size=6, max_size=8))
    rows = [[1] * UA_RING_SLOTS, *([0.0] * UA_RING_SLOTS for _ in range(5)), [1] * UA_RING_SLOTS]
    for _ in range(draw(st.integers(0, 3))):
        r, i = draw(st.integers(0, len(RESULT_ROLES) - 1)), draw(st.integers(0, UA_RING_SLOTS - 1))
        rows[r][i] = draw(ua_value)
    return rows


@FUZZ
@given(ua_rows(), st.integers(1, UA_RING_SLOTS))
def test_opcua_ring_garbage_is_a_hit_or_a_clear_error(rows, n):
    try:
        hit = ring_hit(HitFactory(JOB), rows, n)
    except MalformedResult as e:
        assert f"ring slot {n - 1}" in str(e)
        return
    valid_hit(hit, 1)


@FUZZ
@given(st.one_of(ua_value, st.integers(0, 40).map(float)),
       st.one_of(st.sampled_from(STATES), st.text(max_size=6), st.none(), st.integers()),
       st.integers(0, 30), st.one_of(st.none(), st.integers(0, 40)))
def test_opcua_counter_garbage_is_named_or_accepted(counter, state, last, high):
    try:
        n = check_counter(counter, state, last, high)
    except MalformedResult as e:
        assert "expected" in str(e)
        return
    assert state in STATES and n == counter and last <= n and (high is None or n <= high)


# ---------------------------------------------------------------------------- serial DNC

NUM = st.one_of(st.integers(-10**6, 10**6).map(str), st.floats(-1e6, 1e6).map(lambda v: f"{v:.4f}"),
                st.sampled_from(["1" * 400, "-0", ".5", "1.", "+3", "1e5", "nan", "", "٣"]))


@st.composite
def result_lines(draw: st.DrawFn) -> str:
    if draw(st.integers(0, 4)) == 0:
        return "RUMBA " + draw(st.text(max_size=60))
    fields = ["1", "0", "0", "B1", "1", "1", "10.5", "-3.25", "7", "0", "90"]
    for _ in range(draw(st.integers(0, 3))):
        fields[draw(st.integers(0, len(fields) - 1))] = draw(NUM)
    return "RUMBA " + " ".join(fields)


@FUZZ
@given(result_lines(), st.sampled_from(sorted(DIALECTS)))
@example("RUMBA 1 0 0 B1 1 1 " + "9" * 400 + " 0 0 0 90", "fanuc")  # X parses as inf
def test_serial_result_line_garbage_is_a_hit_or_a_clear_error(line, dialect):
    """The serial link's path: the dialect's line parser (ValueError = "garbled result line"),
    then HitFactory.complete (MalformedResult). Order is checked by the link itself."""
    try:
        hit = DIALECTS[dialect]().parse_result(line)
        if hit is None:
            return
        hit = HitFactory(JOB).complete(hit, line)
    except (ValueError, MalformedResult):
        return
    for v in hit.axes.values():
        assert math.isfinite(v) and abs(v) <= MAX_RESULT_MM
