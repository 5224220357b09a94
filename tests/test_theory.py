"""The paper's continuous model (eq. 2) and its claims, as numbers."""
from __future__ import annotations

import math

import numpy as np
import pytest

from labbench.model import linear
from labbench.model.effective import effective_impedances, measured_wb_star, measured_ws_star
from labbench.model.ve import Plant, VirtualEnvironment

W = np.logspace(-1, 4, 400)
PAPER = Plant(0.1, 0.1)  # device of the paper's Figures 4-8


def d(w, ve):
    return np.exp(-1j * w * (ve.T / 2 + ve.td))  # eq. 8


# eqs. 4, 6, 7 transcribed from the paper, to compare with the general eq. 2
def eq4(p, ve, w):
    s = 1j * w
    return (p.m * s**2 + p.b * s + ve.K * d(w, ve)) / s


def eq6(p, ve, w):
    s, w0 = 1j * w, ve.w0
    return (p.m * s**2 + (p.m * w0 + p.b) * s + (p.b + ve.B * d(w, ve)) * w0) / (s + w0)


def eq7(p, ve, w):
    s, w0, dd = 1j * w, ve.w0, d(w, ve)
    num = p.m * s**3 + (p.m * w0 + p.b) * s**2 + (p.b * w0 + (ve.B * w0 + ve.K) * dd) * s \
        + ve.K * w0 * dd
    return num / (s * (s + w0))


@pytest.mark.parametrize("td", [0.0, 0.002, 0.0057])
@pytest.mark.parametrize("kind,eq", [("spring", eq4), ("damper", eq6), ("spring-damper", eq7)])
def test_eqs_4_6_7_equal_eq_2(kind, eq, td):
    ve = VirtualEnvironment(kind, K=50, B=1, w0=125, td=td)
    np.testing.assert_allclose(linear.z_paper(PAPER, ve, W), eq(PAPER, ve, W), rtol=1e-12)


def test_open_loop_and_unfiltered_damper():
    np.testing.assert_allclose(linear.z_paper(PAPER, VirtualEnvironment(), W),
                               PAPER.m * 1j * W + PAPER.b, rtol=1e-14)
    ve = VirtualEnvironment("damper", B=1, td=0.001)  # no filter: Z = m s + b + B d
    np.testing.assert_allclose(linear.z_paper(PAPER, ve, W),
                               PAPER.m * 1j * W + PAPER.b + d(W, ve), rtol=1e-12)


