"""The CPU wake-up latency request: Linux PM QoS, Windows the 1 ms timer resolution.

Linux: ``/dev/cpu_dma_latency`` takes a binary s32 limit in us, held while the file
stays open (Documentation/power/pm_qos_interface.rst). Windows has no wake-up limit;
what delays a wake-up there is the system timer's period (15.6 ms by default):
``timeBeginPeriod(1)`` (winmm) asks for 1 ms until ``timeEndPeriod(1)``. macOS offers
neither to a user process.
"""
from __future__ import annotations

import ctypes
import os
import struct
import sys

from labbench.platform import is_windows

CPU_LATENCY_FILE = "/dev/cpu_dma_latency"


def kind() -> str | None:
    """"pm_qos" (Linux), "timer_resolution" (Windows) or None."""
    if sys.platform.startswith("linux"):
        return "pm_qos"
    return "timer_resolution" if is_windows() else None


def hold(us: int, undo: list, winmm=None) -> str | None:
    """Ask for wake-ups within ``us`` (Windows: 1 ms timer) until undone; None or the error."""
    if kind() == "timer_resolution" or winmm is not None:
        w = winmm or ctypes.WinDLL("winmm")
        if w.timeBeginPeriod(1) != 0:  # TIMERR_NOERROR
            return "timeBeginPeriod(1) refused"
        undo.append(lambda: w.timeEndPeriod(1))
        return None
    try:  # O_CLOEXEC: not inherited by a child process (POSIX only)
        fd = os.open(CPU_LATENCY_FILE, os.O_WRONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        return exc.strerror
    try:
        os.write(fd, struct.pack("=i", us))
    except OSError as exc:
        os.close(fd)
        return exc.strerror
    undo.append(lambda: os.close(fd))
    return None
