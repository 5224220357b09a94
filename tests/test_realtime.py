"""Real-time scheduling of the loop's thread: granted and undone, refused with one line."""
from __future__ import annotations

import gc
import json
import os
import resource
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time

import pytest

from labbench.errors import UserError
from labbench.loop.realtime import CPU_LATENCY_FILE, RealtimeConfig, acquire, sleep_until
from labbench.rig import Rig, load_rig

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_what_is_granted_is_recorded_and_undone_on_the_way_out():
    policy, cpus, gc_on = os.sched_getscheduler(0), os.sched_getaffinity(0), gc.isenabled()
    idle = threading.Event()
    sibling = threading.Thread(target=idle.wait, daemon=True)
    sibling.start()
    try:
        with acquire(RealtimeConfig(priority=10), warn=lambda line: None) as grant:
            rec = grant.record
            assert not gc.isenabled() and rec["gc"] == "frozen, disabled"
            assert rec["affinity"] == sorted(os.sched_getaffinity(0))
            if len(cpus) >= 2:
                assert rec["affinity"] == [max(cpus)]
            if rec["policy"] == "SCHED_FIFO":
                assert os.sched_getscheduler(0) == os.SCHED_FIFO
                assert os.sched_getparam(0).sched_priority == rec["priority"] == 10
                assert os.sched_getscheduler(sibling.native_id) == os.SCHED_FIFO
                assert os.sched_getparam(sibling.native_id).sched_priority == 9
            else:
                assert rec["refused"]
    finally:
        idle.set()
    assert os.sched_getscheduler(0) == policy and os.sched_getaffinity(0) == cpus
    assert gc.isenabled() == gc_on


def test_a_blas_call_under_realtime_scheduling_returns():
    """BLAS worker threads are not moved below the loop (that livelocked scipy's expm)."""
    code = ("import numpy as np, scipy.linalg as la\n"
            "from labbench.loop.realtime import acquire, RealtimeConfig\n"
            "a = np.random.default_rng(0).normal(size=(400, 400))\n"
            "with acquire(RealtimeConfig(priority=10), warn=print) as g:\n"
            "    la.expm(a / 400); (a @ a).sum()\n"
            "print('done', g.record['policy'])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "done" in out.stdout, out.stderr


def _cpu_latency_limit_us() -> int:
    """The kernel's current CPU wake-up latency limit (reading the QoS file gives it)."""
    with open(CPU_LATENCY_FILE, "rb") as f:
        return struct.unpack("=i", f.read(4))[0]


def test_the_cpu_latency_limit_is_held_only_while_the_loop_runs():
    """Held at 5 us while the loop runs and given back; where the file cannot be written,
    or another process already holds a limit this low, the grant says so instead."""
    if not os.access(CPU_LATENCY_FILE, os.R_OK | os.W_OK):
        with acquire(RealtimeConfig(priority=10, cpu_latency_us=5), warn=lambda line: None) as g:
            assert g.record["cpu_latency_us"] is None
            assert any(CPU_LATENCY_FILE in r for r in g.record["refused"]), g.record
        return
    before = _cpu_latency_limit_us()
    with acquire(RealtimeConfig(priority=10, cpu_latency_us=5), warn=lambda line: None) as g:
        assert _cpu_latency_limit_us() == min(before, 5) and g.record["cpu_latency_us"] == 5
    assert _cpu_latency_limit_us() == before
    with acquire(RealtimeConfig(priority=10, cpu_latency_us=-1), warn=lambda line: None) as g:
        assert _cpu_latency_limit_us() == before and g.record["cpu_latency_us"] is None


def test_sleep_until_never_returns_early():
    for k in range(50):
        deadline = time.perf_counter() + (k % 5) * 2e-4
        sleep_until(deadline)
        assert time.perf_counter() >= deadline


def test_settings_from_the_rig_and_the_flags():
    rig = Rig(sections={"realtime": {"priority": 60, "cpu": 0}})
    assert RealtimeConfig.from_rig(rig) == RealtimeConfig(priority=60, cpu=0)
    assert RealtimeConfig.from_rig(rig, enabled=False, priority=None).enabled is False
    assert RealtimeConfig.from_rig(Rig(sections={"realtime": {"cpu_latency_us": -1}})
                                   ).cpu_latency_us == -1
    for bad in ({"priority": 99}, {"priority": "high"}, {"colour": 1}, {"enabled": 1},
                {"cpu_latency_us": -2}, {"cpu_latency_us": 0.5}):
        with pytest.raises(UserError):
            RealtimeConfig.from_rig(Rig(sections={"realtime": bad}))


def test_a_rig_file_carries_the_realtime_table_and_a_bad_one_stops_at_load(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text("[rig]\nname = 'x'\n[realtime]\npriority = 70\ncpu_latency_us = -1\n")
    assert RealtimeConfig.from_rig(load_rig(good)) == RealtimeConfig(priority=70,
                                                                     cpu_latency_us=-1)
    bad = tmp_path / "bad.toml"
    bad.write_text("[realtime]\npriority = 99\n")
    with pytest.raises(UserError, match="priority must be 1..98"):
        load_rig(bad)


def _unprivileged(cmd: list[str]) -> tuple[list[str], object]:
    """cmd as a user without real-time rights: root drops to nobody (setpriv, util-linux),
    anyone else keeps their uid; either way with an rtprio limit of 0."""
    def no_rtprio():
        resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))

    if os.geteuid() != 0:
        return cmd, no_rtprio
    setpriv = shutil.which("setpriv")
    assert setpriv, "setpriv (util-linux) is needed to run a child without root's rights"
    return [setpriv, "--reuid=65534", "--regid=65534", "--clear-groups", *cmd], no_rtprio


