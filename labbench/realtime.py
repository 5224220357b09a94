"""Real-time scheduling for the thread that runs the haptic loop (Linux).

``acquire(config)`` is a context manager entered by the thread about to run a
paced loop (``labbench.runner.run``: ``labbench run``, the GUI's acquisition
process). For its duration it asks, each step on its own:

* SCHED_FIFO at ``priority`` for this thread; the process's other Python
  threads (a simulated peer standing in for hardware, the session's fsync
  thread, the acquisition process's message feeder) at ``priority - 1``. They
  share the GIL with the loop: left at normal priority, one of them preempted
  by another process while it holds the GIL stalls the loop for a whole time
  slice. Only the threads alive at entry: one started later by the loop's thread
  inherits the loop's own priority and CPU, so start helpers (the session's fsync
  thread) before entering. Only Python threads: a BLAS worker pool moved below
  the loop on its CPU livelocks any BLAS call the loop's thread makes (it
  spin-waits for its workers, which then never run - measured: a scipy ``expm``
  never returned);
* CPU affinity: all these threads on one CPU (the last one allowed) when there
  are two or more, so the GUI and everything else have the others to themselves;
* ``mlockall`` (current and future pages, locked as they fault in): no page of
  the loop is swapped out or reclaimed under memory pressure;
* the cyclic GC collected once, frozen and disabled: a collection of the
  generations the GUI's or analysis' objects fill would stop the loop for ms;
* a GIL switch interval of 100 us: a sibling thread hands the GIL back that fast;
* a CPU wake-up latency limit (the kernel's PM QoS, ``/dev/cpu_dma_latency``,
  held while the file stays open; Documentation/power/pm_qos_interface.rst): at
  ``cpu_latency_us = 0`` an idle CPU polls instead of entering a sleep state, so
  the loop's wake-up is not delayed by the exit from one (measured on a VM whose
  idle state is a halt the hypervisor takes the CPU away on, at no load: periods
  > 1.5 T per 100 000, 280 without it and 89 with it for a paced simulated run,
  184 and 118 for the bare pacer; docs/loop.md). The cost is an idle CPU that
  keeps running (power, and on a VM the host's CPU time).

Where the OS refuses (no CAP_SYS_NICE, a zero rtprio limit), one warning line
per process says how to grant it and the run goes on. ``Grant.record`` is what
was obtained (policy, priority, affinity, memory lock, GC state), stored in the
session beside the timing. Everything is restored on the way out.

``sleep_until`` is the pacing wait: sleep until ``SPIN_S`` before the deadline,
then spin. Never spin longer: a SCHED_FIFO thread spinning without bound owns
its CPU (the kernel's RT throttling leaves others 5 %).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import os
import struct
import sys
import threading
import time
from dataclasses import asdict, dataclass

from labbench.errors import UserError

log = logging.getLogger(__name__)

SPIN_S = 150e-6  # spin this long before a deadline: a sleep's wake-up is later by up to ~100 us
SWITCH_INTERVAL_S = 1e-4
CPU_LATENCY_FILE = "/dev/cpu_dma_latency"
_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4
_warned: set[str] = set()
_lock = threading.Lock()


@dataclass(frozen=True)
class RealtimeConfig:
    """What the loop's thread asks for. ``cpu`` None: the last CPU allowed (when >= 2)."""

    enabled: bool = True
    priority: int = 80
    cpu: int | None = None
    lock_memory: bool = True
    cpu_latency_us: int = 0  # PM QoS wake-up limit while the loop runs; -1: not asked

    def __post_init__(self):
        if not 1 <= self.priority <= 98:  # 99 is the kernel's watchdog/migration threads' level
            raise UserError(f"real-time priority must be 1..98, got {self.priority}")
        if self.cpu is not None and self.cpu < 0:
            raise UserError(f"real-time CPU must be >= 0, got {self.cpu}")
        if self.cpu_latency_us < -1:
            raise UserError(f"CPU latency limit must be >= 0 us (or -1: none), "
                            f"got {self.cpu_latency_us}")

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_rig(cls, rig, **overrides) -> "RealtimeConfig":
        """From the rig's optional ``[realtime]`` table (enabled, priority, cpu, lock_memory,
        cpu_latency_us), then ``overrides`` (None values ignored: the CLI's absent flags)."""
        table = rig.section("realtime") if rig is not None else {}
        kinds = {"enabled": bool, "priority": int, "cpu": int, "lock_memory": bool,
                 "cpu_latency_us": int}
        values = {}
        for name, value in {**table, **{k: v for k, v in overrides.items() if v is not None}}.items():
            if name not in kinds:
                raise UserError(f"{getattr(rig, 'source', 'rig')}: [realtime] {name}: unknown "
                                f"(known: {', '.join(kinds)})")
            if not isinstance(value, kinds[name]) or (kinds[name] is int and isinstance(value, bool)):
                raise UserError(f"{getattr(rig, 'source', 'rig')}: [realtime] {name} must be "
                                f"{'true or false' if kinds[name] is bool else 'a whole number'}, "
                                f"got {value!r}")
            values[name] = value
        return cls(**values)


def sleep_until(deadline: float, clock=time.perf_counter) -> None:
    """Return at ``deadline`` (a ``clock`` time): sleep, then spin at most the last SPIN_S."""
    left = deadline - clock()
    if left > SPIN_S:
        time.sleep(left - SPIN_S)
    while clock() < deadline:
        pass


