"""Cost and timing of the CANopen path on python-can's virtual bus; bus load of the mapping.

1. CPU per loop cycle (goal <= 60 us): ``read()`` (SYNC, host heartbeat when
   due, pump until the TPDO) + ``command()`` (RPDO) against the simulated drive
   in lock-step, as ``thread_time`` of the host thread, and the whole process
   (host + simulated drive thread). Floor, measured in the same run: the
   host's share of the frames alone (two sends, two receives of ready frames
   on a virtual bus, no drive behind).
2. The same through ``labbench.loop.chain.run_loop`` (VE, safety, pages): host CPU per sample.
3. Period jitter at 1 kHz: the paced driver (``realtime=True``), periods between
   returned samples: p50 / p99 / max and late ticks; once with the configured
   stale-TPDO limit (3 periods: on a loaded machine the simulated drive's thread
   can miss it, and the run stops with the fault, as it must), once with a
   limit of 100 periods to see the whole timing distribution.
4. Bus load at 1 Mbit/s of the mapping, from frame bits with a stuffing bound.
5. For each synthetic dictionary of ``tests/eds_family.py`` (one-slot PDOs,
   fixed mappings, guarding only, ...): the planned mapping's bus load and the
   host CPU per cycle against the floor of the same frames.

    .venv/bin/python bench/bench_canopen.py [--cycles 5000] [--paced-s 3]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
import uuid
from pathlib import Path

import can
import numpy as np

from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.device import DeviceFault
from labbench.rig import Rig, rig_from_dict
from labbench.model.ve import VirtualEnvironment
from labbench.sim_backend.canopen_peer import connect_driver, sim_config, start_sim_drive

GOAL_US = 60.0


def frames_floor(n: int, rpdos: int = 1, tpdos: int = 2) -> float:
    """Host thread CPU [s] per cycle to send SYNC and ``rpdos`` frames and receive ``tpdos``
    already queued frames on a virtual bus (no drive behind: the floor of any driver)."""
    ch = f"bench-{uuid.uuid4().hex[:6]}"
    a, b = can.Bus(interface="virtual", channel=ch), can.Bus(interface="virtual", channel=ch)
    sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
    rpdo = can.Message(arbitration_id=0x201, data=bytes(4), is_extended_id=False)
    tpdo = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
    try:
        mine = 0.0
        for _ in range(n):
            c0 = time.thread_time()
            a.send(sync)
            mine += time.thread_time() - c0
            for _ in range(tpdos):
                b.send(tpdo)
            c0 = time.thread_time()
            for _ in range(tpdos):
                a.recv(0)
            for _ in range(rpdos):
                a.send(rpdo)
            mine += time.thread_time() - c0
            for _ in range(rpdos + 1):
                b.recv(0)
    finally:
        a.shutdown()
        b.shutdown()
    return mine / n


def open_drive(rig, realtime=False):
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    return connect_driver(rig, config, peer, bus, realtime=realtime)


def driver_cycles(rig, n: int) -> tuple[float, float, float]:
    """(host thread CPU, process CPU, wall) per read+command cycle, lock-step.

    The cycle includes ``read_raw`` and ``command`` only (no VE, no pages)."""
    with open_drive(rig) as d:
        d.enable()
        for _ in range(3):
            d.read(1.0)
            d.command(0.0)
        forces = (0.3 * np.random.default_rng(0).standard_normal(n)).tolist()
        w0, c0, p0 = time.perf_counter(), time.thread_time(), time.process_time()
        for f in forces:
            x = d.read_raw(1.0)[2]
            d.command(f - 200.0 * x)  # a stiff spring keeps the handle inside its limits
        return ((time.thread_time() - c0) / n, (time.process_time() - p0) / n,
                (time.perf_counter() - w0) / n)


def loop_cycles(rig, n: int) -> tuple[float, float]:
    """(host thread CPU, process CPU) per sample through run_loop, lock-step."""
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=rig.sample_time_s)
    exc = 0.3 * np.random.default_rng(1).standard_normal(n)
    with open_drive(rig) as d:
        c0, p0 = time.thread_time(), time.process_time()
        out = run_loop(d, HapticLoop(ve, SafetyConfig.from_rig(rig)), exc, lambda r: None)
        assert out.status == "completed", out
        return (time.thread_time() - c0) / n, (time.process_time() - p0) / n


# Dictionary variants of tests/eds_family.py: (label, variant, extra [canopen] fields).
VARIANTS = (("synthetic, complete", {}, {}), ("one-slot PDOs (4+4)", "ONE_SLOT", {}),
            ("fixed mappings", "FIXED", {}), ("guarding only", "GUARDING_ONLY", {}),
            ("optional objects missing", "OPTIONAL_MISSING", {}),
            ("0x6076 = 0, vendor mode",
             dict(default={0x6076: "0", 0x6502: "0x00010000"}, limits={0x6060: (-3, 10)}),
             {"rated_torque_mnm": 100.0, "modes": {"current": {"code": -3, "bit": 16}}}))


def variant_rigs(folder: Path):
    """(label, rig) of each dictionary variant, its EDS written into ``folder``."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import eds_family as F

    for k, (label, name, extra) in enumerate(VARIANTS):
        spec = getattr(F, name) if isinstance(name, str) else name
        path = F.write(folder / f"variant{k}.eds", **spec)
        yield label, rig_from_dict({"canopen": {"eds": str(path), **extra}}, source="bench")


