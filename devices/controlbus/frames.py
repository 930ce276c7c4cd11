"""Framing of SLAMTEC's Inter-chip protocol (the Control Bus profile's transport). No I/O.

A frame is ``Flag | Length | Code | Payload | Checksum``:

* Flag ``0x10`` (standard: 1 length byte) or ``0x50`` (long: 2 length bytes, little-endian);
* Length = 1 + len(Payload) (the code byte counts);
* Code is the request CMD or the response code;
* Checksum = XOR of every byte from Flag through the last payload byte, so a whole frame XORs to 0.

``FrameDecoder`` takes bytes in any split and yields ``Frame`` values. It never raises: garbage,
a truncated frame, a bad checksum or an impossible length make it drop the false start's first
byte, count why, and resynchronise on the next flag byte. Its buffer never holds more than the
board's 512 bytes.
"""

from __future__ import annotations

import itertools
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import reduce
from operator import xor
from typing import NamedTuple

import numpy as np

__all__ = [
    "BOARD_BUFFER",
    "FLAG_LONG",
    "FLAG_STANDARD",
    "MAX_STANDARD_PAYLOAD",
    "Dropped",
    "Frame",
    "FrameDecoder",
    "FrameStats",
    "checksum",
    "encode_frame",
]

FLAG_STANDARD = 0x10
FLAG_LONG = 0x50
BOARD_BUFFER = 512  # the reference board's receive buffer, and our decoder's cap
MAX_STANDARD_PAYLOAD = 254  # Length is one byte and counts the code byte too


def checksum(data: bytes | bytearray | memoryview) -> int:
    """XOR of all bytes (the Inter-chip checksum); a whole valid frame gives 0."""
    return reduce(xor, data, 0)


class Frame(NamedTuple):
    """One frame: ``code`` is the request CMD or the response code.

    A NamedTuple rather than a frozen dataclass: the decoder makes hundreds of thousands a
    second, and tuple construction is several times cheaper (the decoder goes further and
    builds them with the C-level ``tuple.__new__``, skipping this class's Python ``__new__``).
    """

    code: int
    payload: bytes = b""
    long: bool = False

    def encode(self) -> bytes:
        return encode_frame(self.code, self.payload, long=self.long)


def encode_frame(code: int, payload: bytes = b"", *, long: bool = False) -> bytes:
    """Bytes of one frame. A payload too large for a standard frame forces a long one."""
    if not 0 <= code <= 0xFF:
        raise ValueError(f"frame code {code} is not a byte")
    length = 1 + len(payload)
    if long or length > MAX_STANDARD_PAYLOAD + 1:
        if length > 0xFFFF:
            raise ValueError(f"payload of {len(payload)} bytes does not fit a long frame")
        head = bytes((FLAG_LONG, length & 0xFF, length >> 8, code))
    else:
        head = bytes((FLAG_STANDARD, length, code))
    body = head + payload
    return body + bytes((checksum(body),))


class Dropped(NamedTuple):
    """A rejection, reported in stream order when ``FrameDecoder.report_drops`` is set.

    reason: "garbage" (bytes before a flag), "too_long" (longer than the buffer),
    "zero_length", "bad_code", "checksum"; ``size``: bytes skipped.
    """

    reason: str
    size: int


@dataclass(slots=True)
class FrameStats:
    """Why bytes were dropped. ``frames`` counts frames delivered."""

    frames: int = 0
    garbage_bytes: int = 0  # bytes skipped while looking for a flag
    bad_checksum: int = 0
    bad_length: int = 0  # zero length, or a frame larger than the buffer
    bad_code: int = 0  # a code byte that is not valid in this direction
    abandoned: int = 0  # incomplete candidates given up on (``skip_candidate``)

    @property
    def dropped(self) -> int:
        return self.bad_checksum + self.bad_length + self.bad_code + self.abandoned


