"""The results server's method calls checked at the door: each method declares its input
arguments (OPC 40001-101 / OPC 10000-5 Annex C), a call with too few or too many arguments, or
one of the wrong kind, is answered with the Call service's status codes (BadArgumentsMissing,
BadTooManyArguments, BadInvalidArgument with BadTypeMismatch / BadOutOfRange per argument)
before the method runs, and a method's own refusal (``ua.UaStatusCodeError``) is answered with
its code. asyncua answers anything a method raises with BadUnexpectedError and logs a traceback;
here only a defect does, as BadInternalError."""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from asyncua import ua

log = logging.getLogger("rumba.opcua")
VT = ua.VariantType
_NUMBERS = {VT.SByte, VT.Byte, VT.Int16, VT.UInt16, VT.Int32, VT.UInt32, VT.Int64, VT.UInt64,
            VT.Float, VT.Double}


@dataclass(frozen=True)
class Arg:
    """One input argument: its name and kind.

    Kinds: ``number`` (any numeric type, finite: a Timeout), ``count`` (an integer 0 … 2³²−1:
    MaxResults, a FileHandle), ``position`` (an integer ≥ 0), ``length`` (an integer, Int32),
    ``string`` (a String, null read as ""), ``strings`` (an array of String), ``filter`` (a
    ContentFilter or null), ``object`` (any structure), ``any`` (not looked at)."""

    name: str
    kind: str


class _Bad(Exception):
    def __init__(self, code: int) -> None:
        self.code = code


def _integer(v: ua.Variant, lo: int, hi: int) -> int:
    if not isinstance(v.Value, (int, float)) or isinstance(v.Value, bool) \
            or v.VariantType not in _NUMBERS or v.is_array:
        raise _Bad(ua.StatusCodes.BadTypeMismatch)
    if not math.isfinite(v.Value) or v.Value != int(v.Value) or not lo <= v.Value <= hi:
        raise _Bad(ua.StatusCodes.BadOutOfRange)
    return int(v.Value)


def _value(v: Any, kind: str) -> Any:
    if not isinstance(v, ua.Variant):
        raise _Bad(ua.StatusCodes.BadTypeMismatch)
    if kind == "any":
        return v.Value
    if kind == "number":
        if v.VariantType not in _NUMBERS or v.is_array or isinstance(v.Value, bool) \
                or not isinstance(v.Value, (int, float)) or not math.isfinite(v.Value):
            raise _Bad(ua.StatusCodes.BadTypeMismatch)
        return float(v.Value)
    if kind == "count":
        return _integer(v, 0, 2**32 - 1)
    if kind == "position":
        return _integer(v, 0, 2**63 - 1)
    if kind == "length":
        return _integer(v, -(2**31), 2**31 - 1)
    if kind == "string":
        if v.VariantType not in (VT.String, VT.Null) or v.is_array \
                or not isinstance(v.Value, (str, type(None))):
            raise _Bad(ua.StatusCodes.BadTypeMismatch)
        return v.Value or ""
    if kind == "strings":
        items = v.Value if v.Value is not None else []
        if v.VariantType not in (VT.String, VT.Null) or not isinstance(items, list) \
                or not all(isinstance(x, (str, type(None))) for x in items):
            raise _Bad(ua.StatusCodes.BadTypeMismatch)
        return [x or "" for x in items]
    if kind in ("filter", "object"):
        if v.VariantType not in (VT.ExtensionObject, VT.Null) or v.is_array:
            raise _Bad(ua.StatusCodes.BadTypeMismatch)
        if kind == "filter" and not isinstance(v.Value, (ua.ContentFilter, type(None))):
            raise _Bad(ua.StatusCodes.BadTypeMismatch)
        return v.Value
    raise AssertionError(f"argument kind {kind!r}")


def check(args: tuple[Any, ...], spec: tuple[Arg, ...]) -> list[Any] | ua.CallMethodResult:
    """The arguments' values, or the Call result that refuses them."""
    if len(args) != len(spec):
        return ua.CallMethodResult(StatusCode=ua.StatusCode(
            ua.StatusCodes.BadArgumentsMissing if len(args) < len(spec)
            else ua.StatusCodes.BadTooManyArguments))
    values, codes, bad = [], [], False
    for v, a in zip(args, spec, strict=True):
        try:
            values.append(_value(v, a.kind))
            codes.append(ua.StatusCode())
        except _Bad as e:
            values.append(None)
            codes.append(ua.StatusCode(e.code))
            bad = True
    if bad:
        return ua.CallMethodResult(StatusCode=ua.StatusCode(ua.StatusCodes.BadInvalidArgument),
                                   InputArgumentResults=codes)
    return values


Handler = Callable[..., Awaitable[Any]]


def method(name: str, *spec: Arg) -> Callable[[Handler], Handler]:
    """Decorate a server method ``fn(self, parent, *values)``: its arguments checked against
    ``spec`` and handed over as Python values; a refusal or a defect answered with a status
    code."""
    def wrap(fn: Handler) -> Handler:
        @functools.wraps(fn)
        async def call(self: Any, parent: ua.NodeId, *args: Any) -> Any:
            values = check(args, spec)
            if isinstance(values, ua.CallMethodResult):
                return values
            try:
                return await fn(self, parent, *values)
            except ua.UaStatusCodeError as e:
                return ua.StatusCode(e.code)
            except Exception:  # a defect of ours: said once (the log's repeat filter)
                log.exception("OPC UA %s failed", name)
                return ua.StatusCode(ua.StatusCodes.BadInternalError)
        return call
    return wrap
