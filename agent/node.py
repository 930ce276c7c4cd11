"""One robot's agent as steps, with no thread of its own: inputs, the control step, the lidar step.

``AgentNode`` is the whole agent between its ports and its links: the core (gate -> operators ->
lease -> pilot -> guard; odometry -> fusion; telemetry), the board session, the map keeper
(mapping, frame restarts, planner renewal) and the map share. It moves bytes and time only:
every decision is in a pure core (``AgentCore``, ``MapKeeper``) and every wait belongs to
whoever calls it:

* in real time, ``AgentRuntime`` (runtime.py) runs the board session, a control worker and a
  lidar worker, and the links' delivery threads call ``on_input``;
* in lockstep, the site's run (``fleetlink.site.lockstep``) calls ``on_input`` as the in-process
  links deliver, ``board.tick()``, ``control(now)`` and ``lidar(now)`` in a fixed order under one
  ``SimClock``, so a seeded mission gives the same bytes twice.

One lock serialises every call into the core (link threads, control and lidar workers), so the
core stays single-threaded; mapping runs outside it, so it never holds up the control loop.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import threading
from collections.abc import Callable, Sequence
from typing import Any

from fleetlink.agent.board.session import BoardSession, PollRates
from fleetlink.agent.config import AgentConfig
from fleetlink.agent.contact import ContactKeeper
from fleetlink.agent.core import AgentCore, Output, board_view
from fleetlink.agent.dose_layer import DoseKeeper, DosePublication, DoseSample
from fleetlink.agent.fusion import Fusion, PoseObservation
from fleetlink.agent.home import HomeKeeper
from fleetlink.agent.mapping.keeper import MapKeeper, Turn, Update, onboard_mapper_config
from fleetlink.agent.mapping.mapper import MapperConfig
from fleetlink.agent.mapping.worker import KeeperHost
from fleetlink.agent.odometry import Odometry
from fleetlink.agent.peers import PeerBodies
from fleetlink.agent.pilot import PayloadRequest, Pilot, PilotConfig
from fleetlink.links.base import Link, QueryLink
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.dose import FloorMask
from fleetlink.shared.messages import (
    Connection,
    ConnectionState,
    FleetFrames,
    LeaseRequest,
    LinkName,
    LinkStatus,
    Pose,
    Scan,
    UwbFix,
)
from fleetlink.shared.scan_codec import scan_fields
from fleetlink.shared.se2 import compose, relative

__all__ = ["INPUTS", "LINK_STATUS_PERIOD_S", "POLL_RATES", "AgentNode", "input_keys", "pilot_config"]

log = logging.getLogger(__name__)

POLL_RATES = PollRates(motion=10.0, telemetry=20.0, motor=20.0, imu=20.0, sensors=20.0, bumpers=20.0, buttons=5.0)
"""The board poll rates the agent uses: wheel distances and the gyro at 20 Hz feed the odometry;
range sensors, bumpers and cliffs at 20 Hz feed the guard. A board with GET_TELEMETRY gives all
four in one exchange at 20 Hz (a quarter of the exchanges, on both ends of the line); a plain
SLAMTEC base is polled for each apart. Motion (SET_V_AND_GET_DEADRECKON) is
only a 10 Hz refresh: every new velocity is sent at once (``BoardSession.set_velocity``), so while
driving it goes out at the control rate anyway, and its dead reckoning is not what the odometry
uses. Every poll feeds the board's 1 s watchdog. Buttons at 5 Hz: the e-stop button latches the
e-stop (an e-stop button stays down until it is twisted free, and the board cuts the motors in
hardware meanwhile; the agent's latch and its report follow within 0.2 s); the home button raises
the pending base command (2 Hz)."""

INPUTS = ("order", "actions", "teleop", LeaseRequest.TOPIC, "zones", UwbFix.TOPIC)
"""The agent's input topics, on every link."""
_COMMANDS = ("order", "actions", "teleop", LeaseRequest.TOPIC)
"""The holder's commands, which jump the queue (its zones are no command: they wait their turn)."""
STOP_TOPICS = frozenset({"actions"})
"""Where anyone's stop, pause and e-stop travel (instant actions): after the holder, before the rest."""


MAX_TURN_S = 1.0
"""Longest interval between turns taken as a turn's length (an RPLIDAR turns at 2-10 Hz); longer
ones are a stalled or reopened lidar, not a turn, and must not backdate the next turns."""
PLACE_SD_THETA_RAD = math.radians(2.0)
"""The fused heading's standard deviation at which the onboard map starts in the site frame."""


def input_keys(robot: str, topic: str, operators: Sequence[str] = ()) -> list[str]:
    """What the agent subscribes for an input topic: a command topic under each allowed operator's
    name (``fleetlink/v1/<robot>/<topic>/<operator>``), or under every name when any operator may
    command it (``.../<topic>/*``); a fix topic as is.

    With an allowlist, what others send never reaches the agent: admission at the transport, and
    cheaper too -- Zenoh caches the route of a key its subscriber named, but works out a wildcard
    subscription's match for every sample (about 13 us more per message on this machine; under a
    10k msg/s flood that is the difference between keeping up and not)."""
    if topic not in keys.SENDER_TOPICS:
        return [keys.key(robot, topic)]
    if operators:
        return [keys.sender_key(robot, topic, op) for op in operators]
    return [keys.sender_filter(robot, topic)]


IDLE_PERIOD_S = 0.1
"""Longest gap between two ticks of an idle control loop (it ticks earlier for every pose, at
20 Hz by default). Idle, a tick at the control rate (50 Hz) would compute the same zero velocity
from the same sensor reading; each tick is a thread wake-up, which costs more than the tick itself
on a VM."""
LINK_STATUS_PERIOD_S = 0.2
"""How often the control step tells the core which links are up."""


def home_keeper(cfg: AgentConfig) -> HomeKeeper:
    """The robot's home keeper: its dock from the configuration, if it has one."""
    h = cfg.home
    if h is None:
        return HomeKeeper()
    return HomeKeeper((h.x, h.y, math.nan if h.theta_deg is None else math.radians(h.theta_deg)))


def pilot_config(cfg: AgentConfig) -> PilotConfig:
    from fleetlink.agent.guard import GuardConfig
    from fleetlink.agent.motion import MotionLimits

    lim = cfg.limits
    return PilotConfig(
        guard=GuardConfig(
            stop_distance_m=lim.stop_distance_m,
            allow_turn_in_place=lim.round_base,
            creep_speed_mps=lim.creep_speed_mps,
            brake_mps2=lim.a_max,
        ),
        limits=MotionLimits(v_max=lim.v_max, omega_max=lim.omega_max, a_max=lim.a_max, alpha_max=lim.alpha_max),
        teleop_ttl_s=lim.teleop_ttl_s,
    )


def mapper_config(cfg: AgentConfig) -> MapperConfig:
    """The robot's onboard mapper: legs laid for the ultrasonic cone unless its guard creeps; loop
    closure unless robot.toml's ``[mapping] loop_closure`` is false."""
    return onboard_mapper_config(cone=cfg.limits.creep_speed_mps == 0.0, closures=cfg.mapping.loop_closure)


HALT_TIMEOUT_S = 0.5
"""How long a shutting-down agent waits for the board to confirm the halt (zero velocity, payload
off); the board's watchdog stops the wheels 1 s after the agent goes quiet in any case."""


class AgentNode:
    def __init__(
        self,
        config: AgentConfig,
        clock: Clock,
        board: BoardSession,
        *,
        links: Sequence[Link] = (),
        map_link: QueryLink | None = None,
        scan_sink: Callable[[Any], None] | None = None,
    ) -> None:
        self.config = config
        self.clock = clock
        self.board = board
        robot = self.robot = config.robot
        self.core = AgentCore(
            robot,
            clock,
            Pilot(pilot_config(config)),
            odometry=Odometry(),
            fusion=Fusion(),
            map_id=config.map_id,
            pose_hz=config.rates.pose_hz,
            state_hz=config.rates.state_hz,
            operators=config.operators,
            home=home_keeper(config),
            contact=ContactKeeper(
                config.comms.policy, config.comms.timeout_s, payload_on_loss=config.comms.payload_on_loss
            ),
            peers=PeerBodies(config.peers),
        )
        self.links: list[Link] = list(links)
        self.map_link = map_link
        self.scan_sink = scan_sink
        self.pans_topic = f"dwm/node/{config.tag or robot}/uplink/location"
        self._keys = {topic: keys.key(robot, topic) for topic in _OUTPUT_TOPICS}
        self._lock = threading.Lock()
        self._conn_counter = wire.HeaderCounter(clock, robot=robot, sender=f"agent-{robot}")
        self._scan_key = keys.key(robot, Scan.TOPIC)
        self._next_scan = -float("inf")
        self._motor: object = None
        self._odom_t = 0.0
        self._next_links = -float("inf")
        self._holder: str | None = None  # none told to the links yet
        self.keeper: KeeperHost | None = None
        self._follows: tuple[float, ...] | None = None
        """The covariance of the last map pose the fusion took (``Turn.follows``)."""
        self.share: Any = None
        uv = config.uv
        self.dose: DoseKeeper | None = (
            DoseKeeper(uv.lamp, uv.target_j_m2, uv.dose_resolution_m) if uv is not None else None
        )
        """The UV dose layer (``[uv]`` configured): fed by the control step, its floor by the map."""
        self.dose_share: Any = None
        """Serves the dose layer on ``map_link`` (agent/dose_share.py), from its first publication."""
        self._lamp_unmodelled = False
        self._closed = False
        self.lidar_fault: str | None = None
        """Why the lidar is not delivering scans (None: it is, or there is none)."""
        self.scans = 0
        self.stale_turns = 0
        """Turns not mapped because a newer one was read with them (``add_revolutions``)."""
        self.published = 0
        self.halted = False
        """Set by ``halt``: inputs are dropped and nothing moves the robot any more (shutting down)."""
        self.on_started: Callable[[], None] | None = None
        """Called (outside the lock) when an input sets an idle robot moving: a real-time control
        loop sleeping until its next pose takes up the control rate at once."""

    # -- wiring -------------------------------------------------------------------------------------

    def subscribe(self) -> None:
        """Subscribe the agent's inputs on every link (PANS locations on MQTT too)."""
        for link in self.links:
            name = link.name

            def receive(key: str, payload: bytes, name: LinkName = name) -> None:
                self.on_input(name, key, payload)

            for topic in INPUTS:
                for key in input_keys(self.robot, topic, self.config.operators):
                    link.subscribe(key, receive)

            def peer(key: str, payload: bytes, name: LinkName = name) -> None:
                self.on_peer(name, key, payload)

            for robot in self.config.peers:
                link.subscribe(keys.key(robot, Pose.TOPIC), peer)
            if self.config.peers and name is LinkName.ZENOH:
                # Where the fleet map found robots without UWB (agent/peers.py): its service shares on
                # the console's Zenoh link (site/fleetmap.py), and the broker's ACL has no such topic.
                link.subscribe(keys.key(keys.FLEET_MAP, FleetFrames.TOPIC), peer)
            if name is LinkName.MQTT:
                link.subscribe(self.pans_topic, receive)

    def connection_payload(self, state: ConnectionState) -> bytes:
        """The retained ``Connection`` message (and the MQTT last will) for ``state``."""
        return wire.encode(self._conn_counter.make(Connection, connectionState=state))

    def open_map(self, keeper: KeeperHost | None = None) -> None:
        """Start mapping (a lidar is configured): the keeper (in line unless ``keeper`` says where
        it runs: agent/mapping/worker.py), and the share on ``map_link``."""
        self.keeper = keeper if keeper is not None else MapKeeper(mapper_config(self.config))
        self._open_share()

    def close(self) -> None:
        self._closed = True
        if self.share is not None:
            self.share.stop()
            self.share = None
        if self.dose_share is not None:
            self.dose_share.stop()
            self.dose_share = None

    # -- inputs ---------------------------------------------------------------------------------------

    def on_input(self, link: LinkName, key: str, payload: bytes) -> bool:
        """One payload from a link. True if it set an idle robot moving (the control loop should
        take up the control rate at once; a UWB fix never does)."""
        with self._lock:
            if self.halted:
                return False
            was_idle = not self.core.driving
            now = self.clock.now()
            if key == self.pans_topic:
                out = self.core.on_pans(link, key, payload, now)
            else:
                out = self.core.on_input(link, key, payload, now)
            self._apply(out)
            self._prioritise_holder(now)
            started = was_idle and self.core.driving
        if started and self.on_started is not None:
            self.on_started()
        return started

    def on_peer(self, link: LinkName, key: str, payload: bytes) -> None:
        """A peer's pose from a link (agent/peers.py): kept for planning, never a command."""
        with self._lock:
            if not self.halted:
                self._apply(self.core.on_peer(link, key, payload, self.clock.now()))

    # -- the control step -------------------------------------------------------------------------

    def control(self, now: float) -> float:
        """One control tick: links, board reading -> core -> velocity and telemetry. Returns when
        the next tick is due: a control period on while driving; idle, when the next pose is due."""
        with self._lock:
            if now >= self._next_links:
                self._next_links = now + LINK_STATUS_PERIOD_S
                self._apply(self.core.set_links(self._link_status(), now))
                counts = {link.name.value: (link.stats.oversized, link.stats.dropped) for link in self.links}
                self._apply(self.core.diagnostics(now, counts))
                self._prioritise_holder(now)  # a lease that ran out
            snap = self.board.snapshot
            if snap.motor is not self._motor:  # a fresh wheel reading: its poll time
                self._motor, self._odom_t = snap.motor, snap.updated
            view = board_view(snap, odom_t=self._odom_t)
            if self.lidar_fault is not None:  # reported in State.errors while it lasts
                view = dataclasses.replace(view, errors=(*view.errors, f"lidar: {self.lidar_fault}"))
            self._apply(self.core.tick(now, view))
            next_t = now + 1.0 / self.config.rates.control_hz
            if not self.core.driving:
                next_t = max(next_t, min(self.core.next_pose_at, now + IDLE_PERIOD_S))
            sample = self._dose_sample(now)
        if sample is not None and self.dose is not None:  # outside the lock: a footprint takes milliseconds
            pub = self.dose.step(sample)
            if pub is not None:
                self._publish_dose(pub)
        return next_t

    def _dose_sample(self, now: float) -> DoseSample | None:
        """What the dose keeper needs from this tick: the board's own report of the lamp, the fused
        pose, whether the robot is placed in the site frame (under the lock)."""
        lamp_on = self.core.board.payload_on
        if self.dose is None:
            if lamp_on and not self._lamp_unmodelled:
                self._lamp_unmodelled = True
                log.warning("%s: the UV lamp is on but robot.toml has no [uv] table: no dose layer is kept", self.robot)
            return None
        p = self.core.fusion.map_pose()
        return DoseSample(now, p.x, p.y, lamp_on, self.core.fusion.position_initialized)

    def _publish_dose(self, pub: DosePublication) -> None:
        if self.dose_share is None and self.map_link is not None and not self._closed:
            from fleetlink.agent.dose_share import DoseShare

            self.dose_share = DoseShare(self.map_link, self.robot, self.clock)
            self.dose_share.start()
        if self.dose_share is not None:
            self.dose_share.publish(pub)

    def _prioritise_holder(self, now: float) -> None:
        """The lease holder's commands jump every link's queue (links/zenoh.py: priority lane): a
        flood from anyone else waits behind them. The key names the sender, so no decoding."""
        holder = self.core.lease.view(now).holder
        if holder == self._holder:
            return
        self._holder = holder
        lane = frozenset(keys.sender_key(self.robot, t, holder) for t in _COMMANDS) if holder else frozenset()
        for link in self.links:
            link.prioritise(lane, then_topics=STOP_TOPICS)

    def _link_status(self) -> LinkStatus:
        def up(name: LinkName) -> bool:
            return any(link.up for link in self.links if link.name is name)

        return LinkStatus(zenoh=up(LinkName.ZENOH), mqtt=up(LinkName.MQTT))

    # -- the lidar step -------------------------------------------------------------------------------

    def add_revolution(self, rev: Any, turn_s: float = 0.0) -> None:
        """One lidar turn: into the map at the fused pose; a fresh planner to the pilot when due.

        ``turn_s``: how long a turn takes (the feed measures it). A turn is complete only when the
        next one begins, so it is stamped about a turn after its first beam; the map takes it as
        seen ``turn_s`` before its stamp, at its start: the fused pose now, moved back by the
        odometry since. Measured on two robots wandering the apartment for 240 s: with the pose at
        the stamp, their maps' walls lay 0.09 and 0.21 m (mean) from the plan's and were drawn two
        or three times over; at the turn's start 0.04 m (a turning robot moves degrees in a turn).
        (The field's A1 casts a whole turn from the pose at its start; a real one sweeps it, and
        its beams are on average half a turn later, the same for every turn.)"""
        keeper = self.keeper
        assert keeper is not None, "open_map() first"
        if self.lidar_fault is not None:
            self.lidar_report(None)
        with self._lock:
            p = self.core.fusion.map_pose()
            # The map starts in the site frame once the heading is known to PLACE_SD_THETA_RAD: a map
            # started at the first heading fix (sd ~5 deg, errors to 10 deg measured) keeps its walls
            # that far askew, and a round planned on it sends the robot into them.
            placed = self.core.fusion.heading_initialized and p.sd_theta <= PLACE_SD_THETA_RAD
            driving = self.core.driving
            waiting = self.core.pilot.waiting_for_way
            now = self.clock.now()
            t = (rev.stamp if rev.stamp is not None else now) - turn_s
            o_now = self.core.fusion.odom_pose()
            o = self.core.fusion.odom_at(t)
            anchored = not self.core.fusion.uwb_stale(now)
            follows = self._follows
            # Without a UWB position the fused pose is the odometry and nothing else: the map is then
            # built in its own frame on the odometry, and the robot localised on it (``Turn.odometry``).
            odometry = None if self.core.fusion.position_initialized else (o.x, o.y, o.theta)
        # The fused pose now, moved back by the odometry to the turn's start.
        seen = compose((p.x, p.y, p.theta), relative((o_now.x, o_now.y, o_now.theta), (o.x, o.y, o.theta)))
        turn = Turn(
            t, rev.distances_m, rev.angles_rad, seen, placed, driving, now, anchored, follows, odometry, waiting
        )
        update = keeper.add(turn)
        self.scans += 1
        self._share_scan(rev, seen, now)
        if update is not None:
            self._use_map(update)
        if self.scan_sink is not None:
            self.scan_sink(rev)

    def add_revolutions(self, revs: list[Any], turn_s: float = 0.0) -> None:
        """Turns read at once: the newest into the map (``add_revolution``). Those before it are
        stale: the reader fell behind (the host busy), and mapping them too would put it further
        behind, each turn later than the last; they are counted (``stale_turns``) and still handed to
        the scan sink (a recording keeps every turn). Measured in the real-time field on a loaded
        two-core host with every turn mapped: a robot turning in place fell 2 s behind its lidar."""
        for rev in revs[:-1]:
            self.stale_turns += 1
            if self.stale_turns == 1:
                log.info("%s: lidar turns read faster than mapped: only the newest of each read is mapped", self.robot)
            if self.scan_sink is not None:
                self.scan_sink(rev)
        newest = revs[-1]
        earliest = self.clock.now() - NEWEST_TURN_AGE * turn_s
        if newest.stamp is not None and turn_s > 0.0 and newest.stamp < earliest:
            # Everything that had arrived was read, so the next turn is under way: the newest was
            # complete at most about a turn ago. Stamped earlier, it is on the lidar's line from
            # before samples were lost, which the driver's stamps draw again within a few reads.
            newest = dataclasses.replace(newest, stamp=earliest)
        self.add_revolution(newest, turn_s)

    def _share_scan(self, rev: Any, seen: tuple[float, float, float], now: float) -> None:
        """The turn as a ``Scan`` on the map's link (Zenoh), at most ``[rates] scan_hz`` a second."""
        hz = self.config.rates.scan_hz
        if hz <= 0.0 or self.map_link is None or now < self._next_scan:
            return
        self._next_scan = now + 1.0 / hz
        msg = self._conn_counter.make(Scan, **scan_fields(rev.angles_rad, rev.distances_m, seen))
        self.map_link.publish(self._scan_key, wire.encode(msg))

    def _use_map(self, update: Update) -> None:
        if update.restarted:
            self._follows = None
        if update.moved is not None or update.seen is not None or update.odom_frame is not None:
            self._localise(update)
        if update.restarted:
            log.info("%s: UWB frame established; the map restarts in it", self.robot)
            self._open_share()
            if self.dose is not None:
                self.dose.set_floor(None, -1)
        pub = update.publication
        if pub is not None and pub.began != self.core.map_began:
            with self._lock:
                self.core.map_begun(pub.began)
        if self.share is not None and pub is not None:
            self.share.publish(pub)
        if self.dose is not None and pub is not None and pub.site_frame:
            self.dose.set_floor(FloorMask.from_occupancy(pub.cells, pub.resolution, pub.origin), pub.version)
        if update.planner is not None:
            with self._lock:
                self.core.use_map(update.planner.route, update.planner)

    def _localise(self, update: Update) -> None:
        """Loop closure moved the map (``moved``): the fused pose moves with it, at once; the turn's
        pose as matched in the map (``seen``) is a pose measurement for the fusion, so the pose the
        pilot drives on stays where the map it plans on says it is (docs/localisation.md). Before UWB
        places the robot, ``odom_frame`` puts the odometry on the map's own frame."""
        with self._lock:
            fusion = self.core.fusion
            if update.odom_frame is not None:  # unplaced: the robot on its map's own frame
                fusion.set_own_frame(update.odom_frame)
            if update.moved is not None:
                fusion.shift_frame(update.moved)
            s = update.seen
            if s is not None and fusion.add_map_pose(PoseObservation(s.t, *s.pose, s.cov), self.clock.now()).accepted:
                self._follows = s.cov

    def lidar_report(self, fault: str | None) -> None:
        """The lidar failed (``fault``) or delivers again (None)."""
        with self._lock:
            self.lidar_fault = fault
            self._apply(self.core.lidar_status(fault, str(self.config.lidar)))

    # -- outputs ----------------------------------------------------------------------------------------

    def halt(self, timeout: float = HALT_TIMEOUT_S) -> bool:
        """Stop the robot for good (shutting down): inputs dropped from now on, zero velocity and
        the payload off sent to the board; True once the board has answered (within ``timeout``)."""
        with self._lock:
            self.halted = True
        self.board.set_velocity(0.0, 0.0)
        # Queued after the zero velocity, which the session sends first: the lamp's answer means both went.
        lamp, *others = [self.board.call(req) for req in PAYLOAD_OFF]
        try:
            lamp.result(timeout)
        except Exception as exc:  # no board, or it refused: the board's own watchdog still stops the wheels
            log.warning("%s: halting: the board did not confirm (%s)", self.robot, exc or type(exc).__name__)
            return False
        for done in others:  # a board without an atomiser or a fan refuses them: nothing to switch off
            with contextlib.suppress(Exception):
                done.result(timeout)
        return True

    def _apply(self, out: Output) -> None:
        if self.halted:
            return
        if out.velocity is not None:
            self.board.set_velocity(*out.velocity)
        for req in out.payload:
            self._payload(req)
        for code in out.clear_faults:
            self.board.clear_error(code)
        for line in out.logs:
            log.warning("%s: %s", self.robot, line)
        for msg, only in out.messages:
            data = wire.encode(msg)
            key = self._keys.get(msg.TOPIC) or keys.key(self.robot, msg.TOPIC)
            for link in self.links:
                if only is None or link.name is only:
                    link.publish(key, data)
            self.published += 1

    def _payload(self, req: PayloadRequest) -> None:
        """One payload request to the board: the UV-C lamp on or off, the atomiser or the fan at a
        level (0 off), or every payload off (an e-stop, a stop, the deadman, a lost link)."""
        from fleetlink.devices.controlbus import protocol as p

        level = (req.level or 1) if req.on else 0
        if req.device == "uv":
            self.board.call(p.SetUvLamp(req.on))
        elif req.device == "atomiser":
            self.board.call(p.SetAtomiser(level))
        elif req.device == "fan":
            self.board.call(p.SetFan(level))
        elif not req.on:  # "all"
            for off in PAYLOAD_OFF:
                self.board.call(off)

    def _open_share(self) -> None:
        from fleetlink.agent.mapping.share import MapShare

        if self.share is not None:
            self.share.stop()
            self.share = None
        if self.map_link is not None:
            self.share = MapShare(self.map_link, self.robot, self.clock)
            self.share.start()


_OUTPUT_TOPICS = ("pose", "state", "ack", "events", "lease", "connection", "diagnostics", "board")


def _payload_off() -> tuple[Any, ...]:
    from fleetlink.devices.controlbus import protocol as p

    return (p.SetUvLamp(False), p.SetAtomiser(0), p.SetFan(0))


PAYLOAD_OFF = _payload_off()
"""Every payload off, lamp first (the one that harms people)."""


LIDAR_READ_PERIOD_S = (0.05, 0.25)
"""Seconds between reads of the lidar's stream: a quarter of a turn, within these bounds. Bytes
arrive every few milliseconds (an A1 sends 40 kB/s); reading them as they came woke the lidar
thread ~200 times a second and ran the decoder on a few dozen nodes each time. A turn of the A1
at 5.5 Hz (180 ms) is read in four batches, a slow 1 Hz turn in four too, and a finished turn
reaches the mapper at most a quarter of a turn late."""
NEWEST_TURN_AGE = 1.5
"""How many turns before it was read the newest turn of a drained read was complete, at most."""
LIDAR_DRAIN_READS = 64
"""Polls a feed's step makes at most to take what has arrived (64 turns: seconds of a backlog)."""
LIDAR_REOPEN_S = 1.0
"""How long a failed lidar rests before it is opened again."""


class LidarFeed:
    """The agent's lidar: open, start, read a quarter turn at a time, into ``AgentNode.add_revolution``.

    ``step(now)`` reads what has arrived and returns when to read next; a lidar that fails (unplugged,
    garbage, stalled) is reported on the node, closed, and opened again ``LIDAR_REOPEN_S`` later,
    while driving goes on (the guard reads the ultrasonic, not the lidar). The real-time runtime
    calls ``step`` from its lidar worker; the lockstep site calls it when it is due.
    """

    def __init__(self, node: AgentNode, open_driver: Callable[[], Any]) -> None:
        self.node = node
        self.open_driver = open_driver
        self.driver: Any = None
        self.failures = 0
        self.turn_s = 0.2
        """The lidar's turn, measured as turns arrive."""
        self._last_turn_at: float | None = None

    def step(self, now: float) -> float:
        try:
            if self.driver is None:
                self.driver = self.open_driver()
                self.driver.start_motor()
                self.driver.start_scan()
            # Everything that has arrived (each poll returns at the first turn complete): a reader
            # that was held up catches up at once rather than a turn or two a wake-up, and maps the
            # newest turn (measured on a loaded host: read a turn or two each time, a robot's lidar
            # fell 6 s behind).
            revs: list[Any] = []
            for _ in range(LIDAR_DRAIN_READS):
                got = self.driver.poll(now)  # never waits
                if not got:
                    break
                revs.extend(got)
            if revs:
                self.node.add_revolutions(revs, self.turn_s)
            self.failures = 0
        except Exception as exc:  # a lidar unplugged or garbage: reopen, keep driving
            self.failures += 1
            if self.failures == 1:
                log.warning("%s: lidar %s failed: %s; reopening", self.node.robot, self.node.config.lidar, exc)
            if self.node.lidar_fault is None:
                self.node.lidar_report(f"{type(exc).__name__}: {exc}"[:200] or "lidar failed")
            self.close()
            return now + LIDAR_REOPEN_S
        now = self.node.clock.now()
        if revs:
            # The turn's length from the driver's stamps (when each turn was complete, on the lidar's
            # clock, however late it was read), smoothed over a few turns.
            last = revs[-1].stamp if revs[-1].stamp is not None else now
            gap = None if self._last_turn_at is None else (last - self._last_turn_at) / len(revs)
            if gap is not None and 0.0 < gap <= MAX_TURN_S:
                self.turn_s += 0.25 * (gap - self.turn_s)
            self._last_turn_at = last
        lo, hi = LIDAR_READ_PERIOD_S
        return now + min(hi, max(lo, self.turn_s / 4.0))

    def close(self) -> None:
        self._last_turn_at = None  # the gap until the next turn after a reopen is no turn's length
        if self.driver is not None:
            try:
                self.driver.close()
            except Exception as exc:  # closing a dead port must not stop the reopen
                log.debug("%s: closing the lidar: %s", self.node.robot, exc)
            self.driver = None
