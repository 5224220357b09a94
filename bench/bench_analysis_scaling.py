"""Every analysis bounded (issue 30): time, peak memory and cancel latency against the
record's length, up to the longest run a protocol allows (1800 s at 1 kHz).

Records: a chirp identification and a white-noise ETFE (K = 50 N/m, B = 1 N s/m) on the
default simulated rig (quantised encoder), seed 1, recorded as sessions at each length.
Cases (``CASES``): ``Session.identify`` with l2, l1 and both (``run chirp-id``'s default
methods), model auto; ``Session.etfe`` with each estimator, with and without ``fit=True``
(the m, b of the theory identified from the record, as the Sessions tab's Re-analyse
does); the live estimator given the whole record at once. Each case runs in a fresh
process (its peak RSS is its own: ``ru_maxrss``, loading the session included), best of
``--repeat`` runs. Time is the process's CPU time (all threads; BLAS and OpenMP held to
one thread, so a shared machine's load and idle BLAS threads spinning do not count) and,
beside it, the wall time. Times are printed against the floor of two real FFTs of the
same length (``scipy.fft.rfft`` of force and position, CPU time, best of 5, measured in
this run), and the ratio of the longest record's time to the first record's, per case
(goal: <= 15 for 1800 s against 120 s; 10 s and 1 GB at 120 s). ``gap`` is the longest
wall time between two checks of the cancel event (how late a Cancel would be heard;
goal about 0.5 s).

Writes docs/analysis-scaling.md.

    .venv/bin/python bench/bench_analysis_scaling.py [--lengths 120,600,1800] [--repeat 3]
                                                      [--only id,etfe,live] [--out FILE]
                                                      [--keep DIR]  (reuse the records there)
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

CASES = {
    "id l2": ("chirp-id", lambda s, **kw: s.identify(method="l2", **kw)),
    "id l1": ("chirp-id", lambda s, **kw: s.identify(method="l1", **kw)),
    "id l2 + l1": ("chirp-id", lambda s, **kw: [s.identify(method=m, **kw) for m in ("l2", "l1")]),
    **{f"etfe {e}{' --fit' if f else ''}": ("etfe", lambda s, e=e, f=f, **kw: s.etfe(estimator=e, fit=f, **kw))
       for e in ("lpm", "h1-log", "h1-welch", "paper") for f in (False, True)},
    "live-welch, whole record": ("etfe", lambda s, **kw: _live(s, **kw)),
}
GOAL_RATIO, GOAL_S, GOAL_BYTES = 15.0, 10.0, 1 << 30
ONE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _live(session, progress=None, cancel=None):
    """The live estimator's whole-record path: every sample added at once, then estimated."""
    from labbench.analysis.etfe_live import LiveEtfe

    rec = session.recording
    live = LiveEtfe(rec.fs)
    live.add(rec.force, rec.position)
    if cancel is not None:
        cancel.is_set()  # no checks inside: one pass, its whole time is the gap
    return live.estimate()


class _Clock:
    """A cancel event that is never set and remembers when (CPU time) it was asked."""

    def __init__(self):
        self.times = []

    def is_set(self) -> bool:
        self.times.append(time.process_time())
        return False


def run_case(name: str, path: str, repeat: int) -> dict:
    """One case in this process: best time, the longest gap between cancel checks, peak RSS."""
    import labbench

    session = labbench.load(path)
    session.recording  # loaded before the clock starts
    fn = CASES[name][1]
    best, wall, gap, peak = np.inf, np.inf, 0.0, 0
    for _ in range(repeat):
        _reset_peak_rss()
        clock = _Clock()
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            fn(session, progress=lambda f, p: None, cancel=clock)
        except TypeError:  # an older labbench without progress/cancel (a baseline run)
            fn(session)
            clock.times = []
        c1, t1 = time.process_time(), time.perf_counter()
        best, wall, peak = min(best, c1 - c0), min(wall, t1 - t0), max(peak, _peak_rss())
        marks = [c0, *clock.times, c1]
        gap = max(gap, float(np.max(np.diff(marks)))) if clock.times else float("nan")
    return {"t": best, "wall": wall, "gap": gap, "rss_analysis": peak,
            "rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}


def _reset_peak_rss() -> None:
    """Start the kernel's RSS high-water mark afresh (Linux: clear_refs 5)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def _peak_rss() -> int:
    """RSS high-water mark [bytes] since the last reset (VmHWM)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    return 0


def record(directory: Path, protocol: str, duration: float) -> Path:
    """A session of ``protocol`` on the default simulated rig, seed 1 (its own analysis runs too),
    as DIRECTORY/PROTOCOL-DURATION.lbsession (an existing one is reused)."""
    path = directory / f"{protocol}-{duration:g}.lbsession"
    if path.exists():
        return path
    from labbench.registry import make_protocol
    from labbench.rig import Rig
    from labbench.runner import run
    from labbench.sessions.session_format import SessionWriter
    from labbench.sim_backend.sim_device import open_sim

    opts = {"duration_s": duration}
    if protocol == "etfe":
        opts["seed"] = 1
    rig = Rig()
    with SessionWriter(directory) as w:
        result = run(open_sim(rig, seed=1), make_protocol(protocol, **opts), [w], rig=rig)
    if result.status != "success":
        raise RuntimeError(f"{protocol} {duration:g} s: {result.reason}")
    w.path.rename(path)
    return path


def floors(n: int) -> tuple[float, float]:
    """CPU time of two real FFTs of n samples, and of one pass over two such arrays (a
    cumulative sum of each: what any linear-time step costs at least), best of 5."""
    from scipy import fft

    rng = np.random.default_rng(0)
    f, x = rng.standard_normal(n), rng.standard_normal(n)
    out = []
    for work in (lambda: (fft.rfft(f), fft.rfft(x)), lambda: (np.cumsum(f), np.cumsum(x))):
        best = np.inf
        for _ in range(5):
            t0 = time.process_time()
            work()
            best = min(best, time.process_time() - t0)
        out.append(best)
    return out[0], out[1]


def measure(name: str, path: Path, repeat: int, timeout: float) -> dict:
    cmd = [sys.executable, __file__, "--case", name, "--file", str(path), "--repeat", str(repeat)]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False,
                             env={**os.environ, **ONE_THREAD})
    except subprocess.TimeoutExpired:
        return {"error": f"over {timeout:g} s"}
    if out.returncode != 0:
        return {"error": (out.stderr.strip().splitlines() or ["failed"])[-1][:120]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _mb(b: float) -> str:
    return f"{b / 2**20:.0f}"


def write_doc(path: Path, lengths, floor, results, elapsed: float) -> None:
    """docs/analysis-scaling.md from a run: ``floor[d]`` = (two FFTs, one pass) CPU seconds."""
    first, last = lengths[0], lengths[-1]
    fft_ratio = floor[last][0] / floor[first][0]
    pass_ratio = floor[last][1] / floor[first][1]
    lines = [
        "# Analysis cost against record length (generated by bench/bench_analysis_scaling.py)",
        "",
        "Every analysis a person can start on a recorded session, on the default simulated rig's",
        f"chirp identification and white-noise ETFE (seed 1) of {', '.join(f'{d:g}' for d in lengths)} s "
        "at 1 kHz, each case in a",
        "fresh process. CPU: the process's CPU time for the analysis (BLAS held to one thread, so",
        "the load of a shared machine and idle BLAS threads spinning do not count), best of the",
        "run's repeats, and in brackets that over two real FFTs of the same length measured in",
        "the same run; wall: elapsed time on this shared machine; peak: the process's RSS high-water",
        "mark during the analysis (the loaded session included; the whole process's, loading",
        "included, in brackets); gap: the longest CPU time",
        "between two checks of the cancel event (how late a Cancel is heard on an idle machine).",
        f"Goals (issue 30): {GOAL_S:g} s (wall) and 1 GB (process peak) at {first:g} s; the {last:g} s "
        f"record at most {GOAL_RATIO:g}x the {first:g} s record's cost (CPU); a gap of about 0.5 s. "
        "\"goals met\" says yes or NO for the first two.",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores shared with other work, Python "
        f"{platform.python_version()}; whole run {elapsed:.0f} s. The floors, CPU time: two FFTs "
        + ", ".join(f"{1e3 * floor[d][0]:.1f} ms at {d:g} s" for d in lengths)
        + f" ({fft_ratio:.1f}x from {first:g} to {last:g} s), one pass over force and position "
        + ", ".join(f"{1e3 * floor[d][1]:.2f} ms" for d in lengths)
        + f" ({pass_ratio:.1f}x for {last / first:g}x the samples).",
        "",
    ]
    head = "| analysis | " + " | ".join(f"{d:g} s: CPU s (x FFT), wall s, peak MB [process], gap s" for d in lengths)
    head += f" | {last:g} s / {first:g} s: CPU | in FFT units | peak | goals met |"
    lines += [head, "|---" * (len(lengths) + 5) + "|"]
    ok = {n: per for n, per in results.items() if all("t" in per.get(d, {}) for d in (first, last))}
    for name, per in results.items():
        cells = []
        for d in lengths:
            r = per.get(d, {"error": "not run"})
            if "error" in r:
                cells.append(r["error"])
                continue
            gap = "-" if np.isnan(r["gap"]) else f"{r['gap']:.2f}"
            cells.append(f"{r['t']:.2f} ({r['t'] / floor[d][0]:.0f}x), {r['wall']:.1f}, {_mb(r['rss_analysis'])} "
                         f"[{_mb(r['rss'])}], {gap}")
        if name in ok:
            a, b = per[first], per[last]
            met = (a["wall"] <= GOAL_S and a["rss"] <= GOAL_BYTES, b["t"] / a["t"] <= GOAL_RATIO)
            ratios = (f"{b['t'] / a['t']:.1f} | {b['t'] / a['t'] / fft_ratio:.2f} | "
                      f"{b['rss_analysis'] / a['rss_analysis']:.1f}x | "
                      f"{'yes' if met[0] else 'NO'}, {'yes' if met[1] else 'NO'}")
        else:
            ratios = "- | - | - | -"
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {ratios} |")
    lines.append("")
    at_first = [(per[first], n) for n, per in results.items() if "t" in per.get(first, {})]
    if at_first:
        t, n = max((r["t"], n) for r, n in at_first)
        w, nw = max((r["wall"], n) for r, n in at_first)
        m, nm = max((r["rss"], n) for r, n in at_first)
        lines.append(f"Worst at {first:g} s: CPU {t:.2f} s ({n}), wall {w:.1f} s ({nw}), process peak RSS "
                     f"{_mb(m)} MB ({nm}).")
    if ok:
        q, n = max((per[last]["t"] / per[first]["t"], n) for n, per in ok.items())
        lines.append(f"Worst {last:g} s / {first:g} s CPU ratio: {q:.1f} ({n}); two FFTs {fft_ratio:.1f}, "
                     f"one pass {pass_ratio:.1f}.")
    gaps = [(per[d]["gap"], n, d) for n, per in results.items() for d in lengths
            if "t" in per.get(d, {}) and not np.isnan(per[d]["gap"])]
    if gaps:
        g, n, d = max(gaps)
        lines.append(f"Longest gap between cancel checks: {g:.2f} s CPU ({n}, {d:g} s).")
    path.write_text("\n".join(lines) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lengths", default="120,600,1800", help="record lengths [s], the first the reference")
    ap.add_argument("--repeat", type=int, default=3, help="runs per case (best kept)")
    ap.add_argument("--only", default="id,etfe,live", help="comma-separated: id, etfe, live")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per case")
    ap.add_argument("--out", default=str(ROOT / "docs" / "analysis-scaling.md"))
    ap.add_argument("--keep", help="directory for the records, reused when there (default: a temporary one)")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--file", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:
        print(json.dumps(run_case(args.case, args.file, args.repeat)))
        return 0
    start = time.perf_counter()
    lengths = [float(v) for v in args.lengths.split(",")]
    kinds = set(args.only.split(","))
    names = [n for n in CASES if n.split()[0].split("-")[0] in kinds]
    results = {n: {} for n in names}
    floor = {}
    with tempfile.TemporaryDirectory() as tmp:
        keep = Path(args.keep or tmp)
        keep.mkdir(parents=True, exist_ok=True)
        for d in lengths:
            floor[d] = floors(int(d * 1000))
            paths = {}
            for protocol in sorted({CASES[n][0] for n in names}):
                t0 = time.perf_counter()
                paths[protocol] = record(keep, protocol, d)
                print(f"{protocol} {d:g} s ready in {time.perf_counter() - t0:.0f} s", flush=True)
            for n in names:
                r = results[n][d] = measure(n, paths[CASES[n][0]], args.repeat, args.timeout)
                shown = r.get("error") or (f"{r['t']:.2f} s CPU ({r['t'] / floor[d][0]:.0f}x FFT), "
                                           f"{r['wall']:.2f} s wall, peak {_mb(r['rss_analysis'])} MB "
                                           f"[{_mb(r['rss'])}], gap {r['gap']:.2f} s")
                print(f"{d:6g} s  {n:28s} {shown}", flush=True)
    write_doc(Path(args.out), lengths, floor, results, time.perf_counter() - start)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
