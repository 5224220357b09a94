"""Real-time scheduling for the thread that runs the haptic loop (Linux; Windows in part).

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

On Windows (``labbench.platform``) the loop's process gets the HIGH priority class and
its thread TIME_CRITICAL, and the timer resolution is 1 ms while the loop runs (the
latency request); there is no whole-process memory lock nor a CPU chosen. macOS offers
none of these to a user process. Each ability the platform lacks is one warning line
(``labbench.platform.missing``) and ``record["unavailable"]`` names it.

Where the OS refuses (no CAP_SYS_NICE, a zero rtprio limit), one warning line
per process says how to grant it and the run goes on. ``Grant.record`` is what
was obtained (policy, priority, affinity, memory lock, GC state), stored in the
session beside the timing. Everything is restored on the way out.

``sleep_until`` is the pacing wait: sleep until ``SPIN_S`` before the deadline,
then spin. Never spin longer: a SCHED_FIFO thread spinning without bound owns
its CPU (the kernel's RT throttling leaves others 5 %).
"""
from __future__ import annotations

import gc
import logging
import sys
import threading
import time
from dataclasses import asdict, dataclass

from labbench.errors import UserError
from labbench.platform import latency, memlock, missing, scheduling
from labbench.platform.latency import CPU_LATENCY_FILE

log = logging.getLogger(__name__)

SPIN_S = 150e-6  # spin this long before a deadline: a sleep's wake-up is later by up to ~100 us
SWITCH_INTERVAL_S = 1e-4
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
    if not sys.platform.startswith("linux"):
        return "see docs/loop.md"
    return ("grant it with '<user> - rtprio 95' and '<user> - memlock unlimited' in "
            "/etc/security/limits.conf (then log in again), or CAP_SYS_NICE and CAP_IPC_LOCK "
            f"on the interpreter (setcap), and write access to {CPU_LATENCY_FILE} (a udev rule); "
            "see docs/loop.md")


class Grant:
    """The context of ``acquire``: ``record`` says what the OS granted."""

    def __init__(self, config: RealtimeConfig, warn=None):
        self.config = config
        self.warn = warn or log.warning
        self.record: dict = {"requested": config.enabled, "policy": scheduling.policy_name(),
                             "priority": 0, "affinity": scheduling.affinity(0),
                             "memory_locked": False,
                             "gc": "enabled" if gc.isenabled() else "disabled",
                             "cpu_latency_us": None,
                             "threads": 0, "refused": [], "unavailable": []}
        self._undo: list = []

    def __enter__(self) -> "Grant":
        if not self.config.enabled:
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
        how = scheduling.kind()
        if how == "linux":
            granted = self._linux_fifo()
        elif how == "windows":
            granted = scheduling.raise_windows_priority(self._undo, refused)
            if granted:
                rec.update(policy="HIGH_PRIORITY_CLASS",
                           priority=scheduling.THREAD_PRIORITY_TIME_CRITICAL)
        else:
            granted = False
            self._missing("real-time scheduling", "the loop runs as an ordinary thread and may "
                                                  "miss periods under load")
        if granted:
            old = sys.getswitchinterval()
            sys.setswitchinterval(SWITCH_INTERVAL_S)
            self._undo.append(lambda: sys.setswitchinterval(old))
        rec["affinity"] = scheduling.affinity(0)
        if cfg.lock_memory:
            if not memlock.available():
                self._missing("memory locking", "a page of the loop may be paged out under "
                                                "memory pressure")
            elif (err := memlock.lock_all()) is None:
                rec["memory_locked"] = True
                self._undo.append(memlock.unlock_all)
            else:
                refused.append(f"mlockall: {err}")
        if cfg.cpu_latency_us >= 0:
            if latency.kind() is None:
                self._missing("the CPU latency request", "an idle CPU's wake-up may delay the "
                                                         "loop's")
            elif (err := latency.hold(cfg.cpu_latency_us, self._undo)) is None:
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

    def _missing(self, ability: str, consequence: str) -> None:
        self.record["unavailable"].append(ability)
        missing(ability, consequence, self.warn)

    def _linux_fifo(self) -> bool:
        """SCHED_FIFO and one CPU for this thread, one level below for the other Python threads."""
        cfg, rec = self.config, self.record
        tid = threading.get_native_id()
        allowed = scheduling.allowed_cpus()
        cpu = None
        if cfg.cpu is not None:
            if cfg.cpu not in allowed:
                raise UserError(f"real-time CPU {cfg.cpu} is not one this process may use "
                                f"({','.join(map(str, allowed))})")
            cpu = cfg.cpu
        elif len(allowed) >= 2:
            cpu = allowed[-1]
        siblings = [t for t in scheduling.python_threads() if t != tid]
        if not scheduling.set_fifo(tid, cpu, cfg.priority, self._undo, rec["refused"]):
            return False
        rec.update(policy="SCHED_FIFO", priority=cfg.priority)
        for t in siblings:
            if scheduling.set_fifo(t, cpu, cfg.priority - 1, self._undo, []):
                rec["threads"] += 1
        return True

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


def _warn_once(warn, message: str) -> None:
    with _lock:
        if message in _warned:
            return
        _warned.add(message)
    warn(message)
