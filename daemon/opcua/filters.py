"""The ContentFilter of GetResultIdListFiltered (OPC 10000-4 §7.7), checked whole before any
run is looked at, then evaluated once per element and run.

A filter is a list of elements; element 0 is the root, an ``ElementOperand`` points to another
element. OPC 10000-4 §7.7.4.2 makes an ElementOperand's index valid only when it is greater
than the index of the element it is part of: a filter is then a DAG, never a cycle, and its
elements are evaluated from the last to the first, each once per run (a chain of elements that
each use the next one twice is 2^depth evaluations when followed recursively, and blocked the
daemon's event loop for minutes at depth 22). Size and depth are bounded; every operand's type
is checked against the field it is compared with before the first run. Anything outside the
supported subset is a ``FilterError`` (the method's Error −3)."""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from asyncua import ua

MAX_ELEMENTS = 64
MAX_DEPTH = 16
"""Elements per filter, and the longest chain of ElementOperands from the root."""
FIELDS = {"ResultId": str, "ResultState": int, "ResultEvaluation": int,
          "CreationTime": dt.datetime, "PartId": str, "JobId": str}
"""The ResultMetaData fields a filter can name, with the type of their values."""
_COMPARE: dict[Any, Callable[[Any, Any], bool]] = {
    ua.FilterOperator.Equals: lambda a, b: a == b,
    ua.FilterOperator.GreaterThan: lambda a, b: a > b,
    ua.FilterOperator.LessThan: lambda a, b: a < b,
    ua.FilterOperator.GreaterThanOrEqual: lambda a, b: a >= b,
    ua.FilterOperator.LessThanOrEqual: lambda a, b: a <= b}
_LOGIC = {ua.FilterOperator.And: 2, ua.FilterOperator.Or: 2, ua.FilterOperator.Not: 1}


class FilterError(ValueError):
    """A ContentFilter outside the supported subset (the method answers ERR_FILTER)."""


@dataclass(frozen=True)
class _Lit:
    value: Any


@dataclass(frozen=True)
class _Field:
    name: str


@dataclass(frozen=True)
class _Ref:
    index: int


@dataclass(frozen=True)
class Compiled:
    """A checked filter: per element (operator, operands), the elements reachable from the
    root (evaluated, last first) and the fields the filter reads."""

    elements: tuple[tuple[Any, tuple[Any, ...]], ...]
    order: tuple[int, ...]
    fields: frozenset[str]

    def matches(self, row: dict[str, Any]) -> bool:
        """Whether the run ``row`` (field → value) passes: each element evaluated once."""
        vals: dict[int, bool] = {}
        for i in self.order:
            op, operands = self.elements[i]
            args = [row.get(o.name) if isinstance(o, _Field) else
                    vals[o.index] if isinstance(o, _Ref) else o.value for o in operands]
            vals[i] = _apply(op, args)
        return vals[0]


def _apply(op: Any, args: list[Any]) -> bool:
    if op == ua.FilterOperator.And:
        return bool(args[0]) and bool(args[1])
    if op == ua.FilterOperator.Or:
        return bool(args[0]) or bool(args[1])
    if op == ua.FilterOperator.Not:
        return not args[0]
    a, b = args
    if a is None or b is None:  # a field the run does not have (no artefact): no match
        return False
    if isinstance(a, dt.datetime) and isinstance(b, dt.datetime):
        a, b = a.replace(tzinfo=a.tzinfo or dt.UTC), b.replace(tzinfo=b.tzinfo or dt.UTC)
    return bool(_COMPARE[op](a, b))


def _kind(value: Any) -> type | None:
    """The comparison kind of a literal (bool, int, str, datetime), None if unsupported."""
    if isinstance(value, bool):
        return bool
    if isinstance(value, int):
        return int
    if isinstance(value, float):
        return int if math.isfinite(value) else None
    if isinstance(value, str):
        return str
    if isinstance(value, dt.datetime):
        return dt.datetime
    return None


def _literal(op: ua.LiteralOperand) -> _Lit:
    variant = op.Value
    value = variant.Value if isinstance(variant, ua.Variant) else None
    if isinstance(value, ua.ResultEvaluationEnum):
        value = int(value)
    if _kind(value) is None:
        raise FilterError(f"literal {type(value).__name__}: a number, string, boolean or "
                          "date-time is expected")
    return _Lit(value)


