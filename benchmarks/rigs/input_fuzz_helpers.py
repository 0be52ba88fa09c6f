"""Shared by tests/test_inputs_fuzz.py: the outcome of one fuzzed input (read, refused,
traceback, hang, wrong acceptance or refusal), its tally, and the special files every reader
must refuse without hanging."""

from __future__ import annotations

import os
import signal
import warnings
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from benchmarks.rigs.reader_helpers import ARTEFACT, CONFIG
from contracts.centres_file import read_centres
from contracts.importers import import_centres
from contracts.probing_log import ProbeLogWarning, read_log
from contracts.yaml_files import ConfigError, read_yaml
from programs.model import load_targets

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests/data/centres"
EXAMPLE_LOG = CONFIG / "examples/thesis_annexB_14poses.csv"
HANG_S = 10  # CPU seconds: a runaway loop (an analysis takes under 1)
BLOCKED_S = 300  # wall seconds: a call blocked without computing (a FIFO's open)
BAD = ("traceback", "hang", "wrong acceptance", "wrong refusal")


class Hang(Exception):
    pass


@contextmanager
def deadline(cpu_s: float, wall_s: float = BLOCKED_S) -> Iterator[None]:
    """A call that computes for ``cpu_s`` CPU seconds (SIGPROF: the process' CPU time) or
    waits for ``wall_s`` seconds (SIGALRM: a blocking open() of a FIFO) ends as Hang. CPU
    time, not the clock, for the loop: on a loaded CI box a 0.6 s analysis took over 10 s
    of wall time, and a wall-clock bound failed a correct reader there."""
    def fire(signum: int, frame: Any) -> None:
        raise Hang

    old_prof = signal.signal(signal.SIGPROF, fire)
    old_alrm = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_PROF, cpu_s)
    signal.setitimer(signal.ITIMER_REAL, wall_s)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGPROF, old_prof)
        signal.signal(signal.SIGALRM, old_alrm)


def outcome(call: Callable[[], Any], path: Path | str, valid: bool | None,
             check: Callable[[Any], bool] = lambda _: True) -> tuple[str, str]:
    """(class, detail) of one example: ``valid`` True: must be read (``check`` holds on the
    result), False: must be refused, None: either."""
    try:
        with deadline(HANG_S), warnings.catch_warnings():
            warnings.simplefilter("ignore", ProbeLogWarning)
            out = call()
    except Hang:
        return "hang", str(path)
    except ConfigError as e:
        msg = str(e)
        if "\n" in msg or not msg.startswith(str(path)) or len(msg) > 600:
            return "traceback", f"not one line naming the file: {msg[:300]!r}"
        return ("wrong refusal", msg[:300]) if valid else ("refused", "")
    except Exception as e:  # the count of what must never happen
        return "traceback", f"{type(e).__name__}: {e}"[:300]
    if valid is False or not check(out):
        return "wrong acceptance", str(path)
    return "read", ""


class Tally:
    """Counts of one fuzz test; the first bad examples kept for the failure message."""

    def __init__(self, name: str) -> None:
        self.name, self.counts, self.bad = name, Counter[str](), []

    def add(self, result: tuple[str, str], example: object) -> None:
        self.counts[result[0]] += 1
        if result[0] in BAD and len(self.bad) < 5:
            self.bad.append(f"{result[0]}: {result[1]} ← {example!r}"[:500])

    def verdict(self) -> None:
        print(f"\n{self.name}: " + ", ".join(f"{k} {self.counts[k]}"
                                           for k in ("read", "refused", *BAD)))
        assert all(self.counts[k] == 0 for k in BAD), self.bad


# ------------------------------------------------------------------- special files, ceilings

READERS: dict[str, Callable[[Path | str], Any]] = {
    "log": lambda p: read_log(p, ARTEFACT),
    "centres": read_centres,
    "kinopt": lambda p: import_centres(p, "kinopt", balls=ARTEFACT.ids, rotary=("B", "C"),
                                       ball="B1"),
    "dmis": lambda p: import_centres(p, "dmis", balls=ARTEFACT.ids, rotary=("B", "C"),
                                     poses=[(0.0, 0.0)] * 14),
    "auto": lambda p: import_centres(p, balls=ARTEFACT.ids, rotary=("B", "C"), ball="B1",
                                     poses=[(0.0, 0.0)] * 14),
    "yaml": read_yaml,
    "targets": lambda p: load_targets(p, ARTEFACT),
}
SAMPLES = {"log": EXAMPLE_LOG, "kinopt": DATA / "kinopt_B1.nc", "dmis": DATA / "dmis_cmm.dmo",
           "auto": DATA / "dmis_cmm.dmo", "yaml": CONFIG / "machines/thesis_wcbxfzyt.yaml"}


def special_file(tmp: Path, kind: str, sample: Path | None) -> tuple[Path | str, bool]:
    """A path of ``kind`` and whether a reader may accept it (regular files only)."""
    if kind.startswith("/dev/"):
        return kind, False
    p = tmp / f"special-{kind}"
    if p.exists() or p.is_symlink():
        p.unlink() if not p.is_dir() or p.is_symlink() else os.rmdir(p)
    if kind in ("fifo", "link-to-fifo"):
        fifo = tmp / "the-fifo"
        if not fifo.exists():
            os.mkfifo(fifo)
        if kind == "fifo":
            return fifo, False
        p.symlink_to(fifo)
        return p, False
    if kind == "dir":
        p.mkdir()
        return p, False
    if kind == "link-to-sample" and sample is not None:
        p.symlink_to(sample)
        return p, True
    p.write_bytes(b"")
    return p, True  # an empty regular file: refused by every reader but YAML's (None)
