"""The fleet map service: one map of the site, built from every robot's onboard map and served on
the link like a robot's map (``fleetlink/v1/fleet/map``, patches on ``.../fleet/map/updates``).

    service = FleetMapService(follower, lock, clock, share=MapShare(link, keys.FLEET_MAP, clock), query=link)
    fetcher = MapFetcher(follower, fetch, clock, lock, after_poll=service.step)   # operator/maps.py

The robots' maps are followed as the console follows them (``MapFollower``: a snapshot per robot,
then its patches, a fresh snapshot when one is missed). ``step()`` (after each fetch round, at most
every ``period_s``) copies the maps that changed under the lock, hands them to the pure core
(agent/mapping/fleetmap.py: inter-robot registration, the site frame, the merge) outside it, puts
the result in the fleet model as the grid ``keys.FLEET_MAP`` (the console's map draws it instead
of the robots' own maps) and publishes it on ``share`` when its cells changed.

With ``query`` (a link that answers queries), each robot's map goes to the core with its submaps:
the build asks each robot for its submap list (``fleetlink/v1/<robot>/map/submaps``: index, version
and pose of each, as its pose graph has them now) and fetches only the submaps whose version it
lacks (``.../map/submap/<index>``, or ``.../submap/*`` for many), so the fleet map is merged from the
robots' optimised submaps, each placed on its own. A robot that lists no submaps (no loop closure)
is merged whole.

Two hosts: the console (cli/console.py), on its own link, so the demo's console serves the fleet
map that ``fleetlink map save --fleet`` fetches; and ``fleetlink map fleet``, a process of its own
for a site with a router (cli/map.py ``run_fleet``).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from fleetlink.agent.mapping.fleetmap import FleetMap, FleetMapConfig, FleetResult, RobotMap, Submap
from fleetlink.agent.mapping.keeper import MapPublication
from fleetlink.agent.mapping.share import MapShare, fetch_submap, fetch_submaps, submap_of
from fleetlink.links.base import QueryLink
from fleetlink.operator.maps import MapFollower, to_grid
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.map_codec import SharedMap, fits_whole
from fleetlink.shared.messages import FleetFrames, RobotFrame
from fleetlink.shared.se2 import apart

__all__ = ["FleetMapService", "publication_of"]

log = logging.getLogger(__name__)

PERIOD_S = 2.0
"""Seconds between builds while the robots' maps change (each robot shares its map every second)."""
QUERY_TIMEOUT_S = 2.0
FRAMES_PERIOD_S = 5.0
"""``FleetFrames`` go out when they change and at least this often (a client that joins later)."""
FRAMES_MOVED_M = 0.01
FRAMES_MOVED_RAD = math.radians(0.1)
"""A frame that moved less than this is not a change worth sending at once."""
FETCH_PER_BUILD = 16
"""Submaps fetched per robot per build at most (one query each): a console that meets a robot with
hundreds of submaps catches up over a few builds, merging its map whole meanwhile."""
POSE_MARGIN_M = 10.0
"""How far outside its robot's shared map a listed submap may lie (its cells reach its sensor's
range from its frame): a list that puts one further is not believed (the map is merged whole)."""


@dataclass
class _Submaps:
    """A robot's submaps as fetched: of the map begun at ``began``, by index."""

    began: float
    held: dict[int, Submap] = field(default_factory=dict)
    bad: set[tuple[int, int]] = field(default_factory=set)
    """(index, version) whose cells did not decode: not asked for again until redrawn."""


