"""Who confirmed a compensation, as the journal records it: a name a person reads in
the journal, the report and a terminal, so it must print as what it is — one line, no control
characters, no terminal escapes, no bidi overrides or invisible characters, a sane length — and
must not pass for the reserved ``unattended`` marker the daemon writes for itself."""

from __future__ import annotations

import unicodedata

UNATTENDED = "unattended"
MAX_LEN = 64

# Letters of other scripts that read as the Latin letters of "unattended" (Unicode's
# confusables for u n a t e d); NFKC already folds full-width and other compatibility forms.
_LOOKALIKE = str.maketrans({
    "а": "a", "ɑ": "a", "α": "a", "е": "e", "ε": "e", "ҽ": "e", "ԁ": "d", "ď": "d",
    "υ": "u", "ս": "u", "μ": "u", "ц": "u", "ո": "n", "η": "n", "п": "n", "τ": "t", "т": "t",
    "ţ": "t", "ı": "i", "ｕ": "u",
})


class BadName(ValueError):
    """A name refused; the message is one line naming the option or field."""


def _skeleton(name: str) -> str:
    """What ``name`` looks like: NFKC, case-folded, look-alike letters mapped to Latin, marks
    and everything that is not a letter dropped ("Un-attended", "ｕｎａｔｔｅｎｄｅｄ")."""
    s = unicodedata.normalize("NFKD", unicodedata.normalize("NFKC", name).casefold())
    s = s.translate(_LOOKALIKE)
    return "".join(c for c in s if c.isalpha() and not unicodedata.combining(c))


def validate_by(name: object, where: str = "--by", *, allow_unattended: bool = True) -> str:
    """``name`` unchanged when it may be journaled as who confirmed, else ``BadName`` naming
    ``where``. The exact marker ``unattended`` passes when ``allow_unattended`` (the guards
    decide about it later); anything that only looks like it never does."""
    if not isinstance(name, str) or not name:
        raise BadName(f"{where}: give a name (who confirms, recorded in the journal)")
    if len(name) > MAX_LEN:
        raise BadName(f"{where}: {len(name)} characters, at most {MAX_LEN}")
    for ch in name:
        cat = unicodedata.category(ch)
        # C*: controls (newline, ESC), format (bidi overrides, zero-width), surrogates, private
        # use, unassigned; Z* other than the plain space: line/paragraph separators, NBSP …
        if cat.startswith("C") or (cat.startswith("Z") and ch != " "):
            raise BadName(f"{where}: character U+{ord(ch):04X} ({cat}) is not allowed: "
                          "printable text on one line only")
    if name != name.strip():
        raise BadName(f"{where}: no leading or trailing spaces")
    if name == UNATTENDED:
        if allow_unattended:
            return name
        raise BadName(f"{where}: {UNATTENDED!r} is reserved for the daemon's own compensation")
    if _skeleton(name) == UNATTENDED:
        raise BadName(f"{where}: {name!r} looks like the reserved marker {UNATTENDED!r}: "
                      "choose another name")
    return name
