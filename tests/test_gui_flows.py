"""Whole flows through the window as a person clicks them, asserting what is on screen at
each step: labels, enabled buttons, table rows, banner and progress text, the log."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import csv  # noqa: E402
import functools  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PySide6 import QtCore  # noqa: E402

from labbench.gui.main_window import LIVE_ESTIMATOR, MainWindow  # noqa: E402
from labbench.gui.settings import open_settings  # noqa: E402
from labbench.rig import Rig  # noqa: E402
from labbench.session_content import load_session  # noqa: E402

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
    assert "force limit" in dev.name_label.text()

    # choose a protocol, edit a field: the pre-check follows the edit
    panel.choice.setCurrentText("etfe")
    panel.set_value(("K",), 80.0)
    assert "stable spring-damper" in panel.precheck.text() and "K_max/K" in panel.precheck.text()
    before = panel.precheck.text()
    panel.set_value(("K",), 60.0)
    assert panel.precheck.text() != before
    panel.set_value(("duration_s",), 40.0)
    panel.set_value(("seed",), 4)

    # start: the settings as a table in the log, Start off, Stop on, the live view updates
    panel.start_button.click()
    assert win.mode == "running" and not panel.start_button.isEnabled() and panel.stop_button.isEnabled()
    log = _log_text(win)
    assert "start etfe with these settings:" in log and "{" not in log.split("these settings:")[1]
    assert any(line.split() == ["K", "60", "N/m"] for line in log.splitlines())
    qtbot.waitUntil(lambda: win.impedance.updates >= 1 and win.traces.frames >= 3, timeout=30_000)
    qtbot.waitUntil(lambda: "%" in panel.time_left.text(), timeout=10_000)
    assert win.impedance.last.estimator == LIVE_ESTIMATOR
    assert "effective impedances from" in win.impedance.title.text
    n_seen = win.buffer.n
    qtbot.waitUntil(lambda: win.buffer.n > n_seen + 500, timeout=10_000)

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
    panel.set_value(("duration_s",), 3.0)
    panel.start_button.click()
    qtbot.waitUntil(lambda: win.buffer.n > 500, timeout=20_000)
    panel.stop_button.click()
    assert panel.time_left.text().startswith("stopping the run at")
    assert not panel.stop_button.isEnabled()
    _done(qtbot, win)
    assert win.last_run.status == "aborted" and panel.time_left.text().startswith("run aborted at")
    assert panel.start_button.isEnabled()

    # a whole short run: the Sessions table lists all three, newest selected
    panel.set_value(("duration_s",), 2.5)
    win.last_run = None
    panel.start_button.click()
    _done(qtbot, win)
    assert win.last_run.status == "success" and panel.time_left.text() == "run success at 100 %"
    qtbot.waitUntil(lambda: len(win.sessions.paths) == 3, timeout=10_000)
    table = win.sessions.table
    statuses = sorted(table.item(r, 3).text() for r in range(table.rowCount()))
    assert statuses == ["aborted", "aborted", "success"]
    assert win.sessions.selected() == win.session_path
    recorded = win.buffer.snapshot()

    # replay it: the same stream through the live view
    win.tabs.setCurrentWidget(win.sessions)
    win.sessions.buttons["Replay fast"].click()
    assert win.mode == "replay" and win.tabs.currentIndex() == 0
    qtbot.waitUntil(lambda: win.mode == "idle" and win.buffer.stop is not None, timeout=20_000)
    assert panel.time_left.text().startswith("replay ")
    np.testing.assert_array_equal(win.buffer.channel("position"), recorded["position"])

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
    win.protocol_panel.set_value(("duration_s",), 5.0)
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
