"""Wire formats of the serial encoder stream: pure functions and parsers, no I/O.

Two board -> host forms (docs/serial-protocol.md is the user-facing spec):

* ASCII, one sample per line: ``<micros>,<count>`` by default (``ASCII_LINE``), or the
  columns a lab's own sketch prints, named in order (``ascii_line``): a time field
  (``micros`` or ``millis``) or none, the ``count``, and extra fields (ignored).
* Binary, COBS-framed (Cheshire & Baker, "Consistent Overhead Byte Stuffing",
  IEEE/ACM Trans. Networking 7(2), 1999) with a 0x00 delimiter after every
  frame and a CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection) over
  the payload. Little-endian payloads:

  sample  (board -> host, 14 bytes):
  ``'S' u8 | seq u16 | micros u32 | count i32 | status u8 | crc u16``
  command (host -> board,  9 bytes):
  ``'F' u8 | seq u16 | value f32 | crc u16``
  params  (host -> board, 24 bytes, protocol v2, on-board VE):
  ``'P' u8 | on u8 | K f32 | B f32 | w0 f32 | limit f32 | metres_per_count f32 | crc u16``

The parsers take arbitrary chunks, keep the partial tail, never raise on bad
input, and count what they threw away, so a stream resynchronises by itself
after garbage or the boot noise of a board that reset on DTR.
"""

from __future__ import annotations

import binascii
import re
import struct
from typing import NamedTuple

SAMPLE_TYPE = 0x53  # 'S'
COMMAND_TYPE = 0x46  # 'F'
PARAMS_TYPE = 0x50  # 'P' (protocol v2): the VE the board renders itself
_SAMPLE = struct.Struct("<BHIiB")
_COMMAND = struct.Struct("<BHf")
_PARAMS = struct.Struct("<BBfffff")
_CRC = struct.Struct("<H")
SAMPLE_PAYLOAD_LEN = _SAMPLE.size + _CRC.size  # 14
COMMAND_PAYLOAD_LEN = _COMMAND.size + _CRC.size  # 9
# COBS adds exactly one byte to payloads shorter than 254 bytes.
SAMPLE_FRAME_LEN = SAMPLE_PAYLOAD_LEN + 1
COMMAND_FRAME_LEN = COMMAND_PAYLOAD_LEN + 1

# Board status bits carried in a sample frame (the reference sketch sets them).
# Protocol v1 defines bits 0-1; v2 adds bits 2-4 (a v1 board leaves them zero).
STATUS_WATCHDOG = 0x01  # board zeroed its output: no command within 3 periods
STATUS_BAD_COMMAND = 0x02  # board discarded a command frame (CRC/format) since last sample
STATUS_MISSED_TICK = 0x04  # v2: a sample before this one was latched but never sent
STATUS_LATE = 0x08  # v2: this frame was queued late after its tick (its timing is suspect)
STATUS_ENCODER = 0x10  # v2: the encoder skipped a state (an edge came too fast to count)
STATUS_RENDERING = 0x20  # v2: the board renders the VE itself ('F' values are excitation)
STATUS_RENDER_LATE = 0x40  # v2: a rendered force was not ready by its tick (the last one held)

# ASCII lines: the time field's unit in microseconds, by its name in a rig's ``fields``.
TIME_FIELDS = {"micros": 1, "millis": 1000}
DEFAULT_FIELDS = ("micros", "count")
# One separator between fields: a comma, semicolon, tab or spaces, blanks around it.
_SEP = rb"[ \t]*(?:[,;\t]|[ ]+)[ \t]*"
_TIME = rb"(?P<t>\d{1,10})"  # decimal, 0..4294967295 (an unsigned long: micros(), millis())
_COUNT = rb"(?P<c>-?\d{1,11})"  # decimal with an optional minus sign
_EXTRA = rb"[^\s,;]+"  # any other field: one token, ignored


def ascii_line(fields=DEFAULT_FIELDS) -> re.Pattern:
    """The accepted line for ``fields`` (names in order: a time field of ``TIME_FIELDS``
    or none, ``count``, any other name an extra field): the fields, one separator between
    each two, blanks at both ends, an optional CR. Groups: ``t`` the time (if any), ``c``
    the count."""
    parts = [_TIME if f in TIME_FIELDS else _COUNT if f == "count" else _EXTRA for f in fields]
    return re.compile(rb"[ \t]*" + _SEP.join(parts) + rb"[ \t]*\r?")


def ascii_form(fields=DEFAULT_FIELDS) -> str:
    """The expected line for people, e.g. ``<micros>,<count>``."""
    return ",".join(f"<{f}>" for f in fields)


