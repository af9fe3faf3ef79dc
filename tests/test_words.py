"""The words every command's output shares."""

from logger.words import plural


def test_plural_follows_the_count() -> None:
    assert [plural(n, "gap") for n in (0, 1, 2)] == ["0 gaps", "1 gap", "2 gaps"]
