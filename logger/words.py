"""Words for people: the small pieces of English every command's output shares."""

from __future__ import annotations


def plural(n: int, word: str, many: str | None = None) -> str:
    """``1 gap``, ``2 gaps``: a count with its noun in the right number (``many`` for a noun not made with -s:
    ``plural(n, "fix", "fixes")``)."""
    return f"{n} {word if n == 1 else many or word + 's'}"
