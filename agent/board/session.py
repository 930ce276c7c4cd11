"""A board session: connect, poll on a schedule, keep a snapshot, reconnect by itself.

``PollSchedule`` is pure (what is due at time t). ``BoardSession`` owns one ``BoardClient`` and
runs the schedule: motion (SET_V_AND_GET_DEADRECKON, which also feeds the board's watchdog) at
50 Hz, wheel distances and range sensors at 20 Hz, bumpers and cliffs at 20 Hz, battery and power
at 1 Hz, health at 2 Hz with the error list fetched when it changes. With a ``telemetry`` rate, a
board that has fleetlink's GET_TELEMETRY gives wheels, gyro, sensors and bumpers in one exchange
instead of four (``PollRates``). ``tick()`` runs one round
and returns when the next one is due; ``run_forever()`` loops it on the injected clock (in a thread
for real time; the lockstep field calls ``tick`` itself).
"""

from __future__ import annotations

import logging
import math
import random
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from queue import Empty as QueueEmpty
from queue import SimpleQueue

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.client import (
    BoardClient,
    BoardDisconnected,
    BoardError,
    BoardRefused,
    BoardTimeout,
)
from fleetlink.devices.controlbus.snapshot import BoardSnapshot
from fleetlink.devices.ports import Port, PortClosed
from fleetlink.shared.body import BODY_RADIUS_M
from fleetlink.shared.clock import Clock
from fleetlink.shared.worker import Worker

log = logging.getLogger(__name__)

__all__ = ["BoardSession", "PollRates", "PollSchedule"]


@dataclass(frozen=True, slots=True)
class PollRates:
    """Hz per poll task; 0 disables a task.

    ``telemetry`` (fleetlink's GET_TELEMETRY extension) reads the wheels, gyro, range sensors and
    bumpers in one exchange. When it is above 0 the session asks for it once at connect: a board
    that has it is polled with it alone, and ``motor``, ``imu``, ``sensors`` and ``bumpers`` are not
    run; a board that answers NOT_SUPPORTED (a plain SLAMTEC base) gets those four polls instead.
    """

    motion: float = 50.0
    telemetry: float = 0.0
    motor: float = 20.0
    sensors: float = 20.0
    bumpers: float = 20.0
    status: float = 1.0
    power: float = 1.0
    health: float = 2.0
    payload: float = 2.0
    env: float = 0.5
    buttons: float = 5.0
    imu: float = 20.0
    base_command: float = 2.0


class PollSchedule:
    """Which poll tasks are due at a given time; tasks keep their phase and never bunch up."""

    def __init__(self, rates: PollRates, start: float) -> None:
        self.periods = {name: 1.0 / hz for name, hz in _fields(rates) if hz > 0}
        self.next_due = dict.fromkeys(self.periods, start)

    def due(self, now: float) -> list[str]:
        tasks = [name for name, t in self.next_due.items() if t <= now]
        for name in tasks:
            period = self.periods[name]
            nxt = self.next_due[name] + period
            # After a stall (reconnect, slow link), skip missed slots instead of bursting.
            self.next_due[name] = nxt if nxt > now else now + period
        return tasks

    def next_time(self) -> float:
        return min(self.next_due.values())

    def ran(self, task: str, now: float) -> None:
        """``task`` was just run out of turn: its next slot is a period from ``now``."""
        if task in self.next_due:
            self.next_due[task] = now + self.periods[task]


def _fields(rates: PollRates) -> list[tuple[str, float]]:
    return [(name, getattr(rates, name)) for name in rates.__dataclass_fields__]


@dataclass(slots=True)
class _Call:
    request: p.Request
    future: Future[p.Reply] = field(default_factory=Future)


