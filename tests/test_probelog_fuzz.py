"""Property-based fuzzing of the probing-log reader: a mutated log is read or refused cleanly."""

import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.rigs.reader_helpers import ARTEFACT, CONFIG, mutate_line, mutate_whole
from contracts.probing_log import (
    HEADER,
    ProbeLog,
    ProbeLogError,
    ProbeLogWarning,
    read_log,
    write_log,
)
from contracts.setup_files import load_machine
from daemon.analysis.touch_centres import rows_to_centres
from simulators.exact_log import Truth, make_rows


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> tuple[Path, list[bytes]]:
    m, _ = load_machine(CONFIG / "machines/thesis_wcbxfzyt.yaml")
    rows = make_rows(m, ARTEFACT, [(0.0, 0.0), (30.0, 90.0)], Truth({"EX0C": -0.1}),
                     touch_noise_um=0.5, seed=1)
    d = tmp_path_factory.mktemp("fuzz")
    write_log(d / "valid.csv", rows)
    return d / "fuzz.csv", (d / "valid.csv").read_bytes().split(b"\n")


_NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(min_value=-10**30, max_value=10**30).map(str),
    st.sampled_from(["1e15", "-1e308", "1e999", "1_0", "٣", "１", "0x10", "", " ", "+", "-.",
                     "1e", "NaN", "inf", "9" * 400, "1.5.2", "\u00a01", "1\x00", '"1,2"']))
_CELLS = st.one_of(_NUMBERS, st.text(max_size=30), st.sampled_from(["B1", "B4", "B9", "synth"]))
_MUTATION = st.one_of(
    st.tuples(st.just("cell"), st.integers(0, 50), st.integers(0, len(HEADER) - 1), _CELLS),
    st.tuples(st.just("drop"), st.integers(0, 50)),
    st.tuples(st.just("dup"), st.integers(0, 50)),
    st.tuples(st.just("swap"), st.integers(0, 50), st.integers(0, 50)),
    st.tuples(st.just("bytes"), st.integers(0, 50), st.integers(0, 300), st.binary(max_size=6)),
    st.tuples(st.just("long"), st.integers(0, 50), st.integers(100, 20_000)),
    st.tuples(st.just("nul"), st.integers(0, 50), st.integers(0, 300)),
    st.tuples(st.sampled_from(["bom", "crlf", "cr", "truncate"]), st.integers(0, 5000)),
)


def _mutate(lines: list[bytes], ops: list[tuple]) -> bytes:
    lines = list(lines)
    for op in ops:
        if not lines:
            break
        if op[0] == "cell":
            k = op[1] % len(lines)
            cells = lines[k].split(b",")
            cells[op[2] % len(cells)] = op[3].encode("utf-8", "surrogatepass")
            lines[k] = b",".join(cells)
        else:
            mutate_line(lines, ("bytes", op[1], op[2], b"\x00") if op[0] == "nul" else op)
    return mutate_whole(b"\n".join(lines), ops)


def _clean(e: ProbeLogError, path: Path) -> None:
    msg = str(e)
    assert "\n" not in msg and msg.startswith(str(path)), msg
    assert len(msg) < 600, msg


@settings(max_examples=150, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ops=st.lists(_MUTATION, min_size=1, max_size=4))
def test_mutated_log_is_read_or_refused_with_one_named_line(valid, ops) -> None:
    path, lines = valid
    path.write_bytes(_mutate(lines, ops))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ProbeLogWarning)
        try:
            log = read_log(path, ARTEFACT)
        except ProbeLogError as e:
            _clean(e, path)
            msg = str(e)
            assert ": line " in msg or "no touch rows" in msg or "bytes, more than" in msg, msg
            return
        assert isinstance(log, ProbeLog) and len(log) > 0
        for name in ("x_mm", "y_mm", "z_mm"):
            assert np.all(np.abs(log.column(name)) <= 1e5)
        try:
            data = rows_to_centres(log, ARTEFACT, 3.0, source=str(path))
        except ProbeLogError as e:
            _clean(e, path)
            return
        assert np.isfinite(data.centres.xyz_mm).all()


def test_the_unmutated_log_reads(valid) -> None:
    path, lines = valid
    path.write_bytes(b"\n".join(lines))
    assert len(rows_to_centres(read_log(path, ARTEFACT), ARTEFACT, 3.0).centres) == 8
