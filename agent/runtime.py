"""The agent process: board session, command links, control loop and telemetry, around AgentCore.

Threads: the board session's poll loop; the control loop (``control_hz`` while the robot drives,
each pose when it is idle: board snapshot -> ``AgentCore.tick`` -> velocity to the board,
telemetry out; a command wakes it at once); zenoh's callback threads and the
MQTT loop thread, which hand each payload to ``AgentCore.on_input`` and push the resulting
velocity to the board at once. One lock serialises every call into the core, so the core itself
stays single-threaded and pure.

Mapping: with a ``lidar`` URL in robot.toml a worker thread opens the lidar (agent/lidar/driver.py),
feeds every revolution with the fused map pose into ``OnboardMapper.add_scan`` and serves the map
with ``MapShare`` over the Zenoh session (``fleetlink/v1/<robot>/map``, docs/mapping.md). The
worker owns the mapper and takes the core's lock only to read the pose, so mapping never blocks
the control loop; a lidar that fails is reopened after a second. ``scan_sink`` also gets every
revolution. A lidar fault is reported (an ``Event`` of kind ``lidar_fault``, ``lidar_ok`` when
scans come back, and an error in ``State.errors`` while it lasts); driving goes on meanwhile, as
the guard reads the front ultrasonic, not the lidar.

Planning: once the map has walls, the worker hands the core a planner over a copy of it
(``AgentCore.use_map``), renewed every ``PLANNER_PERIOD`` seconds while the robot drives and the
map changes, so go-to
and return home follow A* waypoints and re-plan when blocked. The copy belongs to the control
thread alone: the worker keeps writing its own grid. Unknown cells count as free on an onboard map
(a scout is sent into rooms it has not seen; the guard still stops it at anything real).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
from collections.abc import Callable
from typing import Any

from fleetlink.agent.board.session import BoardSession, PollRates
from fleetlink.agent.config import AgentConfig
from fleetlink.agent.core import AgentCore, Output, board_view
from fleetlink.agent.fusion import Fusion
from fleetlink.agent.links.mqtt_link import agent_mqtt_link
from fleetlink.agent.links.zenoh_link import agent_zenoh_link
from fleetlink.agent.odometry import Odometry
from fleetlink.agent.pilot import Pilot, PilotConfig
from fleetlink.devices.ports import Port
from fleetlink.links.mqtt import MqttEndpoint
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.messages import Connection, ConnectionState, LeaseRequest, LinkName, LinkStatus, UwbFix

PLANNER_PERIOD = 2.0
"""Seconds between planners handed to the control thread while the map grows."""
IDLE_PERIOD = 0.1
"""Longest sleep of an idle control loop (it wakes earlier for every pose, at 20 Hz by default).
Idle, a tick at the control rate (50 Hz) would compute the same zero velocity from the same
sensor reading; each tick is a thread wake-up, which costs more than the tick itself on a VM."""
LIDAR_READ_PERIOD = (0.05, 0.25)
"""Seconds between reads of the lidar's stream: a quarter of a turn, within these bounds. Bytes
arrive every few milliseconds (an A1 sends 40 kB/s); reading them as they came woke the lidar
thread ~200 times a second and ran the decoder on a few dozen nodes each time. A turn of the A1
at 5.5 Hz (180 ms) is now read in four batches, a slow 1 Hz turn in four too, and a finished turn
reaches the mapper at most a quarter of a turn late."""

log = logging.getLogger(__name__)

__all__ = ["POLL_RATES", "AgentRuntime"]

POLL_RATES = PollRates(motion=10.0, telemetry=20.0, motor=20.0, imu=20.0, sensors=20.0, bumpers=20.0, buttons=1.0)
"""The board poll rates the agent uses: wheel distances and the gyro at 20 Hz feed the odometry;
range sensors, bumpers and cliffs at 20 Hz feed the guard. A board with GET_TELEMETRY gives all
four in one exchange at 20 Hz (a quarter of the exchanges, on both ends of the line); a plain
SLAMTEC base is polled for each apart. Motion (SET_V_AND_GET_DEADRECKON) is
only a 10 Hz refresh: every new velocity is sent at once (``BoardSession.set_velocity``), so while
driving it goes out at the control rate anyway, and its dead reckoning is not what the odometry
uses. Every poll feeds the board's 1 s watchdog. Buttons at 1 Hz: nothing reads
them but the pending base command (2 Hz) that the home button raises."""
INPUTS = ("order", "actions", "teleop", LeaseRequest.TOPIC, UwbFix.TOPIC)


def _pilot_config(cfg: AgentConfig) -> PilotConfig:
    from fleetlink.agent.guard import GuardConfig
    from fleetlink.agent.motion import MotionLimits

    lim = cfg.limits
    return PilotConfig(
        guard=GuardConfig(stop_distance_m=lim.stop_distance_m),
        limits=MotionLimits(v_max=lim.v_max, omega_max=lim.omega_max, a_max=lim.a_max, alpha_max=lim.alpha_max),
        teleop_ttl_s=lim.teleop_ttl_s,
    )


class AgentRuntime:
    """One robot's agent. ``start()`` / ``stop()``; safe to use as a context manager."""

    def __init__(
        self,
        config: AgentConfig,
        clock: Clock | None = None,
        *,
        open_port: Callable[[], Port] | None = None,
        seed: int | None = None,
        scan_sink: Callable[[Any], None] | None = None,
    ) -> None:
        self.config = config
        self.clock = clock or SystemClock()
        robot = config.robot
        self.core = AgentCore(
            robot,
            self.clock,
            Pilot(_pilot_config(config)),
            odometry=Odometry(),
            fusion=Fusion(),
            map_id=config.map_id,
            pose_hz=config.rates.pose_hz,
            state_hz=config.rates.state_hz,
            operators=config.operators,
        )
        self.scan_sink = scan_sink
        self.board = BoardSession(open_port or _serial_opener(config.board), self.clock, rates=POLL_RATES, seed=seed)
        self._motor: object = None
        self._odom_t = 0.0
        self._lock = threading.Lock()
        self._conn_counter = wire.HeaderCounter(self.clock, robot=robot, sender=f"agent-{robot}")
        self.links: list[ZenohEndpoint | MqttEndpoint] = []
        self.pans_topic = f"dwm/node/{config.tag or robot}/uplink/location"
        if config.zenoh is not None:
            self.zenoh: ZenohEndpoint | None = agent_zenoh_link(
                robot, config.zenoh, on_input=self._on_input, inputs=INPUTS
            )
            self.links.append(self.zenoh)
        else:
            self.zenoh = None
        if config.mqtt is not None:
            self.mqtt: MqttEndpoint | None = agent_mqtt_link(
                robot,
                config.mqtt,
                self._connection_payload,
                on_input=self._on_input,
                inputs=INPUTS,
                extra_topics=(self.pans_topic,),
                seed=seed,
            )
            self.links.append(self.mqtt)
        else:
            self.mqtt = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._lidar_thread: threading.Thread | None = None
        self.mapper: Any = None
        self.lidar_fault: str | None = None
        """Why the lidar is not delivering scans (None: it is, or there is none)."""
        self.scans = 0
        self.published = 0
        self._turn_s = 0.2  # the lidar's turn, measured as turns arrive
        self._last_turn_at: float | None = None

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> AgentRuntime:
        self.board.start()
        for link in self.links:
            try:
                link.start()
            except Exception as exc:  # one link failing to open must not take the robot down
                log.error("%s link failed to start: %s", link.name.value, exc)
        self._thread = threading.Thread(target=self._run, name=f"agent-{self.config.robot}", daemon=True)
        self._thread.start()
        if self.config.lidar:
            self._lidar_thread = threading.Thread(
                target=self._lidar_loop, args=(self.config.lidar,), name=f"lidar-{self.config.robot}", daemon=True
            )
            self._lidar_thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        if self._lidar_thread is not None:
            self._lidar_thread.join(5.0)
            self._lidar_thread = None
        self.board.set_velocity(0.0, 0.0)
        for link in reversed(self.links):
            link.close()
        self.board.stop()

    def __enter__(self) -> AgentRuntime:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- inputs (link threads) -----------------------------------------------------------------

    def _on_input(self, link: LinkName, key: str, payload: bytes) -> None:
        with self._lock:
            was_idle = not self.core.driving
            now = self.clock.now()
            if key == self.pans_topic:
                out = self.core.on_pans(link, key, payload, now)
            else:
                out = self.core.on_input(link, key, payload, now)
            self._apply(out)
            started = was_idle and self.core.driving
        if started:  # an idle control loop takes up the control rate at once (a UWB fix does not wake it)
            self._wake.set()

    # -- the control loop -------------------------------------------------------------------------

    def _run(self) -> None:
        period = 1.0 / self.config.rates.control_hz
        next_t = self.clock.now()
        next_links = next_t
        while not self._stop.is_set():
            now = self.clock.now()
            with self._lock:
                if now >= next_links:
                    next_links = now + 0.2
                    status = LinkStatus(
                        zenoh=self.zenoh is not None and self.zenoh.up,
                        mqtt=self.mqtt is not None and self.mqtt.up,
                    )
                    self._apply(self.core.set_links(status, now))
                snap = self.board.snapshot
                if snap.motor is not self._motor:  # a fresh wheel reading: its poll time
                    self._motor, self._odom_t = snap.motor, snap.updated
                view = board_view(snap, odom_t=self._odom_t)
                fault = self.lidar_fault
                if fault is not None:  # reported in State.errors while it lasts
                    view = dataclasses.replace(view, errors=(*view.errors, f"lidar: {fault}"))
                self._apply(self.core.tick(now, view))
                driving, next_pose = self.core.driving, self.core.next_pose_at
            next_t += period
            if not driving:
                # Idle: nothing to steer until a command comes (it wakes us: ``_wake``); tick when
                # the next pose is due, which also reads the board's 20 Hz sensors as they come.
                next_t = max(next_t, min(next_pose, now + IDLE_PERIOD))
            if next_t < self.clock.now():
                next_t = self.clock.now()
            if isinstance(self.clock, SystemClock):
                self._wake.wait(max(0.0, next_t - self.clock.now()))
                self._wake.clear()
            else:
                self.clock.sleep_until(next_t)

    # -- lidar and mapping (its own thread) ------------------------------------------------------

    def _lidar_loop(self, url: str) -> None:
        from fleetlink.agent.lidar.driver import LidarDriver
        from fleetlink.agent.mapping import OnboardMapper
        from fleetlink.agent.mapping.mapper import MapperConfig
        from fleetlink.agent.mapping.planner import PlannerConfig
        from fleetlink.agent.mapping.share import MapShare

        config = MapperConfig(planner=PlannerConfig(unknown_is_blocked=False))  # see "Planning" above
        self.mapper = mapper = OnboardMapper(config)
        in_uwb_frame = False  # the frame the map is being built in: odometry until UWB fixes place the robot
        planned_version = -1
        next_planner = self.clock.now()
        share = None
        if self.zenoh is not None:
            share = MapShare(self.zenoh, self.config.robot, self.clock)
            share.start()
        driver = None
        failures = 0
        try:
            while not self._stop.is_set():
                try:
                    if driver is None:
                        driver = LidarDriver.open(url, self.clock)
                        driver.start_motor()
                        driver.start_scan()
                    for rev in self._lidar_revolutions(driver):
                        if self.lidar_fault is not None:
                            self._lidar_report(None)
                        with self._lock:
                            p = self.core.fusion.map_pose()
                            placed = self.core.fusion.heading_initialized
                            driving = self.core.driving
                        if placed and not in_uwb_frame:
                            # The fused pose just moved from the odometry frame to the UWB frame: a map
                            # begun in the old frame would be smeared across both. Start it again, once.
                            in_uwb_frame = True
                            if not mapper.grid.empty:
                                log.info("%s: UWB frame established; the map restarts in it", self.config.robot)
                                self.mapper = mapper = OnboardMapper(config)
                                planned_version = -1
                                if share is not None:
                                    share.stop()
                                    share = MapShare(share.link, self.config.robot, self.clock)
                                    share.start()
                        t = rev.stamp if rev.stamp is not None else self.clock.now()
                        mapper.add_scan(t, rev.distances_m, rev.angles_rad, (p.x, p.y, p.theta))
                        self.scans += 1
                        if share is not None:
                            share.publish(mapper)
                        now = self.clock.now()
                        # The first planner as soon as the map has cells; then a fresh one every
                        # PLANNER_PERIOD while the robot drives (standing still, its map changes only
                        # by noise, and a rebuild costs tens of milliseconds).
                        renew = planned_version < 0 or (driving and now >= next_planner)
                        if renew and not mapper.grid.empty and mapper.grid.version != planned_version:
                            next_planner = now + PLANNER_PERIOD
                            planned_version = mapper.grid.version
                            planner = mapper.planner()  # built here, over a copy of the cells
                            with self._lock:
                                self.core.use_map(planner.route)
                        if self.scan_sink is not None:
                            self.scan_sink(rev)
                    failures = 0
                except Exception as exc:  # a lidar unplugged or garbage: reopen, keep driving
                    failures += 1
                    if failures == 1:
                        log.warning("%s: lidar %s failed: %s; reopening", self.config.robot, url, exc)
                    if self.lidar_fault is None:
                        self._lidar_report(f"{type(exc).__name__}: {exc}"[:200] or "lidar failed")
                    if driver is not None:
                        with contextlib.suppress(Exception):
                            driver.close()
                        driver = None
                    self._stop.wait(1.0)
        finally:
            if driver is not None:
                with contextlib.suppress(Exception):
                    driver.close()
            if share is not None:
                share.stop()

    def _lidar_revolutions(self, driver: Any) -> list[Any]:
        """The turns completed since the last call. In real time: everything that has arrived,
        then a pause of a quarter turn before the next read (``LIDAR_READ_PERIOD``); else: wait for one."""
        if isinstance(self.clock, SystemClock):
            revs: list[Any] = driver.poll(self.clock.now())  # takes what is there, never waits
            now = self.clock.now()
            if revs:
                if self._last_turn_at is not None:  # the turn's length, smoothed over a few turns
                    self._turn_s += 0.25 * (min(2.0, (now - self._last_turn_at) / len(revs)) - self._turn_s)
                self._last_turn_at = now
            else:
                lo, hi = LIDAR_READ_PERIOD
                self._stop.wait(min(hi, max(lo, self._turn_s / 4.0)))
            return revs
        return list(driver.poll(self.clock.now() + 0.2))

    def _lidar_report(self, fault: str | None) -> None:
        """The lidar failed (``fault``) or delivers again (None): an event now, the state follows."""
        from fleetlink.shared.messages import Event, KeyValue, Severity

        with self._lock:
            self.lidar_fault = fault
            if fault is None:
                ev = self.core.counter.make(
                    Event, kind="lidar_ok", text="lidar scanning again", severity=Severity.INFO, data=()
                )
            else:
                ev = self.core.counter.make(
                    Event,
                    kind="lidar_fault",
                    text=f"lidar not delivering scans: {fault}; driving on the ultrasonic guard"[:256],
                    severity=Severity.ERROR,
                    data=(KeyValue(key="url", value=str(self.config.lidar)[:256]),),
                )
            self._apply(Output(messages=[(ev, None)]))

    def _apply(self, out: Output) -> None:
        if out.velocity is not None:
            self.board.set_velocity(*out.velocity)
        for on in out.payload:
            self._payload(on)
        for line in out.logs:
            log.warning("%s: %s", self.config.robot, line)
        for msg, only in out.messages:
            data = wire.encode(msg)
            for link in self.links:
                if only is None or link.name is only:
                    link.publish(keys.key(self.config.robot, msg.TOPIC), data)
            self.published += 1

    def _payload(self, on: bool) -> None:
        from fleetlink.devices.controlbus import protocol as p

        self.board.call(p.SetUvLamp(on))  # the disinfection payload: the UV-C lamp

    def _connection_payload(self, state: ConnectionState) -> bytes:
        return wire.encode(self._conn_counter.make(Connection, connectionState=state))

    @property
    def key_prefix(self) -> str:
        return keys.key(self.config.robot, "state").rsplit("/", 1)[0]


def _serial_opener(url: str) -> Callable[[], Port]:
    from fleetlink.devices.ports import SerialPort

    return lambda: SerialPort(url)
