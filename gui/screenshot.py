"""Save a screenshot of a widget once a condition holds (for docs and headless checks)."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from PySide6 import QtCore, QtWidgets


def grab(widget: QtWidgets.QWidget, path) -> Path:
    """Render ``widget`` (works offscreen and under Xvfb) into a PNG at ``path``."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if not widget.grab().save(str(p), "PNG"):
        raise OSError(f"could not write screenshot {p}")
    return p


class ShotWhen(QtCore.QObject):
    """Poll ``ready()`` every ``poll_ms``; when true (or after ``timeout_s``) grab and call ``done(ok, path)``."""

    def __init__(self, widget, path, ready: Callable[[], bool], done: Callable[[bool, Path], None],
                 timeout_s: float = 120.0, settle_ms: int = 300, poll_ms: int = 100):
        super().__init__(widget)
        self.widget, self.path, self.ready, self.done = widget, path, ready, done
        self.deadline = time.monotonic() + timeout_s
        self.settle_ms = settle_ms
        self.timer = QtCore.QTimer(self)
        self.timer.setInterval(poll_ms)
        self.timer.timeout.connect(self._check)
        self.timer.start()

    def _check(self):
        ok = self.ready()
        if ok or time.monotonic() > self.deadline:
            self.timer.stop()
            # let the last redraw land before grabbing
            QtCore.QTimer.singleShot(self.settle_ms, lambda: self.done(ok, grab(self.widget, self.path)))


def wait_until(cond: Callable[[], bool], timeout_s: float, poll_ms: int = 20) -> bool:
    """Run a nested Qt event loop until ``cond()`` or the timeout; True if ``cond()``.

    Not a ``processEvents()`` loop: that holds the GIL through all the C++ work of
    an event pass (measured: up to 130 ms under Xvfb, enough to trip the loop's
    watchdog), while ``QEventLoop.exec`` releases it like ``QApplication.exec``.
    """
    if cond():
        return True
    loop = QtCore.QEventLoop()
    deadline = time.monotonic() + timeout_s
    timer = QtCore.QTimer()
    timer.setInterval(poll_ms)
    timer.timeout.connect(lambda: (cond() or time.monotonic() > deadline) and loop.quit())
    timer.start()
    loop.exec()
    timer.stop()
    return bool(cond())


# what docs/gui.md shows, in the order docs_screenshots makes them
SHOTS = ("first-run.png", "chirp-live.png", "demo-etfe.png", "bode.png", "identification.png",
         "units-hz.png", "sessions.png", "refused-unstable.png", "refused-uncommissioned.png",
         "serial-port.png", "sweeps.png", "commissioning.png", "commissioning-fixed.png")
# the sweep of the Sweeps tab's picture: six short ETFE runs on the simulator
SWEEP_SPEC = """[sweep]
name = "springs"
protocol = "etfe"

[fixed]
duration_s = 2.0

[grid]
K = [20.0, 50.0, 100.0, 200.0, 400.0, 800.0]
"""
# the lying rig of the commissioning pictures: its encoder counts the other way and the
# device has 2 samples of delay the file does not state
LYING_RIG = """# bench 3 by the window (comments stay when the window writes this file)
[rig]
name = "bench 3"

[sim]
sign = -1
extra_delay_samples = 2
"""


