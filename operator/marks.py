"""Marks: naming, merging, the console's marks file, the retained sets, the incident export.
Pure apart from the files at the paths given.

A mark (``Mark``) is identified by ``markId``; a newer version of it (an edit, or ``removed`` for a
removal) is a new ``Mark`` with the same ``markId`` and a newer ``header.timestamp``, written by
whichever console edited it (its ``header.sender`` is that version's author). Every console keeps
the newest version of every mark (``supersedes``/``merge``: newest ``header.timestamp`` wins, the
sender id breaks a tie), wherever it came from: a live ``Mark`` on either link, a console's
retained ``MarkSet`` (MQTT), a Zenoh marks query, the marks file.

* ``MarksStore(path)``: ``new(...)`` builds this console's next mark (ids ``<sender>-<wall
  seconds>-<n>``, unique per console), ``save(marks)`` rewrites the file atomically (a temporary
  file renamed over it), ``load()`` reads it back. The file is JSON::

      {"marks": [{"markId": ..., "x": ..., "y": ..., "label": ..., "kind": ..., "sd_m": ...,
                  "removed": false, "by": <sender>, "robot": <robot>, "timestamp": <wall s>}, ...]}

  Removed marks stay in it (tombstones): a console restarted from its file must not bring a
  removed mark back when another console still holds an older version.
* ``revised(old, header, ...)``: an edit or a removal of ``old``; ``find_mark(marks, ref)``: a
  mark by its id or a unique ``-``-separated tail of it (``:mark rm 1712345678-3``, ``rm 3``).
* ``own_sets(marks, login)``: per robot, the marks whose newest version ``login`` wrote, bounded
  (``bound_set``: oldest tombstones left out first, then the oldest marks) -- what each console
  keeps retained on MQTT as a ``MarkSet``; ``SetTracker`` says which sets changed since they were
  last sent; ``set_message``/``marks_of_set`` convert.
* ``marks_csv``, ``marks_geojson``, ``export_marks(marks, path)``: the incident report's export,
  in the site frame (metres).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from fleetlink.shared import wire
from fleetlink.shared.messages import MAX_MARK_LABEL, MAX_MARK_SET, Mark, MarkEntry, MarkSet

__all__ = [
    "CSV_COLUMNS",
    "DEFAULT_KIND",
    "MARK_KINDS",
    "MAX_KIND",
    "MAX_LABEL",
    "MarksStore",
    "SetTracker",
    "bound_set",
    "export_marks",
    "find_mark",
    "iso_utc",
    "mark_from_record",
    "mark_record",
    "marks_csv",
    "marks_geojson",
    "marks_of_set",
    "merge",
    "own_sets",
    "revised",
    "set_message",
    "supersedes",
    "version_key",
]

log = logging.getLogger(__name__)

MAX_ID = 64
MAX_KIND = 32
MAX_LABEL = MAX_MARK_LABEL
MARK_KINDS = ("casualty", "hazard", "note")
"""The kinds the console offers (the wire takes any text up to ``MAX_KIND`` characters)."""
DEFAULT_KIND = "casualty"
MAX_SD_M = 1000.0
"""The wire's bound on ``Mark.sd_m``."""
EDIT_STEP_S = 0.001
"""An edit is at least this much newer than the version it edits, whatever the editor's clock says."""


# -- versions and merging ----------------------------------------------------------------------


def version_key(mark: Mark) -> tuple[float, str]:
    """What orders two versions of one mark: the newest ``header.timestamp``, then the sender id."""
    return (mark.header.timestamp, mark.header.sender)


def supersedes(new: Mark, old: Mark | None) -> bool:
    """Whether ``new`` replaces ``old`` (a version of the same mark, or None); the same version
    again (heard on both links, in a set and live) does not."""
    return old is None or version_key(new) > version_key(old)


