"""The flight recorder's shell: fleet links in, an MCAP file out (docs/recording.md).

``Recorder`` subscribes to every fleetlink key (and the UWB gateways' status, and the robots'
liveliness tokens) on each link it is given, through the one link layer (``fleetlink.links``),
exactly as the console does. MQTT's thread only stamps the receive time (the injected clock's
``wall()``) and queues the bytes; Zenoh's samples wait in zenoh's own queue, stamped by zenoh on
arrival. One writer ``Worker`` wakes every ``BATCH_PERIOD_S``, takes both, turns them into records
with the pure core (site/recording.py) and writes them with the ``mcap`` library. A second worker
fetches the map and dose snapshots the core asks for (Zenoh queryables), so a robot's map can be
drawn whole and a replay can answer the console's fetches (site/replay.py).

Crash safety: the file is chunked (zstd) and flushed to the OS after every batch the writer
takes (every 250 ms while messages come), and only whole chunks reach it; a chunk is closed when it
holds ``chunk_size`` bytes or its first batch is ``chunk_age_s`` old (checked with every batch),
whichever comes first, so a ``kill -9`` loses at most the chunk being filled and the batch waiting
(at most ``chunk_age_s`` and a batch period of traffic: 1 s with the defaults).
``RecordingReader`` reads a file that was closed properly or recovers everything before a
truncated or damaged tail.
"""

from __future__ import annotations

import io
import json
import logging
import os
import struct
import threading
from collections import Counter, deque
from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetlink.links.base import Link
from fleetlink.shared import keys
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.mqtt import MqttSettings
from fleetlink.shared.worker import Worker
from fleetlink.site.recording import Channel, RecordingCore, RecordingSummary

__all__ = [
    "BATCH_PERIOD_S",
    "CHUNK_AGE_S",
    "CHUNK_SIZE",
    "ZENOH_RUNTIME",
    "FleetStream",
    "MessageAppender",
    "Recorder",
    "RecordingError",
    "RecordingReader",
    "StoredMessage",
    "fetch_snapshots",
    "open_recorder_links",
    "summarise",
    "use_recorder_runtime",
]

log = logging.getLogger(__name__)

CHUNK_SIZE = 256 * 1024
"""Uncompressed bytes a chunk holds before it is closed (~0.5 s of 50 robots' traffic)."""
CHUNK_AGE_S = 0.75
"""A chunk is closed when its first batch is this old, however little traffic there is: with the
batch before it (``BATCH_PERIOD_S``), a crash loses at most 1 s of traffic."""
INBOX_SIZE = 100_000
"""Messages waiting for the writer; beyond it they are dropped and counted (the disk stalled)."""
UWB_STATUS = "fleetlink/uwb/*/status"
ALIVE_TOKENS = keys.ZENOH_ALL_ALIVE
PROFILE = "fleetlink"
SNAPSHOT_TIMEOUT_S = 2.0


class RecordingError(Exception):
    """A recording that cannot be read (not MCAP, nothing readable). ``str()`` says why, for people."""


def open_recorder_links(
    *,
    mqtt_url: str,
    mqtt: MqttSettings | None = None,
    zenoh_listen: Sequence[str] = (),
    zenoh_connect: Sequence[str] = (),
    zenoh_auth: dict[str, Any] | None = None,
    client_id: str = "recorder",
    clock: Clock | None = None,
    role: str = "recorder",
) -> list[Link]:
    """The recorder's two endpoints (not started), set up as the console's (site/operator.py).
    ``role`` names them in logs (``fleetlink foxglove`` listens the same way: ``foxglove``). The
    recorder's Zenoh session stamps what it receives (``peer_config(timestamping=True)``): its
    receive times come from zenoh's thread without Python running per sample."""
    from fleetlink.links.mqtt import MqttEndpoint
    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.operator.links import mqtt_settings_for

    options: dict[str, Any] = dict(zenoh_auth or {})
    if role == "recorder":
        options.setdefault("timestamping", True)
    zenoh = ZenohEndpoint(listen=zenoh_listen, connect=zenoh_connect, clock=clock, label=f"zenoh-{role}", **options)
    broker = MqttEndpoint(mqtt or mqtt_settings_for(mqtt_url), client_id=client_id, clock=clock, label=f"mqtt-{role}")
    return [zenoh, broker]


