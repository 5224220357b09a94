"""labbench.model.predictions: the one set of theory numbers every surface shows."""
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from labbench.model import predictions
from labbench.readout import bandwidth_text
from labbench.model import linear
from labbench.model.effective import effective_impedances
from labbench.readout.units import DisplayUnits
from labbench.model.ve import Plant, VirtualEnvironment

PAPER_PLANT = Plant(0.094, 0.10)
DEMO = VirtualEnvironment("spring-damper", K=50, B=1, w0=125)


def _es(plant, ve, latency):
    return lambda w: effective_impedances(np.array([w]), linear.z_sampled(plant, ve, [w], latency)).ES[0]


@pytest.mark.parametrize("latency", [0.0, 0.001, 0.0025])
def test_ws_star_is_the_zero_of_the_sampled_models_es(latency):
    """The root of ES(w) of the exact sampled model, found by a root finder on the model itself,
    to the grid's resolution (4000 log points: < 0.2 % apart)."""
    bw = predictions.bandwidths(PAPER_PLANT, DEMO, latency)
    root = brentq(_es(PAPER_PLANT, DEMO, latency), 5.0, 60.0, xtol=1e-10)
    assert bw.model == "sampled" and bw.latency_s == latency
    assert bw.ws_star == pytest.approx(root, rel=2e-4)
    assert bw.ws_star_eq5 == pytest.approx(math.sqrt(50 / 0.094), rel=1e-12)
    assert bw.wb_star_w0 == 125.0


def test_wb_star_is_where_the_sampled_ed_is_half_way_to_b():
    """The paper demo: ED falls half-way from its low-frequency value to b at 72.6 rad/s,
    where the continuous closed form says w0 = 125 rad/s."""
    bw = predictions.bandwidths(PAPER_PLANT, DEMO)
    w_low = np.geomspace(1e-3, 2e-3, 3)
    ed_low = float(np.median(linear.z_sampled(PAPER_PLANT, DEMO, w_low).real))
    half = PAPER_PLANT.b + 0.5 * (ed_low - PAPER_PLANT.b)
    root = brentq(lambda w: linear.z_sampled(PAPER_PLANT, DEMO, [w]).real[0] - half, 30, 120,
                  xtol=1e-10)
    assert bw.wb_star == pytest.approx(root, rel=2e-4)
    assert bw.wb_star == pytest.approx(72.57, abs=0.05)


def test_td_off_the_sample_grid_falls_back_to_the_paper_model_labelled():
    ve = VirtualEnvironment("spring", K=50, td=0.0005)
    bw = predictions.bandwidths(PAPER_PLANT, ve)
    assert bw.model == "paper" and bw.wb_star is None and bw.wb_star_w0 is None
    root = brentq(lambda w: effective_impedances(np.array([w]), linear.z_paper(PAPER_PLANT, ve, [w])).ES[0],
                  5, 60, xtol=1e-10)
    assert bw.ws_star == pytest.approx(root, rel=2e-4)


def test_label_names_each_theory_and_converts_units():
    bw = predictions.bandwidths(PAPER_PLANT, DEMO)
    text = bandwidth_text.label("wb", 72.0, bw)
    assert text == (f"w_b* = 72 rad/s (sampled theory {bw.wb_star:.4g} rad/s; paper w0: 125)")
    hz = bandwidth_text.label("ws", 2 * math.pi * 3.5, bw, DisplayUnits(frequency="Hz"))
    assert hz.startswith("w_s* = 3.5 Hz (sampled theory ")
    assert f"{bw.ws_star / (2 * math.pi):.4g} Hz" in hz
    assert f"paper eq. 5: {bw.ws_star_eq5 / (2 * math.pi):.4g}" in hz
    assert bandwidth_text.label("ws", None, None) == "w_s* = - rad/s"



@pytest.mark.parametrize("estimator", ["lpm", "h1-log", "h1-welch", "paper"])
def test_measured_bandwidths_are_read_where_the_rendered_damping_is(tmp_path, estimator):
    """Issue 43B: an h1-welch run's w_b* was 1.04 rad/s in its results, the report and the
    window (the exact sampled theory: 72.6), while the window's live estimate said 53.2: ED's
    three lowest bins, where a drift's edge leakage lives, set the level it falls from. Now
    a run's analysis and `analyze etfe` read every estimate as its rendered K, B are
    (``predictions.measured``), to the same numbers; where the ETFE vouches for its
    estimate, ED at the w_b* read lies within a quarter of its fall from the half-way level
    (at 1.04 rad/s it lay at the top, 0.5). The record: 20 s of the default ETFE, noise seed
    3, on the simulator; the handle ends 4.9 mm from where it started."""
    import labbench
    from labbench.analysis.etfe import DOUBTFUL
    from sim_sessions import TRUTH, record_session
    from truthdata import off_the_half_way_level

    path, run = record_session(tmp_path, "etfe", duration_s=20.0, seed=3, estimator=estimator)
    bw = run.results["bandwidths"]
    truth = Plant(TRUTH["m"], TRUTH["b"])  # the default simulated rig, the run's plant too
    assert bw["wb_star_predicted"] == pytest.approx(72.57, abs=0.05)
    if run.results["etfe"]["verdict"]["level"] != DOUBTFUL:
        assert off_the_half_way_level(bw["wb_star_measured"], truth, DEMO) < 0.25
        assert bw["ws_star_measured"] == pytest.approx(bw["ws_star_predicted"], rel=0.05)
    # `labbench analyze etfe` on the same plant: the same reading, in its own readout too
    analysed = labbench.load(path).etfe(estimator=estimator, m=truth.m, b=truth.b)
    again = analysed.as_dict()["bandwidths"]
    assert (analysed.ws_star, analysed.wb_star) == (again["ws_star_measured"], again["wb_star_measured"])
    for key in ("ws_star_measured", "wb_star_measured", "wb_star_predicted"):
        assert again[key] == pytest.approx(bw[key], rel=1e-9), key
    rows = dict(analysed.readout.row_texts())
    assert rows["w_b*"].startswith(f"measured = {bw['wb_star_measured']:.4g} rad/s")
