"""Reading a stored analysis' JSON text in Python rather than with PostgreSQL's jsonb, which
refuses the NaN and Infinity an analysis may hold."""

from __future__ import annotations

import json
import math
from typing import Any


def analysis_part(text: str | None, *path: str) -> Any:
    """A part of a stored analysis (its JSON text), None when absent. Parsed here, not with
    PostgreSQL's jsonb: the analyses of older versions hold NaN and Infinity, which jsonb
    refuses (the whole query failed, the fleet page answered 500); those numbers come back as
    None, as a valid JSON document has them."""
    if text is None:
        return None
    try:
        node: Any = json.loads(text)
    except ValueError:
        return None
    for key in path:
        node = node.get(key) if isinstance(node, dict) else None
    return _finite(node)


def _finite(node: Any) -> Any:
    if isinstance(node, float):
        return node if math.isfinite(node) else None
    if isinstance(node, dict):
        return {k: _finite(v) for k, v in node.items()}
    if isinstance(node, list):
        return [_finite(v) for v in node]
    return node