def fetch_snapshots(
    links: Sequence[Link],
    wanted: Sequence[tuple[str, str]],
    deliver: Callable[[str, str, bytes], None],
    stopping: Callable[[], bool] = lambda: False,
    timeout_s: float = SNAPSHOT_TIMEOUT_S,
) -> None:
    """Ask each ``(robot, topic)`` snapshot (``fleetlink/v1/<robot>/map``, ``.../dose``) of the first
    link that answers queries (Zenoh's queryables) and hand each reply to ``deliver(link, key,
    payload)``, which checks it as any message. A failed query is tried again when it is wanted again."""
    for robot, topic in wanted:
        if stopping():
            return
        for link in links:
            query = getattr(link, "query", None)
            if query is None:
                continue
            try:
                replies = query(keys.key(robot, topic), timeout_s)
            except Exception as exc:  # a closing session: try again next time
                log.debug("%s query for %s failed: %s", topic, robot, exc)
                continue
            for key, payload in replies:
                deliver(link.name.value, key, payload)
            break


_Heard = tuple[bool, str, str, bytes | bool, float]
"""(liveliness?, link, key, payload or alive, receive time): what a link's thread queues."""

BATCH_PERIOD_S = 0.25
"""How often the writer wakes: it takes the Zenoh samples waiting in zenoh's queue
(``ZenohEndpoint.subscribe_pull``) and the MQTT messages its link queued, and writes them. Every
message keeps the time it arrived (zenoh's stamp, the MQTT link's), so a batch costs no accuracy.
Each wake costs the same ~0.5 ms however few messages it takes (the writer's code and data are
cold again after a pause): four wakes a second write 50 robots' traffic with ~10 % less CPU than
ten (docs/recording.md, "Cost")."""


ZENOH_RUNTIME = "(rx: (worker_threads: 1))"
"""zenoh's runtime in a recorder process (``fleetlink record``; the ``ZENOH_RUNTIME`` variable, RON):
one receive worker thread instead of zenoh's default two. The recorder's session reads a link or
two; with two workers the receive work moved between them, and on a loaded host zenoh's threads
cost 1.6-5.2 % of a core against 1.4-2.0 % with one worker, alternated in the same session at load
4.8-6 (docs/recording.md, "Cost"). One worker reads 50 robots' traffic in about 1.5 % of a core."""


def use_recorder_runtime() -> None:
    """Before the process's first zenoh session (zenoh reads ``ZENOH_RUNTIME`` once, when its
    runtime starts): the recorder's runtime, unless the environment already names one."""
    os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)


_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
"""An MCAP Message record's opcode, length, channel id, sequence, log time and publish time."""
_MESSAGE_OPCODE = 0x05
_MESSAGE_INDEX_OPCODE = 0x07
_PACKED_INDEX: Any = None


def _packed_index_class() -> Any:
    """The ``mcap`` library's ``MessageIndex`` written in one ``struct.pack`` (the library writes
    each entry's two integers apiece: ~1 us a message when a chunk is closed)."""
    global _PACKED_INDEX
    if _PACKED_INDEX is None:
        from mcap.records import MessageIndex

        class PackedIndex(MessageIndex):
            def write(self, stream: Any) -> None:
                n = len(self.records)
                flat = [v for entry in self.records for v in entry]
                stream.write(
                    struct.pack(f"<BQHI{2 * n}Q", _MESSAGE_INDEX_OPCODE, 6 + 16 * n, self.channel_id, 16 * n, *flat)
                )

        _PACKED_INDEX = PackedIndex
    return _PACKED_INDEX


