"""The console's alarms on screen and on the wire: the alarm panel and ``AlarmKeeper``.

``alarm_lines`` (pure) renders the active alarms, one line each (severity, robot, alarm, first and
last seen as ages, count, who acknowledged); ``AlarmPanel`` shows them under the robot detail and
hides itself while there are none. ``AlarmKeeper`` is the console's side of its ``AlarmDesk``
(operator/alarms.py): on a clock of its own (``check_links``, a share of the robots each time) it
tells the desk which robots went quiet on every link and which have a degraded link
(``LinkHealth.degraded``); once per frame (``frame``) it collects the renotifications, writes the audit log (operator/audit.py) and publishes this
console's acknowledgements (``AlarmAck``: on Zenoh, and retained on MQTT when the source can); it
publishes them all again after every broker (re)connect, so a broker that lost its retained
messages gets them back.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from rich.text import Text
from textual.widgets import Static

from fleetlink.operator.alarms import (
    AckEntry,
    AckOutcome,
    Alarm,
    AlarmDesk,
    AlarmKind,
    AlarmSeverity,
    AuditEvent,
    links_quiet,
)
from fleetlink.operator.audit import AuditLog
from fleetlink.operator.feed import ConsoleSource
from fleetlink.operator.linkmanager import FALLBACK, PRIMARY
from fleetlink.shared import wire
from fleetlink.shared.messages import AlarmAck

__all__ = ["MAX_LINES", "AlarmKeeper", "AlarmPanel", "Said", "ago", "alarm_lines", "link_states_of"]

log = logging.getLogger(__name__)

MAX_LINES = 5
"""Alarm lines shown; the rest are counted on the last line."""

QUIET_CHECK_S = 0.5
"""How often the robots' link ages are looked at for ``link_lost`` (as the console's clock tick)."""

SEVERITY_STYLE = {
    AlarmSeverity.CRITICAL: ("CRIT", "bold white on red"),
    AlarmSeverity.WARNING: ("WARN", "bold yellow"),
    AlarmSeverity.INFO: ("INFO", "cyan"),
}


def ago(seconds: float) -> str:
    """``4s``, ``2m05``, ``1h07``: compact ages."""
    s = max(0, int(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}"
    return f"{s // 3600}h{s // 60 % 60:02d}"


def alarm_lines(alarms: Sequence[Alarm], now: float, me: str, selected: str | None = None) -> Text:
    """The panel's text: a title, then one line per alarm (unacknowledged first); the selected
    robot's in bold."""
    out = Text("alarms  (A acknowledges; :ack ROBOT KIND|all)", style="dim")
    for alarm in alarms[:MAX_LINES]:
        tag, style = SEVERITY_STYLE[alarm.severity]
        who = "" if alarm.acked_by is None else f"ack {'you' if alarm.acked_by == me else alarm.acked_by}"
        line = Text("\n")
        line.append(tag, style=style if alarm.acked_by is None else "dim")
        rest = (
            f" {alarm.robot[:10]:<10} {alarm.label[:13]:<13} {ago(now - alarm.first_seen):>5} "
            f"{ago(now - alarm.last_seen):>5} x{alarm.count:<3} {who[:14]}"
        )
        line.append(rest.rstrip(), style="bold" if alarm.robot == selected else "")
        out.append_text(line)
    if len(alarms) > MAX_LINES:
        out.append(f"\n... {len(alarms) - MAX_LINES} more", style="dim")
    return out


