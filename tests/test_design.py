"""The design tool (labbench.design.tradeoffs, labbench.design.checking, ``labbench design``): each number
equals its model, the Z-width rule and the Pareto front against exact truth, the recommended w0
against a campaign measured on the rough simulator, and bad input in one line."""
import json
import math

import pytest

from labbench.design import tradeoffs
from labbench.model import predictions
from labbench.cli.main import main
from labbench.design.checking import check, table_lines
from labbench.errors import UserError
from labbench.model import linear, noise, passivity, stability_friction
from labbench.rig import Rig, rig_from_dict
from labbench.model.ve import Plant, VirtualEnvironment

PLANT = Plant(0.094, 0.10)
DELTA = Rig().metres_per_count
ROUGH = tradeoffs.Device(PLANT, 0.0, DELTA, 0.002, 0.02)  # issue 41's rough simulator
QUANTISED = tradeoffs.Device(PLANT, 0.0, DELTA, 0.002)  # the same without friction
ROUGH_SOURCES = noise.NoiseSources(DELTA, 0.002)


def test_every_number_is_its_models():
    """One model per number, as MODELS names it: the design calls them, nothing else."""
    d = tradeoffs.Designer(ROUGH, tradeoffs.Targets(noise_limit_n=0.004))
    p = d.evaluate(50.0, 1.0, 125.0, 0.001)
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0)
    assert p.k_max == linear.k_max(PLANT, ve)
    assert p.margin == pytest.approx(p.k_max / 50.0)
    assert p.k_passive == passivity.passive_k_max(PLANT, ve)
    assert p.k_quantised == pytest.approx(2 * 0.02 / DELTA)
    assert p.k_friction == stability_friction.friction_boundary(PLANT, ve, 0.02, 1e-3)
    assert p.k_friction > p.k_max and p.b_friction is None  # no hand speed stated
    moving = tradeoffs.Designer(ROUGH, tradeoffs.Targets(motion_m_s=0.05)).evaluate(50, 1, 125, 1e-3)
    assert moving.b_friction == pytest.approx(0.02 * math.sqrt(2 / math.pi) / 0.05)
    bw = predictions.bandwidths(PLANT, ve)
    assert (p.ws_star, p.wb_star) == (bw.ws_star, bw.wb_star)
    assert p.rendered_B == linear.low_frequency(PLANT, ve, "sampled")[0]
    fn = noise.force_noise(PLANT, ve, noise.NoiseSources(DELTA, 0.002, 0.02),
                           excitation=noise.Excitation(tradeoffs.EXCITATION_N))
    assert (p.noise_command, p.noise_felt) == (fn.rms_command, fn.rms_felt)
    assert (p.noise_friction, p.stick_share) == (fn.parts["friction"], fn.friction.stick_share)
    w = tradeoffs.ACCURACY_W
    assert p.ed_error_sampled == pytest.approx(
        abs(linear.z_sampled(PLANT, ve, [w]).real[0] - 1.1) / 1.1)
    assert p.ed_error_paper == pytest.approx(
        abs(linear.z_paper(PLANT, ve, [w]).real[0] - 1.1) / 1.1)
    assert p.stable and p.within_limit


def test_friction_noise_follows_the_stated_motion():
    """With Fc known the noise is friction-aware under the stated motion: the ETFE's 0.5 N by
    default, another std when given, and for a hand speed the white force that moves the
    linearised loop at it (its velocity within 2 %: d's own share of the motion is the rest);
    Fc unknown, the linear model (no friction part)."""
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0)
    src = noise.NoiseSources(DELTA, 0.002, 0.02)
    for targets, std in ((tradeoffs.Targets(), 0.5), (tradeoffs.Targets(excitation_n=0.2), 0.2)):
        p = tradeoffs.Designer(ROUGH, targets).evaluate(50.0, 1.0, 125.0, 1e-3)
        fn = noise.force_noise(PLANT, ve, src, excitation=noise.Excitation(std))
        assert p.noise_command == fn.rms_command and p.noise_friction > 0
    d = tradeoffs.Designer(ROUGH, tradeoffs.Targets(motion_m_s=0.01))
    _, fn = d.detail(50.0, 1.0, 125.0, 1e-3)
    assert fn.friction.velocity_rms == pytest.approx(0.01, rel=0.02)
    plain = tradeoffs.Designer(QUANTISED).evaluate(50.0, 1.0, 125.0, 1e-3)
    assert plain.noise_friction is None and plain.stick_share is None
    assert plain.noise_command == noise.force_noise(PLANT, ve, ROUGH_SOURCES).rms_command
    held = tradeoffs.Designer(ROUGH, tradeoffs.Targets(excitation_n=0.01)).evaluate(50, 1, 125, 1e-3)
    assert held.stable and held.noise_command is None  # friction holds the handle: no number


