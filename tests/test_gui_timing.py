"""The Device panel's "Check timing": the same preflight as ``labbench devices --timing``,
its verdict on the panel, its figures in the log (issue 33)."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

from PySide6 import QtCore  # noqa: E402

from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.rig import load_rig  # noqa: E402

CHECK_TIMEOUT_MS = 90_000  # a process that imports labbench, 1 s of measuring, its report


def window(qtbot, tmp_path, canopen: str):
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text("[rig]\nsample_time_s = 0.01\n[preflight]\nseconds = 1\n"
                        f"[canopen]\n{canopen}\n")
    win = MainWindow(load_rig(rig_file), tmp_path / "sessions", realtime=False)
    qtbot.addWidget(win)
    win.show()
    win.device_panel.backend.setCurrentText("sim-canopen")
    return win


def check(qtbot, win) -> str:
    panel = win.device_panel
    qtbot.mouseClick(panel.timing_button, QtCore.Qt.MouseButton.LeftButton)
    assert not panel.timing_button.isEnabled() and not panel.connect_button.isEnabled()
    assert panel.timing_label.text() == "measuring ..."
    qtbot.waitUntil(lambda: panel.timing_button.isEnabled(), timeout=CHECK_TIMEOUT_MS)
    assert panel.connect_button.isEnabled()
    return panel.timing_label.text()


def test_check_timing_calls_a_slow_drive_too_tight_and_says_what_to_set(qtbot, tmp_path):
    win = window(qtbot, tmp_path, "stale_periods = 1\nsim_answer_delay_ms = 15")
    text = check(qtbot, win)
    assert text.startswith("failed: set stale_periods = "), text
    tip = win.device_panel.timing_label.toolTip()
    assert "verdict: failed: stale limit 10 ms (1 periods): too tight" in tip
    assert "wait for the answer (what the stale limit measures): p50 1" in tip  # ~15 ms
    assert any("timing preflight: simulated CiA 402 drive" in text
               for _, _, text in win.log.entries), "the figures go to the log"


def test_check_timing_passes_an_answering_drive(qtbot, tmp_path):
    win = window(qtbot, tmp_path, "stale_periods = 50")
    text = check(qtbot, win)
    assert text in ("ok: the rig's limits hold", "doubtful: see the tooltip"), text
    assert "stale limit 500 ms (50 periods): holds" in win.device_panel.timing_label.toolTip()


def test_check_timing_is_for_a_device_not_connected(qtbot, tmp_path):
    win = window(qtbot, tmp_path, "")
    win.device_panel.backend.setCurrentText("sim")
    win.connect_device("sim")
    qtbot.waitUntil(lambda: win.state.link == "connected", timeout=CHECK_TIMEOUT_MS)
    assert not win.device_panel.timing_button.isEnabled()
    win.check_timing("sim")  # as if clicked anyway: refused in one line, nothing started
    assert "disconnect the device first" in win.banner.text()
    assert win.device_panel.timing_label.text() == "not checked"
