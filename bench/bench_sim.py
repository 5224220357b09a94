"""Speed of the simulated rig through the real loop: goal >= 300x faster than real time.

A 2-minute 1 kHz white-noise ETFE run (120 000 samples) on the simulated
Phantom-like device with Coulomb friction and encoder quantisation, through
``labbench.loop.chain.run_loop`` with the real ``HapticLoop`` and the rig's safety
envelope, pages going to a list. Printed per sample, against a floor measured in
the same process: an empty Python loop of the same length. Both wall time and
this thread's CPU time are given (the machine is shared: CPU time is what the
code costs, wall time what a user waits). Best of ``--repeat`` runs.

Then a paced run (``realtime=True``, as the GUI and ``--realtime`` use it) of
``--paced-s`` seconds under ``labbench.loop.realtime.acquire`` (as ``labbench.runner``
runs it): loop period p50/p99/max, overruns at 1 kHz and what was granted.
``bench/bench_realtime.py`` is the long version, against the machine's floor.

    .venv/bin/python bench/bench_sim.py [--repeat 3] [--samples 120000] [--paced-s 5]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.loop.realtime import acquire
from labbench.rig import Rig
from labbench.loop.timing import summary as timing_summary
from labbench.model.ve import VirtualEnvironment
from labbench.sim_backend.sim_device import open_sim

GOAL = 300.0


def timed(fn):
    w0, c0 = time.perf_counter(), time.thread_time()
    out = fn()
    return time.perf_counter() - w0, time.thread_time() - c0, out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--samples", type=int, default=120_000)
    ap.add_argument("--paced-s", type=float, default=5.0)
    args = ap.parse_args()
    n = args.samples
    rig = Rig()
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=rig.sample_time_s)
    exc = np.random.default_rng(0).normal(0.0, 1.0, n)
    exc[0] = 0.0

    def empty():
        for _ in range(n):
            pass

    def loop_run():
        dev = open_sim(rig, coulomb_n=0.02, quantize=True, seed=0)
        pages = []
        out = run_loop(dev, HapticLoop(ve, SafetyConfig.from_rig(rig)), exc, pages.append)
        assert out.status == "completed" and out.n_done == n, out
        return out

    floors, runs = [], []
    for _ in range(args.repeat):
        floors.append(timed(empty)[:2])
        runs.append(timed(loop_run))
    f_wall = min(f[0] for f in floors) / n
    f_cpu = min(f[1] for f in floors) / n
    r_wall = min(r[0] for r in runs) / n
    r_cpu = min(r[1] for r in runs) / n
    T = rig.sample_time_s
    timing = min(runs, key=lambda r: r[0])[2].timing
    print(f"bench_sim: {n} samples, spring-damper K=50 B=1 w0=125, Coulomb 0.02 N, quantised,"
          f" best of {args.repeat}")
    print(f"  floor (empty loop)  wall {f_wall * 1e9:7.1f} ns/sample   cpu {f_cpu * 1e9:7.1f} ns/sample")
    print(f"  sim + loop          wall {r_wall * 1e6:7.3f} us/sample   cpu {r_cpu * 1e6:7.3f} us/sample")
    print(f"  ratio to floor      wall {r_wall / f_wall:7.1f}x            cpu {r_cpu / f_cpu:7.1f}x")
    print(f"  loop period         p50 {timing['p50_s'] * 1e6:.2f} us  p99 {timing['p99_s'] * 1e6:.2f} us"
          f"  max {timing['max_s'] * 1e3:.2f} ms")
    for label, per in (("wall", r_wall), ("cpu", r_cpu)):
        ratio = T / per
        verdict = "meets" if ratio >= GOAL else "BELOW"
        print(f"  faster than real time ({label}): {ratio:7.1f}x  ({verdict} the {GOAL:.0f}x goal)")

    m = int(args.paced_s / T)
    if m > 0:
        dev = open_sim(rig, realtime=True, coulomb_n=0.02, quantize=True, seed=0)
        with acquire() as grant:
            out = run_loop(dev, HapticLoop(ve, SafetyConfig.from_rig(rig)), exc[:m],
                           lambda rec: None)
        t = {**out.timing, "realtime": grant.record}
        print(f"paced run, {m} samples at {1 / T:.0f} Hz: {out.status} {out.reason}".rstrip())
        print(f"  {timing_summary(t)}")
        print(f"  loop period p50 {t['p50_s'] * 1e3:.3f} ms  p99 {t['p99_s'] * 1e3:.3f} ms"
              f"  max {t['max_s'] * 1e3:.3f} ms  overruns (> 1.5 T) {t['overruns']}"
              f"  real-time factor {t['realtime_factor']:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