ASCII_LINE = ascii_line()
# Longer lines are malformed: bounds the buffer under garbage (and a wrong baud rate,
# whose bytes seldom form a newline). Room for a CSV line of 8 fields or a banner.
ASCII_MAX_LINE = 96
# A line of text (a banner, a CSV header, a message): printable ASCII with a word of at
# least three letters. Skipped and counted as a comment, never a sample or a link error;
# a corrupted digit (one letter) is not text.
TEXT_LINE = re.compile(rb"[\x20-\x7e\t\r]*[A-Za-z]{3}[\x20-\x7e\t\r]*")
KEPT_LINES = 5  # text and rejected lines kept for the messages (the first ones)
# RawSample.status of an ASCII line (outside a board's 8 status bits): the first text line
# the board sent (its banner) came again before this sample, after samples: a reboot.
BANNER_AGAIN = 0x100
_U32 = 1 << 32


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (check value 0x29B1 for b"123456789")."""
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode ``data`` (no delimiter appended)."""
    out = bytearray()
    for block in data.split(b"\x00"):
        # A block longer than 254 bytes is split into 254-byte runs coded 0xFF.
        while len(block) >= 254:
            out.append(0xFF)
            out += block[:254]
            block = block[254:]
        out.append(len(block) + 1)
        out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes | None:
    """Inverse of ``cobs_encode``; ``None`` if ``data`` is not valid COBS."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        end = i + code
        if code == 0 or end > n:
            return None
        block = data[i + 1 : end]
        if 0 in block:
            return None
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


def _frame(payload: bytes) -> bytes:
    return cobs_encode(payload + _CRC.pack(crc16(payload))) + b"\x00"


def encode_sample(seq: int, t_us: int, count: int, status: int = 0) -> bytes:
    """One framed sample; ``count`` is stored as its low 32 bits (two's complement)."""
    count &= 0xFFFFFFFF
    if count >= 1 << 31:
        count -= 1 << 32
    return _frame(_SAMPLE.pack(SAMPLE_TYPE, seq & 0xFFFF, t_us % _U32, count, status & 0xFF))


def encode_command(seq: int, value: float) -> bytes:
    """One framed force command answering sample ``seq``."""
    return _frame(_COMMAND.pack(COMMAND_TYPE, seq & 0xFFFF, value))


def encode_params(on: bool, K: float, B: float, w0_rad_s: float, limit_n: float,
                  metres_per_count: float) -> bytes:
    """One framed on-board VE (v2): spring K [N/m], damper B [N s/m] on the velocity
    low-passed at w0 [rad/s] (inf: none), force limit [N], encoder metres per count."""
    return _frame(_PARAMS.pack(PARAMS_TYPE, bool(on), K, B, w0_rad_s, limit_n, metres_per_count))


def format_ascii(t_us: int, count: int) -> bytes:
    """The line an Arduino ``Serial.print(t); Serial.print(','); Serial.println(c)`` sends."""
    return b"%d,%d\r\n" % (t_us % _U32, count)


class RawSample(NamedTuple):
    """A sample as the board sent it: ``seq`` is None for ASCII lines.

    ``t_us``: the board's time field as sent: micros() (binary, ASCII ``micros``), millis()
    (ASCII ``millis``), None (an ASCII stream without a time field). ``skipped``: frames or
    lines discarded between the previous good sample and this one.
    """

    seq: int | None
    t_us: int | None
    count: int
    status: int = 0
    skipped: int = 0


class FrameParser:
    """Split a COBS byte stream into checked payloads of one frame type.

    Counters: ``frames`` good, ``crc_errors``, ``bad_frames`` (wrong length,
    type or COBS, or garbage before a frame), ``garbage_bytes``.

    Garbage that runs into a frame without a delimiter (a burst, boot noise) is
    cut off: only the last frame length of a segment can still be a frame, so
    the buffer stays bounded, that frame is recovered when intact, and the
    result does not depend on how the bytes arrive in chunks.
    """

    def __init__(self, frame_type: int, payload_len: int):
        self._type = frame_type
        self._plen = payload_len
        self._flen = payload_len + 1
        self._buf = b""
        self._dropped = 0  # garbage bytes already cut from the segment in the buffer
        self._skipped = 0  # pieces discarded since the last good frame
        self.frames = self.crc_errors = self.bad_frames = self.garbage_bytes = 0

    def feed_payloads(self, data: bytes) -> list[tuple[bytes, int]]:
        """(checked payload without CRC, pieces discarded before it) completed by ``data``."""
        parts = (self._buf + data).split(b"\x00")
        tail = parts.pop()
        out = []
        flen = self._flen
        for part in parts:
            garbage = self._dropped + max(len(part) - flen, 0)
            self._dropped = 0
            if not part and not garbage:
                continue  # back-to-back delimiters (a sender may flush with a zero)
            part = part[-flen:]
            payload = cobs_decode(part) if len(part) == flen else None
            framed = payload is not None and len(payload) == self._plen and payload[0] == self._type
            if framed and crc16(payload[:-2]) == _CRC.unpack_from(payload, self._plen - 2)[0]:
                if garbage:
                    self._discard(garbage)
                self.frames += 1
                out.append((payload[:-2], self._skipped))
                self._skipped = 0
            elif framed and not garbage:
                self.crc_errors += 1
                self._discard(len(part), bad_frame=False)
            else:
                self._discard(garbage + len(part))
        if len(tail) > flen:
            self._dropped += len(tail) - flen
            tail = tail[-flen:]
        self._buf = tail
        return out

    def _discard(self, n_bytes: int, bad_frame: bool = True) -> None:
        self.bad_frames += bad_frame
        self.garbage_bytes += n_bytes
        self._skipped += 1

    @property
    def errors(self) -> int:
        return self.crc_errors + self.bad_frames


class BinarySampleParser(FrameParser):
    """Board -> host sample frames."""

    def __init__(self):
        super().__init__(SAMPLE_TYPE, SAMPLE_PAYLOAD_LEN)

    def feed(self, data: bytes) -> list[RawSample]:
        return [
            RawSample(*_SAMPLE.unpack(p)[1:], skipped) for p, skipped in self.feed_payloads(data)
        ]


class CommandParser(FrameParser):
    """Host -> board command frames (the board side: peer and sketch)."""

    def __init__(self):
        super().__init__(COMMAND_TYPE, COMMAND_PAYLOAD_LEN)

    def feed(self, data: bytes) -> list[tuple[int, float]]:
        return [_COMMAND.unpack(p)[1:] for p, _ in self.feed_payloads(data)]


class AsciiSampleParser:
    """Sample lines of ``fields`` (``ascii_line``); blank lines are skipped, ``#`` lines
    and text lines (``TEXT_LINE``: a banner, a CSV header) are skipped and counted.

    Counters: ``lines`` good, ``comments`` (``#...`` and text), ``malformed`` (anything
    else, including lines over ``ASCII_MAX_LINE`` bytes), ``garbage_bytes``. ``text`` and
    ``rejected`` keep the first ``KEPT_LINES`` of each (for the driver's messages).
    """

    def __init__(self, fields=DEFAULT_FIELDS):
        self._line = ascii_line(fields)
        self._has_time = any(f in TIME_FIELDS for f in fields)
        self._buf = b""
        self._overlong = 0  # bytes of an over-long line still waiting for its newline
        self._skipped = 0
        self.lines = self.comments = self.malformed = self.garbage_bytes = 0
        self.text: list[bytes] = []
        self.rejected: list[bytes] = []
        self._again = 0  # BANNER_AGAIN for the next sample

    def feed(self, data: bytes) -> list[RawSample]:
        parts = (self._buf + data).split(b"\n")
        tail = parts.pop()
        if self._overlong:  # the rest of an over-long line is malformed too, however chunked
            if parts:
                self._discard(self._overlong + len(parts.pop(0)) + 1)
                self._overlong = 0
            else:
                self._overlong += len(tail)
                tail = b""
        out = []
        match, timed = self._line.fullmatch, self._has_time
        for line in parts:
            m = match(line) if len(line) <= ASCII_MAX_LINE else None
            if m is not None:
                t_us = int(m["t"]) if timed else None
                if not timed or t_us < _U32:
                    self.lines += 1
                    out.append(RawSample(None, t_us, int(m["c"]), self._again,
                                         self._skipped))
                    self._skipped = self._again = 0
                    continue
            stripped = line.strip(b" \t\r")
            if not stripped:
                continue
            if len(line) <= ASCII_MAX_LINE and (stripped[:1] == b"#"
                                                or TEXT_LINE.fullmatch(stripped)):
                self.comments += 1
                if self.lines and self.text and stripped == self.text[0]:
                    self._again = BANNER_AGAIN
                if len(self.text) < KEPT_LINES:
                    self.text.append(stripped)
            else:  # (an over-long line is not kept: chunked, its bytes are gone by its end)
                if len(self.rejected) < KEPT_LINES and len(line) <= ASCII_MAX_LINE:
                    self.rejected.append(stripped)
                self._discard(len(line) + 1)
        if len(tail) > ASCII_MAX_LINE:
            self._overlong = len(tail)
            tail = b""
        self._buf = tail
        return out

    def _discard(self, n_bytes: int) -> None:
        self.malformed += 1
        self.garbage_bytes += n_bytes
        self._skipped += 1

    @property
    def errors(self) -> int:
        return self.malformed
