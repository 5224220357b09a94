"""The reference firmware (docs/arduino/labbench_encoder.ino) built for the ATmega328P and
run on simavr around the simulated plant, with the real SerialStream as host.

Truth comes from the harness (sim_backend/avr/harness.c): the count its encoder
pins showed when the sample tick was raised and when its interrupt ran, the force
the firmware's PWM and DIR pins applied, and when each frame went out. The plant is
integrated again here with ``labbench.theory.zoh_matrices`` from the forces the
firmware applied, independently of the harness's own closed form.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from labbench.drivers import serial_stream as ss
from labbench.rig import Rig
from labbench.sim_backend import avr_build
from labbench.theory import zoh_matrices

missing = avr_build.missing_tools()
pytestmark = pytest.mark.skipif(
    bool(missing), reason=f"AVR toolchain/simavr missing ({', '.join(missing)}): make avr-deps"
)

RIG = Rig()
MPC = RIG.metres_per_count
BYTE_S = 10 / 500_000  # one byte on a 500 kbit/s wire


def run(n: int, answer, **options):
    """n lock-step samples through the emulated board: (samples, commands, stats, trace)."""
    from labbench.sim_backend.avr_device import connect_avr_sim

    drv, board = connect_avr_sim(RIG, trace=True, **options)
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

    vec = np.array(trace.vec)  # one row per sample tick: tick k latches sample seq k
    counts = np.array([round(s.position_m / MPC) for s in samples])
    lo, hi = vec[seq, 2], vec[seq, 3]
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

    # The plant, integrated here from the forces the firmware applied, is where
    # the board's encoder says it is (one count: edges are timed within 4 us steps).
    Ad, Bd = None, None
    x = np.zeros(2)
    t_now, f_now, k_event = 0.0, 0.0, 0
    for j, s in enumerate(samples):
        t_tick = vec[s.seq, 0]
        while True:
            t_next = events[k_event][0] if k_event < len(events) else math.inf
            t_stop = min(t_next, t_tick)
            if t_stop > t_now:
                Ad, Bd = zoh_matrices(RIG.nominal_mass_kg, RIG.nominal_damping_ns_m, t_stop - t_now)
                x = Ad @ x + Bd * f_now
                t_now = t_stop
            if t_next <= t_tick:
                f_now = events[k_event][1]
                k_event += 1
            else:
                break
        assert abs(x[0] / MPC - counts[j]) <= 1.0


@pytest.mark.parametrize("cps", [30_000.0, -30_000.0])
def test_encoder_counts_exactly_on_a_driven_trajectory(cps):
    samples, _, counters, stats, trace = run(200, lambda k, s: 0.0, drive_cps=cps,
                                             drive_ms=(20.0, 150.0))
    vec = np.array(trace.vec)
    seq = np.array([s.seq for s in samples])
    counts = np.array([round(s.position_m / MPC) for s in samples])
    lo, hi = vec[seq, 2], vec[seq, 3]
    assert np.all((counts >= np.minimum(lo, hi)) & (counts <= np.maximum(lo, hi)))
    assert counts[-1] == stats["count"] == round(cps * 0.130)
    assert all(s.flags == 0 for s in samples)
