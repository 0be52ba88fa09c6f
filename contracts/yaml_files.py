"""The one YAML reader of every configuration schema: bounded, UTF-8, safe, one-line errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

MAX_YAML_BYTES = 1 << 20
"""Ceiling on the size of a configuration file (1 MiB; the shipped ones are under 2 kB)."""
MAX_YAML_NODES = 100_000
"""Ceiling on the values in one file, aliases counted each time they are used (a YAML "billion
laughs" file is small on disk and huge once expanded)."""
MAX_YAML_DEPTH = 32
"""Ceiling on the nesting of lists and mappings (the schemas need 5)."""

class ConfigError(ValueError):
    """A configuration file is unreadable or invalid; the message is one line for the operator."""


def _one_line(text: object, limit: int = 200) -> str:
    """A user-supplied fragment made printable on one line (keys, parser messages)."""
    s = str(text)
    if not s.isprintable() or len(s) > limit:
        s = repr(s[:limit])
    return s


def _check_shape(data: Any, path: Path | str) -> None:
    """Refuse too deep or (with aliases expanded) too many values: iterative, so a deep file
    cannot exhaust the stack here or later in validation."""
    stack: list[tuple[Any, int, str]] = [(data, 0, "")]
    count = 0
    while stack:
        node, depth, key = stack.pop()
        count += 1
        if count > MAX_YAML_NODES:
            raise ConfigError(f"{path}: {key or '<top>'}: more than {MAX_YAML_NODES} values "
                              "(aliases counted each time they are used)")
        if isinstance(node, dict | list):
            if depth >= MAX_YAML_DEPTH:
                raise ConfigError(f"{path}: {key or '<top>'}: nested deeper than "
                                  f"{MAX_YAML_DEPTH} levels")
            items = node.items() if isinstance(node, dict) else enumerate(node)
            for k, v in items:
                sub = f"{key}.{_one_line(k, 40)}" if key else _one_line(k, 40)
                stack.append((v, depth + 1, sub))


class _TooDeep(Exception):
    pass


class _Loader(yaml.SafeLoader):
    """The safe loader, stopping at MAX_YAML_DEPTH while composing (not after scanning 50 000
    brackets and overflowing the stack)."""

    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH + 1:
                raise _TooDeep
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def read_yaml(path: Path | str) -> Any:
    """The one YAML reader of every schema: size ceiling (MAX_YAML_BYTES), UTF-8, safe loader,
    nesting and value-count ceilings; any failure is one ``ConfigError`` line naming the file."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_YAML_BYTES + 1)
    except (OSError, ValueError) as e:  # ValueError: a NUL in the path
        raise ConfigError(f"{path}: cannot read: {getattr(e, 'strerror', None) or e}") from None
    if len(raw) > MAX_YAML_BYTES:
        raise ConfigError(f"{path}: larger than {MAX_YAML_BYTES} bytes: not a configuration file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: byte {e.start}: not UTF-8 text") from None
    try:
        loader = _Loader(text)
        try:
            data = loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" line {mark.line + 1} column {mark.column + 1}" if mark else ""
        problem = _one_line(getattr(e, "problem", None) or e)
        raise ConfigError(f"{path}:{where}: not valid YAML: {problem}") from None
    except (RecursionError, _TooDeep):
        raise ConfigError(f"{path}: nested deeper than {MAX_YAML_DEPTH} levels") from None
    except (ValueError, OverflowError) as e:  # an integer of > 4300 digits, a bad timestamp
        raise ConfigError(f"{path}: not a valid value: {_one_line(e)}") from None
    _check_shape(data, path)
    return data





def format_validation(path: Path | str, err: ValidationError) -> str:
    """One line per problem: ``file: key.path: message``."""
    parts = []
    for e in err.errors():
        loc = ".".join(_one_line(x, 40) for x in e["loc"]
                       if not str(x).startswith(("function-after",)))
        msg = _one_line(e["msg"].removeprefix("Value error, "), 300)
        if e["type"] == "extra_forbidden":
            msg = "unknown key (not in the schema; check spelling)"
        parts.append(f"{path}: {loc or '<top>'}: {msg}")
    return "; ".join(parts)


class StrictModel(BaseModel):
    """The base of every file schema: unknown keys are errors, values immutable, and
    ``allow_inf_nan=False`` refuses .nan / .inf / 1e400 in every float."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def validate_file(model: type[BaseModel], path: Path | str, data: Any) -> Any:
    """``data`` (read from ``path``) validated by ``model``; one ``ConfigError`` line per
    problem, naming the file and the key."""
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys at top level")
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise ConfigError(format_validation(path, e)) from None
