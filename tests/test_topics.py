"""The topic definitions are the file format: the generated document must match them."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from logger.recording.topics import STAMP, TOPICS

ROOT = Path(__file__).resolve().parents[1]


def test_topics_doc_is_current() -> None:
    spec = importlib.util.spec_from_file_location("topics_doc", ROOT / "tools" / "topics_doc.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert (ROOT / "docs" / "topics.md").read_text() == mod.render(), "run: python tools/topics_doc.py"


def test_sensor_topics_carry_the_full_stamp() -> None:
    for topic in ("/imu", "/baro", "/obd/speed", "/gnss/fix", "/pps"):
        assert set(STAMP) <= set(TOPICS[topic].schema["required"]), topic


def test_location_fix_topics_use_the_foxglove_schema_fields() -> None:
    fox = {"timestamp", "frame_id", "latitude", "longitude", "altitude", "position_covariance",
           "position_covariance_type"}
    assert TOPICS["/gnss/fix"].schema_name == "foxglove.LocationFix"
    assert fox <= set(TOPICS["/gnss/fix"].schema["properties"])


def test_every_field_has_a_unit_or_meaning() -> None:
    for spec in TOPICS.values():
        for name, prop in spec.schema["properties"].items():
            assert len(prop["description"]) > 10, (spec.topic, name)