class MessageAppender:
    """``add(channel_id, log_time, data, publish_time)``: what the ``mcap`` library's
    ``Writer.add_message`` does (the message into the open chunk, its index entry, the file's
    statistics, the chunk closed once it holds ``chunk_size`` bytes), in one packed header instead
    of a ``Message`` object written field by field: ~1 us a message where ``add_message`` takes ~4,
    and a recorder adds ~2600 a second at 50 robots. It works on the writer's own chunk builder and
    statistics (mcap 1.6's private attributes; ``fast`` is False, and ``add`` is ``add_message``,
    if a later version has none of them). tests/test_record.py checks the bytes are the library's."""

    def __init__(self, writer: Any) -> None:
        self._index = _packed_index_class()
        self._writer = writer
        self._stats: Any = getattr(writer, "_Writer__statistics", None)
        self._chunk: Any = getattr(writer, "_Writer__chunk_builder", None)
        self._chunk_size: Any = getattr(writer, "_Writer__chunk_size", None)
        self._finalize: Any = getattr(writer, "_Writer__maybe_finalize_chunk", None)
        self.fast = (
            self._chunk is not None
            and self._finalize is not None
            and isinstance(self._chunk_size, int)
            and all(hasattr(self._stats, a) for a in ("channel_message_counts", "message_count"))
            and all(hasattr(self._chunk, a) for a in ("record_writer", "message_indices", "num_messages"))
            and hasattr(self._chunk.record_writer, "_buffer")
        )
        if not self.fast:
            self.add = self._slow  # type: ignore[method-assign]

    def _slow(self, channel_id: int, log_time: int, data: bytes, publish_time: int) -> None:
        self._writer.add_message(channel_id, log_time=log_time, data=data, publish_time=publish_time)

    def add(self, channel_id: int, log_time: int, data: bytes, publish_time: int) -> None:
        stats = self._stats
        if stats.message_count == 0 or log_time < stats.message_start_time:
            stats.message_start_time = log_time
        if log_time > stats.message_end_time:
            stats.message_end_time = log_time
        stats.channel_message_counts[channel_id] += 1
        stats.message_count += 1
        chunk = self._chunk
        if chunk.num_messages == 0 or log_time < chunk.message_start_time:
            chunk.message_start_time = log_time
        if log_time > chunk.message_end_time:
            chunk.message_end_time = log_time
        index = chunk.message_indices.get(channel_id)
        if index is None:
            index = chunk.message_indices[channel_id] = self._index(channel_id=channel_id, records=[])
        buffer = chunk.record_writer._buffer  # (a new one after every chunk)
        offset = buffer.tell()
        index.records.append((log_time, offset))
        chunk.num_messages += 1
        buffer.write(_MESSAGE_HEAD.pack(_MESSAGE_OPCODE, 22 + len(data), channel_id, 0, log_time, publish_time))
        buffer.write(data)
        if offset + 31 + len(data) > self._chunk_size:
            self._finalize()


