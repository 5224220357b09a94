"""The Design page's redraw: a slider move to the painted page (goal: within 50 ms).

Each move sets one slider of the page (gui/design_view.py) to its next value, which runs the
whole redraw in the window's thread (the setting's K_max, unless cached for its B, w0 and T,
the passive bounds, the noise spectrum, the ED curves, the numbers), then the event loop
until the plots' viewport has painted (checked: a move that painted nothing raises). Moves of
K reuse the cached K_max; moves of B, w0 and T find a new one. The floor is the same page
repainted through the same path with nothing new (``scene().update()``), measured in the
same run; beside the wall time, the process's CPU time per move (what the move costs whatever
else the machine runs). Offscreen, on this shared 2-core machine. ``--coulomb-n``: the page
for the rough simulator's device with that Coulomb friction (its noise friction-aware: the
linearisation solved at every move).

    QT_QPA_PLATFORM=offscreen .venv/bin/python bench/bench_design.py [--moves 40] [--coulomb-n 0.02]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402
from PySide6 import QtCore, QtWidgets  # noqa: E402

from labbench.design.tradeoffs import Device  # noqa: E402
from labbench.gui.design_view import SLIDERS, DesignView  # noqa: E402
from labbench.rig import Rig  # noqa: E402
from labbench.model.ve import DEFAULT_PLANT  # noqa: E402

GOAL_S = 0.050


class PaintCounter(QtCore.QObject):
    """Counts the paint events of one widget."""

    def __init__(self, widget):
        super().__init__()
        self.n = 0
        widget.installEventFilter(self)

    def eventFilter(self, obj, ev):  # noqa: N802 - Qt override
        if ev.type() == QtCore.QEvent.Type.Paint:
            self.n += 1
        return False


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--moves", type=int, default=40, help="moves per slider")
    ap.add_argument("--coulomb-n", type=float, default=None,
                    help="the rough simulator's device with this Coulomb friction [N]")
    args = ap.parse_args()
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv)
    view = DesignView(None if args.coulomb_n is None else Device(
        DEFAULT_PLANT, 0.0, Rig().metres_per_count, 0.002, args.coulomb_n))
    view.resize(1400, 850)
    view.show()
    app.processEvents()
    painted = PaintCounter(view.plots.viewport())

    cpu = {}

    def timed(action, into: str = "floor") -> float:
        painted.n = 0
        t, c = time.perf_counter(), time.process_time()
        action()
        app.processEvents()
        dt = time.perf_counter() - t
        cpu.setdefault(into, []).append(time.process_time() - c)
        if painted.n < 1:
            raise RuntimeError("a move did not paint the plots")
        return dt

    rng = np.random.default_rng(1)
    results = {}
    for name in ("K", "B", "w0", "T"):
        s = view.sliders[name]
        n_values = len(SLIDERS[name][2])
        times = []
        for _ in range(3 + args.moves):  # a random walk: B, w0, T reach uncached settings
            step = int(rng.choice([-1, 1]))
            nxt = s.value() + step if 0 <= s.value() + step < n_values else s.value() - step
            times.append(timed(lambda: s.setValue(nxt), name))
        results[name] = times[3:]
        move = {"K": 50.0, "B": 1.0, "w0": 125.0, "T": 1.0}[name]  # back to the paper's demo
        s.setValue(int(np.argmin(np.abs(SLIDERS[name][2] - move))))
    floor = [timed(lambda: view.plots.scene().update()) for _ in range(args.moves)]
    device = "no friction" if args.coulomb_n is None else f"Coulomb friction {args.coulomb_n:g} N"
    print(f"Design page ({device}), slider move to painted page, {args.moves} moves per slider "
          f"(offscreen, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}):")
    print(f"{'slider':>8} {'median ms':>10} {'p90 ms':>8} {'max ms':>8} {'median/floor':>13} "
          f"{'within 50 ms':>13} {'CPU median ms':>14}")
    f_med = statistics.median(floor)
    for name, times in results.items():
        q = np.quantile(times, [0.5, 0.9])
        within = sum(t <= GOAL_S for t in times)
        print(f"{name:>8} {1e3 * q[0]:>10.1f} {1e3 * q[1]:>8.1f} {1e3 * max(times):>8.1f} "
              f"{q[0] / f_med:>13.1f} {within:>9}/{len(times)} "
              f"{1e3 * statistics.median(cpu[name][3:]):>14.1f}")
    print(f"{'floor':>8} {1e3 * f_med:>10.1f} {1e3 * np.quantile(floor, 0.9):>8.1f} "
          f"{1e3 * max(floor):>8.1f} {'':>13} {'':>13} {1e3 * statistics.median(cpu['floor']):>14.1f}")
    print("(CPU: this process's time, what the move costs whatever the machine's load)")
    worst = max(statistics.median(t) for t in results.values())
    print(f"worst slider's median {1e3 * worst:.1f} ms: goal 50 ms "
          f"{'met' if worst <= GOAL_S else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
