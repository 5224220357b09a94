"""The reference firmware on the emulated ATmega328P (--device avr-sim): what it keeps up
with, and the VE rendered on the host (T = 1 ms, td = T) against the VE rendered on
the board (T_r = 0.2 ms, td = T_r), each against theory.

Prints: emulator speed; exact encoder rate; frame delay under 8-command bursts;
stability boundary K_max and effective-damping drop of both renderings (decay of a
free oscillation on the emulator vs the sampled model's eigenvalues); ETFE error
through the firmware.
Needs `make avr-deps`. About 5 minutes here.
"""

from __future__ import annotations

import math
import time

import numpy as np

from labbench import records
from labbench.model import linear
from labbench.analysis.dataio import recording_from_arrays
from labbench.analysis.etfe import etfe
from labbench.drivers import framing
from labbench.drivers import serial_stream as ss
from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.rig import Rig, rig_from_dict
from labbench.sim_backend import avr_build
from labbench.sim_backend.avr_device import RENDER_DIV, connect_avr_sim
from labbench.model.ve import Plant, VirtualEnvironment

RIG = Rig()
T = RIG.sample_time_s
T_R = T / RENDER_DIV
PLANT = Plant(RIG.nominal_mass_kg, RIG.nominal_damping_ns_m)
MPC = RIG.metres_per_count
SAFETY = SafetyConfig(force_limit_n=RIG.force_limit_n, force_rate_limit_n_per_s=1e9,
                      velocity_limit_m_s=1e3, position_limits_m=(-1e3, 1e3), energy_limit_j=1e3,
                      watchdog_s=1.0, enable_force_threshold_n=1e-12)


def loop_run(ve_host, exc, ve_board=None, rig=RIG):
    """The host loop over the emulated board; ``ve_board`` makes the board render."""
    dev, board = connect_avr_sim(rig)
    pages = []
    t0 = time.perf_counter()
    try:
        if ve_board is not None:
            dev.render_on_board(ve_board)
        out = run_loop(dev, HapticLoop(ve_host, SAFETY), exc, pages.append)
    finally:
        dev.close()
    wall = time.perf_counter() - t0
    return out, records.concat_pages(pages), board.stats, wall


def emulator_speed():
    exc = np.r_[0.0, np.random.default_rng(1).normal(0, 0.5, 2999)]
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=T)
    _, _, st, wall = loop_run(ve, exc)
    emu = st["emulated_s"] / max(st["wall_s"] - st["host_wait_s"], 1e-9)
    print(f"emulator: {st['emulated_s']:.2f} s emulated in {st['wall_s']:.2f} s "
          f"({st['emulated_s'] / st['wall_s']:.2f}x real time with the host in lock-step; "
          f"{emu:.2f}x while emulating, the rest waiting for the host)")


def encoder_rates():
    rig = rig_from_dict({"serial": {"tolerate_drops": 1000}})
    for cps in (100e3, 150e3, 200e3, 220e3, 245e3):
        drv, board = connect_avr_sim(rig, trace=True, drive_cps=cps, drive_ms=(20.0, 320.0))
        samples = []
        try:
            drv.enable()
            for _ in range(400):
                samples.append(drv.read(5.0))
                drv.command(0.0)
        finally:
            drv.close()
        vec = board.trace().sample_ticks()
        seq = np.array([s.seq for s in samples])
        counts = np.array([round(s.position_m / MPC) for s in samples])
        lo = np.minimum(vec[seq, 3], vec[seq, 4])
        hi = np.maximum(vec[seq, 3], vec[seq, 4])
        exact = int(np.sum((counts >= lo) & (counts <= hi)))
        flags = np.bitwise_or.reduce([s.flags for s in samples])
        names = [n for n, b in (("skipped-state", ss.FLAG_BOARD_ENCODER),
                                ("missed-tick", ss.FLAG_BOARD_MISSED_TICK),
                                ("late", ss.FLAG_BOARD_LATE)) if flags & b]
        print(f"encoder {cps / 1e3:5.0f} k counts/s: {exact}/{len(samples)} samples exact, final "
              f"{counts[-1]} of {board.stats['count']}, flags: {', '.join(names) or 'none'}")


def burst_delay():
    drv, board = connect_avr_sim(RIG, trace=True)
    samples = []
    try:
        drv.enable()
        for k in range(500):
            s = drv.read(5.0)
            samples.append(s)
            if k % 5 == 0:
                drv.port.write(b"".join(framing.encode_command(s.seq, 0.01 * i) for i in range(8)))
            else:
                drv.command(0.0)
    finally:
        drv.close()
    tr = board.trace()
    vec = tr.sample_ticks()
    frames = [t for t in tr.tx if t[2] == 16]
    seq = [s.seq for s in samples]
    first = np.array([frames[q][0] - vec[q, 0] for q in seq]) * 1e6
    end = np.array([frames[q][1] - vec[q, 0] for q in seq]) * 1e6 + 20  # + its last byte
    print(f"frames after the tick, 8-command burst every 5th sample: first byte p50 "
          f"{np.median(first):.0f} us, max {first.max():.0f} us (goal <= 400); whole frame max "
          f"{end.max():.0f} us (simavr sends 11 bits a byte: 16 bytes take 352 us, 320 on a wire)")


