"""Words for people: the small pieces of English every command's output shares."""

from __future__ import annotations


def plural(n: int, word: str, many: str | None = None) -> str:
    """``1 gap``, ``2 gaps``: a count with its noun in the right number (``many`` for a noun not made with -s:
    ``plural(n, "fix", "fixes")``)."""
    return f"{n} {word if n == 1 else many or word + 's'}"


def size_text(n: float) -> str:
    """A size a reader can use, in the configuration's binary units: ``984 KiB``, ``50 MiB``, ``3.4 GiB``; never
    ``0.0 GB free`` on a small card nor ``0 MiB`` with 984 KiB left."""
    for unit, shift in (("GiB", 30), ("MiB", 20)):
        if n >= 10 << shift:
            return f"{n / (1 << shift):.0f} {unit}"
        if n >= 1 << shift:
            return f"{n / (1 << shift):.1f} {unit}"
    return f"{int(n) >> 10} KiB" if n >= 1 << 10 else f"{int(n)} bytes"
