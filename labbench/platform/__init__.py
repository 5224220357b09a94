"""What the operating system decides, in one place, each ability degrading on its own.

labbench runs where labs run it: Linux, Windows (where the CAN adapters' drivers ship
first) and macOS. The POSIX-only parts of Python (``signal.SIGHUP``, ``os.sched_*``,
``os.openpty``, ``termios``/``fcntl``/``resource``) are absent from a Windows Python, so no
module refers to them at import; each is looked up where it is used, and a missing
ability gives one warning line (``missing``) and the command goes on without it.

* ``signals``: the signals that end a command (SIGINT, SIGTERM, SIGHUP or SIGBREAK) and,
  on Windows, the console's close / log-off / shut-down events;
* ``scheduling``: the loop thread's priority (Linux SCHED_FIFO and CPU affinity;
  Windows priority class and thread priority);
* ``latency``: the CPU wake-up latency request (Linux PM QoS; Windows the 1 ms timer
  resolution);
* ``memlock``: locking the process's memory (``mlockall``);
* ``serial_peer``: the simulated serial board's transport (a pty on POSIX, a local
  socket through pyserial's ``socket://`` URL elsewhere).
"""
from __future__ import annotations

import logging
import sys
import threading

log = logging.getLogger(__name__)

_missing: set[str] = set()
_lock = threading.Lock()


def missing(ability: str, consequence: str, warn=None) -> None:
    """Say once per process, in one line, that ``ability`` is not available here and what
    that means (``warn``: where the line goes; default a logging warning)."""
    with _lock:
        if ability in _missing:
            return
        _missing.add(ability)
    (warn or log.warning)(f"labbench: {ability} not available on this platform "
                          f"({sys.platform}): {consequence}")


def is_windows() -> bool:
    return sys.platform == "win32"
