"""Target 7: the input surfaces, by their property tests run longer, and real-size logs."""

# The tests of tests/test_inputs_fuzz.py, _surfaces.py and _network.py with their
# example counts raised (``n`` shared out; hypothesis derandomized: the same ``--cases`` gives
# the same examples) and their tallies collected instead of asserted, plus logs of real size.

from __future__ import annotations

import inspect
import random
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks.fuzz.common import Tally

GEOMETRY_SHARE = 0.25  # an analysis against a wrong geometry takes ≈ 0.3 s: fewer of them
SLOW_SHARE = {"test_gcode_on_a_spindle_axis_that_is_no_direction": 0.5,
              "test_an_analysis_against_a_wrong_geometry_is_refused": GEOMETRY_SHARE}


def _tests() -> list[tuple[Any, Callable[..., None]]]:
    import tests.test_inputs_fuzz as t1
    import tests.test_inputs_fuzz_network as t3
    import tests.test_inputs_fuzz_surfaces as t2

    return [(m, f) for m in (t1, t2, t3) for name, f in sorted(vars(m).items())
            if name.startswith("test_") and inspect.isfunction(f)]


def _to_bench(name: str, counts: dict[str, int], bad: list[str], seconds: float) -> Tally:
    """The tests' tally (read / refused / the four bad classes) as this campaign's."""
    t = Tally(name[:22])
    t.tried = sum(counts.values())
    t.accepted, t.clean = counts.get("read", 0), counts.get("refused", 0)
    for mine, theirs in (("traceback", "traceback"), ("hang", "hang"),
                         ("wrong", "wrong acceptance"), ("refusal", "wrong refusal")):
        t.bad[mine] = counts.get(theirs, 0)
        t.cases[mine] = [b for b in bad if b.startswith(theirs)][:3]
    t.seconds = seconds
    return t


def _huge_logs(rng: random.Random, n: int, tmp: Path) -> Tally:
    """Logs of real size, each refused within the time limit (``input_fuzz_helpers.HANG_S``):
    one row over the 250 000-row ceiling (it once took 241 s), ten times over,
    one 64 MiB line, a 10 GB sparse file, /dev/zero, a FIFO."""
    import contracts.probing_log as pl
    from benchmarks.rigs.input_fuzz_helpers import EXAMPLE_LOG, READERS, outcome, special_file

    lines = EXAMPLE_LOG.read_text().splitlines()
    head, row = lines[:2], lines[2].split(",")

    def rows(count: int, path: Path) -> Path:
        if not path.exists():
            with path.open("w") as f:
                f.write("\n".join(head) + "\n")
                for k in range(count):
                    row[1], row[4], row[8] = str(k + 1), str(k // 20), str(k % 5 + 1)
                    f.write(",".join(row) + "\n")
        return path

    kinds = ["over-by-one", "ten-times", "one-line", "sparse", "/dev/zero", "fifo"]
    counts: dict[str, int] = {}
    bad: list[str] = []
    t0 = time.perf_counter()
    for _ in range(n):
        kind = rng.choice(kinds)
        reader = rng.choice(["log", "centres", "kinopt", "dmis", "auto"])
        if kind == "over-by-one":
            path: Path | str = rows(pl.MAX_LOG_ROWS + 1, tmp / "over.csv")
        elif kind == "ten-times":
            path = rows(10 * pl.MAX_LOG_ROWS, tmp / "ten.csv")
        elif kind == "one-line":
            path = tmp / "line.csv"
            if not path.exists():
                path.write_bytes(b"x" * (64 << 20))
        elif kind == "sparse":
            path = tmp / "sparse.csv"
            if not path.exists():
                with path.open("wb") as f:
                    f.truncate(10 << 30)
        else:
            path = special_file(tmp, kind, None)[0]
        cls, detail = outcome(lambda p=path, r=reader: READERS[r](p), path, False)
        counts[cls] = counts.get(cls, 0) + 1
        if cls not in ("read", "refused") and len(bad) < 3:
            bad.append(f"{cls}: {detail} <- {reader} {kind}")
    return _to_bench("huge logs", counts, bad, time.perf_counter() - t0)


def fuzz(rng: random.Random, n: int) -> list[Tally]:
    import pytest
    from hypothesis import settings

    import tests.test_inputs_fuzz as t1
    import tests.test_inputs_fuzz_network as t3
    import tests.test_inputs_fuzz_surfaces as t2

    tests = _tests()
    per = max(10, n // (len(tests) + 1))
    tallies: list[Tally] = []
    seen: list[tuple[str, dict[str, int], list[str]]] = []

    class Recorded(t1.Tally):  # type: ignore[name-defined,misc]
        def verdict(self) -> None:  # counted here, judged by the campaign's table
            seen.append((self.name, dict(self.counts), list(self.bad)))

    with tempfile.TemporaryDirectory(prefix="rumba-fuzz-inputs-") as d, \
            pytest.MonkeyPatch.context() as mp:
        tmp = Path(d)
        for m in (t1, t2, t3):
            mp.setattr(m, "Tally", Recorded)
            mp.setattr(m, "FUZZ", settings(t1.FUZZ, max_examples=per))
        mp.setattr(t1, "GEOMETRY_EXAMPLES", max(5, round(per * GEOMETRY_SHARE)))
        for module, test in tests:
            share = SLOW_SHARE.get(test.__name__, 1.0)
            mp.setattr(module, "FUZZ", settings(t1.FUZZ, max_examples=max(5, round(per * share))))
            work = tmp / test.__name__
            work.mkdir()
            kw: dict[str, Any] = {}
            params = inspect.signature(test).parameters
            t0 = time.perf_counter()
            with pytest.MonkeyPatch.context() as local:
                if "tmp_path" in params:
                    kw["tmp_path"] = work
                if "monkeypatch" in params:
                    kw["monkeypatch"] = local
                if "example_centres" in params:
                    kw["example_centres"] = t1.example_centres._get_wrapped_function()()
                before = len(seen)
                try:
                    test(**kw)
                except Exception as e:  # the harness itself: counted, never hidden
                    seen.append((test.__name__, {"traceback": 1},
                                 [f"traceback: {type(e).__name__}: {str(e)[:200]}"]))
            for name, counts, bad in seen[before:]:
                tallies.append(_to_bench(name, counts, bad, time.perf_counter() - t0))
        mp.undo()
        tallies.append(_huge_logs(rng, max(6, per // 5), tmp))
    return tallies
