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
    drv.start_scan()                     # motor on (DTR low, and SET_MOTOR_PWM), SCAN, descriptor
    while running:
        for rev in drv.poll(clock.now() + 0.2):
            use(rev.angles_rad, rev.distances_m)
    drv.close()                          # STOP, motor off, port closed

Requests (``get_info`` and friends) stop a running scan first, as SLAMTEC's SDK requires. ``stop()``
sends STOP and then discards what still arrives until the line has been quiet for ``settle``
seconds, so stale nodes never reach the next answer.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TypeVar

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
]

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
    last_rx: float | None = None  # clock time of the last bytes received


A = TypeVar("A", lp.DeviceInfo, lp.DeviceHealth, lp.SampleRate)


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
    ) -> None:
        """``timeout``: for each answer; ``settle``: the quiet time that ends a STOP's drain;
        ``stall_timeout``: ``poll`` raises ``LidarTimeout`` after this long without a byte while
        scanning; ``pwm_motor_control``: also send SET_MOTOR_PWM to start/stop the motor (an A1
        ignores it, units with a motor controller and our simulator over TCP need it);
        ``opener``: makes a fresh port for ``reconnect()``."""
        self.port = port
        self.clock = clock
        self.timeout = timeout
        self.settle = settle
        self.stall_timeout = stall_timeout
        self.motor_pwm = motor_pwm
        self.pwm_motor_control = pwm_motor_control
        self.opener = opener
        self.stats = DriverStats()
        self.decoder = lp.LidarDecoder(batch=True)
        self.assembler = lp.RevolutionAssembler()
        self._scanning = False
        self._motor_on = False
        self._ready: list[lp.Revolution] = []
        self._closed = False

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
        """Start the motor (again: its state is unknown after a power cycle or a lost request), send
        SCAN (FORCE_SCAN: stream even before the motor is up to speed) and wait for the scan
        descriptor. Nodes that follow it in the same read are kept for ``poll``."""
        if self._scanning:
            self.stop()
        self.start_motor()
        self.decoder.reset()
        self.assembler.reset()
        self._ready.clear()
        cmd = lp.Command.FORCE_SCAN if force else lp.Command.SCAN
        self.stats.requests += 1
        self._write(lp.encode_request(cmd))
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
                if ev != lp.SCAN_DESCRIPTOR:
                    self.stats.protocol_errors += 1
                    self.decoder.reset()
                    raise LidarProtocolError(f"{cmd.name}: unexpected answer {ev} (wanted {lp.SCAN_DESCRIPTOR})")
                self._scanning = True
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
            revs = self._absorb(self.decoder.feed(data))
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

    def _request(self, cmd: lp.Command, kind: type[A], answer: lp.AnswerType, timeout: float | None) -> A:
        if self._scanning:
            self.stop()
        self.decoder.reset()
        self.stats.requests += 1
        self._write(lp.encode_request(cmd))
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

    def _absorb(self, events: Iterable[lp.Event]) -> list[lp.Revolution]:
        out: list[lp.Revolution] = []
        now = self.clock.now()
        for ev in events:
            if isinstance(ev, (lp.NodeBatch, lp.Node)):
                for rev in self.assembler.push(ev):
                    out.append(lp.Revolution(rev.angles_rad, rev.distances_m, rev.qualities, now))
            else:
                # A descriptor mid-scan: the lidar restarted its stream; the turn in progress is void.
                self.stats.stray_events += 1
                if isinstance(ev, lp.Descriptor):
                    self.assembler.reset()
        self.stats.revolutions += len(out)
        return out

    def _end_scan(self) -> None:
        self._scanning = False
        self._ready.clear()
        self.assembler.reset()

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
