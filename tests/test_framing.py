"""Wire formats of the serial encoder stream against known vectors and exhaustive corruption."""

import struct

import pytest

from labbench.drivers import framing
from labbench.drivers.framing import (
    AsciiSampleParser,
    BinarySampleParser,
    CommandParser,
    RawSample,
    cobs_decode,
    cobs_encode,
    crc16,
    encode_command,
    encode_sample,
)


def test_crc16_ccitt_false_check_value():
    # The catalogued check value of CRC-16/CCITT-FALSE over "123456789".
    assert crc16(b"123456789") == 0x29B1


@pytest.mark.parametrize(
    "raw, encoded",
    [
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (b"", b"\x01"),
    ],
)
def test_cobs_known_vectors(raw, encoded):
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == raw


def test_cobs_long_runs_round_trip():
    for data in (
        bytes(range(1, 255)),
        bytes(range(256)) * 3,
        b"\x00" * 300,
        bytes(range(1, 256)) * 2,
    ):
        enc = cobs_encode(data)
        assert 0 not in enc
        assert cobs_decode(enc) == data


@pytest.mark.parametrize("bad", [b"\x00\x01", b"\x05\x11", b"\x03\x11\x00"])
def test_cobs_rejects_invalid(bad):
    assert cobs_decode(bad) is None


def test_sample_frame_layout():
    frame = encode_sample(0x1234, 4_000_000_000, -5, status=framing.STATUS_WATCHDOG)
    assert frame[-1] == 0 and 0 not in frame[:-1]
    assert len(frame) == framing.SAMPLE_FRAME_LEN + 1
    payload = cobs_decode(frame[:-1])
    assert payload[:12] == struct.pack("<BHIiB", 0x53, 0x1234, 4_000_000_000, -5, 1)
    assert struct.unpack("<H", payload[12:])[0] == crc16(payload[:12])


def test_sample_and_command_round_trip_with_wrapping_fields():
    p = BinarySampleParser()
    stream = encode_sample(70000, 2**32 + 7, 2**31 + 3) + encode_sample(1, 2, -(2**31))
    assert p.feed(stream) == [
        RawSample(70000 % 65536, 7, -(2**31) + 3, 0),
        RawSample(1, 2, -(2**31), 0),
    ]
    c = CommandParser()
    assert c.feed(encode_command(65537, 1.5)) == [(1, 1.5)]


def test_every_single_bit_flip_is_rejected_and_the_stream_resynchronises():
    good = [encode_sample(k, 1000 * k, 3 * k - 50) for k in range(3)]
    middle = good[1]
    for i in range(len(middle) * 8):
        corrupt = bytearray(middle)
        corrupt[i // 8] ^= 1 << (i % 8)
        p = BinarySampleParser()
        got = p.feed(good[0] + bytes(corrupt) + good[2])
        # The corrupt frame never yields a sample; the next one survives even when
        # the flip hit the delimiter between them (it is cut off the merged segment).
        assert [g[:4] for g in got] == [(0, 0, -50, 0), (2, 2000, -44, 0)], f"bit {i}"
        assert p.errors >= 1 and got[1].skipped >= 1  # the loss is marked on the next good frame


def test_binary_parser_counts_and_bounds_garbage():
    p = BinarySampleParser()
    assert p.feed(b"\xff" * 10_000) == []
    assert len(p._buf) <= framing.SAMPLE_FRAME_LEN
    got = p.feed(b"\x00" + encode_sample(5, 50, 7))
    assert got == [RawSample(5, 50, 7, 0, skipped=1)]
    assert p.garbage_bytes == 10_000 and p.frames == 1


def test_command_frame_is_not_a_sample():
    p = BinarySampleParser()
    assert p.feed(encode_command(1, 2.0)) == []
    assert p.bad_frames == 1


ACCEPTED = [
    (b"123,456\n", (123, 456)),
    (b"123,-456\r\n", (123, -456)),
    (b" 123 , 456 \r\n", (123, 456)),
    (b"123\t456\n", (123, 456)),
    (b"123;456\n", (123, 456)),
    (b"123 456\n", (123, 456)),
    (b"4294967295,65535\n", (4294967295, 65535)),
    (b"0,-2147483648\n", (0, -2147483648)),
]
REJECTED = [
    b"123,456,789\n",
    b"ab,1\n",
    b"1.5,3\n",
    b"+1,2\n",
    b"123,\n",
    b"4294967296,1\n",
    b"1_000,2\n",
    b"12,,3\n",
    b"-1,2\n",
    b"123,4x\n",
    b"\xff\xfe,1\n",
]


@pytest.mark.parametrize("line, expected", ACCEPTED)
def test_ascii_accepted_forms(line, expected):
    p = AsciiSampleParser()
    assert p.feed(line) == [RawSample(None, *expected)]
    assert p.malformed == 0


@pytest.mark.parametrize("line", REJECTED)
def test_ascii_rejected_forms(line):
    p = AsciiSampleParser()
    assert p.feed(line) == []
    assert p.malformed == 1


@pytest.mark.parametrize("fields, line, expected", [
    (("count",), b"-17\r\n", (None, -17)),
    (("millis", "count"), b"10240 -3\r\n", (10240, -3)),
    (("count", "micros"), b"5;77\n", (77, 5)),
    (("micros", "count", "speed", "dir"), b"100,7,1.5e3,-1\r\n", (100, 7)),
])
def test_ascii_lines_of_declared_fields(fields, line, expected):
    p = AsciiSampleParser(fields)
    assert p.feed(line) == [RawSample(None, *expected)]
    assert p.feed(b"1,2,3,4,5\n") == [] and p.malformed == 1 and p.rejected == [b"1,2,3,4,5"]


def test_text_lines_are_comments_kept_and_a_repeated_banner_marks_the_next_sample():
    p = AsciiSampleParser(("count",))
    got = p.feed(b"Encoder ready\r\nt_us,count,dir\r\n5\r\n12a4\r\nEncoder ready\r\n6\r\n")
    assert [(g.count, g.status) for g in got] == [(5, 0), (6, framing.BANNER_AGAIN)]
    assert p.text == [b"Encoder ready", b"t_us,count,dir", b"Encoder ready"]
    assert p.comments == 3 and p.malformed == 1 and p.rejected == [b"12a4"]  # one letter: corrupt


def test_ascii_comments_blank_lines_and_partial_tail():
    p = AsciiSampleParser()
    got = p.feed(b"#labbench encoder v1\r\n\r\n\n1000,5\r\n2000,")
    assert got == [RawSample(None, 1000, 5)]
    assert p.comments == 1 and p.malformed == 0
    assert p.feed(b"6\r\n") == [RawSample(None, 2000, 6)]


def test_ascii_overlong_line_is_dropped_without_growing_the_buffer():
    p = AsciiSampleParser()
    p.feed(b"9" * 5000)
    assert len(p._buf) <= framing.ASCII_MAX_LINE
    assert p.feed(b"\n1,2\n") == [RawSample(None, 1, 2, skipped=1)]
    assert p.malformed == 1
