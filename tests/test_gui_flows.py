"""Whole flows through the window as a person clicks them, asserting what is on screen at
each step: labels, enabled buttons, table rows, banner and progress text, the log."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import csv  # noqa: E402
import functools  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PySide6 import QtCore  # noqa: E402

from labbench.gui.id_view import cells  # noqa: E402
from labbench.readout.wording import session_label  # noqa: E402
from labbench.gui.live_estimate import LIVE as LIVE_ESTIMATOR  # noqa: E402
from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.readout.numfmt import fmt  # noqa: E402
from labbench.gui.settings import open_settings  # noqa: E402
from labbench.rig import Rig  # noqa: E402
from labbench.sessions.session_content import load_session  # noqa: E402

RUN_MS = 60_000


def _window(qtbot, folder, settings=None, realtime=True):
    win = MainWindow(Rig(), folder, realtime=realtime, settings=settings)
    qtbot.addWidget(win)
    win.show()
    return win


def _done(qtbot, win, timeout=RUN_MS):
    qtbot.waitUntil(lambda: win.mode == "idle" and win.last_run is not None, timeout=timeout)


def _frame(qtbot):
    """One redraw period of the window (<= 30 Hz): what 'at once' means on screen."""
    qtbot.wait(40)


def _log_text(win) -> str:
    return win.log.toPlainText()


def test_a_session_from_connect_to_restart(qtbot, tmp_path):
    ini, folder = tmp_path / "settings.ini", tmp_path / "sessions"
    win = _window(qtbot, folder, open_settings(ini))
    panel, dev = win.protocol_panel, win.device_panel

    # connect: the button says Disconnect, the device is named, Enable offered
    assert dev.connect_button.text() == "Connect" and not dev.enable_button.isEnabled()
    dev.connect_button.click()
    qtbot.waitUntil(lambda: win.device is not None, timeout=20_000)
    assert dev.connect_button.text() == "Disconnect" and dev.enable_button.isEnabled()
    assert "simulated" in dev.name_label.text() and "force limit" in dev.name_label.toolTip()

    # choose a protocol, edit a field: the pre-check follows the edit
    panel.choice.setCurrentText("etfe")
    panel.set_value("K", 80.0)
    assert "stable spring-damper" in panel.precheck.text() and "K_max/K" in panel.precheck.text()
    assert "N/m at B = 1 N s/m" in panel.precheck.text()  # commissioning's K_max is for B = 0
    before = panel.precheck.text()
    panel.set_value("K", 60.0)
    assert panel.precheck.text() != before
    panel.set_value("duration_s", 40.0)
    panel.set_value("seed", 4)

    # start: the settings as a table in the log, Start off, Stop on, the live view updates
    panel.start_button.click()
    assert win.mode == "running" and not panel.start_button.isEnabled() and panel.stop_button.isEnabled()
    log = _log_text(win)
    assert "start etfe with these settings:" in log and "{" not in log.split("these settings:")[1]
    assert any(line.split() == ["K", "60", "N/m"] for line in log.splitlines())
    qtbot.waitUntil(lambda: win.live.impedance.updates >= 1 and win.live.traces.frames >= 3, timeout=30_000)
    qtbot.waitUntil(lambda: "%" in panel.time_left.text(), timeout=10_000)
    assert win.live.impedance.last.estimator == LIVE_ESTIMATOR
    assert "effective impedances from" in win.live.impedance.title.text
    n_seen = win.live.buffer.n
    qtbot.waitUntil(lambda: win.live.buffer.n > n_seen + 500, timeout=10_000)

    # E-STOP (Esc) mid-run: within one frame the progress line, the buttons and the log say so
    win.activateWindow()
    qtbot.keyClick(win, QtCore.Qt.Key.Key_Escape)
    assert panel.time_left.text().startswith("E-STOP: force zeroed, run stopped at")
    assert not panel.start_button.isEnabled() and not panel.stop_button.isEnabled()
    _frame(qtbot)  # the run may have ended by now: either way the line says E-STOP
    assert "E-STOP" in panel.time_left.text() and "left" not in panel.time_left.text()
    assert win.estop.latched and "LATCHED" in win.estop.text()
    assert any("E-STOP: force zeroed" in t for t in win.log.texts("warning")) and win.log.following()
    _done(qtbot, win, 15_000)
    assert win.last_run.status == "aborted"
    assert panel.time_left.text().startswith("run aborted at ")
    assert "left" not in panel.time_left.text()  # no stale "N s left"
    assert not panel.start_button.isEnabled()  # the latch holds: Start says why
    assert "E-STOP is latched" in panel.start_button.toolTip()
    assert not win.banner.isVisible()

    # reconnect: the latch clears, Start is offered again; start again, Stop mid-run
    dev.connect_button.click()  # Disconnect
    assert dev.connect_button.text() == "Connect" and dev.name_label.text() == "not connected"
    assert not win.estop.latched and panel.start_button.isEnabled()
    dev.connect_button.click()
    qtbot.waitUntil(lambda: win.device is not None, timeout=20_000)
    panel.set_value("duration_s", 3.0)
    panel.start_button.click()
    qtbot.waitUntil(lambda: win.live.buffer.n > 500, timeout=20_000)
    panel.stop_button.click()
    assert panel.time_left.text().startswith("stopping the run at")
    assert not panel.stop_button.isEnabled()
    _done(qtbot, win)
    assert win.last_run.status == "aborted" and panel.time_left.text().startswith("run aborted at")
    assert panel.start_button.isEnabled()

    # a whole short run: the Sessions table lists all three, newest selected
    panel.set_value("duration_s", 2.5)
    win.last_run = None
    panel.start_button.click()
    _done(qtbot, win)
    assert win.last_run.status == "success" and panel.time_left.text() == "run success at 100 %"
    qtbot.waitUntil(lambda: len(win.sessions.paths) == 3, timeout=10_000)
    table = win.sessions.table
    from labbench.gui.sessions_view import COLUMNS

    statuses = sorted(table.item(r, COLUMNS.index("status")).text().split(",")[0]  # ", N overruns"
                      for r in range(table.rowCount()))
    assert statuses == ["aborted", "aborted", "success"]
    assert win.sessions.selected() == win.session_path
    recorded = win.live.buffer.snapshot()

    # replay it: the same stream through the live view
    win.tabs.setCurrentWidget(win.sessions)
    win.sessions.buttons["Replay fast"].click()
    assert win.mode == "replay" and win.tabs.currentIndex() == 0
    qtbot.waitUntil(lambda: win.mode == "idle" and win.live.buffer.stop is not None, timeout=20_000)
    assert panel.time_left.text().startswith("replay ")
    np.testing.assert_array_equal(win.live.buffer.channel("position"), recorded["position"])
    results = load_session(win.session_path)[4]["results"]  # its verdicts, as recorded
    verdicts = {"ETFE": results["etfe"].get("verdict"), "closed-loop fit": results["loop_fit"].get("verdict")}
    assert win.live.verdicts.levels() == {k: v["level"] for k, v in verdicts.items() if v}
    assert "ETFE" in win.live.verdicts.levels()

    # re-analyse: the identification tab fills from the session
    win.sessions.buttons["Re-analyse"].click()
    qtbot.waitUntil(lambda: any("re-analysis done" in t for t in win.log.texts("info")), timeout=RUN_MS)
    assert win.id_view.table.rowCount() > 0 and win.id_view.table.columnCount() == 2
    headers = [win.id_view.table.horizontalHeaderItem(c).text() for c in range(2)]
    assert headers == ["l2 fit", "l1 fit"]

    # export the report and CSV: both named in the log; the CSV holds the session's samples
    win.sessions.buttons["Export CSV"].click()
    win.sessions.buttons["Export report"].click()
    qtbot.waitUntil(lambda: sum("exported" in t for t in win.log.texts("info")) >= 2, timeout=RUN_MS)
    exported = " ".join(t for t in win.log.texts("info") if "exported" in t)
    assert ".csv" in exported and ".html" in exported and ".pdf" in exported
    csv_path = next((folder / "exports").glob("*.csv"))
    with open(csv_path) as f:
        rows = [r for r in csv.reader(f) if r and not r[0].startswith("#")]
    assert len(rows) - 1 == 2500
    win.close()

    # restart: protocol and the edited fields come back
    again = _window(qtbot, folder, open_settings(ini))
    assert again.protocol_panel.choice.currentText() == "etfe"
    values = again.protocol_panel.values()
    assert (values["K"], values["duration_s"], values["seed"]) == (60.0, 2.5, 4)
    qtbot.waitUntil(lambda: len(again.sessions.paths) == 3, timeout=10_000)
    again.close()


def test_a_fault_shows_at_once_and_its_banner_goes_with_the_next_action(qtbot, tmp_path):
    from gui_faulty_device import open_faulty

    win = _window(qtbot, tmp_path / "sessions", realtime=False)
    win.connect_device("sim", opener=functools.partial(open_faulty, n_ok=1500))
    qtbot.waitUntil(lambda: win.device is not None, timeout=20_000)
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("duration_s", 5.0)
    win.start_protocol()
    _done(qtbot, win)
    panel = win.protocol_panel
    assert win.last_run.status == "failed"
    assert panel.time_left.text().startswith("run failed at ") and "over-current" in panel.time_left.text()
    assert win.banner.isVisible() and "over-current" in win.banner.text()
    assert panel.start_button.isEnabled() and not panel.stop_button.isEnabled()
    assert "over-current" in win.log.texts()[-1] or any("over-current" in t for t in win.log.texts()[-4:])
    win.protocol_panel.choice.setCurrentText("chirp-id")  # the next action
    assert not win.banner.isVisible()
    assert any("over-current" in t for t in win.log.texts("error"))  # the log keeps it
    win.close()


def test_the_log_follows_its_newest_line_unless_scrolled_up(qtbot, tmp_path):
    win = _window(qtbot, tmp_path / "sessions", realtime=False)
    for i in range(200):
        win.log.add("info", f"line {i}")
    bar = win.log.verticalScrollBar()
    assert bar.maximum() > 0 and bar.value() == bar.maximum()
    bar.setValue(0)  # the user scrolls up to read
    win.log.add("warning", "a new line")
    assert bar.value() == 0 and not win.log.following()
    bar.setValue(bar.maximum())  # back at the bottom: it follows again
    win.log.add("warning", "another")
    assert bar.value() == bar.maximum() and win.log.following()
    win.close()


def _run(qtbot, win, protocol: str, **settings):
    """Choose ``protocol``, edit its fields, press Start, wait for the run's end."""
    win.last_run = None
    win.protocol_panel.choice.setCurrentText(protocol)
    for name, value in settings.items():
        win.protocol_panel.set_value(name, value)
    win.protocol_panel.start_button.click()
    _done(qtbot, win)
    assert win.last_run.status == "success", win.last_run.reason
    return win.last_run