class Recorder:
    """Records what ``links`` deliver into ``out`` (an MCAP file). ``start()``, then ``stop()``."""

    def __init__(
        self,
        out: Path | str,
        links: Sequence[Link],
        clock: Clock | None = None,
        *,
        chunk_size: int = CHUNK_SIZE,
        chunk_age_s: float = CHUNK_AGE_S,
        compression: str = "zstd",
        fetch_maps: bool = True,
    ) -> None:
        self.out = Path(out)
        self.links = list(links)
        self.clock: Clock = clock or SystemClock()
        self.chunk_size = chunk_size
        self.chunk_age_s = chunk_age_s
        self.compression = compression
        self.core = RecordingCore()
        self.dropped = 0
        self.written = 0
        self._inbox: deque[_Heard] = deque()
        self._inbox_lock = threading.Lock()
        self._file: io.BufferedWriter | None = None
        self._writer: Any = None
        self._append: MessageAppender | None = None
        self._ids: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._chunk_started: float | None = None
        self._to_fetch: set[tuple[str, str]] = set()
        """(robot, ``map`` or ``dose``) snapshots the core wants (``RecordingCore.wanted_snapshots``)."""
        self._fetch_lock = threading.Lock()
        self._pulls: list[tuple[str, Any]] = []
        """(link, ``PullSubscription``): Zenoh's samples, taken in batches by the writer."""
        self._writing = Worker("recorder-writer", clock=self.clock, target=self._write_loop)
        self._fetching = Worker("recorder-maps", clock=self.clock, target=self._fetch_loop) if fetch_maps else None
        self._started = False
        self._started_wall = 0.0

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> Recorder:
        from mcap.writer import CompressionType, Writer

        self._file = self.out.open("wb")
        self._writer = Writer(
            self._file,
            chunk_size=self.chunk_size,
            compression=CompressionType.ZSTD if self.compression == "zstd" else CompressionType.LZ4,
            # The data section's CRC in Data End: without it a chunk whose opcode byte is damaged
            # is an "unknown record" a reader skips without a word (its messages silently gone).
            enable_data_crcs=True,
        )
        self._writer.start(profile=PROFILE, library="fleetlink recorder")
        self._append = MessageAppender(self._writer)
        self._started_wall = self.clock.wall()
        self._file.flush()  # the header: the file is an MCAP file from now on
        wall = self.clock.wall
        for link in self.links:
            name = link.name.value
            pull = getattr(link, "subscribe_pull", None)
            if pull is not None:  # Zenoh: no Python per sample on its thread, taken in batches
                self._pulls += [(name, pull(keys.ZENOH_ALL)), (name, pull(UWB_STATUS))]
            else:

                def receive(key: str, payload: bytes, name: str = name) -> None:
                    self._put((False, name, key, payload, wall()))

                link.subscribe(keys.ZENOH_ALL, receive)
                link.subscribe(UWB_STATUS, receive)
            watch = getattr(link, "watch_liveliness", None)
            if watch is not None:

                def token(key: str, alive: bool, name: str = name) -> None:
                    self._put((True, name, key, alive, wall()))

                watch(ALIVE_TOKENS, token)
        self._writing.start()
        if self._fetching is not None:
            self._fetching.start()
        for link in self.links:
            link.start()
        self._started = True
        return self

    def stop(self) -> None:
        """Close the links, write what is queued, close the file with its summary. Idempotent."""
        if not self._started:
            return
        self._started = False
        self._writing.stop()
        self._pull()  # what zenoh holds for us, before its subscribers go with the session
        for link in self.links:
            try:
                link.close()
            except Exception as exc:  # the file must be closed whatever a transport does
                log.warning("closing %s: %s", link.name.value, exc)
        if self._fetching is not None:
            self._fetching.stop()
        self._drain()
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.add_metadata(
                "fleetlink.recording",
                {
                    "robots": json.dumps(sorted(self.core.robots)),
                    "rejected": json.dumps(dict(self.core.rejected.most_common(64))),
                    "dropped": str(self.dropped),
                    "started": repr(self._started_wall),
                    "stopped": repr(self.clock.wall()),
                },
            )
            writer.finish()  # (does not flush: closing the file does)
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> Recorder:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- the links' side ------------------------------------------------------------------------

    def _put(self, heard: _Heard) -> None:
        with self._inbox_lock:
            if len(self._inbox) >= INBOX_SIZE:
                self.dropped += 1
                return
            self._inbox.append(heard)
        # No wake-up per message: the writer looks every few milliseconds (one wake per burst).

    def _pull(self) -> None:
        """Take the Zenoh samples waiting (stamped by zenoh when they arrived: a sample without a
        stamp gets the time it is taken) into the writer's inbox."""
        got: list[tuple[str, bytes, float | None]] = []
        batch: list[_Heard] = []
        for name, pull in self._pulls:
            got.clear()
            if not pull.drain(got):
                continue
            now = self.clock.wall()
            batch += [(False, name, key, payload, now if stamp is None else stamp) for key, payload, stamp in got]
        if batch:
            with self._inbox_lock:
                room = INBOX_SIZE - len(self._inbox)
                if len(batch) > room:
                    self.dropped += len(batch) - max(0, room)
                    batch = batch[: max(0, room)]
                self._inbox.extend(batch)

    # -- the writer -----------------------------------------------------------------------------

    def _write_loop(self, worker: Worker) -> None:
        while not worker.stopping:
            worker.wait(BATCH_PERIOD_S)
            self._pull()
            self._drain()

    def _drain(self) -> None:
        with self._inbox_lock:
            batch, self._inbox = self._inbox, deque()
        writer = self._writer
        if writer is None:
            return
        core = self.core
        ids = self._ids
        assert self._append is not None
        add = self._append.add
        written = 0
        for alive, link, key, payload, wall in batch:
            if alive:
                records = core.alive(link, key, bool(payload), wall)
            else:
                assert isinstance(payload, bytes)
                records = core.receive(link, key, payload, wall)
            for channel, data, log_time, publish_time in records:
                cid = ids.get(channel.topic)
                if cid is None:
                    cid = self._channel_id(channel)
                add(cid, log_time, data, publish_time)
            written += len(records)
        self.written += written
        if core.new_reasons:
            reasons, core.new_reasons = core.new_reasons, []
            for reason in reasons:  # once per reason; the count goes on in core.rejected
                log.warning("recorder: refused an input (%s); further ones are counted", reason)
        now = self.clock.now()
        if batch and self._chunk_started is None:
            self._chunk_started = now
        if self._chunk_started is not None and now - self._chunk_started >= self.chunk_age_s:
            writer.flush()  # closes the chunk being filled, and flushes the file
            self._chunk_started = None
        elif batch and self._file is not None:
            self._file.flush()  # a chunk the writer closed for its size: in the OS now, not in our buffer
        wanted = core.wanted_snapshots()
        if wanted and self._fetching is not None:
            with self._fetch_lock:
                self._to_fetch.update(wanted)
            self._fetching.wake()

    def _channel_id(self, channel: Channel) -> int:
        found = self._ids.get(channel.topic)
        if found is not None:
            return found
        schema_id = self._schemas.get(channel.schema_name)
        if schema_id is None:
            schema_id = self._schemas[channel.schema_name] = self._writer.register_schema(
                name=channel.schema_name, encoding="jsonschema", data=channel.schema
            )
        cid: int = self._writer.register_channel(
            topic=channel.topic, message_encoding="json", schema_id=schema_id, metadata=channel.metadata()
        )
        self._ids[channel.topic] = cid
        return cid

    # -- map and dose snapshots -----------------------------------------------------------------

    def _fetch_loop(self, worker: Worker) -> None:
        while not worker.stopping:
            worker.wait(1.0)
            with self._fetch_lock:
                wanted, self._to_fetch = sorted(self._to_fetch), set()

            def deliver(link: str, key: str, payload: bytes) -> None:
                self._put((False, link, key, payload, self.clock.wall()))

            fetch_snapshots(self.links, wanted, deliver, lambda: worker.stopping)


