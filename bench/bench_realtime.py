"""Loop overruns at 1 kHz, as a user starts the program, against the machine's floor.

Each arm is a fresh process, started as a user would start it:

* ``floor``: the pacing alone (``labbench.loop.realtime.sleep_until`` at 1 kHz, under the
  same real-time settings, no loop work): what this machine and its scheduler allow;
* ``sim``: ``labbench run etfe --realtime`` (simulator, real-time scheduling asked for);
* ``sim-nort``: the same with ``--no-rt`` (what the program did before);
* ``floor-idle``, ``sim-idle``: ``floor`` and ``sim`` with ``[realtime] cpu_latency_us = -1``
  (idle CPUs may sleep: what the CPU latency limit is worth);
* ``canopen``: ``labbench run etfe --device sim-canopen --realtime`` with the driver's
  real monitor limits (stale TPDO after 3 periods, heartbeat 100 ms, RPDO 50 ms), not
  the simulation's relaxed defaults;
* ``canopen-process``: the same with the simulated drive in its own process
  (``[canopen] sim_drive = "process"``, over udp_multicast), as a real drive is: a host
  stall no longer stalls the drive, so its faults can be set against the floor's stalls.

with 0 and 2 CPU hogs (``while True: pass`` processes at normal priority, one per core
of this 2-core machine). Printed per arm: periods > 1.5 T, max period and when, p99,
and the ratio of overruns to the floor's in the same conditions. Arms are interleaved
and repeated so the machine's other load falls on all; the load average and the CPU
time the hypervisor stole from this VM meanwhile (``steal`` in /proc/stat: no guest
scheduling policy can get that back) are printed.

    .venv/bin/python bench/bench_realtime.py [--seconds 120] [--arms floor,sim,...]
        [--hogs 0,2] [--repeats 1] [--watchdog-s 1.0]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PY = sys.executable
FLOOR = """
import json, sys, time
from labbench.loop.realtime import RealtimeConfig, acquire, sleep_until
from labbench.loop.timing import period_stats
n, T = int(float(sys.argv[1]) / 1e-3), 1e-3
per = [0.0] * n
with acquire(RealtimeConfig(cpu_latency_us=int(sys.argv[2]))) as g:
    t0 = prev = time.perf_counter()
    for k in range(n):
        sleep_until(t0 + (k + 1) * T)
        now = time.perf_counter(); per[k] = now - prev; prev = now
p = per[1:]
i = max(range(len(p)), key=p.__getitem__)
s = period_stats(p, T, True, i + 1, (i + 1) * T)
s["realtime"] = g.record
print(json.dumps({"status": "success", "timing": s}))
"""
RIG = """
[rig]
name = "bench"
[canopen]
stale_periods = 3
heartbeat_consumer_ms = 100
rpdo_timeout_ms = 50
"""


def arm_command(arm: str, seconds: float, out: str, rig: str) -> list[str]:
    idle = arm.endswith("-idle")
    if arm.startswith("floor"):
        return [PY, "-c", FLOOR, str(seconds), "-1" if idle else "0"]
    cmd = [PY, "-m", "labbench", "run", "etfe", "--realtime", "--json", "--out", out,
           "--duration-s", str(seconds), "--plant-from", "nominal"]
    if arm == "sim-nort":
        cmd.append("--no-rt")
    variant = {"-idle": "-idle", "canopen-process": "-process"}
    suffix = next((v for k, v in variant.items() if arm.endswith(k)), "")
    cmd += ["--rig", rig.replace(".toml", f"{suffix}.toml")]
    if arm.startswith("canopen"):
        cmd += ["--device", "sim-canopen"]
    return cmd


def steal_s() -> float:
    """CPU time the hypervisor took from this virtual machine, all CPUs (/proc/stat)."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def run_arm(arm, seconds, out, rig) -> dict:
    load0, steal0 = os.getloadavg()[0], steal_s()
    t0 = time.monotonic()
    proc = subprocess.run(arm_command(arm, seconds, out, rig), capture_output=True, text=True,
                          timeout=seconds * 3 + 120)
    res = {"arm": arm, "wall": time.monotonic() - t0, "load": (load0 + os.getloadavg()[0]) / 2,
           "steal": steal_s() - steal0}
    try:
        res.update(json.loads(proc.stdout.strip().splitlines()[-1]))
    except (ValueError, IndexError):
        res.update(status="crashed", reason=proc.stderr.strip()[-300:])
    return res


