"""The reference firmware (docs/arduino/labbench_encoder.ino) built for the ATmega328P and
run on simavr around the simulated plant, with the real SerialStream as host.

Truth comes from the harness (sim_backend/avr/harness.c): the count its encoder
pins showed when the sample tick was raised and when its interrupt ran, the force
the firmware's PWM and DIR pins applied, and when each frame went out. The plant is
integrated again here with ``labbench.model.linear.zoh_matrices`` from the forces the
firmware applied, independently of the harness's own closed form.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from labbench.drivers import framing
from labbench.drivers import serial_stream as ss
from labbench.rig import Rig, rig_from_dict
from labbench.sim_backend.avr_device import connect_avr_sim

pytestmark = pytest.mark.usefixtures("avr_toolchain")  # tests/conftest.py

RIG = Rig()
MPC = RIG.metres_per_count
BYTE_S = 10 / 500_000  # one byte on a 500 kbit/s wire


def run(n: int, answer, rig=RIG, **options):
    """n lock-step samples through the emulated board: (samples, commands, stats, trace)."""
    drv, board = connect_avr_sim(rig, trace=True, **options)
    samples, commands = [], []
    try:
        drv.enable()
        for k in range(n):
            s = drv.read(2.0)
            samples.append(s)
            f = answer(k, s)
            commands.append(f)
            drv.command(f)
        counters = drv.counters()
    finally:
        drv.close()
    return samples, commands, counters, board.stats, board.trace()


def quantised(f: float) -> float:
    """The force the sketch drives for a command: f32 on the wire, duty rounded to 1/40 N."""
    d = float(np.float32(f)) * 40.0
    d = max(-255.0, min(255.0, math.copysign(math.floor(abs(d) + 0.5), d)))
    return d / 40.0


def force_before(force_events, t: float) -> float:
    value = 0.0
    for at, f in force_events:
        if at >= t:
            break
        value = f
    return value


def test_closed_loop_in_lock_step_counts_and_force_feedback():
    rng = np.random.default_rng(7)
    forces = rng.uniform(-0.3, 0.3, 600)
    samples, commands, counters, stats, trace = run(600, lambda k, s: forces[k])
    assert stats["exit_code"] == 0 and not stats["crashed"]
    assert counters["crc_errors"] == 0 and counters["lost"] == 0
    seq = np.array([s.seq for s in samples])
    assert np.all(np.diff(seq) == 1)
    t = np.array([s.t_s for s in samples])
    np.testing.assert_allclose(np.diff(t), RIG.sample_time_s, rtol=0, atol=1e-9)
    assert all(s.flags == 0 for s in samples)  # no watchdog, no late frame, no lost count

    vec = trace.sample_ticks()  # row k: the tick that latched sample seq k
    counts = np.array([round(s.position_m / MPC) for s in samples])
    lo, hi = vec[seq, 3], vec[seq, 4]
    # The latched count is one the pins showed between the tick and its interrupt.
    assert np.all((counts >= np.minimum(lo, hi)) & (counts <= np.maximum(lo, hi)))
    assert np.ptp(counts) > 50  # the handle really moved

    # Force out: from tick k+1 the board drives the answer to sample k, quantised.
    events = trace.force
    for j in range(len(samples) - 2):
        tick = vec[seq[j] + 2, 0]  # just before the tick after the one that applied it
        assert force_before(events, tick) == pytest.approx(quantised(commands[j]), abs=1e-12)
    # ... and changes only inside the tick interrupt.
    starts = vec[:, 1]
    for at, _ in events[1:]:
        i = np.searchsorted(starts, at) - 1
        assert 0 <= i and at - starts[i] < 30e-6

    # The plant, integrated again from the forces the firmware applied, is where the
    # board's encoder says it is (one count: edges are timed within 4 us steps).
    x = trace.plant_positions(vec[seq, 0], RIG.nominal_mass_kg, RIG.nominal_damping_ns_m)
    assert np.max(np.abs(x / MPC - counts)) <= 1.0


def truth_error(samples, vec):
    """Per sample: counts outside what the pins showed between its tick and its interrupt."""
    seq = np.array([s.seq for s in samples])
    counts = np.array([round(s.position_m / MPC) for s in samples])
    lo = np.minimum(vec[seq, 3], vec[seq, 4])
    hi = np.maximum(vec[seq, 3], vec[seq, 4])
    return np.where(counts > hi, counts - hi, np.where(counts < lo, counts - lo, 0)), counts


@pytest.mark.parametrize("cps", [105_000.0, -105_000.0])
def test_encoder_counts_exactly_above_100k_counts_per_second(cps):
    samples, _, counters, stats, trace = run(200, lambda k, s: 0.0, drive_cps=cps,
                                             drive_ms=(20.0, 150.0))
    err, counts = truth_error(samples, trace.sample_ticks())
    assert not err.any()
    assert counts[-1] == stats["count"] == round(cps * 0.130)
    assert np.ptp(np.diff(counts)[30:140]) <= 2  # about cps / 1000 per sample
    assert all(s.flags == 0 for s in samples)  # no skipped state, no late or missed sample
    assert counters["lost"] == 0


def test_beyond_its_rate_the_board_flags_every_count_and_sample_it_loses():
    # 245 k counts/s: edges 65 cycles apart, the encoder interrupt takes 54: the board
    # skips states, loses counts now and then, and says so where it happens (at
    # 260 k it cannot send at all, and the host's stale limit trips).
    rig = rig_from_dict({"serial": {"tolerate_drops": 1000}})
    samples, _, _, stats, trace = run(200, lambda k, s: 0.0, rig=rig, drive_cps=245_000.0,
                                      drive_ms=(20.0, 150.0))
    err, counts = truth_error(samples, trace.sample_ticks())
    assert counts[-1] != stats["count"]  # counts really were lost
    flags = np.array([s.flags for s in samples])
    seq = np.array([s.seq for s in samples])
    lost = ss.FLAG_BOARD_ENCODER | ss.FLAG_BOARD_MISSED_TICK
    changed = np.nonzero(np.diff(np.r_[0, err]))[0]
    gaps = np.nonzero(np.diff(seq) > 1)[0] + 1
    assert len(changed) > 0
    assert all(flags[i] & lost for i in changed)
    assert all(flags[i] & ss.FLAG_BOARD_MISSED_TICK for i in gaps)


def test_a_burst_of_8_commands_does_not_delay_the_samples():
    drv, board = connect_avr_sim(RIG, trace=True)
    samples, burst_at = [], set()
    try:
        drv.enable()
        for k in range(300):
            s = drv.read(2.0)
            samples.append(s)
            if k % 5 == 0:  # 8 commands at once, the last one the answer
                burst_at.add(s.seq)
                burst = b"".join(framing.encode_command(s.seq, 0.01 * i) for i in range(8))
                assert os.write(drv.port.fileno(), burst) == len(burst)  # as the driver writes
            else:
                drv.command(0.05 * math.sin(k / 20))
        counters = drv.counters()
    finally:
        drv.close()
    trace = board.trace()
    vec = trace.sample_ticks()
    frames = [t for t in trace.tx if t[2] == 16]  # sample frames, in tick order
    seq = np.array([s.seq for s in samples])
    assert np.all(np.diff(seq) == 1) and counters["lost"] == 0
    first = np.array([frames[q][0] - vec[q, 0] for q in seq])  # first byte on the wire
    assert first.max() <= 0.4e-3
    after_burst = [i for i, q in enumerate(seq) if q - 1 in burst_at]
    assert max(first[after_burst]) > np.median(first)  # the bursts were there to be felt
    flags = {s.flags & ~ss.FLAG_BACKLOG & ~ss.FLAG_BOARD_LATE for s in samples}
    assert flags == {0}  # no command lost or corrupt, no sample missed


def test_samples_the_board_cannot_send_are_flagged_not_hidden():
    # 16-byte frames at 500 kbit/s take 0.32 ms: a 0.2 ms period cannot be kept.
    rig = rig_from_dict({"rig": {"sample_time_s": 0.0002},
                         "serial": {"tolerate_drops": 5, "sync_timeout_s": 10.0}})
    drv, board = connect_avr_sim(rig)
    samples = []
    try:
        drv.enable()
        for k in range(300):
            samples.append(drv.read(2.0))
            drv.command(0.0)
    finally:
        drv.close()
    seq = np.array([s.seq for s in samples])
    gaps = np.nonzero(np.diff(seq) > 1)[0] + 1
    assert len(gaps) > 50
    assert all(samples[i].flags & ss.FLAG_BOARD_MISSED_TICK for i in gaps)
    assert all(s.flags & ss.FLAG_BOARD_LATE for s in samples[1:])


def test_the_board_renders_a_spring_damper_itself_at_5_khz_and_keeps_it_when_the_host_stalls():
    from labbench.model.ve import VirtualEnvironment

    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=RIG.sample_time_s)
    drv, board = connect_avr_sim(RIG, trace=True)
    samples, push = [], 0.5  # N of excitation: the spring gives way by push / K
    try:
        drv.render_on_board(ve)
        drv.enable()
        for k in range(1100):
            samples.append(drv.read(2.0))
            if k < 400:
                drv.command(push)
            else:  # the host stalls: frames without a command (lock-step goes on); one
                # os.write as the driver writes (pyserial's 20 ms write timeout also fires
                # when this thread is merely descheduled: CI under load)
                os.write(drv.port.fileno(), b"\x00")
    finally:
        drv.close()
    trace = board.trace()
    flags = np.array([s.flags for s in samples])
    x = np.array([s.position_m for s in samples])
    rendering = flags & ss.FLAG_BOARD_RENDERING != 0
    assert rendering[5:].all()
    # Force resolution 1/40 N: the handle rests within half a duty step of push / K.
    dead_band = 0.5 / 40.0 / ve.K + MPC
    assert abs(np.median(x[300:400]) - push / ve.K) <= dead_band
    # The host is silent: the excitation goes (watchdog), the spring stays and
    # brings the handle back.
    assert (flags[410:] & ss.FLAG_BOARD_WATCHDOG).all()
    assert abs(np.median(x[1000:])) <= dead_band
    # 5 render ticks per sample while rendering; the force changes at them, also
    # between samples (while the handle moves).
    vec = np.array(trace.vec)
    t0, t1 = trace.sample_ticks()[[10, 300], 0]
    ticks = vec[(vec[:, 0] >= t0) & (vec[:, 0] < t1), 0]
    assert len(ticks) / (t1 - t0) >= 5000 * 0.999
    changes = np.array([at for at, _ in trace.force if t0 <= at < t1])
    assert np.all((changes - t0) % 200e-6 < 10e-6)  # each right after a render tick
    between = ((changes - t0) % 1e-3) > 100e-6
    assert between.sum() > 50
