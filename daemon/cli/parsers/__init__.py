"""The arguments of every ``rumba`` subcommand, one light module each (no numpy)."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from typing import Any


class Parser(argparse.ArgumentParser):
    """A subcommand's parser whose ``later`` callbacks add the arguments defined in a heavy
    module (``rumba sim``'s ``simulators.serve``: asyncio) when it is first used — parse, help
    or usage — so building every parser for ``rumba --help`` does not import them."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.later: list[Callable[[argparse.ArgumentParser], None]] = []

    def _complete(self) -> None:
        while self.later:
            self.later.pop(0)(self)

    def parse_known_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                         namespace: argparse.Namespace | None = None
                         ) -> tuple[argparse.Namespace, list[str]]:
        self._complete()
        return super().parse_known_args(args, namespace)

    def format_usage(self) -> str:
        self._complete()
        return super().format_usage()

    def format_help(self) -> str:
        self._complete()
        return super().format_help()


def add_later(parser: argparse.ArgumentParser,
              add: Callable[[argparse.ArgumentParser], None]) -> None:
    """``add(parser)`` when ``parser`` is first used (a ``Parser``), else at once."""
    if isinstance(parser, Parser):
        parser.later.append(add)
    else:
        add(parser)


def names() -> list[str]:
    """The subcommands: this package's modules, sorted (no pkgutil: it imports inspect)."""
    import os

    return sorted(f.removesuffix(".py") for f in os.listdir(__path__[0])
                  if f.endswith(".py") and not f.startswith("_"))