def _final_estimate(qtbot, win):
    qtbot.waitUntil(lambda: win.live.impedance.last is not None and win.mode == "idle"
                    and win.live.impedance.last.n_samples == win.live.buffer.n
                    and win.live.impedance.last.estimator != LIVE_ESTIMATOR, timeout=RUN_MS)
    return win.live.impedance.last


def _read_id(fit: dict, method: str) -> dict[str, str]:
    """An identification's rows as labbench.readout.wording writes them."""
    from labbench.readout import wording

    return dict(wording.of_identification(fit, method).row_texts())


def _read_fit(fit: dict) -> dict[str, str]:
    """A loop fit's m, b, td, tv as labbench.readout.wording writes them."""
    from labbench.readout import wording

    rows = dict(wording.of_results("etfe", {"etfe": {}, "loop_fit": fit}).rows)
    return {name: value.text() for name, value in rows["closed-loop fit"]}


def test_identification_shows_what_the_overlay_uses_and_the_loop_fit(qtbot, tmp_path):
    folder = tmp_path / "sessions"
    win = _window(qtbot, folder, realtime=False)
    view = win.id_view
    assert "the rig's nominal model" in view.overlay.text()  # nothing identified yet
    assert view.table.isHidden() and view.fit_table.isHidden()

    # chirp-ID: its fits, the session they come from, the verdict of each
    chirp = _run(qtbot, win, "chirp-id", f0_hz=0.2, duration_s=20.0)
    chirp_path = win.session_path
    assert win.tabs.currentWidget() is view
    assert Path(chirp_path).name in view.source.text()
    fits = chirp.results["identification"]
    table = cells(view.table)
    # the numbers as labbench.readout.wording writes them (the CLI's and the report's)
    assert table["mass m"] == [_read_id(fits[m], m)["mass m"] for m in ("l2", "l1")]
    assert table["verdict"] == [fits["l2"]["verdict"]["level"], fits["l1"]["verdict"]["level"]]
    assert view.verdicts.levels() == {f"{m} fit": fits[m]["verdict"]["level"] for m in ("l2", "l1")}
    assert [view.table.horizontalHeaderItem(c).text() for c in range(2)] == ["l2 fit (next runs)", "l1 fit"]

    # the next ETFE takes that identification, says so before Start, and records where from
    qtbot.waitUntil(lambda: (win.identified or {}).get("session") == chirp_path, timeout=10_000)
    win.protocol_panel.choice.setCurrentText("etfe")
    label = session_label(chirp_path)
    assert f"identified in {label}" in win.protocol_panel.precheck.text()
    etfe = _run(qtbot, win, "etfe", duration_s=8.0, seed=2)
    est = _final_estimate(qtbot, win)
    assert est.plant_source == f"identified in {label}"
    assert (est.plant.m, est.plant.b) == (fits["l2"]["m"], fits["l2"]["b"])
    assert f"m = {fmt(est.plant.m)} kg" in view.overlay.text() and label in view.overlay.text()
    assert load_session(win.session_path)[0]["plant_from"]["session"] == chirp_path

    # its closed-loop fit: m, b, td, tv with intervals, the delay model, the verdict
    lf = etfe.results["loop_fit"]
    rows = cells(view.fit_table)
    parts = _read_fit(lf)
    assert rows["mass m"] == [parts["m"]] and rows["damping b"] == [parts["b"]]
    assert rows["device latency td"] == [parts["td"]]
    assert rows["VE-path delay tv"] == [f"{fmt(1e3 * lf['tv_s'])} ms, held (not fitted)"]
    assert rows["delay model"][0].startswith(lf["delay_model"]) and lf["delay_model"] == "common"
    assert view.fit_verdict.levels() == {"closed-loop fit": lf["verdict"]["level"]}
    assert win.live.verdicts.levels() == {"ETFE": etfe.results["etfe"]["verdict"]["level"],
                                            "against the theory": etfe.results["rendered"]["verdict"]["level"],
                                            "closed-loop fit": lf["verdict"]["level"]}
    etfe_path = win.session_path
    win.close()

    # a new window: the tab shows the identification the overlay will use, not "none yet"
    again = _window(qtbot, folder, realtime=False)
    qtbot.waitUntil(lambda: not again.id_view.table.isHidden(), timeout=20_000)
    assert Path(chirp_path).name in again.id_view.source.text()
    assert cells(again.id_view.table)["mass m"] == table["mass m"]
    assert f"identified in {label}" in again.id_view.overlay.text()

    # Re-analyse the ETFE session: labbench analyze etfe --fit's numbers (CV-chosen delays)
    from labbench.session_api import load

    again.sessions.select_path(etfe_path)
    again.sessions.estimator.setCurrentText("h1-welch")
    again.sessions.buttons["Re-analyse"].click()
    qtbot.waitUntil(lambda: "labbench analyze etfe --fit" in again.id_view.fit_source.text(),
                    timeout=RUN_MS)
    fit = load(etfe_path).etfe(estimator="h1-welch", fit=True).fit.as_dict()
    rows = cells(again.id_view.fit_table)
    assert rows["mass m"] == [_read_fit(fit)["m"]]
    assert rows["delay model"][0].startswith(fit["delay_model"])
    assert again.live.verdicts.levels()["closed-loop fit"] == fit["verdict"]["level"]
    # the Live page shows the record re-analysed, not another's
    assert again.live.buffer.n == 8000 and again.live.buffer.start["uid"][:8] in etfe_path
    again.close()


