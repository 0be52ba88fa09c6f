"""Line-level reading shared by the probing log, the centres CSV and the instrument importers:
bounded byte lines, UTF-8 text, data rows with a ceiling, duplicate keys and seq gaps, and the
error and warning classes they raise (``contracts.probing_log`` re-exports them)."""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from contracts.input_files import bounded_lines, count_rows, opened
from contracts.yaml_files import ConfigError

MAX_LOG_BYTES = 64 * 2**20
MAX_LINE_BYTES = 4096
CONTROL_RE = re.compile(r"[\x00-\x1f\x7f]")
# the control characters Python's str.strip() removes as if they were spaces
STRIPPED_CONTROL_RE = re.compile(r"[\x0b\x0c\x1c-\x1f]")


class ProbeLogError(ConfigError):
    """The log cannot be used as is; the message names file, line and column (or ball/pose);
    a ``ConfigError``, so every ``rumba`` command ends on it with one ``error:`` line."""


class ProbeLogWarning(UserWarning):
    """Something was left out of the analysis (e.g. an incomplete ball-pose)."""


def decoded(raw_lines: Iterable[bytes], name: str,
            error: type[ProbeLogError] | None = None, *, printable: bool = False
            ) -> Iterator[str]:
    """Bytes lines (bounded: ``byte_lines``) → text lines, refusing non-UTF-8; ``printable``:
    and the control characters str.strip() takes away (\\x0b, \\x0c, \\x1c-\\x1f) anywhere
    on the line: the checks after strip cells, keys and the first line, and would read such a
    character as if it were not there (found by tests/test_inputs_fuzz_surfaces.py;
    the other control characters are refused by those checks, naming the column)."""
    err = error or ProbeLogError
    for n, raw in enumerate(raw_lines, start=1):
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as e:
            raise err(f"{name}: line {n}: not UTF-8 text (byte {e.start + 1} of the "
                      f"line is {raw[e.start:e.start + 1]!r})") from None
        if printable and (bad := STRIPPED_CONTROL_RE.search(text)):
            where = " in a comment" if text.startswith("##") else ""
            raise err(f"{name}: line {n}: a control character (U+{ord(bad.group()):04X})"
                      f"{where}: expected printable text")
        yield text[1:] if n == 1 and text.startswith("\ufeff") else text


def duplicate_key(keys: np.ndarray, lines: np.ndarray) -> tuple[int, int] | None:
    """(first line, repeating line) of the earliest repeated key row, or None."""
    order = np.lexsort(keys.T[::-1])  # stable: equal keys stay in file order
    k = keys[order]
    same = np.flatnonzero(np.all(k[1:] == k[:-1], axis=1))
    if same.size == 0:
        return None
    j = int(same[np.argmin(lines[order[same + 1]])])  # the earliest repeating line
    start = j
    while start > 0 and np.all(k[start - 1] == k[j]):
        start -= 1
    return int(lines[order[start]]), int(lines[order[j + 1]])


@contextmanager
def byte_lines(path: Path | str, text: str | None, error: type[ProbeLogError] = ProbeLogError,
               note: str = "", *, rows: tuple[int, str] | None = None, noun: str = "log",
               comments: bytes | None = b"#") -> Iterator[Iterable[bytes]]:
    """The file's byte lines (``text``'s if given), bounded (``contracts.input_files``): a
    regular file only, at most ``MAX_LOG_BYTES`` (``note`` added to the message) and
    ``MAX_LINE_BYTES`` a line; ``rows`` = (ceiling, what): more data rows than the ceiling are
    refused before any is parsed (lines starting with ``comments`` are not rows). An
    ``OSError`` in the block is one ``error`` line too."""
    name = str(path)
    with opened(path, text, error, max_bytes=MAX_LOG_BYTES, note=note) as f:
        if rows is not None:
            count_rows(f, name, error, max_bytes=MAX_LOG_BYTES, max_line=MAX_LINE_BYTES,
                       max_rows=rows[0], headers=1 if comments else 0, what=rows[1],
                       noun=noun, comments=comments)
        yield bounded_lines(f, name, error, MAX_LOG_BYTES, MAX_LINE_BYTES, noun)


def data_rows(reader: Iterator[list[str]], name: str, columns: int, offset: int, ceiling: int,
              error: type[ProbeLogError], what: str) -> Iterator[tuple[int, list[str]]]:
    """(file line, cells) of the non-blank rows; a wrong cell count or row ``ceiling`` errs."""
    count = 0
    for cells in reader:
        lineno = offset + reader.line_num  # type: ignore[attr-defined]
        if not cells or (len(cells) == 1 and not cells[0].strip()):
            continue
        if len(cells) != columns:
            raise error(f"{name}: line {lineno}: expected {columns} columns, got {len(cells)}")
        if count >= ceiling:
            raise error(f"{name}: line {lineno}: more than {ceiling} {what}")
        count += 1
        yield lineno, cells


def seq_gaps(seq: np.ndarray) -> str:
    """The ranges missing between one run's ``seq`` numbers, the first eight named ('' if none)."""
    v = np.sort(seq)
    missing = [f"{v[k] + 1}" if v[k + 1] - v[k] == 2 else f"{v[k] + 1}–{v[k + 1] - 1}"
               for k in np.flatnonzero(np.diff(v) > 1)]
    return ", ".join(missing[:8]) + (f" and {len(missing) - 8} more gaps"
                                     if len(missing) > 8 else "")
