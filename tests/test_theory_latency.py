"""The sampled model with a fractional actuator latency against a brute-force simulation."""
import math

import numpy as np
import pytest
from scipy import signal

from labbench.model import linear
from labbench.model.ve import Plant, VirtualEnvironment

PLANT = Plant(0.094, 0.10)
T = 0.001


def _brute_force(plant, ve, f_exo, latency, substeps=40):
    """The loop in time on a grid of T/substeps: the controller samples x[k], computes the VE
    force (backward difference, low-pass, K x + B v), sends u[k] = f_exo[k] - f[k - n]; the
    actuator applies u[k] from kT + latency to (k + 1) T + latency. latency must fall on the grid."""
    h = T / substeps
    shift = round(latency / h)
    assert abs(shift * h - latency) < 1e-12
    Ad, Bd = linear.zoh_matrices(plant.m, plant.b, h)
    n, a = ve.delay_samples, ve.filter_pole
    state = np.zeros(2)
    x_prev = v_prev = 0.0
    f_line = [0.0] * (n + 1)
    u_sent = []
    xs = []
    for k, fe in enumerate(f_exo):
        x = state[0]
        xs.append(x)
        v = a * v_prev + (1 - a) * (x - x_prev) / T
        f_line = [ve.K * x + ve.B * v] + f_line[:-1]
        u_sent.append(fe - f_line[n])
        x_prev, v_prev = x, v
        for i in range(substeps):  # step k on the fine grid: command index (k*substeps + i - shift) // substeps
            j = (k * substeps + i - shift) // substeps
            u = u_sent[j] if j >= 0 else 0.0
            state = Ad @ state + Bd * u
    return np.array(xs)


@pytest.mark.parametrize("latency_samples", [0.0, 0.35, 1.0, 1.5, 3.0, 2.725])
@pytest.mark.parametrize("ve", [VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, td=0.002),
                                VirtualEnvironment("damper", B=0.5, w0=300.0)])
def test_closed_loop_with_latency_equals_brute_force(ve, latency_samples):
    f = np.random.default_rng(1).standard_normal(400)
    latency = latency_samples * T
    _, y, _ = signal.dlsim(linear.closed_loop(PLANT, ve, latency).as_dlti(), f)
    ref = _brute_force(PLANT, ve, f, latency)
    assert np.max(np.abs(y[:, 0] - ref)) < 1e-9 * np.max(np.abs(ref))


@pytest.mark.parametrize("latency_samples", [0.0, 0.35, 1.5, 3.0])
def test_z_sampled_with_latency_is_the_state_space_response(latency_samples):
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, td=0.001)
    loop = linear.closed_loop(PLANT, ve, latency_samples * T)
    w = np.geomspace(1.0, 0.9 * math.pi / T, 25)
    z = np.exp(1j * w * T)
    H = np.array([(loop.C @ np.linalg.solve(zk * np.eye(len(loop.A)) - loop.A, loop.B))[0, 0] for zk in z])
    Z = linear.z_sampled(PLANT, ve, w, latency_samples * T)
    assert np.allclose(Z, 1 / (1j * w * H), rtol=1e-8)


def test_latency_is_continuous_across_whole_samples():
    ve = VirtualEnvironment("spring", K=30.0)
    w = np.array([5.0, 50.0, 500.0])
    below = linear.z_sampled(PLANT, ve, w, (2 - 1e-7) * T)
    at = linear.z_sampled(PLANT, ve, w, 2 * T)
    assert np.allclose(below, at, rtol=1e-5)


def test_latency_lowers_k_max_like_extra_td():
    # the exogenous path does not enter the characteristic equation: a latency of whole
    # samples on the command is, for stability, the same as that much more td
    ve = VirtualEnvironment("spring", K=10.0, td=0.001)
    k_lat = linear.k_max(PLANT, ve, latency=2 * T)
    k_td = linear.k_max(PLANT, ve.with_(td=0.003))
    assert k_lat == pytest.approx(k_td, rel=1e-3)
    assert linear.k_max(PLANT, ve, latency=1.5 * T) < linear.k_max(PLANT, ve, latency=1.0 * T)


@pytest.mark.parametrize("whole, fraction", [(0, 0.5), (1, 0.5), (3, 0.0), (2, 0.25)])
def test_simulator_latency_is_the_model_latency(whole, fraction):
    from labbench.rig import Rig
    from labbench.sim_backend.sim_device import open_sim

    f = np.random.default_rng(2).standard_normal(300)
    dev = open_sim(Rig(), extra_delay_samples=whole, extra_delay_fraction=fraction)
    dev.enable()
    xs = [dev.read_raw(1.0)[2]]
    for u in f[:-1]:
        dev.command(u)
        xs.append(dev.read_raw(1.0)[2])
    loop = linear.closed_loop(PLANT, VirtualEnvironment("none"), (whole + fraction) * T)
    _, y, _ = signal.dlsim(loop.as_dlti(), f)
    assert np.max(np.abs(np.array(xs) - y[:, 0])) < 1e-10 * np.max(np.abs(y))


def test_simulator_fractional_latency_must_be_below_one_sample():
    # (with friction it is accepted: tests/test_sim_device.py checks it against an ODE)
    from labbench.errors import UserError
    from labbench.rig import Rig
    from labbench.sim_backend.sim_device import open_sim

    with pytest.raises(UserError, match="extra_delay_fraction"):
        open_sim(Rig(), extra_delay_fraction=1.0)


@pytest.mark.parametrize("m, b, tau", [(0.094, 0.1, 1e-3), (0.094, 0.0, 1e-3), (0.005, 40.0, 1e-3),
                                       (25.0, 40.0, 0.01), (0.094, 0.1, 3e-7), (1.0, 9.9, 1e-3)])
def test_closed_form_zoh_is_the_matrix_exponential(m, b, tau):
    from scipy.linalg import expm

    M = np.zeros((3, 3))
    M[0, 1], M[1, 1], M[1, 2] = 1.0, -b / m, 1.0 / m
    E = expm(M * tau)
    Ad, Bd = linear.zoh_matrices(m, b, tau)
    assert np.allclose(Ad, E[:2, :2], rtol=1e-13, atol=0)
    assert np.allclose(Bd, E[:2, 2], rtol=1e-12, atol=0)
