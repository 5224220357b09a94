"""``labbench run``: JSON shape, sessions on disk, one-line errors with exit 2, the demo."""
from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from labbench.model import linear
from labbench.cli import main
from labbench.cli.progress import ProgressBar
from labbench.sessions.session_format import read_session
from labbench.model.ve import Plant, VirtualEnvironment

ROOT = Path(__file__).resolve().parents[1]


def _json(capsys, argv):
    code = main(argv)
    out = capsys.readouterr().out
    return code, json.loads(out)


def test_stability_json_keys_and_session(tmp_path, capsys):
    code, out = _json(capsys, ["run", "stability", "--td-s", "0.002", "--K", "30",
                               "--out", str(tmp_path), "--json"])
    assert code == 0
    assert set(out) >= {"protocol", "status", "reason", "session", "sessions", "results", "timing"}
    assert out["status"] == "success" and out["protocol"] == "stability"
    km = linear.k_max(Plant(0.094, 0.1), VirtualEnvironment("spring", 1.0, td=0.002))
    assert out["results"]["exact_boundary"] == pytest.approx(km)
    assert out["results"]["measured_boundary"] == pytest.approx(km, rel=0.01)
    recs = list(read_session(out["session"]))
    assert recs[0]["kind"] == "start" and recs[-1]["kind"] == "stop"
    assert recs[-1]["status"] == "success"
    assert recs[-1]["results"]["measured_boundary"] == pytest.approx(out["results"]["measured_boundary"])