def merge(held: Mapping[str, Mark], incoming: Iterable[Mark]) -> dict[str, Mark]:
    """``held`` (markId -> newest version) with ``incoming`` merged in: a new dict, in any order of
    arrival the same result."""
    out = dict(held)
    for mark in incoming:
        if supersedes(mark, out.get(mark.markId)):
            out[mark.markId] = mark
    return out


def revised(
    old: Mark, header: wire.Header, *, label: str | None = None, kind: str | None = None, removed: bool | None = None
) -> Mark:
    """A new version of ``old`` (same markId, place, robot and uncertainty) by ``header.sender``:
    a new label or kind, or removed. Its timestamp is ``header``'s, but never earlier than just
    after ``old``'s (an editor whose clock is behind still edits)."""
    stamp = max(header.timestamp, old.header.timestamp + EDIT_STEP_S)
    return dataclasses.replace(
        old,
        header=dataclasses.replace(header, timestamp=stamp, robot=old.header.robot),
        label=old.label if label is None else label,
        kind=old.kind if kind is None else kind,
        removed=old.removed if removed is None else removed,
    )


def find_mark(marks: Mapping[str, Mark], ref: str) -> Mark | str:
    """The live mark ``ref`` names: its id, or a unique tail of it after a ``-`` (``3``,
    ``1712345678-3``). Otherwise the reason, as a notice says it."""
    exact = marks.get(ref)
    if exact is not None:
        return exact if not exact.removed else f"mark {ref} was removed already"
    found = [m for m in marks.values() if not m.removed and m.markId.endswith("-" + ref)]
    if len(found) == 1:
        return found[0]
    if not found:
        return f"no mark {ref!r} (ids are shown when marks are placed, and by ':marks')"
    ids = ", ".join(sorted(m.markId for m in found)[:5])
    return f"{ref!r} names {len(found)} marks ({ids}{', ...' if len(found) > 5 else ''}): type more of the id"


# -- the retained sets ---------------------------------------------------------------------------


def entry_of(mark: Mark) -> MarkEntry:
    return MarkEntry(
        markId=mark.markId,
        x=mark.x,
        y=mark.y,
        label=mark.label,
        kind=mark.kind,
        sd_m=mark.sd_m,
        removed=mark.removed,
        timestamp=mark.header.timestamp,
    )


def marks_of_set(msg: MarkSet) -> list[Mark]:
    """The set's entries as ``Mark``s by its sender under its robot (header ids 0)."""
    h = msg.header
    return [
        Mark(
            header=wire.Header(headerId=0, timestamp=e.timestamp, version=h.version, robot=h.robot, sender=h.sender),
            markId=e.markId,
            x=e.x,
            y=e.y,
            label=e.label,
            kind=e.kind,
            sd_m=e.sd_m,
            removed=e.removed,
        )
        for e in msg.marks
    ]


def set_message(header: wire.Header, marks: Iterable[Mark]) -> MarkSet:
    """The ``MarkSet`` holding ``marks`` (all by ``header.sender`` under ``header.robot``)."""
    return MarkSet(header=header, marks=tuple(entry_of(m) for m in marks))


def bound_set(marks: Iterable[Mark], limit: int = MAX_MARK_SET) -> tuple[Mark, ...]:
    """At most ``limit`` marks, oldest first: beyond it the oldest tombstones are left out first,
    then the oldest marks (they still travel live and in the Zenoh answers; a tombstone left out
    can let a late console see an older version of that mark again)."""
    ordered = sorted(marks, key=version_key)
    if len(ordered) <= limit:
        return tuple(ordered)
    live = [m for m in ordered if not m.removed][-limit:] if limit > 0 else []
    room = limit - len(live)
    dead = [m for m in ordered if m.removed][-room:] if room > 0 else []
    return tuple(sorted(live + dead, key=version_key))


def own_sets(marks: Iterable[Mark], login: str, limit: int = MAX_MARK_SET) -> dict[str, tuple[Mark, ...]]:
    """robot -> the marks (newest versions, removed ones included) that ``login`` wrote under it,
    bounded by ``bound_set``."""
    by_robot: dict[str, list[Mark]] = {}
    for mark in marks:
        if mark.header.sender == login:
            by_robot.setdefault(mark.header.robot, []).append(mark)
    return {robot: bound_set(ms, limit) for robot, ms in by_robot.items()}