class BoardSession:
    """Owns the board link. Thread-safe entry points: ``set_velocity``, ``call``, ``snapshot``, ``stop``.

    ``direct``: a new velocity is written to the board by the thread that calls ``set_velocity``
    (the agent's: the link thread that decided it, or the control loop), when no exchange is in
    flight; the worker takes the board's reply with its next exchange (it is woken for it).
    Otherwise -- an exchange in flight, or ``direct`` off -- the worker is woken and sends it before
    anything else. The frame is the same SET_VELOCITY either way; direct sending only saves the
    wake-up of the session's thread (and its wait for the GIL) between a command and the board.
    Real-time agents send directly (agent/runtime.py); lockstep runs do not (their board session
    runs when the run ticks it, so the order of every step stays the run's)."""

    def __init__(
        self,
        open_port: Callable[[], Port],
        clock: Clock,
        profile: p.Profile = p.DEFAULT_PROFILE,
        rates: PollRates | None = None,
        timeout: float = 0.1,
        retries: int = 2,
        max_failures: int = 3,
        on_update: Callable[[BoardSnapshot], None] | None = None,
        seed: int | None = None,
        direct: bool = False,
    ) -> None:
        self._open_port = open_port
        self.clock = clock
        self.profile = profile
        self.rates = rates or PollRates()
        self.timeout = timeout
        self.retries = retries
        self.max_failures = max_failures
        self.on_update = on_update
        self.client: BoardClient | None = None
        self._snap = BoardSnapshot()
        self._lock = threading.Lock()
        self._calls: SimpleQueue[_Call] = SimpleQueue()
        self._command = (0.0, 0.0)
        self.direct = direct
        # One exchange at a time on the port: the worker holds this for each of its exchanges, a
        # direct velocity for writing its request; a request written and not yet answered is
        # ``_in_flight`` (the velocity it carries), finished by the worker before anything else.
        self._io = threading.Lock()
        self._in_flight: tuple[float, float] | None = None
        self.direct_sends = 0
        """Velocities written by the caller's thread (``direct``)."""
        # A new velocity is sent at once, not at the next 50 Hz slot: set_velocity wakes the worker.
        self._worker = Worker("board-session", clock=clock, target=lambda _w: self.run_forever())
        self._urgent = False
        self._failures = 0
        self._schedule: PollSchedule | None = None
        self._backoff = 0.2
        self._retry_at = 0.0
        self._rng = random.Random(seed)
        self.telemetry_supported: bool | None = None
        """Whether the board answered GET_TELEMETRY at the last connect (None: not asked)."""

    # -- thread-safe API -------------------------------------------------------------------

    @property
    def snapshot(self) -> BoardSnapshot:
        return self._snap

    @property
    def urgent(self) -> bool:
        """A new velocity waits to be sent (a lockstep run ticks the session again at once)."""
        return self._urgent

    def set_velocity(self, vx: float, omega: float) -> None:
        """Body velocity sent at the motion rate; non-finite values are refused."""
        if not (math.isfinite(vx) and math.isfinite(omega)):
            raise ValueError(f"velocity must be finite, got vx={vx} omega={omega}")
        if (vx, omega) != self._command:
            self._command = (vx, omega)
            if not (self.direct and self._send_now(vx, omega)):
                self._urgent = True
            self._worker.wake()

    def _send_now(self, vx: float, omega: float) -> bool:
        """Write SET_VELOCITY from this thread if the port is free; the worker reads the reply."""
        if self.client is None or not self._io.acquire(blocking=False):
            return False
        try:
            client = self.client
            if client is None or self._in_flight is not None or client.in_flight:
                return False
            try:
                client.begin(p.SetVelocity(vx, 0.0, omega))
            except BoardError:  # the port failed: the worker's next exchange finds out and reconnects
                return False
            self._in_flight = (vx, omega)
            self.direct_sends += 1
            return True
        finally:
            self._io.release()

    def call(self, request: p.Request) -> Future[p.Reply]:
        """Queue a one-off request (payload, LEDs, ...), sent between polls."""
        item = _Call(request)
        self._calls.put(item)
        return item.future

    def start(self) -> None:
        if not self._worker.running:
            self._worker.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._worker.stop(timeout)
        if self.client is not None:
            with self._io:
                self.client.close()
                self.client = None
                self._in_flight = None
            self._set(connected=False, last_error="stopped")

    def __enter__(self) -> BoardSession:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- the loop ---------------------------------------------------------------------------

    def run_forever(self) -> None:
        """The worker's loop: tick, then wait on the clock until the next poll or a new velocity."""
        worker = self._worker
        while not worker.stopping:
            nxt = min(self.tick(), self.clock.now() + 0.05)
            worker.wait(max(0.0, nxt - self.clock.now()))

    def tick(self) -> float:
        """One round: connect if needed, run what is due, serve queued calls. Returns the next due time."""
        now = self.clock.now()
        if self.client is None:
            if now < self._retry_at:
                return self._retry_at
            if not self._connect():
                return self._retry_at
        assert self._schedule is not None
        try:
            self._finish_direct()
            if self._urgent:
                self._urgent = False
                if "motion" in self._schedule.next_due:
                    self._schedule.next_due["motion"] = now
            for task in self._schedule.due(now):
                getattr(self, f"_poll_{task}")()
            self._serve_calls()
            self._failures = 0
        except BoardDisconnected as exc:
            self._disconnect(str(exc))
            return self._retry_at
        except (BoardTimeout, BoardError) as exc:
            self._failures += 1
            self._set(last_error=str(exc))
            if self._failures >= self.max_failures:
                self._disconnect(f"{self._failures} failed exchanges in a row: {exc}")
                return self._retry_at
        return self._schedule.next_time()

    def _connect(self) -> bool:
        try:
            port = self._open_port()
        except (PortClosed, OSError) as exc:
            self._schedule_retry(f"cannot open board port: {exc}")
            return False
        client = BoardClient(port, self.clock, self.profile, self.timeout, self.retries)
        try:
            info = client.connect(attempts=2)
            conf = client.request(p.GetBaseConf())
        except BoardError as exc:
            client.close()
            self._schedule_retry(f"board handshake failed: {exc}")
            return False
        assert isinstance(conf, p.BaseConf)
        if abs(conf.radius - BODY_RADIUS_M) > 0.005:
            # The planner, the guard and the peers' bodies take the fleet's base (shared/body.py):
            # a different base is driven as if it were that one, which its operator must know.
            log.warning(
                "board reports a base of radius %.3f m; the agent plans and guards for %.3f m",
                conf.radius,
                BODY_RADIUS_M,
            )
        try:
            telemetry = self._probe_telemetry(client)
        except BoardError as exc:
            client.close()
            self._schedule_retry(f"board handshake failed: {exc}")
            return False
        self.client = client
        self._failures = 0
        self._backoff = 0.2
        self._schedule = PollSchedule(self._rates_for(telemetry is not None), self.clock.now())
        log.info("board connected: %s firmware %s serial %s", info.model, info.firmware_text, info.serial_text)
        self._set(connected=True, info=info, conf=conf, connects=self._snap.connects + 1, last_error="")
        if telemetry is not None:
            self._store_telemetry(telemetry)
        return True

    def _probe_telemetry(self, client: BoardClient) -> p.Telemetry | None:
        """The first GET_TELEMETRY reading, or None when the board lacks it (or it is not wanted)."""
        if self.rates.telemetry <= 0:
            self.telemetry_supported = None
            return None
        try:
            reply = client.request(p.GetTelemetry())
        except BoardRefused as exc:
            if self.telemetry_supported is not False:
                log.info("board has no GET_TELEMETRY (%s): polling wheels, gyro, sensors, bumpers apart", exc)
            self.telemetry_supported = False
            return None
        assert isinstance(reply, p.Telemetry)
        self.telemetry_supported = True
        return reply

    def _rates_for(self, telemetry: bool) -> PollRates:
        if telemetry:
            return replace(self.rates, motor=0.0, imu=0.0, sensors=0.0, bumpers=0.0)
        return replace(self.rates, telemetry=0.0)

    def _schedule_retry(self, reason: str) -> None:
        if self._snap.last_error != reason:
            log.warning("%s (retrying)", reason)
        # Jittered exponential backoff, capped at 2 s.
        delay = self._backoff * (0.5 + self._rng.random())
        self._backoff = min(2.0, self._backoff * 2)
        self._retry_at = self.clock.now() + delay
        self._set(connected=False, last_error=reason)

    def _disconnect(self, reason: str) -> None:
        if self.client is not None:
            log.warning("board link lost: %s", reason)
            with self._io:
                self.client.close()
                self.client = None
                self._in_flight = None
            self._schedule_retry(reason)

    def _set(self, **changes: object) -> None:
        with self._lock:
            self._snap = replace(self._snap, **changes)  # type: ignore[arg-type]
            snap = self._snap
        if self.on_update is not None:
            self.on_update(snap)

    def _ask(self, req: p.Request) -> p.Reply:
        client = self.client
        assert client is not None
        with self._io:
            self._finish_direct_locked()
            return client.request(req)

    def _finish_direct(self) -> None:
        """Take the reply to a velocity a caller wrote (``direct``), if there is one."""
        if self._in_flight is not None:
            with self._io:
                self._finish_direct_locked()

    def _finish_direct_locked(self) -> None:
        sent = self._in_flight
        if sent is None:
            return
        self._in_flight = None
        assert self.client is not None
        dr = self.client.finish()
        assert isinstance(dr, p.DeadReckon)
        self._dead_reckon(dr, sent)
        if self._schedule is not None:
            self._schedule.ran("motion", self.clock.now())  # it counts as the motion poll

    def _serve_calls(self) -> None:
        while True:
            try:
                call = self._calls.get_nowait()
            except QueueEmpty:
                return
            if not call.future.set_running_or_notify_cancel():
                continue
            try:
                call.future.set_result(self._ask(call.request))
            except BoardRefused as exc:
                call.future.set_exception(exc)
            except BoardError as exc:
                call.future.set_exception(exc)
                raise

    # -- poll tasks -------------------------------------------------------------------------

    def _poll_motion(self) -> None:
        vx, omega = self._command
        dr = self._ask(p.SetVelocity(vx, 0.0, omega))
        assert isinstance(dr, p.DeadReckon)
        self._dead_reckon(dr, (vx, omega))

    def _dead_reckon(self, dr: p.DeadReckon, command: tuple[float, float]) -> None:
        vx, omega = command
        x, y, th = self._snap.odom
        c, s = math.cos(th), math.sin(th)
        odom = (x + c * dr.dx - s * dr.dy, y + s * dr.dx + c * dr.dy, _wrap(th + dr.dtheta))
        self._set(odom=odom, command=(vx, omega), updated=self.clock.now())

    def _poll_telemetry(self) -> None:
        reply = self._ask(p.GetTelemetry())
        assert isinstance(reply, p.Telemetry)
        self._store_telemetry(reply)

    def _store_telemetry(self, t: p.Telemetry) -> None:
        self._set(motor=t.motor, imu=t.imu, sensors=t.sensors, bumpers=t.bumpers, updated=self.clock.now())

    def _poll_motor(self) -> None:
        self._set(motor=self._ask(p.GetMotorData()), updated=self.clock.now())

    def _poll_sensors(self) -> None:
        self._set(sensors=self._ask(p.GetSensorData()))

    def _poll_bumpers(self) -> None:
        self._set(bumpers=self._ask(p.GetBumperData()))

    def _poll_status(self) -> None:
        self._set(status=self._ask(p.GetBaseStatus()))

    def _poll_power(self) -> None:
        self._set(power=self._optional(p.GetPowerData()))

    def _poll_payload(self) -> None:
        self._set(payload=self._optional(p.GetPayloadStatus()))

    def _poll_env(self) -> None:
        self._set(env=self._optional(p.GetEnvData()))

    def _poll_buttons(self) -> None:
        self._set(buttons=self._optional(p.GetButtons()))

    def _poll_imu(self) -> None:
        self._set(imu=self._optional(p.GetImuData()))

    def _poll_base_command(self) -> None:
        pending = self._ask(p.PollBaseCommand())
        assert isinstance(pending, p.PendingBaseCommand)
        if pending.command is not None:
            log.info("base asks for command 0x%02X", pending.command)
            self._ask(p.AnswerBaseCommand())
            if pending.command == p.PendingCommandCode.GO_HOME:
                self._set(home_requests=self._snap.home_requests + 1)

    def _poll_health(self) -> None:
        health = self._ask(p.GetHealth())
        assert isinstance(health, p.Health)
        if health != self._snap.health:
            errors = []
            for i in range(health.error_count):
                err = self._ask(p.GetHealthError(i))
                assert isinstance(err, p.HealthError)
                errors.append(err)
            for err in errors:
                if err not in self._snap.errors:
                    log.warning("board health: 0x%04X %s", err.code, err.message)
            self._set(health=health, errors=tuple(errors))

    def _optional(self, req: p.Request) -> p.Reply | None:
        """Extension commands: a board without them answers NOT_SUPPORTED; stop asking."""
        try:
            return self._ask(req)
        except BoardRefused as exc:
            if exc.code == p.ErrorCode.NOT_SUPPORTED and self._schedule is not None:
                name = _TASK_OF.get(type(req))
                if name:
                    self._schedule.next_due.pop(name, None)
            return None

    def clear_error(self, code: int) -> Future[p.Reply]:
        return self.call(p.ClearHealthError(code))


_TASK_OF: dict[type, str] = {
    p.GetPowerData: "power",
    p.GetPayloadStatus: "payload",
    p.GetEnvData: "env",
    p.GetButtons: "buttons",
    p.GetImuData: "imu",
}


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi
