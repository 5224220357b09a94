"""Loop timing a user can see: the period histogram, overruns and the worst stall.

``labbench.loop.chain.run_loop`` stores the wall-clock period before every sample
(``time.perf_counter`` differences; the period of the first sample, which
includes starting the device, and the ``enable`` call are left out) and hands
them to ``period_stats``. ``merge`` joins the segments of one run
(``labbench.runner``), ``summary`` makes the one line the CLI and GUI show, and
``report_rows`` the rows of the report's "Loop timing" table.

An overrun is a period longer than ``OVERRUN_T`` = 1.5 T: the sample came at
least half a period late, so the force of the previous step was held 50 % too
long (and, on hardware, a watchdog counting periods comes close to firing).
Only paced devices (hardware, the real-time simulator) are judged; an unpaced
simulator's periods are compute times.
"""
from __future__ import annotations

import numpy as np

OVERRUN_T = 1.5
# The events a run records of its timing (what the live status bar showed): ``overrun`` (at
# most one a second, ``labbench.loop.chain``), a simulator's ``stall`` beyond the watchdog, and
# ``loop_timing``, the run's totals (``summary``) when it had overruns (``labbench.runner``).
EVENTS = ("overrun", "stall", "loop_timing")
# Histogram bin edges in periods T; the last bin is open-ended (>= 20 T).
EDGES_T = (0.0, 0.5, 0.9, 1.1, 1.5, 2.0, 3.0, 5.0, 10.0, 20.0)


def period_stats(periods, T: float, paced: bool, worst_sample: int = -1,
                 worst_t_s: float | None = None, worst_wall_s: float | None = None) -> dict:
    """Condense the loop periods (seconds) of one ``run_loop`` call.

    ``worst_*`` say where the longest period ended (sample index in the segment,
    device time and wall time since the loop started), as the loop saw it.
    """
    p = np.asarray(periods, float)
    if not len(p):
        p = np.zeros(1)
    counts, _ = np.histogram(p, bins=np.array([*EDGES_T, np.inf]) * T)
    return {
        "T_s": T, "paced": bool(paced), "periods": int(len(p)),
        "p50_s": float(np.percentile(p, 50)), "p99_s": float(np.percentile(p, 99)),
        "max_s": float(p.max()),
        "overruns": int(np.count_nonzero(p > OVERRUN_T * T)) if paced else 0,
        "histogram": {"edges_T": list(EDGES_T), "counts": counts.tolist()},
        "worst": {"period_s": float(p.max()), "sample": int(worst_sample),
                  "t_s": worst_t_s, "wall_s": worst_wall_s},
    }


def merge(parts: list[dict], starts: list[int]) -> dict:
    """One run's timing from its segments' (``starts``: first sample of each in the run).

    Counts and histograms add; max and the worst stall are the worst segment's; p99
    is the worst segment's p99 (an upper bound of the run's), p50 the median of theirs.
    """
    parts_starts = [(p, s) for p, s in zip(parts, starts) if p]
    if not parts_starts:
        return {}
    parts = [p for p, _ in parts_starts]
    out = {"segments": len(parts), "T_s": parts[0].get("T_s"),
           "paced": any(p.get("paced") for p in parts),
           "periods": sum(p.get("periods", 0) for p in parts),
           "p50_s": float(np.median([p["p50_s"] for p in parts])),
           "p99_s": max(p["p99_s"] for p in parts), "max_s": max(p["max_s"] for p in parts),
           "overruns": sum(p.get("overruns", 0) for p in parts)}
    hists = [p["histogram"]["counts"] for p in parts if "histogram" in p]
    if hists:
        out["histogram"] = {"edges_T": list(EDGES_T),
                            "counts": np.sum(hists, axis=0).astype(int).tolist()}
    worst_part, start = max(parts_starts, key=lambda ps: ps[0]["max_s"])
    if "worst" in worst_part:
        w = dict(worst_part["worst"])
        if w.get("sample", -1) >= 0:
            w["sample"] += start
        out["worst"] = w
    for key in ("wall_s",):
        if all(key in p for p in parts):
            out[key] = sum(p[key] for p in parts)
    return out


def summary(timing: dict) -> str:
    """One line: overruns, the worst stall and when, p99, what the scheduler granted."""
    if not timing:
        return "loop timing: not recorded"
    T = timing.get("T_s")
    rate = f"{1 / T:.0f} Hz " if T else ""
    if not timing.get("paced"):
        line = (f"loop timing: unpaced {rate}run, {_ms(timing.get('p50_s'))} per sample (median)")
    else:
        w = timing.get("worst") or {}
        when = f" at t = {w['t_s']:.3f} s" if isinstance(w.get("t_s"), (int, float)) else ""
        line = (f"loop timing: {timing.get('overruns', 0)} overruns (> {OVERRUN_T:g} T) in "
                f"{timing.get('periods', '?')} periods at {rate}".rstrip()
                + f"; worst {_ms(timing.get('max_s'))}{when}; p99 {_ms(timing.get('p99_s'))}")
    rt = timing.get("realtime")
    if rt:
        line += f"; {scheduling(rt)}"
    return line


def status_figures(timing: dict) -> dict:
    """What a status bar shows, from one timing summary: a run's (``merge``, the loop's
    ``period_stats``) or a live snapshot (``labbench.runner.run``'s ``live_timing``).

    ``samples_per_s``: samples over wall seconds. On a paced device it is the loop's
    rate (1/T when it keeps up). On an unpaced one (lock-step) it is how fast the host
    simulates, not a loop rate: ``speed`` (simulated seconds per wall second) says so,
    and the periods (``p50_s``, ``p99_s``) are compute times per sample. A window that
    counted its own samples per second beside the loop's p99 showed "1999 Hz" beside
    "p99 1.65 ms" for a lock-step avr-sim run: both true, neither a loop rate.
    """
    T = timing.get("T_s")
    n = timing.get("periods", timing.get("n"))
    wall = timing.get("wall_s")
    per_s = n / wall if isinstance(n, (int, float)) and isinstance(wall, (int, float)) \
        and wall > 0 else None
    paced = bool(timing.get("paced"))
    out = {"paced": paced, "sample_rate_hz": 1 / T if T else None, "samples_per_s": per_s,
           "speed": per_s * T if per_s is not None and T else None,
           "p50_s": timing.get("p50_s"), "p99_s": timing.get("p99_s"),
           "overruns": timing.get("overruns", 0) if paced else None,
           "max_s": timing.get("max_s"),
           "worst_t_s": timing.get("worst_t_s", (timing.get("worst") or {}).get("t_s"))}
    if paced:
        rate = f"{per_s:.0f} samples/s" if per_s is not None else "-"
        out["rate_text"] = f"paced at {out['sample_rate_hz']:.0f} Hz: {rate}"
    else:
        speed = f"{out['speed']:.2g}x real time" if out["speed"] is not None else "-"
        out["rate_text"] = f"lock-step (unpaced): {speed}"
    return out


def scheduling(rt: dict) -> str:
    """What the loop's thread ran with, e.g. 'SCHED_FIFO 80 on CPU 1, memory locked, GC frozen,
    CPU wake-up latency <= 0 us'."""
    if not rt.get("requested"):
        return "real-time scheduling off"
    parts = [rt.get("policy", "?") + (f" {rt['priority']}" if rt.get("priority") else "")]
    cpus = rt.get("affinity")
    if cpus:
        parts[0] += f" on CPU {','.join(map(str, cpus))}"
    parts.append("memory locked" if rt.get("memory_locked") else "memory not locked")
    parts.append(f"GC {rt.get('gc', '?')}")
    if isinstance(rt.get("cpu_latency_us"), int):  # absent in sessions recorded before it
        parts.append(f"CPU wake-up latency <= {rt['cpu_latency_us']} us")
    return ", ".join(parts)


def report_rows(timing: dict) -> list[tuple[str, object]]:
    """(label, value: text or number) rows of the report's loop-timing table, histogram included."""
    if not timing:
        return [("timing", "not recorded")]
    rows = [("summary", summary(timing))]
    for key in ("p50_s", "p99_s", "max_s"):
        if isinstance(timing.get(key), (int, float)):
            rows.append((f"period {key[:-2]} (ms)", float(f"{timing[key] * 1e3:.4g}")))
    if timing.get("paced"):
        rows.append((f"overruns (> {OVERRUN_T:g} T)", int(timing.get("overruns", 0))))
    hist = timing.get("histogram")
    if hist:  # zip: a session's lists may disagree in length (a faulty writer)
        edges = hist.get("edges_T") or []
        for i, (c, _lo) in enumerate(zip(hist.get("counts") or [], edges)):
            hi = f"{edges[i + 1]:g} T" if i + 1 < len(edges) else "inf"
            rows.append((f"periods in [{edges[i]:g} T, {hi})", int(c)))
    for key, label in (("wall_s", "wall time (s)"), ("realtime_factor", "simulated s per wall s")):
        if isinstance(timing.get(key), (int, float)):
            rows.append((label, float(f"{timing[key]:.4g}")))
    if not timing.get("paced"):
        rows.append(("note", "unpaced run (simulator as fast as possible): the periods are "
                             "compute times per sample"))
    return rows


def _ms(v) -> str:
    return f"{v * 1e3:.3g} ms" if isinstance(v, (int, float)) else "-"
