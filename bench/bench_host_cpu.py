"""The host's CPU per 1 kHz period on the bus: labbench's loop against a bare python-can loop.

In the same run, against the same simulated drive on the same interface, two hosts
exchange the same frames each period (SYNC, the host heartbeat every 20 ms, the TPDOs
of the SYNC in, the RPDO out):

* **labbench**: ``labbench.loop.chain.run_loop`` over the CANopen driver (``read_raw``: SYNC,
  pump the bus until every TPDO is in, decode; the VE, safety checks and pages;
  ``command``: the RPDO);
* **bare**: the least a Python host can do with python-can alone: send SYNC, ``recv``
  until the TPDOs' COB-IDs are in, unpack the position, compute a spring force, pack and
  send the RPDO. The drive is brought up by the driver first (NMT, mapping, enabled);
  then the bare loop owns the bus.

Lock-step (each period's work, no waiting for a clock) and paced at 1 kHz. Paced, both
keep time as labbench does (``labbench.loop.realtime.sleep_until``: sleep, then spin the last
150 us, so that a SYNC leaves on time to a few us); the bare loop is also run with a
plain ``time.sleep`` to each deadline (cheaper, and its SYNCs leave as late as the
sleep wakes: the p50/p99 lateness is printed), to show what the spin costs. Interfaces:
python-can's ``virtual`` bus with the drive in a thread of this process (host CPU = the
loop thread's ``thread_time``) and ``udp_multicast`` with the drive in its own process
(host CPU = this process's ``process_time``). Each figure is the median of ``--rounds``
rounds, the hosts alternating (this machine's load moves single figures by 20 %).
Printed: CPU per period of each and the ratio (goal: labbench within 1.5x the bare
loop's at the same pacing).

    .venv/bin/python bench/bench_host_cpu.py [--cycles 3000] [--rounds 5] [--profile]
"""
from __future__ import annotations

import argparse
import struct
import time

import numpy as np

from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.loop.realtime import sleep_until
from labbench.registry import open_device
from labbench.rig import rig_from_dict
from labbench.model.ve import VirtualEnvironment

GOAL = 1.5
K_SPRING = 50.0


def rig_for(interface: str):
    sim_drive = "process" if interface == "udp_multicast" else "thread"
    return rig_from_dict({"canopen": {"sim_drive": sim_drive, "stale_periods": 100,
                                      "lockstep_timeout_s": 5.0,
                                      "heartbeat_consumer_ms": 2000, "rpdo_timeout_ms": 2000},
                          "sim": {"quantize": True}, "safety": {"watchdog_s": 2.0}},
                         source="bench")


def clocks(interface: str):
    """The host's CPU clock: the loop thread's where the drive shares the process."""
    return time.thread_time if interface == "virtual" else time.process_time


def labbench_loop(interface: str, n: int, paced: bool) -> float:
    rig = rig_for(interface)
    cpu = clocks(interface)
    ve = VirtualEnvironment("spring", K=K_SPRING, B=0.0, T=rig.sample_time_s)
    exc = 0.3 * np.random.default_rng(1).standard_normal(n)
    with open_device("sim-canopen", rig, realtime=paced) as d:
        c0 = cpu()
        out = run_loop(d, HapticLoop(ve, SafetyConfig.from_rig(rig)), exc, lambda r: None)
        used = cpu() - c0
    assert out.status == "completed", out
    return used / n