def start_hogs(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([PY, "-c", "while True: pass"]) for _ in range(n)]


def stop_hogs(hogs) -> None:
    for h in hogs:
        h.kill()
        h.wait()


def line(r: dict) -> str:
    t = r.get("timing") or {}
    w = t.get("worst") or {}
    rt = t.get("realtime") or {}
    sched = (f"{rt.get('policy', '?')} {rt.get('priority') or ''}".strip()
             if rt.get("requested") else "rt off")
    if not t:
        return f"{r['arm']:15s} {r.get('status')}: {r.get('reason', '')}"
    at = f"{w['t_s']:.1f}" if isinstance(w.get("t_s"), (int, float)) else "-"
    return (f"{r['arm']:15s} {r.get('status', '?'):8s} periods {t.get('periods', 0):7d}  overruns "
            f"{t['overruns']:5d}  max {t['max_s'] * 1e3:6.2f} ms at {at:>6s} s  p99 "
            f"{t['p99_s'] * 1e3:5.3f} ms  [{sched}]  load {r['load']:.1f}  steal {r['steal']:.2f} s"
            + ("" if r.get("status") == "success" else f"  ({r.get('reason', '')})"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="per arm (issue goal: 600)")
    ap.add_argument("--arms", default="floor,floor-idle,sim,sim-idle,sim-nort,canopen,canopen-process")
    ap.add_argument("--hogs", default="0,2")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--watchdog-s", type=float, default=None,
                    help="the rig's loop watchdog (default 0.05 s): longer to count the "
                         "overruns of a whole run through stalls that would trip it")
    args = ap.parse_args()
    arms = args.arms.split(",")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        rig = Path(tmp) / "rig.toml"
        rig.write_text(RIG + ("" if args.watchdog_s is None
                              else f"[safety]\nwatchdog_s = {args.watchdog_s}\n"))
        (Path(tmp) / "rig-idle.toml").write_text(rig.read_text()
                                                 + "[realtime]\ncpu_latency_us = -1\n")
        (Path(tmp) / "rig-process.toml").write_text(
            rig.read_text().replace("[canopen]\n", '[canopen]\nsim_drive = "process"\n'))
        for rep in range(args.repeats):
            for n_hogs in (int(h) for h in args.hogs.split(",")):
                print(f"-- {n_hogs} CPU hogs, {args.seconds:g} s per arm, repeat {rep + 1}",
                      flush=True)
                hogs = start_hogs(n_hogs)
                try:
                    for arm in arms:
                        r = run_arm(arm, args.seconds, tmp, str(rig))
                        r["hogs"] = n_hogs
                        results.append(r)
                        print("  " + line(r), flush=True)
                finally:
                    stop_hogs(hogs)
    print("overruns per 100 000 periods, against the floor in the same conditions "
          "(all repeats; a run that tripped counts up to its trip):")
    for n_hogs in sorted({r["hogs"] for r in results}):
        rate = {}
        for a in arms:
            ts = [r.get("timing") or {} for r in results if r["arm"] == a and r["hogs"] == n_hogs]
            periods = sum(t.get("periods", 0) for t in ts)
            rate[a] = 1e5 * sum(t.get("overruns", 0) for t in ts) / periods if periods else None
        floor = rate.get("floor")
        parts = [f"{a} {rate[a]:.3g}" + (f" ({rate[a] / floor:.2g}x)" if floor else "")
                 for a in arms if rate[a] is not None]
        print(f"  {n_hogs} hogs: " + ", ".join(parts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
