"""Bounded reading of the files rumba is given (probing logs, centres files, instrument files,
YAML): regular files only, a byte ceiling, a line-length ceiling, and a row ceiling checked
before anything is parsed. Every refusal is one line naming the file (and the line).

Why each bound: a FIFO blocks ``open()`` and ``read()`` until a writer comes (forever, for an
operator who typed the wrong path); a character device such as ``/dev/zero`` never ends and has
no line breaks, so reading it "line by line" fills the memory; a file of a million valid rows is
refused by the row ceiling only after each row was parsed (minutes), while counting its lines
takes milliseconds.
"""

from __future__ import annotations

import io
import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISDIR, "a directory"),
          (stat.S_ISSOCK, "a socket"))


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def open_regular(path: Path | str, error: type[Exception]) -> BinaryIO:
    """``path`` opened for binary reading, or one ``error`` line: a missing or unreadable file,
    or anything but a regular file (FIFO, device, directory, socket), refused before a byte is
    read. Opened non-blocking and checked again on the open descriptor, so a FIFO swapped in
    between the two checks cannot block either."""
    name = str(path)
    check_regular(path, error)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as e:
        raise error(f"{name}: cannot read: {e.strerror or e}") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise error(f"{name}: is {_kind(mode)}: expected a regular file")
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def check_regular(path: Path | str, error: type[Exception]) -> None:
    """One ``error`` line unless ``path`` is a regular file that exists (by its metadata alone,
    nothing opened): the refusal ``open_regular`` gives, for a command to give it before it
    loads anything (its argument checks)."""
    name = str(path)
    try:
        mode = os.stat(path).st_mode
    except OSError as e:
        raise error(f"{name}: cannot read: {e.strerror or e}") from None
    except ValueError as e:  # a NUL in the path
        raise error(f"{name}: cannot read: {e}") from None
    if not stat.S_ISREG(mode):
        raise error(f"{name}: is {_kind(mode)}: expected a regular file")


def read_bounded(path: Path | str, error: type[Exception], max_bytes: int,
                 what: str = "file") -> bytes:
    """The bytes of the regular file ``path`` (``open_regular``), refused beyond ``max_bytes``
    after reading no more than one byte over: one ``error`` line, "not a ``what``"."""
    try:
        with open_regular(path, error) as f:
            raw = f.read(max_bytes + 1)
    except OSError as e:
        raise error(f"{path}: cannot read: {e.strerror or e}") from None
    if len(raw) > max_bytes:
        raise error(f"{path}: larger than {max_bytes} bytes: not a {what}")
    return raw


def bounded_lines(f: BinaryIO, name: str, error: type[Exception], max_bytes: int,
                  max_line: int, noun: str = "file") -> Iterator[bytes]:
    """The byte lines of ``f``, each read with ``readline(max_line + 1)`` so that a line longer
    than ``max_line`` bytes is refused after reading that much (not after reading it all), and
    the file refused once its lines add up to more than ``max_bytes``."""
    total, n = 0, 0
    while True:
        raw = f.readline(max_line + 1)
        if not raw:
            return
        n += 1
        total += len(raw)
        if total > max_bytes:
            raise error(f"{name}: line {n}: the {noun} is larger than {max_bytes} bytes (the "
                        "reader's ceiling; one run is far smaller)")
        if len(raw) > max_line:
            raise error(f"{name}: line {n}: longer than {max_line} bytes")
        yield raw


def count_rows(f: BinaryIO, name: str, error: type[Exception], *, max_bytes: int,
               max_line: int, max_rows: int, headers: int, what: str, noun: str = "file",
               comments: bytes | None = b"#") -> None:
    """Refuse, before any parsing, a file with more than ``max_rows`` data rows: non-blank lines
    not starting with ``comments`` (``#``: comments, magic lines, preamble keys; None: every
    non-blank line counts), less ``headers`` header lines. An upper bound of what the parser
    would accept (a row spread over lines by quotes is refused by the parser anyway), so a
    file passing here is not refused for its size later; the line named is the one the
    streaming check would name. Rewinds ``f``."""
    rows = -headers
    for n, raw in enumerate(bounded_lines(f, name, error, max_bytes, max_line, noun), start=1):
        s = raw.strip()
        if s and not (comments and s.startswith(comments)):
            rows += 1
            if rows > max_rows:
                raise error(f"{name}: line {n}: more than {max_rows} {what}")
    f.seek(0)


@contextmanager
def opened(path: Path | str, text: str | None, error: type[Exception], *, max_bytes: int,
           note: str = "") -> Iterator[BinaryIO]:
    """The file (``text``'s bytes if given) for bounded reading; a regular file whose size is
    beyond ``max_bytes`` (``note`` added) is refused before reading, and an ``OSError`` while
    reading ends as one ``error`` line as well."""
    name = str(path)
    f = (io.BytesIO(text.encode("utf-8", "surrogatepass")) if text is not None
         else open_regular(path, error))
    try:
        with f:
            size = os.fstat(f.fileno()).st_size if text is None else 0
            if size > max_bytes:
                raise error(f"{name}: {size} bytes, more than the reader's ceiling of "
                            f"{max_bytes}{note}")
            yield f
    except OSError as e:
        raise error(f"{name}: cannot read: {e.strerror or e}") from None
