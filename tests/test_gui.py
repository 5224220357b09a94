"""The desktop application, offscreen: runs on the simulator, e-stop, replay, export, errors."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import functools  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

import h5py  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from PySide6 import QtCore  # noqa: E402

from labbench.gui.app import run_app  # noqa: E402
from labbench.gui.live_estimate import estimate  # noqa: E402
from labbench.analysis.compare import ve_from_meta  # noqa: E402
from labbench.gui.live_estimate import LIVE as LIVE_ESTIMATOR  # noqa: E402
from labbench.gui.live_view import IDENTIFIED  # noqa: E402
from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.rig import Rig  # noqa: E402
from labbench.sessions.session_catalogue import list_sessions  # noqa: E402
from labbench.sessions.session_content import analysis_meta, load_session  # noqa: E402
from labbench.model.ve import Plant  # noqa: E402

TRUTH = Plant(0.094, 0.10)  # the simulator's default plant (labbench.sim_backend.sim_device)
RUN_TIMEOUT_MS = 60_000


@pytest.fixture
def make_window(qtbot, tmp_path):
    def make(realtime=False, rig=None):
        win = MainWindow(rig or Rig(), tmp_path / "sessions", realtime=realtime)
        qtbot.addWidget(win)
        win.show()
        return win

    return make


def start(win, protocol, **settings):
    win.protocol_panel.choice.setCurrentText(protocol)
    for name, value in settings.items():
        win.protocol_panel.set_value(name, value)
    win.start_protocol()


def wait_run_done(qtbot, win, timeout=RUN_TIMEOUT_MS):
    qtbot.waitUntil(lambda: win.last_run is not None and win.mode == "idle", timeout=timeout)


def wait_final_estimate(qtbot, win, timeout=RUN_TIMEOUT_MS):
    """The estimate of the whole run, made after its end (with the run's own estimator)."""
    qtbot.waitUntil(lambda: win.live.impedance.last is not None and win.mode == "idle"
                    and win.live.impedance.last.n_samples == win.live.buffer.n
                    and win.live.impedance.last.estimator != LIVE_ESTIMATOR, timeout=timeout)


def test_etfe_run_on_simulator_fills_plots_with_the_recorded_data(qtbot, make_window):
    win = make_window()
    win.live.theory_plant.setCurrentIndex(IDENTIFIED)
    start(win, "etfe", duration_s=6.0, seed=5)
    wait_run_done(qtbot, win)
    wait_final_estimate(qtbot, win)
    assert win.last_run.status == "success", win.last_run.reason
    assert win.live.buffer.n == 6000

    # time traces: the last 5000 samples of the stream per channel, as what their line
    # covers in each pixel column: one span (low, high) a column, at its centre
    t = win.live.buffer.channel("t")[-5000:]
    for name in ("position", "velocity", "command", "excitation"):
        x, y = win.live.traces.curves[name].getOriginalDataset()
        raw = win.live.buffer.channel(name)[-5000:]
        vb = win.live.traces.plots[{"command": "force", "excitation": "force"}.get(name, name)].getViewBox()
        (x0, x1), _ = vb.viewRange()
        columns = (t[-1] - t[0]) / (x1 - x0) * vb.width() * win.live.traces.devicePixelRatioF()
        assert columns - 2 <= x.size / 2 <= columns + 2
        assert np.all(x[0::2] == x[1::2]) and np.all(y[0::2] <= y[1::2])
        assert y.min() == raw.min() and y.max() == raw.max()
        assert x[0] < t[0] - t[-1] + 0.02 and x[-1] > -0.02

    # the session on disk holds the same stream, plus what the settings form showed
    summaries = list_sessions(win.session_dir)
    assert len(summaries) == 1 and summaries[0].n_samples == 6000
    start_rec, desc, ch, _events, stop, problem = load_session(summaries[0].path)
    assert problem is None and stop["status"] == "success"
    assert start_rec["gui_settings"]["K"] == "50"  # as the form showed it
    np.testing.assert_array_equal(ch["position"], win.live.buffer.channel("position"))

    # the drawn estimate is the ETFE of the recorded data, with the theory for the identified plant
    est = win.live.impedance.last
    meta = analysis_meta(start_rec, desc)
    again = estimate({k: ch[k] for k in ch}, meta, ve_from_meta(meta), None)
    np.testing.assert_allclose(est.Z, again.Z, rtol=1e-12)
    # the simulator is exact and noise-free: l2 on the commanded force recovers its plant
    assert est.plant_source == "identified (l2)"
    assert est.plant.m == pytest.approx(TRUTH.m, rel=0.01)
    assert est.plant.b == pytest.approx(TRUTH.b, rel=0.05)
    from labbench.model.linear import theory_curve

    wt, yt = win.live.impedance.curves["ED_theory"].getOriginalDataset()
    Zt = theory_curve(est.plant, ve_from_meta(meta), est.theory["w"], "sampled")
    shown = np.isfinite(yt)  # up to a third of Nyquist
    assert shown.sum() > 300 and wt[shown].max() == pytest.approx(np.pi * 1000 / 3, rel=0.01)
    np.testing.assert_allclose(yt[shown], Zt.real[shown], rtol=1e-9)
    # the ETFE follows the exact theory of the true plant over the paper's band (2-100 rad/s):
    # the simulator is noise-free, so only estimator bias remains (0.09 % median seen here)
    band = (est.w >= 2) & (est.w <= 100)
    Zb = theory_curve(TRUTH, ve_from_meta(meta), est.w[band], "sampled")
    assert np.median(np.abs(est.Z[band] - Zb) / np.abs(Zb)) < 0.01
    # w_s* is marked where the measured ES crosses zero, as it does on the exact theory curve
    from labbench.model.effective import effective_impedances, measured_ws_star

    wg = np.geomspace(1, 300, 3000)
    ws_true = measured_ws_star(wg, effective_impedances(wg, theory_curve(
        TRUTH, ve_from_meta(meta), wg, "sampled")).ES)
    assert win.live.impedance.marks["ws"].isVisible()
    assert 10 ** win.live.impedance.marks["ws"].value() == pytest.approx(est.ws_measured)
    assert est.ws_measured == pytest.approx(ws_true, rel=0.05)


def test_live_estimate_updates_during_a_realtime_run(qtbot, make_window):
    # a 1 s watchdog: on a loaded machine one stall over the default 50 ms trips the loop
    # (as it should on hardware) and ends the run before the live view has been watched
    win = make_window(realtime=True, rig=Rig(sections={"safety": {"watchdog_s": 1.0}}))
    start(win, "etfe", duration_s=5.0, seed=2)
    qtbot.waitUntil(lambda: win.mode == "running", timeout=10_000)
    seen, stalls = [], []

    def watch():
        seen.append((win.live.impedance.updates, win.mode))
        stalls.append(win.loop_status.labels["worst stall"].text())
        return win.mode == "idle"

    qtbot.waitUntil(watch, timeout=RUN_TIMEOUT_MS)
    during = max(u for u, mode in seen if mode == "running")
    # 5 s of data, estimates from 2 s on, every 0.5 s: several while the run goes on
    assert during >= 2, seen[-5:]
    assert win.live.traces.frames >= 20
    # the loop's timing reached the status bar while the run went on, then its total
    assert any(t.startswith("worst stall: ") and t.endswith("(live)") for t in stalls)
    timing = win.last_run.timing
    assert stalls[-1].startswith(f"worst stall: {timing['max_s'] * 1e3:.2f} ms")
    assert win.loop_status.labels["overruns"].text() == f"overruns: {timing['overruns']}"
    assert timing["realtime"]["requested"] and sum(timing["histogram"]["counts"]) > 4000


def test_chirp_id_fills_identification_view(qtbot, make_window):
    win = make_window()
    start(win, "chirp-id", f0_hz=0.5, duration_s=4.0)
    wait_run_done(qtbot, win)
    assert win.last_run.status == "success"
    view = win.id_view
    assert set(view.results) == {"l2", "l1"}
    for method in ("l2", "l1"):
        assert view.results[method]["m"] == pytest.approx(TRUTH.m, rel=0.01)
    rows = [view.table.verticalHeaderItem(i).text() for i in range(view.table.rowCount())]
    assert rows[:2] == ["mass m", "damping b"]  # each with its unit and interval in the cell
    assert view.table.item(0, 0).text().startswith("0.094") and " kg" in view.table.item(0, 0).text()
    assert "rms force residual (N)" in rows and "derivative cut-off (Hz)" in rows
    assert not any("_" in r for r in rows)  # labels, not internal keys
    assert "model chosen: mb" in view.chosen.text()
    # the open-loop impedance of the chirp against the identified Z = b + j w m
    w, z_meas = view.z_measured.getOriginalDataset()  # SI, not the log axes' values
    _, z_model = view.z_model.getOriginalDataset()
    assert len(w) > 10 and w.max() <= np.pi * 1000 * 0.3
    assert np.median(np.abs(z_meas - z_model) / z_model) < 0.01  # exact plant: ETFE bias only
    # the true plant's exact sampled Z (the continuous b + j w m is 3.7 % under it at 0.3 fs)
    from labbench.analysis.compare import theory_curves
    from labbench.model.ve import VirtualEnvironment

    exact = np.abs(theory_curves(TRUTH, VirtualEnvironment("none", T=1e-3), w)["Z"])
    np.testing.assert_allclose(z_model, exact, rtol=0.02)
    # residual of the fitted samples: the model explains an exact plant's force
    t, resid = view.residual.getData()
    assert len(t) == view.results["l2"]["n_used"]
    force = win.live.buffer.snapshot()["command"]
    assert np.sqrt(np.mean(resid**2)) < 1e-3 * np.sqrt(np.mean(force**2))


def test_estop_label_fits_and_enable_button_follows_the_device(qtbot, make_window):
    from PySide6 import QtGui

    win = make_window()
    button = win.estop
    for latched in (False, True):
        button.set_latched(latched)
        qtbot.waitUntil(lambda: button.height() >= button.minimumHeight(), timeout=2_000)
        box = QtGui.QFontMetrics(button.font()).boundingRect(
            button.contentsRect(), int(QtCore.Qt.AlignmentFlag.AlignCenter), button.text())
        assert button.contentsRect().contains(box), (latched, box, button.contentsRect())
    button.set_latched(False)
    panel, shown = win.device_panel, []
    set_enabled = panel.set_enabled

    def spy(on):  # what the button said each time the window learnt the device's state
        set_enabled(on)
        shown.append((win.mode, panel.enable_button.text()))

    panel.set_enabled = spy
    start(win, "chirp-id", f0_hz=0.5, duration_s=4.0)
    wait_run_done(qtbot, win)
    # the run enabled the device: the button offered to disable it; at the end, to enable
    assert ("running", "Disable") in shown and shown[-1][1] == "Enable"


def test_estop_key_zeroes_force_and_stops_the_run(qtbot, make_window):
    win = make_window(realtime=True)
    start(win, "etfe", duration_s=60.0, seed=1)
    qtbot.waitUntil(lambda: win.live.buffer.n > 300, timeout=20_000)
    # the loop runs in its own process, which has not loaded Qt
    with open(f"/proc/{win.acquisition.process.pid}/maps") as f:
        maps = f.read()
    assert "python" in maps and "Qt6" not in maps and "PySide6" not in maps
    win.activateWindow()
    qtbot.keyClick(win, QtCore.Qt.Key.Key_Escape)
    # the key sets the shared event the acquisition process's e-stop thread is blocked on
    assert win.acquisition.estop.is_set()
    assert win.estop.latched and "LATCHED" in win.estop.text()
    # that thread emergency-stops the device itself (it latches: health says so)
    qtbot.waitUntil(lambda: win.estop_confirmed, timeout=5_000)
    qtbot.waitUntil(lambda: win.health.get("state") == "E-STOP latched", timeout=5_000)
    wait_run_done(qtbot, win, timeout=10_000)
    assert win.last_run.status in ("aborted", "failed")
    qtbot.waitUntil(lambda: win.device_panel.health["state"].text() == "E-STOP latched",
                    timeout=5_000)  # the device panel shows the child's report
    assert win.live.buffer.n < 20_000
    assert any("E-STOP" in t for t in win.log.texts("warning"))
    win.start_protocol()  # refused while the latch holds
    assert "E-STOP is latched" in win.banner.text() and win.mode == "idle"


def test_unstable_settings_are_refused_with_a_message(qtbot, make_window):
    win = make_window()
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("ve", "spring")
    win.protocol_panel.set_value("K", 5000.0)
    assert "refusing unstable" in win.protocol_panel.precheck.text()
    win.start_protocol()
    qtbot.waitUntil(lambda: win.banner.isVisible(), timeout=10_000)
    assert "refusing unstable" in win.banner.text()
    assert any("refusing unstable" in t for t in win.log.texts("error"))
    assert win.mode == "idle" and win.protocol_panel.start_button.isEnabled()
    assert not list(win.session_dir.glob("*.lbsession"))


def test_typed_settings_are_parsed_and_a_bad_one_is_named(qtbot, make_window):
    """The settings form as a person types into it: numbers as text, empty = default."""
    win = make_window()
    panel = win.protocol_panel
    panel.choice.setCurrentText("etfe")
    fields = panel.form.fields
    for name, text in (("K", "1.5e2"), ("seed", "3000000017"), ("band_hi_hz", "40")):
        fields[name].widget.clear()
        qtbot.keyClicks(fields[name].widget, text)
    fields["estimator"].widget.setCurrentText("(default)")
    values = panel.values()
    assert (values["K"], values["seed"], values["band_hi_hz"]) == (150.0, 3_000_000_017, 40.0)
    assert values["estimator"] is None and values["plant_m_kg"] is None
    assert win.make_protocol().seed == 3_000_000_017
    # a word where a number goes: framed red, named in the pre-check, Start refused
    fields["B"].widget.clear()
    qtbot.keyClicks(fields["B"].widget, "1,5")
    assert "B: '1,5' is not a number" in panel.precheck.text()
    assert "b00020" in fields["B"].widget.styleSheet() and not fields["K"].widget.styleSheet()
    win.start_protocol()
    assert "B: '1,5' is not a number" in win.banner.text() and win.mode == "idle"
    # below the unit's lower limit, and a fraction for a whole number
    fields["B"].widget.setText("-1")
    assert "B: -1 is below 0 N s/m" in panel.precheck.text()
    fields["B"].widget.setText("1")
    fields["window"].widget.setText("200.5")
    assert "window: '200.5' is not a whole number" in panel.precheck.text()
    fields["window"].widget.setText("256")
    assert panel.values()["window"] == 256 and not fields["B"].widget.styleSheet()
    assert "refusing" not in panel.precheck.text() and "not a" not in panel.precheck.text()


def test_device_fault_mid_run_is_reported_not_raised(qtbot, make_window):
    from gui_faulty_device import open_faulty  # importable in the acquisition process: no Qt

    win = make_window()
    win.connect_device("sim", opener=functools.partial(open_faulty, n_ok=1500))
    qtbot.waitUntil(lambda: win.device is not None, timeout=20_000)
    start(win, "etfe", duration_s=5.0, seed=1)
    wait_run_done(qtbot, win)
    assert win.last_run.status == "failed"
    assert win.banner.isVisible() and "over-current" in win.banner.text()
    assert win.live.buffer.n < 5000


def test_a_host_stall_does_not_end_a_simulated_run(qtbot, make_window):
    """A sleep of 0.3 s in the acquisition process (six times the watchdog) mid-run: the
    simulator's run goes on, the stall is in the log, the timing and the session."""
    from gui_faulty_device import open_stalling

    win = make_window(realtime=True)
    win.connect_device("sim", opener=functools.partial(open_stalling, at=1000, stall_s=0.3))
    qtbot.waitUntil(lambda: win.device is not None, timeout=20_000)
    start(win, "etfe", duration_s=2.5, seed=1)
    wait_run_done(qtbot, win)
    assert win.last_run.status == "success", win.last_run.reason
    assert win.live.buffer.n == 2500 and not win.banner.isVisible()
    assert any("host stall" in t and "run goes on" in t for t in win.log.texts("event"))
    assert win.last_run.timing["max_s"] >= 0.3
    assert "worst stall: 3" in win.loop_status.labels["worst stall"].text()  # 300-odd ms
    start_rec = load_session(win.session_path)[0]
    assert start_rec["watchdog"]["applies"] == "simulator"


def test_replay_session_through_the_live_view(qtbot, make_window):
    win = make_window()
    start(win, "etfe", duration_s=4.0, seed=3)
    wait_run_done(qtbot, win)
    wait_final_estimate(qtbot, win)
    recorded = win.live.buffer.snapshot()
    z_live = win.live.impedance.last.Z
    win.refresh_sessions()
    qtbot.waitUntil(lambda: len(win.sessions.paths) == 1, timeout=10_000)
    win.sessions.buttons["Replay fast"].click()
    qtbot.waitUntil(lambda: win.mode == "idle" and win.live.buffer.stop is not None, timeout=20_000)
    wait_final_estimate(qtbot, win)
    for name in ("t", "position", "command"):
        np.testing.assert_array_equal(win.live.buffer.channel(name), recorded[name])
    np.testing.assert_allclose(win.live.impedance.last.Z, z_live, rtol=1e-12)


def test_export_session_data_and_report(qtbot, make_window):
    win = make_window()
    start(win, "chirp-id", f0_hz=0.5, duration_s=3.0, model="mb")
    wait_run_done(qtbot, win)
    qtbot.waitUntil(lambda: len(win.sessions.paths) == 1, timeout=10_000)
    out = win.session_dir / "exports"
    for fmt in ("hdf5", "csv"):
        win.sessions.buttons[f"Export {fmt.upper()}"].click()
    qtbot.waitUntil(lambda: sum("exported" in t for t in win.log.texts("info")) >= 2,
                    timeout=20_000)  # both jobs finished, not just their files created
    with h5py.File(next(out.glob("*.h5")), "r") as f:
        np.testing.assert_array_equal(f["channels/position"][()], win.live.buffer.channel("position"))
    win.sessions.buttons["Export report"].click()
    qtbot.waitUntil(lambda: any("exported" in t and ".pdf" in t for t in win.log.texts("info")),
                    timeout=RUN_TIMEOUT_MS)
    html = next(out.rglob("*.html"))
    assert html.stat().st_size > 0 and next(out.rglob("*.pdf")).stat().st_size > 0


def test_bad_session_file_gives_a_message(qtbot, make_window, tmp_path):
    win = make_window()
    junk = tmp_path / "junk.lbsession"
    junk.write_bytes(b"not a session at all")
    win.replay(str(junk), None)
    assert win.banner.isVisible() and "not a labbench session" in win.banner.text()
    assert win.mode == "idle"


DEMO_SCRIPT = """
import sys
from labbench.gui.app import run_app
from labbench.rig import Rig
from PySide6 import QtGui
code = run_app(Rig(), sys.argv[1] + "/s", demo=True, screenshot=sys.argv[1] + "/shot.png", timeout_s=60,
               demo_settings={"duration_s": 3.0, "seed": 1}, realtime=False)
img = QtGui.QImage(sys.argv[1] + "/shot.png")
print(code, img.width(), img.height())
"""


def test_demo_screenshot_in_process(tmp_path):
    """run_app's own event loop and quit, in a process of its own: after its app.quit() a later
    window of the same process never heard back from its acquisition process."""
    out = subprocess.run([sys.executable, "-c", DEMO_SCRIPT, str(tmp_path)], capture_output=True,
                         text=True, timeout=120, env={**os.environ, "QT_QPA_PLATFORM": "offscreen"})
    code, width, height = map(int, out.stdout.split()[-3:])
    assert code == 0, out.stderr
    assert width >= 1200 and height >= 800


def test_cli_does_not_import_qt_until_gui_runs():
    code = ("import sys, labbench.cli as c; c.build_parser().parse_args(['gui', '--demo']); "
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith(('PySide6', 'pyqtgraph')))))")
    out = subprocess.run([sys.executable, "-c", "import json; " + code], capture_output=True,
                         text=True, timeout=60, check=True)
    assert json.loads(out.stdout) == []


