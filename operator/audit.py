"""The console's alarm audit log: one JSON object per line, appended, flushed line by line.

``AuditLog(path, console)``: ``write(records)`` appends each ``AuditRecord`` (operator/alarms.py)
as a line, with this console's login, and flushes after every line, so a crash loses at most the
line being written; a line is never rewritten. ``path`` None: nothing is written. A file that
cannot be opened or written is logged once and the console goes on without it. A line::

    {"at": 1767225612.5, "console": "op-alice", "event": "acknowledged", "robot": "r1",
     "kind": "estop", "severity": "critical", "text": "e-stop remote", "by": "op-bob",
     "since": 1767225600.25, "count": 1}

``event``: raised, escalated, renotified, cleared, acknowledged, refused (an acknowledgement
refused, with the reason as ``text``). Times are seconds since the Unix epoch.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import IO

from fleetlink.operator.alarms import AuditRecord

__all__ = ["AuditLog"]

log = logging.getLogger(__name__)


class AuditLog:
    def __init__(self, path: Path | None, console: str) -> None:
        self.path = path
        self.console = console
        self.lines = 0
        """Lines written since this log was opened."""
        self._file: IO[str] | None = None
        self._failed = False

    def write(self, records: Iterable[AuditRecord]) -> None:
        for record in records:
            line = json.dumps({"at": record.at, "console": self.console, **record.as_dict()}, separators=(", ", ": "))
            self._line(line)

    def _line(self, line: str) -> None:
        if self.path is None or self._failed:
            return
        try:
            if self._file is None:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 -- kept open, closed in close()
            self._file.write(line + "\n")
            self._file.flush()
        except OSError as exc:
            self._failed = True
            log.warning("alarm audit log %s: %s; no more audit lines are written", self.path, exc)
            return
        self.lines += 1

    def close(self) -> None:
        f, self._file = self._file, None
        if f is not None:
            try:
                f.close()
            except OSError as exc:
                log.warning("alarm audit log %s: %s", self.path, exc)
