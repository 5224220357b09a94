"""Encoder sketches of the kinds labs run (docs/arduino/styles/, our own), built for the
ATmega328P and run on simavr, read by the real driver: with the rig that declares each
one's format the counts match the emulated encoder within one count, sign included; with
the rig a lab writes first, one line names the one change.

Truth is the harness's prescribed motion (``avr_device.drive_counts``: the count its
encoder pins show at each emulated time) and its trace of every line the sketch sent
(when its first byte left). A sketch reads its count just before it prints: each count
must lie within one count of those the pins showed in the ``READ_WINDOW_S`` before its
line's first byte (a motion of at most 628 counts/s moves 0.63 count in that window).
The emulator runs at 0.4 to 2x real time here: every check is on emulated time.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labbench.errors import LabbenchError, UserError
from labbench.rig import load_rig, rig_from_dict
from labbench.sim_backend.avr_device import connect_sketch, drive_counts

pytestmark = pytest.mark.usefixtures("avr_toolchain")  # tests/conftest.py

STYLES = Path(__file__).resolve().parents[1] / "docs" / "arduino" / "styles"
READ_WINDOW_S = 1e-3  # a count is read at most this long before its line's first byte
# From 20 ms (the sketch has set its counter to 0 by then), +-100 counts at 1 Hz for 1.1 s
# of emulated time, then at rest: both signs; through 0 (an unsigned 16-bit counter wraps to
# 65535 there); at most 628 counts/s
DRIVE = {"drive_cps": 0.0, "drive_ms": (20.0, 1120.0), "drive_sine": (100.0, 1.0)}


def truth_range(line_first_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest count the encoder showed in the window before each line."""
    grid = line_first_s[:, None] - np.linspace(0.0, READ_WINDOW_S, 41)[None, :]
    counts = drive_counts(grid, **DRIVE)
    return counts.min(axis=1), counts.max(axis=1)