def test_display_units_follow_the_choice_and_are_remembered(qtbot, tmp_path):
    from labbench.readout import bandwidth_text
    from labbench.readout.units import SI, DisplayUnits

    ini, folder = tmp_path / "settings.ini", tmp_path / "sessions"
    win = _window(qtbot, folder, open_settings(ini), realtime=False)
    _run(qtbot, win, "etfe", duration_s=8.0, seed=3)
    est = _final_estimate(qtbot, win)
    ws_si = win.live.impedance.marks["ws"].label.format

    # a person picks mm, deg and Hz from the drop-down lists
    for kind, unit in (("length", "mm"), ("angle", "deg"), ("frequency", "Hz")):
        win.units_choice.combos[kind].setCurrentText(unit)
    chosen = DisplayUnits("mm", "deg", "Hz")
    assert win.units_choice.units() == chosen
    label = win.live.impedance.marks["ws"].label.format
    assert label.replace("\n", " ") == bandwidth_text.label("ws", est.ws_measured, est.predicted, chosen)
    assert label != ws_si and " Hz" in label
    assert 10 ** win.live.impedance.marks["ws"].value() == pytest.approx(est.ws_measured / (2 * np.pi))
    x, _ = win.live.impedance.curves["ED"].getOriginalDataset()
    assert x[0] == pytest.approx(est.w[est.w > 0][0] / (2 * np.pi))
    assert win.live.impedance.plots["EM"].getAxis("bottom").labelUnits == "Hz"
    assert win.live.traces.plots["position"].getAxis("left").labelUnits == "mm"
    assert win.live.traces.plots["position"].getAxis("left").scale == 1e3
    win.live.impedance.setCurrentIndex(1)  # Bode: phase in degrees
    _, phase = win.live.impedance.curves["bode_phase"].getOriginalDataset()
    ok = (est.w > 0) & (est.w <= est.w_nyquist / 3)
    np.testing.assert_allclose(phase, np.degrees(np.unwrap(np.angle(est.Z[ok]))))
    win.close()

    again = _window(qtbot, folder, open_settings(ini), realtime=False)
    assert again.units_choice.units() == chosen  # remembered
    assert again.live.impedance.plots["EM"].getAxis("bottom").labelUnits == "Hz"
    again.close()
    # `labbench gui --units ...` wins over what was remembered
    given = MainWindow(Rig(), folder, realtime=False, settings=open_settings(ini), units=SI)
    qtbot.addWidget(given)
    assert given.units_choice.units() == SI
    assert given.live.traces.plots["position"].getAxis("left").labelUnits == "m"
    given.close()