def _content(marks: Iterable[Mark]) -> frozenset[MarkEntry]:
    return frozenset(entry_of(m) for m in marks)


class SetTracker:
    """Which of this console's sets to (re)publish. Pure.

    ``due(sets)`` gives the robots whose set differs from what the broker was last told (sent by
    us, or heard back from it after a restart: ``heard``), an empty set included when a robot's
    marks have all become someone else's; ``resend()`` (after a reconnect) makes every known set
    due once more.
    ``sent(robot, marks)`` records a set the broker took.
    """

    def __init__(self) -> None:
        self._held: dict[str, frozenset[MarkEntry]] = {}
        """robot -> what the broker holds for us (as far as we know)."""
        self._resend = False

    def due(self, sets: Mapping[str, Sequence[Mark]]) -> list[tuple[str, tuple[Mark, ...]]]:
        robots = sorted(set(sets) | set(self._held))
        out = []
        for robot in robots:
            marks = tuple(sets.get(robot, ()))
            if self._resend or self._held.get(robot) != _content(marks):
                out.append((robot, marks))
        self._resend = False
        return out

    def sent(self, robot: str, marks: Iterable[Mark]) -> None:
        self._held[robot] = _content(marks)

    def heard(self, robot: str, marks: Iterable[Mark]) -> None:
        """Our own set for ``robot`` as the broker returned it: what it holds from an earlier run
        (a restart), compared from now on. Ignored for a robot whose set this run already sent or
        heard (the broker echoing what we sent: an echo of an older set must not make a newer one
        look unsent)."""
        self._held.setdefault(robot, _content(marks))

    def resend(self) -> None:
        self._resend = True


# -- the marks file ------------------------------------------------------------------------------


def mark_record(mark: Mark) -> dict[str, Any]:
    """One mark as the file keeps it."""
    return {
        "markId": mark.markId,
        "x": mark.x,
        "y": mark.y,
        "label": mark.label,
        "kind": mark.kind,
        "sd_m": mark.sd_m,
        "removed": mark.removed,
        "by": mark.header.sender,
        "robot": mark.header.robot,
        "timestamp": mark.header.timestamp,
    }


def mark_from_record(record: dict[str, Any]) -> Mark:
    """A mark read back from the file, validated like one off the wire (ValueError, KeyError or
    TypeError if it is not one). Files written before ``sd_m`` and ``removed`` read as 0 and false."""
    header = wire.Header(
        headerId=0,
        timestamp=float(record["timestamp"]),
        version=wire.WIRE_VERSION,
        robot=record["robot"],
        sender=record["by"],
    )
    removed = record.get("removed", False)
    if not isinstance(removed, bool):
        raise TypeError(f"removed: expected true or false, got {removed!r}")
    mark = Mark(
        header=header,
        markId=record["markId"],
        x=float(record["x"]),
        y=float(record["y"]),
        label=record["label"],
        kind=record["kind"],
        sd_m=float(record.get("sd_m", 0.0)),
        removed=removed,
    )
    wire.encode(mark)  # validates: sizes, types, finite numbers
    return mark


