"""Python's cyclic garbage collection run in the GUI thread only, while a window is up.

Python collects cycles in whichever thread allocates past a threshold. The window's worker
threads (the sweep points, a replay, the live estimator, the acquisition reader) allocate a
lot, so a cycle holding PySide wrappers (pyqtgraph's items and menus hold many) could be
freed from one of them: Qt objects deleted off the GUI thread, or while the GUI thread is
inside Qt. PySide 6.11 crashed there in Shiboken::BindingManager::releaseWrapper (CI,
stop 28: a segfault with a sweep worker thread running). pyqtgraph's remedy
(``pyqtgraph.util.garbage_collector.GarbageCollector``, after E. Janssens) turns automatic
collection off and collects from a timer of the GUI thread; this holds one and undoes it on
``close`` (the tests' windows share a process with tests that need automatic collection).
"""
from __future__ import annotations

import gc

from pyqtgraph.util.garbage_collector import GarbageCollector


class GuiThreadCollection:
    """Automatic collection off, a GUI-thread timer collecting every ``interval_s`` (make
    it in the GUI thread, with a QApplication); ``close`` collects once and restores."""

    def __init__(self, interval_s: float = 1.0):
        self._was_enabled = gc.isenabled()
        self._collector = GarbageCollector(interval=interval_s)

    def close(self) -> None:
        self._collector.timer.stop()
        gc.collect()
        if self._was_enabled:
            gc.enable()
