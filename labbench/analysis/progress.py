"""Progress reports and cancellation of a long analysis (a window's progress bar and
Cancel button; docs/notebook.md).

The analysis entry points (``labbench.session_api``'s ``Session.etfe`` and
``Session.identify``, and the analyses under them) take ``progress(fraction, phrase)``,
fraction 0..1 never going back, and ``cancel``, a ``threading.Event``: once it is set
the analysis raises ``labbench.errors.Cancelled`` at its next check. The checks sit
between steps that take well under half a second on the longest record a run can make
(1800 s at 1 kHz; bench/bench_analysis_scaling.py measures the longest gap).
"""
from __future__ import annotations

import threading
from collections.abc import Callable

from labbench.errors import Cancelled

Progress = Callable[[float, str], None]


class Steps:
    """One analysis's progress callback and cancel event (either may be None)."""

    def __init__(self, progress: Progress | None = None, cancel: threading.Event | None = None):
        self.progress = progress
        self.cancel = cancel

    def check(self) -> None:
        """Raise Cancelled if the cancel event is set."""
        if self.cancel is not None and self.cancel.is_set():
            raise Cancelled("analysis cancelled")

    def report(self, fraction: float, phrase: str) -> None:
        """Check, then tell the callback how far the analysis is (0..1) and what it does."""
        self.check()
        if self.progress is not None:
            self.progress(min(max(float(fraction), 0.0), 1.0), phrase)

    def part(self, lo: float, hi: float) -> Progress | None:
        """A progress callback for a sub-analysis: its 0..1 maps onto lo..hi of this one."""
        outer = self.progress
        if outer is None:
            return None
        return lambda fraction, phrase: outer(lo + (hi - lo) * fraction, phrase)
