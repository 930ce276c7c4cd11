"""The official VDA 5050 2.1.0 JSON schemas (``schemas/``, package data) and a validator over them.

``load_schemas()`` reads the copies shipped inside the package (their source: ``schemas/README.md``);
``SchemaValidator(schemas)`` is pure: ``problems(topic, doc)`` lists what breaks the topic's schema
(empty when the message is valid). Formats (``date-time``) are checked where ``jsonschema`` can.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

__all__ = ["SCHEMA_TOPICS", "SchemaValidator", "load_schemas"]

SCHEMA_TOPICS = ("connection", "factsheet", "instantActions", "order", "state", "visualization")
"""The VDA 5050 topics, each with its ``<topic>.schema``."""

MAX_PROBLEMS = 4


def load_schemas(folder: Path | None = None) -> dict[str, dict[str, Any]]:
    """topic -> schema, from ``folder`` or from the package's own copies."""
    out: dict[str, dict[str, Any]] = {}
    for topic in SCHEMA_TOPICS:
        if folder is not None:
            text = (folder / f"{topic}.schema").read_text(encoding="utf-8")
        else:
            text = resources.files("fleetlink.operator.vda5050.schemas").joinpath(f"{topic}.schema").read_text("utf-8")
        out[topic] = json.loads(text)
    return out


class SchemaValidator:
    """Validates VDA 5050 messages against their topic's schema (thread-safe, no I/O)."""

    def __init__(self, schemas: Mapping[str, Mapping[str, Any]]) -> None:
        import jsonschema

        self._validators: dict[str, Any] = {}
        for topic, schema in schemas.items():
            cls = jsonschema.validators.validator_for(schema)
            cls.check_schema(schema)
            self._validators[topic] = cls(schema, format_checker=cls.FORMAT_CHECKER)

    def problems(self, topic: str, doc: object) -> list[str]:
        """What is wrong with ``doc`` as a ``topic`` message (at most a few, shortest path first)."""
        validator = self._validators.get(topic)
        if validator is None:
            return [f"no schema for topic {topic!r}"]
        errors = sorted(validator.iter_errors(doc), key=lambda e: (len(e.absolute_path), str(e.message)))
        out = []
        for e in errors[:MAX_PROBLEMS]:
            where = "/".join(str(p) for p in e.absolute_path) or "(message)"
            out.append(f"{where}: {e.message}"[:200])
        return out

    def valid(self, topic: str, doc: object) -> bool:
        return not self.problems(topic, doc)
