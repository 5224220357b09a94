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