def test_chirp_id_json_and_human_output(tmp_path, capsys):
    code, out = _json(capsys, ["run", "chirp-id", "--duration-s", "20", "--methods", "l2",
                               "--out", str(tmp_path), "--json"])
    assert code == 0
    fit = out["results"]["identification"]["l2"]
    assert fit["m"] == pytest.approx(0.094, rel=0.02) and fit["b"] == pytest.approx(0.10, rel=0.02)
    assert main(["run", "chirp-id", "--duration-s", "20", "--methods", "l2", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "chirp-id: success" in text and "mass m: 0.094 kg" in text and "identification (l2): ok" in text


def test_a_failed_analysis_is_never_success_exit_3_with_the_session_kept(tmp_path, capsys,
                                                                            monkeypatch):
    from labbench.analysis import identify
    from labbench.errors import UserError

    def refuses(*_a, **_kw):
        raise UserError("too little excitation to identify")

    monkeypatch.setattr(identify, "identify", refuses)
    argv = ["run", "chirp-id", "--duration-s", "12", "--methods", "l2", "--out", str(tmp_path)]
    code, out = _json(capsys, argv + ["--json"])
    assert code == 3
    assert out["status"] == "failed" and out["cause"] == "analysis"
    assert "analysis failed: too little excitation" in out["reason"]
    assert out["readout"]["title"] == "Analysis failed"
    stop = list(read_session(out["session"]))[-1]
    assert stop["status"] == "failed" and stop["cause"] == "analysis" and stop["n_samples"] > 0
    assert main(argv) == 3
    captured = capsys.readouterr()
    assert "chirp-id: failed (recorded, but the analysis failed: too little excitation" \
        in captured.out and "success" not in captured.out
    err = captured.err.strip().splitlines()
    assert err[-1].startswith("labbench run: error: recorded, but the analysis failed: too "
                              "little excitation") and "(session " in err[-1]


@pytest.mark.parametrize("argv,words", [
    (["run", "etfe", "--K", "-3"], "K must be >= 0"),
    (["run", "etfe", "--K", "abc"], "expected a number"),
    (["run", "etfe", "--ve", "spring", "--K", "400", "--B", "0", "--w0-rad-s", "none"],
     "refusing unstable spring"),
    (["run", "etfe", "--td-s", "0.0005"], "whole number of samples"),
    (["run", "etfe", "--device", "nope"], "invalid choice"),
    (["run", "chirp-id", "--rig", "/nonexistent/rig.toml"], "rig file not found"),
    (["run", "chirp-id", "--x-max-m", "0.09"], "outside the rig's window"),
    (["run", "demo", "--etfe-duration-s", "0"], "must be positive"),
])
def test_bad_options_exit_2_with_one_line(tmp_path, capsys, argv, words):
    try:
        code = main([*argv, "--out", str(tmp_path)])
    except SystemExit as e:  # argparse's own errors
        code = e.code
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and words in lines[0], err
    assert list(tmp_path.iterdir()) == []  # nothing recorded


def test_bad_option_in_a_real_process_is_one_line_no_traceback(tmp_path):
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    p = subprocess.run([sys.executable, "-m", "labbench.cli", "run", "etfe", "--ve", "spring",
                        "--K", "400", "--B", "0", "--w0-rad-s", "none", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=120, check=False, cwd=ROOT, env=env)
    assert p.returncode == 2
    assert p.stderr.count("\n") == 1 and "refusing unstable spring" in p.stderr
    assert "Traceback" not in p.stderr and p.stdout == ""


def test_demo_short_produces_sessions_and_report(tmp_path, capsys):
    code, out = _json(capsys, ["run", "demo", "--chirp-duration-s", "20", "--etfe-duration-s", "30",
                               "--out", str(tmp_path), "--json"])
    assert code == 0 and out["status"] == "success"
    assert len(out["sessions"]) == 2 and all(Path(p).exists() for p in out["sessions"])
    chirp, etfe = out["results"]["chirp-id"], out["results"]["etfe"]
    # the ETFE overlay uses the chirp's identified plant
    assert etfe["plant"] == {"m": chirp["m"], "b": chirp["b"]}
    start = next(iter(read_session(out["sessions"][1])))
    assert start["protocol"]["plant_m_kg"] == chirp["m"]
    assert start["plant_from"]["session"] == out["sessions"][0]  # and says whence, on record
    label = Path(out["sessions"][0]).stem.rsplit("_", 1)[0]
    assert out["readouts"]["etfe"]["plant"]["source"] == f"identified in {label}"
    assert start["protocol"]["K"] == 50.0 and start["protocol"]["w0_rad_s"] == 125.0
    assert etfe["deviation_vs_sampled"]["max_rel"] < 0.05
    assert Path(out["report"]["html"]).stat().st_size > 0
    assert Path(out["report"]["pdf"]).read_bytes()[:5] == b"%PDF-"


def test_ctrl_c_stops_safely_and_closes_the_session_as_aborted(tmp_path):
    """A real process, paced in real time, interrupted with SIGINT mid-run."""
    import signal
    import time

    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    # A lenient watchdog: on this shared machine a paced loop can stall for tens of ms,
    # and this test is about Ctrl-C, not pacing.
    rig = tmp_path / "rig.toml"
    rig.write_text("[safety]\nwatchdog_s = 2.0\n")
    out_dir = tmp_path / "sessions"
    p = subprocess.Popen([sys.executable, "-m", "labbench.cli", "run", "etfe", "--realtime",
                          "--rig", str(rig), "--duration-s", "30", "--seed", "1",
                          "--out", str(out_dir), "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    try:
        deadline = time.monotonic() + 60
        while not list(out_dir.glob("*.lbsession")) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)  # about a second of samples
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    result = json.loads(out)
    assert result["status"] == "aborted" and "Ctrl-C" in result["reason"]
    recs = list(read_session(result["session"]))
    assert recs[-1]["kind"] == "stop" and recs[-1]["status"] == "aborted"
    assert any(r["kind"] == "event" and r["name"] == "stop" for r in recs)
    n = recs[-1]["n_samples"]
    assert 300 < n < 30000


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_progress_bar_draws_on_a_terminal_only():
    tty = _Tty()
    now = [100.0]
    with ProgressBar("etfe", stream=tty, min_interval_s=0.0, clock=lambda: now[0]) as bar:
        bar(0.0, "start")
        now[0] += 12.0
        bar(0.25, "white-noise")  # 12 s for a quarter: 36 s to go
        now[0] += 3600.0
        bar(1.0, "analysis")
    text = tty.getvalue()
    assert "[########----------------------]  25.0% 0:12 ETA 0:36    white-noise" in text
    assert "ETA ?" in text  # nothing done yet: no estimate
    assert " 100.0% 1:00:12 ETA 0:00    analysis" in text and text.endswith("\n")
    pipe = io.StringIO()
    with ProgressBar("etfe", stream=pipe) as bar:
        bar(0.5, "x")
    assert pipe.getvalue() == ""


def test_etfe_uses_the_last_identified_plant_of_the_rig(tmp_path, capsys):
    rig = tmp_path / "heavy.toml"  # simulated device differs from the rig's nominal model
    rig.write_text('[rig]\nname = "heavy sim"\n[sim]\nm = 0.2\nb = 0.3\n')
    out = str(tmp_path / "s")
    code, chirp = _json(capsys, ["run", "chirp-id", "--rig", str(rig), "--duration-s", "20",
                                 "--methods", "l2", "--out", out, "--json"])
    assert code == 0 and chirp["results"]["m"] == pytest.approx(0.2, rel=0.02)
    code, etfe = _json(capsys, ["run", "etfe", "--rig", str(rig), "--duration-s", "10", "--seed", "2",
                                "--out", out, "--json"])
    assert code == 0
    assert etfe["results"]["plant"] == {"m": chirp["results"]["m"], "b": chirp["results"]["b"]}
    start = next(iter(read_session(etfe["session"])))
    assert start["plant"]["m"] == chirp["results"]["m"]
    assert start["plant_from"]["session"] == chirp["session"]  # where it came from, on record
    code, nominal = _json(capsys, ["run", "etfe", "--rig", str(rig), "--duration-s", "10",
                                   "--seed", "2", "--out", out, "--json", "--plant-from", "nominal"])
    assert nominal["results"]["plant"] == {"m": 0.094, "b": 0.10}
