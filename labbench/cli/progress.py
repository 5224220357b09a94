"""What a command says on stderr besides its error: a one-line progress bar with elapsed time and
ETA (drawn only on a terminal), and warnings (``warner``)."""
from __future__ import annotations

import sys
import time
from collections.abc import Callable


def warner(command: str) -> Callable[[str], None]:
    """``warn(line)`` printing ``labbench <command>: warning: <line>`` on one line."""
    from labbench.readout.escape import one_line

    def warn(line: str) -> None:
        print(f"labbench {command}: warning: {one_line(line)}", file=sys.stderr, flush=True)

    return warn


def clock_text(seconds: float) -> str:
    """``m:ss`` (``h:mm:ss`` from an hour on)."""
    s = int(round(max(seconds, 0.0)))
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class ProgressBar:
    """Callable ``(fraction, message)``, as ``labbench.runner.run`` expects.

    Shows the time since the first call and an estimate of the time left
    (elapsed x (1 - f) / f: a run's samples come at a steady rate).
    Redraws at most every ``min_interval_s`` (the loop reports every page) and
    stays silent when ``stream`` is not a tty (pipes, files, ``--json``).
    """

    def __init__(self, label: str, stream=None, width: int = 30, min_interval_s: float = 0.1,
                 clock=time.monotonic):
        self.stream = stream if stream is not None else sys.stderr
        self.label, self.width, self.min_interval_s = label, width, min_interval_s
        isatty = getattr(self.stream, "isatty", None)
        self.enabled = bool(isatty and isatty())
        self._clock = clock
        self._t0: float | None = None
        self._last = -float("inf")
        self._drawn = False

    def line(self, fraction: float, message: str = "") -> str:
        """The text of the bar at ``fraction`` done (0-1)."""
        now = self._clock()
        if self._t0 is None:
            self._t0 = now
        elapsed = now - self._t0
        fraction = min(max(fraction, 0.0), 1.0)
        filled = round(fraction * self.width)
        bar = "#" * filled + "-" * (self.width - filled)
        eta = clock_text(elapsed * (1 - fraction) / fraction) if fraction > 0 else "?"
        return (f"{self.label} [{bar}] {fraction * 100:5.1f}% {clock_text(elapsed)} "
                f"ETA {eta:<7} {message[:30]:<30}")

    def __call__(self, fraction: float, message: str = "") -> None:
        if not self.enabled:
            return
        now = self._clock()
        if self._t0 is not None and fraction < 1.0 and now - self._last < self.min_interval_s:
            return
        self._last = now
        self.stream.write("\r" + self.line(fraction, message))
        self.stream.flush()
        self._drawn = True

    def close(self) -> None:
        """End the line (if anything was drawn); safe to call twice."""
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