def docs_screenshots(out_dir, seconds: float = 30.0, realtime: bool = False) -> list[Path]:
    """The screenshots of docs/gui.md (``SHOTS``), made from the current build as a person
    would click: the first launch, chirp-ID (its live view), then the paper's ETFE (live
    view, Bode, identification with the closed-loop fit, display units in Hz), the
    sessions, two refusals, a serial board without a port, a sweep spec run in the Sweeps
    tab, and commissioning a rig file that lies (then written and run again).

    Runs real protocols on the simulator (``python -m labbench.gui.screenshot DIR``; under
    Xvfb for a real X server's rendering). Not paced by default: on a shared,
    loaded machine a paced run can trip the loop's 50 ms watchdog (seen with and
    without the GUI), and the pictures are the same.
    """
    import tempfile

    from labbench.gui.app import demo_finished, start_demo, tune_interpreter
    from labbench.gui.main_window import FIRST_SIZE, MainWindow
    from labbench.rig import Rig, load_rig
    from labbench.readout.units import SI, DisplayUnits

    tune_interpreter()
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    app.setApplicationName("labbench")
    out = Path(out_dir)
    work = Path(tempfile.mkdtemp(prefix="labbench-shots-"))
    shots = []

    def settle_and_grab(win, name, shows: bool = True):
        """Grab ``name`` once ``shows`` holds (what the docs say the picture shows)."""
        if not shows:
            raise RuntimeError(f"{name}: the window does not show what the docs say; log: "
                               + " | ".join(win.log.texts()[-8:]))
        wait_until(lambda: False, 0.5)
        shots.append(grab(win, out / name))

    def run(win, protocol, timeout_s=200.0, **settings):
        win.last_run = None
        win.protocol_panel.choice.setCurrentText(protocol)
        for key, value in settings.items():
            win.protocol_panel.set_value(key, value)
        win.start_protocol()
        if not wait_until(lambda: win.last_run is not None and win.mode == "idle", timeout_s):
            raise RuntimeError(f"{protocol} did not finish; log: " + " | ".join(win.log.texts()))

    win = MainWindow(Rig(), work / "sessions", realtime=realtime)
    win.resize(*FIRST_SIZE)  # the pictures' size on any screen (xvfb-run's is 640 x 480)
    win.show()
    settle_and_grab(win, "first-run.png", win.guide.next_step() == "connect")
    run(win, "chirp-id", f0_hz=0.2, duration_s=20.0)  # the plant the ETFE's theory then takes
    win.tabs.setCurrentWidget(win.live)
    wait_until(lambda: demo_finished(win), 60)
    settle_and_grab(win, "chirp-live.png", not win.live.impedance.marks["ws"].isVisible()
                    and "not excited" in win.live.impedance.title.text)
    win.last_run = None
    start_demo(win, {"duration_s": seconds, "seed": 1})
    if realtime:  # a mid-run picture needs a paced run
        if not wait_until(lambda: win.live.impedance.updates >= 2 and win.live.buffer.n > seconds * 400,
                          4 * seconds):
            raise RuntimeError("live estimate did not appear; log: " + " | ".join(win.log.texts()))
        settle_and_grab(win, "live-etfe-running.png")
    if not wait_until(lambda: demo_finished(win), 4 * seconds + 60):
        raise RuntimeError("demo run did not finish; log: " + " | ".join(win.log.texts()))
    settle_and_grab(win, "demo-etfe.png", bool(win.live.verdicts.shown)
                    and "identified in" in win.live.impedance.title.text)
    win.live.impedance.setCurrentIndex(1)
    settle_and_grab(win, "bode.png")
    win.live.impedance.setCurrentIndex(0)
    win.tabs.setCurrentWidget(win.id_view)
    settle_and_grab(win, "identification.png", win.id_view.table.isVisible()
                    and win.id_view.fit_table.isVisible())
    win.tabs.setCurrentIndex(0)
    win.units_choice.set_units(DisplayUnits.parse("mm,deg,Hz"))
    settle_and_grab(win, "units-hz.png", "Hz" in win.live.impedance.marks["ws"].label.format)
    win.units_choice.set_units(SI)

    win.tabs.setCurrentWidget(win.sessions)
    settle_and_grab(win, "sessions.png", wait_until(lambda: len(win.sessions.paths) >= 2, 10))

    win.tabs.setCurrentIndex(0)
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("ve", "spring")
    win.protocol_panel.set_value("K", 5000.0)
    win.start_protocol()
    settle_and_grab(win, "refused-unstable.png", "refusing unstable" in win.banner.text())
    win.protocol_panel.set_value("K", 50.0)
    win.disconnect_device()
    win.device_panel.backend.setCurrentText("canopen")  # real hardware, never commissioned
    win.start_protocol()
    settle_and_grab(win, "refused-uncommissioned.png", "Commissioning tab" in win.banner.text())
    win.device_panel.backend.setCurrentText("serial")  # a board: its port chosen in the window
    win.device_panel.port.setCurrentText("")
    win.device_panel.connect_button.click()
    settle_and_grab(win, "serial-port.png", "serial port in the Device panel" in win.banner.text())
    win.device_panel.backend.setCurrentText("sim")
    win.banner.mousePressEvent(None)  # read: dismissed by a click

    spec = work / "springs.toml"
    spec.write_text(SWEEP_SPEC)
    win.tabs.setCurrentWidget(win.sweeps)
    win.sweeps.workers.setValue(0)
    win.sweeps.open_spec(spec)
    win.sweeps.run_button.click()
    wait_until(lambda: win.sweeps.run is None, 300)
    settle_and_grab(win, "sweeps.png", "complete" in win.sweeps.progress_text.text())
    win.close()

    rig_file = work / "bench3.toml"
    rig_file.write_text(LYING_RIG)
    win = MainWindow(load_rig(rig_file), work / "bench3-sessions", realtime=realtime)
    win.resize(*FIRST_SIZE)
    win.show()
    win.tabs.setCurrentWidget(win.commission)
    # the lie named and written, then the rig run again: every check passes
    for name, levels in (("commissioning.png", ["failed", "failed", "ok", "ok", "ok"]),
                         ("commissioning-fixed.png", ["ok"] * 5)):
        win.commission.run_button.click()
        if not wait_until(lambda: win.last_run is not None and win.mode == "idle", 200):
            raise RuntimeError("commissioning did not finish; log: " + " | ".join(win.log.texts()))
        shown = [cells[0] for cells in win.commission.check_rows().values()]
        win.commission.write_button.click()
        settle_and_grab(win, name, shown == levels)
        win.last_run = None
    win.close()
    return shots


if __name__ == "__main__":
    import sys

    for p in docs_screenshots(sys.argv[1] if len(sys.argv) > 1 else "docs/screenshots"):
        print(p)
