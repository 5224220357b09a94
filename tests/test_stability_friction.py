"""Stability with Coulomb friction: the describing-function model against its definitions and
the linear model, and the stability probe on the rough simulator against the model."""
import math

import numpy as np
import pytest

from labbench.model import linear
from labbench.model import stability_friction as sf
from labbench.protocol import precheck
from labbench.registry import make_protocol
from labbench.rig import Rig, rig_from_dict
from labbench.runner import run
from labbench.sim_backend.sim_device import open_sim
from labbench.model.ve import Plant, VirtualEnvironment

T = 0.001
PLANT = Plant(0.094, 0.10)


def ve(K=1.0, B=0.0, w0=125.0, td=0.0):
    return VirtualEnvironment("spring-damper", K, B, w0, T, td)


def test_equivalent_damping_is_the_fundamental_of_the_friction_force():
    # friction fc sign(v) under v = w X cos(w t): its first Fourier coefficient over the
    # velocity amplitude is the damper that takes out the same energy a cycle (4 fc X)
    fc, w, X = 0.02, 60.0, 0.004
    t = np.linspace(0.0, 2 * math.pi / w, 200001)[:-1]
    v = w * X * np.cos(w * t)
    first = 2 * np.mean(fc * np.sign(v) * np.cos(w * t))
    assert sf.equivalent_damping(fc, w, X) == pytest.approx(first / (w * X), rel=1e-4)
    work = np.mean(fc * np.abs(v)) * 2 * math.pi / w  # energy friction takes a cycle
    assert work == pytest.approx(4 * fc * X, rel=1e-4)
    assert sf.equivalent_damping(0.0, w, X) == 0.0
    assert sf.equivalent_damping(fc, w, 0.0) == math.inf


@pytest.mark.parametrize("B,td", [(0.0, 0.0), (1.0, 0.0), (0.5, 0.002)])
def test_damping_needed_puts_the_linear_boundary_at_that_stiffness(B, td):
    K = 1.6 * linear.k_max(PLANT, ve(B=B, td=td))
    need = sf.damping_needed(PLANT, ve(K, B, td=td))
    assert need > PLANT.b
    # with b*, this K is the linear boundary (to the two bisections' tolerances)
    assert linear.k_max(Plant(PLANT.m, need), ve(B=B, td=td)) == pytest.approx(K, rel=2e-3)
    # and there the least stable pole sits on the unit circle, at the marginal frequency
    marginal = Plant(PLANT.m, need)
    assert abs(linear.stability(marginal, ve(K, B, td=td)).margin) < 1e-3
    assert sf.marginal_frequency(marginal, ve(K, B, td=td)) > 0
    # a stable VE needs nothing more than the plant has
    assert sf.damping_needed(PLANT, ve(0.5 * K / 1.6, B, td=td)) == PLANT.b


def test_spring_boundary_follows_the_paper_condition_with_friction_as_damping():
    # a spring without filter: b + b_eq = K (T/2) to first order (the paper's condition with
    # the friction's equivalent damping added), and the oscillation at ~sqrt(K/m)
    fc, X = 0.02, 0.005
    k = sf.friction_boundary(PLANT, VirtualEnvironment("spring", 1.0, 0.0, math.inf, T, 0.0),
                             fc, X)
    w = math.sqrt(k / PLANT.m)
    assert k == pytest.approx((PLANT.b + sf.equivalent_damping(fc, w, X)) / (T / 2), rel=0.01)


@pytest.mark.parametrize("B", [0.0, 1.0])
def test_friction_boundary_and_limit_cycle_amplitude_are_inverse(B):
    fc = 0.02
    k_lin = linear.k_max(PLANT, ve(B=B))
    assert sf.friction_boundary(PLANT, ve(B=B), 0.0, 0.005) == k_lin
    assert sf.limit_cycle_amplitude(PLANT, ve(0.9 * k_lin, B), fc) == math.inf
    amplitudes = [sf.limit_cycle_amplitude(PLANT, ve(f * k_lin, B), fc) for f in (1.1, 1.3, 1.6)]
    assert amplitudes[0] > amplitudes[1] > amplitudes[2] > 0  # stiffer: smaller motions grow
    for f, X in zip((1.1, 1.3, 1.6), amplitudes):
        assert sf.friction_boundary(PLANT, ve(B=B), fc, X) == pytest.approx(f * k_lin, rel=3e-3)
    # larger swings see less of the friction: the boundary falls towards the linear one
    # (a metre's swing: friction's damping is under 1 % of the device's b)
    ks = [sf.friction_boundary(PLANT, ve(B=B), fc, X) for X in (0.001, 0.003, 0.01, 1.0)]
    assert ks[0] > ks[1] > ks[2] > ks[3] > k_lin
    assert ks[3] == pytest.approx(k_lin, rel=0.01)
    assert sf.friction_boundary(PLANT, ve(B=B), fc, 0.001, k_cap=1.05 * k_lin) == math.inf


