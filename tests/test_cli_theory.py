"""``labbench theory``: the CLI contract (keys, values, errors)."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from labbench.model import predictions
from labbench.model import linear
from labbench.cli import main
from labbench.model.ve import Plant, VirtualEnvironment

SD = ["theory", "--ve", "spring-damper", "--m", "0.1", "--b", "0.1", "--K", "50", "--B", "1",
      "--w0", "125"]


def run_cli(argv, capsys):
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse usage errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def strict_json(text):
    def no_constants(name):
        raise AssertionError(f"non-strict JSON constant {name}")
    return json.loads(text, parse_constant=no_constants)


@pytest.mark.parametrize("model", ["paper", "sampled"])
def test_json_keys_and_values(model, capsys):
    code, out, err = run_cli(SD + ["--td", "0.002", "--w", "1,10,100", "--model", model, "--json"],
                             capsys)
    assert code == 0, err
    d = strict_json(out)
    assert d["w"] == [1.0, 10.0, 100.0]
    plant = Plant(0.1, 0.1)
    ve = VirtualEnvironment("spring-damper", K=50, B=1, w0=125, td=0.002)
    w = np.array(d["w"])
    Z = linear.theory_curve(plant, ve, w, model)
    np.testing.assert_allclose(d["Z_re"], Z.real, rtol=1e-12)
    np.testing.assert_allclose(d["Z_im"], Z.imag, rtol=1e-12)
    np.testing.assert_allclose(d["ES"], -w * Z.imag, rtol=1e-12)
    np.testing.assert_allclose(d["ED"], Z.real, rtol=1e-12)
    np.testing.assert_allclose(d["EM"], Z.imag / w, rtol=1e-12)
    st = linear.stability(plant, ve)
    assert d["stable"] is st.stable is True
    assert d["spectral_radius"] == pytest.approx(st.spectral_radius, rel=1e-12)
    assert d["K_max"] == pytest.approx(linear.k_max(plant, ve), rel=1e-12)
    assert d["K_max_approx"] == pytest.approx(1.1 / 0.0025)
    # one truth (labbench.model.predictions): read off the exact sampled model, closed forms beside
    bw = predictions.bandwidths(plant, ve)
    assert (d["ws_star"], d["wb_star"], d["bandwidths_model"]) == (bw.ws_star, bw.wb_star, "sampled")
    assert d["ws_star_eq5"] == pytest.approx(math.sqrt(500)) and d["wb_star_w0"] == 125
    assert d["wb_star"] < 0.8 * 125  # the sampled loop loses damping well before w0


def test_json_damper_has_null_k_max_and_default_grid(capsys):
    code, out, _ = run_cli(["theory", "--ve", "damper", "--m", "0.1", "--b", "0.1", "--B", "1",
                            "--json"], capsys)
    assert code == 0
    d = strict_json(out)
    assert d["K_max"] is None and d["K_max_approx"] is None and d["ws_star"] is None
    assert d["wb_star_w0"] is None  # no filter: no closed form; the sampled curve's own reading
    bw = linear.predicted_bandwidths(Plant(0.1, 0.1), VirtualEnvironment("damper", B=1))
    assert d["wb_star"] == bw["wb_star"]
    assert len(d["w"]) == len(d["ED"]) > 10 and d["w"] == sorted(d["w"])
    assert d["stable"] is True


def test_unstable_spring_is_reported(capsys):
    code, out, _ = run_cli(["theory", "--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "300",
                            "--w", "5", "--json"], capsys)
    d = strict_json(out)
    assert code == 0 and d["stable"] is False and d["spectral_radius"] > 1
    assert d["K_max"] == pytest.approx(200.03, rel=1e-3)


def test_fractional_td_with_paper_model_has_no_sampled_stability(capsys):
    code, out, _ = run_cli(["theory", "--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10",
                            "--td", "0.0015", "--w", "1,2", "--json"], capsys)
    d = strict_json(out)
    assert code == 0 and d["stable"] is None and d["K_max"] is None
    assert d["K_max_approx"] == pytest.approx(0.1 / 0.002)


def test_table(capsys):
    code, out, _ = run_cli(SD + ["--w", "1,10,100,1000"], capsys)
    assert code == 0
    lines = out.strip().splitlines()
    assert "stable" in lines[1] and "K_max" in lines[1]
    rows = [ln for ln in lines if ln.strip() and ln.split()[0].replace(".", "").isdigit()]
    assert [float(r.split()[0]) for r in rows] == [1, 10, 100, 1000]


@pytest.mark.parametrize("suffix", [".png", ".svg", ".pdf"])
def test_plot_overlays_delays(tmp_path, suffix, capsys):
    path = tmp_path / f"fig{suffix}"
    code, out, err = run_cli(SD + ["--td", "0,0.002,0.005", "--plot", str(path)], capsys)
    assert code == 0, err
    assert len(out.strip().splitlines()) == 4  # one line per td, then "wrote ..."
    head = path.read_bytes()[:8]
    assert head.startswith({".png": b"\x89PNG", ".svg": b"<?xml", ".pdf": b"%PDF"}[suffix])


BAD = [
    ["--ve", "spring", "--m", "-1", "--b", "0.1", "--K", "10"],
    ["--ve", "spring", "--m", "0", "--b", "0.1", "--K", "10"],
    ["--ve", "wall", "--m", "0.1", "--b", "0.1", "--K", "10"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10", "--td", "0.0015",
     "--model", "sampled"],
    ["--ve", "spring", "--m", "heavy", "--b", "0.1", "--K", "10"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10", "--w", "1,x"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10", "--w", "0,1"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "nan"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1"],
    ["--ve", "damper", "--m", "0.1", "--b", "0.1", "--B", "1", "--K", "10"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10", "--w0", "100"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10", "--td", "0,0.001", "--json"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10", "--td", "0,0.001"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10", "--plot", "fig.jpg"],
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10", "--T", "0"],
    ["--ve", "spring-damper", "--m", "0.1", "--b", "0.01", "--K", "50", "--B", "1", "--w0", "125",
     "--w", "3200"],  # above pi/T: an alias (ED +4275 N s/m, silently, before)
    ["--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10", "--T", "0.002", "--w",
     "1,1571", "--model", "paper"],
]


@pytest.mark.parametrize("args", BAD, ids=[" ".join(a[1:]) for a in BAD])
def test_bad_input_is_one_line_exit_2(args, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(["theory", *args], capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert not list(tmp_path.iterdir())  # no figure written on error


def test_bad_input_through_the_console_entry_point():
    r = subprocess.run([sys.executable, "-m", "labbench.cli", "theory", "--ve", "spring",
                        "--m", "0.1", "--b", "0.1", "--K", "10", "--td", "0.0015",
                        "--model", "sampled"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and "whole number of samples" in r.stderr


def test_frequencies_up_to_nyquist_are_answered(capsys):
    code, out, _ = run_cli(["theory", "--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "10",
                            "--w", f"1,{math.pi / 0.001!r}", "--model", "sampled", "--json"], capsys)
    assert code == 0 and len(strict_json(out)["ED"]) == 2


@pytest.mark.parametrize("model", ["paper", "sampled"])
def test_each_field_says_which_model_it_is_of(model, capsys):
    """Under --model paper, stable and K_max are still the sampled loop's: the JSON says so,
    and so does the text."""
    code, out, _ = run_cli(SD + ["--w", "1,10", "--model", model, "--json"], capsys)
    d = strict_json(out)
    of = d["model_of"]
    assert {of[k] for k in ("Z_re", "Z_im", "ES", "ED", "EM")} == {model}
    assert {of[k] for k in ("stable", "spectral_radius", "stability_margin", "K_max")} == {"sampled"}
    assert of["K_max_approx"] == "paper" and of["ws_star"] == d["bandwidths_model"]
    assert set(of) <= set(d)
    code, out, _ = run_cli(SD + ["--w", "1,10", "--model", model], capsys)
    head = out.splitlines()
    assert f"{model} model" in head[0] and "sampled loop stable" in head[1]
    assert "N/m sampled (paper approx" in head[1]


def test_a_soft_spring_on_a_damped_device_is_stable_beside_its_k_max(capsys):
    """The issue's contradiction: K = 1e-4 N/m, b = 1000 N s/m said stable: false beside
    K_max = 2.5e6 N/m (tests/test_theory_edges.py checks it against a 40-digit reference)."""
    args = ["theory", "--ve", "spring", "--m", "0.1", "--b", "1000", "--K", "1e-4", "--w", "1"]
    code, out, _ = run_cli(args + ["--json"], capsys)
    d = strict_json(out)
    assert d["stable"] is True and d["K_max"] > 1e6
    assert d["stability_margin"] == pytest.approx(1e-10, rel=1e-3)
    code, out, _ = run_cli(args, capsys)
    assert "sampled loop stable (spectral radius 1 - 1e-10)" in out.splitlines()[1]
