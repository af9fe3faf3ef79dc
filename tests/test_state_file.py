"""The state folder's JSON files are written whole or not at all, and a failure is a warning, not an error."""

from __future__ import annotations

import json
import logging

from logger.runtime.state_file import save_json


def test_a_state_file_is_replaced_whole_and_a_failed_write_leaves_the_old_one(tmp_path, caplog) -> None:
    path = tmp_path / "state" / "mount.json"
    assert save_json(path, {"a": 1}, "the test state")
    assert json.loads(path.read_text()) == {"a": 1} and not path.with_suffix(".tmp").exists()
    path.with_suffix(".tmp").mkdir()  # the temporary file cannot be written: the old one must stay
    with caplog.at_level(logging.WARNING):
        assert not save_json(path, {"a": 2}, "the test state")
    assert json.loads(path.read_text()) == {"a": 1}
    assert "cannot save the test state" in caplog.text
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    assert not save_json(blocked / "mount.json", {"a": 3}, "the test state")  # its folder cannot be made