def test_an_unstable_setting_says_so_and_has_no_noise():
    d = tradeoffs.Designer(ROUGH)
    p = d.evaluate(2000.0, 1.0, 125.0, 0.001)  # K_max 1212 N/m
    assert not p.stable and not p.within_limit
    assert p.noise_felt is None and p.rendered_B is None


def test_the_noise_limit_holds_the_noise_it_names():
    """At B = 2, w0 = 180 the command noise is 4.37 mN and the felt 4.19 (held: the hold's
    sinc^2 lowers the quantisation's share more than the amplifier's 2 mN adds): a 4.3 mN
    limit on the command refuses it, the same limit on the felt force takes it."""
    limit = 0.0043
    on_command = tradeoffs.Designer(QUANTISED, tradeoffs.Targets(noise_limit_n=limit)).evaluate(
        50, 2, 180, 1e-3)
    on_felt = tradeoffs.Designer(QUANTISED, tradeoffs.Targets(noise_limit_n=limit, noise_of="felt")
                              ).evaluate(50, 2, 180, 1e-3)
    assert on_command.noise_command > limit > on_command.noise_felt
    assert not on_command.within_limit and on_felt.within_limit


def test_zwidth_rule_against_exact_areas():
    Bs = [0.0, 1.0, 2.0]
    # no limit: the trapezoid of a line is exact
    assert tradeoffs.zwidth(Bs, [100.0, 300.0, 500.0], [1, 2, 3], None) == (600.0, 2.0)
    # the limit crossed half-way between B = 1 and 2: K_max there 400, area 200 + 175
    area, b_lim = tradeoffs.zwidth(Bs, [100.0, 300.0, 500.0], [1.0, 2.0, 4.0], 3.0)
    assert b_lim == pytest.approx(1.5) and area == pytest.approx(200 + 0.5 * (300 + 400) * 0.5)
    assert tradeoffs.zwidth(Bs, [100.0, 300.0, 500.0], [5.0, 6.0, 7.0], 3.0) == (0.0, None)
    assert tradeoffs.zwidth(Bs, [100.0, 300.0, 500.0], [1.0, 2.0, math.inf], 3.0) == (200.0, 1.0)


def test_pareto_front_is_exactly_the_undominated_set():
    d = tradeoffs.Designer(ROUGH)
    pts = d.sweep([50.0, 150.0], [0.0, 0.5, 1.0, 2.0], [60.0, 125.0, 250.0, 500.0], [0.001])
    front = tradeoffs.pareto(pts)
    stable = [p for p in pts if p.stable]

    def key(p):
        return (p.margin, p.wb_star or 0.0, -p.noise_felt)

    def dominates(q, p):
        return all(a >= b for a, b in zip(key(q), key(p))) and key(q) != key(p)

    assert front and all(not any(dominates(q, p) for q in stable) for p in front)
    assert all(any(dominates(q, p) for q in front) for p in stable if p not in front)
    assert len(front) < len(stable)  # something was dominated (the grid's K = 150 points)


def test_recommend_is_the_argmax_of_the_measured_rule_on_the_models():
    """Truth computed here from the models directly: per w0, K_max at each B (linear.k_max),
    the command noise (noise.force_noise) and the Z-width rule; the design's choice is its
    argmax, interior (a faster filter raises K_max but the noise limit lowers B)."""
    Bs, w0s = [0.0, 0.5, 1.0, 1.5, 2.0], [60.0, 125.0, 180.0, 250.0, 360.0]
    d = tradeoffs.Designer(QUANTISED, tradeoffs.Targets(noise_limit_n=0.004))
    rec = d.recommend(50.0, Bs, w0s, 0.001)
    areas = {}
    for w0 in w0s:
        ves = [VirtualEnvironment("spring-damper", K=50.0, B=B, w0=w0) for B in Bs]
        k = [linear.k_max(PLANT, ve) for ve in ves]
        n = [noise.force_noise(PLANT, ve, noise.NoiseSources(DELTA, 0.002)).rms_command
             for ve in ves]
        areas[w0] = tradeoffs.zwidth(Bs, k, n, 0.004)[0]
    assert rec["w0"] == max(areas, key=areas.get) == 180.0
    assert [r["value"] for r in rec["by_w0"]] == pytest.approx([areas[w] for w in w0s])
    no_limit = tradeoffs.Designer(QUANTISED).recommend(50.0, Bs, w0s, 0.001)
    assert no_limit["w0"] == 360.0  # without a limit the fastest filter is stiffest


