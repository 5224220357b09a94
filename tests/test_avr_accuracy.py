"""Accuracy through the emulated firmware: the haptic loop on the host, the reference
sketch on simavr, the simulated mass-damper behind it.

The board latches the newest command at its tick, so the force commanded after
sample k acts over period k+1: the excitation reaches the plant one sample late
and the VE force one sample late (the sampled model with td = T, excitation
taken as applied). Its PWM quantises the force to 1/40 N and its encoder the
position to one count; both stay in these runs, as noise the estimators see.
"""

from __future__ import annotations

import numpy as np
import pytest

from labbench import records
from labbench.model import linear
from labbench.analysis.dataio import recording_from_arrays
from labbench.analysis.etfe import etfe
from labbench.analysis.identify import identify
from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.registry import make_protocol
from labbench.rig import Rig
from labbench.model.ve import Plant, VirtualEnvironment

pytestmark = pytest.mark.usefixtures("avr_toolchain")  # tests/conftest.py

RIG = Rig()
PLANT = Plant(RIG.nominal_mass_kg, RIG.nominal_damping_ns_m)
T = RIG.sample_time_s
SAFETY = SafetyConfig(force_limit_n=RIG.force_limit_n, force_rate_limit_n_per_s=1e9,
                      velocity_limit_m_s=1e3, position_limits_m=(-1e3, 1e3), energy_limit_j=1e3,
                      watchdog_s=1.0, enable_force_threshold_n=1e-12)


def through_board(ve: VirtualEnvironment, exc: np.ndarray, trace: bool = False):
    """The loop's record of ``exc`` under ``ve`` on the emulated board (and its trace)."""
    from labbench.sim_backend.avr_device import connect_avr_sim

    dev, board = connect_avr_sim(RIG, trace=trace)
    pages = []
    try:
        out = run_loop(dev, HapticLoop(ve, SAFETY), exc, pages.append)
    finally:
        dev.close()
    assert out.status == "completed", out
    data = records.concat_pages(pages)
    return (data, board.trace()) if trace else data


def applied(u: np.ndarray) -> np.ndarray:
    """What the board drives over each period: the command one sample before, as duty."""
    d = np.float32(u).astype(float) * 40.0
    q = np.clip(np.sign(d) * np.floor(np.abs(d) + 0.5), -255, 255) / 40.0
    return np.r_[0.0, q[:-1]]


def test_the_host_loop_closes_through_the_board_one_sample_late_quantised():
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=T)
    exc = np.random.default_rng(5).normal(0.0, 0.5, 1500)
    exc[0] = 0.0  # the enable gate opens at the first sample
    data, trace = through_board(ve, exc, trace=True)
    ticks = trace.sample_ticks()[data["seq"], 0]
    # Over each period the board drives the command sent after the previous sample.
    np.testing.assert_array_equal(trace.force_at(ticks + 50e-6), applied(data["command"]))
    measured = data["position"] / RIG.metres_per_count
    assert np.ptp(measured) > 100  # the handle moved
    x = trace.plant_positions(ticks, PLANT.m, PLANT.b) / RIG.metres_per_count
    assert np.max(np.abs(measured - x)) <= 1.0  # one count of encoder quantisation
    # ... and the loop rendered the spring-damper on those positions.
    assert np.corrcoef(data["command"] - data["excitation"], measured)[0, 1] < -0.5


@pytest.mark.slow
def test_etfe_through_the_firmware_matches_the_sampled_theory_with_td_one_sample():
    proto = make_protocol("etfe", duration_s=120.0, seed=11, td_s=0.0)
    exc = proto.excitation()
    exc[0] = 0.0  # the enable gate opens at the first sample
    data = through_board(proto.ve, exc)
    rec = recording_from_arrays(data["t"], np.r_[0.0, data["excitation"][:-1]], data["position"])
    est = etfe(rec)
    ve_td = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=T, td=T)
    w = np.asarray(est.w)
    band = (w >= 2.0) & (w <= 100.0)
    z = linear.z_sampled(PLANT, ve_td, w[band])
    rel = np.abs(np.asarray(est.Z)[band] - z) / np.abs(z)
    assert np.median(rel) <= 0.005, np.median(rel)


@pytest.mark.slow
def test_chirp_identification_through_the_firmware_within_one_percent():
    proto = make_protocol("chirp-id")
    exc = proto.excitation(PLANT)
    data = through_board(proto.ve, exc)
    rec = recording_from_arrays(data["t"], np.r_[0.0, data["command"][:-1]], data["position"])
    fit = identify(rec, model="auto", method="l2", hold="zoh")
    assert fit.m == pytest.approx(PLANT.m, rel=0.01)
    assert fit.b == pytest.approx(PLANT.b, rel=0.01)