def test_figure_3_sample_system():
    """Eq. 1, Z = (s^2 + 20 s + 100) / (100 s): ED = 0.2, ES = 1 - w^2/100 below
    w = 10, EM = 0.01 - 1/w^2 above, no jerk or integral feedback."""
    s = 1j * W
    eff = effective_impedances(W, (s**2 + 20 * s + 100) / (100 * s))
    np.testing.assert_allclose(eff.ED, 0.2, rtol=1e-12)
    lo, hi = W < 10, W > 10
    np.testing.assert_allclose(eff.ES[lo], 1 - W[lo] ** 2 / 100, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(eff.EM[hi], 0.01 - 1 / W[hi] ** 2, rtol=1e-9, atol=1e-12)
    assert (eff.ES[lo] > 0).all() and (eff.EM[hi] > 0).all()
    assert not eff.EJF.any() and not eff.EIF.any()


DELAYS = [0.0, 0.001, 0.002, 0.005]


@pytest.mark.parametrize("td", DELAYS)
def test_spring_stiffness_below_ws_and_mass_above(td):
    """ES = K cos(w tau) - m w^2 for eq. 4: within 1.1 % of K at w <= ws*/10;
    EM = m - K cos(w tau)/w^2 within 1.1 % of m at w >= 10 ws*."""
    ve = VirtualEnvironment("spring", K=10, td=td)
    ws = linear.predicted_ws_star(PAPER, ve)
    assert ws == pytest.approx(10.0)
    eff = effective_impedances(W, linear.z_paper(PAPER, ve, W))
    low, high = W <= ws / 10, W >= 10 * ws
    assert np.all(np.abs(eff.ES[low] / ve.K - 1) < 0.011)
    assert np.all(np.abs(eff.EM[high] / PAPER.m - 1) < 0.011)
    # the stiffness bandwidth read off the curve is ws* (delay shifts it by < 1 %)
    assert measured_ws_star(W, eff.ES) == pytest.approx(ws, rel=0.01)


@pytest.mark.parametrize("td", [0.0, 0.002, 0.005])
def test_spring_damper_figure_8_claims(td):
    """K = 50, B = 1, w0 = 125: ES ~ K below ws*, ED ~ b + B - K tau below w0,
    EM -> m well above ws* and w0."""
    ve = VirtualEnvironment("spring-damper", K=50, B=1, w0=125, td=td)
    eff = effective_impedances(W, linear.z_paper(PAPER, ve, W))
    ws = linear.predicted_ws_star(PAPER, ve)
    low = W <= ws / 10
    assert np.all(np.abs(eff.ES[low] / ve.K - 1) < 0.02)
    assert np.all(np.abs(eff.EM[W >= 10 * ve.w0] / PAPER.m - 1) < 0.02)
    ed_low = PAPER.b + ve.B - ve.K * ve.delay
    assert np.all(np.abs(eff.ED[W <= ve.w0 / 100] - ed_low) < 1e-3 * ed_low)
    de = linear.delay_effects(PAPER, ve)
    assert de["ED_drop_paper"] == pytest.approx(ve.K * ve.delay, rel=1e-9)
    assert de["K_tau"] == pytest.approx(ve.K * (ve.T / 2 + td))


def test_damping_bandwidth_is_w0():
    """Damper with a negligible delay: ED = b + B w0^2/(w^2 + w0^2), half-way at w0."""
    ve = VirtualEnvironment("damper", B=1, w0=300, T=1e-7)
    eff = effective_impedances(W, linear.z_paper(PAPER, ve, W))
    assert linear.predicted_wb_star(ve) == 300
    assert measured_wb_star(W, eff.ED, PAPER.b) == pytest.approx(300, rel=2e-3)
    assert linear.predicted_wb_star(VirtualEnvironment("damper", B=1)) is None
    assert linear.predicted_wb_star(VirtualEnvironment("spring", K=1)) is None
    assert linear.predicted_ws_star(PAPER, ve) is None


@pytest.mark.parametrize("td", DELAYS)
def test_damper_em_drop_is_b_tau(td):
    """w0 >> (b + B)/m: EM at low frequency is m - B/w0 - B (T/2 + td)."""
    ve = VirtualEnvironment("damper", B=1, w0=2000, td=td)
    de = linear.delay_effects(PAPER, ve)
    assert de["EM_nodelay"] == pytest.approx(PAPER.m - 1 / 2000)
    assert de["EM_drop_paper"] == pytest.approx(ve.B * ve.delay, rel=1e-9)
    w = np.array([0.05])
    em = linear.z_paper(PAPER, ve, w).imag / w
    assert em[0] == pytest.approx(PAPER.m - 1 / 2000 - ve.B * ve.delay, rel=1e-6)


@pytest.mark.parametrize("td", DELAYS)
def test_negative_ed_exactly_when_b_below_k_tau(td):
    ve = VirtualEnvironment("spring", K=1, td=td)
    boundary = PAPER.b / ve.delay
    assert linear.k_max_approx(PAPER, ve) == pytest.approx(boundary)
    for factor in (0.99, 1.01):
        v = ve.with_(K=factor * boundary)
        w = np.array([1e-3 * math.sqrt(v.K / PAPER.m)])
        ed = linear.z_paper(PAPER, v, w).real[0]
        assert (ed < 0) == (factor > 1), (factor, ed)
        assert (linear.delay_effects(PAPER, v)["ED_low_paper"] < 0) == (factor > 1)


def test_k_max_approx_spring_damper_and_kinds_without_spring():
    ve = VirtualEnvironment("spring-damper", K=50, B=1, w0=125, td=0.002)
    assert linear.k_max_approx(PAPER, ve) == pytest.approx((0.1 + 1) / 0.0025)
    damper = VirtualEnvironment("damper", B=1)
    assert linear.k_max(PAPER, damper) is None and linear.k_max_approx(PAPER, damper) is None
    assert linear.delay_effects(PAPER, VirtualEnvironment()) == {"tau": 0.0005}


def test_theory_curve_dispatch():
    ve = VirtualEnvironment("spring", K=10, td=0.002)
    np.testing.assert_array_equal(linear.theory_curve(PAPER, ve, W), linear.z_paper(PAPER, ve, W))
    np.testing.assert_array_equal(linear.theory_curve(PAPER, ve, W, "sampled"),
                                  linear.z_sampled(PAPER, ve, W))
    with pytest.raises(ValueError):
        linear.theory_curve(PAPER, ve, W, "exact")


@pytest.mark.parametrize("T", [1e-3, 1e-4])
def test_sampled_model_tends_to_paper_model_times_half_sample_advance(T):
    """Z_sampled ~ e^{jwT/2} Z_paper well below the Nyquist rate (both forces
    pass through the same hold); the relative gap stays below (wT)^2."""
    ve = VirtualEnvironment("spring-damper", K=50, B=1, w0=125, td=0.002, T=T)
    w = np.array([1.0, 10.0, 100.0, 1000.0])
    w = w[w * T < 0.5]
    ratio = linear.z_sampled(PAPER, ve, w) / (np.exp(1j * w * T / 2) * linear.z_paper(PAPER, ve, w))
    assert np.all(np.abs(ratio - 1) < (w * T) ** 2)


def test_paper_figure_draws_measured_points_with_bands(tmp_path, monkeypatch):
    """paper_figure: 5 panels, one line per curve plus marks, 95 % bands on |Z|, ES, ED, EM."""
    from matplotlib.figure import Figure

    from labbench.errors import UserError
    from labbench.readout.figures import Curve, paper_figure

    drawn = []
    save = Figure.savefig

    def capture(fig, path, **kw):
        drawn.append(fig)
        save(fig, path, **kw)

    monkeypatch.setattr(Figure, "savefig", capture)
    ve = VirtualEnvironment("spring-damper", K=50, B=1, w0=125)
    Z = linear.z_paper(PAPER, ve, W)
    curves = [Curve("theory", W, Z),
              Curve("measured", W, Z * 1.01, style="points", Z_err=0.05 * abs(Z))]
    marks = {"ws*": 22.4, "wb*": 125, "none": None}
    paper_figure(curves, tmp_path / "f.png", title="t", marks=marks)
    assert (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"
    axes = drawn[0].axes
    assert len(axes) == 5
    for ax in axes:
        assert len(ax.lines) == 2 + 2  # two curves, two marks
    mag, phase = axes[0], axes[1]
    assert len(mag.collections) == 1 and len(phase.collections) == 0
    assert all(len(ax.collections) == 1 for ax in axes[2:])
    np.testing.assert_allclose(mag.lines[0].get_ydata(), 20 * np.log10(abs(Z)))
    with pytest.raises(UserError):
        paper_figure(curves, tmp_path / "f.jpg")
    with pytest.raises(ValueError):
        paper_figure([Curve("x", W, Z, style="dots")], tmp_path / "g.png")
