"""File names built from data (run ids, ball ids …) are joined to their directory only here."""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath, PureWindowsPath

from contracts.yaml_files import ConfigError


class UnsafePathError(ConfigError):
    """A name taken from data would leave its directory; one line for the operator (a
    ConfigError subclass so that ``rumba`` prints it as ``error: …``, exit 2)."""


def plain_name(name: str, where: str = "") -> str:
    """``name`` unchanged if it is one plain file name: not empty, '.' or '..', no separator
    (neither '/' nor '\\', so a log written on Windows cannot smuggle one), no NUL or control
    character, not absolute or drive-qualified. Else ``UnsafePathError`` naming ``where``."""
    bad = (not isinstance(name, str) or not name or name in (".", "..")
           or "/" in name or "\\" in name or os.sep in name
           or (os.altsep is not None and os.altsep in name)
           or any(ord(ch) < 32 or ord(ch) == 127 for ch in name)
           or PurePosixPath(name).is_absolute() or PureWindowsPath(name).drive != "")
    if bad:
        raise UnsafePathError(f"{where or 'file name'}: refusing {name!r}: expected one plain "
                              "file name (no '/', '\\', '..' or control character)")
    return name


def contained_path(base: Path | str, name: str) -> Path:
    """``base / name``, refused unless ``name`` is a plain file name (``plain_name``) and the
    result, with symlinks resolved, is inside ``base`` (a planted symlink pointing elsewhere
    is refused too)."""
    base = Path(base)
    path = base / plain_name(name, str(base))
    if not path.resolve().is_relative_to(base.resolve()):
        raise UnsafePathError(f"{base}: refusing file name {name!r}: it resolves to "
                              f"{path.resolve()}, outside this directory")
    return path
