"""Garbage in the controller's variables: whatever a SINUMERIK server returns for the R parameters
of a result slot or the counter (any OPC UA variant: Double, Int, Boolean, String, ByteString,
an array, null, NaN, ±inf), or a Haas data port for the macro variables, the decoder
(drivers/variable_ring.py) returns the program's next touch with plausible values or raises
``MalformedResult`` naming the variable — never another exception, never a wrong acceptance.
Counted over the examples: tracebacks 0, wrong acceptances 0 (hangs: no I/O here, the live
paths are tests/test_sinumerik_link.py)."""

from __future__ import annotations

import math

from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from contracts.jobs import ProgramJob
from contracts.messages import TouchId
from contracts.result_lines import MAX_RESULT_DEG, MAX_RESULT_MM, RESULT_FIELDS, SLOT_FIELDS
from contracts.touch_table import TouchTable
from drivers.hits import HitFactory, MalformedResult
from drivers.variable_ring import check_counter, decode, slot_numbers

FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
TOUCHES = 20
JOB = ProgramJob(run_id="fuzz", text="", dialect="siemens", touch_count=TOUCHES,
                 touches=TouchTable(TouchId(seq=k, pose=(k - 1) // 5, ball="B1",
                                            touch=(k - 1) % 5 + 1, repeat=0)
                                    for k in range(1, TOUCHES + 1)))
NAMES = [f"R{k}" for k in slot_numbers(100, 1)]

anything = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-2**70, 2**70), st.booleans(),
    st.none(), st.text(max_size=8), st.binary(max_size=8),
    st.lists(st.floats(allow_nan=False), max_size=3))


def good(seq: int) -> list[float]:
    return [float(seq), 0.0, float((seq - 1) // 5), 1.0, float((seq - 1) % 5 + 1), 1.0,
            -111.05, -91.05, 152.0, 30.0, 60.0]


@st.composite
def slots(draw: st.DrawFn) -> tuple[list, int]:
    """A valid slot of touch n with some fields replaced by anything, or pure garbage."""
    n = draw(st.integers(1, TOUCHES))
    if draw(st.booleans()):
        return draw(st.lists(anything, min_size=SLOT_FIELDS, max_size=SLOT_FIELDS)), n
    values: list = good(n)
    for i in draw(st.lists(st.integers(0, SLOT_FIELDS - 1), max_size=3)):
        values[i] = draw(anything)
    return values, n


def _factory_at(n: int) -> HitFactory:
    hits = HitFactory(JOB)
    hits.made = n - 1  # touches 1..n-1 already delivered
    return hits


@FUZZ
@given(slots())
@example((good(1), 1), )
@example(([1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 2.2e5, 0.0, 0.0, 0.0, 0.0], 1))  # 220 m: implausible
@example(([1.0, 0.0, 0.0, 1.0, 1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0], 1))  # trig 0.5
@example(([1.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0], 1))  # pose 1, table 0
@example(([2.0, *good(1)[1:]], 1))  # seq 2 where touch 1 is due
@example(([True, *good(1)[1:]], 1))  # a Boolean seq
def test_slot_garbage_is_the_next_touch_or_a_named_error(case):
    values, n = case
    try:
        hit = decode(_factory_at(n), values, NAMES, n, "slot R100-R110")
    except MalformedResult as e:
        assert "malformed result" in str(e) or "not in the program" in str(e), e
        return
    # accepted: it must be exactly the touch due, as the program's table has it
    assert hit.seq == n and (hit.pose, hit.touch, hit.repeat) == ((n - 1) // 5,
                                                                   (n - 1) % 5 + 1, 0)
    raw = dict(zip(RESULT_FIELDS, values, strict=True))
    assert raw["seq"] == n and not isinstance(raw["seq"], bool)
    assert raw["trig"] in (0, 1) and hit.triggered == (raw["trig"] == 1)
    for key, v in hit.axes.items():
        limit = MAX_RESULT_MM if key in "XYZ" else MAX_RESULT_DEG
        assert math.isfinite(v) and abs(v) <= limit, (key, v)


@FUZZ
@given(anything, st.integers(0, TOUCHES), st.one_of(st.none(), st.integers(0, TOUCHES)))
@example(float("nan"), 0, 20)
@example(21.0, 0, 20)  # beyond the program
@example(3.0, 5, 20)  # backwards
@example(3.5, 0, 20)
def test_counter_garbage_is_named_or_accepted(value, last, high):
    try:
        n = check_counter(value, "R99", last, high)
    except MalformedResult as e:
        assert "R99" in str(e)
        return
    assert isinstance(value, int | float) and not isinstance(value, bool)
    assert float(value).is_integer() and n == value
    assert last <= n and (high is None or n <= high)


def test_slot_numbers_are_the_dialect_ring():
    """Touch n's slot is (n-1) mod 8, eleven variables from the ring's base."""
    assert slot_numbers(100, 1) == list(range(100, 111))
    assert slot_numbers(100, 8) == list(range(177, 188))
    assert slot_numbers(100, 9) == slot_numbers(100, 1)
    assert slot_numbers(600, 2) == list(range(611, 622))