def test_cli_refuses_headless_window_without_screenshot(monkeypatch, capsys, tmp_path):
    from labbench.cli import main

    monkeypatch.chdir(tmp_path)
    for var in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM"):
        monkeypatch.delenv(var, raising=False)
    assert main(["gui"]) == 2
    assert "no display" in capsys.readouterr().err


def test_cli_names_the_library_qts_x11_plugin_lacks(monkeypatch, capsys, tmp_path):
    # Qt 6.5+ aborts with "could not load the Qt platform plugin xcb" and no name on a fresh
    # Ubuntu desktop (no libxcb-cursor0): the command says which library, in one line, first
    import ctypes

    from labbench.cli import main

    def cdll(path, *args, **kwargs):
        if path.endswith("libqxcb.so"):
            raise OSError("libxcb-cursor.so.0: cannot open shared object file: No such file")
        return real(path, *args, **kwargs)

    def no_window(*args, **kwargs):  # a regression fails here, not in Qt's abort
        raise AssertionError("the window was opened")

    real = ctypes.CDLL
    monkeypatch.setattr(ctypes, "CDLL", cdll)
    monkeypatch.setattr("labbench.gui.app.run_app", no_window)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DISPLAY", ":99")
    monkeypatch.delenv("QT_QPA_PLATFORM", raising=False)
    assert main(["gui"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "libxcb-cursor.so.0 is missing" in err
    assert "apt install libxcb-cursor0" in err
    monkeypatch.setenv("QT_QPA_PLATFORM", "offscreen")  # not X11: not checked
    from labbench.cli.gui import check_x11_plugin
    check_x11_plugin()


@pytest.mark.slow
def test_cli_demo_screenshot(tmp_path):
    shot = tmp_path / "demo.png"
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    subprocess.run([sys.executable, "-m", "labbench.cli", "gui", "--demo", "--sessions",
                    str(tmp_path / "s"), "--screenshot", str(shot)], env=env, check=True,
                   timeout=240, cwd=tmp_path)
    assert shot.stat().st_size > 10_000


PARENT_SCRIPT = """
import os, signal, sys, time
from labbench.gui.acquisition import Acquisition
from labbench.gui.worker import Mailbox
from labbench.registry import open_device
from labbench.rig import Rig
import functools

mailbox = Mailbox()
acq = Acquisition(mailbox)
acq.connect(functools.partial(open_device, "sim"), Rig(), {"realtime": True})
acq.run("etfe", {"duration_s": 60.0, "seed": 1}, Rig(), sys.argv[1], None, simulated=True)
deadline = time.monotonic() + 60
records = 0
while records < 5 and time.monotonic() < deadline:  # the run is streaming
    records += sum(kind == "record" for kind, _ in mailbox.drain())
    time.sleep(0.05)
print(acq.process.pid, records, flush=True)
os.kill(os.getpid(), signal.SIGKILL)  # the GUI process dies without any cleanup
"""


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/status") as f:
            return any(line.startswith("State:") and "Z" in line for line in f)
    except FileNotFoundError:
        return True


def test_acquisition_process_stops_the_run_when_the_gui_process_dies(qtbot, tmp_path):
    """The parent watchdog: a killed GUI process leaves no device driven and no process behind."""
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": repo}
    out = subprocess.run([sys.executable, "-c", PARENT_SCRIPT, str(tmp_path)], capture_output=True,
                         text=True, timeout=120, env=env, check=False)  # it kills itself
    pid, records = map(int, out.stdout.split())
    assert records >= 5, out.stderr
    qtbot.waitUntil(lambda: _gone(pid), timeout=15_000)
    # the run was ended by the runner (force zero, device disabled): its session has a stop record
    (path,) = tmp_path.glob("*.lbsession")
    _start, _desc, ch, _events, stop, problem = load_session(path)
    assert problem is None and stop is not None and stop["status"] in ("aborted", "failed")
    assert len(ch["t"]) < 60_000


def test_acquisition_flags_never_block_on_a_process_that_died_waiting():
    """The E-STOP and Stop flags shared with the acquisition process: setting them returns at
    once even when a process was killed in the middle of waiting on them. (A
    multiprocessing.Event's set() waits for every waiter to wake; a waiter that cannot, a
    daemon thread frozen in a child's exit, blocked the window's close for ever.)"""
    import multiprocessing as mp
    import signal
    import threading

    from gui_faulty_device import wait_on
    from labbench.gui.acquisition import SharedFlag

    ctx = mp.get_context("spawn")
    flag, ready = SharedFlag(ctx), SharedFlag(ctx)
    waiter = ctx.Process(target=wait_on, args=(flag, ready), daemon=True)
    waiter.start()
    assert ready.wait(30.0)
    os.kill(waiter.pid, signal.SIGKILL)
    waiter.join(10.0)
    assert not waiter.is_alive()
    done = threading.Event()
    threading.Thread(target=lambda: (flag.set(), done.set()), daemon=True).start()
    assert done.wait(5.0) and flag.is_set()
    flag.clear()
    assert not flag.is_set() and not flag.wait(0.01)


def test_window_remembers_its_state_after_a_restart(qtbot, tmp_path):
    """Geometry, splitters, tab, backend, protocol and its settings, rig file and sessions
    folder come back in a new window (a temporary settings file)."""
    from labbench.gui.settings import open_settings, remembered_paths
    from labbench.rig import load_rig

    ini = tmp_path / "settings.ini"
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text('[rig]\nname = "remembered rig"\n')
    folder = tmp_path / "my sessions"
    folder.mkdir()
    win = MainWindow(load_rig(str(rig_file)), folder, settings=open_settings(ini))
    qtbot.addWidget(win)
    win.show()
    win.resize(1234, 720)  # the offscreen screen is 800 x 800: restores clamp to it
    win.splitters["live"].setSizes([300, 900])
    win.tabs.setCurrentIndex(2)
    win.device_panel.backend.setCurrentText("sim-serial")
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("K", 77.0)
    win.protocol_panel.set_value("duration_s", 33.0)
    win.protocol_panel.choice.setCurrentText("chirp-id")  # etfe's settings are kept
    win.protocol_panel.set_value("f1_hz", 12.5)
    live_sizes = win.splitters["live"].sizes()
    win.close()

    settings = open_settings(ini)
    assert remembered_paths(settings, None, None, "sessions") == (str(rig_file.resolve()),
                                                                  str(folder.resolve()))
    assert remembered_paths(settings, "other.toml", "here", "sessions") == ("other.toml", "here")
    again = MainWindow(load_rig(str(rig_file)), folder, settings=settings)
    qtbot.addWidget(again)
    again.show()
    assert again.height() == 720  # a fresh window would be 1000 tall, clamped to the screen
    sizes = again.splitters["live"].sizes()  # a narrower window: the same split
    assert sizes[0] / sum(sizes) == pytest.approx(live_sizes[0] / sum(live_sizes), abs=0.01)
    assert live_sizes[0] / sum(live_sizes) == pytest.approx(0.25, abs=0.01)  # not the default
    assert again.tabs.currentIndex() == 2
    assert again.device_panel.backend.currentText() == "sim-serial"
    assert again.protocol_panel.choice.currentText() == "chirp-id"
    assert again.protocol_panel.values()["f1_hz"] == 12.5
    again.protocol_panel.choice.setCurrentText("etfe")
    assert again.protocol_panel.values()["K"] == 77.0
    assert again.protocol_panel.values()["duration_s"] == 33.0
    again.close()
    rig_file.unlink()  # a rig file that is gone is not offered again
    assert remembered_paths(open_settings(ini), None, None, "sessions")[0] is None


def test_window_without_settings_remembers_nothing(qtbot, make_window):
    win = make_window()
    win.protocol_panel.choice.setCurrentText("chirp-id")
    win.close()
    assert make_window().protocol_panel.choice.currentText() == win.protocol_panel.choice.itemText(0)


def test_a_large_seed_is_shown_as_it_is(qtbot, make_window):
    win = make_window()
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("seed", 3_000_000_017)  # above 2^31: was clamped
    assert win.protocol_panel.values()["seed"] == 3_000_000_017
    assert win.make_protocol().seed == 3_000_000_017


def test_live_axes_follow_the_trusted_estimate(qtbot):
    """Points whose 95 % radius exceeds a quarter of |Z| are drawn but do not set the range
    (early in a white-noise run they spanned +-400 000 N/m and flattened the curve)."""
    from labbench.model import linear
    from labbench.model.effective import effective_impedances
    from labbench.gui.live_estimate import Estimate
    from labbench.gui.live_plots import ImpedancePlots
    from labbench.model.ve import VirtualEnvironment

    plots = ImpedancePlots()
    qtbot.addWidget(plots)
    ve = VirtualEnvironment("spring-damper", 50.0, 1.0, 125.0, 0.001, 0.0)
    w = np.geomspace(1.0, 1000.0, 200)
    Z = linear.z_sampled(TRUTH, ve, w)
    Z_err = 0.01 * np.abs(Z)
    wild = w < 3.0  # few averages down there yet: wild values, wide bands
    Z = np.where(wild, Z * (1 - 2e5j), Z)
    Z_err = np.where(wild, 3e4 * np.abs(Z), Z_err)
    eff = effective_impedances(w, Z)
    plots.show_estimate(Estimate(6000, w, Z, Z_err, eff.ES, eff.ED, eff.EM, None, None, TRUTH,
                                 "given", w_nyquist=np.pi * 1000))
    lo, hi = plots.plots["ES"].getViewBox().viewRange()[1]
    trusted_es = eff.ES[~wild & (Z.imag < 0)]
    assert np.abs(eff.ES[wild]).max() > 1e5  # the wild points are there ...
    assert hi < 1.2 * trusted_es.max() and lo > -0.2 * trusted_es.max()  # ... and ignored
    assert hi >= trusted_es.max()  # the trusted estimate fills the axis


def test_garbage_of_worker_threads_is_collected_in_the_gui_thread(qtbot):
    """labbench.gui.gc_policy: cycles made and dropped by a worker thread are freed by the GUI
    thread's timer, never by the worker; automatic collection comes back at close."""
    import gc
    import threading
    import weakref

    from labbench.gui.gc_policy import GuiThreadCollection

    # this test's own collection (the conftest already holds one for qtbot tests)
    collection = GuiThreadCollection(interval_s=0.05)
    assert not gc.isenabled()
    freed_in = []

    class Node:
        pass

    def work():
        for _ in range(20_000):  # far past the gen-0 threshold (700)
            a, b = Node(), Node()
            a.other, b.other = b, a
            weakref.finalize(a, lambda: freed_in.append(threading.current_thread().name))

    worker = threading.Thread(target=work, name="worker")
    worker.start()
    worker.join()
    assert freed_in == []  # with automatic collection, the worker freed most of them
    qtbot.waitUntil(lambda: len(freed_in) == 20_000, timeout=10_000)
    assert set(freed_in) == {threading.main_thread().name}
    collection.close()
    assert not gc.isenabled()  # the conftest's collection still holds


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(remembered=st.dictionaries(
    st.sampled_from(["K", "seed", "window", "estimator", "band_hi_hz", "ve", "allow_unstable",
                     "std_n", "duration_s", "plant_m_kg", "gone"]),
    st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                 lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner,
                                                                             max_size=3),
                 max_leaves=6)))
def test_hostile_remembered_settings_are_left_out_or_named(qapp, remembered):
    """Remembered settings are a file a person or a crash can spoil: every JSON value a
    field cannot hold leaves its default, and what is shown parses or names its field."""
    from labbench.errors import UserError
    from labbench.gui.protocol_panel import SettingsForm
    from labbench.registry import make_protocol

    config = make_protocol("etfe").config.as_dict()
    form = SettingsForm(config)
    form.apply(remembered)
    try:
        values = form.values()
    except UserError as exc:  # a number the field shows but does not take, named
        assert str(exc).split(":")[0] in remembered
        return
    def same(a, b):
        return a == b or (isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b))

    for name, value in values.items():  # as remembered, exactly, or else the default
        assert same(value, remembered.get(name, config[name])) or same(value, config[name])
