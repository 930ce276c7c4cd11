"""The console's marks file and the marks it places. Pure apart from the file at the injected path.

``MarksStore(path)``: ``new(...)`` builds this console's next ``Mark`` (ids ``<sender>-<wall
seconds>-<n>``, unique per console run), ``save(marks)`` rewrites the file atomically (a temporary
file renamed over it) and ``load()`` reads it back. The file is JSON::

    {"marks": [{"markId": ..., "x": ..., "y": ..., "label": ..., "kind": ...,
                "by": <sender>, "robot": <robot>, "timestamp": <wall seconds>}, ...]}

The marks themselves live in the fleet model (``FleetModel.marks``, by markId, newest wins), with
the ones other consoles placed: the store only names, writes and reads them.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from fleetlink.shared import wire
from fleetlink.shared.messages import Mark

__all__ = ["MarksStore", "mark_from_record", "mark_record"]

log = logging.getLogger(__name__)

MAX_ID = 64
MAX_KIND = 32
MAX_LABEL = 64


def mark_record(mark: Mark) -> dict[str, Any]:
    """One mark as the file keeps it."""
    return {
        "markId": mark.markId,
        "x": mark.x,
        "y": mark.y,
        "label": mark.label,
        "kind": mark.kind,
        "by": mark.header.sender,
        "robot": mark.header.robot,
        "timestamp": mark.header.timestamp,
    }


def mark_from_record(record: dict[str, Any]) -> Mark:
    """A mark read back from the file, validated like one off the wire (ValueError, KeyError or
    TypeError if it is not one)."""
    header = wire.Header(
        headerId=0,
        timestamp=float(record["timestamp"]),
        version=wire.WIRE_VERSION,
        robot=record["robot"],
        sender=record["by"],
    )
    mark = Mark(
        header=header,
        markId=record["markId"],
        x=float(record["x"]),
        y=float(record["y"]),
        label=record["label"],
        kind=record["kind"],
        removed=False,
    )
    wire.encode(mark)  # validates: sizes, types, finite numbers
    return mark


class MarksStore:
    """This console's marks: new ones named, all of them saved to and loaded from ``path``
    (None: nothing is written or read)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._seq = 0

    def new(self, header: wire.Header, x: float, y: float, kind: str, label: str, wall: float) -> Mark:
        """The next mark this console places; ``header`` is its wire header (sender, robot), a
        missing label is the kind, and over-long texts are cut to what the wire allows."""
        self._seq += 1
        return Mark(
            header=header,
            markId=f"{header.sender}-{int(wall)}-{self._seq}"[:MAX_ID],
            x=x,
            y=y,
            label=label[:MAX_LABEL] or kind,
            kind=kind[:MAX_KIND],
            removed=False,
        )

    def save(self, marks: Iterable[Mark]) -> None:
        if self.path is None:
            return
        document = {"marks": [mark_record(m) for m in marks]}
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(document, indent=2) + "\n")
        tmp.replace(self.path)  # atomic: a crash leaves the old file or the new one, never half

    def load(self) -> list[Mark]:
        """The marks in the file, [] if there is none. A bad file is logged and read no further
        (the marks before the bad one are kept)."""
        if self.path is None or not self.path.exists():
            return []
        marks: list[Mark] = []
        try:
            data = json.loads(self.path.read_text())
            for record in data.get("marks", []):
                marks.append(mark_from_record(record))
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            log.warning("marks file %s ignored: %s", self.path, exc)
        return marks
