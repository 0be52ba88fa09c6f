"""Property-based fuzzing of the centres readers (centres CSV, KinOpt, DMIS): a mutated file is
read — and then holds only finite, in-range, unambiguous centres — or refused with one line
naming the file; a cell made invalid is never accepted."""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.rigs.reader_helpers import ARTEFACT, centre_rows, mutate_line, mutate_whole
from contracts.centres_file import HEADER, CentresFile, CentresFileError, write_centres
from contracts.importers import import_centres
from contracts.probing_log import ProbeLogError, ProbeLogWarning
from contracts.setup_files import load_machine
from daemon.analysis.centres_input import load
from tests.regen_centres_fixtures import centres

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "centres"
MACHINE, _ = load_machine(ROOT / "config/machines/thesis_wcbxfzyt.yaml")
POSES = centres()[0]
SETTINGS = settings(max_examples=120, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])

_NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(min_value=-10**30, max_value=10**30).map(str),
    st.sampled_from(["1e15", "-1e308", "1e999", "1_0", "٣", "１", "0x10", "", " ", "+", "-.",
                     "1e", "NaN", "inf", "9" * 400, "1.5.2", "\u00a01", "1\x00", '"1,2"',
                     "V.L.X[0]", "$", "$$", "'", "(", ")", "\\", "]", "@P1 = 2"]))
_CELLS = st.one_of(_NUMBERS, st.text(max_size=30), st.sampled_from(["B1", "B4", "B9", "run"]))
_MUTATION = st.one_of(
    st.tuples(st.just("cell"), st.integers(0, 500), st.integers(0, 40), _CELLS),
    st.tuples(st.just("drop"), st.integers(0, 500)),
    st.tuples(st.just("dup"), st.integers(0, 500)),
    st.tuples(st.just("swap"), st.integers(0, 500), st.integers(0, 500)),
    st.tuples(st.just("bytes"), st.integers(0, 500), st.integers(0, 300), st.binary(max_size=6)),
    st.tuples(st.just("long"), st.integers(0, 500), st.integers(100, 20_000)),
    st.tuples(st.sampled_from(["bom", "crlf", "truncate"]), st.integers(0, 50_000)),
)
_SEP = re.compile(rb"([,=])")


def _mutate(data: bytes, ops: list[tuple]) -> bytes:
    lines = data.split(b"\n")
    for op in ops:
        if op[0] == "cell":  # replace one field between separators (, or =)
            k = op[1] % len(lines)
            parts = _SEP.split(lines[k])
            j = 2 * (op[2] % (len(parts) // 2 + 1))
            parts[min(j, len(parts) - 1)] = op[3].encode("utf-8", "surrogatepass")
            lines[k] = b"".join(parts)
        else:
            mutate_line(lines, op)
        if not lines:
            break
    return mutate_whole(b"\n".join(lines), ops)


def _check(path: Path, fmt: str) -> CentresFile | None:
    """Read ``path``; a refusal must be one clean line naming the file."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ProbeLogWarning)
        try:
            cf = import_centres(path, fmt, balls=ARTEFACT.ids, rotary=("B", "C"), ball="B1",
                                poses=POSES)
        except CentresFileError as e:
            msg = str(e)
            assert "\n" not in msg and msg.startswith(str(path)) and len(msg) < 600, msg
            return None
    rows = cf.rows
    assert rows
    xyz = np.array([[r.x_mm, r.y_mm, r.z_mm] for r in rows])
    assert np.isfinite(xyz).all() and np.abs(xyz).max() <= 1e5
    keys = {(r.run_id, r.repeat, r.pose, r.ball) for r in rows}
    assert len(keys) == len(rows) and len({(r.run_id, r.seq) for r in rows}) == len(rows)
    u = [r.u_um for r in rows]
    assert all(math.isnan(x) for x in u) or all(0 < x <= 1e4 for x in u)
    assert all(r.ball in ARTEFACT.ids for r in rows)
    return cf


def _downstream(path: Path, fmt: str) -> None:
    """An accepted file reaches the analyses' input (one run, finite centres) or is refused."""
    try:
        inp = load(path, fmt, MACHINE, ARTEFACT, ball="B1", plan_poses=POSES)
    except ProbeLogError as e:  # the file's errors, and the one-run check's
        assert "\n" not in str(e)
        return
    assert np.isfinite(inp.data.centres.xyz_mm).all()


@pytest.fixture(scope="module")
def csv_bytes(tmp_path_factory) -> bytes:
    p = tmp_path_factory.mktemp("c") / "c.csv"
    write_centres(p, centre_rows(u=0.5), repeatability_um=(0.3, 0.3, 0.3))
    return p.read_bytes()


_VALID = re.compile(r"[ \t]*[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?[ \t]*")


@SETTINGS
@given(ops=st.lists(_MUTATION, min_size=1, max_size=4))
def test_mutated_centres_csv_is_read_or_refused(csv_bytes, tmp_path, ops) -> None:
    path = tmp_path / "fuzz.csv"
    path.write_bytes(_mutate(csv_bytes, ops))
    if _check(path, "csv") is not None:
        _downstream(path, "csv")


@SETTINGS
@given(row=st.integers(0, 7), col=st.sampled_from(["t_s", "x_mm", "y_mm", "z_mm", "b_deg",
                                                    "c_deg", "u_um"]), cell=_NUMBERS)
def test_an_invalid_number_is_never_accepted(csv_bytes, tmp_path, row, col, cell) -> None:
    lines = csv_bytes.decode().split("\n")
    first = next(i for i, x in enumerate(lines) if x.startswith("run_id,")) + 1
    cells = lines[first + row].split(",")
    cells[HEADER.index(col)] = cell
    lines[first + row] = ",".join(cells)
    path = tmp_path / "one.csv"
    path.write_text("\n".join(lines), encoding="utf-8", errors="surrogatepass")
    lo, hi = {"t_s": (0, 1e8), "u_um": (0, 1e4)}.get(col, (-1e5, 1e5))
    ok = "," not in cell and '"' not in cell and "\n" not in cell and "\r" not in cell \
        and bool(_VALID.fullmatch(cell)) and lo <= float(cell) <= hi \
        and (col != "u_um" or float(cell) > 0)
    cf = _check(path, "csv")
    if not ok:
        assert cf is None, f"{col} = {cell!r} accepted"
    elif cf is not None:
        assert getattr(cf.rows[row], col) == float(cell)


@pytest.mark.parametrize(("fmt", "sample"), [("kinopt", "kinopt_B1.nc"),
                                             ("dmis", "dmis_cmm.dmo")])
@SETTINGS
@given(ops=st.lists(_MUTATION, min_size=1, max_size=4), auto=st.sampled_from([True, False]))
def test_mutated_instrument_file_is_read_or_refused(tmp_path, fmt, sample, ops, auto) -> None:
    """A KinOpt program or DMIS results file, read as ``auto`` or as its own format."""
    path = tmp_path / f"fuzz{Path(sample).suffix}"
    path.write_bytes(_mutate((DATA / sample).read_bytes(), ops))
    if _check(path, "auto" if auto else fmt) is not None and not auto:
        _downstream(path, fmt)