def test_band_objective_takes_the_fastest_filter_within_the_limit():
    d = tradeoffs.Designer(QUANTISED, tradeoffs.Targets(noise_limit_n=0.004))
    rec = d.recommend(50.0, [1.0], [60.0, 125.0, 250.0, 360.0], 0.001, "band", B=1.0)
    assert rec["w0"] == 250.0  # 360 rad/s: 4.16 mN at B = 1
    assert rec["by_w0"][-1]["value"] is None


def test_rig_noise_sources():
    hw, where = tradeoffs.rig_noise(Rig(), simulated=False)
    assert hw == noise.NoiseSources(DELTA, 0.0) and where["force_noise"] == "none stated"
    rough = rig_from_dict({"sim": {"quantize": True, "force_noise_n": 0.002}})
    assert tradeoffs.rig_noise(rough, True)[0] == noise.NoiseSources(DELTA, 0.002)
    assert tradeoffs.rig_noise(Rig(), True)[0] == noise.NoiseSources(0.0, 0.0)  # ideal simulator


@pytest.mark.parametrize("kw,match", [({"noise_limit_n": -1.0}, "noise limit"),
                                      ({"noise_limit_n": math.nan}, "noise limit"),
                                      ({"noise_of": "loud"}, "applies to"),
                                      ({"at_w": 0.0}, "accuracy frequency"),
                                      ({"motion_m_s": -0.1}, "hand speed"),
                                      ({"amplitude_m": 0.0}, "amplitude"),
                                      ({"excitation_n": 0.0}, "excitation")])
def test_targets_refuse_bad_values(kw, match):
    with pytest.raises(UserError, match=match):
        tradeoffs.Targets(**kw)


# ----------------------------------------------------------------- predict, then measure
@pytest.fixture(scope="module")
def campaigns(tmp_path_factory):
    """The design check's two campaigns on the rough simulator, cut to three w0 around the
    recommended one and three B (ETFE of 20 s: the noise within ~1.5 %)."""
    from labbench.cli.main import main as cli

    d = tmp_path_factory.mktemp("design")
    rig = d / "rough.toml"
    rig.write_text('[rig]\nname = "rough"\n[sim]\nquantize = true\nforce_noise_n = 0.002\n')
    grid = "[grid]\nw0_rad_s = [125.0, 180.0, 250.0]\nB = [0.0, 1.0, 2.0]\n"
    (d / "noise.toml").write_text('[sweep]\nname = "n"\nprotocol = "etfe"\n[fixed]\n'
                                  've = "spring-damper"\nK = 50.0\nduration_s = 20.0\nseed = 3\n'
                                  + grid)
    (d / "zw.toml").write_text('[sweep]\nname = "z"\nprotocol = "stability"\n[fixed]\n'
                               've = "spring-damper"\nK_frac_k_max = 0.5\nratio = 1.08\n'
                               'max_over = 1.5\nseed = 3\n' + grid)
    for name in ("noise", "zw"):
        assert cli(["campaign", str(d / f"{name}.toml"), "--device", "sim", "--rig", str(rig),
                    "--table", str(d / f"{name}.sweep"), "--out", str(d / "s"),
                    "--plant-from", "nominal"]) == 0
    return d, rig


def test_predictions_beside_the_campaigns_measurements(campaigns):
    """On the rough simulator: K_max within 0.5 % (the probe's own accuracy, docs/campaign.md),
    force noise within 10 % (the goal; its 95 % interval ~ +-1.5 % at 20 s), rendered K and B
    within their 95 % intervals; the measured best w0 the predicted one (with 3 w0, one grid
    step each way to go wrong)."""
    from labbench.sweep import table as tables

    d, _ = campaigns
    rows = tables.read_table(d / "noise.sweep").to_pylist() + \
        tables.read_table(d / "zw.sweep").to_pylist()
    designer = tradeoffs.Designer(QUANTISED, tradeoffs.Targets(noise_limit_n=0.004))  # as simulated
    c = check(designer, rows)
    assert len(c.rows) == 9
    for r in c.rows:
        p, m, ci = r.predicted, r.measured, r.ci
        assert m["k_max"] == pytest.approx(p["k_max"], rel=0.005)
        assert abs(m["noise"] / p["noise"] - 1) < 0.10
        for key in ("rendered_K", "rendered_B"):
            assert ci[key][0] <= p[key] <= ci[key][1], (r.B, r.w0, key)
    assert c.best_predicted == c.best_measured == 180.0 and c.steps_apart == 0
    text = "\n".join(table_lines(c))
    assert "predicted best <- measured best" in text