def test_refused_gives_one_line_and_the_run_goes_on():
    """As an unprivileged user (no CAP_SYS_NICE, rtprio limit 0) a paced run still records."""
    with tempfile.TemporaryDirectory() as out_dir:  # in /tmp: pytest's tmp_path is root-only
        os.chmod(out_dir, 0o777)
        cmd, limit = _unprivileged([sys.executable, "-m", "labbench", "run", "etfe", "--realtime",
                                    "--duration-s", "1", "--json", "--out", out_dir])
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=out_dir,
                             preexec_fn=limit, check=False)
    assert out.returncode == 0, out.stderr
    warnings = [line for line in out.stderr.splitlines() if "real-time scheduling refused" in line]
    assert len(warnings) == 1 and "limits.conf" in warnings[0] and "CAP_SYS_NICE" in warnings[0]
    rt = json.loads(out.stdout)["timing"]["realtime"]
    assert rt["policy"] == "SCHED_OTHER" and any("SCHED_FIFO" in r for r in rt["refused"])
    assert rt["cpu_latency_us"] is None and any(CPU_LATENCY_FILE in r for r in rt["refused"])


def test_threads_of_a_recorded_run_sit_just_below_the_loop(tmp_path):
    """The session's fsync thread and the simulated drive's thread run at the loop's
    priority - 1 on its CPU: a thread started inside the grant would inherit the loop's
    own priority, and one left at normal priority could hold the GIL while preempted."""
    from labbench.registry import make_protocol, open_device
    from labbench.runner import run_recorded

    seen: dict[str, tuple[int, int]] = {}

    def look(_snapshot):
        for t in threading.enumerate():
            seen[t.name] = (os.sched_getscheduler(t.native_id),
                            os.sched_getparam(t.native_id).sched_priority)

    rig = Rig()
    device = open_device("sim-canopen", rig, realtime=True)
    result, path = run_recorded(device, make_protocol("etfe", duration_s=1.0, seed=1), tmp_path,
                                rig=rig, simulated=True, live_timing=look,
                                realtime=RealtimeConfig(priority=20), warn=lambda line: None)
    assert path is not None and result.timing["realtime"]["threads"] >= 2
    main = threading.current_thread().name
    if result.timing["realtime"]["policy"] != "SCHED_FIFO":  # refused here: all stay ordinary
        assert any("SCHED_FIFO" in r for r in result.timing["realtime"]["refused"])
        assert seen[main] == seen["session-fsync"] == seen["sim-canopen-drive"] == (os.SCHED_OTHER, 0)
        return
    assert seen[main] == (os.SCHED_FIFO, 20)
    assert seen["session-fsync"] == seen["sim-canopen-drive"] == (os.SCHED_FIFO, 19)


def test_a_paced_process_drive_is_scheduled_as_hardware():
    """sim-canopen's drive in its own process, paced: SCHED_FIFO one below the loop, on the
    first CPU (the loop takes the last), for the thread that answers the bus; refused, one
    line on its stderr. Unpaced (lock-step) it stays an ordinary process."""
    from labbench.registry import open_device
    from labbench.rig import rig_from_dict

    def drive_threads(paced: bool):
        rig = rig_from_dict({"canopen": {"sim_drive": "process"},
                             "realtime": {"priority": 30}}, source="t")
        d = open_device("sim-canopen", rig, realtime=paced)
        try:
            tasks = [int(t) for t in os.listdir(f"/proc/{d.peer.pid}/task")]
            return ({t: (os.sched_getscheduler(t), os.sched_getparam(t).sched_priority,
                         os.sched_getaffinity(t)) for t in tasks}, d.peer.stderr())
        finally:
            d.close()

    threads, stderr = drive_threads(paced=True)
    fifo = [s for s in threads.values() if s[0] == os.SCHED_FIFO]
    cpus = sorted(os.sched_getaffinity(0))
    if os.geteuid() == 0:
        # the main thread and the drive's (started after): both at 29 on the first CPU
        assert len(fifo) >= 2 and all(s[1] == 29 for s in fifo), threads
        assert all(s[2] == ({cpus[0]} if len(cpus) >= 2 else set(cpus)) for s in fifo)
    else:
        assert not fifo and "real-time scheduling refused" in stderr
    threads, _ = drive_threads(paced=False)
    assert all(s[0] != os.SCHED_FIFO for s in threads.values())
