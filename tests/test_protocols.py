"""Protocols: excitation signals, validated configs, the stability precheck, and each
protocol on the simulator against known truth (the simulated plant, the exact sampled theory)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from labbench.readout import wording
from labbench.model import linear
from labbench.errors import UserError
from labbench.readout.numfmt import frequency_text
from labbench.rig import Rig, rig_from_dict
from labbench.runner import run
from labbench.model.ve import Plant, VirtualEnvironment
from labbench.protocol import precheck
from labbench.protocols import excitation
from labbench.registry import make_protocol, protocol_class, protocol_names
from labbench.protocols.stability_probe import growth_rate
from labbench.sim_backend.sim_device import open_sim

T = 0.001
TRUTH = Plant(0.094, 0.10)  # the simulator's default plant (labbench.sim_backend.sim_device)


# ---------------------------------------------------------------- excitation

@pytest.mark.parametrize("sweep", ["log", "linear"])
def test_chirp_instantaneous_frequency_is_the_phase_derivative(sweep):
    n = 20000
    phase, f = excitation.chirp_phase(n, T, 0.1, 25.0, sweep)
    assert f[0] == pytest.approx(0.1)
    assert f[-1] == pytest.approx(25.0, rel=2e-3)  # last sample is one T short of D
    dphase = np.diff(phase) / T / (2 * np.pi)  # mid-point frequency
    mid = 0.5 * (f[1:] + f[:-1])
    assert np.max(np.abs(dphase - mid) / mid) < 1e-3


def test_displacement_envelope_keeps_the_free_plant_amplitude():
    f = np.array([0.1, 1.0, 5.0, 25.0])
    amp = excitation.displacement_envelope(f, 0.094, 0.1, 0.02, 1.0)
    w = 2 * np.pi * f
    x = amp / (w * np.abs(0.1 + 1j * w * 0.094))  # |X/F| of m x'' + b x' = f
    assert np.all(x <= 0.02 * (1 + 1e-12))
    assert amp[-1] == 1.0 and x[0] == pytest.approx(0.02)


def test_white_noise_std_band_and_seed():
    n = 2**16
    u = excitation.white_noise(n, T, 0.7, (5.0, 50.0), seed=3)
    assert u.std() == pytest.approx(0.7, rel=1e-12)
    U = np.abs(np.fft.rfft(u)) ** 2
    f = np.fft.rfftfreq(n, T)
    outside = U[(f < 5) | (f > 50)].sum() / U.sum()
    assert outside < 1e-20
    assert np.array_equal(u, excitation.white_noise(n, T, 0.7, (5.0, 50.0), seed=3))
    assert not np.array_equal(u, excitation.white_noise(n, T, 0.7, (5.0, 50.0), seed=4))


def test_pulse_shape():
    p = excitation.pulse(1000, T, 0.5, 0.02, at_s=0.05)
    assert np.count_nonzero(p) == 20 and np.flatnonzero(p)[0] == 50
    assert p.max() == pytest.approx(0.5, rel=0.01)


# ---------------------------------------------------------------- configs

@pytest.mark.parametrize("name,options,words", [
    ("etfe", {"K": -1.0}, "K must be >= 0"),
    ("etfe", {"std_n": "x"}, "std_n must be a number"),
    ("etfe", {"td_s": 0.0015}, "whole number of samples"),
    ("etfe", {"band_hi_hz": 600.0}, "band_hi_hz must be <= 500"),
    ("etfe", {"band_lo_hz": 50.0, "band_hi_hz": 10.0}, "band_lo_hz"),
    ("etfe", {"ve": "wall"}, "ve must be one of"),
    ("etfe", {"seed": -2}, "seed must be >= 0"),
    ("etfe", {"duration_s": math.nan}, "duration_s must be finite"),
    ("etfe", {"duration_s": 1e9}, "duration_s must be <= 1800 s"),
    ("etfe", {"bogus": 1}, "unknown option(s) for etfe: bogus"),
    ("chirp-id", {"f0_hz": 30.0}, "must be below f1_hz"),
    ("chirp-id", {"f1_hz": 600.0}, "Nyquist"),
    ("chirp-id", {"sweep": "cubic"}, "sweep must be one of"),
    ("chirp-id", {"methods": ("l3",)}, "methods must be one of"),
    ("chirp-id", {"methods": 5}, "methods must be a list"),
    ("chirp-id", {"methods": ()}, "at least one"),
    ("chirp-id", {"duration_s": 5.0}, "at least one period"),
    ("stability", {"variable": "B"}, "variable must be one of"),
    ("stability", {"ratio": 1.0}, "ratio must be > 1"),
    ("stability", {"K": 50.0, "K_stop": 40.0}, "K_stop"),
    ("stability", {"ve": "damper"}, "ve must be one of"),
])
def test_bad_option_is_one_user_error_naming_the_field(name, options, words):
    with pytest.raises(UserError) as e:
        make_protocol(name, **options)
    assert words in str(e.value)
    assert "\n" not in str(e.value)


def test_unknown_protocol():
    with pytest.raises(UserError, match="unknown protocol"):
        make_protocol("sweep")


def test_configs_serialise_with_their_name():
    for name in protocol_names():
        d = make_protocol(name).describe()
        assert d["protocol"] == name
        assert all(not isinstance(v, (tuple, np.ndarray)) for v in d.values())


def test_etfe_seed_is_drawn_and_recorded_when_absent():
    p = make_protocol("etfe")
    assert isinstance(p.seed, int)
    assert make_protocol("etfe", seed=7).seed == 7


# ---------------------------------------------------------------- precheck

def test_precheck_refuses_unstable_ve_with_numbers():
    km = linear.k_max(TRUTH, VirtualEnvironment("spring", K=1.0, td=0.002))
    p = make_protocol("etfe", ve="spring", K=1.2 * km, B=0.0, w0_rad_s=None, td_s=0.002)
    with pytest.raises(UserError) as e:
        precheck(p, TRUTH)
    msg = str(e.value)
    assert "refusing unstable spring" in msg and f"{km:.4g}" in msg and "spectral radius" in msg


def test_precheck_passes_stable_ve_and_reports_margin():
    p = make_protocol("etfe")
    rep = precheck(p, TRUTH)
    (c,) = rep["checks"]
    assert rep["stable"] and c["stable"] and c["spectral_radius"] < 1
    assert c["k_max"] == pytest.approx(linear.k_max(TRUTH, p.ve))


def test_precheck_override_lets_unstable_through():
    p = make_protocol("etfe", ve="spring", K=400.0, B=0.0, w0_rad_s=None, allow_unstable=True)
    rep = precheck(p, TRUTH)
    assert rep["stable"] is False


def test_precheck_uses_the_given_plant():
    # Stable for a damped device, unstable for an undamped one (b < K (T/2 + td)).
    p = make_protocol("etfe", ve="spring", K=30.0, B=0.0, w0_rad_s=None, td_s=0.002)
    precheck(p, Plant(0.094, 0.2))
    with pytest.raises(UserError):
        precheck(p, Plant(0.094, 0.02))


def test_chirp_plan_that_leaves_the_window_is_refused():
    p = make_protocol("chirp-id", x_max_m=0.08)
    with pytest.raises(UserError, match="outside the rig's window"):
        precheck(p, TRUTH, Rig())
    rep = precheck(make_protocol("chirp-id"), TRUTH, Rig())
    lo, hi = rep["plan"]["predicted_x_range_m"]
    assert -0.1 < lo < hi < 0.1


def test_probe_ceiling_is_capped_at_max_over_times_exact():
    with pytest.raises(UserError, match="above 1.5 x the exact"):
        precheck(make_protocol("stability", K=20.0, K_stop=1000.0), TRUTH, Rig())


# ---------------------------------------------------------------- growth detector

@pytest.mark.parametrize("sigma", [-2.0, -0.1, 0.05, 1.5])
@pytest.mark.parametrize("offset", [0.0, 3e-4])
def test_growth_rate_of_an_exact_exponential_sinusoid(sigma, offset):
    t = np.arange(0, 3.0, T)
    x = offset + 1e-3 * np.exp(sigma * t) * np.sin(40 * t + 0.3)
    assert growth_rate(t, x) == pytest.approx(sigma, abs=2e-3)


# ---------------------------------------------------------------- on the simulator

def _run(name, **options):
    records = []
    res = run(open_sim(Rig()), make_protocol(name, **options), [records.append], rig=Rig())
    return res, records


def test_chirp_id_on_sim_recovers_the_simulated_plant_l2_and_l1():
    res, _ = _run("chirp-id")
    assert res.status == "success"
    for method in ("l2", "l1"):
        fit = res.results["identification"][method]
        assert fit["m"] == pytest.approx(TRUTH.m, rel=0.02)
        assert fit["b"] == pytest.approx(TRUTH.b, rel=0.02)
    assert res.results["m"] == res.results["identification"]["l2"]["m"]


def test_chirp_id_on_a_quantised_noisy_sim_stays_within_2_percent():
    rig = rig_from_dict({"sim": {"quantize": True, "force_noise_n": 0.002}})
    res = run(open_sim(rig, seed=4), make_protocol("chirp-id", methods=("l2",)), [], rig=rig)
    fit = res.results["identification"]["l2"]
    assert fit["m"] == pytest.approx(TRUTH.m, rel=0.02)
    assert fit["b"] == pytest.approx(TRUTH.b, rel=0.02)


def test_etfe_on_sim_matches_exact_sampled_theory_within_5_percent():
    res, _ = _run("etfe", seed=11)
    assert res.status == "success", res.reason
    r = res.results
    w = np.asarray(r["etfe"]["w"])
    Z = np.asarray(r["etfe"]["Z_re"]) + 1j * np.asarray(r["etfe"]["Z_im"])
    band = (w >= 2) & (w <= 100)
    ve = VirtualEnvironment("spring-damper", 50.0, 1.0, 125.0, T, 0.0)
    z_true = linear.z_sampled(TRUTH, ve, w[band])  # truth computed here, not read from results
    rel = np.abs(Z[band] - z_true) / np.abs(z_true)
    assert band.sum() > 20
    assert rel.max() < 0.05
    dev = r["deviation_vs_sampled"]
    assert dev["max_rel"] == pytest.approx(rel.max())
    # where the max lies and the band there, so a reader can weigh it against its noise
    i = int(np.argmax(rel))
    assert dev["max_rad_s"] == pytest.approx(w[band][i])
    band_rel = np.asarray(r["etfe"]["Z_err"])[band][i] / abs(z_true[i])
    assert dev["max_band_rel"] == pytest.approx(band_rel)
    row = dict(wording.of_results("etfe", r, {}).rows)["|Z - Z_theory| / |Z_theory|"]
    assert f"at {frequency_text(w[band][i])} (95 % band there {100 * band_rel:.2g} %)" in row, row


@pytest.mark.parametrize("td_s", [0.002, 0.005])
def test_stability_probe_finds_the_exact_boundary(td_s):
    res, _ = _run("stability", K=0.8 * 0.1 / (T / 2 + td_s), td_s=td_s)
    r = res.results
    exact = linear.k_max(TRUTH, VirtualEnvironment("spring", K=1.0, T=T, td=td_s))
    assert r["exact_boundary"] == pytest.approx(exact)
    assert r["measured_boundary"] == pytest.approx(exact, rel=1e-3)
    assert r["measured_ci95"][0] <= r["measured_boundary"] <= r["measured_ci95"][1]
    bracket = [s for s in r["steps"] if s["phase"] == "bracket"]
    assert not any(s["unstable"] for s in bracket[:-1]) and bracket[-1]["unstable"]
    assert bracket[-2]["K"] < exact < bracket[-1]["K"]
    refine = [s for s in r["steps"] if s["phase"] == "refine"]  # either side of the crossing
    assert [s["unstable"] for s in refine] == [False, True]
    assert refine[0]["K"] < exact < refine[1]["K"]
    assert r["bracket"] == [refine[0]["K"], refine[1]["K"]]


def test_stability_probe_over_td_finds_the_first_unstable_sample():
    res, _ = _run("stability", K=50.0, variable="td", td_stop_s=0.005)
    r = res.results
    # exact: first whole-sample td where the sampled loop is unstable at K = 50
    exact = next(n * T for n in range(6)
                 if not linear.stability(TRUTH, VirtualEnvironment("spring", 50.0, T=T, td=n * T)).stable)
    assert r["exact_boundary"] == pytest.approx(exact)
    assert r["measured_boundary"] == pytest.approx(exact)


def test_etfe_on_a_quantised_noisy_sim_within_5_percent():
    rig = rig_from_dict({"sim": {"quantize": True, "force_noise_n": 0.002}})
    res = run(open_sim(rig, seed=5), make_protocol("etfe", seed=5), [], rig=rig)
    assert res.results["deviation_vs_sampled"]["max_rel"] < 0.05


def test_boundary_from_growth_rates_and_trips():
    from labbench.protocols.stability_probe import _crossing

    steps = [{"K": 10.0, "sigma_per_s": -0.2, "unstable": False},
             {"K": 20.0, "sigma_per_s": 0.2, "unstable": True}]
    assert _crossing(steps, "K") == pytest.approx(15.0)
    # a step ended by the energy observer before sigma could be fitted: midpoint
    steps[1] = {"K": 20.0, "sigma_per_s": None, "unstable": True}
    assert _crossing(steps, "K") == pytest.approx(15.0)
    steps[0]["sigma_per_s"] = -0.6
    steps[1]["sigma_per_s"] = 0.2
    assert _crossing(steps, "K") == pytest.approx(17.5)
    assert _crossing(steps[:1], "K") is None


def test_chirp_plan_prediction_equals_the_exact_zoh_recursion():
    from labbench.sim_backend.plant import MassDamperPlant

    p = make_protocol("chirp-id", duration_s=15.0)
    f = p.excitation(TRUTH)
    plant = MassDamperPlant(TRUTH.m, TRUTH.b, T)
    xs, vs = [], []
    for u in f:  # oracle: the exact ZOH step, one sample at a time
        xs.append(plant.position)
        vs.append(plant.velocity)
        plant.step(u)
    plan = precheck(p, TRUTH, Rig())["plan"]
    # 1 nm: the transfer-function form rounds differently; the window is centimetres
    assert plan["predicted_x_range_m"] == pytest.approx([min(xs), max(xs)], rel=1e-9, abs=1e-9)
    assert plan["predicted_v_max_m_s"] == pytest.approx(max(map(abs, vs)), rel=1e-9)


@pytest.mark.parametrize("name", protocol_names())
def test_any_bad_value_of_any_field_is_a_user_error_never_a_crash(name):
    from dataclasses import fields

    config_cls = protocol_class(name).Config
    weird = [None, "x", -1, -1.5, math.nan, math.inf, [], {}, True, 10**9, "0.1"]
    for f in fields(config_cls):
        for value in weird:
            try:
                make_protocol(name, **{f.name: value})
            except UserError as e:
                assert "\n" not in str(e)
