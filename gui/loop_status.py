"""The loop's health in the status bar: mode, pacing and rate, period p99, overruns, worst
stall and bus load, all from one timing summary (``labbench.loop.timing.status_figures``): live
during a run (the snapshots the acquisition process sends 4 times a second) and the run's
totals at its end. A lock-step simulator says so ("lock-step (unpaced): 2.3x real time")
instead of a loop rate it does not have, and has no overruns to count."""
from __future__ import annotations

from PySide6 import QtWidgets

FIELDS = ("mode", "loop rate", "period p99", "overruns", "worst stall", "bus load")
SHOWN_WHEN_MEASURED = ("bus load",)  # a CAN bus's: not shown for a backend without one


class LoopStatus:
    """Permanent labels in ``status_bar``; ``labels`` by field name (what a person reads)."""

    def __init__(self, status_bar: QtWidgets.QStatusBar):
        self.labels = {k: QtWidgets.QLabel(f"{k}: -") for k in FIELDS}
        for key, lab in self.labels.items():
            status_bar.addPermanentWidget(lab)
            lab.setVisible(key not in SHOWN_WHEN_MEASURED)

    def show_mode(self, mode: str) -> None:
        self.labels["mode"].setText(f"mode: {mode}")

    def clear(self, why: str = "-") -> None:
        """A new run or a replay: nothing of the last run's figures stays."""
        for key in FIELDS[1:]:
            self.labels[key].setText(f"{key}: {why if key == 'loop rate' else '-'}")

    def show_overruns(self, n: int) -> None:
        """Overruns counted from the samples' flags (a replay: no timing is sent)."""
        self.labels["overruns"].setText(f"overruns: {n} (recorded)")

    def show_timing(self, timing: dict, live: bool = False, recorded: bool = False) -> None:
        """``live``: a run's figures so far; ``recorded``: a replayed session's, as its run
        ended (the stop record's timing: what the live window showed then)."""
        from labbench.loop.timing import status_figures

        fig = status_figures(timing)

        def ms(v):
            return f"{v * 1e3:.2f} ms" if isinstance(v, (int, float)) else "-"

        tag = " (live)" if live else " (recorded)" if recorded else ""
        if fig["paced"]:
            rate = fig["rate_text"]
        else:  # a lock-step simulator: how fast the host simulates, not a loop rate
            s = fig["speed"]
            speed = "-" if s is None else f"{s:.0f}x real time" if s >= 10 else f"{s:.2g}x real time"
            rate = f"lock-step (unpaced): {speed}"
        self.labels["loop rate"].setText(f"loop: {rate}{tag}")
        if fig["p99_s"] is not None or not live:
            what = "period p99" if fig["paced"] else "compute per sample p99"
            self.labels["period p99"].setText(f"{what}: {ms(fig['p99_s'])}")
        overruns = "- (unpaced: no period to overrun)" if fig["overruns"] is None else fig["overruns"]
        self.labels["overruns"].setText(f"overruns: {overruns}{tag}")
        at = f" at {fig['worst_t_s']:.1f} s" if isinstance(fig["worst_t_s"], (int, float)) else ""
        self.labels["worst stall"].setText(f"worst stall: {ms(fig['max_s'])}{at}{tag}")
        if "bus_load" in timing:
            self.labels["bus load"].setText(f"bus load: {100 * timing['bus_load']:.0f} %")
            self.labels["bus load"].setVisible(True)