def paced_periods(rig, seconds: float) -> tuple[np.ndarray, int, str]:
    """Periods between samples of the paced driver; stops at a device fault (reported)."""
    n = int(seconds / rig.sample_time_s)
    stamps = []
    fault = ""
    with open_drive(rig, realtime=True) as d:
        d.enable()
        try:
            for _ in range(n):
                x = d.read_raw(1.0)[2]
                stamps.append(time.perf_counter())
                d.command(-200.0 * x)
        except DeviceFault as exc:
            fault = str(exc)
        late = d.counters["late_ticks"]
    return np.diff(stamps), late, fault


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=5000)
    ap.add_argument("--paced-s", type=float, default=3.0)
    args = ap.parse_args()
    rig = Rig()
    floor = frames_floor(args.cycles)
    host, proc, wall = driver_cycles(rig, args.cycles)
    lhost, lproc = loop_cycles(rig, args.cycles)
    us = 1e6
    print(f"CANopen path on the virtual bus, {args.cycles} cycles, lock-step")
    print(f"  floor (host share of 4 frames, no drive)  {floor * us:7.1f} us")
    print(f"  driver read+command, host thread CPU      {host * us:7.1f} us  "
          f"({host / floor:.2f}x floor; goal <= {GOAL_US:g} us: "
          f"{'met' if host * us <= GOAL_US else 'NOT met'})")
    print(f"  driver read+command, process CPU          {proc * us:7.1f} us  "
          f"(host + simulated drive; {proc / floor:.2f}x floor)")
    print(f"  driver read+command, wall                 {wall * us:7.1f} us")
    print(f"  run_loop per sample, host thread CPU      {lhost * us:7.1f} us  "
          f"({lhost / floor:.2f}x floor)")
    print(f"  run_loop per sample, process CPU          {lproc * us:7.1f} us")
    for label, stale in (("stale limit 3 periods (as configured)", 3),
                         ("stale limit 100 periods (timing only)", 100)):
        prig = rig_from_dict({"canopen": {"stale_periods": stale}})
        periods, late, fault = paced_periods(prig, args.paced_s)
        p = periods * 1e3
        print(f"paced at 1 kHz, {label}: {len(p) + 1} samples; period p50 "
              f"{np.percentile(p, 50):.3f} ms, p99 {np.percentile(p, 99):.3f} ms, "
              f"max {p.max():.3f} ms, late ticks {late}"
              + (f"; stopped by: {fault}" if fault else ""))
    with open_drive(rig) as d:
        load = d.assessment.bus_load(d.config, rig.sample_time_s)
    print(f"bus load at {load['bitrate'] / 1e6:g} Mbit/s: {load['load_nominal'] * 100:.1f} % "
          f"nominal, {load['load_worst'] * 100:.1f} % with worst-case stuffing")
    for name, n_bytes, rate in load["frames"]:
        print(f"  {name:<28} {n_bytes} bytes  {rate:7.1f} /s")
    n = max(args.cycles // 2, 500)
    print(f"planned mappings of the synthetic dictionaries ({n} cycles each, lock-step; "
          "floor: the same frames with no drive):")
    with tempfile.TemporaryDirectory() as folder:
        for label, vrig in variant_rigs(Path(folder)):
            with open_drive(vrig) as d:
                plan = d.assessment.plan
                vload = d.assessment.bus_load(d.config, vrig.sample_time_s)
            vfloor = frames_floor(n, len(plan.rpdos), len(plan.tpdos))
            vhost = driver_cycles(vrig, n)[0]
            print(f"  {label:<26} {len(plan.rpdos)} RPDO + {len(plan.tpdos)} TPDO: bus load "
                  f"{vload['load_nominal'] * 100:5.1f} % nominal, {vload['load_worst'] * 100:5.1f}"
                  f" % worst; host CPU {vhost * us:5.1f} us = {vhost / vfloor:.2f}x floor "
                  f"({vfloor * us:.1f} us)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