def test_a_campaign_rows_noise_prediction_knows_the_devices_friction(tmp_path):
    """A white-noise ETFE point on a simulator rubbing with 0.02 N (B = 0, where the linear
    model misses the record's noise by 43 %): the row's prediction takes the simulator's
    friction and the run's own excitation and lands within 10 % of the measured noise."""
    from labbench.cli.main import main as cli
    from labbench.sweep import table as tables

    rig = tmp_path / "rough.toml"
    rig.write_text('[rig]\nname = "rough"\n[sim]\nquantize = true\nforce_noise_n = 0.002\n'
                   'coulomb_n = 0.02\n')
    (tmp_path / "n.toml").write_text('[sweep]\nname = "n"\nprotocol = "etfe"\n[fixed]\n'
                                     've = "spring-damper"\nK = 50.0\nduration_s = 30.0\n'
                                     'seed = 3\n[grid]\nB = [0.0]\n')
    assert cli(["campaign", str(tmp_path / "n.toml"), "--device", "sim", "--rig", str(rig),
                "--table", str(tmp_path / "n.sweep"), "--out", str(tmp_path / "s"),
                "--plant-from", "nominal"]) == 0
    row = tables.read_table(tmp_path / "n.sweep").to_pylist()[0]
    assert row["pred.noise_coulomb_n"] == 0.02 and row["pred.noise_stick_share"] < 0.01
    assert abs(row["res.force_noise.rms_n"] / row["pred.noise_command"] - 1) < 0.10


def test_cli_design_compare_json_and_figure(campaigns, capsys):
    d, rig = campaigns
    fig = d / "check.png"
    assert main(["design", "--rig", str(rig), "--simulated", "--noise-limit-n", "0.004",
                 "--B", "0,1,2", "--w0", "125,180,250", "--out", str(d / "s"),
                 "--plant-from", "nominal", "--compare", str(d / "noise.sweep"),
                 str(d / "zw.sweep"), "--plot", str(fig), "--json"]) == 0
    out = json.loads(capsys.readouterr().out.splitlines()[0])
    assert fig.stat().st_size > 10_000
    assert out["recommendation"]["w0"] == 180.0
    assert out["check"]["best_w0_measured"] == 180.0
    assert out["device"]["quantum_m"] == pytest.approx(DELTA)
    assert out["device"]["force_noise_n"] == 0.002
    assert set(out["models"]) >= {"k_max", "noise_felt", "zwidth"}
    assert len(out["points"]) == 9 and out["pareto"]


def test_cli_design_text(capsys):
    assert main(["design", "--B", "0,1", "--w0", "60,125", "--K", "50,5000",
                 "--plant-from", "nominal", "--noise-limit-n", "0.002"]) == 0
    out = capsys.readouterr().out
    assert "recommended w0 = " in out and "UNSTABLE" in out  # K = 5000 beyond every K_max
    assert "encoder step 38.35 um" in out and "amplifier noise 0 mN (none stated)" in out


def test_cli_design_with_friction_names_its_noise_model(capsys, tmp_path):
    """A simulated rig rubbing with 0.02 N: its friction is the design's (the simulator's own,
    said so), the noise model names it and the motion, each point carries friction's part;
    at 0.1 N of excitation against 0.05 N the stick share is over the limit and said so."""
    rig = tmp_path / "rough.toml"
    rig.write_text('[rig]\nname = "r"\n[sim]\nquantize = true\ncoulomb_n = 0.02\n')
    assert main(["design", "--rig", str(rig), "--simulated", "--B", "1", "--w0", "125",
                 "--out", str(tmp_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["device"]["coulomb_n"] == 0.02 and "simulator" in out["device"]["sources"]["coulomb"]
    assert out["targets"]["excitation_n"] == tradeoffs.EXCITATION_N
    assert out["points"][0]["noise_friction"] > 0 and "arcsine" in out["models"]["noise_friction"]
    assert main(["design", "--B", "1", "--w0", "125", "--out", str(tmp_path), "--coulomb-n",
                 "0.05", "--excitation-n", "0.1"]) == 0
    text = capsys.readouterr().out
    assert "Coulomb friction 0.05 N under 0.1 N of white excitation" in text
    assert "the Gaussian velocity it assumes fails" in text


@pytest.mark.parametrize("argv,match", [
    (["--plant-m-kg", "0.1"], "together"),
    (["--quantum-m", "-1"], "--quantum-m"),
    (["--band-hz", "10"], "two numbers"),
    (["--noise-limit-n", "0"], "noise limit"),
    (["--K", "0"], "K must be > 0"),
    (["--T", "0"], "sample time"),
    (["--w0", "nan"], "finite"),
    (["--at-w", "5000"], "Nyquist"),
    (["--excitation-n", "-1"], "excitation"),
    (["--K", ",".join(["1"] * 80), "--B", ",".join(["1"] * 80)], "at most 5000"),
    (["--plot", "x.txt"], ".png"),
    (["--compare", "/nonexistent.sweep"], "nonexistent"),
])
def test_cli_design_bad_input_is_one_line(argv, match, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["design", "--plant-from", "nominal", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and match in err
