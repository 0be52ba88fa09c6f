"""The ``rumba`` command: subcommands are the modules of ``daemon.commands`` (one file each).

Every subcommand module defines ``register(subparsers) -> None`` which adds its parser and sets
``func`` (returning an exit code). Expected failures (bad config, bad log, unreachable controller)
raise ``UserError`` or ``ConfigError`` and end as one ``error: …`` line with exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence

import daemon.commands
from daemon.config import ConfigError


class UserError(Exception):
    """An expected failure the operator can fix; printed as one line, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rumba",
        description="Five-axis machine verification with an uncalibrated ball artefact",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(daemon.commands.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"daemon.commands.{info.name}")
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


if __name__ == "__main__":
    sys.exit(main())