def test_a_safety_trip_shows_at_once(qtbot, tmp_path):
    from labbench.rig import rig_from_dict

    narrow = rig_from_dict({"rig": {"position_limits_m": [-0.002, 0.002]}})  # a 4 mm window
    win = MainWindow(narrow, tmp_path / "sessions", realtime=False)
    qtbot.addWidget(win)
    win.show()
    panel = win.protocol_panel
    panel.choice.setCurrentText("etfe")
    panel.set_value("duration_s", 5.0)
    panel.start_button.click()
    _done(qtbot, win)  # the frame that handled the run's end: all of it says so
    assert win.last_run.status == "failed" and "position" in win.last_run.reason
    assert panel.time_left.text().startswith("run failed at ") and "outside the window" in panel.time_left.text()
    assert win.banner.isVisible() and "outside the window" in win.banner.text()
    assert panel.start_button.isEnabled() and not panel.stop_button.isEnabled()
    assert any("position_limit" in t or "outside the window" in t for t in win.log.texts("event"))
    assert win.log.following()
    assert win.device_panel.enable_button.text() == "Enable"  # the run disabled the device
    win.close()


def test_disconnect_is_refused_mid_run_and_a_lost_acquisition_process_shows_at_once(qtbot, tmp_path):
    import signal

    win = _window(qtbot, tmp_path / "sessions")  # paced: the run lasts
    panel, dev = win.protocol_panel, win.device_panel
    panel.choice.setCurrentText("etfe")
    panel.set_value("duration_s", 60.0)
    panel.start_button.click()
    qtbot.waitUntil(lambda: win.mode == "running" and win.live.buffer.n > 500, timeout=30_000)
    dev.connect_button.click()  # Disconnect, mid-run
    assert win.banner.isVisible() and win.banner.text() == "stop the run before disconnecting"
    assert win.mode == "running" and panel.stop_button.isEnabled()
    assert dev.connect_button.text() == "Disconnect"

    # the device's process is lost (killed): the window says so within the frame that hears it
    os.kill(win.acquisition.process.pid, signal.SIGKILL)
    qtbot.waitUntil(lambda: win.mode == "idle", timeout=10_000)
    assert panel.time_left.text() == "run ended: the acquisition process died"
    assert win.banner.isVisible() and "acquisition process ended unexpectedly" in win.banner.text()
    assert dev.connect_button.text() == "Connect" and dev.name_label.text() == "not connected"
    assert panel.start_button.isEnabled() and not panel.stop_button.isEnabled()
    assert win.commission.run_button.isEnabled()

    # and it can be started again: Start reconnects
    panel.set_value("duration_s", 2.0)
    win.last_run = None
    panel.start_button.click()
    assert not panel.start_button.isEnabled()  # waiting for the device: no second Start
    assert panel.time_left.text().startswith("connecting to")
    _done(qtbot, win)
    assert win.last_run.status == "success"
    win.close()
