"""Where the daemon's log goes and how much of it: a message that repeats is counted, not
repeated (``RepeatFilter``), and a log file rotates at a size (``setup_logging``), so no fault
in the daemon or a library can fill a disk. Under systemd the log is stderr, i.e. the journal,
which journald rotates and rate-limits itself; the repeat filter applies there too."""

from __future__ import annotations

import logging
import logging.handlers
import re
import sys
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
REPEAT_WINDOW_S = 60.0
"""A message seen again within this time of its last logged occurrence is counted, not
logged; the next one after it is logged with the count of those held back."""
MAX_KEYS = 2048
"""Distinct messages remembered (least recently seen forgotten first): bounds the filter's memory
whatever the daemon logs."""
LOG_MAX_BYTES = 10 * 1024 * 1024
LOG_BACKUPS = 5
"""A log file rotates at ``LOG_MAX_BYTES`` and keeps ``LOG_BACKUPS`` older files: at most
6 × 10 MiB on disk by default."""
NOISY = ("asyncua", "pymodbus", "aiohttp.access")
"""Libraries whose INFO lines say nothing an operator needs (one per request or packet)."""


@dataclass
class _Seen:
    last_logged: float
    held: int = 0
    first_held: float = 0.0


_DIGITS = re.compile(r"[0-9]+")


def _key(record: logging.LogRecord) -> tuple:
    """What makes two records "the same message": logger, level, the message's text with every
    number as '#' (a flood of one fault rarely repeats a count or a position exactly, while a
    run's phases — one template, other words — stay distinct) and, with an exception, its type
    and where it was raised."""
    where: tuple = ()
    if record.exc_info and record.exc_info[0] is not None:
        tb = record.exc_info[2]
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        frame = (tb.tb_frame.f_code.co_filename, tb.tb_lineno) if tb is not None else ()
        where = (record.exc_info[0].__name__, *frame)
    try:
        text = record.getMessage()
    except Exception:  # a record whose arguments do not fit: its template then
        text = str(record.msg)
    return record.name, record.levelno, _DIGITS.sub("#", text[:300]), where


class RepeatFilter(logging.Filter):
    """Lets the first of a run of identical messages through, holds back (and counts) those that
    follow within ``window_s`` of the last one logged, and logs the next one after that with the
    count, as one line without its traceback. ``flush`` logs the counts still held (at exit)."""

    def __init__(self, window_s: float = REPEAT_WINDOW_S, max_keys: int = MAX_KEYS,
                 clock: object = time.monotonic) -> None:
        super().__init__()
        self.window_s = window_s
        self.max_keys = max_keys
        self._clock = clock
        self._seen: OrderedDict[tuple, _Seen] = OrderedDict()
        self._lock = threading.Lock()  # records come from worker threads too
        self.held_total = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "rumba_repeat_summary", False):
            return True
        now = self._clock()  # type: ignore[operator]
        key = _key(record)
        with self._lock:
            seen = self._seen.get(key)
            if seen is None:
                self._seen[key] = _Seen(now)
                if len(self._seen) > self.max_keys:
                    self._seen.popitem(last=False)
                return True
            self._seen.move_to_end(key)
            if now - seen.last_logged < self.window_s:
                if not seen.held:
                    seen.first_held = now
                seen.held += 1
                self.held_total += 1
                return False
            held, since = seen.held, seen.first_held
            seen.last_logged, seen.held = now, 0
        if held:
            _mark_repeat(record, held, now - since)
        return True

    def flush(self, logger: logging.Logger | None = None) -> int:
        """Log one line per message with repeats still held back; return how many lines."""
        out = logger or logging.getLogger("rumba")
        with self._lock:
            pending = [(k, s.held) for k, s in self._seen.items() if s.held]
            for _, s in self._seen.items():
                s.held = 0
        for (name, level, msg, where), held in pending:
            text = msg.split("\n", 1)[0][:200]
            out.log(level, "%s: %r%s was repeated %d more times (numbers as #), not logged",
                    name, text, f" ({where[0]})" if where else "", held,
                    extra={"rumba_repeat_summary": True})
        return len(pending)


def _mark_repeat(record: logging.LogRecord, held: int, span_s: float) -> None:
    """Turn the record into its one-line repeat summary (the traceback was logged the first
    time)."""
    if record.exc_info and record.exc_info[0] is not None:
        record.msg = f"{record.msg} [{record.exc_info[0].__name__}: {record.exc_info[1]}]"
    record.exc_info, record.exc_text, record.stack_info = None, None, None
    record.msg = f"{record.msg} (repeated {held} times in the last {span_s:.0f} s, not logged)"


class OneLineFormatter(logging.Formatter):
    """For a person's terminal (``rumba verify``): ``warning: logger: message`` and, instead of
    a traceback, the exception's type and text on the same line."""

    def format(self, record: logging.LogRecord) -> str:
        text = f"{record.levelname.lower()}: {record.name}: {record.getMessage()}"
        if record.exc_info and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            text += f" ({type(exc).__name__}: {exc})" if str(exc) else f" ({type(exc).__name__})"
        return text


def setup_terminal_logging(level: int, tracebacks: bool = False) -> RepeatFilter:
    """Logging of a command a person watches: one line per record (tracebacks only when
    ``tracebacks``: RUMBA_DEBUG), repeats counted; like ``setup_logging`` it leaves a root
    logger with someone else's handlers alone."""
    root = logging.getLogger()
    repeats = RepeatFilter()
    if any(not getattr(h, "rumba_handler", False) for h in root.handlers):
        return repeats
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s: %(name)s: %(message)s")
                         if tracebacks else OneLineFormatter())
    handler.addFilter(repeats)
    handler.setLevel(level)  # a record a filter lowered (asyncua's reconnect noise) stays out
    handler.rumba_handler = True  # type: ignore[attr-defined]
    for old in list(root.handlers):
        root.removeHandler(old)
        old.close()
    root.addHandler(handler)
    root.setLevel(level)
    return repeats


def setup_logging(level: int, log_file: Path | None = None,
                  max_bytes: int = LOG_MAX_BYTES, backups: int = LOG_BACKUPS) -> RepeatFilter:
    """The daemon's logging: to ``log_file`` (rotated at ``max_bytes``, ``backups`` kept) or to
    stderr (the journal under systemd), behind a ``RepeatFilter``, returned for its ``flush`` at
    exit. Like ``logging.basicConfig``, it leaves a root logger that already has handlers of
    someone else's (an embedding program, pytest) as it is."""
    root = logging.getLogger()
    repeats = RepeatFilter()
    if any(not getattr(h, "rumba_handler", False) for h in root.handlers):
        return repeats
    handler: logging.Handler
    if log_file is not None:
        log_file.parent.mkdir(parents=True, exist_ok=True)
        handler = logging.handlers.RotatingFileHandler(log_file, maxBytes=max_bytes,
                                                       backupCount=backups, encoding="utf-8")
    else:
        handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(FORMAT))
    handler.addFilter(repeats)
    handler.setLevel(level)
    handler.rumba_handler = True  # type: ignore[attr-defined]
    for old in list(root.handlers):
        root.removeHandler(old)
        old.close()
    root.addHandler(handler)
    root.setLevel(level)
    for noisy in NOISY:
        logging.getLogger(noisy).setLevel(logging.WARNING)
    logging.captureWarnings(True)
    return repeats
