"""Closed-loop fit of m, b and the extra loop delay td from the ETFE, against known truth."""
import json

import numpy as np
import pytest
from truthdata import PAPER_B, PAPER_M, closed_loop_recording, write_csv

from labbench.analysis import compare
from labbench.analysis.etfe import etfe
from labbench.analysis.loopfit import fit_loop
from labbench.cli import main
from labbench.errors import UserError
from labbench.ve import Plant, VirtualEnvironment

T = 0.001
SD = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0)
START = Plant(0.08, 0.2)  # deliberately off: the fit must not lean on its start


@pytest.mark.parametrize("delay", [0.0, 1.5, 3.0, 0.3])
def test_fit_recovers_plant_and_fractional_delay_on_exact_data(delay):
    rec = closed_loop_recording(SD, n=30000, latency=delay * T)
    fit = fit_loop(etfe(rec), compare.ve_from_meta(rec.meta, rec.fs), START)
    assert abs(fit.td_s / T - delay) < 0.01  # samples
    assert abs(fit.m / PAPER_M - 1) < 1e-3 and abs(fit.b / PAPER_B - 1) < 1e-2
    assert fit.residual_rms < 1e-3 and fit.td_meta_s == 0.0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_fit_intervals_cover_the_truth_under_process_noise(seed):
    # 0.3 N rms of force the plant feels and the record does not hold, VE td = 1 sample
    ve = SD.with_(td=T)
    rec = closed_loop_recording(ve, n=30000, seed=seed, latency=1.5 * T, process_noise=0.3)
    fit = fit_loop(etfe(rec), compare.ve_from_meta(rec.meta, rec.fs), START)
    for k, truth in (("m", PAPER_M), ("b", PAPER_B), ("td_s", 1.5 * T)):
        lo, hi = fit.ci95[k]
        assert lo <= truth <= hi, (k, lo, hi)
    assert fit.ci95["td_s"][1] - fit.ci95["td_s"][0] < 0.1 * T  # informative
    assert fit.td_meta_s == T and fit.as_dict()["loop_delay_s"] == pytest.approx(T + fit.td_s)


def test_fit_ve_recovers_the_rendered_gains():
    ve = VirtualEnvironment("spring-damper", K=80.0, B=0.5, w0=200.0)
    rec = closed_loop_recording(ve, n=30000, latency=2.0 * T)
    rendered = ve.with_(K=100.0, B=0.8)  # metadata claim gains the loop did not render
    fit = fit_loop(etfe(rec), rendered, START, fit_ve=True)
    assert fit.K == pytest.approx(80.0, rel=1e-3) and fit.B == pytest.approx(0.5, rel=1e-2)
    assert abs(fit.td_s / T - 2.0) < 0.01


def test_cli_fit_json_and_text(tmp_path, capsys):
    p = tmp_path / "loop.csv"
    rec = closed_loop_recording(SD.with_(td=2 * T), n=30000, latency=1.5 * T)
    write_csv(rec, p)  # the metadata say td = 2 ms: the VE's own delay, not the rig's extra
    assert main(["analyze", "etfe", str(p), "--fit", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    fit = d["fit"]
    assert set(fit) >= {"m", "b", "td_s", "ci95", "td_meta_s", "residual_rms"}
    assert set(fit["ci95"]) == {"m", "b", "td_s"}
    assert abs(fit["td_s"] / T - 1.5) < 0.01 and fit["td_meta_s"] == 0.002
    # the theory overlay uses the fitted plant and delay, so it matches the data
    assert d["theory"]["plant_source"].startswith("fitted") and d["theory"]["deviation_median"] < 1e-3
    assert main(["analyze", "etfe", str(p), "--fit-ve"]) == 0
    out = capsys.readouterr().out
    assert "closed-loop fit" in out and "td  = " in out and "K   = " in out


def test_fit_needs_a_ve(tmp_path, capsys):
    rec = closed_loop_recording(SD, n=5000)
    rec.meta.pop("ve")
    p = tmp_path / "open.csv"
    write_csv(rec, p)
    assert main(["analyze", "etfe", str(p), "--fit"]) == 2
    assert "--fit needs the VE" in capsys.readouterr().err
    with pytest.raises(UserError, match="fit-ve needs a VE"):
        fit_loop(etfe(rec), VirtualEnvironment("none"), START, fit_ve=True)


@pytest.mark.parametrize("whole, fraction", [(0, 0.0), (1, 0.5), (3, 0.0)])
def test_fit_measures_the_simulator_latency_from_a_session(tmp_path, whole, fraction):
    # end to end: the etfe protocol on the simulator with an actuator latency the metadata
    # do not know, recorded to a session, analysed from the file
    from labbench.analysis.dataio import load_recording
    from labbench.registry import make_protocol
    from labbench.rig import Rig
    from labbench.runner import run
    from labbench.session_format import SessionWriter
    from labbench.sim_backend.sim_device import open_sim

    writer = SessionWriter(tmp_path)
    dev = open_sim(Rig(), seed=5, extra_delay_samples=whole, extra_delay_fraction=fraction)
    res = run(dev, make_protocol("etfe", duration_s=30.0, seed=5, K=20.0), [writer], rig=Rig())
    writer.close()
    assert res.status == "success", res.reason
    rec = load_recording(writer.path)
    fit = fit_loop(etfe(rec), compare.ve_from_meta(rec.meta, rec.fs), START)
    assert abs(fit.td_s / T - (whole + fraction)) < 0.01
    assert abs(fit.m / PAPER_M - 1) < 1e-3
