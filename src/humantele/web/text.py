"""Client-supplied text made fit for one log line (the servers' guards and refusals)."""

from __future__ import annotations


def printable(text: str) -> str:
    """``text`` with every non-printable character (newline, escape, bidi control, lone
    surrogate...) written as its Python escape, so a client-supplied value stays on one log
    line and shows what it is."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode() for c in text)
