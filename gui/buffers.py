"""The GUI's copy of one record stream (live run or replay), without Qt.

Pages are appended into growable numpy arrays so the plots can take the last
N points and the live estimator a snapshot of everything so far without
re-joining lists on every frame. Only the GUI thread touches a buffer: the
acquisition thread hands records over through a queue (``labbench.gui.worker``).
"""
from __future__ import annotations

import numpy as np

from labbench.records import CHANNELS, RecordRouter


class StreamBuffer(RecordRouter):
    """Accumulates start/descriptor/page/event/stop records of one run."""

    def __init__(self, capacity: int = 16384):
        self._cap = capacity
        self._data = {name: np.empty(capacity) for name in CHANNELS}
        self.n = 0
        self.start: dict | None = None
        self.descriptor: dict | None = None
        self.stop: dict | None = None
        self.events: list[dict] = []
        self.version = 0  # bumps on every page, so views know when to redraw

    def on_start(self, rec: dict) -> None:
        self.start = rec

    def on_descriptor(self, rec: dict) -> None:
        self.descriptor = rec

    def on_event(self, rec: dict) -> None:
        self.events.append(rec)

    def on_stop(self, rec: dict) -> None:
        self.stop = rec

    def on_page(self, rec: dict) -> None:
        data = rec["data"]
        k = len(np.asarray(data["t"]))
        if self.n + k > self._cap:
            self._cap = max(2 * self._cap, self.n + k)
            for name, arr in self._data.items():
                grown = np.empty(self._cap)
                grown[: self.n] = arr[: self.n]
                self._data[name] = grown
        for name in CHANNELS:
            self._data[name][self.n : self.n + k] = np.asarray(data[name], dtype=float)
        self.n += k
        self.version += 1

    def channel(self, name: str, last: int | None = None) -> np.ndarray:
        """A view of channel ``name`` (the last ``last`` samples if given)."""
        lo = 0 if last is None else max(0, self.n - last)
        return self._data[name][lo : self.n]

    def snapshot(self, names=None) -> dict[str, np.ndarray]:
        """Copies of the channels ``names`` (default all) so far, safe to hand to another
        thread or process."""
        return {name: self._data[name][: self.n].copy() for name in (names or CHANNELS)}

    @property
    def sample_time_s(self) -> float | None:
        if self.descriptor and self.descriptor.get("sample_time_s"):
            return float(self.descriptor["sample_time_s"])
        return None
