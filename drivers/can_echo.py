"""A bus that hands back no frame of its own sending (python-can's ``udp_multicast``
does: every member of the group, the sender too, receives each datagram)."""
from __future__ import annotations

import threading
import time
from collections import deque

import can

PENDING_MAX = 4096  # own frames not yet seen back; older ones are taken as lost
# A datagram socket with a timeout polls for room before it sends (CPython's socket
# timeouts): a host thread kept off the CPU past a 1 ms send timeout then reads as a
# transmit failure though nothing was full. The bus's own limit, never below this.
SEND_TIMEOUT_FLOOR_S = 0.05


def _key(msg: can.Message) -> tuple:
    return msg.arbitration_id, msg.is_remote_frame, msg.is_error_frame, bytes(msg.data)


class EchoFreeBus:
    """``bus`` whose ``recv`` drops the copies of frames this side sent.

    The copies come back in the order sent, among others' frames: a received
    frame equal to a pending own frame is its copy (it and older unmatched ones
    are struck off). ``echoes`` counts the dropped copies.
    """

    def __init__(self, bus: can.BusABC):
        self.bus = bus
        self.echoes = 0
        self._pending: deque = deque(maxlen=PENDING_MAX)
        self._lock = threading.Lock()

    def send(self, msg: can.Message, timeout=None) -> None:
        with self._lock:
            self._pending.append(_key(msg))
        self.bus.send(msg, None if timeout is None else max(timeout, SEND_TIMEOUT_FLOOR_S))

    def _is_echo(self, msg: can.Message) -> bool:
        key = _key(msg)
        with self._lock:
            pending = self._pending
            if not pending:
                return False
            if pending[0] == key:
                pending.popleft()
                return True
            if key not in pending:
                return False
            while pending.popleft() != key:
                pass
            return True

    def recv(self, timeout=None):
        end = None if timeout is None else time.perf_counter() + timeout
        while True:
            msg = self.bus.recv(timeout)
            if msg is None or not self._is_echo(msg):
                return msg
            self.echoes += 1
            if end is not None:
                timeout = max(0.0, end - time.perf_counter())

    def shutdown(self) -> None:
        self.bus.shutdown()

    def __getattr__(self, name):  # state, channel_info, filters, ... of the real bus
        return getattr(self.bus, name)