def _field(op: ua.SimpleAttributeOperand) -> _Field:
    path = op.BrowsePath or []
    last = path[-1] if path else None
    name = last.Name if isinstance(last, ua.QualifiedName) else ""
    if name not in FIELDS or len(path) > 2:
        raise FilterError(f"operand {str(name)[:40]!r}: one of {sorted(FIELDS)}")
    return _Field(name)


def compile_filter(flt: Any) -> Compiled:
    """Check ``flt`` whole (type, size, operators, operands, references, depth, the types
    compared) and return it ready to evaluate; ``FilterError`` naming the first problem."""
    if not isinstance(flt, ua.ContentFilter):
        raise FilterError(f"the filter is a {type(flt).__name__}, not a ContentFilter")
    raw = list(flt.Elements or [])
    if not raw:
        return Compiled((), (), frozenset())
    if len(raw) > MAX_ELEMENTS:
        raise FilterError(f"{len(raw)} elements: at most {MAX_ELEMENTS}")
    elements: list[tuple[Any, tuple[Any, ...]]] = []
    for i, el in enumerate(raw):
        if not isinstance(el, ua.ContentFilterElement):
            raise FilterError(f"element {i} is a {type(el).__name__}")
        op, operands = el.FilterOperator, list(el.FilterOperands or [])
        if not isinstance(op, int):
            raise FilterError(f"element {i}: no operator")
        want = _LOGIC.get(op, 2 if op in _COMPARE else None)
        if want is None:
            raise FilterError(f"element {i}: operator {_name(op)} not supported")
        if len(operands) != want:
            raise FilterError(f"element {i}: {len(operands)} operands, {_name(op)} takes "
                              f"{want}")
        out: list[Any] = []
        for o in operands:
            if isinstance(o, ua.LiteralOperand):
                out.append(_literal(o))
            elif isinstance(o, ua.SimpleAttributeOperand):
                out.append(_field(o))
            elif isinstance(o, ua.ElementOperand):
                j = o.Index
                if not isinstance(j, int) or not i < j < len(raw):
                    # OPC 10000-4 §7.7.4.2: only a later element (no cycle, no self)
                    raise FilterError(f"element {i}: element operand {j} is not a later "
                                      f"element (1 … {len(raw) - 1} after {i})")
                out.append(_Ref(j))
            else:
                raise FilterError(f"element {i}: operand {type(o).__name__} not supported")
        elements.append((op, tuple(out)))
    order = _reachable(elements)
    _check_types(elements, order)
    fields = frozenset(o.name for i in order for o in elements[i][1] if isinstance(o, _Field))
    return Compiled(tuple(elements), order, fields)


def _reachable(elements: list[tuple[Any, tuple[Any, ...]]]) -> tuple[int, ...]:
    """The elements the root depends on, last first (each after the ones it uses); the
    depth of the chain from the root is bounded by ``MAX_DEPTH``."""
    depth = {0: 1}
    for i in range(len(elements)):  # references only point forward: one pass is enough
        if i not in depth:
            continue
        for o in elements[i][1]:
            if isinstance(o, _Ref):
                depth[o.index] = max(depth.get(o.index, 0), depth[i] + 1)
                if depth[o.index] > MAX_DEPTH:
                    raise FilterError(f"deeper than {MAX_DEPTH} elements")
    return tuple(sorted(depth, reverse=True))


def _check_types(elements: list[tuple[Any, tuple[Any, ...]]], order: tuple[int, ...]) -> None:
    """Every comparison compares values of one kind (numbers with numbers, strings with
    strings, date-times with date-times); logic operators take booleans."""
    def kind(o: Any) -> type | None:
        if isinstance(o, _Field):
            return FIELDS[o.name]
        if isinstance(o, _Ref):
            return bool
        return _kind(o.value)

    for i in order:
        op, operands = elements[i]
        kinds = [kind(o) for o in operands]
        if op in _LOGIC:
            if any(k is not bool for k in kinds):
                raise FilterError(f"element {i}: {_name(op)} takes conditions (elements or "
                                  "booleans)")
            continue
        a, b = (int if k is bool else k for k in kinds)  # a condition compares as 0/1
        if a is not b:
            raise FilterError(f"element {i}: cannot compare a {a.__name__} with a "
                              f"{b.__name__}")


def _name(op: Any) -> str:
    return str(getattr(op, "name", op))