def rough_rig(fc, **sim):
    """The rough simulator (docs/loop.md): Coulomb friction, the 38.3 um encoder, 2 mN noise."""
    return rig_from_dict({"sim": {"coulomb_n": fc, "quantize": True, "force_noise_n": 0.002,
                                  **sim}})


def probe(rig, B, believed_fc, seed=1, **options):
    k_lin = linear.k_max(PLANT, ve(B=B))
    p = make_protocol("stability", ve="spring-damper", B=B, w0_rad_s=125.0, K=0.5 * k_lin,
                      ratio=1.08, plant_coulomb_n=believed_fc, **options)
    res = run(open_sim(rig, seed=seed), p, [], rig=rig)
    assert res.status == "success", res.reason
    return res.results, k_lin


@pytest.mark.parametrize("B", [0.0, 1.0])
def test_probe_on_the_rough_rig_measures_the_friction_aware_boundary(B):
    # Before: the probe stopped at its 1.5 x linear cap and called it "no boundary" (at
    # B = 1 its steps above K_lin were never even enabled: friction held the handle off
    # centre). Now the steps go past the linear boundary as far as the friction-aware plan
    # says, and the measured boundary is bracketed by a stable and an unstable step.
    fc = 0.02
    r, k_lin = probe(rough_rig(fc), B, fc)
    f = r["friction"]
    lo, hi = r["measured_ci95"]
    assert r["measured_basis"] == "bracket" and r["bracket"] == [lo, hi]
    assert lo <= r["measured_boundary"] <= hi
    assert all(s["rendered"] for s in r["steps"])
    assert max(s["K"] for s in r["steps"]) <= 3.0 * k_lin * (1 + 1e-9)  # the safety cap
    assert r["measured_boundary"] > 1.1 * k_lin  # friction moved it well beyond the linear one
    # The prediction at the swing the steps started from lies in the measured bracket,
    # up to its own tolerance f_c / (K X) (the describing function's sinusoid):
    # measured grid (bench/bench_stability_friction.py) within 1.3 %.
    assert f["agrees"] is True
    assert lo * (1 - f["tolerance"]) <= f["k_max"] <= hi * (1 + f["tolerance"])
    assert abs(f["rel_error"]) <= (hi - lo) / lo + f["tolerance"]
    assert "boundary measured" in r["stopped"] and "predicts" in r["stopped"]


def test_a_frictionless_device_believed_to_have_friction_disagrees():
    # the comparison can fail: a friction the device does not have predicts a boundary
    # far beyond the one it shows (the linear one)
    r, k_lin = probe(rough_rig(0.0), 0.0, 0.02)
    assert r["measured_boundary"] == pytest.approx(k_lin, rel=0.03)
    assert r["friction"]["agrees"] is False
    assert r["friction"]["k_max"] > 1.5 * k_lin


def test_without_known_friction_the_probe_says_why_it_found_no_boundary():
    # the "before": the linear ceiling, no step grew, and now a reason
    r, k_lin = probe(rough_rig(0.02), 0.0, None)
    assert r["measured_boundary"] is None and r["friction"] is None
    top = max(s["K"] for s in r["steps"])
    assert top <= 1.5 * k_lin and top > 1.35 * k_lin
    assert r["stopped"].startswith(f"no sustained oscillation up to K = {top:.4g} N/m")
    assert "max_over 1.5 x the linear boundary" in r["stopped"]
    assert "friction?" in r["stopped"]


def test_friction_beyond_the_safety_cap_stops_there_and_says_so():
    fc = 0.05  # its boundary at the probe's swing is ~3 x the linear one: past friction_cap
    r, k_lin = probe(rough_rig(fc), 0.0, fc, friction_cap=2.0)
    assert r["measured_boundary"] is None
    assert max(s["K"] for s in r["steps"]) <= 2.0 * k_lin
    assert "friction_cap 2 x the linear boundary" in r["stopped"]
    assert r["friction"]["k_max"] > 2.0 * k_lin  # the reason it found none
    assert "die out, larger ones grow" in r["stopped"]


def test_a_step_the_enable_gate_kept_shut_is_not_called_stable():
    # friction above the homing spring's 0.1 N pull: a step leaves the handle off centre
    # where the next, stiffer spring cannot be enabled; that step measured nothing
    r, _ = probe(rough_rig(0.5), 0.0, 0.5)
    last = r["steps"][-1]
    assert last["rendered"] is False and last["unstable"] is None
    assert r["measured_boundary"] is None and r["bracket"] is None
    assert "enable gate stayed shut" in r["stopped"]


