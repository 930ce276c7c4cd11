"""The blocking Control Bus master: a ``BoardConnection`` driven over a ``Port`` on a clock.

``BoardClient`` turns a typed request into a typed reply, or raises one of the connection's
errors (``BoardTimeout``, ``BoardRefused``, ``BoardProtocolError``; ``BoardDisconnected`` when the
port fails). Every decision (retries, SYNC, stale replies, timeouts) is the connection's; this
class only moves bytes and reads the clock. It lives here rather than in the agent because every
master uses it: the agent's ``BoardSession``, ``fleetlink board probe``, the benches and tests.
"""

from __future__ import annotations

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.connection import (
    Answered,
    BoardConnection,
    BoardDisconnected,
    BoardError,
    BoardProtocolError,
    BoardRefused,
    BoardTimeout,
    Echoed,
    Event,
    Failed,
    LinkStats,
    Synced,
    Transmit,
    Waiting,
)
from fleetlink.devices.ports import Port, PortClosed
from fleetlink.shared.clock import Clock

__all__ = [
    "BoardClient",
    "BoardDisconnected",
    "BoardError",
    "BoardProtocolError",
    "BoardRefused",
    "BoardTimeout",
    "LinkStats",
]


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
        self.connection = BoardConnection(profile, timeout, retries)

    @property
    def stats(self) -> LinkStats:
        return self.connection.stats

    @property
    def profile(self) -> p.Profile:
        return self.connection.profile

    @property
    def timeout(self) -> float:
        return self.connection.timeout

    @property
    def retries(self) -> int:
        return self.connection.retries

    def request(self, req: p.Request, timeout: float | None = None) -> p.Reply:
        """Send one typed request; return its typed reply (retrying timeouts and garbled exchanges)."""
        self.begin(req, timeout)
        return self._reply(self._complete())

    def begin(self, req: p.Request, timeout: float | None = None) -> None:
        """Write a request and return at once, without its reply: ``finish()`` takes the reply (and
        runs the retries). ``request`` is the two in a row. A caller that must not wait for the
        board's answer (a new velocity, sent from the thread that decided it) begins the exchange
        and leaves it to the one who finishes; nothing else may be sent in between."""
        data = self.connection.send(req, self.clock.now(), timeout)
        try:
            self.port.write(data)
        except PortClosed as exc:
            self.connection.abandon()
            raise BoardDisconnected(str(exc)) from exc

    @property
    def in_flight(self) -> bool:
        """An exchange has begun and not finished."""
        return self.connection.busy

    def finish(self) -> p.Reply:
        """The reply to the request ``begin`` wrote (waiting for it, retrying as the connection
        says). What has already arrived is taken first: a reply that came in time is not taken for
        a timeout because its reader came late."""
        try:
            self.connection.receive_data(self.port.read_some(self.clock, self.clock.now()))
        except PortClosed as exc:
            self.connection.abandon()
            raise BoardDisconnected(str(exc)) from exc
        return self._reply(self._complete())

    @staticmethod
    def _reply(event: Event) -> p.Reply:
        if isinstance(event, Answered):
            return event.reply
        raise _error(event)

    def sync(self, timeout: float | None = None) -> None:
        """SYNC with a fresh nonce; everything received before its echo is discarded."""
        event = self._exchange(self.connection.sync(self.clock.now(), timeout))
        if not isinstance(event, Synced):
            raise _error(event)

    def echo(self, data: bytes) -> bytes:
        """ECHO: the board sends the frame back; returns the echoed payload."""
        event = self._exchange(self.connection.echo(data, self.clock.now()))
        if isinstance(event, Echoed):
            return event.data
        raise _error(event)

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

    def _exchange(self, data: bytes) -> Event:
        """Write ``data``, then move bytes and time until the connection has an answer."""
        try:
            self.port.write(data)
        except PortClosed as exc:
            self.connection.abandon()
            raise BoardDisconnected(str(exc)) from exc
        return self._complete()

    def _complete(self) -> Event:
        """Move bytes and time until the exchange in flight has an answer."""
        conn = self.connection
        clock = self.clock
        try:
            now = clock.now()
            while True:
                event = conn.next_event(now)
                if type(event) is Waiting:
                    deadline = event.deadline
                    assert deadline is not None
                    data = self.port.read_some(clock, deadline)
                    conn.receive_data(data)
                    # Nothing read means the port waited out the deadline (or, in lockstep, will not wait).
                    now = clock.now() if data else max(clock.now(), deadline)
                elif type(event) is Transmit:
                    self.port.write(event.data)
                    now = clock.now()
                else:
                    return event
        except PortClosed as exc:
            conn.abandon()
            raise BoardDisconnected(str(exc)) from exc


def _error(event: Event) -> BoardError:
    if isinstance(event, Failed):
        return event.error
    return BoardProtocolError(f"unexpected {type(event).__name__} from the connection")
