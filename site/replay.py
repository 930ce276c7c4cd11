"""Replay a flight recording into the console (``fleetlink replay``, docs/recording.md).

``ReplaySource`` is a console data source (operator/feed.py ``ConsoleSource``) that plays an MCAP
file made by the recorder: each recorded wire message goes to the console's sinks with the link it
came on and its receive time, UWB gateway status to the anchor sinks, liveliness to the presence
sinks, at the recorded times scaled by ``speed``. The link manager (operator/linkmanager.py, pure)
hears the robots' messages as the live console's did, so the link and health columns show what
they showed then (without the commands: a replay sends none).

Its clock (``ReplayClock``) is the recording's: ``now()`` and ``wall()`` are the recorded receive
time being played (epoch seconds), so ages, lost robots and alarms read as they did live. It stops
at the end of the recording: the console then shows the fleet as the recording left it.

Reading: the file is never held. ``FleetStream`` (site/recorder.py) reads a file closed properly
through its MCAP index (the summary when it opens, then each chunk when the time being played
reaches it, in receive-time order), a recovered file in file order; the source keeps an iterator
and the next message only, so an hour-long recording costs what one chunk does.

Seeking: ``start_s`` (seconds after the first message) fast-forwards through everything before it
at once, so the fleet model holds the state at that moment, and plays on from there; ``seek(t)``
does the same while playing (the fleet model is cumulative, so the chunks before the target are
needed, the ones after it are not read until played): forward from where it is, each chunk read
once; back, from the recording's start again, after the restart listeners (the console's
``FleetFeed.forget``) forgot what they heard. ``set_speed(x)`` changes the speed: the console's
``:seek`` and ``:speed``.

Snapshots: the console asks a robot's map and dose layer as it asks a live robot's queryable
(``fetch_map``, ``fetch_dose``), and gets what the robot would have answered at the time being
played: the last recorded snapshot (the recorder fetched it when the robot's updates could not be
applied) brought up to date with every recorded update played since. So a console that fetches
late still follows the updates that come after (each one follows its copy), as it did live.
Read-only: ``send`` and ``publish`` refuse (and count); the console runs read-only and says so.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import threading
from collections import Counter
from collections.abc import Callable, Generator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fleetlink.operator.linkmanager import Failed, LinkHealth, LinkManager, LinkPolicy, Switch
from fleetlink.operator.links import ROBOT_TOPICS
from fleetlink.shared import dose_codec, map_codec, wire, wire_json
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.dose_codec import SharedDose
from fleetlink.shared.map_codec import SharedMap
from fleetlink.shared.messages import DoseSnapshot, DoseUpdate, MapSnapshot, MapUpdate
from fleetlink.shared.worker import Worker
from fleetlink.site.recorder import FleetStream, RecordingError, StoredMessage

__all__ = ["ReadOnlyReplay", "ReplayClock", "ReplaySource"]

log = logging.getLogger(__name__)

SENDER = "replay"
POLL_S = 0.02
"""The link manager's poll period in recorded time: the live console's (operator/links.py, 50 Hz)."""
MAX_POLL_GAP_S = 5.0
JUMP_WAIT_S = 5.0
"""How long a fetch waits for a start or seek under way (then: no answer, asked again later)."""


class ReadOnlyReplay(RuntimeError):
    """A replay sends nothing: the recording is what happened."""


class ReplayClock:
    """The recording's time while it plays (a ``Clock``): ``now()`` = ``wall()`` = the recorded
    receive time (epoch seconds) being played; waits and sleeps run on the real clock."""

    def __init__(self, start: float, real: Clock | None = None) -> None:
        self.real: Clock = real or SystemClock()
        self._lock = threading.Lock()
        self._pos = start
        self._real0 = self.real.now()
        self._speed = 0.0
        self._end = math.inf

    def now(self) -> float:
        with self._lock:
            return min(self._end, self._pos + (self.real.now() - self._real0) * self._speed)

    def wall(self) -> float:
        return self.now()

    def run(self, position: float, speed: float, end: float = math.inf) -> None:
        """From now on time goes from ``position`` at ``speed`` times real time, up to ``end``."""
        with self._lock:
            self._pos, self._real0, self._speed, self._end = position, self.real.now(), speed, end

    def hold(self, position: float) -> None:
        with self._lock:
            self._pos, self._real0, self._speed = position, self.real.now(), 0.0

    def sleep_until(self, deadline: float) -> None:
        self.real.sleep_until(self.real.now() + max(0.0, deadline - self.now()))

    def wait(self, event: threading.Event, timeout: float | None) -> bool:
        return self.real.wait(event, timeout)


def _stopped(metadata: dict[str, dict[str, str]]) -> float:
    try:
        value = float(metadata.get("fleetlink.recording", {}).get("stopped", "0"))
    except ValueError:
        return 0.0
    return value if math.isfinite(value) else 0.0


class ReplaySource:
    """Plays ``path`` into the console's sinks. ``start()`` plays in real time x ``speed``;
    ``play_until(t)`` delivers everything up to recorded time ``t`` at once (tests, seeking)."""

    def __init__(
        self, path: Path | str, *, speed: float = 1.0, start_s: float = 0.0, real: Clock | None = None
    ) -> None:
        if not (speed > 0 and math.isfinite(speed)):
            raise ValueError(f"speed must be a positive number, got {speed}")
        if start_s < 0:
            raise ValueError(f"start must be >= 0 s, got {start_s}")
        stream = FleetStream(path)
        if not stream.count or stream.first_ns is None or stream.last_ns is None:
            stream.close()
            why = f": {stream.problem}" if stream.problem else ""
            raise RecordingError(f"{path}: no fleet messages to replay{why}")
        self.path = Path(path)
        self.stream = stream
        """The recording, read as it plays (``FleetStream``: chunk by chunk through its index)."""
        self.complete = stream.complete
        self.sender = SENDER
        self.speed = speed
        self.total = stream.count
        """Fleet messages in the recording."""
        self.first = stream.first_ns / 1e9
        self.last = max(stream.last_ns / 1e9, _stopped(stream.metadata))
        """Where the recording ends: when the recorder stopped (a crashed one: its last message)."""
        self.start_at = min(self.last, self.first + start_s)
        self.clock = ReplayClock(self.first, real)
        self.refused: Counter[str] = Counter()
        """Commands and publishes the console tried (a read-only console tries none)."""
        self._lock = threading.Lock()
        self._playing = threading.RLock()
        """Held while messages are read and delivered (the player, a seek from the console)."""
        self._sinks: list[Callable[[wire.Message, str, float], None]] = []
        self._listeners: list[Callable[[Switch | Failed], None]] = []
        self._anchor_sinks: list[Callable[[str, list[tuple[str, float, float, float]]], None]] = []
        self._presence_sinks: list[Callable[[str, str, bool, float], None]] = []
        self._restart_listeners: list[Callable[[], None]] = []
        self._copies_lock = threading.Lock()
        self._player: Worker | None = None
        self._still = threading.Event()
        """Clear while a start or seek applies what comes before its target: a fetch waits for it."""
        self._still.set()
        self._from_the_start()

    def _from_the_start(self) -> None:
        """Everything played is forgotten and the recording is read again from its first message
        (a closed file: through its index; a recovered one: in file order again), as when the
        source was made; then the restart listeners forget what they heard (the console's
        ``FleetFeed.forget``). The clock waits at the first message, as it does while ``start``
        fast-forwards, so what is applied now reads as it does in a replay started there."""
        with self._playing:
            played = getattr(self, "_messages", None)
            if played is not None:
                played.close()  # its chunk let go
            self._messages: Generator[StoredMessage, None, None] = self.stream.messages()
            self._peek: StoredMessage | None = next(self._messages, None)
            self._delivered = 0
            self._played_to = -math.inf
            """The latest time played up to (``play_until``): a seek before it starts again."""
            self._polled: float | None = None
            with self._lock:
                self.manager = LinkManager(LinkPolicy(redundant=True))
                """As the consoles' default (redundant sending: the link column says ``both``,
                nothing fails over); a recording does not say how the recorded console sent."""
            self.skipped: Counter[str] = Counter()
            """Recorded messages that no longer decode, by reason."""
            with self._copies_lock:
                self._snapshots: dict[tuple[str, str], MapSnapshot | DoseSnapshot] = {}
                """(robot, topic) -> the last recorded snapshot (its header and fields, to answer with)."""
                self._copies: dict[tuple[str, str], SharedMap | SharedDose] = {}
                """(robot, topic) -> that snapshot brought up to date with the updates played since."""
                self._answers: dict[tuple[str, str], MapSnapshot | DoseSnapshot] = {}
                """(robot, topic) -> the last snapshot built from a copy (rebuilt when the copy's version moved)."""
            self.clock.hold(self.first)
            for listener in self._restart_listeners:
                listener()

    # -- ConsoleSource --------------------------------------------------------------------------

    def send(self, cls: type[wire.Message], robot: str, *, expect_ack: bool = True, **fields: Any) -> wire.Message:
        self.refused[cls.TOPIC] += 1
        raise ReadOnlyReplay(f"a replay sends no commands ({cls.TOPIC} to {robot} refused)")

    def publish(self, msg: wire.Message, *, links: Sequence[str] = ("zenoh",)) -> None:
        self.refused[type(msg).TOPIC] += 1
        raise ReadOnlyReplay(f"a replay publishes nothing ({type(msg).TOPIC} refused)")

    def active(self, robot: str) -> str:
        with self._lock:
            return self.manager.route(robot)

    def health(self, robot: str) -> tuple[LinkHealth, ...]:
        with self._lock:
            return self.manager.health(robot, self.clock.now())

    def link_states(self, robot: str) -> tuple[tuple[str, float | None, str], ...]:
        """Each link's (name, age of the last message, why it is degraded): ``LinkManager.link_states``."""
        with self._lock:
            return self.manager.link_states(robot, self.clock.now())

    def add_listener(self, listener: Callable[[Switch | Failed], None]) -> None:
        self._listeners.append(listener)

    def add_sink(self, sink: Callable[[wire.Message, str, float], None]) -> None:
        self._sinks.append(sink)

    def add_anchor_sink(self, sink: Callable[[str, list[tuple[str, float, float, float]]], None]) -> None:
        self._anchor_sinks.append(sink)

    def add_presence_sink(self, sink: Callable[[str, str, bool, float], None]) -> None:
        self._presence_sinks.append(sink)

    def add_restart_listener(self, listener: Callable[[], None]) -> None:
        """``listener()`` is called when a seek back plays the recording again from its start, on
        the seeking thread, before anything is played again: forget what was heard."""
        self._restart_listeners.append(listener)

    def fetch_map(self, robot: str, timeout: float = 0.0) -> MapSnapshot | None:
        """The robot's map as it would have answered at the time being played: its last recorded
        snapshot with the recorded updates played since applied (None before its first snapshot)."""
        found = self._answer(robot, MapSnapshot.TOPIC)
        return found if isinstance(found, MapSnapshot) else None

    def fetch_dose(self, robot: str, timeout: float = 0.0) -> DoseSnapshot | None:
        """The robot's dose layer as it would have answered at the time being played (as ``fetch_map``)."""
        found = self._answer(robot, DoseSnapshot.TOPIC)
        return found if isinstance(found, DoseSnapshot) else None

    def _answer(self, robot: str, topic: str) -> MapSnapshot | DoseSnapshot | None:
        # Not while a seek jumps: the answer would be of a moment passed at once, and an update
        # played before the console took it would be lost to its copy.
        if not self._still.wait(JUMP_WAIT_S):
            return None
        key = (robot, topic)
        with self._copies_lock:
            recorded, copy = self._snapshots.get(key), self._copies.get(key)
            if recorded is None or copy is None or copy.version == recorded.version:
                return recorded
            built = self._answers.get(key)
            if built is not None and built.version == copy.version:
                return built  # (an answer of an earlier map is dropped when its snapshot is: ``_follow``)
            fields: dict[str, Any] | None
            if isinstance(copy, SharedMap):
                fields = dict(
                    map_codec.snapshot_fields(copy.cells, copy.resolution, copy.origin, copy.version, copy.began)
                )
            else:
                assert copy.lamp is not None  # (a copy is made from a snapshot, which names its lamp)
                fields = dose_codec.snapshot_fields(
                    copy.cells.astype(np.float64), copy.resolution, copy.origin, copy.version,
                    target_j_m2=copy.target_j_m2, lamp_on_s=copy.lamp_on_s, unplaced_s=copy.unplaced_s,
                    lamp=copy.lamp,
                )  # fmt: skip
                if fields is None:  # too many distinct doses to answer in one message: the recorded one
                    return recorded
            built = self._answers[key] = dataclasses.replace(recorded, **fields)
            return built

    def _follow(self, msg: wire.Message) -> None:
        """A recorded snapshot becomes the robot's copy; a played update brings it up to date."""
        key = (msg.header.robot, msg.TOPIC.removesuffix("/updates"))
        try:
            with self._copies_lock:
                if isinstance(msg, MapSnapshot):
                    self._snapshots[key], self._copies[key] = msg, SharedMap.from_snapshot(msg)
                    self._answers.pop(key, None)  # built from the copy it replaces (another map's, maybe)
                elif isinstance(msg, DoseSnapshot):
                    self._snapshots[key], self._copies[key] = msg, SharedDose.from_snapshot(msg)
                    self._answers.pop(key, None)
                elif isinstance(msg, MapUpdate | DoseUpdate):
                    copy = self._copies.get(key)
                    if copy is not None:
                        copy.apply(msg)  # type: ignore[arg-type]  # (a map's copy takes map updates)
        except (wire.WireError, ValueError) as exc:  # cells that cannot be right: as the console would
            self.skipped[f"bad {msg.TOPIC} cells: {exc}"[:200]] += 1

    def pending(self, robot: str) -> int:
        return 0

    # -- playing --------------------------------------------------------------------------------

    def start(self) -> ReplaySource:
        """Fast-forward to ``start_s``, then play on a worker at ``speed``."""
        self._go(self.start_at)
        self._player = Worker("replay-player", clock=self.clock.real, target=self._play).start()
        return self

    def close(self) -> None:
        """Stop playing and close the file (what was played stays with the sinks)."""
        if self._player is not None:
            self._player.stop()
            self._player = None
        self.stream.close()

    @property
    def problem(self) -> str | None:
        """What was wrong with the file (damage, truncation) where playing stopped, or None."""
        return self.stream.problem

    def seek(self, seconds: float) -> None:
        """Jump to ``seconds`` after the first message (past the end: the end), as ``start_s``
        does: forward, what lies between is played at once; back, the recording is played again
        from its start up to there (``_from_the_start``: the console forgets what it heard first).
        ``ValueError`` for a time that is not one (NaN, infinite, negative): nothing moves."""
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"seek to {seconds!r} refused: a time of 0 s or more into the recording")
        self._go(min(self.last, self.first + seconds))

    def _go(self, target: float) -> None:
        """Play everything up to ``target`` (epoch s) at once, from the recording's start again if
        it was played past already, then play on from there (``start``, ``seek``)."""
        with self._playing:
            self._still.clear()
            try:
                if target < self._played_to:
                    self._from_the_start()
                self.play_until(target)
                self.clock.run(target, self.speed, self.last)
            finally:
                self._still.set()
        if self._player is not None:
            self._player.wake()  # it may wait at the end

    def set_speed(self, speed: float) -> None:
        """Play at ``speed`` times real time from now on (the console's ``:speed``)."""
        if not (speed > 0 and math.isfinite(speed)):
            raise ValueError(f"speed must be a positive number, got {speed}")
        with self._playing:
            self.speed = speed
            if self._player is not None:  # playing: time goes on from here at the new speed
                self.clock.run(self.clock.now(), speed, self.last)

    @property
    def position(self) -> float:
        """Seconds after the first message of the time being played (what ``seek`` takes)."""
        return self.clock.now() - self.first

    @property
    def delivered(self) -> int:
        """Recorded messages played so far."""
        return self._delivered

    @property
    def done(self) -> bool:
        return self._peek is None

    def play_until(self, t: float) -> int:
        """Deliver every recorded message received at or before ``t`` (epoch s) not yet delivered,
        polling the link manager every ``POLL_S`` of recorded time in between, as the live
        console's link worker did (so failovers happen where they happened)."""
        n = 0
        limit = round(t * 1e9)
        with self._playing:
            while (stored := self._peek) is not None and stored.log_time_ns <= limit:
                self._poll_until(stored.log_time_ns / 1e9)
                self._peek = next(self._messages, None)
                self._delivered += 1
                self._deliver(stored)
                n += 1
            self._poll_until(t)
            self._played_to = max(self._played_to, t)
        return n

    def _poll_until(self, t: float) -> None:
        if self._polled is None:
            self._polled = t
        if t - self._polled > MAX_POLL_GAP_S:  # a long silence: its start and its end are enough
            self._poll(self._polled + POLL_S)
            self._polled = t - POLL_S
        while self._polled + POLL_S <= t:
            self._polled += POLL_S
            self._poll(self._polled)

    def _poll(self, t: float) -> None:
        with self._lock:
            actions = self.manager.poll(t)
        for action in actions:
            if isinstance(action, Switch | Failed):
                for listener in self._listeners:
                    listener(action)

    def _play(self, worker: Worker) -> None:
        while not worker.stopping:
            with self._playing:  # the time read under it: a seek meanwhile has moved it
                now = self.clock.now()
                self.play_until(now)
                ended = self.done and now >= self.last
                if ended:
                    self.clock.hold(self.last)
            worker.wait(None if ended else POLL_S)  # at the end: until a seek wakes it (or close)

    def _deliver(self, stored: StoredMessage) -> None:
        t = stored.log_time_ns / 1e9
        kind = stored.metadata.get("kind")
        link = stored.metadata.get("link", "zenoh")
        if kind == "alive":
            try:
                doc = json.loads(stored.data)
                robot, alive = str(doc["robot"]), bool(doc["alive"])
            except (ValueError, KeyError, TypeError) as exc:
                self.skipped[f"bad liveliness record: {exc}"] += 1
                return
            for presence in self._presence_sinks:
                presence(robot, link, alive, t)
            return
        if kind == "uwb-status":
            self._gateway(stored.data)
            return
        try:
            cls = wire.message_type(stored.metadata.get("wire_topic", ""))
            msg = wire_json.from_json(cls, stored.data)
        except (KeyError, wire.WireError) as exc:
            self.skipped[str(exc)[:200]] += 1
            return
        if isinstance(msg, MapSnapshot | DoseSnapshot):
            self._follow(msg)  # a queryable's answer: fetched, not heard
            return
        if isinstance(msg, MapUpdate | DoseUpdate):
            self._follow(msg)
        if msg.TOPIC in ROBOT_TOPICS:
            with self._lock:
                self.manager.heard(msg.header.robot, link, t)
        for sink in self._sinks:
            sink(msg, link, t)

    def _gateway(self, data: bytes) -> None:
        try:
            status = json.loads(data)["status"]
            gateway = str(status["gateway"])
            anchors = [(str(a[0]), float(a[1]), float(a[2]), float(a[3])) for a in status.get("anchors", [])]
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            self.skipped[f"bad UWB gateway status: {exc}"] += 1
            return
        for sink in self._anchor_sinks:
            sink(gateway, anchors)