@dataclass(slots=True)
class FrameDecoder:
    """Sans-I/O frame splitter.

    ``valid_codes`` (optional) is the set of codes legal in this direction: responses for the
    master, requests for the board. A candidate whose code byte is outside it is rejected at
    once, before its length is awaited, which makes false starts in noise both rarer and cheaper.
    ``max_frame`` caps a whole frame (the board's 512-byte buffer by default).
    """

    valid_codes: frozenset[int] | None = None
    max_frame: int = BOARD_BUFFER
    report_drops: bool = False  # also yield a ``Dropped`` marker, in order, for each rejection
    stats: FrameStats = field(default_factory=FrameStats)
    _buf: bytearray = field(default_factory=bytearray)
    _table: bytes = field(default=b"", init=False, repr=False, compare=False)
    _table_for: frozenset[int] | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame | Dropped]:
        """Take bytes in; return the frames they complete (possibly none).

        Whatever stays buffered afterwards is one incomplete candidate, shorter than
        ``max_frame`` by construction, so the buffer never exceeds the board's cap.
        """
        out: list[Frame | Dropped] = []
        if data:
            self._buf += data
            self._scan(out)
        return out

    def skip_candidate(self) -> None:
        """Give up on the incomplete frame at the head of the buffer (e.g. after a timeout).

        A false start that claims a long length would otherwise hold back the real frames
        behind it until enough bytes arrive.
        """
        if self._buf:
            self._drop_candidate("abandoned")

    def frames_from_buffer(self) -> list[Frame | Dropped]:
        """Re-scan what is buffered (after ``skip_candidate``)."""
        out: list[Frame | Dropped] = []
        self._scan(out)
        return out

    def reset(self) -> None:
        self._buf.clear()

    # -- internals ---------------------------------------------------------------------------

    def _drop_candidate(self, reason: str) -> None:
        del self._buf[:1]
        st = self.stats
        setattr(st, reason, getattr(st, reason) + 1)

    def _code_table(self) -> bytes:
        """``table[code]`` is 1 when ``code`` may start a frame: one index instead of a set test."""
        codes = self.valid_codes
        if codes is not self._table_for or not self._table:
            self._table = bytes(1 if codes is None or c in codes else 0 for c in range(256))
            self._table_for = codes
        return self._table

    def _scan(self, out: list[Frame | Dropped]) -> None:
        buf = self._buf
        n = len(buf)
        # Three zero bytes of padding let one struct call read a header at any position; every
        # test below uses n, the real length, so the padding is never part of a frame.
        buf += _PAD
        data = bytes(buf)
        del buf[n:]
        header = _HEADER.unpack_from
        valid = self._code_table()
        cap = self.max_frame
        cap_long = cap - 4  # largest Length of a long frame (3 header bytes and the checksum)
        cap_std = cap - 3
        st = self.stats
        report = self.report_drops
        # Frames are collected as plain tuples and made Frames in one C-level pass at the end
        # (Frame's own __new__ is Python code, several times slower); drop markers, when
        # reported, remember how many frames preceded them.
        found: list[tuple[int, bytes, bool]] = []
        push = found.append
        marks: list[tuple[int, Dropped]] = []
        # Prefix XOR of the buffer, computed once per scan and only when a candidate is
        # complete: the checksum of data[a:b] is then px[a] ^ px[b], O(1) per frame.
        px: bytes | None = None
        pos = 0
        while pos < n:
            # Fast path: a complete, valid frame is delivered at once (one test each for the
            # length, the code, completeness and the checksum); any failure falls through to
            # the exact classification below, which keeps the drop reasons and their order.
            flag, word, third = header(data, pos)
            if flag == FLAG_LONG:
                length = word
                code = third
                end = pos + 4 + length
                if 0 < length <= cap_long and valid[code] and end <= n:
                    if px is None:
                        px = _prefix_xor(data)
                    if px[pos] == px[end]:
                        push((code, data[pos + 4 : end - 1], True))
                        pos = end
                        continue
                head = 4  # bytes a complete header needs (through the code byte)
            elif flag == FLAG_STANDARD:
                length = word & 0xFF
                code = word >> 8
                end = pos + 3 + length
                if 0 < length <= cap_std and valid[code] and end <= n:
                    if px is None:
                        px = _prefix_xor(data)
                    if px[pos] == px[end]:
                        push((code, data[pos + 3 : end - 1], False))
                        pos = end
                        continue
                head = 3
            else:
                # Skip to the next candidate flag byte with C-level searches.
                a = data.find(b"\x10", pos + 1, n)
                b = data.find(b"\x50", pos + 1, n)
                if a < 0:
                    nxt = b if b >= 0 else n
                elif b < 0 or a < b:
                    nxt = a
                else:
                    nxt = b
                st.garbage_bytes += nxt - pos
                if report:
                    marks.append((len(found), Dropped("garbage", nxt - pos)))
                pos = nxt
                continue
            # The candidate at pos failed a test: which one, in the order the checks apply.
            if n - pos < head:
                break  # header incomplete: wait for more
            if length == 0 or end - pos > cap:
                st.bad_length += 1
                if report:
                    marks.append((len(found), Dropped("too_long" if length else "zero_length", 1)))
            elif not valid[code]:
                st.bad_code += 1
                if report:
                    marks.append((len(found), Dropped("bad_code", 1)))
            elif end > n:
                break  # plausible so far: wait for the rest
            else:
                st.bad_checksum += 1
                if report:
                    marks.append((len(found), Dropped("checksum", 1)))
            pos += 1
        st.frames += len(found)
        if marks:
            _interleave(out, found, marks)
        else:
            out += map(_new, itertools.repeat(Frame), found)
        if pos:
            del buf[:pos]


# _scan's helpers.
_PAD = b"\x00\x00\x00"  # lets _HEADER read at any position of a buffer
_HEADER = struct.Struct("<BHB")  # flag, u16 (a long frame's Length; a standard one's Length + code), u8
_new = tuple.__new__  # C-level construction of a NamedTuple from a tuple


def _interleave(
    out: list[Frame | Dropped], found: list[tuple[int, bytes, bool]], marks: list[tuple[int, Dropped]]
) -> None:
    """Append the frames with each drop marker at its place in the stream."""
    done = 0
    for k, mark in marks:
        out += map(_new, itertools.repeat(Frame), found[done:k])
        out.append(mark)
        done = k
    out += map(_new, itertools.repeat(Frame), found[done:])


def _prefix_xor(buf: bytes) -> bytes:
    """px[i] = XOR of buf[:i]; len(px) == len(buf) + 1."""
    if len(buf) < 48:
        acc = 0
        out = bytearray(len(buf) + 1)
        for i, b in enumerate(buf, 1):
            acc ^= b
            out[i] = acc
        return bytes(out)
    return b"\x00" + np.bitwise_xor.accumulate(np.frombuffer(buf, dtype=np.uint8)).tobytes()


def split_frames(data: Iterable[bytes], valid_codes: frozenset[int] | None = None) -> list[Frame]:
    """Convenience for tests and tools: decode a whole stream given as chunks."""
    dec = FrameDecoder(valid_codes)
    out: list[Frame] = []
    for chunk in data:
        out.extend(f for f in dec.feed(chunk) if isinstance(f, Frame))
    return out