def z_of(t, exc, x):
    est = etfe(recording_from_arrays(t, np.r_[0.0, exc[:-1]], x))
    return np.asarray(est.w), np.asarray(est.Z)


def etfe_accuracy(duration_s=30.0):
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=T)
    exc = np.r_[0.0, np.random.default_rng(11).normal(0, 0.5, round(duration_s / T) - 1)]
    _, d, _, wall = loop_run(ve, exc)
    w, Z = z_of(d["t"], exc, d["position"])
    band = (w >= 2) & (w <= 100)
    z_th = linear.z_sampled(PLANT, ve.with_(td=T), w)
    rel = np.abs(Z - z_th) / np.abs(z_th)
    print(f"ETFE through the firmware, host loop, {duration_s:g} s record: median "
          f"{np.median(rel[band]):.2%}, max {np.max(rel[band]):.2%} vs sampled theory "
          f"(td = T) over 2-100 rad/s ({wall:.0f} s wall; tests/test_avr_accuracy.py: 120 s)")


def decay_rate(t, x, floor):
    """Exponential rate [1/s] of a free oscillation: a line through log |peaks| above floor."""
    a = np.abs(x)
    peaks = np.nonzero((a[1:-1] > a[:-2]) & (a[1:-1] >= a[2:]) & (a[1:-1] > floor))[0] + 1
    return float(np.polyfit(t[peaks], np.log(a[peaks]), 1)[0]) if len(peaks) >= 4 else math.nan


def free_response(K, board, seconds=2.0):
    """Decay rate after a push of a rendered spring K: host loop or on board."""
    exc = np.zeros(round(seconds / T))
    exc[1:40] = 1.0  # N: K x stays well inside the 5 N limit, x far above one count
    if board:
        ve = VirtualEnvironment("spring", K=K, T=T_R)
        out, d, _, _ = loop_run(VirtualEnvironment("none", T=T), exc, ve_board=ve)
    else:
        ve = VirtualEnvironment("spring", K=K, T=T)
        out, d, _, _ = loop_run(ve, exc)
    t, x = d["t"] - d["t"][0], d["position"]
    keep = t > 0.1
    return decay_rate(t[keep], x[keep], 20 * MPC), ve


def sigma_theory(ve):
    """The sampled model's slowest rate, ln(spectral radius) / T, with td = one tick."""
    rho = linear.stability(PLANT, ve.with_(td=ve.T)).spectral_radius
    return math.log(rho) / ve.T


def stability_and_damping():
    for name, T_ve, board in (("host loop (T = 1 ms, td = T)", T, False),
                              ("on board (T_r = 0.2 ms, td = T_r)", T_R, True)):
        k_th = linear.k_max(PLANT, VirtualEnvironment("spring", K=1.0, T=T_ve, td=T_ve))
        rows = []
        for K in sorted({50.0, *(k_th * f for f in (0.7, 0.9, 1.1, 1.3))}):
            sigma, ve = free_response(K, board)
            rows.append((K, sigma, sigma_theory(ve)))
        ks, sm, st = (np.array(c) for c in zip(*rows))
        cross = np.nonzero(np.diff(np.sign(sm)))[0]
        k_meas = (float(np.interp(0.0, sm[cross[0]:cross[0] + 2], ks[cross[0]:cross[0] + 2]))
                  if len(cross) else math.nan)
        print(f"{name}: stability boundary K_max theory {k_th:.1f} N/m, emulator {k_meas:.1f} N/m")
        for K, a, b in rows:
            # A free spring-mass decays at ED / (2 m): ED = -2 m sigma.
            print(f"  K {K:6.1f} N/m: decay rate emulator {a:+.3f} /s, theory {b:+.3f} /s; "
                  f"ED drop b - ED: emulator {PLANT.b + 2 * PLANT.m * a:.4f}, theory "
                  f"{PLANT.b + 2 * PLANT.m * b:.4f}, paper K (T/2 + td) {K * 1.5 * T_ve:.4f} N s/m")


def main():
    problem = avr_build.problem()
    if problem:
        print(f"bench_avr: skipped: {problem}")
        return
    emulator_speed()
    encoder_rates()
    burst_delay()
    stability_and_damping()
    etfe_accuracy()


if __name__ == "__main__":
    main()
