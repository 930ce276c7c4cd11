"""What the network tells the console, carried into the fleet model.

``FleetFeed`` subscribes once to a console source (``OperatorLink``: decoded messages, link
switches and lost commands, UWB gateways' anchors, robots' liveliness tokens coming and going)
and folds each into a ``FleetModel`` (and map updates into the ``MapFollower``, dose updates into the
``DoseFollower``, and what shows or
acknowledges an alarm into the model's ``AlarmDesk``, operator/alarms.py). It works in one of two ways:

* **bound to an app** (``bind(wake)``, what ``ConsoleApp`` does while it runs): a network thread
  only appends what it heard to an inbox and, if no wake-up is pending yet, calls ``wake()``
  (the app posts itself a Textual message). The app's own thread then calls ``drain()``, which
  folds everything waiting into the model. A burst of hundreds of messages costs one wake-up, and
  the model is only ever written on the UI thread by the network side. A robot's pose that comes
  while an older one of its poses still waits takes that one's place (``conflated``): a busy app
  folds each robot's latest pose, so a console behind 500 robots x 20 Hz catches up instead of
  falling further behind; the poses passed over still leave their points on the robot's trail.
* **unbound** (headless, before the app starts, after it stops): each item is folded in at once
  on the network thread.

Either way under ``lock``: the fleet model is also read by the marks queryable and written by the
map fetcher (operator/maps.py), each on its own thread.

One feed per fleet model: ``attach`` for a model that already has one returns that one, so a
caller that attached the model (cli, tests) and the app that shows it share it.

A replay (site/replay.py) seeks: while it does, the feed folds in at once on the seeking thread
(``at_once``), and a seek back first has it forget everything heard (``forget``: the one way a
console's state goes back to a new console's) before the recording plays again from its start.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, cast

from fleetlink.operator.dose import DoseFollower
from fleetlink.operator.fleet import TRAIL_POINTS, FleetModel
from fleetlink.operator.linkmanager import PRIMARY, Failed, LinkHealth, Switch
from fleetlink.operator.maps import MapFollower
from fleetlink.shared import wire
from fleetlink.shared.keys import FLEET_MAP
from fleetlink.shared.messages import AlarmAck, Connection, DoseUpdate, MapUpdate, Pose

__all__ = ["AnchorsHeard", "ConsoleSource", "FleetFeed", "Heard", "LinkEvent", "PresenceHeard", "attach"]

log = logging.getLogger(__name__)


class ConsoleSource(Protocol):
    """What the console needs from the network side (``OperatorLink`` provides it)."""

    sender: str

    def send(self, cls: type[wire.Message], robot: str, *, expect_ack: bool = True, **fields: Any) -> wire.Message: ...

    def publish(self, msg: wire.Message, *, links: Sequence[str] = ...) -> None: ...

    def active(self, robot: str) -> str: ...

    def health(self, robot: str) -> tuple[LinkHealth, ...]: ...

    def add_listener(self, listener: Callable[[Switch | Failed], None]) -> None: ...

    def add_sink(self, sink: Callable[[wire.Message, str, float], None]) -> None: ...


@dataclass(frozen=True, slots=True)
class Heard:
    """A decoded message, the link it came on, and when (the link's clock)."""

    msg: wire.Message
    link: str
    now: float


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """The link manager moved a robot's commands, or gave up on a command."""

    action: Switch | Failed


@dataclass(frozen=True, slots=True)
class AnchorsHeard:
    """A UWB gateway's status: its anchors (id, x, y, z)."""

    gateway: str
    anchors: tuple[tuple[str, float, float, float], ...]


@dataclass(frozen=True, slots=True)
class PresenceHeard:
    """A robot's liveliness token appeared (``alive``) or went, on ``link``, at ``wall``."""

    robot: str
    link: str
    alive: bool
    wall: float


Item = Heard | LinkEvent | AnchorsHeard | PresenceHeard

_feeds: weakref.WeakValueDictionary[int, FleetFeed] = weakref.WeakValueDictionary()
"""id(fleet model) -> its feed. Weak: a feed lives as long as its source holds its callbacks."""
_feeds_lock = threading.Lock()


class FleetFeed:
    def __init__(
        self,
        source: ConsoleSource,
        fleet: FleetModel,
        lock: threading.Lock,
        maps: MapFollower | None = None,
        doses: DoseFollower | None = None,
    ) -> None:
        self.source = source
        self.fleet = fleet
        self.lock = lock
        self.maps = maps
        self.doses = doses
        self.applied = 0
        """Items folded into the model so far (either way)."""
        self.conflated = 0
        """Poses that came while an older one of the same robot still waited, and took its place."""
        self._inbox: deque[Item | tuple[str, str]] = deque()
        """What waits for the app, in order; a robot's pose as its (robot, sender), whose latest
        pose is in ``_poses``."""
        self._poses: dict[tuple[str, str], Heard] = {}
        self._passed: dict[tuple[str, str], list[tuple[float, float]]] = {}
        """Where a robot was at the poses its waiting one took the place of (for its trail)."""
        self._wake: Callable[[], bool] | None = None
        self._wake_pending = False
        self._inbox_lock = threading.Lock()
        """Guards the binding and the pending flag, never the model: network threads hold it for
        an append, so they never wait on the UI."""
        source.add_sink(lambda msg, link, now: self._put(Heard(msg, link, now)))
        source.add_listener(lambda action: self._put(LinkEvent(action)))
        add_anchor_sink = getattr(source, "add_anchor_sink", None)
        if add_anchor_sink is not None:
            add_anchor_sink(lambda gateway, found: self._put(AnchorsHeard(gateway, tuple(found))))
        add_presence_sink = getattr(source, "add_presence_sink", None)
        if add_presence_sink is not None:
            add_presence_sink(lambda robot, link, alive, wall: self._put(PresenceHeard(robot, link, alive, wall)))
        clock = getattr(source, "clock", None)
        self._wall: Callable[[], float] | None = getattr(clock, "wall", None)
        self._at_once = 0
        """Inside ``at_once``: items are folded in on the source's thread, as unbound."""
        self._forget_listeners: list[Callable[[], None]] = []
        add_restart_listener = getattr(source, "add_restart_listener", None)
        if add_restart_listener is not None:  # a replay seeking back plays again from its start
            add_restart_listener(self.forget)

    def forget(self) -> None:
        """Forget everything heard, as a new feed would have heard nothing: what waits in the
        inbox, the fleet model (robots, marks, alarms, notices), the maps and dose layers, then what
        the listeners (``on_forget``: the app's alarm keeper and notices) keep, all under ``lock``.
        The one way a console's state is reset: a replay seeking back (site/replay.py) calls it on
        its own thread before it plays again from the recording's start."""
        with self.lock:
            with self._inbox_lock:
                self._inbox.clear()
                self._poses.clear()
                self._passed.clear()
            self.fleet.forget()
            if self.maps is not None:
                self.maps.forget()
            if self.doses is not None:
                self.doses.forget()
            for listener in self._forget_listeners:
                listener()

    def on_forget(self, listener: Callable[[], None]) -> None:
        """``listener()`` is called by ``forget``, with ``lock`` held, on the source's thread."""
        self._forget_listeners.append(listener)

    @contextlib.contextmanager
    def at_once(self) -> Iterator[None]:
        """While inside, what the source says is folded in at once on the thread that says it, as
        unbound: a replay's seek applies everything up to its target at once, as ``--start`` does,
        with the replay's clock where it is then (not queued for the UI to fold later). What waited
        is folded first, under the same hold of ``lock``, so the order holds."""
        with self.lock:
            with self._inbox_lock:
                self._at_once += 1
            self._fold()
        try:
            yield
        finally:
            with self._inbox_lock:
                self._at_once -= 1

    # -- the app's side -------------------------------------------------------------------------

    def bind(self, wake: Callable[[], bool]) -> None:
        """From now on items wait in the inbox; ``wake()`` is called (from a network thread) when
        the first one arrives after a ``drain``. It returns False if the app can no longer take
        messages (shutting down): the items then wait for ``unbind``."""
        with self._inbox_lock:
            self._wake = wake
            self._wake_pending = False

    def unbind(self) -> None:
        """Back to folding items in at once; whatever waits in the inbox is folded in now."""
        with self._inbox_lock:
            self._wake = None
        self.drain()

    def drain(self, budget_s: float | None = None) -> int:
        """Fold what waits into the model (the app's thread). How many items.

        With ``budget_s`` it stops once that much time went (checked every few items) and leaves
        the rest waiting (``pending``): the app folds it in slices, so a key press queued behind
        a burst of telemetry waits one slice, not the whole burst."""
        with self._inbox_lock:
            self._wake_pending = False  # cleared first: an item that comes during the drain wakes again
        with self.lock:
            return self._fold(budget_s)

    def _fold(self, budget_s: float | None = None) -> int:
        """``drain``'s work (the caller holds ``lock``)."""
        n = 0
        inbox = self._inbox
        end = None if budget_s is None else time.perf_counter() + budget_s
        while inbox:
            item = inbox.popleft()
            if isinstance(item, tuple):  # a robot's pose: the latest that came
                with self._inbox_lock:
                    slot, item = item, self._poses.pop(item)
                    passed = self._passed.pop(slot, None)
                if passed:  # the poses it took the place of: their points on the trail
                    self.fleet.trail_through(slot[0], passed)
            self._apply(item)
            n += 1
            if end is not None and n % 32 == 0 and time.perf_counter() >= end:
                break
        return n

    @property
    def pending(self) -> bool:
        """Items wait in the inbox (a budgeted ``drain`` left them)."""
        return bool(self._inbox)

    # -- the network's side ---------------------------------------------------------------------

    def _put(self, item: Item) -> None:
        with self._inbox_lock:
            wake = self._wake if not self._at_once else None
            if wake is not None:
                self._queue(item)
                if self._wake_pending:
                    return
                self._wake_pending = True
        if wake is None:
            with self.lock:
                self._apply(item)
            return
        if not wake():
            with self._inbox_lock:
                self._wake_pending = False

    def _queue(self, item: Item) -> None:
        """Into the inbox (the caller holds ``_inbox_lock``). A robot's pose takes the place of
        one of its poses still waiting (the newer of the two, by header id): while the app is
        busy (a frame, a burst) it folds each robot's latest pose once, not every pose that came
        meanwhile, so what it has to do is bounded by the robots, not by their rate."""
        if isinstance(item, Heard) and isinstance(item.msg, Pose):
            header = item.msg.header
            slot = (header.robot, header.sender)
            waiting = self._poses.get(slot)
            if waiting is None:
                self._poses[slot] = item
                self._inbox.append(slot)
                return
            self.conflated += 1
            if header.headerId > waiting.msg.header.headerId:  # (not a copy from the other link)
                passed = self._passed.setdefault(slot, [])
                before = cast(Pose, waiting.msg)
                if len(passed) < TRAIL_POINTS:
                    passed.append((before.x, before.y))
                self._poses[slot] = item
            return
        self._inbox.append(item)

    def _apply(self, item: Item) -> None:
        """Fold one item into the model (the caller holds ``lock``)."""
        self.applied += 1
        fleet = self.fleet
        if isinstance(item, Heard):
            msg = item.msg
            if msg.header.robot == FLEET_MAP:
                return  # another host's fleet map: no robot, and this console builds its own
            wall = self._wall() if self._wall is not None else msg.header.timestamp
            if isinstance(msg, AlarmAck):
                self._refused(fleet.alarms.receive_ack(msg, wall), msg)
            elif fleet.apply(msg, item.link, item.now):
                if self.maps is not None and isinstance(msg, MapUpdate):
                    self.maps.on_update(msg)
                elif self.doses is not None and isinstance(msg, DoseUpdate):
                    self.doses.on_update(msg)
                fleet.alarms.observe(msg, wall)
                if isinstance(msg, Connection):
                    fleet.presence(msg.header.robot, fleet.alarms.present(msg.header.robot))
        elif isinstance(item, PresenceHeard):
            fleet.alarms.presence(item.robot, item.link, item.alive, item.wall)
            fleet.presence(item.robot, fleet.alarms.present(item.robot))
        elif isinstance(item, AnchorsHeard):
            for name, x, y, _z in item.anchors:
                fleet.add_anchor(name, x, y)
        elif isinstance(item.action, Switch):
            action = item.action
            severity = "warning" if action.to_link != PRIMARY else "info"
            fleet.notify(action.at, severity, f"failover: {action.describe()}")
        else:
            failed = item.action
            fleet.notify(0.0, "error", f"{failed.robot}: {failed.topic} #{failed.header_id} lost: {failed.reason}")

    def _refused(self, reason: str | None, msg: AlarmAck) -> None:
        if reason is not None and self.fleet.alarms.refused[reason] == 1:  # once per reason
            log.warning(
                "refused an alarm acknowledgement from %s on %s: %s", msg.header.sender, msg.header.robot, reason
            )


def attach(
    source: ConsoleSource,
    fleet: FleetModel,
    lock: threading.Lock,
    maps: MapFollower | None = None,
    doses: DoseFollower | None = None,
) -> FleetFeed:
    """The feed of ``fleet`` from ``source``: made (and subscribed) the first time, the same one
    after that (``lock`` is then the first call's; ``maps`` and ``doses`` the first given)."""
    with _feeds_lock:
        feed = _feeds.get(id(fleet))
        if feed is None or feed.fleet is not fleet or feed.source is not source:
            feed = _feeds[id(fleet)] = FleetFeed(source, fleet, lock, maps, doses)
        else:
            if maps is not None and feed.maps is None:
                feed.maps = maps
            if doses is not None and feed.doses is None:
                feed.doses = doses
        return feed
