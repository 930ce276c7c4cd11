"""The master's side of the Control Bus as a sans-I/O state machine, in the manner of h11.

``BoardConnection`` holds what one exchange needs: the request in flight, its deadline, the SYNC
nonce and the retry count. It never reads, writes or looks at a clock: ``send(request, now)``
returns the bytes to write, ``receive_data(data)`` takes whatever arrived, and ``next_event(now)``
says what happened:

* ``Waiting(deadline)``: nothing yet; read until ``deadline`` and feed what comes (or call
  ``next_event`` again with ``now >= deadline`` if nothing will);
* ``Transmit(data)``: write these bytes (a retry: the SYNC that flushes stale replies, then the
  request again);
* ``Answered(request, reply, rtt)``, ``Synced()``, ``Echoed(data)``: the exchange is done;
* ``Failed(error)``: it is done and failed, with one of the error tree below.

One exchange at a time. Timeouts and protocol errors are retried after a SYNC with a fresh nonce
(everything received before its echo is discarded); refusals are not, since asking again gets the
same answer. Errors:

    BoardError
    ├── BoardTimeout       no reply in time (also a TimeoutError)
    ├── BoardRefused       the board understood and said no (0x8000, 0x8001, 0x8002)
    ├── BoardProtocolError the exchange broke: 0x0010/0x0020/0x0040 replies, or a reply we
    │                      cannot parse (we, or the line, broke the protocol)
    └── BoardDisconnected  the port failed or closed (raised by the I/O side, ``client``)
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple, TypeAlias

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.frames import Frame, FrameDecoder

__all__ = [
    "Answered",
    "BoardConnection",
    "BoardDisconnected",
    "BoardError",
    "BoardProtocolError",
    "BoardRefused",
    "BoardTimeout",
    "Echoed",
    "Event",
    "Failed",
    "LinkStats",
    "Synced",
    "Transmit",
    "Waiting",
]


class BoardError(Exception):
    """Anything that went wrong talking to the board."""


class BoardTimeout(BoardError, TimeoutError):
    pass


class BoardRefused(BoardError):
    def __init__(self, request: object, code: int) -> None:
        super().__init__(f"board refused {type(request).__name__}: {p.ErrorCode.describe(code)}")
        self.request = request
        self.code = code


class BoardProtocolError(BoardError):
    pass


class BoardDisconnected(BoardError, ConnectionError):
    pass


@dataclass(slots=True)
class LinkStats:
    requests: int = 0
    replies: int = 0
    timeouts: int = 0
    retries: int = 0
    refusals: int = 0
    protocol_errors: int = 0
    syncs: int = 0
    stale_replies: int = 0
    rtt_s: deque[float] = field(default_factory=lambda: deque(maxlen=512))


# -- events ----------------------------------------------------------------------------------------


class Waiting(NamedTuple):
    """Nothing to report: read until ``deadline`` (None: no exchange in flight)."""

    deadline: float | None


class Transmit(NamedTuple):
    """Bytes the connection decided to send on its own (a retry)."""

    data: bytes


class Answered(NamedTuple):
    request: p.Request
    reply: p.Reply
    rtt: float  # s, from the last attempt's send to its reply


class Synced(NamedTuple):
    pass


class Echoed(NamedTuple):
    data: bytes


class Failed(NamedTuple):
    error: BoardError


Event: TypeAlias = Waiting | Transmit | Answered | Synced | Echoed | Failed

_IDLE, _REQUEST, _SYNC, _ECHO = range(4)


class BoardConnection:
    """One master's exchanges with one board, without I/O. Not thread-safe."""

    def __init__(self, profile: p.Profile = p.DEFAULT_PROFILE, timeout: float = 0.1, retries: int = 2) -> None:
        self.profile = profile
        self.timeout = timeout
        self.retries = retries
        self.stats = LinkStats()
        self._decoder = FrameDecoder(valid_codes=p.REPLY_CODES)
        self._pending: deque[Frame] = deque()
        self._state = _IDLE
        self._nonce = 0
        self._nonce_bytes = b""
        self._deadline = 0.0
        # The request in flight: its bytes, its timeout, when its last attempt went out, attempts made.
        self._request: p.Request | None = None
        self._frame = b""
        self._request_timeout = timeout
        self._start = 0.0
        self._attempt = 0
        self._retrying = False  # the SYNC in flight is a retry's, and the request follows it

    @property
    def busy(self) -> bool:
        return self._state != _IDLE

    @property
    def deadline(self) -> float | None:
        return None if self._state == _IDLE else self._deadline

    # -- starting an exchange ----------------------------------------------------------------------

    def send(self, request: p.Request, now: float, timeout: float | None = None) -> bytes:
        """Start a request (with its retries); returns the bytes to write."""
        self._check_idle()
        self._request = request
        self._frame = p.encode_request(request, self.profile)
        self._request_timeout = timeout or self.timeout
        self._attempt = 0
        self._begin_request(now)
        return self._frame

    def sync(self, now: float, timeout: float | None = None) -> bytes:
        """Start a SYNC with a fresh nonce; returns the bytes to write."""
        self._check_idle()
        self._retrying = False
        return self._begin_sync(now, timeout or self.timeout)

    def echo(self, data: bytes, now: float) -> bytes:
        """Start an ECHO; returns the bytes to write."""
        self._check_idle()
        self._state = _ECHO
        self._deadline = now + self.timeout
        return p.encode_echo(data, self.profile)

    def abandon(self) -> None:
        """Forget the exchange in flight (the port failed); later replies count as stale."""
        self._state = _IDLE
        self._request = None

    # -- what arrives ------------------------------------------------------------------------------

    def receive_data(self, data: bytes) -> None:
        if data:
            pending = self._pending
            for item in self._decoder.feed(data):
                if isinstance(item, Frame):
                    pending.append(item)

    def next_event(self, now: float) -> Event:
        pending = self._pending
        while True:
            state = self._state
            if state == _IDLE:
                return Waiting(None)  # replies nobody asked for wait here, counted stale later
            if not pending:
                if now < self._deadline:
                    return Waiting(self._deadline)
                return self._timed_out(now)
            frame = pending.popleft()
            if state == _REQUEST:
                event = self._on_reply(frame, now)
                if event is not None:
                    return event
            elif state == _SYNC:
                if frame.code == p.RESP_SYNC and frame.payload == self._nonce_bytes:
                    if not self._retrying:
                        self._state = _IDLE
                        return Synced()
                    self._begin_request(now)
                    return Transmit(self._frame)
                self.stats.stale_replies += 1
            else:  # _ECHO
                if frame.code == p.RESP_ECHO:
                    self._state = _IDLE
                    return Echoed(frame.payload)
                self.stats.stale_replies += 1

    # -- internals ---------------------------------------------------------------------------------

    def _check_idle(self) -> None:
        if self._state != _IDLE:
            raise RuntimeError("a Control Bus exchange is already in flight")

    def _begin_request(self, now: float) -> None:
        if self._pending:
            # Replies nobody asked for (late answers to an abandoned request).
            self.stats.stale_replies += len(self._pending)
            self._pending.clear()
        self.stats.requests += 1
        self._state = _REQUEST
        self._start = now
        self._deadline = now + self._request_timeout

    def _begin_sync(self, now: float, timeout: float) -> bytes:
        self._nonce = (self._nonce + 1) & 0xFFFF_FFFF
        self._nonce_bytes = self._nonce.to_bytes(4, "little")
        self.stats.syncs += 1
        self._pending.clear()
        self._state = _SYNC
        self._deadline = now + timeout
        return p.encode_sync(self._nonce_bytes, self.profile)

    def _on_reply(self, frame: Frame, now: float) -> Event | None:
        request = self._request
        assert request is not None
        reply = p.decode_reply(frame, request.REPLY)
        if isinstance(reply, (p.Sync, p.Echo)):
            self.stats.stale_replies += 1
            return None
        stats = self.stats
        stats.replies += 1
        rtt = now - self._start
        stats.rtt_s.append(rtt)
        if isinstance(reply, p.ErrorReply):
            if reply.is_protocol_error:
                stats.protocol_errors += 1
                return self._attempt_failed(
                    BoardProtocolError(f"{type(request).__name__}: board answered {reply}"), now
                )
            stats.refusals += 1
            self._state = _IDLE
            return Failed(BoardRefused(request, reply.code))
        if isinstance(reply, (p.Malformed, p.InvalidReply)):
            stats.protocol_errors += 1
            return self._attempt_failed(BoardProtocolError(f"{type(request).__name__}: {reply}"), now)
        self._state = _IDLE
        return Answered(request, reply, rtt)

    def _timed_out(self, now: float) -> Event:
        self.stats.timeouts += 1
        state = self._state
        if state == _REQUEST:
            self._decoder.skip_candidate()  # a false start must not hold back the next reply
            name = type(self._request).__name__
            return self._attempt_failed(
                BoardTimeout(f"no reply to {name} within {self._request_timeout * 1000:.0f} ms"), now
            )
        if state == _SYNC:
            error = BoardTimeout("no answer to SYNC")
            if self._retrying:
                return self._attempt_failed(error, now)
        else:
            error = BoardTimeout("no answer to ECHO")
        self._state = _IDLE
        return Failed(error)

    def _attempt_failed(self, error: BoardError, now: float) -> Event:
        """A timeout or a broken exchange: retry after a SYNC while attempts remain."""
        if self._attempt < self.retries:
            self._attempt += 1
            self.stats.retries += 1
            self._retrying = True
            return Transmit(self._begin_sync(now, self.timeout))
        self._state = _IDLE
        self._retrying = False
        return Failed(error)
