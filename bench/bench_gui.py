"""GUI cost: frame time of the live view, and loop overruns with and without the GUI.

1. Frame time: what one redraw tick costs the window's process: 0.1 s of new
   data into the buffer, the 4 time-trace curves x 5000 points re-set, a new live
   ETFE estimate shown (ES/ED/EM with bands, theory, marks, title) and the paint
   Qt then does of the changed widgets; also a tick between two estimates
   (traces only). Each against a floor measured in the same run (the same widgets
   repainted with no new data). Goal: <= 8 ms for the tick with an estimate.
2. Loop overruns (periods > 1.5 T): the same short white-noise ETFE on the
   real-time simulator, headless through ``labbench.runner.run`` recording a
   session (as ``labbench run`` does), then from the window (the run in its
   acquisition process, ``labbench.gui.acquisition``; redraw timer and live ETFE in the
   window's process) under the Qt event loop. Goal: the GUI adds none.
   Runs alternate to spread the noise of this shared machine over both arms. With
   ``--hogs N``, N CPU-bound processes (``while True: pass``) compete for the cores
   during the loop runs (not the frame timing). Both arms ask for real-time
   scheduling (``labbench.loop.realtime``; in the window, its acquisition process does).

Run: ``QT_QPA_PLATFORM=offscreen .venv/bin/python bench/bench_gui.py [--seconds 20] [--repeats 2]
[--hogs 2] [--skip-frames | --frames-only]``
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
from PySide6 import QtCore, QtWidgets  # noqa: E402

from labbench.gui.app import tune_interpreter  # noqa: E402
from labbench.gui.screenshot import wait_until  # noqa: E402
from labbench.gui.buffers import StreamBuffer  # noqa: E402
from labbench.analysis.etfe_live import LiveEtfe  # noqa: E402
from labbench.gui.live_estimate import LIVE, estimate  # noqa: E402
from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.registry import open_device  # noqa: E402
from labbench.records import CHANNELS, PAGE  # noqa: E402
from labbench.rig import Rig  # noqa: E402
from labbench.runner import run  # noqa: E402
from labbench.loop.timing import summary as timing_summary  # noqa: E402
from labbench.sessions.session_format import SessionWriter  # noqa: E402
from labbench.registry import make_protocol  # noqa: E402


def recorded_run(seconds: float, realtime: bool, session_dir=None,
                 rig: Rig | None = None) -> tuple[list[dict], dict]:
    """Records and timing of an ETFE run on the simulator, without any GUI (recorded to a
    session file like ``labbench run`` when ``session_dir`` is given)."""
    rig = rig or Rig()
    recs: list[dict] = []
    consumers = [recs.append]
    writer = SessionWriter(session_dir) if session_dir else None
    if writer:
        consumers.append(writer)
    dev = open_device("sim", rig, realtime=realtime)
    try:
        res = run(dev, make_protocol("etfe", duration_s=seconds, seed=3), consumers, rig=rig)
    finally:
        if writer:
            writer.close()
    return recs, res.timing


class PaintCounter(QtCore.QObject):
    """Counts the paint events of the widgets it is installed on (viewports)."""

    def __init__(self, widgets):
        super().__init__()
        self.counts = {w: 0 for w in widgets}
        for w in widgets:
            w.installEventFilter(self)

    def eventFilter(self, obj, ev):  # noqa: N802 - Qt override
        if ev.type() == QtCore.QEvent.Type.Paint:
            self.counts[obj] += 1
        return False


def frame_times(app, win: MainWindow, recs: list[dict], n_frames: int = 60, preload_s: float = 60.0):
    """Per-frame times [s] of what one redraw-timer tick costs the GUI process: new
    data in (``MainWindow._tick``'s calls), then the event loop's work until the changed
    widgets are painted. The stream goes on as in a run: after ``preload_s`` of
    ``recs``, each frame adds the next page (0.1 s) to the window's buffer, and a frame
    with an estimate shows the next of the live estimates that differ (made
    beforehand, as the worker thread makes them). Frames: with a new estimate, traces only, and
    the floors (the same widgets repainted through the same path, ``scene().update()``,
    with no new data). Raises if a frame did not paint what it changed, so the times
    always include the paint. Returns the times and the live updates' times [s]."""
    from labbench.sessions.session_content import analysis_meta
    from labbench.analysis.compare import ve_from_meta

    n_pages = round(preload_s / 0.1)
    at = [i for i, r in enumerate(recs) if r["kind"] == PAGE][n_pages]
    preload, stream = recs[:at], iter(recs[at:])
    buf = StreamBuffer()
    for r in preload:
        buf(r)
    win.live.buffer = buf
    meta = analysis_meta(buf.start, buf.descriptor)
    plant, ve = Rig().nominal_plant, ve_from_meta(meta)
    # The estimates the estimate frames show: the live estimator's on the whole record,
    # one every 0.5 s of data as the window makes them, keeping those that changed the
    # curves (the others change only the title: the worst case is a frame where all of
    # curves, bands, marks, ranges may move), shown in turn.
    shadow, live, distinct, etfe_s = StreamBuffer(), LiveEtfe(float(meta["fs"])), [], []
    for i, r in enumerate(recs):
        shadow(r)
        if r["kind"] != PAGE or shadow.n % 500:
            continue
        t0 = time.perf_counter()
        est = estimate({k: shadow.channel(k) for k in CHANNELS}, meta, ve, plant,
                       estimator=LIVE, live=live)
        etfe_s.append(time.perf_counter() - t0)
        if est is not None and not (distinct and np.array_equal(est.Z, distinct[-1].Z)):
            distinct.append(est)
    estimates = [distinct[i % len(distinct)] for i in range(5 + n_frames)]
    estimates = iter(estimates)
    win.tabs.setCurrentIndex(0)
    app.processEvents()
    traces, effective = win.live.traces, win.live.impedance.effective
    painted = PaintCounter([traces.viewport(), effective.viewport()])

    def frame(new_estimate: bool = False, floor: str | None = None):
        painted.counts = dict.fromkeys(painted.counts, 0)
        est = next(estimates) if new_estimate else None
        t = time.perf_counter()
        if floor:
            traces.scene().update()
            if floor == "both":
                effective.scene().update()
        else:
            buf(next(stream))
            traces.update_from(buf)
            if est is not None:
                win.live.impedance.show_estimate(est)
        app.processEvents()
        dt = time.perf_counter() - t
        if painted.counts[traces.viewport()] < 1 or (
                (new_estimate or floor == "both") and painted.counts[effective.viewport()] < 1):
            raise RuntimeError(f"a frame did not paint what it changed: {painted.counts}")
        return dt

    # the frames are the ticks: the window's own redraw and estimate timers would add
    # a second tick's work to some of them
    timers = (win.redraw_timer, win.estimate_timer)
    for timer in timers:
        timer.stop()
    try:
        for _ in range(5):  # warm-up
            frame(new_estimate=True)
        return {"estimate": [frame(new_estimate=True) for _ in range(n_frames)],
                "floor": [frame(floor="both") for _ in range(n_frames)],
                "traces": [frame() for _ in range(n_frames)],
                "floor_traces": [frame(floor="traces") for _ in range(n_frames)],
                }, etfe_s
    finally:
        for timer in timers:
            timer.start()


def gui_run(app, win: MainWindow, seconds: float) -> dict:
    """The same run inside the window (live plots and estimate on); its loop timing."""
    win.last_run = None
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("duration_s", seconds)
    win.protocol_panel.set_value("seed", 3)
    win.start_protocol()
    # the Qt event loop, as in the application (a processEvents() loop would hold the GIL)
    wait_until(lambda: win.last_run is not None and win.mode == "idle", seconds * 4 + 30)
    if win.last_run is None:
        raise SystemExit("GUI run did not finish")
    return {**win.last_run.timing, "frames": win.live.traces.frames, "estimates": win.live.impedance.updates}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--hogs", type=int, default=0, help="CPU hogs during the loop runs")
    ap.add_argument("--skip-frames", action="store_true", help="loop runs only")
    ap.add_argument("--frames-only", action="store_true", help="frame times only")
    ap.add_argument("--watchdog-s", type=float, default=None,
                    help="the loop's watchdog (default 0.05 s): longer to count the overruns "
                         "of a whole run through stalls that would trip it")
    args = ap.parse_args()
    rig = Rig(sections={} if args.watchdog_s is None
              else {"safety": {"watchdog_s": args.watchdog_s}})
    tune_interpreter()
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    tmp = tempfile.mkdtemp(prefix="bench_gui_")
    win = MainWindow(rig, tmp, realtime=True)
    win.resize(1600, 1000)
    win.show()
    app.processEvents()

    if not args.skip_frames:
        print_frame_times(app, win)
    if args.frames_only:
        win.close()
        return 0
    gui_run(app, win, 3.0)  # warm-up: first connection, first paint, lazy imports
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.hogs)]
    try:
        headless, in_gui = [], []
        for i in range(args.repeats):
            headless.append(recorded_run(args.seconds, realtime=True, session_dir=tmp, rig=rig)[1])
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
    recs, _ = recorded_run(75.0, realtime=False)
    times, etfe_s = frame_times(app, win, recs)
    ms = {k: (statistics.median(v) * 1e3, np.percentile(v, 90) * 1e3) for k, v in times.items()}
    print(f"frame time, one redraw tick (4 curves x {win.live.traces.window} points, 0.1 s of new data a "
          f"frame after 60 s, live ETFE update), {QtWidgets.QApplication.platformName()}, "
          f"load average {os.getloadavg()[0]:.1f}:")
    for key, floor, what in (("estimate", "floor", "with a new estimate (goal <= 8 ms)"),
                             ("traces", "floor_traces", "traces only (between two estimates)")):
        print(f"  {what}: median {ms[key][0]:.2f} ms, p90 {ms[key][1]:.2f} ms; floor (the same "
              f"widgets repainted, no new data) {ms[floor][0]:.2f} ms; ratio {ms[key][0] / ms[floor][0]:.2f}")
    print(f"  live ETFE update for 0.5 s of new data (worker thread): median "
          f"{statistics.median(etfe_s) * 1e3:.2f} ms")


if __name__ == "__main__":
    sys.exit(main())
