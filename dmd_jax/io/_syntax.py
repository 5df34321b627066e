"""The syntax every text reader shares (OBJ, OFF, ASCII PLY, ASCII STL): lines, tokens
and number tokens, as a C reader of these formats sees them.

Python's own parsing is wider than the formats': `float()` and `int()` take `1_0`,
full-width and other Unicode digits and surrounding Unicode spaces, `str.splitlines()`
breaks lines at U+2028, U+2029, NEL, form feed and more, and `str.split()` separates
at any Unicode space. A file read that way holds values, or statements hidden in a
comment, that its writer never wrote and a C reader would not see. So here:

* lines end at `\\n`, `\\r\\n` or `\\r` only;
* tokens are separated by ASCII blanks (space, tab, vertical tab, form feed: C's
  `isspace` less the line breaks); any other character belongs to a token;
* a real number is what C `strtod` reads whole: decimal (`-1.5e3`, `.5`, `2.`),
  hexadecimal (`0x1.8p3`), `inf`/`infinity`/`nan`/`nan(chars)` in any case, in ASCII;
* an integer is what C `strtol` reads whole in base 10: `[+-]?[0-9]+`.

Anything else is refused by the reader, naming the file and the line.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

import numpy as np

_LINE_BREAK = re.compile(r"\r\n|\r|\n")
_BLANKS = re.compile(r"[ \t\v\f]+")
_BLANK_CHARS = " \t\v\f"

_DECIMAL = r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
_HEX = r"[+-]?0[xX](?:[0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)(?:[pP][+-]?[0-9]+)?"
_SPECIAL = r"[+-]?(?:[iI][nN][fF](?:[iI][nN][iI][tT][yY])?|[nN][aA][nN](?:\([0-9A-Za-z_]*\))?)"
_INTEGER = r"[+-]?[0-9]+"
_PATTERNS = {
    kind: (re.compile(text), re.compile(text.encode()))
    for kind, text in (
        ("decimal", _DECIMAL),
        ("hex", _HEX),
        ("special", _SPECIAL),
        ("integer", _INTEGER),
    )
}
# Tokens made of these characters only are decimal numbers (or integers) exactly when
# Python's float() (int()) takes them: Python's extras are `_` and non-ASCII.
_PLAIN_FLOAT = frozenset("0123456789+-.eE")
_PLAIN_INT = frozenset("0123456789+-")
_PLAIN_FLOAT_BYTES = b"0123456789+-.eE"
_PLAIN_INT_BYTES = b"0123456789+-"


class TokenError(ValueError):
    """A token outside the grammar; `token` is it, for a reader to find its line."""

    def __init__(self, message: str, token: str | bytes):
        super().__init__(message)
        self.token = token


def lines(text: str) -> list[str]:
    """The lines of `text`, split at `\\n`, `\\r\\n` and `\\r` only."""
    return _LINE_BREAK.split(text)


def tokens(line: str) -> list[str]:
    """The tokens of one line, separated by ASCII blanks only."""
    return [t for t in _BLANKS.split(line.strip(_BLANK_CHARS)) if t]


def _match(kind: str, token: str | bytes) -> bool:
    pattern = _PATTERNS[kind][isinstance(token, bytes)]
    return pattern.fullmatch(token) is not None


def _shown(token: str | bytes) -> str:
    if isinstance(token, bytes):
        token = token.decode("ascii", "backslashreplace")
    return repr(token[:30])


def float_of(token: str | bytes) -> float:
    """The value of one real-number token (the grammar of C `strtod`).

    Raises:
      TokenError: `'TOKEN' is not a number` (a `ValueError`).
    """
    if _match("decimal", token):
        return float(token)
    if _match("hex", token):
        text = token.decode("ascii") if isinstance(token, bytes) else token
        try:
            return float.fromhex(text)
        except OverflowError:  # strtod gives an infinity (refused as such later)
            return -math.inf if text.startswith("-") else math.inf
    if _match("special", token):
        text = token.decode("ascii") if isinstance(token, bytes) else token
        value = math.inf if text.lstrip("+-")[:1] in "iI" else math.nan
        return -value if text.startswith("-") else value
    raise TokenError(f"{_shown(token)} is not a number", token)


def int_of(token: str | bytes) -> int:
    """The value of one integer token (the grammar of C `strtol`, base 10).

    Raises:
      TokenError: `'TOKEN' is not an integer` (a `ValueError`).
    """
    if _match("integer", token):
        return int(token)
    raise TokenError(f"{_shown(token)} is not an integer", token)


def _plain(items: Sequence[str | bytes], chars: frozenset, chars_bytes: bytes) -> bool:
    """Whether every token is made of `chars` only (then Python parses it as C does)."""
    if not items:
        return True
    if isinstance(items[0], bytes):
        return not b"".join(items).translate(None, chars_bytes)
    return set("".join(items)) <= chars


def floats(items: Sequence[str | bytes]) -> np.ndarray:
    """Real-number tokens as float64, each read as `float_of` reads it.

    Raises:
      ValueError: naming the first token that is not a number.
    """
    if _plain(items, _PLAIN_FLOAT, _PLAIN_FLOAT_BYTES):
        try:
            # float() one token at a time: a NumPy string array would be as wide as
            # the longest token, which a hostile file can make enormous.
            return np.fromiter(map(float, items), np.float64, len(items))
        except ValueError:
            pass  # a malformed token (`1e`, `+-1`): found and named below
    return np.fromiter(map(float_of, items), np.float64, len(items))


def ints(items: Sequence[str | bytes]) -> np.ndarray:
    """Integer tokens as int64, each read as `int_of` reads it.

    Raises:
      ValueError: naming the first token that is not an integer, or one beyond int64.
    """
    convert = int if _plain(items, _PLAIN_INT, _PLAIN_INT_BYTES) else int_of
    try:
        return np.fromiter(map(convert, items), np.int64, len(items))
    except ValueError:
        if convert is int:  # a malformed token (`+-1`, `1-`): found and named below
            return np.fromiter(map(int_of, items), np.int64, len(items))
        raise
    except OverflowError:
        big = next(t for t in items if not -(2**63) <= int_of(t) < 2**63)
        raise TokenError(f"{_shown(big)} is beyond the range of a 64-bit integer", big) from None
