"""A one-line terminal progress bar on stderr, drawn only when stderr is a terminal."""
from __future__ import annotations

import sys
import time


class ProgressBar:
    """Callable ``(fraction, message)``, as ``labbench.runner.run`` expects.

    Redraws at most every ``min_interval_s`` (the loop reports every page) and
    stays silent when ``stream`` is not a tty (pipes, files, ``--json``).
    """

    def __init__(self, label: str, stream=None, width: int = 30, min_interval_s: float = 0.1):
        self.stream = stream if stream is not None else sys.stderr
        self.label, self.width, self.min_interval_s = label, width, min_interval_s
        isatty = getattr(self.stream, "isatty", None)
        self.enabled = bool(isatty and isatty())
        self._last = 0.0
        self._drawn = False

    def __call__(self, fraction: float, message: str = "") -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if fraction < 1.0 and now - self._last < self.min_interval_s:
            return
        self._last = now
        fraction = min(max(fraction, 0.0), 1.0)
        filled = round(fraction * self.width)
        bar = "#" * filled + "-" * (self.width - filled)
        self.stream.write(f"\r{self.label} [{bar}] {fraction * 100:5.1f}% {message[:30]:<30}")
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
