"""A raw CAN trace of everything a driver sends and receives, through python-can's writers.

``TracedBus`` wraps an open bus: each frame sent (marked Tx) and received (Rx)
goes to ``can.Logger(path)``, which picks the format from the suffix (.asc,
.blf, .log, .trc, .csv, ...), readable back with ``can.LogReader`` and by
candump or Vector tools. Frames sent are not echoed by most interfaces, hence
the wrapper rather than a listener. Frames are written under a lock: in the
service phase the receive thread and the caller's thread both write (a
writer's file is not safe for two threads: interleaved writes corrupt it).
"""
from __future__ import annotations

import threading
import time

import can

from labbench.errors import UserError


class TracedBus:
    """``bus`` with every frame written to ``path``; ``shutdown()`` closes both."""

    def __init__(self, bus: can.BusABC, path: str):
        try:
            self._writer = can.Logger(path)
        except (ValueError, OSError) as exc:
            raise UserError(f"cannot write CAN trace {path}: {exc}") from None
        self.bus, self.path = bus, str(path)
        self._lock = threading.Lock()

    def send(self, msg: can.Message, timeout=None) -> None:
        self.bus.send(msg, timeout)
        msg.timestamp, msg.is_rx = time.time(), False
        with self._lock:
            self._writer.on_message_received(msg)

    def recv(self, timeout=None):
        msg = self.bus.recv(timeout)
        if msg is not None:
            with self._lock:
                self._writer.on_message_received(msg)
        return msg

    def shutdown(self) -> None:
        try:
            self.bus.shutdown()
        finally:
            with self._lock:
                self._writer.stop()

    def __getattr__(self, name):  # state, channel_info, filters, ... of the real bus
        return getattr(self.bus, name)