def test_plan_goes_past_the_linear_ceiling_only_as_far_as_friction_predicts():
    fc = 0.02
    k_lin = linear.k_max(PLANT, ve())
    p = make_protocol("stability", ve="spring-damper", w0_rad_s=125.0, K=0.5 * k_lin,
                      ratio=1.08, plant_coulomb_n=fc)
    plan = precheck(p, PLANT, Rig())["plan"]
    kf = plan["friction"]["k_max"]
    assert 1.5 * k_lin < kf < 2.0 * k_lin
    assert plan["last"]["K"] <= min(1.5 * kf, 3.0 * k_lin)
    assert plan["last"]["K"] * 1.08 > min(1.5 * kf, 3.0 * k_lin)
    plain = make_protocol("stability", ve="spring-damper", w0_rad_s=125.0, K=0.5 * k_lin,
                          ratio=1.08)
    assert "friction" not in precheck(plain, PLANT, Rig())["plan"]
    assert precheck(plain, PLANT, Rig())["plan"]["last"]["K"] <= 1.5 * k_lin


def test_zwidth_campaign_on_the_rough_rig_gives_a_boundary_or_the_reason_it_has_none(tmp_path):
    # Before: "no step grew" up to 1.47 x K_max and nothing said why. With the device's
    # friction known (here given to the point; a campaign takes the commissioning's) the
    # row holds the measured boundary beside the friction-aware prediction; without it, the
    # reason the probe found none. The chart and the report show both.
    from labbench.campaign import engine
    from labbench.campaign.figures import _friction_aware
    from labbench.campaign.plan import Context, make_plan
    from labbench.campaign.report import build
    from labbench.rig import CampaignSettings
    from labbench.cli.campaign import point_runner
    from labbench.loop.interrupts import StopRequest
    from labbench.report.blocks import Table
    from labbench.sweep import table as tables
    from labbench.sweep.spec import spec_from_dict
    from test_campaign import args_for

    rig = rough_rig(0.02)
    spec = spec_from_dict({"sweep": {"name": "z", "protocol": "stability"},
                           "fixed": {"ve": "spring-damper", "w0_rad_s": 125.0, "B": 0.0,
                                     "K_frac_k_max": 0.5, "ratio": 1.08, "seed": 1},
                           "cases": {"friction": [{"label": "unknown"},
                                                  {"label": "known", "plant_coulomb_n": 0.02}]}})
    ctx = Context("sim", rig, PLANT, "nominal", True, CampaignSettings.from_rig(rig, True))
    (tmp_path / "s").mkdir()
    summary = engine.run_campaign(make_plan(spec, ctx), tmp_path / "t.sweep",
                                  point_runner(args_for(tmp_path / "s")), StopRequest())
    assert summary.complete
    rows = {r["friction"]: r for r in tables.read_table(tmp_path / "t.sweep").to_pylist()}
    unknown, known = rows["unknown"], rows["known"]
    k_lin = unknown["pred.k_max"]
    assert unknown["zw.k_max"] is None and unknown["zw.k_max_above"] > 1.35 * k_lin
    assert unknown["zw.stopped"].startswith("no sustained oscillation") and \
        unknown["pred.k_max_friction"] is None
    assert known["zw.k_max"] > 1.5 * k_lin and known["zw.friction_agrees"] is True
    assert known["zw.k_friction_lo"] <= known["zw.ci_hi"]
    assert known["zw.ci_lo"] <= known["zw.k_friction_hi"]
    assert known["pred.k_max_friction"] == pytest.approx(known["zw.k_friction"], rel=0.03)
    # the chart's friction-aware series (the whole chart's theory curves take seconds)
    (diamonds,) = _friction_aware(list(enumerate([unknown, known])), "C0", "w0 = 125 rad/s")
    assert "stable with friction" in diamonds.label
    assert list(diamonds.y) == [known["zw.k_friction"]] and diamonds.rows == (1,)  # unknown: none
    _, _, blocks = build(tmp_path / "t.sweep")
    points = next(b for b in blocks if isinstance(b, Table) and b.title.startswith("One row"))
    assert f"#{unknown['index']}: no sustained oscillation" in points.note
    assert f"#{known['index']}" not in points.note
    friction_col = points.columns.index("with friction, at the swing (N/m)")
    cells = {row[0]: row[friction_col] for row in points.rows}
    assert cells[str(unknown["index"])] == "-" and "mm" in cells[str(known["index"])]


