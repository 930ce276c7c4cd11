"""The master side of the Control Bus: one request in flight, timeouts, bounded retries, resync.

``BoardClient`` turns a typed request into a typed reply over a ``Port``, or raises one of a small
tree of errors:

    BoardError
    ├── BoardTimeout       no reply in time (also a TimeoutError)
    ├── BoardRefused       the board understood and said no (0x8000, 0x8001, 0x8002)
    ├── BoardProtocolError the exchange broke: 0x0010/0x0020/0x0040 replies, or a reply we
    │                      cannot parse (we, or the line, broke the protocol)
    └── BoardDisconnected  the port failed or closed

Timeouts and protocol errors are retried after a SYNC (which flushes stale replies); refusals
are not, since asking again gets the same answer.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field
from typing import TypeVar

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.frames import Frame, FrameDecoder
from fleetlink.devices.ports import Port, PortClosed
from fleetlink.shared.clock import Clock

log = logging.getLogger(__name__)

__all__ = [
    "BoardClient",
    "BoardDisconnected",
    "BoardError",
    "BoardProtocolError",
    "BoardRefused",
    "BoardTimeout",
    "LinkStats",
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


R = TypeVar("R")


class BoardClient:
    """Synchronous request/response over one port. Not thread-safe: one caller at a time."""

    def __init__(
        self,
        port: Port,
        clock: Clock,
        profile: p.Profile = p.DEFAULT_PROFILE,
        timeout: float = 0.1,
        retries: int = 2,
    ) -> None:
        self.port = port
        self.clock = clock
        self.profile = profile
        self.timeout = timeout
        self.retries = retries
        self.stats = LinkStats()
        self._decoder = FrameDecoder(valid_codes=p.REPLY_CODES)
        self._pending: deque[Frame] = deque()
        self._nonce = 0

    # -- public ---------------------------------------------------------------------------

    def request(self, req: p.Request, timeout: float | None = None) -> p.Reply:
        """Send one typed request; return its typed reply (retrying timeouts and garbled exchanges)."""
        frame = p.encode_request(req, self.profile)
        last: BoardError | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                self.stats.retries += 1
                try:
                    self.sync()
                except BoardTimeout as exc:
                    last = exc
                    continue
            try:
                return self._exchange(req, frame, timeout or self.timeout)
            except (BoardTimeout, BoardProtocolError) as exc:
                last = exc
                log.debug("board %s on %s (attempt %d)", type(exc).__name__, type(req).__name__, attempt + 1)
        assert last is not None
        raise last

    def sync(self, timeout: float | None = None) -> None:
        """SYNC with a fresh nonce; everything received before its echo is discarded."""
        self._nonce = (self._nonce + 1) & 0xFFFF_FFFF
        nonce = self._nonce.to_bytes(4, "little")
        self.stats.syncs += 1
        self._pending.clear()
        self._write(p.encode_sync(nonce, self.profile))
        deadline = self.clock.now() + (timeout or self.timeout)
        while True:
            frame = self._next_frame(deadline)
            if frame is None:
                self.stats.timeouts += 1
                raise BoardTimeout("no answer to SYNC")
            if frame.code == p.RESP_SYNC and frame.payload == nonce:
                return
            self.stats.stale_replies += 1

    def echo(self, data: bytes) -> bytes:
        """ECHO: the board sends the frame back; returns the echoed payload."""
        self._write(p.encode_echo(data, self.profile))
        deadline = self.clock.now() + self.timeout
        while True:
            frame = self._next_frame(deadline)
            if frame is None:
                self.stats.timeouts += 1
                raise BoardTimeout("no answer to ECHO")
            if frame.code == p.RESP_ECHO:
                return frame.payload
            self.stats.stale_replies += 1

    def connect(self, attempts: int = 5) -> p.BaseInfo:
        """SYNC then CONNECT_BASE, repeated until the board answers (the master's handshake)."""
        last: BoardError | None = None
        for _ in range(max(1, attempts)):
            try:
                self.sync()
                info = self.request(p.ConnectBase(1))
                assert isinstance(info, p.BaseInfo)
                return info
            except (BoardTimeout, BoardProtocolError) as exc:
                last = exc
        raise BoardTimeout(f"board did not answer CONNECT_BASE after {attempts} attempts: {last}")

    def close(self) -> None:
        self.port.close()

    # -- internals ------------------------------------------------------------------------

    def _exchange(self, req: p.Request, frame: bytes, timeout: float) -> p.Reply:
        if self._pending:
            # Replies nobody asked for (late answers to an abandoned request).
            self.stats.stale_replies += len(self._pending)
            self._pending.clear()
        self.stats.requests += 1
        start = self.clock.now()
        self._write(frame)
        deadline = start + timeout
        while True:
            got = self._next_frame(deadline)
            if got is None:
                self.stats.timeouts += 1
                self._decoder.skip_candidate()  # a false start must not hold back the next reply
                raise BoardTimeout(f"no reply to {type(req).__name__} within {timeout * 1000:.0f} ms")
            reply = p.decode_reply(got, req.REPLY)
            if isinstance(reply, (p.Sync, p.Echo)):
                self.stats.stale_replies += 1
                continue
            self.stats.replies += 1
            self.stats.rtt_s.append(self.clock.now() - start)
            if isinstance(reply, p.ErrorReply):
                if reply.is_protocol_error:
                    self.stats.protocol_errors += 1
                    raise BoardProtocolError(f"{type(req).__name__}: board answered {reply}")
                self.stats.refusals += 1
                raise BoardRefused(req, reply.code)
            if isinstance(reply, (p.Malformed, p.InvalidReply)):
                self.stats.protocol_errors += 1
                raise BoardProtocolError(f"{type(req).__name__}: {reply}")
            return reply

    def _write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except PortClosed as exc:
            raise BoardDisconnected(str(exc)) from exc

    def _next_frame(self, deadline: float) -> Frame | None:
        while not self._pending:
            try:
                data = self.port.read_some(self.clock, deadline)
            except PortClosed as exc:
                raise BoardDisconnected(str(exc)) from exc
            if not data:
                return None
            for item in self._decoder.feed(data):
                if isinstance(item, Frame):
                    self._pending.append(item)
            if not self._pending and self.clock.now() >= deadline:
                return None  # bytes keep coming, but no frame in them
        return self._pending.popleft()