def bare_loop(interface: str, n: int, paced: bool, spin: bool = True) -> tuple[float, list]:
    """The bare python-can host (module doc) on a drive the driver brought up: (CPU per
    period, each slept SYNC's lateness after its time when paced). ``spin``: pace with
    ``sleep_until`` (as labbench), else a plain ``time.sleep``; behind, the schedule
    re-phases (as labbench's does) instead of bursting SYNCs."""
    rig = rig_for(interface)
    cpu = clocks(interface)
    T = rig.sample_time_s
    with open_device("sim-canopen", rig, realtime=False) as d:
        d.enable()
        for _ in range(10):  # until the drive shows OPERATION ENABLED
            d.read(1.0)
            d.command(0.0)
        bus = d._bus
        plan = d.assessment.plan
        (rpdo,) = plan.rpdos
        tpdo = plan.tpdos[0]
        tpdo_ids = {p.cob_id for p in plan.tpdos}
        pos_at = tpdo.roles().index("position")
        tx_fmt, rx_fmt = struct.Struct(tpdo.struct().format), rpdo.struct()
        order = rpdo.roles()  # torque and controlword, in the mapped order
        per_newton = d.assessment.force_to_command
        mpc = rig.metres_per_count
        import can

        sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
        out = can.Message(arbitration_id=rpdo.cob_id, data=bytes(rpdo.n_bytes),
                          is_extended_id=False)
        heartbeat = can.Message(arbitration_id=0x700 + d.config.host_node_id, data=b"\x05",
                                is_extended_id=False)
        exc = (0.3 * np.random.default_rng(1).standard_normal(n)).tolist()
        late = []
        c0 = cpu()
        due = time.perf_counter()
        last_hb = -1.0
        for k in range(n):
            if paced:
                due += T
                left = due - time.perf_counter()
                if left <= 0:
                    due = time.perf_counter()  # behind: re-phase, as labbench's pacing does
                elif spin:
                    sleep_until(due)
                else:
                    time.sleep(left)
            bus.send(sync)
            now = time.perf_counter()
            if paced and left > 0:
                late.append(now - due)  # how late the SYNC left after a sleep
            if now - last_hb >= 0.02:
                bus.send(heartbeat)
                last_hb = now
            seen = set()
            x = 0.0
            while seen != tpdo_ids:
                msg = bus.recv(1.0)
                if msg.arbitration_id in tpdo_ids:
                    seen.add(msg.arbitration_id)
                    if msg.arbitration_id == tpdo.cob_id:
                        x = tx_fmt.unpack_from(msg.data)[pos_at] * mpc
            torque = round((exc[k] - K_SPRING * x) * per_newton)
            out.data = rx_fmt.pack(*[torque if r == "torque" else 0x0F for r in order])
            bus.send(out)
        used = cpu() - c0
        # hand the drive back to the driver, which winds it down at close
        d.command(0.0)
    return used / n, late


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=3000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--profile", action="store_true",
                    help="profile labbench's lock-step loop on the virtual bus (cProfile, "
                         "the loop thread's CPU time)")
    args = ap.parse_args()
    if args.profile:
        import cProfile
        import pstats

        prof = cProfile.Profile(time.thread_time)  # CPU of the loop thread, not waiting
        prof.runcall(labbench_loop, "virtual", args.cycles, False)
        pstats.Stats(prof).sort_stats("tottime").print_stats(15)
        return 0
    n = args.cycles
    print(f"host CPU per period, median of {args.rounds} rounds of {n} periods "
          f"(goal: labbench <= {GOAL}x bare at the same pacing)")
    print(f"{'interface':<14} {'mode':<10} {'bare':>8} {'labbench':>9} {'ratio':>6}   "
          "bare with a plain sleep: CPU, SYNC late p50/p99")
    worst = 0.0
    for interface in ("virtual", "udp_multicast"):
        for paced in (False, True):
            bare, ours, plain, late = [], [], [], []
            for _ in range(args.rounds):
                bare.append(bare_loop(interface, n, paced)[0])
                ours.append(labbench_loop(interface, n, paced))
                if paced:
                    cpu, lateness = bare_loop(interface, n, paced, spin=False)
                    plain.append(cpu)
                    late += lateness
            b, o = float(np.median(bare)), float(np.median(ours))
            worst = max(worst, o / b)
            extra = (f"   {np.median(plain) * 1e6:5.0f} us, {np.percentile(late, 50) * 1e6:.0f}"
                     f"/{np.percentile(late, 99) * 1e6:.0f} us" if paced else "")
            print(f"{interface:<14} {'paced' if paced else 'lock-step':<10} {b * 1e6:5.0f} us "
                  f"{o * 1e6:6.0f} us {o / b:5.2f}x{extra}", flush=True)
    print(f"worst ratio {worst:.2f}x: {'within' if worst <= GOAL else 'above'} the goal")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