def test_a_campaign_takes_the_friction_of_the_chirp_id_that_gave_its_plant(tmp_path):
    # the plant of a campaign from the rig's last chirp-ID (its default): that fit's Coulomb
    # term is the friction its probes plan and compare with, before a commissioning's
    import argparse

    from labbench.cli import main
    from labbench.cli.campaign import make_context

    rig_file = tmp_path / "rough.toml"
    rig_file.write_text('[rig]\nname = "rough"\n[sim]\ncoulomb_n = 0.02\nquantize = true\n'
                        "force_noise_n = 0.002\n")
    out = tmp_path / "s"
    assert main(["run", "chirp-id", "--rig", str(rig_file), "--duration-s", "20", "--methods",
                 "l2", "--model", "mbc", "--out", str(out)]) == 0
    args = argparse.Namespace(rig=str(rig_file), device="sim", out=str(out), plant_m_kg=None,
                              plant_b=None, plant_from="last-id", skip_commissioning=False)
    ctx = make_context(args)
    assert ctx.plant_from.endswith(".lbsession") and ctx.commission == {}
    assert ctx.coulomb_n == pytest.approx(0.02, rel=0.1)  # the fit's, not the truth's
    assert ctx.coulomb_n != 0.02
    nominal = make_context(argparse.Namespace(**{**vars(args), "plant_from": "nominal"}))
    assert nominal.coulomb_n is None


def _planned_rows(rig, **fixed):
    """The rows a Z-width campaign over B = 0 and 2 plans (not run): its predictions."""
    from labbench.campaign.plan import Context, make_plan
    from labbench.campaign.rows import skipped_row
    from labbench.rig import CampaignSettings
    from labbench.sweep.spec import spec_from_dict

    spec = spec_from_dict({"sweep": {"name": "z", "protocol": "stability"},
                           "fixed": {"ve": "spring-damper", "w0_rad_s": 125.0, "K_frac_k_max": 0.5,
                                     "ratio": 1.08, **fixed}, "grid": {"B": [0.0, 2.0]}})
    ctx = Context("sim", rig, PLANT, "nominal", True, CampaignSettings.from_rig(rig, True))
    return [skipped_row(pp, ctx) for pp in make_plan(spec, ctx).points]


def test_the_zwidth_chart_draws_the_friction_aware_boundary_over_b_as_the_probe_plans_it():
    # 41B's chart had a diamond per point only: the probe's swing changes with K and B, so
    # the curve between points needs the plan's swing at each B, from the table alone

    from labbench.campaign.figures import _friction_curve

    rig = rough_rig(0.02)
    rows = _planned_rows(rig, plant_coulomb_n=0.02)
    (line,) = _friction_curve(list(enumerate(rows)), 125.0, 2.0, "C0", "w0 = 125 rad/s")
    assert "with friction 0.02 N, at the swing the probe plans at each B" in line.label
    curve = dict(zip(line.x, line.y))
    for r in rows:  # through each point's planned prediction
        assert curve[r["ve.B"]] == pytest.approx(r["pred.k_max_friction"], rel=1e-12)
    # between the points: what a probe planned at that B expects (1438 N/m at B = 1.05) ...
    between = make_protocol("stability", ve="spring-damper", B=1.05, w0_rad_s=125.0, K=300.0,
                            ratio=1.08, plant_coulomb_n=0.02)
    precheck(between, PLANT, rig)
    assert curve[1.05] == pytest.approx(between.k_friction(PLANT), rel=1e-12)
    # ... not the boundary at either point's swing (1302 and 1527 N/m: -9 % and +6 %)
    for r in rows:
        x = between.planned_amplitude(ve(r["pred.k_max_friction"], r["ve.B"]), PLANT)
        assert abs(sf.friction_boundary(PLANT, ve(B=1.05), 0.02, x) / curve[1.05] - 1) > 0.05
    assert all(curve[b] > linear.k_max(PLANT, ve(B=b)) for b in curve)


def test_the_friction_aware_curve_stops_at_the_probes_safety_cap():

    from labbench.campaign.figures import _friction_curve

    rows = _planned_rows(rough_rig(0.05), plant_coulomb_n=0.05, friction_cap=2.0)
    assert rows[0]["pred.k_max_friction"] is None  # B = 0: beyond 2 x the linear boundary
    (line,) = _friction_curve(list(enumerate(rows)), 125.0, 2.0, "C0", "w0 = 125 rad/s")
    curve = dict(zip(line.x, line.y))
    assert math.isnan(curve[0.0]) and curve[2.0] == pytest.approx(rows[1]["pred.k_max_friction"])
    assert curve[2.0] <= 2.0 * linear.k_max(PLANT, ve(B=2.0))
    # a campaign that does not know the friction draws none
    assert _friction_curve(list(enumerate(_planned_rows(rough_rig(0.05)))), 125.0, 2.0, "C0",
                           "w0 = 125 rad/s") == []