# --------------------------------------------------------------------------------------------------
# Reading


@dataclass(frozen=True, slots=True)
class StoredMessage:
    topic: str
    schema_name: str
    metadata: dict[str, str]
    log_time_ns: int
    publish_time_ns: int
    data: bytes


class RecordingReader:
    """Every message of an MCAP file in file order, whether it was closed properly or not.

    ``messages()`` stops at a truncated or damaged tail (``complete`` is then False and ``problem``
    says what was wrong); a file that is not MCAP at all raises ``RecordingError``.
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.complete = False
        self.problem: str | None = None
        self.metadata: dict[str, dict[str, str]] = {}
        self.channels: dict[int, tuple[str, str, dict[str, str]]] = {}

    def messages(self) -> Iterator[StoredMessage]:
        from mcap.records import Channel as McapChannel
        from mcap.records import Footer, Metadata, Schema
        from mcap.records import Message as McapMessage
        from mcap.stream_reader import StreamReader

        try:
            handle = self.path.open("rb")
        except OSError as exc:
            raise RecordingError(f"cannot open {self.path}: {exc.strerror or exc}") from None
        schemas: dict[int, str] = {}
        seen = 0
        with handle:
            records = StreamReader(handle, validate_crcs=True, record_size_limit=1 << 30).records
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    break
                except Exception as exc:  # McapError, struct.error, EOF, a compressor's own error: damage
                    if seen == 0 and _bad_magic(exc):
                        raise RecordingError(f"{self.path} is not an MCAP file ({exc})") from None
                    self.problem = _describe(exc)
                    return
                seen += 1
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, McapChannel):
                    self.channels[record.id] = (record.topic, schemas.get(record.schema_id, "?"), dict(record.metadata))
                elif isinstance(record, McapMessage):
                    topic, schema, meta = self.channels.get(record.channel_id, ("?", "?", {}))
                    yield StoredMessage(topic, schema, meta, record.log_time, record.publish_time, record.data)
                elif isinstance(record, Metadata):
                    self.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Footer):
                    self.complete = True
        if not self.complete and self.problem is None:
            self.problem = "the file ends before its footer"


FLEET_KINDS = frozenset({"wire", "uwb-status", "alive"})
"""The channels a replay plays (``Channel.kind``): what the console heard; not the Foxglove ones."""
REORDER_S = 2.0
"""A recovered file (no index) is read in file order; its messages are put in time order within
this window (the recorder writes a batch every 250 ms, the links' messages interleaved)."""


class _CountingFile:
    """A file that counts the bytes read from it (what a reader actually read, for tests and notes).
    Not an ``io.RawIOBase``: the mcap library would wrap that in a read-ahead buffer."""

    def __init__(self, path: Path) -> None:
        self._f = path.open("rb")
        self.bytes_read = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def read(self, size: int | None = -1) -> bytes:
        data = self._f.read(size)
        self.bytes_read += len(data)
        return data

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def close(self) -> None:
        self._f.close()


class FleetStream:
    """The fleet messages of a recording (``FLEET_KINDS``), in receive-time order, read as they are
    wanted: a replay never holds the recording.

    A file closed properly is read through its index (the ``mcap`` library's seeking reader: the
    summary first, then each chunk when the replay reaches its time, one chunk at a time). A
    recovered file (no summary) is read in file order with ``RecordingReader``, once through to
    learn its time span, then again as it plays, sorted within ``REORDER_S``. ``bytes_read`` says
    how much of the file has been read."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        try:
            self._file = _CountingFile(self.path)
        except OSError as exc:
            raise RecordingError(f"cannot open {self.path}: {exc.strerror or exc}") from None
        self._scanned = 0
        self.metadata: dict[str, dict[str, str]] = {}
        self.complete = False
        self.problem: str | None = None
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self.count = 0
        """Fleet messages in the file (a recovered file: up to its damage)."""
        self.indexed = False
        """Read through its index (a file closed properly); False: in file order (recovered)."""
        self._reader: Any = None
        self._topics: list[str] = []
        try:
            if not self._open_indexed():
                self._scan()
        except BaseException:
            self._file.close()
            raise

    @property
    def bytes_read(self) -> int:
        return self._file.bytes_read + self._scanned

    def close(self) -> None:
        self._file.close()

    def _open_indexed(self) -> bool:
        from mcap.reader import SeekingReader

        try:
            reader = SeekingReader(self._file, validate_crcs=True)  # type: ignore[arg-type]
            summary = reader.get_summary()
        except Exception:  # not MCAP, truncated, no footer: read it as a recovered file
            return False
        if summary is None or not summary.chunk_indexes or summary.statistics is None:
            return False
        fleet = {cid for cid, ch in summary.channels.items() if (ch.metadata or {}).get("kind") in FLEET_KINDS}
        self._topics = sorted({summary.channels[cid].topic for cid in fleet})
        counts = summary.statistics.channel_message_counts
        self.count = sum(counts.get(cid, 0) for cid in fleet)
        times = [
            (c.message_start_time, c.message_end_time)
            for c in summary.chunk_indexes
            if fleet & set(c.message_index_offsets)
        ]
        if times:
            self.first_ns = min(t[0] for t in times)
            self.last_ns = max(t[1] for t in times)
        try:
            for record in reader.iter_metadata():
                self.metadata[record.name] = dict(record.metadata)
        except Exception as exc:  # a damaged metadata record: play without it
            log.debug("metadata of %s: %s", self.path, exc)
        self._reader = reader
        self.complete = self.indexed = True
        return True

    def _scan(self) -> None:
        reader = RecordingReader(self.path)
        for m in reader.messages():  # one pass, nothing kept: the span and the count
            if m.metadata.get("kind") in FLEET_KINDS:
                self.count += 1
                t = m.log_time_ns
                self.first_ns = t if self.first_ns is None else min(self.first_ns, t)
                self.last_ns = t if self.last_ns is None else max(self.last_ns, t)
        self._scanned = self.path.stat().st_size
        self.metadata = reader.metadata
        self.complete = reader.complete
        self.problem = reader.problem

    def messages(self) -> Generator[StoredMessage, None, None]:
        """The fleet messages in receive-time order (file order among equal times). A file damaged
        where the index said it was not: stops there, ``problem`` says why."""
        if self._reader is None:
            yield from self._recovered()
            return
        try:
            for schema, channel, message in self._reader.iter_messages(topics=self._topics, log_time_order=True):
                yield StoredMessage(
                    channel.topic,
                    schema.name if schema is not None else "?",
                    dict(channel.metadata),
                    message.log_time,
                    message.publish_time,
                    message.data,
                )
        except Exception as exc:  # a chunk that does not read back (its CRC, a compressor's error)
            self.problem = _describe(exc)

    def _recovered(self) -> Generator[StoredMessage, None, None]:
        import heapq

        reader = RecordingReader(self.path)
        window = round(REORDER_S * 1e9)
        heap: list[tuple[int, int, StoredMessage]] = []
        n = 0
        for m in reader.messages():
            if m.metadata.get("kind") not in FLEET_KINDS:
                continue
            heapq.heappush(heap, (m.log_time_ns, n, m))
            n += 1
            while heap and heap[0][0] <= m.log_time_ns - window:
                yield heapq.heappop(heap)[2]
        self._scanned += self.path.stat().st_size
        while heap:
            yield heapq.heappop(heap)[2]


def _bad_magic(exc: Exception) -> bool:
    return "magic" in type(exc).__name__.lower() or "magic" in str(exc).lower()


def _describe(exc: Exception) -> str:
    from mcap.records import DataEnd
    from mcap.stream_reader import CRCValidationError

    if isinstance(exc, CRCValidationError) and isinstance(exc.record, DataEnd):
        # Found at the data section's end: the damage is somewhere before it, where nothing else
        # noticed (a chunk whose opcode is damaged is skipped as an unknown record).
        return "damaged: the data section's CRC does not match, so messages read from it may be missing or wrong"
    text = str(exc) or type(exc).__name__
    return f"damaged or truncated after this point ({type(exc).__name__}: {text[:120]})"


def summarise(path: Path | str, *, index: bool = True) -> RecordingSummary:
    """What ``fleetlink record --summary`` prints. A file closed properly is summarised from its
    summary section (``_summarise_indexed``: statistics, channels, the recorder's metadata; no
    chunk is read, so a recording of hours answers at once); a file without a usable one (cut short
    by a crash) or with ``index=False`` is read message by message up to its end or its damage (and
    every chunk's CRC checked), with a note saying why. Raises ``RecordingError`` for a file that
    is not MCAP."""
    why: str | None = None
    if index:
        found = _summarise_indexed(Path(path))
        if isinstance(found, RecordingSummary):
            return found
        why = found
    return _summarise_scan(path, why)


def _summarise_indexed(path: Path) -> RecordingSummary | str:
    """The summary from ``path``'s summary section, or why it cannot be (then the file is read
    message by message)."""
    from mcap.reader import SeekingReader

    try:
        f = _CountingFile(path)
    except OSError as exc:
        raise RecordingError(f"cannot open {path}: {exc.strerror or exc}") from None
    try:
        try:
            reader = SeekingReader(f, validate_crcs=True)  # type: ignore[arg-type]
            summary = reader.get_summary()
        except Exception:  # no footer at the end: not closed (or not MCAP: the scan says so)
            return "no summary section (the file was not closed: cut short by a crash?)"
        if summary is None:
            return "its footer says it has no summary section"
        stats = summary.statistics
        if stats is None:
            return "its summary section has no statistics"
        problem = _summary_crc_problem(f, path)
        if problem is not None:
            return problem
        try:
            meta = next((dict(m.metadata) for m in reader.iter_metadata() if m.name == "fleetlink.recording"), None)
            robots = None if meta is None else json.loads(meta.get("robots", "null"))
        except Exception as exc:  # a damaged metadata record: the messages say which robots
            return f"its fleetlink.recording metadata does not read back ({type(exc).__name__})"
        if not (isinstance(robots, list) and all(isinstance(r, str) for r in robots)):
            return "it has no fleetlink.recording metadata with the robots"
        counts: Counter[str] = Counter()
        schemas: dict[str, str] = {}
        for cid, n in stats.channel_message_counts.items():
            channel = summary.channels.get(cid)
            if channel is None:
                return f"its statistics count channel {cid}, which its summary does not have"
            counts[channel.topic] += n
            schema = summary.schemas.get(channel.schema_id)
            schemas[channel.topic] = schema.name if schema is not None else "?"
        span = (stats.message_start_time, stats.message_end_time) if stats.message_count else None
        notes = []
        if meta is not None and meta.get("dropped", "0") != "0":
            notes.append(f"note: the recorder dropped {meta['dropped']} messages (its disk could not keep up)")
        return RecordingSummary.build(
            counts, schemas, span, robots, complete=True, notes=notes, from_index=True, bytes_read=f.bytes_read
        )
    finally:
        f.close()


_FOOTER_CRC_OFFSET = 8 + 4
"""From the end of an MCAP file: its closing magic (8 bytes), then the footer's summary CRC (4),
which covers everything from the summary section's start up to it."""


def _summary_crc_problem(f: _CountingFile, path: Path) -> str | None:
    """None if ``path``'s summary section matches the CRC in its footer (or it has none)."""
    import zlib

    from mcap.reader import FOOTER_SIZE
    from mcap.stream_reader import MAGIC_SIZE

    size = path.stat().st_size
    f.seek(size - MAGIC_SIZE - FOOTER_SIZE)
    footer = f.read(FOOTER_SIZE)
    summary_start, crc = struct.unpack_from("<Q", footer, 9)[0], struct.unpack_from("<I", footer, FOOTER_SIZE - 4)[0]
    if crc == 0:  # the writer did not compute one
        return None
    f.seek(summary_start)
    covered = f.read(size - _FOOTER_CRC_OFFSET - summary_start)
    if zlib.crc32(covered) != crc:
        return "its summary section does not match the CRC in its footer"
    return None


def _summarise_scan(path: Path | str, why: str | None) -> RecordingSummary:
    reader = RecordingReader(path)
    counts: Counter[str] = Counter()
    schemas: dict[str, str] = {}
    robots: set[str] = set()
    lo: int | None = None
    hi: int | None = None
    for m in reader.messages():
        counts[m.topic] += 1
        schemas[m.topic] = m.schema_name
        lo = m.log_time_ns if lo is None else min(lo, m.log_time_ns)
        hi = m.log_time_ns if hi is None else max(hi, m.log_time_ns)
        if m.metadata.get("kind") in ("wire", "alive"):
            robot = _robot_of(m.data)
            if robot is not None and robot != keys.FLEET_MAP:
                robots.add(robot)
    meta = reader.metadata.get("fleetlink.recording")
    notes: list[str] = []
    if why is not None:
        notes.append(f"note: {why}: read message by message")
    if reader.problem is not None:
        notes.append(f"note: {reader.problem}; everything before it is listed")
    if meta is not None and meta.get("dropped", "0") != "0":
        notes.append(f"note: the recorder dropped {meta['dropped']} messages (its disk could not keep up)")
    if not counts and reader.problem is not None and not reader.channels:
        raise RecordingError(
            f"{path}: no message in it ({reader.problem}): a recorder stopped before its first chunk was written?"
        )
    span = None if lo is None or hi is None else (lo, hi)
    size = Path(path).stat().st_size
    return RecordingSummary.build(counts, schemas, span, robots, complete=reader.complete, notes=notes, bytes_read=size)


def _robot_of(data: bytes) -> str | None:
    """The first ``"robot"`` of a record's JSON (a wire message's header comes first): found without
    parsing the whole message, which a long recording would pay for millions of times."""
    at = data.find(b'"robot":"')
    if at < 0:
        return None
    start = at + 9
    end = data.find(b'"', start)
    return data[start:end].decode("utf-8", "replace") if end > start else None
