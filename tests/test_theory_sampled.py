"""The exact sampled-data model against a brute-force per-sample simulation of the loop.

The simulator below is the oracle: a plain loop written straight from the
definition in labbench.model.linear (ZOH plant, backward-difference velocity through a
first-order low-pass, VE force applied n samples later, exogenous force in
its own step). It shares only the ZOH matrices with the code under test.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq
from scipy.signal import dlsim

from labbench.model import linear
from labbench.errors import UserError
from labbench.model.ve import Plant, VirtualEnvironment
from labbench.model.linear import zoh_matrices


def simulate(plant: Plant, ve: VirtualEnvironment, f_exo: np.ndarray,
             x0: float = 0.0, v0: float = 0.0) -> np.ndarray:
    """x[k], position at the start of step k, for the exogenous force sequence f_exo."""
    Ad, Bd = zoh_matrices(plant.m, plant.b, ve.T)
    n = int(round(ve.td / ve.T))
    a = 0.0 if math.isinf(ve.w0) else math.exp(-ve.w0 * ve.T)
    x, xd, x_prev, v = x0, v0, x0, 0.0
    line = deque([0.0] * n)
    out = np.empty(len(f_exo))
    for k, fe in enumerate(f_exo):
        out[k] = x
        v = a * v + (1 - a) * (x - x_prev) / ve.T
        x_prev = x
        line.append(ve.K * x + ve.B * v)
        u = fe - line.popleft()
        x, xd = (Ad[0, 0] * x + Ad[0, 1] * xd + Bd[0] * u,
                 Ad[1, 0] * x + Ad[1, 1] * xd + Bd[1] * u)
    return out


def phasor(y: np.ndarray, w: float, T: float) -> complex:
    """Complex amplitude Y of y[k] = c + Re(Y e^{j w k T}) by least squares."""
    k = np.arange(len(y))
    M = np.column_stack([np.ones_like(y), np.cos(w * k * T), np.sin(w * k * T)])
    c, re, im = np.linalg.lstsq(M, y, rcond=None)[0]
    return complex(re, -im)


def simulated_z(plant, ve, w, n_settle, n_fit):
    """Z = F/(jw X) from the steady-state response to f_exo = sin(w k T)."""
    k = np.arange(n_settle + 2 * n_fit)
    f = np.sin(w * k * ve.T)
    x = simulate(plant, ve, f)
    z1 = phasor(f[-n_fit:], w, ve.T) / (1j * w * phasor(x[-n_fit:], w, ve.T))
    z0 = phasor(f[-2 * n_fit:-n_fit], w, ve.T) / (1j * w * phasor(x[-2 * n_fit:-n_fit], w, ve.T))
    assert abs(z1 - z0) < 1e-9 * abs(z1), "oracle: transient has not died out"
    return z1


CASES = [  # (plant, ve, samples to settle)
    (Plant(0.1, 0.5), VirtualEnvironment("spring", K=20, td=0.001), 14000),
    (Plant(0.1, 0.1), VirtualEnvironment("damper", B=1, w0=200, td=0.002), 4000),
    (Plant(0.094, 0.1), VirtualEnvironment("spring-damper", K=50, B=1, w0=125, td=0.005), 8000),
    (Plant(0.2, 2.0), VirtualEnvironment("none"), 8000),
]


@pytest.mark.parametrize("plant,ve,n_settle", CASES, ids=[c[1].kind for c in CASES])
def test_sampled_z_matches_brute_force_sine_response(plant, ve, n_settle):
    for w in (3.0, 23.0, 130.0, 900.0, 2500.0):
        n_fit = max(2000, int(4 * 2 * math.pi / (w * ve.T)))
        expected = simulated_z(plant, ve, w, n_settle, n_fit)
        got = linear.z_sampled(plant, ve, np.array([w]))[0]
        assert abs(got - expected) <= 1e-6 * abs(expected), (w, got, expected)


@pytest.mark.parametrize("plant,ve,n_settle", CASES, ids=[c[1].kind for c in CASES])
def test_closed_loop_state_space_is_the_same_loop(plant, ve, n_settle):
    loop = linear.closed_loop(plant, ve)
    f = np.random.default_rng(1).standard_normal(3000)
    _, y, _ = dlsim(loop.as_dlti(), f)
    x = simulate(plant, ve, f)
    assert np.max(np.abs(y[:, 0] - x)) <= 1e-9 * np.max(np.abs(x))
    # its frequency response is the closed-form z_sampled
    w = np.array([2.0, 40.0, 700.0])
    I = np.eye(loop.A.shape[0])
    G = np.array([(loop.C @ np.linalg.solve(np.exp(1j * wi * ve.T) * I - loop.A, loop.B))[0, 0]
                  for wi in w])
    np.testing.assert_allclose(1 / (1j * w * G), linear.z_sampled(plant, ve, w), rtol=1e-9)


def growth(plant, ve, n, x0=1e-3, v0=1e-2) -> float:
    """max |x[k] - x[k-1]| over the last 10 % of a free response / over the first 10 %.

    Differences, so that a constant position offset (an equilibrium without a
    spring) counts as settled.
    """
    dx = np.abs(np.diff(simulate(plant, ve, np.zeros(n), x0=x0, v0=v0)))
    tenth = n // 10
    return dx[-tenth:].max() / dx[:tenth].max()


SPRING = Plant(0.1, 0.1)


@pytest.mark.parametrize("td_samples", range(6))
def test_k_max_spring_against_unit_circle_crossing_and_simulation(td_samples):
    ve = VirtualEnvironment("spring", K=10, td=td_samples * 0.001)
    km = linear.k_max(SPRING, ve)
    # independent: the smallest K > 0 for which 1 + z^-n K P(z) = 0 has a root on |z| = 1
    Ad, Bd = zoh_matrices(SPRING.m, SPRING.b, ve.T)

    def k_on_circle(th):
        z = np.exp(1j * th)
        P = np.linalg.solve(z * np.eye(2) - Ad, Bd)[0]
        return -z**td_samples / P

    th = np.linspace(1e-4, math.pi, 20001)
    im = np.array([k_on_circle(t).imag for t in th])
    roots = [brentq(lambda t: k_on_circle(t).imag, th[i], th[i + 1])
             for i in np.flatnonzero(np.sign(im[:-1]) != np.sign(im[1:]))]
    crossings = [k_on_circle(t).real for t in roots] + [k_on_circle(math.pi).real]
    k_cross = min(k for k in crossings if k > 0)
    assert km == pytest.approx(k_cross, rel=1e-3)
    # and the paper's approximation b / (T/2 + td) is within 1 % for this light device
    assert km == pytest.approx(linear.k_max_approx(SPRING, ve), rel=0.01)
    # verdicts either side of K_max, by simulated growth / decay
    for factor, stable in ((0.9, True), (1.1, False)):
        v = ve.with_(K=factor * km)
        assert linear.stability(SPRING, v).stable is stable
        g = growth(SPRING, v, 40000)
        assert (g < 0.5) if stable else (g > 2.0), (factor, g)


VERDICT_CASES = [
    (Plant(0.094, 0.1), VirtualEnvironment("spring-damper", K=50, B=1, w0=125, td=0.005), True),
    (Plant(0.094, 0.1), VirtualEnvironment("spring-damper", K=400, B=1, w0=125, td=0.002), False),
    (Plant(0.1, 0.1), VirtualEnvironment("damper", B=1, w0=1000, td=0.002), True),
    (Plant(0.1, 0.1), VirtualEnvironment("damper", B=60, w0=1000, td=0.002), False),
    (Plant(0.1, 0.1), VirtualEnvironment("none"), True),
]


@pytest.mark.parametrize("plant,ve,stable", VERDICT_CASES)
def test_stability_verdict_matches_simulated_growth(plant, ve, stable):
    st = linear.stability(plant, ve)
    assert st.stable is stable
    g = growth(plant, ve, 20000 if stable else 3000)  # short enough not to overflow
    assert (g < 1e-3) if stable else (g > 10.0), g
    # the spectral radius predicts the growth rate of the slowest mode
    if not stable:
        assert st.spectral_radius > 1.0


def test_damper_offset_mode_is_not_called_unstable():
    plant, ve = Plant(0.1, 0.1), VirtualEnvironment("damper", B=1, w0=200)
    A = linear.closed_loop(plant, ve).A
    assert np.max(np.abs(np.linalg.eigvals(A))) == pytest.approx(1.0, abs=1e-12)
    st = linear.stability(plant, ve)
    assert st.stable and st.spectral_radius < 0.999
    x = simulate(plant, ve, np.zeros(5000), x0=0.0, v0=0.05)
    assert abs(x[-1] - x[-2]) < 1e-12 and abs(x[-1]) > 1e-4  # settles at an offset


def test_k_max_spring_damper_brackets_the_simulated_boundary():
    plant = Plant(0.094, 0.1)
    ve = VirtualEnvironment("spring-damper", K=50, B=1, w0=125, td=0.002)
    km = linear.k_max(plant, ve)
    assert linear.stability(plant, ve.with_(K=km * 0.999)).stable
    assert not linear.stability(plant, ve.with_(K=km * 1.001)).stable
    assert growth(plant, ve.with_(K=km * 1.05), 12000) > 2.0
    assert growth(plant, ve.with_(K=km * 0.95), 12000) < 0.5


def test_sampled_ed_drop_is_k_td():
    """The exogenous force shares the hold with the VE force, so the ETFE's
    low-frequency ED loses K td (not K (T/2 + td)); checked on the model."""
    plant = Plant(0.094, 0.1)
    for td in (0.0, 0.002, 0.005):
        ve = VirtualEnvironment("spring-damper", K=50, B=1, w0=125, td=td)
        eff = linear.delay_effects(plant, ve)
        assert eff["ED_drop_sampled"] == pytest.approx(50 * td, abs=1e-9)
        w = np.array([1e-2])
        assert linear.z_sampled(plant, ve, w)[0].real == pytest.approx(1.1 - 50 * td, abs=1e-6)


def test_fractional_delay_is_a_clear_error():
    ve = VirtualEnvironment("spring", K=10, td=0.0015)
    for f in (lambda: linear.z_sampled(SPRING, ve, [1.0]), lambda: linear.closed_loop(SPRING, ve),
              lambda: linear.theory_curve(SPRING, ve, [1.0], "sampled")):
        with pytest.raises(UserError, match="whole number of samples"):
            f()
    assert linear.delay_effects(SPRING, ve)["ED_drop_sampled"] is None
    assert np.isfinite(linear.z_paper(SPRING, ve, [1.0])).all()


def test_undamped_device_cannot_render_a_stable_spring():
    """b = 0: b > K (T/2 + td) fails for every K > 0, and so does the sampled loop."""
    plant = Plant(0.1, 0.0)
    ve = VirtualEnvironment("spring", K=10)
    assert linear.k_max(plant, ve) == 0.0
    assert not linear.stability(plant, ve).stable
    assert growth(plant, ve, 20000) > 1.3  # rho^18000 = 1.57
    # open loop, no damping: a marginal double integrator, not called stable
    st = linear.stability(plant, VirtualEnvironment())
    assert not st.stable and st.spectral_radius == pytest.approx(1.0, abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(m=st.floats(0.01, 2.0), b=st.floats(0.0, 5.0), K=st.floats(0.0, 500.0),
       B=st.floats(0.0, 5.0), w0=st.one_of(st.just(math.inf), st.floats(10.0, 5000.0)),
       n=st.integers(0, 6), T=st.sampled_from([1e-4, 5e-4, 1e-3, 4e-3]))
def test_closed_form_equals_state_space_for_any_loop(m, b, K, B, w0, n, T):
    """Two derivations of the same loop: z_sampled's transfer-function algebra and
    closed_loop's state matrices (whose time response matches the simulator above)."""
    plant = Plant(m, b)
    ve = VirtualEnvironment("spring-damper", K=K, B=B, w0=w0, T=T, td=n * T)
    loop = linear.closed_loop(plant, ve)
    w = np.array([0.3, 7.0, 90.0, 0.9 * math.pi / T])
    I = np.eye(loop.A.shape[0])
    G = np.array([(loop.C @ np.linalg.solve(np.exp(1j * wi * T) * I - loop.A, loop.B))[0, 0]
                  for wi in w])
    np.testing.assert_allclose(linear.z_sampled(plant, ve, w), 1 / (1j * w * G), rtol=1e-7)
