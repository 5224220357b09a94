"""The device's own delay (labbench.model.device_delay): where it comes from, what the start
record and the analysis metadata say, and the theory that carries it."""
import json
import math

import numpy as np
import pytest

from labbench.model import device_delay
from labbench.model import linear
from labbench.device import DeviceDescription
from labbench.errors import UserError
from labbench.rig import Rig
from labbench.model.ve import Plant, VirtualEnvironment

PLANT = Plant(0.094, 0.10)
T = 0.001


def _desc(delay=0.0, why=""):
    return DeviceDescription("sim", "x", T, 5.0, (-0.1, 0.1), device_delay_s=delay,
                             device_delay_why=why)


def test_first_found_wins_given_rig_device_none():
    rig = Rig(measured_td_s=0.0015, measured_td_from="commissioning", source="r.toml")
    dev = _desc(0.001, "the drive applies the torque at the next SYNC")
    assert device_delay.resolve(rig, dev, explicit=0.002).as_dict() == {
        "s": 0.002, "source": "given", "origin": "given"}
    got = device_delay.resolve(rig, dev)
    assert (got.s, got.origin) == (0.0015, "rig") and "commissioning" in got.source
    got = device_delay.resolve(Rig(), dev)
    assert (got.s, got.origin) == (0.001, "device") and "next SYNC" in got.source
    assert device_delay.resolve(Rig(), _desc()) == device_delay.NONE
    assert device_delay.resolve() == device_delay.NONE


@pytest.mark.parametrize("bad", [-1e-3, 2.0, math.nan, math.inf, "1", True, None])
def test_a_bad_given_delay_is_one_error(bad):
    with pytest.raises(UserError, match="device delay"):
        device_delay.given(bad)


def test_recorded_delays_are_read_back_old_and_new_and_hostile_ones_are_not_trusted():
    new = {"device_delay": {"s": 0.001, "source": "canopen: next SYNC", "origin": "device"}}
    assert device_delay.from_start(new).as_dict() == new["device_delay"]
    old = {"precheck": {"measured_td": {"td_s": 0.0015, "source": "rig.toml"}}}
    assert device_delay.from_start(old).as_dict() == {"s": 0.0015, "source": "rig.toml", "origin": "rig"}
    for hostile in ({"device_delay": "1 ms"}, {"device_delay": {"s": -1}},
                    {"device_delay": {"s": 1e308}}, {"precheck": "x"},
                    {"precheck": {"measured_td": {"td_s": "x"}}}, "start", None):
        assert device_delay.from_start(hostile) == device_delay.NONE
    assert device_delay.from_meta({"device_delay_s": "0.002"}) == 0.002
    assert device_delay.from_meta({"td_measured": 0.001}) == 0.001
    assert device_delay.from_meta({}) == 0.0
    with pytest.raises(UserError, match="device_delay_s"):
        device_delay.from_meta({"device_delay_s": "soon"})
    with pytest.raises(UserError, match="device_delay_s"):
        device_delay.from_meta({"device_delay_s": -0.001})


def test_a_run_records_the_declared_delay_and_its_analysis_uses_it(tmp_path):
    # a device declaring a one-period delay, without a rig measurement: the start record, the
    # precheck and the analysis metadata all carry it, and the identification shifts the force
    from dataclasses import replace

    from labbench.sessions import session_content
    from labbench.registry import make_protocol
    from labbench.runner import run
    from labbench.sessions.session_format import SessionWriter
    from labbench.sim_backend.sim_device import open_sim

    dev = open_sim(Rig(), seed=1, extra_delay_samples=1)
    declared = replace(dev.describe(), device_delay_s=T, device_delay_why="commands take effect one tick late")
    dev.describe = lambda: declared
    writer = SessionWriter(tmp_path / "s")
    res = run(dev, make_protocol("chirp-id"), [writer])
    writer.close()
    assert res.status == "success", res.reason
    start, desc, *_ = session_content.load_session(writer.path)
    assert start["device_delay"] == {"s": T, "origin": "device",
                                     "source": "sim: commands take effect one tick late"}
    assert start["precheck"]["device_delay"] == start["device_delay"]
    assert session_content.analysis_meta(start, desc)["device_delay_s"] == T
    # the plant's truth is the default one: the delayed regression finds it
    assert res.results["m"] == pytest.approx(PLANT.m, rel=0.01)
    assert res.results["b"] == pytest.approx(PLANT.b, rel=0.05)


def test_theory_with_a_device_delay_is_e_jw_latency_times_the_felt_impedance():
    # both models: Z_measured = e^{jw L} Z_felt, Z_felt = the model with td + L on the VE and
    # no latency (same poles: the same K_max); the exact sampled model keeps its e^{jwT/2}
    # relation to eq. 2 at low frequency
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=T, td=T)
    w = np.geomspace(1.0, 300.0, 40)
    L = 2 * T
    felt = linear.z_paper(PLANT, ve.with_(td=ve.td + L), w)
    assert np.allclose(linear.z_paper(PLANT, ve, w, L), np.exp(1j * w * L) * felt, rtol=1e-12)
    felt_s = linear.z_sampled(PLANT, ve.with_(td=ve.td + L), w)
    assert np.allclose(linear.z_sampled(PLANT, ve, w, L), np.exp(1j * w * L) * felt_s, rtol=1e-9)
    low = w < 20
    ratio = linear.z_sampled(PLANT, ve, w, L)[low] / linear.z_paper(PLANT, ve, w, L)[low]
    assert np.allclose(ratio, np.exp(1j * w[low] * T / 2), rtol=2e-3)
    assert linear.k_max(PLANT, ve, latency=L) == pytest.approx(
        linear.k_max(PLANT, ve.with_(td=ve.td + L)), rel=1e-3)


def test_the_measured_low_frequency_ed_does_not_see_the_device_delay_but_the_felt_one_does():
    ve = VirtualEnvironment("spring", K=50.0, T=T, td=0.0)
    with_delay = linear.delay_effects(PLANT, ve, latency=3 * T)
    without = linear.delay_effects(PLANT, ve)
    for model in ("paper", "sampled"):
        assert with_delay[f"ED_low_{model}"] == pytest.approx(without[f"ED_low_{model}"], abs=1e-6)
    assert with_delay["K_tau_felt"] == pytest.approx(50.0 * (T / 2 + 3 * T))


def test_cli_theory_device_delay(capsys):
    from labbench.cli import main

    args = ["theory", "--ve", "spring", "--m", "0.094", "--b", "0.1", "--K", "50",
            "--w", "1,10,100", "--model", "sampled", "--json"]
    assert main(args + ["--device-delay-s", "0.0015"]) == 0
    d = json.loads(capsys.readouterr().out)
    ve = VirtualEnvironment("spring", K=50.0, T=T)
    Z = linear.z_sampled(PLANT, ve, [1.0, 10.0, 100.0], 0.0015)
    assert d["Z_re"] == pytest.approx(Z.real.tolist()) and d["device_delay_s"] == 0.0015
    assert d["K_max"] == pytest.approx(linear.k_max(PLANT, ve, latency=0.0015), rel=1e-3)
    assert main(args + ["--device-delay-s", "-1"]) == 2
    assert "--device-delay-s" in capsys.readouterr().err
