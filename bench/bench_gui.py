"""GUI cost: frame time of the live view, and loop overruns with and without the GUI.

1. Frame time: 4 time-trace curves x 5000 points (setData) plus a live ETFE
   update (ES/ED/EM with bands, theory) and the synchronous paint of those two
   plot widgets (what Qt repaints on such a tick), against a floor measured in
   the same run (the same widgets repainted with no new data). Goal: <= 8 ms.
2. Loop overruns (periods > 1.5 T): the same short white-noise ETFE on the
   real-time simulator, headless through ``labbench.runner.run`` recording a
   session (as ``labbench run`` does), then from the window (the run in its
   acquisition process, ``labbench.gui.acquisition``; redraw timer and live ETFE in the
   window's process) under the Qt event loop. Goal: the GUI adds none.
   Runs alternate to spread the noise of this shared machine over both arms. With
   ``--hogs N``, N CPU-bound processes (``while True: pass``) compete for the cores
   during the loop runs (not the frame timing). Both arms ask for real-time
   scheduling (``labbench.realtime``; in the window, its acquisition process does).

Run: ``QT_QPA_PLATFORM=offscreen .venv/bin/python bench/bench_gui.py [--seconds 20] [--repeats 2]
[--hogs 2] [--skip-frames]``
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402
from PySide6 import QtWidgets  # noqa: E402

from labbench.gui.app import tune_interpreter  # noqa: E402
from labbench.gui.screenshot import wait_until  # noqa: E402
from labbench.gui.buffers import StreamBuffer  # noqa: E402
from labbench.analysis.etfe_live import LiveEtfe  # noqa: E402
from labbench.gui.live_estimate import LIVE, estimate  # noqa: E402
from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.registry import open_device  # noqa: E402
from labbench.records import PAGE  # noqa: E402
from labbench.rig import Rig  # noqa: E402
from labbench.runner import run  # noqa: E402
from labbench.timing import summary as timing_summary  # noqa: E402
from labbench.session_format import SessionWriter  # noqa: E402
from labbench.registry import make_protocol  # noqa: E402


def recorded_run(seconds: float, realtime: bool, session_dir=None) -> tuple[list[dict], dict]:
    """Records and timing of an ETFE run on the simulator, without any GUI (recorded to a
    session file like ``labbench run`` when ``session_dir`` is given)."""
    recs: list[dict] = []
    consumers = [recs.append]
    writer = SessionWriter(session_dir) if session_dir else None
    if writer:
        consumers.append(writer)
    dev = open_device("sim", Rig(), realtime=realtime)
    try:
        res = run(dev, make_protocol("etfe", duration_s=seconds, seed=3), consumers, rig=Rig())
    finally:
        if writer:
            writer.close()
    return recs, res.timing


def frame_times(app, win: MainWindow, recs: list[dict], n_frames: int = 60):
    """(frame with new data, floor) per-frame times [s]: data + live estimate + synchronous paint."""
    buf = StreamBuffer()
    for r in recs:
        buf(r)
    win.buffer = buf
    start, desc = buf.start, buf.descriptor
    from labbench.session_content import analysis_meta
    from labbench.gui.main_window import ve_from_meta

    meta = analysis_meta(start, desc)
    # the live update as the window makes it: the newest 0.1 s added to the running sums
    data, plant, ve = buf.snapshot(), Rig().nominal_plant, ve_from_meta(meta)
    live = LiveEtfe(float(meta["fs"]))
    estimate({k: v[:-100] for k, v in data.items()}, meta, ve, plant, estimator=LIVE, live=live)
    t0 = time.perf_counter()
    est = estimate(data, meta, ve, plant, estimator=LIVE, live=live)
    etfe_s = time.perf_counter() - t0
    win.tabs.setCurrentIndex(0)
    app.processEvents()

    def frame(traces: bool, estimate_too: bool):
        """What one redraw-timer tick costs: new data in, the plot widgets painted (once:
        update() coalesces with the repaint the new data asked for)."""
        t = time.perf_counter()
        if traces:
            win.traces.update_from(buf)
        if estimate_too:
            win.impedance.show_estimate(est)
        win.traces.viewport().update()
        win.impedance.effective.viewport().update()
        app.processEvents()
        return time.perf_counter() - t

    for _ in range(5):  # warm-up
        frame(True, True)
    with_data = [frame(True, True) for _ in range(n_frames)]
    floor = [frame(False, False) for _ in range(n_frames)]
    traces_only = [frame(True, False) for _ in range(n_frames)]
    return with_data, floor, traces_only, etfe_s, est.n_samples


def gui_run(app, win: MainWindow, seconds: float) -> dict:
    """The same run inside the window (live plots and estimate on); its loop timing."""
    win.last_run = None
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value(("duration_s",), seconds)
    win.protocol_panel.set_value(("seed",), 3)
    win.start_protocol()
    # the Qt event loop, as in the application (a processEvents() loop would hold the GIL)
    wait_until(lambda: win.last_run is not None and win.mode == "idle", seconds * 4 + 30)
    if win.last_run is None:
        raise SystemExit("GUI run did not finish")
    return {**win.last_run.timing, "frames": win.traces.frames, "estimates": win.impedance.updates}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--hogs", type=int, default=0, help="CPU hogs during the loop runs")
    ap.add_argument("--skip-frames", action="store_true", help="loop runs only")
    args = ap.parse_args()
    tune_interpreter()
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    tmp = tempfile.mkdtemp(prefix="bench_gui_")
    win = MainWindow(Rig(), tmp, realtime=True)
    win.resize(1600, 1000)
    win.show()
    app.processEvents()

    if not args.skip_frames:
        print_frame_times(app, win)
    gui_run(app, win, 3.0)  # warm-up: first connection, first paint, lazy imports
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.hogs)]
    try:
        headless, in_gui = [], []
        for i in range(args.repeats):
            headless.append(recorded_run(args.seconds, realtime=True, session_dir=tmp)[1])
            in_gui.append(gui_run(app, win, args.seconds))
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    print(f"loop timing, {args.seconds:g} s real-time ETFE runs x {args.repeats} (alternating), "
          f"{args.hogs} CPU hogs, load average {os.getloadavg()[0]:.1f}:")
    for name, runs in (("without GUI", headless), ("with GUI", in_gui)):
        ov = [r.get("overruns") for r in runs]
        p99 = [r.get("p99_s", float("nan")) * 1e3 for r in runs]
        mx = [r.get("max_s", float("nan")) * 1e3 for r in runs]
        extra = (f", frames {[r['frames'] for r in runs]}, estimates {[r['estimates'] for r in runs]}"
                 if "frames" in runs[0] else "")
        print(f"  {name:12s} overruns {ov} in {[r.get('periods') for r in runs]} periods, p99 "
              f"{[f'{v:.2f}' for v in p99]} ms, max {[f'{v:.1f}' for v in mx]} ms{extra}")
        print(f"  {'':12s} {[timing_summary(r) for r in runs]}")
    def rate(runs):  # a run the watchdog ended counts up to its trip
        return 1e5 * sum(r["overruns"] for r in runs) / max(sum(r["periods"] for r in runs), 1)

    print(f"  overruns per 100 000 periods: without GUI {rate(headless):.3g}, with GUI "
          f"{rate(in_gui):.3g} (added by the GUI {rate(in_gui) - rate(headless):+.3g})")
    win.close()
    threading.Event().wait(0.1)
    return 0


def print_frame_times(app, win) -> None:
    recs, _ = recorded_run(60.0, realtime=False)
    n = sum(len(r["data"]["t"]) for r in recs if r["kind"] == PAGE)
    with_data, floor, traces_only, etfe_s, n_est = frame_times(app, win, recs)
    med = statistics.median
    print(f"frame time (4 curves x {win.traces.window} points + live ETFE update, "
          f"{QtWidgets.QApplication.platformName()}):")
    print(f"  median {med(with_data) * 1e3:.2f} ms, p90 {np.percentile(with_data, 90) * 1e3:.2f} ms"
          f" (goal <= 8 ms); floor (same widgets repainted, no new data) {med(floor) * 1e3:.2f} ms;"
          f" ratio {med(with_data) / med(floor):.2f}")
    print(f"  traces only (a frame between two estimates) {med(traces_only) * 1e3:.2f} ms;"
          f" live ETFE update + theory on {n_est} of {n} samples (worker thread) "
          f"{etfe_s * 1e3:.1f} ms")


if __name__ == "__main__":
    sys.exit(main())