def hint() -> str:
    """How to grant a user real-time scheduling, locked memory and the CPU latency limit."""
    return ("grant it with '<user> - rtprio 95' and '<user> - memlock unlimited' in "
            "/etc/security/limits.conf (then log in again), or CAP_SYS_NICE and CAP_IPC_LOCK "
            f"on the interpreter (setcap), and write access to {CPU_LATENCY_FILE} (a udev rule); "
            "see docs/loop.md")


class Grant:
    """The context of ``acquire``: ``record`` says what the OS granted."""

    def __init__(self, config: RealtimeConfig, warn=None):
        self.config = config
        self.warn = warn or log.warning
        self.record: dict = {"requested": config.enabled, "policy": _policy_name(),
                             "priority": 0, "affinity": _affinity(0), "memory_locked": False,
                             "gc": "enabled" if gc.isenabled() else "disabled",
                             "cpu_latency_us": None,
                             "threads": 0, "refused": []}
        self._undo: list = []

    def __enter__(self) -> "Grant":
        if not self.config.enabled or not sys.platform.startswith("linux"):
            if self.config.enabled:
                self.record["refused"].append(f"not available on {sys.platform}")
            return self
        try:
            self._enter()
        except BaseException:
            self._restore()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._restore()

    # ------------------------------------------------------------------------------------
    def _enter(self) -> None:
        cfg, rec, refused = self.config, self.record, self.record["refused"]
        tid = threading.get_native_id()
        allowed = sorted(os.sched_getaffinity(0))
        cpu = None
        if cfg.cpu is not None:
            if cfg.cpu not in allowed:
                raise UserError(f"real-time CPU {cfg.cpu} is not one this process may use "
                                f"({','.join(map(str, allowed))})")
            cpu = cfg.cpu
        elif len(allowed) >= 2:
            cpu = allowed[-1]
        siblings = [t for t in _threads() if t != tid]
        granted = _set_thread(tid, cpu, cfg.priority, self._undo, refused)
        if granted:
            rec.update(policy="SCHED_FIFO", priority=cfg.priority)
            for t in siblings:
                if _set_thread(t, cpu, cfg.priority - 1, self._undo, []):
                    rec["threads"] += 1
            old = sys.getswitchinterval()
            sys.setswitchinterval(SWITCH_INTERVAL_S)
            self._undo.append(lambda: sys.setswitchinterval(old))
        rec["affinity"] = _affinity(0)
        if cfg.lock_memory:
            err = _mlockall()
            if err is None:
                rec["memory_locked"] = True
                self._undo.append(_munlockall)
            else:
                refused.append(f"mlockall: {err}")
        if cfg.cpu_latency_us >= 0:
            err = self._hold_cpu_latency(cfg.cpu_latency_us)
            if err is None:
                rec["cpu_latency_us"] = cfg.cpu_latency_us
            else:
                refused.append(f"CPU latency limit ({CPU_LATENCY_FILE}): {err}")
        was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        self._undo.append(lambda: (gc.unfreeze(), gc.enable() if was_enabled else None))
        rec["gc"] = "frozen, disabled"
        if refused:
            _warn_once(self.warn, f"labbench: real-time scheduling refused ({'; '.join(refused)});"
                                  f" the loop runs as an ordinary process and may miss periods "
                                  f"under load: {hint()}")

    def _hold_cpu_latency(self, us: int) -> str | None:
        """Ask the kernel to keep CPU wake-up latency <= ``us`` until undone; None or the error."""
        try:
            fd = os.open(CPU_LATENCY_FILE, os.O_WRONLY | os.O_CLOEXEC)
        except OSError as exc:
            return exc.strerror
        try:
            os.write(fd, struct.pack("=i", us))  # a binary s32: the request lasts while open
        except OSError as exc:
            os.close(fd)
            return exc.strerror
        self._undo.append(lambda: os.close(fd))
        return None

    def _restore(self) -> None:
        while self._undo:
            undo = self._undo.pop()
            try:
                undo()
            except OSError:  # a sibling thread ended meanwhile
                pass


def acquire(config: RealtimeConfig | None = None, warn=None) -> Grant:
    """Context manager: real-time scheduling for the calling thread (see the module docstring)."""
    return Grant(config or RealtimeConfig(), warn)


# ----------------------------------------------------------------------------------- internals
def _set_thread(tid: int, cpu: int | None, priority: int, undo: list, refused: list) -> bool:
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


def _threads() -> list[int]:
    """Native ids of this process's live Python threads."""
    return [t.native_id for t in threading.enumerate() if t.native_id is not None]


def _affinity(tid: int) -> list[int]:
    try:
        return sorted(os.sched_getaffinity(tid))
    except OSError:
        return []


def _policy_name() -> str:
    try:
        policy = os.sched_getscheduler(0)
    except (OSError, AttributeError):
        return "unknown"
    names = {getattr(os, n): n for n in ("SCHED_OTHER", "SCHED_FIFO", "SCHED_RR", "SCHED_BATCH",
                                          "SCHED_IDLE") if hasattr(os, n)}
    return names.get(policy, str(policy))


def _libc():
    return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def _mlockall() -> str | None:
    """Lock current and future pages (as they fault in, where the kernel can); None or the error."""
    libc = _libc()
    for flags in (_MCL_CURRENT | _MCL_FUTURE | _MCL_ONFAULT, _MCL_CURRENT | _MCL_FUTURE):
        if libc.mlockall(flags) == 0:
            return None
        err = ctypes.get_errno()
        if err != 22:  # EINVAL: no MCL_ONFAULT before Linux 4.4, try without
            return os.strerror(err)
    return os.strerror(err)


def _munlockall() -> None:
    _libc().munlockall()


def _warn_once(warn, message: str) -> None:
    with _lock:
        if message in _warned:
            return
        _warned.add(message)
    warn(message)
