"""An AQDEF (Q-DAS ASCII transfer format, K-field form) reader written from the format's
description, not from rumba's writer: used by the tests to read back what the export wrote.

A line is ``K`` + four digits, an optional ``/index``, one space, the field content. K0100 is the
number of characteristics; K1xxx are part fields; K2xxx/i describe characteristic i; in the value
part a ``K0001/i`` opens a new value record of characteristic i and the following K00xx/i fields
(K0002 … K0020) belong to that record until the next K0001/i."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

LINE = re.compile(r"K(\d{4})(?:/(\d+))? (.*)")


class AqdefSyntaxError(ValueError):
    pass


@dataclass
class AqdefFile:
    header: dict[str, str] = field(default_factory=dict)  # K0100, K1xxx (no index)
    characteristics: dict[int, dict[str, str]] = field(default_factory=dict)
    values: dict[int, list[dict[str, str]]] = field(default_factory=dict)
    keys: list[str] = field(default_factory=list)  # every K-field key as read, in order


def read_aqdef(path: Path, encoding: str = "cp1252") -> AqdefFile:
    raw = path.read_bytes()
    lines = raw.split(b"\r\n")
    if lines[-1] != b"":
        raise AqdefSyntaxError("the file does not end with CR LF")
    out = AqdefFile()
    for n, b in enumerate(lines[:-1], start=1):
        if b"\n" in b or b"\r" in b:
            raise AqdefSyntaxError(f"line {n}: a bare line break")
        s = b.decode(encoding)
        m = LINE.fullmatch(s)
        if m is None:
            raise AqdefSyntaxError(f"line {n}: not a K-field: {s!r}")
        key, idx, content = "K" + m.group(1), m.group(2), m.group(3)
        out.keys.append(key)
        num = int(m.group(1))
        if idx is None:
            if num >= 2000 or (num < 1000 and key != "K0100"):
                raise AqdefSyntaxError(f"line {n}: {key} needs a characteristic index")
            out.header[key] = content
        elif num >= 2000:
            out.characteristics.setdefault(int(idx), {})[key] = content
        elif num < 100:
            i = int(idx)
            if key == "K0001":
                out.values.setdefault(i, []).append({key: content})
            elif not out.values.get(i):
                raise AqdefSyntaxError(f"line {n}: {key}/{i} before any K0001/{i}")
            else:
                out.values[i][-1][key] = content
        else:
            out.header[f"{key}/{idx}"] = content
    if int(out.header.get("K0100", "-1")) != len(out.characteristics):
        raise AqdefSyntaxError(f"K0100 says {out.header.get('K0100')} characteristics, "
                               f"the file describes {len(out.characteristics)}")
    return out
