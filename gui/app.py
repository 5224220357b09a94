"""Start the desktop application: ``labbench gui [--rig FILE] [--demo] [--screenshot FILE.png]``."""
from __future__ import annotations

import logging
import sys
from pathlib import Path

from PySide6 import QtCore, QtWidgets

from labbench.gui.gc_policy import GuiThreadCollection
from labbench.gui.main_window import FIRST_SIZE, MainWindow
from labbench.loop.interrupts import handle_signals
from labbench.gui.screenshot import ShotWhen

log = logging.getLogger(__name__)

# The demo: a short closed-loop white-noise ETFE on the simulator (the paper's sec. 4.2 VE).
DEMO_PROTOCOL = "etfe"
DEMO_SETTINGS = {"duration_s": 20.0, "seed": 1}


def tune_interpreter(switch_interval_s: float = 0.0005) -> None:
    """Let worker threads (a 1x replay, the reader of the acquisition process's messages)
    get the GIL back within 0.5 ms instead of Python's default 5 ms while the GUI thread
    runs Python (pyqtgraph's paint code). The 1 kHz loop itself runs in its own process
    (``labbench.gui.acquisition``)."""
    sys.setswitchinterval(switch_interval_s)


def start_demo(win: MainWindow, settings: dict | None = None) -> None:
    """Select the demo protocol with short settings and press Start (connects the simulator)."""
    win.protocol_panel.choice.setCurrentText(DEMO_PROTOCOL)
    for name, value in (settings or DEMO_SETTINGS).items():
        win.protocol_panel.set_value(name, value)
    win.start_protocol()


def demo_finished(win: MainWindow) -> bool:
    """The run is over and the live estimate shows all of its data."""
    est = win.live.impedance.last
    return (win.mode == "idle" and win.last_run is not None and est is not None
            and est.n_samples == win.live.buffer.n and not win.live.estimator.busy)


def run_app(rig, session_dir, demo: bool = False, screenshot: Path | None = None,
            timeout_s: float = 180.0, demo_settings: dict | None = None, realtime: bool = True,
            settings=None, units=None, skip_commissioning: bool = False) -> int:
    """Open the window (and with ``demo`` start the demo); returns the exit code.
    ``settings``: the QSettings the window restores and saves its state with (None: none);
    ``units``, ``skip_commissioning``: as ``MainWindow``'s."""
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])
    app.setApplicationName("labbench")
    tune_interpreter()
    collection = GuiThreadCollection()
    win = MainWindow(rig, session_dir, realtime=realtime, settings=settings, units=units,
                     skip_commissioning=skip_commissioning)
    previous_hook = sys.excepthook

    def hook(kind, exc, tb):  # a last resort: report in the window, keep running
        log.error("uncaught", exc_info=(kind, exc, tb))
        win.show_error(f"internal error: {kind.__name__}: {exc}")

    sys.excepthook = hook
    if screenshot is not None:
        win.resize(*FIRST_SIZE)  # the same picture on any screen, offscreen too
    win.show()
    result = {"code": 0}
    if demo:
        start_demo(win, demo_settings)
    if screenshot is not None:
        def done(ok, path):
            if ok:
                print(f"screenshot saved: {path}")
            else:
                print(f"labbench gui: live estimate not visible after {timeout_s:g} s; "
                      f"screenshot saved anyway: {path}", file=sys.stderr)
                result["code"] = 1
            win.close()
            app.quit()

        ready = (lambda: demo_finished(win)) if demo else (lambda: True)
        ShotWhen(win, screenshot, ready, done, timeout_s=timeout_s)
    def on_signal(signum):  # Ctrl-C, a logout: close as the window's close button does
        result["code"] = result["code"] or 128 + signum
        QtCore.QTimer.singleShot(0, win.close)

    try:
        # Python runs the handler at the window's next timer tick (30 Hz)
        with handle_signals(on_signal):
            code = app.exec()
    finally:
        sys.excepthook = previous_hook
        collection.close()
    return result["code"] or code