def off_by(counts: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Counts outside [lo, hi] (0 inside)."""
    return np.where(counts > hi, counts - hi, np.where(counts < lo, lo - counts, 0))


def read_lines(name: str, n: int):
    """n samples, in order, of sketch ``name`` read with its own rig: (counts, trace, rig)."""
    rig = load_rig(str(STYLES / f"{name}.toml"))
    drv, board = connect_sketch(rig, STYLES / f"{name}.ino", **DRIVE)
    try:
        drv.enable()
        samples = [drv.read(3.0) for _ in range(n)]
        counters, info = drv.counters(), drv.stream_info()
    finally:
        drv.close()
    assert board.stats["exit_code"] == 0 and not board.stats["crashed"]
    assert counters["lost"] == counters["malformed_lines"] == counters["duplicates"] == 0
    assert np.all(np.diff([s.seq for s in samples]) == 1)
    counts = np.array([round(s.position_m / rig.metres_per_count) for s in samples])
    return counts, board.trace(), info


@pytest.mark.parametrize("name, n, period_s", [
    ("millis_count", 90, 0.010),
    ("csv_fields", 180, 0.005),
    ("count16_unsigned", 450, 0.002),
])
def test_timed_sketch_read_with_its_rig_matches_the_encoder(name, n, period_s):
    counts, trace, info = read_lines(name, n)
    assert info["period_s"] == pytest.approx(period_s, rel=1e-6)  # by the board's own field
    first = np.array([t[0] for t in trace.line])
    lo, hi = truth_range(first)
    # the sample lines in order: which line the first sample was is where they all fit
    errs = [off_by(counts, lo[i:i + n], hi[i:i + n]).max() for i in range(len(first) - n + 1)]
    best = int(np.argmin(errs))
    assert errs[best] <= 1, f"{name}: {errs[best]} counts off the encoder"
    assert sorted(errs)[1] > errs[best]  # one placement only: a line earlier or later is off
    assert counts.max() >= 95 and counts.min() <= -95  # both signs, the right way round


def test_count_on_change_is_held_and_sampled_by_the_host():
    rig = load_rig(str(STYLES / "count_on_change.toml"))
    end = int(drive_counts(1.12, **DRIVE))  # where the motion stops
    drv, board = connect_sketch(rig, STYLES / "count_on_change.ino", **DRIVE)
    held = []
    try:
        drv.enable()
        while len(held) < 50 or len(set(held[-50:])) > 1:  # until it rests 50 samples
            held.append(round(drv.read(3.0).position_m / rig.metres_per_count))
            assert len(held) < 2000, "the motion never ended"
        printed = np.array([c for _, c, _ in drv._decoder.seen])  # every line, as printed
        info = drv.stream_info()
    finally:
        drv.close()
    trace = board.trace()
    assert info["time"].startswith("host") and len(printed) < 512  # seen kept them all
    # the trace's first line is the banner; then one line per printed count
    first = np.array([t[0] for t in trace.line[1:]])
    assert len(first) == len(printed)
    lo, hi = truth_range(first)
    assert off_by(printed, lo, hi).max() <= 1
    assert set(np.abs(np.diff(printed))) == {1}  # it printed every change
    assert set(held) <= set(printed)  # the host holds what was printed, nothing else
    assert max(printed) == 100 and min(printed) == -100
    # the host samples the held count at its own pace: on a loaded machine it can miss the
    # few lines the top count lasts (CI: 99), so the extremes within the goal's one count
    assert max(held) >= 99 and min(held) <= -99 and held[-1] == end == printed[-1]


WRONG = {  # the rig a lab writes first: the default layout, its baud rate and period
    "millis_count": ({"rig": {"sample_time_s": 0.01}, "serial": {"format": "ascii"}},
                     r'counts milliseconds, not microseconds: .* set \[serial\] fields = '
                     r'\["millis", "count"\]'),
    "count_on_change": ({"rig": {"sample_time_s": 0.01}, "serial": {"format": "ascii"}},
                        r'got `-?1`, expected `<micros>,<count>` .*: a count alone: set fields = '
                        r'\["count"\] and on_change = true'),
    "csv_fields": ({"rig": {"sample_time_s": 0.005}, "serial": {"format": "ascii"}},
                   r'the lines have 4 fields: name them in order, e.g. fields = \["micros", '
                   r'"count", "field3", "field4"\]'),
    "count16_unsigned": ({"rig": {"sample_time_s": 0.002}, "serial": {"format": "ascii"}},
                         r'16 bits wide and wrapped: set \[serial\] count_bits = 16 '
                         r'\(count_signed = false'),
}


@pytest.mark.parametrize("name", sorted(WRONG))
def test_the_rig_a_lab_writes_first_is_refused_in_one_line_naming_the_change(name):
    table, words = WRONG[name]
    rig = rig_from_dict({**table, "serial": {"port": "x", **table["serial"]}}, source="lab.toml")
    with pytest.raises(LabbenchError, match=words) as err:
        drv, _ = connect_sketch(rig, STYLES / f"{name}.ino", **DRIVE)
        try:  # a wrap shows only once the count goes below zero: read until then
            for _ in range(600):
                drv.read(3.0)
        finally:
            drv.close()
    assert "\n" not in str(err.value)
    assert isinstance(err.value, UserError) or name == "count16_unsigned"


def test_the_reference_sketchs_ascii_build_is_read_as_text_every_count_exact():
    """``labbench_encoder.ino -DLABBENCH_ASCII=1``: ``<t_us>,<count>`` lines, the count
    latched by the tick (t_us = tick x period): each is one the pins showed between the
    tick and its interrupt (the harness traces both), at up to 25 k counts/s."""
    from labbench.sim_backend.avr_build import SKETCH
    from labbench.sim_backend.avr_device import firmware_defines

    rig = rig_from_dict({"rig": {"sample_time_s": 0.001},
                         "serial": {"port": "x", "format": "ascii", "baudrate": 500000}})
    drive = {"drive_cps": 0.0, "drive_ms": (20.0, 1e6), "drive_sine": (2000.0, 2.0)}
    drv, board = connect_sketch(rig, SKETCH, defines={**firmware_defines(rig, 500000),
                                                      "LABBENCH_ASCII": 1}, **drive)
    try:
        drv.enable()
        samples = [drv.read(3.0) for _ in range(400)]
        assert drv.counters()["lost"] == 0
    finally:
        drv.close()
    seq = np.array([s.seq for s in samples])
    assert np.all(np.diff(seq) == 1)
    counts = np.array([round(s.position_m / rig.metres_per_count) for s in samples])
    vec = board.trace().sample_ticks()  # row k: the tick that latched the line of t_us = k T
    lo, hi = np.minimum(vec[seq, 3], vec[seq, 4]), np.maximum(vec[seq, 3], vec[seq, 4])
    assert off_by(counts, lo, hi).max() == 0
    assert np.ptp(counts) > 1000  # it moved, both ways within the sine
