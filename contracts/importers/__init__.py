"""Centres measured by instruments, brought to the centres contract (``contracts.centres_file``):
the formats rumba reads, how a file's format is told, one entry point. Pure parsing."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from contracts.centres_file import MAGIC, CentresFile, check_rows, read_centres
from contracts.importers.common import CentresImportError, text_lines
from contracts.importers.dmis import read_dmis
from contracts.importers.kinopt import RECORD_CYCLE, read_kinopt

FORMATS = ("auto", "csv", "kinopt", "dmis")
DETECT_LINES = 200  # the format shows in the first lines of every supported file

__all__ = ["FORMATS", "CentresImportError", "detect", "import_centres"]


def detect(path: Path | str, text: str | None = None) -> str:
    """``csv``, ``kinopt`` or ``dmis`` from the first lines; a ``CentresImportError`` when the
    file is none of them (name it with ``--format``)."""
    for n, line in text_lines(path, text):
        u = line.strip().upper()
        if n == 1 and line.strip() == MAGIC:
            return "csv"
        if RECORD_CYCLE in u:
            return "kinopt"
        if "FEAT/SPHERE" in u or u.startswith(("DMISMN/", "FILNAM/")):
            return "dmis"
        if n >= DETECT_LINES:
            break
    raise CentresImportError(f"{path}: cannot tell the format: expected a rumba centres CSV "
                             f"(first line {MAGIC!r}), a KinOpt program (SysCalibFitAddRecord.ecy "
                             "calls) or a DMIS results file (FA(…)=FEAT/SPHERE); name it with "
                             "--format csv|kinopt|dmis")


def import_centres(path: Path | str, fmt: str = "auto", *, balls: Sequence[str],
                   rotary: Sequence[str], ball: str | None = None,
                   poses: Sequence[tuple[float, float]] | None = None,
                   text: str | None = None) -> CentresFile:
    """Read ``path`` as ``fmt`` and check its rows as the centres CSV reader does.

    ``balls``: the artefact's ball ids; ``rotary``: the machine's two rotary axis letters in
    alphabetical order (the ``b``/``c`` columns); ``ball``: the ball a KinOpt program measured
    (default: the artefact's only ball); ``poses``: the plan's (b, c) per pose number, which a
    DMIS file refers to."""
    if fmt not in FORMATS:
        raise CentresImportError(f"--format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    kind = detect(path, text) if fmt == "auto" else fmt
    if kind == "csv":
        return read_centres(path, text=text)
    if kind == "kinopt":
        if ball is None:
            if len(balls) != 1:
                raise CentresImportError(f"{path}: a KinOpt program measures one sphere and names "
                                         f"none: give the ball with --ball (one of "
                                         f"{', '.join(balls)})")
            ball = balls[0]
        if ball not in balls:
            raise CentresImportError(f"--ball: unknown ball {ball!r} (the artefact has "
                                     f"{', '.join(balls)})")
        cf = read_kinopt(path, ball, rotary, text=text)
    else:
        if poses is None:
            raise CentresImportError(f"{path}: a DMIS results file names poses by number "
                                     "(<ball>_P<pose>): give the plan they index with --plan")
        cf = read_dmis(path, balls, poses, text=text)
    check_rows(cf, cf.name)
    return cf
