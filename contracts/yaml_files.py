"""The one YAML reader of every configuration schema: bounded, UTF-8, safe, one-line errors."""

from __future__ import annotations

import ipaddress
import re
import types
import typing
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    ValidationError,
    ValidationInfo,
    field_validator,
)

from contracts.input_files import read_bounded

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


class _DuplicateKey(Exception):
    def __init__(self, key: object, line: int, first: int) -> None:
        super().__init__(key, line, first)
        self.key, self.line, self.first = key, line, first


_BOOL_TAG = "tag:yaml.org,2002:bool"


class _Loader(yaml.SafeLoader):
    """The safe loader, stopping at MAX_YAML_DEPTH while composing (not after scanning 50 000
    brackets and overflowing the stack), refusing a key given twice in one mapping (PyYAML
    keeps the last silently: an edit appended below an old value would win unseen), and with
    YAML 1.2 booleans: only true/false (YAML 1.1 also reads yes/no/on/off, so ``country: no``
    or ``mode: off`` would turn into a boolean)."""

    _depth = 0

    yaml_implicit_resolvers = {
        first: [(tag, rx) for tag, rx in resolvers if tag != _BOOL_TAG]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # '<<': merged keys may be
                    continue  # overridden by the mapping's own, as YAML intends
                key = self.construct_object(key_node, deep=True)
                line = key_node.start_mark.line + 1
                try:
                    if key in seen:
                        raise _DuplicateKey(key, line, seen[key])
                    seen[key] = line
                except TypeError:  # an unhashable key: the base constructor names it
                    continue
        return super().construct_mapping(node, deep=deep)

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH + 1:
                raise _TooDeep
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _construct_bool(loader: _Loader, node: Any) -> bool:
    """An explicit ``!!bool`` as strict as the implicit one (PyYAML's takes yes/on, and ends
    in a bare KeyError on anything else)."""
    value = str(loader.construct_scalar(node))
    if value.lower() not in ("true", "false"):
        raise yaml.constructor.ConstructorError(
            None, None, f"expected true or false, got {_one_line(value, 40)!r}", node.start_mark)
    return value.lower() == "true"


_Loader.add_implicit_resolver(_BOOL_TAG, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
                              list("tTfF"))
_Loader.add_constructor(_BOOL_TAG, _construct_bool)


def read_yaml(path: Path | str) -> Any:
    """The one YAML reader of every schema: size ceiling (MAX_YAML_BYTES), UTF-8, safe loader,
    nesting and value-count ceilings, a regular file only (a FIFO would block), no key twice
    in a mapping, booleans only true/false; any failure is one ``ConfigError`` line naming the
    file."""
    path = Path(path)
    raw = read_bounded(path, ConfigError, MAX_YAML_BYTES, "configuration file")
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
    except _DuplicateKey as e:
        raise ConfigError(f"{path}: line {e.line}: key '{_one_line(e.key, 40)}' given twice "
                          f"(first on line {e.first}); a key is given once per mapping") from None
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


def _is_bool_field(annotation: Any) -> bool:
    """``bool`` or ``bool | None`` (the only boolean shapes the schemas use)."""
    if annotation is bool:
        return True
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        args = typing.get_args(annotation)
        return bool in args and all(a in (bool, type(None)) for a in args)
    return False


class StrictModel(BaseModel):
    """The base of every file schema: unknown keys are errors, values immutable, and
    ``allow_inf_nan=False`` refuses .nan / .inf / 1e400 in every float. Booleans are strict:
    only a YAML true/false (pydantic would take 'yes', 'on', 1, '1' — ``unattended: 'yes'``
    would switch on unattended compensation from a quoted string)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _strict_bool(cls, v: Any, info: ValidationInfo) -> Any:
        field = cls.model_fields.get(info.field_name or "")
        if field is not None and _is_bool_field(field.annotation) and not isinstance(v, bool) \
                and not (v is None and field.annotation is not bool):
            raise ValueError(f"expected true or false, got {_one_line(repr(v), 40)}")
        return v


_LABEL = r"[A-Za-z0-9_](?:[A-Za-z0-9_-]{0,61}[A-Za-z0-9_])?"
_HOST = re.compile(rf"(?=.{{1,253}}\Z){_LABEL}(?:\.{_LABEL})*\.?")


def host_name(v: str) -> str:
    """A host to connect to or listen on: an IPv4 or IPv6 address, or a DNS name (RFC 1123
    labels, '_' tolerated as some site DNS uses it); never empty, no blanks, no scheme or
    port."""
    try:
        ipaddress.ip_address(v)
        return v
    except ValueError:
        pass
    if not _HOST.fullmatch(v):
        raise ValueError(f"{v!r}: expected a host name or an IP address (e.g. broker.local, "
                         "192.168.1.20, ::1)")
    return v


HostName = Annotated[str, AfterValidator(host_name)]
"""A configuration field naming a host (``host_name``)."""


def validate_file(model: type[BaseModel], path: Path | str, data: Any) -> Any:
    """``data`` (read from ``path``) validated by ``model``; one ``ConfigError`` line per
    problem, naming the file and the key."""
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys at top level")
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise ConfigError(format_validation(path, e)) from None
