"""What the centres importers share: bounded text reading and the rows they build."""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from pathlib import Path

from contracts.centres_file import MAX_CENTRE_ROWS, CentresFileError
from contracts.probing_log import CONTROL_RE, RANGES, byte_lines, decoded

VENDOR_FLOAT_RE = re.compile(
    r"[ \t]*[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?[ \t]*")
"""A number in an instrument's own file: ASCII decimal as instruments print it (a '+' sign,
'.5' and '5.' included), unlike rumba's own files (contracts.probing_log.FLOAT_RE)."""
MAX_IMPORT_LINES = 10 * MAX_CENTRE_ROWS
"""Ceiling on the non-blank lines of an instrument file (500 000), counted before anything is
parsed: a KinOpt record is 8 lines in the documentation and a DMIS sphere a statement or a
few, so even a file at the centre-row ceiling stays below 10 lines a centre (real files have
tens of centres). Bounds the parsing time of the largest file accepted to about 1.5 s."""


class CentresImportError(CentresFileError):
    """An instrument file that cannot be imported; the message names file, line and what was
    expected (a ``ConfigError``: one ``error:`` line in every command)."""


def text_lines(path: Path | str, text: str | None = None) -> Iterator[tuple[int, str]]:
    """(line number, text without line end) of a file, with the probing log's ceilings
    (a regular file, 64 MiB, 4 096 bytes per line, UTF-8 only), at most ``MAX_IMPORT_LINES``
    non-blank lines (counted first) and no control character but the tab."""
    with byte_lines(path, text, CentresImportError, noun="file", comments=None,
                    rows=(MAX_IMPORT_LINES, "lines (the importer's ceiling)")) as raw:
        for n, line in enumerate(decoded(raw, str(path), CentresImportError), start=1):
            line = line.rstrip("\r\n")
            bad = CONTROL_RE.search(line.replace("\t", " "))
            if bad:
                # A NUL or an escape is no part of an NC program or a DMIS file, comment or
                # not: the file is binary or damaged, and a comment is no place to hide it.
                raise CentresImportError(f"{path}: line {n}: column {bad.start() + 1}: control "
                                         f"character {bad.group()!r}: expected printable text")
            yield n, line


def continued(bodies: Iterable[tuple[int, str]], name: str, mark: str, what: str,
              max_lines: int, sep: str = "") -> Iterator[tuple[int, str]]:
    """(first line number, text) of each ``what`` (statement, block) in (line number, text)
    lines, a line ending with ``mark`` continuing on the next (``sep`` joins the parts)."""
    parts: list[str] = []
    start = 0
    for n, body in bodies:
        if not parts:
            start = n
        if body.endswith(mark):
            parts.append(body[:-len(mark)])
            if len(parts) > max_lines:
                raise CentresImportError(f"{name}: line {start}: a {what} continued over more "
                                         f"than {max_lines} lines")
            continue
        parts.append(body)
        yield start, sep.join(parts)
        parts = []
    if parts:
        raise CentresImportError(f"{name}: line {start}: the last {what} ends with '{mark}' "
                                 "(continued past the end of the file)")


def number(cell: str, where: str, what: str, column: str = "x_mm") -> float:
    """A plain ASCII decimal within the centres file's range for ``column``."""
    if not VENDOR_FLOAT_RE.fullmatch(cell):
        raise CentresImportError(f"{where}: {what}: expected a number, got {cell.strip()[:40]!r} "
                           "(ASCII decimal)")
    v = float(cell)
    lo, hi = RANGES[column]
    if not lo <= v <= hi:
        raise CentresImportError(f"{where}: {what}: {cell.strip()} outside [{lo:g}, {hi:g}]")
    return v
