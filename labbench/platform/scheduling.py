"""The loop thread's priority: Linux SCHED_FIFO and CPU affinity, Windows priority classes.

``labbench.loop.realtime`` decides what to ask for and why; this module holds the calls.
Every function that changes something appends its undo to ``undo`` and the reason of a
refusal to ``refused``.
"""
from __future__ import annotations

import ctypes
import os
import sys
import threading

from labbench.platform import is_windows

_LINUX_CALLS = ("sched_getscheduler", "sched_setscheduler", "sched_getparam", "sched_param",
                "sched_getaffinity", "sched_setaffinity", "SCHED_FIFO")
# Windows (winbase.h): HIGH, not REALTIME, class: a REALTIME process can starve the input
# and disk threads of the system; TIME_CRITICAL is the highest thread level in a class.
HIGH_PRIORITY_CLASS = 0x80
THREAD_PRIORITY_TIME_CRITICAL = 15


def kind() -> str | None:
    """"linux" (os.sched_*), "windows" (kernel32 priorities) or None: nothing to ask."""
    if sys.platform.startswith("linux") and all(hasattr(os, n) for n in _LINUX_CALLS):
        return "linux"
    return "windows" if is_windows() else None


# ------------------------------------------------------------------------------------ Linux
def allowed_cpus() -> list[int]:
    """The CPUs this process may run on ([] where the OS does not say)."""
    return affinity(0)


def affinity(tid: int) -> list[int]:
    try:
        return sorted(os.sched_getaffinity(tid))
    except (OSError, AttributeError):
        return []


def policy_name() -> str:
    try:
        policy = os.sched_getscheduler(0)
    except (OSError, AttributeError):
        return "unknown"
    names = {getattr(os, n): n for n in ("SCHED_OTHER", "SCHED_FIFO", "SCHED_RR", "SCHED_BATCH",
                                          "SCHED_IDLE") if hasattr(os, n)}
    return names.get(policy, str(policy))


def python_threads() -> list[int]:
    """Native ids of this process's live Python threads."""
    return [t.native_id for t in threading.enumerate() if t.native_id is not None]


def set_fifo(tid: int, cpu: int | None, priority: int, undo: list, refused: list) -> bool:
    """Affinity ``cpu`` and SCHED_FIFO ``priority`` for thread ``tid``; True if FIFO was granted.
    (Linux: both calls act on one thread when given its id.)"""
    try:
        old_policy, old_param = os.sched_getscheduler(tid), os.sched_getparam(tid)
        old_cpus = os.sched_getaffinity(tid)
    except OSError as exc:  # the thread ended
        refused.append(f"thread {tid}: {exc.strerror}")
        return False
    if cpu is not None and old_cpus != {cpu}:
        try:
            os.sched_setaffinity(tid, {cpu})
            undo.append(lambda: os.sched_setaffinity(tid, old_cpus))
        except OSError as exc:
            refused.append(f"CPU affinity: {exc.strerror}")
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        refused.append(f"SCHED_FIFO {priority}: {exc.strerror}")
        return False
    undo.append(lambda: os.sched_setscheduler(tid, old_policy, old_param))
    return True


# ---------------------------------------------------------------------------------- Windows
def _last_error():
    """The calling thread's Windows error code (ctypes has it on Windows only)."""
    return ctypes.get_last_error() if is_windows() else "unknown"


def raise_windows_priority(undo: list, refused: list, kernel32=None) -> bool:
    """The process in the HIGH priority class, the calling thread TIME_CRITICAL; True if both
    were granted. (The undo must run on the calling thread: its handle is a pseudo-handle.)"""
    k = kernel32 or ctypes.WinDLL("kernel32", use_last_error=True)
    for handle, get, put, value, name in (
            (k.GetCurrentProcess(), k.GetPriorityClass, k.SetPriorityClass, HIGH_PRIORITY_CLASS,
             "HIGH_PRIORITY_CLASS"),
            (k.GetCurrentThread(), k.GetThreadPriority, k.SetThreadPriority,
             THREAD_PRIORITY_TIME_CRITICAL, "THREAD_PRIORITY_TIME_CRITICAL")):
        old = get(handle)
        if not put(handle, value):
            refused.append(f"{name}: Windows error {_last_error()}")
            return False
        undo.append(lambda put=put, handle=handle, old=old: put(handle, old))
    return True
