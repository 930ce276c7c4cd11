"""An MCAP file checked record by record against the MCAP specification (mcap.dev/spec), as the
``mcap doctor`` command of the official CLI checks one: what the Python library's readers take on
trust (a message index entry, a chunk index's offsets, the statistics, the data section's CRC).

``doctor(path)`` returns the problems found (an empty list: none). It reads the whole file
(a test's recording: a few MB at most). Warnings the CLI only prints (messages out of log-time
order across channels) are not problems here: the recorder writes each batch's two links one
after the other (docs/recording.md).

Checks:

* the magic at both ends; every record's opcode and length; a Header first (with its library
  named), a DataEnd and a Footer last; the DataEnd's CRC of the data section;
* schemas: id not 0, the same id never with other contents; channels: their schema known, the same
  id never with other contents;
* every chunk: its compression known, its records decompressed to ``uncompressed_size`` with
  ``uncompressed_crc``; inside only schemas, channels and messages, each message on a channel
  defined before it; its message start and end times the earliest and latest message's; the message
  indexes after it: one per channel, an entry (log time, offset) for every message and none for
  anything else;
* the summary: a chunk index for every chunk (offset, length, times, compression, sizes, its
  message index offsets and their total length); every channel (and its schema) a chunk uses
  repeated in the summary; the statistics (message, schema, channel, chunk and metadata counts,
  messages per channel, the time span); the metadata index (offset, length, name of each
  metadata record); the summary offsets (each group's start and length; an empty group's length 0); the footer's
  summary start, summary offset start and summary CRC.
"""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
_READERS: dict[int, Any] = {
    Opcode.HEADER: Header.read,
    Opcode.FOOTER: Footer.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read,
    Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.STATISTICS: Statistics.read,
    Opcode.METADATA: Metadata.read,
    Opcode.METADATA_INDEX: MetadataIndex.read,
    Opcode.SUMMARY_OFFSET: SummaryOffset.read,
    Opcode.DATA_END: DataEnd.read,
}


def _lex(data: bytes, start: int, end: int) -> list[tuple[int, int, int, Any]]:
    """(offset, opcode, record length incl. its 9-byte head, parsed record or None) from ``start``
    to ``end``; raises ValueError where a record does not fit."""
    out = []
    pos = start
    while pos < end:
        if pos + 9 > end:
            raise ValueError(f"a record head cut short at offset {pos}")
        opcode, length = struct.unpack_from("<BQ", data, pos)
        if pos + 9 + length > end:
            raise ValueError(f"record 0x{opcode:02x} at offset {pos} runs past the end ({length} bytes)")
        body = data[pos + 9 : pos + 9 + length]
        if opcode == Opcode.MESSAGE:
            record: Any = Message.read(ReadDataStream(io.BytesIO(body)), length)
        else:
            reader = _READERS.get(opcode)
            record = reader(ReadDataStream(io.BytesIO(body))) if reader is not None else None
        out.append((pos, opcode, 9 + length, record))
        pos += 9 + length
    return out


def _decompress(chunk: Chunk) -> bytes:
    if chunk.compression == "":
        return bytes(chunk.data)
    if chunk.compression == "zstd":
        import zstandard

        return bytes(zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size))
    if chunk.compression == "lz4":
        import lz4.frame

        return bytes(lz4.frame.decompress(chunk.data))
    raise ValueError(f"unknown compression {chunk.compression!r}")


