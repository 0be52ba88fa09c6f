"""The configuration reference: every key of every file rumba reads, with its type, default and
limits from the pydantic schema's JSON schema, and what it means from the comment the schema's
source carries beside the field."""

from __future__ import annotations

import inspect
import json
import re
import types
import typing
from typing import Any

from pydantic import BaseModel

from docs.gen.text import cell, code, docstring, table

_FIELD = re.compile(r"^ {4}(\w+)\s*:(?!=)")


def field_comments(cls: type) -> dict[str, str]:
    """The comment lines just above a field and the comments at the end of its lines."""
    try:
        lines = inspect.getsource(cls).splitlines()[1:]
    except (OSError, TypeError):
        return {}
    out: dict[str, list[str]] = {}
    pending: list[str] = []
    last: str | None = None
    for line in lines:
        stripped = line.strip()
        indent = len(line) - len(line.lstrip())
        if stripped.startswith("#"):
            if indent == 4:
                pending.append(stripped[1:].strip())
            continue
        m = _FIELD.match(line)
        if m and not stripped.startswith(("def ", "class ", "model_config")):
            last = m.group(1)
            out[last] = [*pending]
            pending = []
        elif indent <= 4:
            last, pending = None, []
        if last is not None and "  # " in line:
            out[last].append(line.split("  # ", 1)[1].strip())
    return {k: " ".join(c for c in v if not c.startswith(("type:", "noqa")))
            for k, v in out.items() if v}


def own_doc(cls: type) -> str:
    """The class's own docstring (not its base's), cleaned."""
    doc = cls.__dict__.get("__doc__")
    return docstring(cls) if doc else ""


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    found: list[type[BaseModel]] = []
    for arg in typing.get_args(annotation):
        found += _models_in(arg)
    return found


def _container(annotation: Any) -> str:
    """'[]' for a list of models, '.<name>' for a mapping of them, '' for one model."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(annotation):
            if _models_in(arg):
                return _container(arg)
    if origin in (list, tuple):
        return "[]"
    if origin is dict:
        key = typing.get_args(annotation)[0]
        if typing.get_origin(key) is typing.Literal:
            return ".<" + "|".join(map(str, typing.get_args(key))) + ">"
        return ".<name>"
    return ""


def _type(s: dict[str, Any], defs: dict[str, Any]) -> str:
    if "$ref" in s:
        return "section"
    if "const" in s:
        return f"exactly {code(s['const'])}"
    if "enum" in s:
        return "one of " + ", ".join(code(v) for v in s["enum"])
    if "anyOf" in s:
        kinds = [_type(a, defs) for a in s["anyOf"] if a.get("type") != "null"]
        nullable = any(a.get("type") == "null" for a in s["anyOf"])
        text = " or ".join(dict.fromkeys(kinds))
        return f"{text} or null" if nullable and text else (text or "null")
    t = s.get("type")
    if t == "array":
        items = s.get("items")
        if isinstance(items, dict) and items:
            return f"list of {_type(items, defs)}"
        if "prefixItems" in s:
            return f"list of {len(s['prefixItems'])} " + \
                   " and ".join(dict.fromkeys(_type(a, defs) for a in s["prefixItems"]))
        return "list"
    if t == "object":
        extra = s.get("additionalProperties")
        if isinstance(extra, dict) and extra:
            return f"mapping of text to {_type(extra, defs)}"
        return "mapping"
    if t == "string" and s.get("format") in ("date", "date-time"):
        return "date (YYYY-MM-DD)" if s["format"] == "date" else "date and time (ISO 8601)"
    return {"string": "text", "integer": "integer", "number": "number", "boolean": "true/false",
            "null": "null"}.get(t, "any")


def _limits(s: dict[str, Any]) -> str:
    parts = []
    for key, fmt in (("minimum", "≥ {}"), ("exclusiveMinimum", "> {}"), ("maximum", "≤ {}"),
                     ("exclusiveMaximum", "< {}"), ("minLength", "≥ {} characters"),
                     ("maxLength", "≤ {} characters"), ("minItems", "≥ {} items"),
                     ("maxItems", "≤ {} items"), ("pattern", "matches {}")):
        for sub in [s, *s.get("anyOf", []), s.get("items") or {}]:
            if isinstance(sub, dict) and key in sub:
                value = sub[key]
                parts.append(fmt.format(code(value) if key == "pattern" else f"{value:g}"
                                        if isinstance(value, float) else value))
                break
    text = ", ".join(dict.fromkeys(parts))
    text = re.sub(r"≥ (\d+) items, ≤ \1 items", r"\1 items", text)
    text = re.sub(r"≥ (\d+) characters, ≤ (\d+) characters", r"\1-\2 characters", text)
    return text.replace("matches `^[^\\x00-\\x1f\\x7f]+$`", "no control characters")


def _default(name: str, s: dict[str, Any], required: set[str]) -> str:
    if name in required:
        return "required"
    if "default" not in s:
        return ""
    value = s["default"]
    if value is None:
        return "—"
    return code(json.dumps(value, ensure_ascii=False))


def rows(model: type[BaseModel], prefix: str = "") -> list[list[str]]:
    """One row per key of ``model`` and of every section inside it (dotted paths)."""
    schema = model.model_json_schema(mode="validation")
    defs = schema.get("$defs", {})
    required = set(schema.get("required", []))
    comments = field_comments(model)
    out: list[list[str]] = []
    for name, prop in schema.get("properties", {}).items():
        field = model.model_fields.get(name)
        annotation = field.annotation if field is not None else None
        nested = _models_in(annotation)
        what = prop.get("description") or comments.get(name, "")
        key = f"{prefix}{name}"
        if nested:
            suffix = _container(annotation)
            doc = what or own_doc(nested[0]).split("\n\n")[0]
            kind = ("list of sections" if suffix == "[]" else
                    "mapping of sections" if suffix.startswith(".<") else "section")
            default = "required" if name in required else ""
            out.append([code(key), kind, default, "", cell(doc)])
            for sub in nested:
                out += rows(sub, f"{key}{suffix}.")
            continue
        out.append([code(key), _type(prop, defs), _default(name, prop, required),
                    _limits(prop), cell(what)])
    return out


def section(model: type[BaseModel], prefix: str = "", intro: str | None = None) -> str:
    text = intro if intro is not None else own_doc(model)
    body = table(["key", "type", "default", "limits", "what"], rows(model, prefix))
    return (text + "\n\n" if text else "") + body