class AlarmPanel(Static):
    """``alarm_lines`` on screen; hidden while no alarm is active."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("", **kwargs)
        self._shown: tuple[str, tuple[Any, ...]] | None = None

    def show(self, text: Text, any_alarm: bool) -> None:
        key = (text.plain, tuple(text.spans))
        if key != self._shown:
            self._shown = key
            self.update(text)
        self.display = any_alarm


def link_states_of(source: ConsoleSource) -> Callable[[str], Sequence[tuple[str, float | None, str]]]:
    """``AlarmKeeper.frame``'s ``links`` for ``source``: its ``link_states`` (``OperatorLink``,
    the replay), else made from its ``health``."""
    states: Callable[[str], Sequence[tuple[str, float | None, str]]] | None = getattr(source, "link_states", None)
    if states is not None:
        return states
    return lambda robot: [(h.link, h.age_s, h.degraded) for h in source.health(robot)]


@dataclass(frozen=True, slots=True)
class Said:
    """What the console should tell the operator after a frame: a notice, and whether to ring."""

    severity: str
    text: str
    bell: bool = False


class AlarmKeeper:
    """See the module docstring. ``frame`` and ``acknowledge`` are called with the fleet model's
    lock held (the desk is part of the model); they hand back what to publish, which
    ``publish`` sends outside the lock."""

    def __init__(self, source: ConsoleSource, desk: AlarmDesk, audit: AuditLog) -> None:
        self.source = source
        self.desk = desk
        self.audit = audit
        self._republish = threading.Event()
        self._quiet_checked = -math.inf
        self._quiet_next = 0
        """Where the next share of the robots starts (``check_links``)."""
        listen = getattr(source, "add_connect_listener", None)
        if listen is not None:
            listen(self._republish.set)  # on the broker's thread: only a flag

    def forget(self) -> None:
        """Look at every robot's links afresh (a replay seeking back: its clock went back, the desk
        was forgotten)."""
        self._quiet_checked = -math.inf
        self._quiet_next = 0

    def check_links(
        self, wall: float, robots: Iterable[str], links: Callable[[str], Sequence[tuple[str, float | None, str]]]
    ) -> None:
        """The link alarms (link quiet, a link degraded) for the share of ``robots`` due at ``wall``
        (the console's wall clock): called as often as the caller likes, each robot is looked at
        about every ``QUIET_CHECK_S``, in turn, so no call does the whole fleet (but the first, and
        one after a pause as long as that). ``links(robot)``: each of its links' (name, age of the
        last message, why it is degraded), ``OperatorLink.link_states`` (``link_states_of`` makes
        it for any source)."""
        desk = self.desk
        fleet = list(robots)
        share = min(1.0, (wall - self._quiet_checked) / QUIET_CHECK_S) if wall > self._quiet_checked else 0.0
        count = min(len(fleet), math.ceil(len(fleet) * share)) if fleet else 0
        if not count:
            return
        self._quiet_checked = wall
        start = self._quiet_next % len(fleet)
        self._quiet_next = start + count
        for robot in (fleet * 2)[start : start + count] if start + count > len(fleet) else fleet[start : start + count]:
            states = links(robot)
            quiet = links_quiet([age for _, age, _ in states])
            desk.link_quiet(robot, quiet, wall)
            # One link degraded while the robot is still heard (silent on all: link_lost).
            desk.link_degraded(robot, [] if quiet else [(link, why) for link, _, why in states if why], wall)

    def frame(
        self,
        wall: float,
        robots: Iterable[str] = (),
        links: Callable[[str], Sequence[tuple[str, float | None, str]]] | None = None,
    ) -> tuple[list[Said], list[tuple[str, tuple[AckEntry, ...]]]]:
        """Once per frame (``wall``: the console's wall clock): renotifications, the audit log, and
        with ``links`` the link alarms' share of ``robots`` (``check_links``; the console looks at
        them on a clock of its own, between frames). Returns what to tell the operator and the
        acknowledgement lists to publish."""
        desk = self.desk
        if links is not None:
            self.check_links(wall, robots, links)
        desk.tick(wall)
        records = desk.drain_audit()
        self.audit.write(records)
        said: list[Said] = []
        for r in records:
            if r.event is AuditEvent.RENOTIFIED:
                said.append(Said("error", f"ALARM {r.robot}: {r.text} ({r.kind}) still unacknowledged", bell=True))
            elif r.event in (AuditEvent.RAISED, AuditEvent.ESCALATED) and r.severity == AlarmSeverity.CRITICAL:
                said.append(Said("error", f"ALARM {r.robot}: {r.text} ({r.kind})", bell=True))
            elif r.event is AuditEvent.ACKNOWLEDGED and r.by != desk.operator:
                said.append(Said("info", f"{r.robot}: {r.kind} acknowledged by {r.by}"))
        outgoing = desk.outgoing()
        if self._republish.is_set():
            self._republish.clear()
            outgoing = desk.published()
        return said, outgoing

    def acknowledge(self, robot: str, kind: AlarmKind | None, wall: float, *, every: bool = False) -> AckOutcome:
        """This operator acknowledges (see ``AlarmDesk.acknowledge``)."""
        return self.desk.acknowledge(robot, kind, wall, every=every)

    def publish(
        self, header: Callable[[str, str], wire.Header], lists: Sequence[tuple[str, tuple[AckEntry, ...]]]
    ) -> None:
        """Publish each (robot, acknowledgements) as an ``AlarmAck``: on Zenoh, and retained on MQTT
        when the source can (else on both links as is)."""
        retained = getattr(self.source, "publish_retained", None)
        for robot, entries in lists:
            msg = AlarmAck(header=header(AlarmAck.TOPIC, robot), acks=tuple(e.wire() for e in entries))
            try:
                if retained is not None:
                    self.source.publish(msg, links=(PRIMARY,))
                    retained(msg)
                else:
                    self.source.publish(msg, links=(PRIMARY, FALLBACK))
            except Exception as exc:  # a dead transport must not take the console down
                log.warning("publishing the acknowledgements of %s failed: %s", robot, exc)

    def close(self) -> None:
        self.audit.write(self.desk.drain_audit())
        self.audit.close()