def _write_atomically(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8", newline="")
    tmp.replace(path)  # atomic: a crash leaves the old file or the new one, never half


class MarksStore:
    """This console's marks: new ones named, all of them saved to and loaded from ``path``
    (None: nothing is written or read)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._seq = 0

    def new(
        self, header: wire.Header, x: float, y: float, kind: str, label: str, wall: float, sd_m: float = 0.0
    ) -> Mark:
        """The next mark this console places; ``header`` is its wire header (sender, robot), a
        missing label is the kind, over-long texts are cut to what the wire allows (the console
        refuses them before this), ``sd_m`` capped at the wire's bound."""
        self._seq += 1
        return Mark(
            header=header,
            markId=f"{header.sender}-{int(wall)}-{self._seq}"[:MAX_ID],
            x=x,
            y=y,
            label=label[:MAX_LABEL] or kind[:MAX_LABEL],
            kind=kind[:MAX_KIND],
            sd_m=min(MAX_SD_M, max(0.0, sd_m)),
            removed=False,
        )

    def save(self, marks: Iterable[Mark]) -> None:
        if self.path is None:
            return
        document = {"marks": [mark_record(m) for m in marks]}
        _write_atomically(self.path, json.dumps(document, indent=2) + "\n")

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


# -- the incident report's export ------------------------------------------------------------------

CSV_COLUMNS = ("markId", "kind", "label", "x_m", "y_m", "sd_m", "robot", "by", "time_utc")
FRAME_NOTE = (
    "coordinates are metres in the site (map/UWB) frame, x east-ish and y north-ish as the site's "
    "plan draws them, not WGS84 longitude/latitude: RFC 7946 allows another CRS only by prior "
    "arrangement, and this is it"
)


def iso_utc(timestamp: float) -> str:
    """Epoch seconds as ISO 8601 UTC to the millisecond: ``2026-01-01T12:00:00.500Z``."""
    return datetime.fromtimestamp(timestamp, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _exported(marks: Iterable[Mark]) -> list[Mark]:
    """The live marks, oldest first (removed ones are not in the report)."""
    return sorted((m for m in marks if not m.removed), key=lambda m: (m.header.timestamp, m.markId))


def _cell(text: str) -> str:
    # A spreadsheet would run a cell starting with these as a formula (CSV injection): a label is
    # anyone's words, so such a text is shown as text.
    return "'" + text if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text


def _metres(value: float) -> str:
    return f"{value:.3f}" if math.isfinite(value) else ""


def marks_csv(marks: Iterable[Mark]) -> str:
    """One row per live mark, oldest first, columns ``CSV_COLUMNS`` (metres, site frame)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\r\n")
    writer.writerow(CSV_COLUMNS)
    for m in _exported(marks):
        writer.writerow(
            [
                _cell(m.markId),
                _cell(m.kind),
                _cell(m.label),
                _metres(m.x),
                _metres(m.y),
                _metres(m.sd_m),
                m.header.robot,
                m.header.sender,
                iso_utc(m.header.timestamp),
            ]
        )
    return buf.getvalue()


def marks_geojson(marks: Iterable[Mark]) -> dict[str, Any]:
    """A GeoJSON FeatureCollection of Points, one per live mark, coordinates ``[x, y]`` in metres
    in the site frame (``"frame": "site"`` in the collection and in every feature's properties;
    see ``FRAME_NOTE``)."""
    features = [
        {
            "type": "Feature",
            "id": m.markId,
            "geometry": {"type": "Point", "coordinates": [round(m.x, 3), round(m.y, 3)]},
            "properties": {
                "markId": m.markId,
                "kind": m.kind,
                "label": m.label,
                "sd_m": round(m.sd_m, 3),
                "robot": m.header.robot,
                "by": m.header.sender,
                "time_utc": iso_utc(m.header.timestamp),
                "frame": "site",
            },
        }
        for m in _exported(marks)
    ]
    return {"type": "FeatureCollection", "frame": "site", "units": "m", "note": FRAME_NOTE, "features": features}


def export_marks(marks: Iterable[Mark], path: Path) -> int:
    """Write the live marks to ``path``: CSV for ``.csv``, GeoJSON for ``.geojson``/``.json``
    (atomically). Returns how many; ValueError for another suffix, OSError if it cannot be written."""
    live = _exported(marks)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        text = marks_csv(live)
    elif suffix in (".geojson", ".json"):
        text = json.dumps(marks_geojson(live), indent=2, ensure_ascii=False) + "\n"
    else:
        raise ValueError(f"{path}: the export is .csv or .geojson, not {path.suffix or 'no suffix'!r}")
    _write_atomically(path, text)
    return len(live)
