"""Synthetic record streams with known content, and a recorder process to kill.

``synthetic_stream`` closes a simple spring-damper loop around the exact ZOH
mass-damper (labbench.sim_backend.plant) so every channel holds plausible, reproducible
data. Run as a script it records such a stream at about 1 kHz, paced in real
time, printing ``<path>`` first and then one ``emitted <n_samples>`` line per
page (flushed), so a test can kill it at a random moment and know what was sent.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from labbench import records
from labbench.model.ve import VirtualEnvironment
from labbench.sim_backend.plant import MassDamperPlant

M, B_PLANT = 0.094, 0.10
VE = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=0.001, td=0.0)


def synthetic_pages(n_samples: int, page_size: int = 100, seed: int = 1, std_n: float = 0.5):
    """Yield page records of a closed spring-damper loop driven by white noise."""
    rng = np.random.default_rng(seed)
    T = VE.T
    plant = MassDamperPlant(M, B_PLANT, T)
    a = VE.filter_pole
    x_prev, v = 0.0, 0.0
    exc = rng.normal(0.0, std_n, n_samples)
    for index, lo in enumerate(range(0, n_samples, page_size)):
        n = min(page_size, n_samples - lo)
        cols = {name: np.zeros(n) for name in records.CHANNELS}
        cols["seq"] = np.zeros(n, dtype=np.int64)
        cols["flags"] = np.zeros(n, dtype=np.int64)
        for j in range(n):
            k = lo + j
            x = plant.position
            v = a * v + (1 - a) * (x - x_prev) / T
            x_prev = x
            f_ve = VE.K * x + VE.B * v
            u = exc[k] - f_ve
            plant.step(u)
            for name, value in (("t", k * T), ("seq", k), ("position", x), ("velocity", v),
                                ("ve_force", f_ve), ("excitation", exc[k]), ("command", u)):
                cols[name][j] = value
        yield records.page_record(index, cols)


def synthetic_stream(n_samples: int = 2000, page_size: int = 100, seed: int = 1,
                     status: str | None = "success", events: bool = True,
                     protocol: str = "etfe") -> list[dict]:
    """A whole run: start, descriptor, pages (and one event), stop (unless status is None)."""
    rig = {"name": "synthetic test rig", "sample_time_s": VE.T, "sim": {"m": M, "b": B_PLANT}}
    proto = {"name": protocol, "ve": VE.as_dict(), "std_n": 0.5, "seed": seed}
    out = [records.start_record(rig, proto, seed), records.descriptor_record(VE.T)]
    for page in synthetic_pages(n_samples, page_size, seed):
        out.append(page)
        if events and page["index"] == 3:
            out.append(records.event_record(float(page["data"]["t"][0]), "force_limit",
                                            "commanded 5.2 N > 5 N limit", value_n=5.2))
    if status is not None:
        out.append(records.stop_record(status, "done", timing={"p50_s": 0.001, "p99_s": 0.0012,
                                                                "max_s": 0.004, "overruns": 0}))
    return out


def main() -> int:
    from labbench.sessions.session_format import SessionWriter

    ap = argparse.ArgumentParser()
    ap.add_argument("directory")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--page-size", type=int, default=100)
    args = ap.parse_args()
    T = VE.T
    n = round(args.seconds / T)
    stream = synthetic_stream(n, args.page_size, status="success", events=False)
    with SessionWriter(args.directory) as writer:
        t0 = time.monotonic()
        emitted = 0
        for rec in stream:
            if rec["kind"] == records.PAGE:
                # a page is emitted once its last sample has been acquired
                emitted += len(rec["data"]["t"])
                delay = t0 + emitted * T - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            writer(rec)
            if rec["kind"] == records.START:
                print(writer.path, flush=True)
            elif rec["kind"] == records.PAGE:
                print(f"emitted {emitted}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
