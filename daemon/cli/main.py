"""The ``rumba`` command: subcommands are the modules of ``daemon.cli.commands`` (one file each).

Every subcommand module defines ``register(subparsers) -> None`` which adds its parser and sets
``func`` (returning an exit code). Expected failures (bad config, bad log, unreachable controller)
raise ``UserError`` or ``ConfigError`` and end as one ``error: …`` line with exit code 2.
Anything else is a defect of rumba-cnc, not of the input: it ends as one ``internal error`` line
with exit code 70 (EX_SOFTWARE) and the traceback goes to a crash file the line names, so no
exception type reaches an operator's terminal (RUMBA_DEBUG=1 lets it through for developers).
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
import tempfile
import time
import traceback
from collections.abc import Sequence
from pathlib import Path

import daemon.cli.commands
from contracts.yaml_files import ConfigError


class UserError(Exception):
    """An expected failure the operator can fix; printed as one line, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rumba",
        description="Five-axis machine verification with an uncalibrated ball artefact",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(daemon.cli.commands.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"daemon.cli.commands.{info.name}")
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UserError, ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # the last resort: a defect, reported without a traceback
        if os.environ.get("RUMBA_DEBUG"):
            raise
        crash = write_crash_file(e)
        print(f"error: internal error in rumba-cnc ({_one_line(e)}); this is a defect, "
              f"please report it with {crash}", file=sys.stderr)
        return EX_SOFTWARE


EX_SOFTWARE = 70  # sysexits.h: an internal software error, distinct from bad input (2)


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return (text[:200] + "…") if len(text) > 200 else (text or "no message")


def write_crash_file(e: BaseException) -> Path:
    """Write the traceback of ``e`` to a fresh file (RUMBA_CRASH_DIR or the temp dir)."""
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
