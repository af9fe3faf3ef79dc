"""Every recorded topic and the JSON schema of its messages: the one place the file format is defined.

Field names carry their units (``_mps``, ``_ns``, ``_deg``...) so a reader needs no other document;
``docs/topics.md`` is generated from this module by ``tools/topics_doc.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class TopicSpec:
    topic: str
    schema_name: str
    schema: dict[str, Any]
    description: str
