"""labbench.predictions: the one set of theory numbers every surface shows."""
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from labbench import predictions
from labbench.model import linear
from labbench.effective import effective_impedances
from labbench.units import DisplayUnits
from labbench.ve import Plant, VirtualEnvironment

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
    text = predictions.label("wb", 72.0, bw)
    assert text == (f"w_b* = 72 rad/s (sampled theory {bw.wb_star:.4g} rad/s; paper w0: 125)")
    hz = predictions.label("ws", 2 * math.pi * 3.5, bw, DisplayUnits(frequency="Hz"))
    assert hz.startswith("w_s* = 3.5 Hz (sampled theory ")
    assert f"{bw.ws_star / (2 * math.pi):.4g} Hz" in hz
    assert f"paper eq. 5: {bw.ws_star_eq5 / (2 * math.pi):.4g}" in hz
    assert predictions.label("ws", None, None) == "w_s* = - rad/s"
