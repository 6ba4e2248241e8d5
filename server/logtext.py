"""Peer-supplied text made safe for one log line (issue 39, item 6).

A peer chooses a Bye's reason, an Error's message, a client name: written raw, a newline in
one forges a whole log line (a fake `arlight serve: admin token ...`), and other control
characters can rewrite a terminal. `printable` escapes every character that is not
printable (newlines, carriage returns, escape sequences, other Unicode controls and
separators) the way Python's repr does and cuts the text to a length.
"""

from __future__ import annotations

PEER_TEXT_CHARS = 256  # of a peer's text in one log line; the rest is counted, not shown


def printable(text: object, limit: int = PEER_TEXT_CHARS) -> str:
    """`text` (str() of it) on one line: non-printable characters as \\n, \\x1b, \\u2028,
    ...; longer than `limit` characters: cut, with how many were left out."""
    s = str(text)
    cut = len(s) - limit
    s = s[:limit]
    if not s.isprintable():
        s = "".join(c if c.isprintable() else repr(c)[1:-1] for c in s)
    return s if cut <= 0 else f"{s}... ({cut} more characters)"
