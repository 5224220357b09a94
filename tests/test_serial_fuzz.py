"""Fuzzing the serial parsers with hypothesis: no exception escapes, counts stay right.

The default run is short; ``-m slow`` runs the same properties with many more examples.
"""

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labbench.drivers import framing
from labbench.drivers import serial_diagnosis as diagnosis
from labbench.drivers.serial_stream import (SYNC_LINES, Decoded, Mismatch, Reboot, SerialConfig,
                                           StreamDecoder)
from labbench.rig import rig_from_dict

SHORT = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
LONG = settings(max_examples=3000, deadline=None, suppress_health_check=[HealthCheck.too_slow])

u32 = st.integers(0, 2**32 - 1)
i32 = st.integers(-(2**31), 2**31 - 1)


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    """``data`` split at the given cut points (any chunking a serial read may produce)."""
    points = sorted({c % (len(data) + 1) for c in cuts})
    return [data[a:b] for a, b in zip([0] + points, points + [len(data)])]


def feed_all(parser, chunks):
    out = []
    for c in chunks:
        out += parser.feed(c)
    return out


def decoder(fmt="binary", count_bits=32):
    rig = rig_from_dict({"serial": {"format": fmt, "count_bits": count_bits}})
    return StreamDecoder(SerialConfig.from_rig(rig), rig.sample_time_s, rig.metres_per_count)


# -- any bytes at all -------------------------------------------------------------------
def _any_bytes(data, cuts):
    for parser in (
        framing.BinarySampleParser(),
        framing.CommandParser(),
        framing.AsciiSampleParser(),
    ):
        feed_all(parser, chunked(data, cuts))  # must not raise
        assert len(parser._buf) <= max(framing.SAMPLE_FRAME_LEN, framing.ASCII_MAX_LINE)
    for fmt in ("binary", "ascii"):
        dec = decoder(fmt, 16)
        for item in feed_all(dec, chunked(data, cuts)):
            assert isinstance(item, (Decoded, Reboot, Mismatch))


@SHORT
@given(st.binary(max_size=600), st.lists(st.integers(0, 10_000), max_size=8))
def test_any_bytes_never_raise(data, cuts):
    _any_bytes(data, cuts)


@pytest.mark.slow
@LONG
@given(st.binary(max_size=5000), st.lists(st.integers(0, 100_000), max_size=30))
def test_any_bytes_never_raise_long(data, cuts):
    _any_bytes(data, cuts)


# -- chunking never changes the outcome -------------------------------------------------------
def _chunk_invariance(data, cuts):
    for make in (framing.BinarySampleParser, framing.AsciiSampleParser):
        whole, pieces = make(), make()
        assert whole.feed(data) == feed_all(pieces, chunked(data, cuts))
        assert vars(whole) == vars(pieces)  # counters and the buffered tail too


frame_soup = st.lists(
    st.one_of(
        st.binary(max_size=40),
        st.tuples(st.integers(0, 65535), u32, i32).map(lambda f: framing.encode_sample(*f)),
        st.tuples(u32, i32).map(lambda f: framing.format_ascii(*f)),
    ),
    max_size=20,
).map(b"".join)


@SHORT
@given(frame_soup, st.lists(st.integers(0, 5000), max_size=10))
def test_chunking_never_changes_the_outcome(data, cuts):
    _chunk_invariance(data, cuts)


@pytest.mark.slow
@LONG
@given(frame_soup, st.lists(st.integers(0, 50_000), max_size=40))
def test_chunking_never_changes_the_outcome_long(data, cuts):
    _chunk_invariance(data, cuts)


# -- frames with delimited garbage between them: every frame recovered, exactly -------------
frames_st = st.lists(st.tuples(st.integers(0, 65535), u32, i32, st.integers(0, 255)), max_size=30)
garbage_st = st.lists(st.binary(max_size=40).map(lambda b: b + b"\x00"), max_size=30)


def _frames_and_garbage(frames, garbage, cuts):
    stream = b""
    for i, f in enumerate(frames):
        if i < len(garbage):
            stream += garbage[i]
        stream += framing.encode_sample(*f)
    p = framing.BinarySampleParser()
    got = feed_all(p, chunked(stream, cuts))
    assert [g[:4] for g in got] == [tuple(f) for f in frames]
    assert p.frames == len(frames)
    skipped = sum(g.skipped for g in got)
    assert skipped == p.errors  # every discarded piece is reported before the next good frame
    assert skipped >= sum(1 for g in garbage[: len(frames)] if g.strip(b"\x00"))


