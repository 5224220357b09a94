"""Serial encoder stream: parse rates, chunked read vs readline, end-to-end rate through a pty.

Prints ratios against floors measured in the same run (this machine is shared
and noisy; absolute numbers drift, ratios much less):

1. parse cost per sample, ASCII lines and COBS binary frames, against the bare
   ``bytes.split`` of the same buffer (the least any line/frame parser can do);
2. host reading from a pty: ``read(in_waiting)`` + parser vs pyserial ``readline()``;
3. lock-step cycles through the real driver and the simulated board on a pty,
   against the plain in-process simulator (read + command);
4. stale-stream detection of a free-running board at 1 kHz: silence before
   the force is zeroed, in periods.

Run: ``.venv/bin/python bench/bench_serial.py``.
"""

from __future__ import annotations

import os
import threading
import time
import tty

import numpy as np
import serial

from labbench.drivers import framing
from labbench.device import DeviceFault
from labbench.rig import Rig, rig_from_dict
from labbench.sim_backend.arduino_peer import Fault, connect_sim_serial
from labbench.sim_backend.sim_device import SimDevice

N = 100_000


def best_of(fn, repeat=5) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def parse_rates() -> None:
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.integers(990, 1010, N))
    c = np.cumsum(rng.integers(-30, 30, N))
    ascii_buf = b"".join(framing.format_ascii(int(a), int(b)) for a, b in zip(t, c))
    bin_buf = b"".join(
        framing.encode_sample(k, int(a), int(b)) for k, (a, b) in enumerate(zip(t, c))
    )
    chunk = 4096

    def feed(parser, buf):
        for i in range(0, len(buf), chunk):
            parser.feed(buf[i : i + chunk])

    floor_a = best_of(lambda: ascii_buf.split(b"\n"))
    floor_b = best_of(lambda: bin_buf.split(b"\x00"))
    t_a = best_of(lambda: feed(framing.AsciiSampleParser(), ascii_buf))
    t_b = best_of(lambda: feed(framing.BinarySampleParser(), bin_buf))
    print("1. parse cost per sample (4096-byte chunks)")
    print(
        f"   ASCII : {t_a / N * 1e6:6.2f} us/line   = {t_a / floor_a:5.1f} x bare split "
        f"({floor_a / N * 1e9:.0f} ns), {N / t_a / 1e3:.0f} k lines/s, "
        f"{len(ascii_buf) / N:.1f} B/sample"
    )
    print(
        f"   binary: {t_b / N * 1e6:6.2f} us/frame  = {t_b / floor_b:5.1f} x bare split "
        f"({floor_b / N * 1e9:.0f} ns), {N / t_b / 1e3:.0f} k frames/s, "
        f"{len(bin_buf) / N:.1f} B/sample"
    )
    print(f"   binary / ASCII time per sample: {t_b / t_a:.2f}")


def read_styles(n=20_000) -> None:
    lines = b"".join(framing.format_ascii(1000 * k, k) for k in range(n))

    def through_pty(consume) -> float:
        master, slave = os.openpty()
        tty.setraw(slave)
        port = serial.Serial(os.ttyname(slave), timeout=0.5)
        writer = threading.Thread(target=lambda: os.write(master, lines))
        t = time.perf_counter()
        writer.start()
        consume(port)
        dt = time.perf_counter() - t
        writer.join()
        port.close()
        os.close(master)
        os.close(slave)
        return dt

    def by_readline(port):
        for _ in range(n):
            port.readline()

    def by_chunks(port):
        p = framing.AsciiSampleParser()
        got = 0
        while got < n:
            got += len(p.feed(port.read(port.in_waiting or 1)))

    t_line = through_pty(by_readline)
    t_chunk = through_pty(by_chunks)
    print("2. host reading ASCII lines from a pty")
    print(
        f"   readline(): {n / t_line / 1e3:6.0f} k lines/s; read(in_waiting) + parser: "
        f"{n / t_chunk / 1e3:6.0f} k lines/s  -> {t_line / t_chunk:.1f} x faster"
    )


def end_to_end(n=5000) -> None:
    rig = Rig()
    sim = SimDevice(rig)
    sim.enable()

    def plain():
        for _ in range(n):
            sim.read_raw(1.0)
            sim.command(0.1)

    floor = best_of(plain, 3)
    print("3. lock-step cycles (read + command) through driver, pty and simulated board")
    print(f"   plain simulator (floor): {floor / n * 1e6:7.1f} us/cycle")
    for fmt in ("binary", "ascii"):
        r = rig_from_dict({"serial": {"format": fmt}})
        drv, _peer = connect_sim_serial(r, seed=1)
        with drv:
            drv.enable(1.0)
            stamps = np.empty(n)
            t0 = time.perf_counter()
            for k in range(n):
                drv.read(1.0)
                stamps[k] = time.perf_counter()
                drv.command(0.1)
            wall = time.perf_counter() - t0
        d = np.diff(stamps) * 1e6
        print(
            f"   sim-serial {fmt:6s}: {wall / n * 1e6:7.1f} us/cycle = "
            f"{wall / floor:5.1f} x floor, "
            f"{n / wall:6.0f} samples/s; cycle p50 {np.percentile(d, 50):.0f} us, "
            f"p99 {np.percentile(d, 99):.0f} us, max {d.max():.0f} us"
        )


def stale_detection(trials=5) -> None:
    rig = rig_from_dict({"serial": {"stale_periods": 2.5}})
    T = rig.sample_time_s
    silent, tripped = [], 0
    for i in range(trials):
        drv, _peer = connect_sim_serial(
            rig, realtime=True, seed=i, faults=[Fault("stall", 400, seconds=0.05)]
        )
        with drv:
            try:
                drv.enable(0.5)
                for _ in range(1000):
                    drv.read(0.5)
                    drv.command(0.0)
            except DeviceFault as exc:
                msg = str(exc)
                if "stale" in msg:
                    tripped += 1
                    silent.append(float(msg.split("no sample for ")[1].split(" ms")[0]) * 1e-3 / T)
    print(
        "4. free-running board at 1 kHz, board stalls: "
        "silence before force zero (stale_periods 2.5)"
    )
    if silent:
        print(
            f"   {tripped}/{trials} trips on stale; "
            f"silence {np.min(silent):.2f} .. {np.max(silent):.2f} "
            f"periods (limit 2.5, poll T/4: ideal <= 2.75)"
        )
    else:
        print("   no stale trip observed (another fault came first)")


def main() -> None:
    parse_rates()
    read_styles()
    end_to_end()
    stale_detection()


if __name__ == "__main__":
    main()
