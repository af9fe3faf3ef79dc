"""The words every command's output shares."""

from logger.words import plural


def test_plural_follows_the_count() -> None:
    assert [plural(n, "gap") for n in (0, 1, 2)] == ["0 gaps", "1 gap", "2 gaps"]
    assert [plural(n, "GNSS fix", "GNSS fixes") for n in (0, 1, 2)] == ["0 GNSS fixes", "1 GNSS fix", "2 GNSS fixes"]