@SHORT
@given(frames_st, garbage_st, st.lists(st.integers(0, 5000), max_size=10))
def test_frames_survive_delimited_garbage(frames, garbage, cuts):
    _frames_and_garbage(frames, garbage, cuts)


@pytest.mark.slow
@LONG
@given(frames_st, garbage_st, st.lists(st.integers(0, 50_000), max_size=40))
def test_frames_survive_delimited_garbage_long(frames, garbage, cuts):
    _frames_and_garbage(frames, garbage, cuts)


# -- a stream with losses and bit flips: decoded + lost covers every sequence number ------------
def _losses_and_flips(n, start_seq, start_t, drops, flips, cuts):
    T_us = 1000
    stream = b""
    sent = {}
    for k in range(n):
        seq = (start_seq + k) & 0xFFFF
        frame = framing.encode_sample(seq, start_t + k * T_us, 7 * k - 100)
        if k in drops and 0 < k < n - 1:
            continue
        if k in flips and 0 < k < n - 1:
            buf = bytearray(frame)
            bit = flips[k] % (8 * (len(buf) - 1))  # never the delimiter
            buf[bit // 8] ^= 1 << (bit % 8)
            frame = bytes(buf)
        sent[k] = frame
        stream += frame
    dec = decoder()
    items = feed_all(dec, chunked(stream, cuts))
    assert all(isinstance(i, Decoded) for i in items)  # time only moves on: no reboot
    samples = [i.sample for i in items]
    # The first and last frames are intact, so the seq span is the whole run.
    assert samples[0].seq == start_seq and samples[-1].seq == start_seq + n - 1
    assert len(samples) + dec.lost == n
    for s in samples:  # every accepted sample is the one sent with that number
        k = s.seq - start_seq
        assert round(s.t_s * 1e6) == start_t + k * T_us


@SHORT
@given(
    st.integers(2, 60),
    st.integers(0, 65535),
    st.integers(0, 2**32 - 1 - 70_000),
    st.sets(st.integers(0, 60), max_size=10),
    st.dictionaries(st.integers(0, 60), st.integers(0, 10**6), max_size=10),
    st.lists(st.integers(0, 5000), max_size=10),
)
def test_losses_and_flips_are_counted(n, start_seq, start_t, drops, flips, cuts):
    _losses_and_flips(n, start_seq, start_t, drops, flips, cuts)


@pytest.mark.slow
@LONG
@given(
    st.integers(2, 300),
    st.integers(0, 65535),
    st.integers(0, 2**32 - 1 - 400_000),
    st.sets(st.integers(0, 300), max_size=40),
    st.dictionaries(st.integers(0, 300), st.integers(0, 10**6), max_size=40),
    st.lists(st.integers(0, 50_000), max_size=40),
)
def test_losses_and_flips_are_counted_long(n, start_seq, start_t, drops, flips, cuts):
    _losses_and_flips(n, start_seq, start_t, drops, flips, cuts)


# -- ASCII lines between junk lines ---------------------------------------------------------
junk_line = st.binary(max_size=30).filter(
    lambda b: (
        b"\n" not in b
        and framing.ASCII_LINE.fullmatch(b) is None
        and not b.strip(b" \t\r").startswith(b"#")
        and framing.TEXT_LINE.fullmatch(b.strip(b" \t\r")) is None
        and b.strip(b" \t\r") != b""
    )
)


def _ascii(samples, junk, cuts):
    stream = b""
    for i, (t, c) in enumerate(samples):
        if i < len(junk):
            stream += junk[i] + b"\n"
        stream += framing.format_ascii(t, c)
    p = framing.AsciiSampleParser()
    got = feed_all(p, chunked(stream, cuts))
    assert [(g.t_us, g.count) for g in got] == samples
    assert p.malformed == min(len(junk), len(samples))


@SHORT
@given(
    st.lists(st.tuples(u32, i32), max_size=30),
    st.lists(junk_line, max_size=30),
    st.lists(st.integers(0, 3000), max_size=10),
)
def test_ascii_lines_survive_junk_lines(samples, junk, cuts):
    _ascii(samples, junk, cuts)


@pytest.mark.slow
@LONG
@given(
    st.lists(st.tuples(u32, i32), max_size=200),
    st.lists(junk_line, max_size=200),
    st.lists(st.integers(0, 30_000), max_size=40),
)
def test_ascii_lines_survive_junk_lines_long(samples, junk, cuts):
    _ascii(samples, junk, cuts)


# -- the driver on arbitrary input: only DeviceFault or TimeoutError, and force stays zero after ----
class ScriptedPort:
    """A port that returns the given chunks, then nothing (a fake clock moves per read)."""

    port = "scripted"
    timeout = write_timeout = None

    def __init__(self, chunks, now):
        self.chunks, self.now, self.written = list(chunks), now, []

    @property
    def in_waiting(self):
        return len(self.chunks[0]) if self.chunks else 0

    def read(self, n):
        self.now[0] += 0.0002
        return self.chunks.pop(0) if self.chunks else b""

    def write(self, data):
        self.written.append(data)
        return len(data)

    def close(self):
        pass


def _driver_on_any_input(fmt, prefix, chunks):
    from labbench.drivers.serial_stream import SerialStream
    from labbench.device import DeviceFault

    rig = rig_from_dict({"serial": {"format": fmt, "force_command": True}})
    now = [0.0]
    good = [
        framing.encode_sample(k, 1000 * k, k)
        if fmt == "binary"
        else framing.format_ascii(1000 * k, k)
        for k in range(SYNC_LINES + 1)  # enough for either form's handshake
    ]
    port = ScriptedPort([b"".join(good), *prefix, *chunks], now)
    drv = SerialStream(port, SerialConfig.from_rig(rig), rig, clock=lambda: now[0])
    drv.wait_for_stream(1.0)
    drv.enable(0.1)
    for _ in range(len(chunks) + 5):
        try:
            drv.read(0.01)
            drv.command(0.5)
        except (DeviceFault, TimeoutError):
            assert drv.commanded_force_n == 0.0 and drv.fault
            break
    if drv.fault:  # once latched, everything sent is zero
        drv.command(1.0)
        assert port.written[-1] == framing.encode_command(drv._last_seq, 0.0)


@SHORT
@given(
    st.sampled_from(["binary", "ascii"]),
    st.lists(st.binary(max_size=40), max_size=3),
    st.lists(st.binary(max_size=200), max_size=10),
)
def test_driver_on_any_input_raises_only_faults(fmt, prefix, chunks):
    _driver_on_any_input(fmt, prefix, chunks)


@pytest.mark.slow
@LONG
@given(
    st.sampled_from(["binary", "ascii"]),
    st.lists(st.binary(max_size=40), max_size=3),
    st.lists(st.binary(max_size=2000), max_size=40),
)
def test_driver_on_any_input_raises_only_faults_long(fmt, prefix, chunks):
    _driver_on_any_input(fmt, prefix, chunks)


# -- a lab's own layout, and the diagnosis of what never became a stream ----------------------
layouts = st.lists(st.sampled_from(["count", "micros", "millis", "speed", "dir"]), min_size=1,
                   max_size=5, unique=True).filter(
    lambda f: "count" in f and not {"micros", "millis"} <= set(f))
text_bytes = st.lists(st.sampled_from([b"1", b"-", b",", b" ", b"\t", b";", b"\r\n", b"x",
                                       b"Encoder ", b"\x00", b"\xff", b"65535", b"#"]),
                      max_size=120).map(b"".join)


@SHORT
@given(layouts, st.one_of(text_bytes, st.binary(max_size=400)),
       st.lists(st.integers(0, 10_000), max_size=8), st.booleans())
def test_any_layout_on_any_bytes_parses_the_same_however_chunked(fields, data, cuts, on_change):
    whole = framing.AsciiSampleParser(fields)
    parts = framing.AsciiSampleParser(fields)
    assert whole.feed(data) == feed_all(parts, chunked(data, cuts))
    assert (whole.lines, whole.comments, whole.malformed) == (parts.lines, parts.comments,
                                                              parts.malformed)
    assert len(parts._buf) <= framing.ASCII_MAX_LINE and len(parts.rejected) <= framing.KEPT_LINES
    rig = rig_from_dict({"serial": {"format": "ascii", "fields": fields, "on_change": on_change,
                                    "count_bits": 16}})
    dec = StreamDecoder(SerialConfig.from_rig(rig), rig.sample_time_s, rig.metres_per_count)
    feed_all(dec, chunked(data, cuts))
    seen = diagnosis.Seen("fuzz", head=bytearray(data[:diagnosis.HEAD_BYTES]), nbytes=len(data))
    seen.samples = [(t, c, 0.01 * i) for i, (t, c, _) in enumerate(dec.seen)]  # 10 ms apart
    seen.text, seen.rejected = dec.parser.text, dec.parser.rejected
    cfg = SerialConfig.from_rig(rig)
    for line in (diagnosis.refusal(seen, cfg, 0.001, 1.0, {}), diagnosis.timing(seen, cfg, 0.001)):
        assert line is None or (isinstance(line, str) and "\n" not in line)
