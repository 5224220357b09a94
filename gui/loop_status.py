"""The loop's health in the status bar: mode, loop rate, period p99, overruns, worst stall
and bus load, live during a run (``labbench.timing``'s snapshots, sent by the acquisition
process 4 times a second) and the run's totals at its end."""
from __future__ import annotations

from PySide6 import QtWidgets

FIELDS = ("mode", "loop rate", "period p99", "overruns", "worst stall", "bus load")


class LoopStatus:
    """Permanent labels in ``status_bar``; ``labels`` by field name (what a person reads)."""

    def __init__(self, status_bar: QtWidgets.QStatusBar):
        self.labels = {k: QtWidgets.QLabel(f"{k}: -") for k in FIELDS}
        for lab in self.labels.values():
            status_bar.addPermanentWidget(lab)

    def show_mode(self, mode: str) -> None:
        self.labels["mode"].setText(f"mode: {mode}")

    def show_rate(self, rate: float | None) -> None:
        self.labels["loop rate"].setText(f"loop rate: {'-' if rate is None else f'{rate:.0f} Hz'}")

    def show_overruns(self, n: int) -> None:
        """Overruns counted from the samples' flags (a replay: no timing is sent)."""
        self.labels["overruns"].setText(f"overruns: {n} (live)")

    def show_timing(self, timing: dict, live: bool = False) -> None:
        def ms(key):
            v = timing.get(key)
            return f"{v * 1e3:.2f} ms" if isinstance(v, (int, float)) else "-"

        tag = " (live)" if live else ""
        if not live:
            self.labels["period p99"].setText(f"period p99: {ms('p99_s')}")
        self.labels["overruns"].setText(f"overruns: {timing.get('overruns', '-')}{tag}")
        when = timing.get("worst_t_s", (timing.get("worst") or {}).get("t_s"))
        at = f" at {when:.1f} s" if isinstance(when, (int, float)) else ""
        self.labels["worst stall"].setText(f"worst stall: {ms('max_s')}{at}{tag}")
        if "bus_load" in timing:
            self.labels["bus load"].setText(f"bus load: {100 * timing['bus_load']:.0f} %")