def doctor(path: Path | str) -> list[str]:
    """The problems of the MCAP file at ``path`` (see the module's docstring); [] when none."""
    data = Path(path).read_bytes()
    problems: list[str] = []
    if not (data.startswith(MAGIC) and data.endswith(MAGIC) and len(data) >= 2 * len(MAGIC) + 9):
        return ["no MCAP magic at both ends (not a file closed properly)"]
    try:
        records = _lex(data, len(MAGIC), len(data) - len(MAGIC))
    except ValueError as exc:
        return [str(exc)]
    if not records or records[0][1] != Opcode.HEADER:
        problems.append("the first record is not a Header")
    elif not records[0][3].library:
        problems.append("the Header names no library")
    if records[-1][1] != Opcode.FOOTER:
        return [*problems, "the last record is not a Footer"]
    ends = [i for i, r in enumerate(records) if r[1] == Opcode.DATA_END]
    if len(ends) != 1:
        return [*problems, f"{len(ends)} DataEnd records (one expected)"]
    data_end = ends[0]
    end_offset = records[data_end][0]
    crc = records[data_end][3].data_section_crc
    if crc and crc != zlib.crc32(data[:end_offset]):
        problems.append("the DataEnd's data section CRC does not match the data section")

    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}

    def define(record: Any, where: str, summary: bool) -> None:
        known = schemas if isinstance(record, Schema) else channels
        kind = type(record).__name__
        if isinstance(record, Schema) and record.id == 0:
            problems.append(f"{where}: schema id 0 is reserved")
        if isinstance(record, Channel) and record.schema_id != 0 and record.schema_id not in schemas:
            problems.append(f"{where}: channel {record.id} names unknown schema {record.schema_id}")
        previous = known.get(record.id)
        if previous is not None and previous != record:
            problems.append(f"{where}: two different {kind} records with id {record.id}")
        if summary and previous is None:
            problems.append(f"{where}: {kind} {record.id} in the summary was never in the data section")
        if not summary:
            known[record.id] = record  # type: ignore[index]

    chunks: dict[int, tuple[Chunk, int, dict[int, tuple[int, int]]]] = {}
    """chunk offset -> (chunk, record length, channel -> (message index offset, its record length))"""
    used: dict[int, set[int]] = {}
    counts: dict[int, int] = {}
    times: list[int] = []
    metadata: dict[int, tuple[int, str]] = {}
    i = 0
    while i < data_end:
        offset, opcode, length, record = records[i]
        where = f"offset {offset}"
        if opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            define(record, where, summary=False)
        elif opcode == Opcode.MESSAGE:
            problems.append(f"{where}: a message outside any chunk")
        elif opcode == Opcode.METADATA:
            metadata[offset] = (length, record.name)
        elif opcode == Opcode.CHUNK:
            chunk: Chunk = record
            indexes: dict[int, tuple[int, int]] = {}
            entries: dict[int, list[tuple[int, int]]] = {}
            j = i + 1
            while j < data_end and records[j][1] == Opcode.MESSAGE_INDEX:
                mi: MessageIndex = records[j][3]
                if mi.channel_id in indexes:
                    problems.append(f"{where}: two message indexes for channel {mi.channel_id}")
                indexes[mi.channel_id] = (records[j][0], records[j][2])
                entries[mi.channel_id] = sorted((t, o) for t, o in mi.records)
                j += 1
            chunks[offset] = (chunk, length, indexes)
            try:
                inner = _decompress(chunk)
            except Exception as exc:
                problems.append(f"{where}: chunk does not decompress: {exc}")
                i = j
                continue
            if len(inner) != chunk.uncompressed_size:
                problems.append(
                    f"{where}: chunk is {len(inner)} bytes, its uncompressed_size {chunk.uncompressed_size}"
                )
            if chunk.uncompressed_crc and zlib.crc32(inner) != chunk.uncompressed_crc:
                problems.append(f"{where}: chunk CRC does not match")
            try:
                content = _lex(inner, 0, len(inner))
            except ValueError as exc:
                problems.append(f"{where}: inside the chunk: {exc}")
                content = []
            found: dict[int, list[tuple[int, int]]] = {}
            chunk_times = []
            for at, op, _n, rec in content:
                if op in (Opcode.SCHEMA, Opcode.CHANNEL):
                    define(rec, f"{where}+{at}", summary=False)
                elif op == Opcode.MESSAGE:
                    if rec.channel_id not in channels:
                        problems.append(f"{where}+{at}: a message on channel {rec.channel_id} before its Channel")
                    found.setdefault(rec.channel_id, []).append((rec.log_time, at))
                    chunk_times.append(rec.log_time)
                    counts[rec.channel_id] = counts.get(rec.channel_id, 0) + 1
                else:
                    problems.append(f"{where}+{at}: record 0x{op:02x} may not be in a chunk")
            if chunk_times and (min(chunk_times), max(chunk_times)) != (
                chunk.message_start_time,
                chunk.message_end_time,
            ):
                problems.append(f"{where}: chunk start/end time is not its messages' earliest/latest log time")
            times += chunk_times
            used[offset] = set(found)
            if {c: sorted(v) for c, v in found.items()} != entries:
                problems.append(f"{where}: the message indexes after the chunk do not list exactly its messages")
            i = j
            continue
        elif opcode != Opcode.HEADER:
            problems.append(f"{where}: record 0x{opcode:02x} in the data section")
        i += 1

    # The summary section.
    footer: Footer = records[-1][3]
    summary = records[data_end + 1 : -1]
    summary_start = summary[0][0] if summary else 0
    if footer.summary_start != summary_start:
        problems.append(f"the footer's summary_start {footer.summary_start} is not {summary_start}")
    offsets = [r for r in summary if r[1] == Opcode.SUMMARY_OFFSET]
    offsets_start = offsets[0][0] if offsets else 0
    if footer.summary_offset_start != offsets_start:
        problems.append(f"the footer's summary_offset_start {footer.summary_offset_start} is not {offsets_start}")
    summary_bytes = data[summary_start : records[-1][0] + 9 + 8 + 8]  # up to the footer's summary_crc
    if footer.summary_crc and summary and footer.summary_crc != zlib.crc32(summary_bytes):
        problems.append("the footer's summary CRC does not match the summary section")
    groups: dict[int, list[tuple[int, int, int, Any]]] = {}
    for r in summary:
        if r[1] != Opcode.SUMMARY_OFFSET:
            groups.setdefault(r[1], []).append(r)
    for _o, _op, _n, so in offsets:
        group = groups.get(so.group_opcode, [])
        if (
            (so.group_length != 0)
            if not group
            else (so.group_start, so.group_length) != (group[0][0], sum(g[2] for g in group))
        ):
            problems.append(f"the summary offset of group 0x{so.group_opcode:02x} does not match that group")
    for _o, op, _n, rec in summary:
        if op in (Opcode.SCHEMA, Opcode.CHANNEL):
            define(rec, "summary", summary=True)
    summary_channels = {rec.id for _o, op, _n, rec in summary if op == Opcode.CHANNEL}
    summary_schemas = {rec.id for _o, op, _n, rec in summary if op == Opcode.SCHEMA}
    for at, ids in used.items():
        for cid in ids - summary_channels:
            problems.append(f"chunk at {at} uses channel {cid}, which the summary does not repeat")
        for cid in ids & summary_channels:
            sid = channels[cid].schema_id
            if sid and sid not in summary_schemas:
                problems.append(f"chunk at {at} uses schema {sid}, which the summary does not repeat")
    indexed = {rec.chunk_start_offset: rec for _o, op, _n, rec in summary if op == Opcode.CHUNK_INDEX}
    if set(indexed) != set(chunks):
        problems.append(f"chunk indexes for {sorted(indexed)}, chunks at {sorted(chunks)}")
    for at, ci in indexed.items():
        if at not in chunks:
            continue
        chunk, length, indexes = chunks[at]
        seen = (
            ci.chunk_length, ci.message_start_time, ci.message_end_time, ci.compression,
            ci.compressed_size, ci.uncompressed_size,
        )  # fmt: skip
        want = (
            length, chunk.message_start_time, chunk.message_end_time, chunk.compression,
            len(chunk.data), chunk.uncompressed_size,
        )  # fmt: skip
        if seen != want:
            problems.append(f"the chunk index of the chunk at {at} says {seen}, the chunk {want}")
        if dict(ci.message_index_offsets) != {c: o for c, (o, _n) in indexes.items()}:
            problems.append(f"the chunk index of the chunk at {at}: message index offsets do not match")
        if ci.message_index_length != sum(n for _o, n in indexes.values()):
            problems.append(f"the chunk index of the chunk at {at}: message_index_length does not match")
    meta_index = {rec.offset: (rec.length, rec.name) for _o, op, _n, rec in summary if op == Opcode.METADATA_INDEX}
    if meta_index != metadata:
        problems.append(f"the metadata index {meta_index} does not match the metadata records {metadata}")
    stats = [rec for _o, op, _n, rec in summary if op == Opcode.STATISTICS]
    if len(stats) != 1:
        problems.append(f"{len(stats)} Statistics records in the summary (one expected)")
    else:
        st: Statistics = stats[0]
        want_stats = (
            sum(counts.values()), len(schemas), len(channels), len(chunks), len(metadata),
            {c: n for c, n in counts.items() if n},
        )  # fmt: skip
        seen_stats = (
            st.message_count, st.schema_count, st.channel_count, st.chunk_count, st.metadata_count,
            {c: n for c, n in st.channel_message_counts.items() if n},
        )  # fmt: skip
        if seen_stats != want_stats:
            problems.append(f"the statistics say {seen_stats}, the file holds {want_stats}")
        if times and (st.message_start_time, st.message_end_time) != (min(times), max(times)):
            problems.append("the statistics' time span is not the messages' earliest and latest log time")
    return problems
