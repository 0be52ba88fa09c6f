"""A command's argument checks that need nothing heavy, run before it imports its work.

Every parser's ``preflight`` (``set_defaults(preflight=…)``) runs before its ``func``: the
input files exist and are regular files, the output folders exist, the values parse. A wrong
path or value is answered before numpy, pydantic, scipy or a network stack is loaded — in a
tenth of a second on a busy shop PC, not after seconds of imports. The messages are those the
command would give later (the same functions give them), so nothing an operator or a script
reads changes. What needs a setup file to judge (a link name of this machine, an effect on one
of its axes) is checked by the command once the file is read.
"""

from __future__ import annotations

import argparse
import errno
import math
import os
from collections.abc import Iterable, Sequence


def user_error(msg: str) -> Exception:
    """The ``UserError`` (one ``error:`` line, exit 2) of ``msg``."""
    from daemon.cli.main import UserError  # late import: main imports the parsers

    return UserError(msg)


def inputs(args: argparse.Namespace, names: Iterable[str]) -> None:
    """Each of the attributes ``names`` that is set names an existing regular file."""
    from contracts.input_files import check_regular  # stdlib only

    for name in names:
        value = getattr(args, name, None)
        for path in value if isinstance(value, list) else [value]:
            if path is not None:
                check_regular(path, user_error)


def output_folder(path: object, prefix: str) -> None:
    """The folder ``path`` is to be written in exists and is one: else ``prefix: cannot write:
    <reason>`` as the write would fail (a file that cannot be written for another reason —
    permissions, a full disk — fails when written, with the same message)."""
    if path is None:
        return
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))  # type: ignore[arg-type]
    if not os.path.isdir(folder):
        reason = os.strerror(errno.ENOTDIR if os.path.exists(folder) else errno.ENOENT)
        raise user_error(f"{prefix}: cannot write: {reason}")


def parse_poses(text: str | None) -> list[int]:
    """``--validate-poses``: a comma list of pose numbers."""
    if not text:
        return []
    try:
        return sorted({int(x) for x in text.split(",") if x.strip()})
    except ValueError:
        raise user_error(f"--validate-poses: expected a comma list of pose numbers as in the "
                          f"log's pose column, got {text!r}") from None


def parse_repeatability(text: str | None) -> list[float] | None:
    """``--repeatability-um``: one or three positive numbers (x, y, z), as three."""
    if not text:
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) not in (1, 3) or not all(math.isfinite(x) and x > 0 for x in v):
        raise user_error(f"--repeatability-um: expected one or three positive numbers "
                          f"(x,y,z centre std in µm), got {text!r}")
    return v * 3 if len(v) == 1 else v


def parse_families(text: str | None, families: Sequence[str]) -> tuple[str, ...]:
    """``--families``: a comma list of effect families (all of ``families`` when empty)."""
    if not text:
        return tuple(families)
    names = tuple(x.strip() for x in text.split(",") if x.strip())
    bad = [x for x in names if x not in families]
    if bad or not names:
        raise user_error(f"--families: unknown {bad or [text]}; expected a comma list of "
                          f"{', '.join(families)}")
    return names
