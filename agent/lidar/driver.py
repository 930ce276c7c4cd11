"""The master side of the RPLIDAR A1 link over a port: requests, the motor, the scan stream.

``LidarDriver(port, clock)`` talks through any ``fleetlink.devices.ports`` port (``SerialPort`` by
URL: ``/dev/ttyUSB0``, a pty, ``socket://host:port``; an ``InProcessPort``, such as
``field.rplidar.SimulatedRplidar.in_process_port``). It is thread-free and not thread-safe: one
caller at a time (the agent runs it in a thread of its own). Failures raise one small tree:

    LidarError
    ├── LidarTimeout        no answer in time, or a scan that stopped delivering (also TimeoutError)
    ├── LidarProtocolError  an answer of the wrong type or size
    └── LidarDisconnected   the port failed or closed (also ConnectionError); ``reconnect()``

Typical use::

    drv = LidarDriver.open("/dev/ttyUSB0", SystemClock())
    drv.get_health()                     # DeviceHealth(status=0, error_code=0)
    drv.start_scan()                     # motor on (DTR low, and SET_MOTOR_PWM), the scan mode
                                         # (GET_LIDAR_CONF's typical one), EXPRESS_SCAN or SCAN
    while running:
        for rev in drv.poll(clock.now() + 0.2):
            use(rev.angles_rad, rev.distances_m)
    drv.close()                          # STOP, motor off, port closed

Scan modes, as SLAMTEC's SDK picks them (``scan_mode="auto"``, the default): GET_LIDAR_CONF asks
for the typical mode and its answer type; capsules (0x82) mean EXPRESS_SCAN with the mode's id,
nodes (0x81) mean SCAN; a typical mode in a format fleetlink does not decode falls back to another
capsule mode the unit lists, else SCAN. A unit that does not answer GET_LIDAR_CONF within
``conf_timeout`` (firmware before 1.24) gets SCAN. The choice is kept until ``reconnect()``.
``scan_mode="standard"`` always sends SCAN, ``"express"`` the legacy EXPRESS_SCAN (working mode 0).

Requests (``get_info`` and friends) stop a running scan first, as SLAMTEC's SDK requires. ``stop()``
sends STOP and then discards what still arrives until the line has been quiet for ``settle``
seconds, so stale nodes never reach the next answer.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Literal, TypeVar

from fleetlink.agent.lidar.stamps import TurnStamps
from fleetlink.devices.ports import Port, PortClosed
from fleetlink.devices.rplidar import protocol as lp
from fleetlink.shared.clock import Clock

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_MOTOR_PWM",
    "DriverStats",
    "LidarDisconnected",
    "LidarDriver",
    "LidarError",
    "LidarProtocolError",
    "LidarTimeout",
    "ScanChoice",
]

ScanChoice = Literal["auto", "standard", "express"]

DEFAULT_MOTOR_PWM = 660  # SLAMTEC's default motor duty for units with PWM motor control


class LidarError(Exception):
    """Anything that went wrong talking to the lidar."""


class LidarTimeout(LidarError, TimeoutError):
    pass


class LidarProtocolError(LidarError):
    pass


class LidarDisconnected(LidarError, ConnectionError):
    pass


@dataclass(slots=True)
class DriverStats:
    requests: int = 0
    timeouts: int = 0
    protocol_errors: int = 0
    scans: int = 0  # scans started
    revolutions: int = 0
    bytes_in: int = 0
    stale_bytes: int = 0  # discarded after STOP / RESET
    stray_events: int = 0  # answers nobody asked for (e.g. a descriptor in the middle of a scan)
    reconnects: int = 0
    conf_unanswered: int = 0  # GET_LIDAR_CONF timed out while picking the scan mode (old firmware)
    last_rx: float | None = None  # clock time of the last bytes received


T = TypeVar("T")
A = TypeVar("A", lp.DeviceInfo, lp.DeviceHealth, lp.SampleRate, lp.LidarConf)


class LidarDriver:
    """Synchronous RPLIDAR master over one port."""

    def __init__(
        self,
        port: Port,
        clock: Clock,
        *,
        timeout: float = 0.5,
        settle: float = 0.02,
        stall_timeout: float = 2.0,
        motor_pwm: int = DEFAULT_MOTOR_PWM,
        pwm_motor_control: bool = True,
        opener: Callable[[], Port] | None = None,
        scan_mode: ScanChoice = "auto",
        conf_timeout: float | None = None,
    ) -> None:
        """``timeout``: for each answer; ``settle``: the quiet time that ends a STOP's drain;
        ``stall_timeout``: ``poll`` raises ``LidarTimeout`` after this long without a byte while
        scanning; ``pwm_motor_control``: also send SET_MOTOR_PWM to start/stop the motor (an A1
        ignores it, units with a motor controller and our simulator over TCP need it);
        ``opener``: makes a fresh port for ``reconnect()``; ``scan_mode``: "auto" (the unit's typical
        mode, as SLAMTEC's SDK), "standard" (SCAN) or "express" (legacy EXPRESS_SCAN);
        ``conf_timeout``: how long "auto" waits for GET_LIDAR_CONF before taking SCAN (``timeout``)."""
        if scan_mode not in ("auto", "standard", "express"):
            raise ValueError(f"scan_mode {scan_mode!r} is not auto, standard or express")
        self.port = port
        self.clock = clock
        self.timeout = timeout
        self.settle = settle
        self.stall_timeout = stall_timeout
        self.motor_pwm = motor_pwm
        self.pwm_motor_control = pwm_motor_control
        self.opener = opener
        self.scan_mode = scan_mode
        self.conf_timeout = conf_timeout
        self.stats = DriverStats()
        self.decoder = lp.LidarDecoder(batch=True)
        self.assembler = lp.RevolutionAssembler()
        self.turns = TurnStamps()  # each turn's stamp: when it was complete, not when it was read
        self._scanning = False
        self._motor_on = False
        self._ready: list[lp.Revolution] = []
        self._closed = False
        self._choice: tuple[int, lp.ScanMode | None] | None = None  # (working mode or -1 for SCAN, mode)
        self.mode: lp.ScanMode | None = None  # the scan mode of the running scan, if the unit described it

    @classmethod
    def open(cls, url: str, clock: Clock, baudrate: int = 115200, **kwargs: object) -> LidarDriver:
        """Open a port by URL (pyserial's ``serial_for_url``); ``reconnect()`` reopens the same URL."""
        from fleetlink.devices.ports import SerialPort

        def opener() -> Port:
            return SerialPort(url, baudrate)

        try:
            port = opener()
        except PortClosed as exc:
            raise LidarDisconnected(str(exc)) from exc
        return cls(port, clock, opener=opener, **kwargs)  # type: ignore[arg-type]

    # -- state -----------------------------------------------------------------------------------

    @property
    def scanning(self) -> bool:
        return self._scanning

    @property
    def motor_on(self) -> bool:
        return self._motor_on

    # -- requests --------------------------------------------------------------------------------

    def get_info(self, timeout: float | None = None) -> lp.DeviceInfo:
        return self._request(lp.Command.GET_INFO, lp.DeviceInfo, lp.AnswerType.DEVICE_INFO, timeout)

    def get_health(self, timeout: float | None = None) -> lp.DeviceHealth:
        return self._request(lp.Command.GET_HEALTH, lp.DeviceHealth, lp.AnswerType.DEVICE_HEALTH, timeout)

    def get_samplerate(self, timeout: float | None = None) -> lp.SampleRate:
        return self._request(lp.Command.GET_SAMPLERATE, lp.SampleRate, lp.AnswerType.SAMPLE_RATE, timeout)

    def get_lidar_conf(self, conf: int, mode: int | None = None, timeout: float | None = None) -> lp.LidarConf:
        """One GET_LIDAR_CONF entry (``lp.ConfType``), for scan mode ``mode`` where the entry is per mode."""
        ans = self._request(
            lp.Command.GET_LIDAR_CONF,
            lp.LidarConf,
            lp.AnswerType.LIDAR_CONF,
            timeout,
            payload=lp.encode_conf_request(conf, mode)[3:-1],
        )
        if ans.type != conf:
            self.stats.protocol_errors += 1
            raise LidarProtocolError(f"GET_LIDAR_CONF 0x{conf:X}: the answer is for 0x{ans.type:X}")
        return ans

    def get_typical_mode(self, timeout: float | None = None) -> int:
        return self._conf_value(lambda: self.get_lidar_conf(lp.ConfType.SCAN_MODE_TYPICAL, None, timeout).u16())

    def get_scan_mode(self, mode: int, timeout: float | None = None) -> lp.ScanMode:
        """A scan mode's description: four GET_LIDAR_CONF requests, as SLAMTEC's SDK makes them."""
        c = lp.ConfType

        def ask() -> lp.ScanMode:
            us = self.get_lidar_conf(c.SCAN_MODE_US_PER_SAMPLE, mode, timeout).q8()
            dist = self.get_lidar_conf(c.SCAN_MODE_MAX_DISTANCE, mode, timeout).q8()
            ans = self.get_lidar_conf(c.SCAN_MODE_ANS_TYPE, mode, timeout).u8()
            name = self.get_lidar_conf(c.SCAN_MODE_NAME, mode, timeout).text()
            return lp.ScanMode(mode, name, us, dist, ans)

        return self._conf_value(ask)

    def get_scan_modes(self, timeout: float | None = None) -> list[lp.ScanMode]:
        count = self._conf_value(lambda: self.get_lidar_conf(lp.ConfType.SCAN_MODE_COUNT, None, timeout).u16())
        return [self.get_scan_mode(i, timeout) for i in range(count)]

    def stop(self) -> None:
        """STOP: end the scan (the motor keeps turning); discard what is still on its way."""
        self._write(lp.encode_request(lp.Command.STOP))
        self._end_scan()
        self._drain(self.settle)

    def reset(self, wait: float = 0.05) -> bytes:
        """RESET the lidar's core; returns what it printed within ``wait`` quiet seconds (its boot
        banner, on units that print one). A real A1 needs a few hundred ms before it answers again."""
        self._write(lp.encode_request(lp.Command.RESET))
        self._end_scan()
        return self._drain(wait, keep=True)

    # -- motor -----------------------------------------------------------------------------------

    def start_motor(self, pwm: int | None = None) -> None:
        """DTR low where the port has DTR (the A1's motor), and SET_MOTOR_PWM if enabled."""
        self._set_dtr(False)
        if self.pwm_motor_control:
            self.set_motor_pwm(self.motor_pwm if pwm is None else pwm)
        self._motor_on = True

    def stop_motor(self) -> None:
        self._set_dtr(True)
        if self.pwm_motor_control:
            self.set_motor_pwm(0)
        self._motor_on = False

    def set_motor_pwm(self, pwm: int) -> None:
        if not 0 <= pwm <= 1023:
            raise ValueError(f"motor PWM {pwm} is outside 0-1023")
        self._write(lp.encode_request(lp.Command.SET_MOTOR_PWM, pwm.to_bytes(2, "little")))

    # -- scanning --------------------------------------------------------------------------------

    def start_scan(self, force: bool = False, timeout: float | None = None) -> lp.Descriptor:
        """Start the motor (again: its state is unknown after a power cycle or a lost request), pick
        the scan mode (``scan_mode``; the first scan asks the unit), send EXPRESS_SCAN or SCAN
        (FORCE_SCAN with ``force``: stream even before the motor is up to speed; express scans have
        no forced variant) and wait for the descriptor. Samples that follow it in the same read are
        kept for ``poll``."""
        if self._scanning:
            self.stop()
        working_mode, mode = self._pick_mode()
        self.start_motor()
        self.decoder.reset()
        self.assembler.reset()
        self.turns.reset()
        self._ready.clear()
        if working_mode < 0:
            cmd = lp.Command.FORCE_SCAN if force else lp.Command.SCAN
            request = lp.encode_request(cmd)
            wanted = lp.SCAN_DESCRIPTOR
        else:
            cmd = lp.Command.EXPRESS_SCAN
            request = lp.encode_express_request(working_mode)
            wanted = lp.EXPRESS_DESCRIPTOR
        self.stats.requests += 1
        self._write(request)
        wait = self.timeout if timeout is None else timeout
        deadline = self.clock.now() + wait
        while True:
            data = self._read(deadline)
            if not data:
                self.stats.timeouts += 1
                raise LidarTimeout(f"no answer to {cmd.name} within {wait * 1000:.0f} ms")
            events = self.decoder.feed(data)
            for i, ev in enumerate(events):
                if not isinstance(ev, lp.Descriptor):
                    self.stats.stray_events += 1
                    continue
                if ev != wanted:
                    self.stats.protocol_errors += 1
                    self.decoder.reset()
                    raise LidarProtocolError(f"{cmd.name}: unexpected answer {ev} (wanted {wanted})")
                self._scanning = True
                self.mode = mode
                self.stats.scans += 1
                self.stats.last_rx = self.clock.now()
                self._ready.extend(self._absorb(events[i + 1 :]))
                return ev

    def poll(self, deadline: float) -> list[lp.Revolution]:
        """Revolutions completed by ``deadline``: returns as soon as at least one is, or ``[]`` at the
        deadline. Raises ``LidarTimeout`` when nothing at all has arrived for ``stall_timeout``."""
        if not self._scanning:
            raise LidarError("not scanning: call start_scan() first")
        if self._ready:
            out, self._ready = self._ready, []
            return out
        while True:
            data = self._read(deadline)
            if not data:
                last = self.stats.last_rx
                if last is not None and self.clock.now() - last > self.stall_timeout:
                    self.stats.timeouts += 1
                    raise LidarTimeout(f"scanning, but nothing received for {self.clock.now() - last:.1f} s")
                return []
            # A read as long as the port's chunk (``SerialPort.READ_CHUNK``) may have left more waiting.
            revs = self._absorb(self.decoder.feed(data), len(data) < getattr(self.port, "READ_CHUNK", math.inf))
            if revs:
                return revs

    def read_revolutions(self, count: int, timeout: float) -> list[lp.Revolution]:
        """Exactly ``count`` revolutions (extra ones are kept for the next call), or ``LidarTimeout``."""
        deadline = self.clock.now() + timeout
        got: list[lp.Revolution] = []
        while len(got) < count:
            got.extend(self.poll(deadline))
            if len(got) < count and self.clock.now() >= deadline:
                self._ready[:0] = got
                raise LidarTimeout(f"{len(got)} of {count} revolutions within {timeout:.1f} s")
        self._ready[:0] = got[count:]
        return got[:count]

    # -- connection ------------------------------------------------------------------------------

    def reconnect(self) -> None:
        """Close the port and open a fresh one with ``opener`` (after ``LidarDisconnected``)."""
        if self.opener is None:
            raise LidarDisconnected("no opener to reconnect with")
        with contextlib.suppress(Exception):
            self.port.close()
        self._end_scan()
        self._motor_on = False
        self._choice = None  # the unit behind the port may have changed
        self.decoder.reset()
        try:
            self.port = self.opener()
        except PortClosed as exc:
            raise LidarDisconnected(str(exc)) from exc
        self.stats.reconnects += 1
        self._closed = False

    def close(self, stop_motor: bool = True) -> None:
        """STOP a running scan, stop the motor, close the port. Idempotent; never raises."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(LidarError):
            if self._scanning:
                self._write(lp.encode_request(lp.Command.STOP))
            if stop_motor and self._motor_on:
                self.stop_motor()
        self._end_scan()
        with contextlib.suppress(Exception):
            self.port.close()

    def __enter__(self) -> LidarDriver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals -------------------------------------------------------------------------------

    def _pick_mode(self) -> tuple[int, lp.ScanMode | None]:
        """(EXPRESS_SCAN working mode, or -1 for SCAN; the mode's description if the unit gave one)."""
        if self.scan_mode == "standard":
            return -1, None
        if self.scan_mode == "express":
            return 0, None
        if self._choice is not None:
            return self._choice
        choice = self._ask_mode()
        if choice is None:  # unanswered: SCAN this time, and ask again next time
            return -1, None
        self._choice = choice
        return choice

    def _ask_mode(self) -> tuple[int, lp.ScanMode | None] | None:
        wait = self.timeout if self.conf_timeout is None else self.conf_timeout
        try:
            typical = self.get_scan_mode(self.get_typical_mode(wait), wait)
        except LidarTimeout:
            self.stats.conf_unanswered += 1
            if self.stats.conf_unanswered == 1:
                log.info("lidar: no answer to GET_LIDAR_CONF (firmware before 1.24?): standard scan")
            return None
        candidates = [typical]
        if typical.answer_type not in (lp.AnswerType.MEASUREMENT, lp.AnswerType.MEASUREMENT_CAPSULED):
            candidates = self.get_scan_modes(wait)  # e.g. ultra capsules: find a mode we decode
        for mode in candidates:
            if mode.answer_type == lp.AnswerType.MEASUREMENT_CAPSULED:
                return mode.id, mode
        for mode in candidates:
            if mode.answer_type == lp.AnswerType.MEASUREMENT:
                return -1, mode
        return -1, None

    def _conf_value(self, ask: Callable[[], T]) -> T:
        """A value read from GET_LIDAR_CONF answers; one too short to hold it is a protocol error."""
        try:
            return ask()
        except ValueError as exc:
            self.stats.protocol_errors += 1
            raise LidarProtocolError(f"GET_LIDAR_CONF: {exc}") from exc

    def _request(
        self, cmd: lp.Command, kind: type[A], answer: lp.AnswerType, timeout: float | None, payload: bytes = b""
    ) -> A:
        if self._scanning:
            self.stop()
        self.decoder.reset()
        self.stats.requests += 1
        self._write(lp.encode_request(cmd, payload))
        wait = self.timeout if timeout is None else timeout
        deadline = self.clock.now() + wait
        while True:
            data = self._read(deadline)
            if not data:
                self.stats.timeouts += 1
                self.decoder.reset()
                raise LidarTimeout(f"no answer to {cmd.name} within {wait * 1000:.0f} ms")
            for ev in self.decoder.feed(data):
                if isinstance(ev, kind):
                    return ev
                if isinstance(ev, lp.Response) and ev.type == answer:
                    self.stats.protocol_errors += 1
                    raise LidarProtocolError(f"{cmd.name}: answer of {len(ev.payload)} bytes: {ev.payload.hex()}")
                if isinstance(ev, lp.Descriptor) and ev.type == answer and ev.mode != lp.SEND_MODE_SINGLE:
                    self.stats.protocol_errors += 1
                    self.decoder.reset()
                    raise LidarProtocolError(f"{cmd.name}: answer sent as a stream: {ev}")
                if not (isinstance(ev, lp.Descriptor) and ev.type == answer):
                    self.stats.stray_events += 1

    def _absorb(self, events: Iterable[lp.Event], drained: bool = True) -> list[lp.Revolution]:
        """The turns the events complete, each stamped when it was complete on the lidar's clock
        (``TurnStamps``: from the samples read so far and when). ``drained``: the read took all that
        was waiting (a read cut at the port's chunk size left more behind: it was late by whatever
        followed, and is not a reading of when its samples were sent)."""
        out: list[lp.Revolution] = []
        ends: list[float | None] = []
        now = self.clock.now()
        for ev in events:
            if isinstance(ev, (lp.NodeBatch, lp.Node)):
                for rev in self.assembler.push(ev):
                    out.append(rev)
                    ends.append(self.turns.count(len(rev)))
            else:
                # A descriptor mid-scan: the lidar restarted its stream; the turn in progress is void.
                self.stats.stray_events += 1
                if isinstance(ev, lp.Descriptor):
                    self.assembler.reset()
                    self.turns.reset()
                    ends = [None] * len(ends)  # on the line before the restart: stamped when read
        if drained and self.assembler.started:
            # Every sample whose bytes have come: the turns', the turn under way's and a capsule's held
            # back (not before a turn's start: the nodes before it are dropped, a capsule's with them).
            self.turns.observe(self.turns.samples + self.assembler.partial + self.decoder.held_samples, now)
        self.stats.revolutions += len(out)
        return [
            lp.Revolution(r.angles_rad, r.distances_m, r.qualities, now if end is None else self.turns.stamp(end, now))
            for r, end in zip(out, ends, strict=True)
        ]

    def _end_scan(self) -> None:
        self._scanning = False
        self._ready.clear()
        self.assembler.reset()
        self.turns.reset()

    def _drain(self, quiet: float, keep: bool = False, limit: float = 0.5) -> bytes:
        """Read until the line has been quiet for ``quiet`` s (at most ``limit`` s); then the decoder
        starts afresh. Returns what was read if ``keep``."""
        kept = bytearray()
        end = self.clock.now() + limit
        while True:
            now = self.clock.now()
            if now >= end:
                break
            data = self._read(min(end, now + quiet))
            if not data:
                break
            self.stats.stale_bytes += len(data)
            if keep:
                kept += data
        self.decoder.reset()
        return bytes(kept)

    def _set_dtr(self, level: bool) -> None:
        set_dtr = getattr(self.port, "set_dtr", None)
        if set_dtr is not None:
            try:
                set_dtr(level)
            except PortClosed as exc:
                raise LidarDisconnected(str(exc)) from exc

    def _write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except PortClosed as exc:
            self._end_scan()
            raise LidarDisconnected(str(exc)) from exc

    def _read(self, deadline: float) -> bytes:
        try:
            data = self.port.read_some(self.clock, deadline)
        except PortClosed as exc:
            self._end_scan()
            raise LidarDisconnected(str(exc)) from exc
        if data:
            self.stats.bytes_in += len(data)
            self.stats.last_rx = self.clock.now()
        return data
