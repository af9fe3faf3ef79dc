"""Words for people: the small pieces of English every command's output shares."""

from __future__ import annotations


def plural(n: int, word: str) -> str:
    """``1 gap``, ``2 gaps``: a count with its noun in the right number."""
    return f"{n} {word}{'' if n == 1 else 's'}"
