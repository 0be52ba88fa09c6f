"""What the centres importers share: bounded text reading and the rows they build."""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path

from contracts.centres_file import CentresFileError
from contracts.probing_log import _FLOAT_RE, _RANGES, MAX_LOG_BYTES, ProbeLogError, _decoded


class CentresImportError(CentresFileError):
    """An instrument file that cannot be imported; the message names file, line and what was
    expected (a ``ConfigError``: one ``error:`` line in every command)."""


def text_lines(path: Path | str, text: str | None = None) -> Iterator[tuple[int, str]]:
    """(line number, text without line end) of a file, with the probing log's ceilings
    (64 MiB, 4 096 bytes per line, UTF-8 only)."""
    name = str(path)
    try:
        if text is not None:
            raw: io.BufferedIOBase = io.BytesIO(text.encode("utf-8", "surrogatepass"))
        else:
            raw = open(path, "rb")  # noqa: SIM115  # closed below, also on errors
    except OSError as e:
        raise CentresImportError(f"{name}: cannot read: {e.strerror or e}") from None
    with raw:
        try:
            size = os.fstat(raw.fileno()).st_size if text is None else 0
        except OSError as e:
            raise CentresImportError(f"{name}: cannot read: {e.strerror or e}") from None
        if size > MAX_LOG_BYTES:
            raise CentresImportError(f"{name}: {size} bytes, more than the reader's ceiling of "
                               f"{MAX_LOG_BYTES}")
        try:
            for n, line in enumerate(_decoded(raw, name), start=1):
                yield n, line.rstrip("\r\n")
        except OSError as e:
            raise CentresImportError(f"{name}: cannot read: {e.strerror or e}") from None
        except CentresImportError:
            raise
        except ProbeLogError as e:  # the probing log's line reader (size, length, UTF-8)
            raise CentresImportError(str(e)) from None


def number(cell: str, where: str, what: str, column: str = "x_mm") -> float:
    """A plain ASCII decimal within the centres file's range for ``column``."""
    if not _FLOAT_RE.fullmatch(cell):
        raise CentresImportError(f"{where}: {what}: expected a number, got {cell.strip()[:40]!r} "
                           "(ASCII decimal)")
    v = float(cell)
    lo, hi = _RANGES[column]
    if not lo <= v <= hi:
        raise CentresImportError(f"{where}: {what}: {cell.strip()} outside [{lo:g}, {hi:g}]")
    return v