class FleetMapService:
    def __init__(
        self,
        follower: MapFollower,
        lock: threading.Lock,
        clock: Clock,
        *,
        share: MapShare | None = None,
        period_s: float = PERIOD_S,
        config: FleetMapConfig | None = None,
        on_built: Callable[[FleetResult], None] | None = None,
        query: QueryLink | None = None,
    ) -> None:
        self.follower = follower
        self.lock = lock
        self.clock = clock
        self.share = share
        self.period_s = period_s
        self.core = FleetMap(config or FleetMapConfig())
        self.on_built = on_built
        self.result: FleetResult | None = None
        self.builds = 0
        self._next = -float("inf")
        self._seen: dict[str, tuple[float, int]] = {}  # each map (its began, version) as last built from
        self._published: MapPublication | None = None
        self.query = query
        self._submaps: dict[str, _Submaps] = {}
        self.submaps_fetched = 0
        self.submaps_refused = 0
        """Submap replies left out: cells that do not decode, a bad reply, another map's or robot's."""
        self._logged: set[tuple[str, str]] = set()
        self._incomplete = False  # some robot's listed submaps are still being fetched: build again
        # Per robot: its map as last asked about (began, version, shape, origin) and the answer then.
        self._answered: dict[str, tuple[object, tuple[Submap, ...], bool]] = {}
        self._site_frames: dict[str, bool] = {}  # each robot's map frame as its list last said
        self._began: dict[str, float] = {}  # each robot's map as its list last said (``MapSubmaps.began``)
        self._built_began: dict[str, float] = {}  # the same, for the maps the last build was made of
        self._frame_states: dict[str, tuple[str, str]] = {}  # per robot: what was last logged of its frame
        # The frames, robots not found and maps' ``began`` as last published.
        self._frames_sent: tuple[dict[str, tuple[float, float, float]], tuple[str, ...], dict[str, float]] | None = None
        self._frames_next = -float("inf")

    def step(self) -> bool:
        """Build and publish if the robots' maps changed and ``period_s`` has passed. True if built."""
        now = self.clock.now()
        if self.result is not None and now >= self._frames_next:
            self._publish_frames(self.result, now)  # again now and then: for whoever joined since
        if now < self._next:
            return False
        with self.lock:
            maps = {r: m for r, m in self.follower.maps.items() if r != keys.FLEET_MAP}
            versions = {r: (m.began, m.version) for r, m in maps.items()}
            if versions == self._seen and not self._incomplete and not self.core.pending:
                return False
            copies = {r: SharedMap(m.cells.copy(), m.resolution, m.origin, m.version, m.began) for r, m in maps.items()}
        self._next = now + self.period_s
        for robot in set(self.core.maps) - set(copies):
            self.core.forget(robot)
        for robot in set(self._submaps) - set(copies):
            del self._submaps[robot]
        for robot in set(self._answered) - set(copies):
            del self._answered[robot]
        for robot in set(self._site_frames) - set(copies):
            del self._site_frames[robot]
        for robot in set(self._began) - set(copies):
            del self._began[robot]
        self._incomplete = False
        for robot, m in copies.items():
            try:
                fetched = self._fetch(robot, m)
                if fetched is None:
                    # The copy is of a map its robot has left (its agent restarted): left out until the
                    # new one is fetched, lest it be placed, and its frame sent, as the new one's.
                    self.core.forget(robot)
                    self._incomplete = True
                    continue
                submaps, site_frame = fetched
                self.core.put(robot, RobotMap(m.cells, m.resolution, m.origin, m.version, submaps, site_frame))
            except ValueError as exc:
                self._log_once(robot, "put", f"its map left out: {exc}")
        try:
            result = self.core.build()
        except ValueError as exc:  # maps placed absurdly far apart: wait for them to change
            self._log_once("*", "build", f"not built: {exc}")
            result = None
        self._seen = versions
        if result is None:
            return False
        self.result = result
        # Each frame is of the map its cells came from: the copy's (a sender before 1.2.0: its list's).
        self._built_began = {r: m.began or self._began.get(r, 0.0) for r, m in copies.items()}
        self.builds += 1
        with self.lock:
            self.follower.fleet.set_grid(
                keys.FLEET_MAP, to_grid(SharedMap(result.cells, result.resolution, result.origin, result.version))
            )
            self.follower.fleet.set_frames(result.frames, result.unframed, self.core.global_why, self._built_began)
        self._log_frames(result, copies)
        if self._frames_changed(result):
            self._publish_frames(result, now)
        if self.share is not None:
            pub = publication_of(result, self._published)
            if self._published is None or pub.version != self._published.version:
                self.share.publish(pub)
                self._published = pub
        if self.on_built is not None:
            self.on_built(result)
        return True

    def _frames_changed(self, result: FleetResult) -> bool:
        """The frames moved (beyond ``FRAMES_MOVED_M`` / ``FRAMES_MOVED_RAD``: every build refines them
        by millimetres), came, went, or the robots not found changed since last published."""
        sent = self._frames_sent
        if sent is None or set(sent[0]) != set(result.frames) or sent[1] != tuple(sorted(result.unframed)):
            return True
        if any(self._built_began.get(r) != sent[2].get(r) for r in result.frames):
            return True  # a map begun again, found where the old one was
        return any(apart(f, sent[0][r], FRAMES_MOVED_M, FRAMES_MOVED_RAD) for r, f in result.frames.items())

    def _publish_frames(self, result: FleetResult, now: float) -> None:
        """``FleetFrames`` on ``fleetlink/v1/fleet/frames`` (on the share's link): where the robots in
        their own frames lie on the fleet map, for clients that draw them (Foxglove, a recorder)."""
        self._frames_next = now + FRAMES_PERIOD_S
        self._frames_sent = (dict(result.frames), tuple(sorted(result.unframed)), dict(self._built_began))
        if self.share is None:
            return
        frames = tuple(
            RobotFrame(
                robot=r, x=f[0], y=f[1], theta=math.remainder(f[2], math.tau), began=self._built_began.get(r, 0.0)
            )
            for r, f in sorted(result.frames.items())
        )
        site = any(r not in result.frames for r in result.corrections)
        reference = "" if site or not result.frames else min(result.frames)
        msg = self.share.counter.make(
            FleetFrames, reference=reference, frames=frames, unframed=tuple(sorted(result.unframed))
        )
        self.share.link.publish(wire.key_of(msg), wire.encode(msg))

    def _fetch(self, robot: str, m: SharedMap) -> tuple[tuple[Submap, ...], bool] | None:
        """``robot``'s submaps at the poses its graph gives them now, once every listed one is held;
        () until then, and when it lists none (its map is then merged whole); and whether its map is
        in the site frame, as its list says (a robot that does not answer, as it last said; the site's
        if it never did). Only the
        submaps whose version is not held are fetched, at most ``FETCH_PER_BUILD`` a build. Bad
        replies are left out, counted and logged once per robot and reason; a link that fails
        leaves the map whole. None: the copy ``m`` is of another map than the one the robot lists
        (``began``: its agent restarted since the copy was fetched)."""
        if self.query is None:
            return (), True
        # A robot's submaps change only as its map does (a solve that moves them redraws the map):
        # while its map keeps its version, the answer stands and the robot is not asked again.
        seen = (m.began, m.version, m.cells.shape, m.origin)
        memo = self._answered.get(robot)
        if memo is not None and memo[0] == seen:
            return memo[1], memo[2]
        try:
            listing = fetch_submaps(self.query, robot, QUERY_TIMEOUT_S)
        except Exception as exc:  # one robot's failed query must not stop the build for the others
            self._log_once(robot, "list", f"its submap list could not be asked for: {exc}")
            return (), self._site_frames.get(robot, True)
        if listing is None:
            # No answer (lost, or an agent that predates the list): its frame as last heard, the
            # site's if never; asked again at the next build (an answer lost is not remembered).
            return (), self._site_frames.get(robot, True)
        self._site_frames[robot] = listing.site_frame
        if self._began.get(robot, listing.began) != listing.began:
            self.core.forget(robot)  # a map begun again: nothing registered of the old one holds
        self._began[robot] = listing.began
        if m.began and listing.began != m.began:
            return None  # the copy is of another map than the robot lists now
        if not listing.submaps:  # loop closure off: its map whole, in the frame the list says
            self._answered[robot] = (seen, (), listing.site_frame)
            return (), listing.site_frame
        h, w = m.cells.shape
        x0, y0 = m.origin[0] - POSE_MARGIN_M, m.origin[1] - POSE_MARGIN_M
        x1, y1 = m.origin[0] + w * m.resolution + POSE_MARGIN_M, m.origin[1] + h * m.resolution + POSE_MARGIN_M
        far = [e.index for e in listing.submaps if not (x0 <= e.x <= x1 and y0 <= e.y <= y1)]
        if far:
            self._log_once(robot, "far", f"its list puts submap {far[0]} outside its map: merged whole")
            return (), listing.site_frame
        known = self._submaps.get(robot)
        if known is None or known.began != listing.began:
            known = self._submaps[robot] = _Submaps(listing.began)
        listed = {e.index: e for e in listing.submaps}
        for i in set(known.held) - set(listed):
            del known.held[i]
        missing = [
            e.index
            for e in listing.submaps
            if (e.index not in known.held or known.held[e.index].version != e.version)
            and (e.index, e.version) not in known.bad
        ]
        rejected: list[str] = []
        for index in missing[:FETCH_PER_BUILD]:
            try:
                replies = fetch_submap(self.query, robot, index, QUERY_TIMEOUT_S, rejected=rejected)
            except Exception as exc:
                self._log_once(robot, "fetch", f"its submaps could not be asked for: {exc}")
                break
            for msg in replies:
                if msg.began != known.began or msg.index != index or msg.version != listed[index].version:
                    rejected.append(f"submap {msg.index} version {msg.version} of the map begun at {msg.began}")
                    continue
                try:
                    known.held[index] = submap_of(msg)
                    self.submaps_fetched += 1
                except ValueError as exc:
                    known.bad.add((index, msg.version))
                    rejected.append(f"submap {index}: {exc}")
        if rejected:
            self.submaps_refused += len(rejected)
            self._log_once(robot, "rejected", f"submap reply left out: {rejected[0]} (further ones counted)")
        pending = [
            (i, e.version) for i, e in listed.items() if i not in known.held or known.held[i].version != e.version
        ]
        if pending:
            # Not all held yet: merged whole meanwhile, and built again at the next period even if no
            # map changes (a robot standing still); one that does not decode waits for its redrawing.
            self._incomplete |= any(p not in known.bad for p in pending)
            return (), listing.site_frame
        out = tuple(replace(known.held[i], pose=(e.x, e.y, e.theta)) for i, e in sorted(listed.items()))
        self._answered[robot] = (seen, out, listing.site_frame)
        return out, listing.site_frame

    def _log_frames(self, result: FleetResult, copies: dict[str, SharedMap]) -> None:
        """Say when a robot's map changes frames, and when one in its own frame is found or lost."""
        for robot in copies:
            held = self.core.maps.get(robot)
            own = held is not None and not held.map.site_frame
            state = "unframed" if robot in result.unframed else ("own frame" if own else "site frame")
            why = self.core.global_why.get(robot, "")
            if self._frame_states.get(robot) != (state, why):
                self._frame_states[robot] = (state, why)
                where = result.frames.get(robot)
                at = "" if where is None else f" at ({where[0]:.2f}, {where[1]:.2f}, {math.degrees(where[2]):.1f} deg)"
                log.info("fleet map: %s: %s%s%s", robot, state, at, f" ({why})" if why else "")

    def _log_once(self, robot: str, kind: str, text: str) -> None:
        if (robot, kind) not in self._logged:
            self._logged.add((robot, kind))
            log.warning("fleet map: %s: %s", robot, text)


def publication_of(result: FleetResult, previous: MapPublication | None) -> MapPublication:
    """The fleet map as a share publishes it: the box that changed since ``previous`` when the two
    are on the same cells, the whole map when it grew or moved (a receiver then fetches it again)."""
    cells = result.cells
    h, w = cells.shape
    changed: tuple[int, int, int, int] | None = (0, 0, h, w)
    if previous is not None and previous.cells.shape == cells.shape and previous.origin == result.origin:
        rows, cols = np.nonzero(previous.cells != cells)
        changed = (
            None if not len(rows) else (int(rows.min()), int(cols.min()), int(rows.max()) + 1, int(cols.max()) + 1)
        )
    if not fits_whole(cells):
        changed = None  # served coarser as a snapshot; no patch would apply
    return MapPublication(result.version, cells, result.resolution, result.origin, changed, site_frame=True)
