"""The ``rumba`` command: subcommands are the modules of ``daemon.cli.parsers`` (one file each).

Every parser module defines ``register(subparsers) -> None`` which adds its parser and sets
``func`` (returning an exit code). The parsers are light (argument definitions only): ``func``
imports the command's module of ``daemon.cli.commands`` when it runs, so ``rumba --help`` and
argument errors import neither numpy, scipy, rich nor the network stacks.
Expected failures (bad config, bad log, unreachable controller) raise ``UserError`` or
``ConfigError`` and end as one ``error: …`` line with exit code 2.
Anything else is a defect of rumba-cnc, not of the input: it ends as one ``internal error`` line
with exit code 70 (EX_SOFTWARE) and the traceback goes to a crash file the line names, so no
exception type reaches an operator's terminal (RUMBA_DEBUG=1 lets it through for developers).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import daemon.cli.parsers


class UserError(Exception):
    """An expected failure the operator can fix; printed as one line, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rumba",
        description="Five-axis machine verification with an uncalibrated ball artefact",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=daemon.cli.parsers.Parser)
    for name in daemon.cli.parsers.names():
        importlib.import_module(f"daemon.cli.parsers.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        preflight = getattr(args, "preflight", None)
        if preflight is not None:  # the arguments, before the command imports its work
            preflight(args)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        if expected(e):
            print(f"error: {e}", file=sys.stderr)
            return 2
        if os.environ.get("RUMBA_DEBUG"):  # the last resort: a defect, without a traceback
            raise
        crash = write_crash_file(e)
        print(f"error: internal error in rumba-cnc ({_one_line(e)}); this is a defect, "
              f"please report it with {crash}", file=sys.stderr)
        return EX_SOFTWARE


EX_SOFTWARE = 70  # sysexits.h: an internal software error, distinct from bad input (2)


def expected(e: BaseException) -> bool:
    """A ``UserError`` or a ``contracts.yaml_files.ConfigError`` (looked up, not imported: a
    ConfigError was raised only if its module is loaded, and the parser stays without pydantic)."""
    yaml_files = sys.modules.get("contracts.yaml_files")
    return isinstance(e, UserError) or (yaml_files is not None
                                         and isinstance(e, yaml_files.ConfigError))


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return (text[:200] + "…") if len(text) > 200 else (text or "no message")


def write_crash_file(e: BaseException) -> Path:
    """Write the traceback of ``e`` to a fresh file (RUMBA_CRASH_DIR or the temp dir)."""
    import tempfile  # only on a defect: neither is needed by a command that works
    import traceback

    directory = Path(os.environ.get("RUMBA_CRASH_DIR") or tempfile.gettempdir())
    stamp = time.strftime("%Y%m%dT%H%M%S")
    try:
        fd, name = tempfile.mkstemp(prefix=f"rumba-crash-{stamp}-", suffix=".txt",
                                    dir=directory)
    except OSError:
        fd, name = tempfile.mkstemp(prefix=f"rumba-crash-{stamp}-", suffix=".txt")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write("".join(traceback.format_exception(e)))
    return Path(name)


if __name__ == "__main__":
    sys.exit(main())
