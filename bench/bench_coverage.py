"""Where each method holds and where it fails (issue 24): the coverage of its 95 % intervals
and its silent failures on known-truth grids, for the identification (``analyze id``), the
ETFE's bands (``analyze etfe``) and the loop fit (``analyze etfe --fit``).

A result is outside its target when a number misses both its accuracy target (issue 24's)
and its own stated precision (``labbench.readout.verdict.holds``: the 95 % interval stretched to
99.9 %): whoever read it was misled. Per part:

* identification: m beyond 1 %, b beyond 2 % of the truth, and beyond its 99.9 % interval;
* loop fit: m beyond 2 %, b beyond 5 %, a delay (td, tv) beyond 0.05 ms, and beyond its
  99.9 % interval;
* ETFE: a frequency in 2-100 rad/s whose error exceeds 1 % of |Z| (ETFE_TARGET) and whose
  band gives it a chance below 1e-6 (|dZ|^2 / se^2 beyond the 1 - 1e-6 quantile of F(2, 2
  dof): the band is off by far more than its width, as issue 24's 20-28 % errors under
  9-11 % bands were; dZ counted beyond what the band holds besides noise, ``Z_allow``).

A silent failure is a result outside its target whose verdict is ``ok``; a false alarm, one
within its accuracy targets (the fixed ones above: an identification with m within 1 % and b
within 2 %, ...) whose verdict is not ``ok`` (issue 30: a verdict that cries wolf is as wrong
as one that stays silent). A number beyond its fixed target but inside its own interval is
neither: imprecise, and its interval says so. Coverage: the share of 95 % intervals that hold the truth (ETFE: of the
bands, per frequency in 2-100 rad/s).
Truth: ``tests/truthdata.py`` (exact open-loop chirps, the exact sampled closed loop, the
loop with delays simulated step by step); every record's noise is its own seed's.

Writes docs/method-map-tables.md (the tables docs/method-map.md reads from).

    .venv/bin/python bench/bench_coverage.py [--seeds 20] [--loop-seeds 12] [--jobs 2]
                                             [--only id,etfe,loop] [--quick]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy import special

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from truthdata import (  # noqa: E402
    PAPER_B,
    PAPER_M,
    chirp_force,
    chirp_recording,
    closed_loop_recording,
    delayed_loop_recording,
    open_loop,
    sensor_chirp_recording,
    with_noise,
    z_truth,
)

from labbench.model import linear  # noqa: E402
from labbench.analysis import compare  # noqa: E402
from labbench.analysis.dataio import recording_from_arrays  # noqa: E402
from labbench.analysis.etfe import W_BAND, etfe  # noqa: E402
from labbench.analysis.loopfit import fit_loop  # noqa: E402
from labbench.session_api import identify_recording  # noqa: E402
from labbench.model.ve import Plant, VirtualEnvironment  # noqa: E402
from labbench.readout.verdict import holds  # noqa: E402

T = 1e-3
START = Plant(0.08, 0.2)  # the loop fit's start, deliberately off
ID_TARGETS = {"m": 0.01, "b": 0.02}  # relative
LOOP_TARGETS = {"m": 0.02 * PAPER_M, "b": 0.05 * PAPER_B, "td_s": 5e-5, "tv_s": 5e-5}
ETFE_TAIL = 1e-6  # an error its band gives a smaller chance than this is a failure ...
ETFE_TARGET = 0.01  # ... when it also exceeds this share of |Z|


# ----------------------------------------------------------------------------- identification
def _late_chirp(n=30000):
    """A device that applies its command one period late, the record not saying so."""
    f = chirp_force(n)
    x, _ = open_loop(np.concatenate([[0.0], f[:-1]]), PAPER_M, PAPER_B, 1000.0)
    return recording_from_arrays(np.arange(n) / 1000.0, f, x, {"fs": 1000.0, "force_hold": "zoh"}, "late")


def _closed_loop_id(seed):
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, td=T)
    return closed_loop_recording(ve, n=30000, seed=seed, process_noise=0.1)


ID_CELLS = {  # name -> (record factory(seed), truth, methods)
    "chirp 30 s, force noise 0.02 N": (lambda s: with_noise(chirp_recording(n=30000), _rng(s), force_noise=0.02),
                                       {}, ("l2",)),
    "chirp 30 s, force noise 0.05 N": (lambda s: with_noise(chirp_recording(n=30000), _rng(s), force_noise=0.05),
                                       {}, ("l2", "l1")),
    "chirp 30 s, force noise 0.2 N": (lambda s: with_noise(chirp_recording(n=30000), _rng(s), force_noise=0.2),
                                      {}, ("l2", "l1")),
    "chirp 7.5 s, force noise 0.05 N": (lambda s: with_noise(chirp_recording(n=7500), _rng(s), force_noise=0.05),
                                        {}, ("l2",)),
    "encoder step 30 um, 0.01 N": (lambda s: with_noise(chirp_recording(n=30000), _rng(s), force_noise=0.01,
                                                        quantum=30e-6), {}, ("l2", "l1")),
    "encoder step 100 um, 0.01 N": (lambda s: with_noise(chirp_recording(n=30000), _rng(s), force_noise=0.01,
                                                         quantum=100e-6), {}, ("l2",)),
    "encoder step 300 um, 0.01 N": (lambda s: with_noise(chirp_recording(n=30000), _rng(s), force_noise=0.01,
                                                         quantum=300e-6), {}, ("l2",)),
    "Coulomb 0.05 N, 0.05 N + 30 um": (lambda s: with_noise(chirp_recording(n=30000, coulomb=0.05), _rng(s),
                                                            force_noise=0.05, quantum=30e-6),
                                       {"coulomb": 0.05}, ("l2", "l1")),
    "Coulomb 0.2 N, 0.02 N": (lambda s: with_noise(chirp_recording(n=30000, coulomb=0.2), _rng(s), force_noise=0.02),
                              {"coulomb": 0.2}, ("l2",)),
    "Coulomb 0.05 N + offset 0.3 N, 0.05 N": (
        lambda s: with_noise(chirp_recording(n=30000, coulomb=0.05, offset=0.3), _rng(s), force_noise=0.05),
        {"coulomb": 0.05, "offset": 0.3}, ("l2",)),
    "stick-slip: 0.15 N chirp, Coulomb 0.1 N": (
        lambda s: with_noise(chirp_recording(n=30000, coulomb=0.1, amp=0.15), _rng(s), force_noise=0.005),
        {"coulomb": 0.1}, ("l2",)),
    "sensor force (continuous), 0.05 N": (lambda s: with_noise(sensor_chirp_recording(), _rng(s), force_noise=0.05),
                                          {}, ("l2",)),
    "device one period late, unstated, 0.02 N": (lambda s: with_noise(_late_chirp(), _rng(s), force_noise=0.02),
                                                 {}, ("l2",)),
    "closed loop (spring-damper), process 0.1 N": (_closed_loop_id, {}, ("l2",)),
}


def _rng(seed):
    return np.random.default_rng(10_000 + seed)


def id_task(name, method, seed):
    make, extra, _ = ID_CELLS[name]
    r = identify_recording(make(seed), method=method).result  # as analyze id runs it
    truth = {"m": PAPER_M, "b": PAPER_B, **extra}
    value = {k: r.params.get(k) for k in truth}
    beyond = [k for k, t in ID_TARGETS.items() if abs(value[k] - truth[k]) > t * truth[k]]
    miss = [k for k in beyond if not _holds(value[k], r.ci95.get(k), truth[k], ID_TARGETS[k] * truth[k])]
    covers = {k: bool(r.ci95[k][0] <= truth[k] <= r.ci95[k][1]) for k in truth if k in r.ci95}
    return {"cell": name, "method": method, "seed": seed, "miss": miss, "beyond": beyond, "covers": covers,
            "level": r.verdict.level, "why": _why(r.verdict), "model": r.model}


# ----------------------------------------------------------------------------- ETFE bands
SD = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0)
ETFE_VES = {
    "spring-damper K 50": SD,
    "damper B 1": VirtualEnvironment("damper", B=1.0, w0=125.0),
    "spring K 150 (0.75 K_max)": VirtualEnvironment("spring", K=150.0),
    "spring K 180 (0.9 K_max)": VirtualEnvironment("spring", K=180.0),
    "spring K 100, w0 30": VirtualEnvironment("spring", K=100.0, w0=30.0),
}
ETFE_NOISES = {  # name -> (closed_loop_recording kwargs, position noise, quantum, sensor noise)
    "process 0.1 N": ({"process_noise": 0.1}, 0.0, 0.0, 0.0),
    "process 0.3 N": ({"process_noise": 0.3}, 0.0, 0.0, 0.0),
    "position 1e-5 m": ({}, 1e-5, 0.0, 0.0),
    "encoder 3e-5 m": ({}, 0.0, 3e-5, 0.0),
    "sensor 0.05 N": ({}, 0.0, 0.0, 0.05),
    "sensor 0.05 N on 0.25 N": ({"force_std": 0.25}, 0.0, 0.0, 0.05),
}
ETFE_LENGTHS = {"30 s": 30000, "120 s": 120000}
OTHER_ESTIMATORS = ("h1-log", "h1-welch", "paper")


def etfe_record(ve_name, noise, n, seed):
    kw, pos, quantum, sensor = ETFE_NOISES[noise]
    ve = ETFE_VES[ve_name]
    rec = closed_loop_recording(ve, n=n, seed=seed, **kw)
    rng = _rng(seed)
    x = rec.position + pos * rng.standard_normal(n) if pos else rec.position
    if quantum:
        x = np.round(x / quantum) * quantum
    f = rec.force + sensor * rng.standard_normal(n) if sensor else rec.force
    # the force is the command unless a sensor read it (then the record does not say)
    meta = rec.meta if sensor else {**rec.meta, "force_hold": "zoh"}
    return recording_from_arrays(rec.t, f, x, meta), ve


def etfe_task(ve_name, noise, length, estimator, seed):
    rec, ve = etfe_record(ve_name, noise, ETFE_LENGTHS[length], seed)
    r = etfe(rec, estimator)
    band = (r.w >= W_BAND[0]) & (r.w <= W_BAND[1])
    zt = z_truth(ve, r.w[band])
    err = np.abs(r.Z[band] - zt)
    inside = err <= r.Z_err[band]
    # the band's own tail: what its noise part leaves, |dZ|^2 / se^2 ~ F(2, 2 dof), dof from
    # its noise radius (etfe.radius95); the rest of the band (Z_allow) is reach, not noise
    allow = r.Z_allow[band] if r.Z_allow is not None else 0.0
    se = np.maximum(r.Z_se[band], 1e-300)
    dof = _dof_of_radius((r.Z_err[band] - allow) / se)
    tail = special.fdtrc(2, 2 * dof, (np.maximum(err - allow, 0.0) / se) ** 2)
    far = bool(np.any((tail < ETFE_TAIL) & (err > ETFE_TARGET * np.abs(zt))))
    return {"cell": (ve_name, noise, length, estimator), "seed": seed, "inside": int(inside.sum()),
            "n": int(band.sum()), "far": far, "level": r.verdict.level, "why": _why(r.verdict),
            "median_err": float(np.median(err / np.abs(zt)))}


def _dof_of_radius(ratio):
    """Invert etfe.radius95 (the F(2, 2 dof) 95 % quantile's root) for the band's dof."""
    grid = np.concatenate([np.arange(1, 400), [1e4]])
    r = np.sqrt(special.fdtri(2, 2 * grid, 0.95))
    return np.interp(-ratio, -r, grid)  # r falls with dof


# ----------------------------------------------------------------------------- loop fit
LOOP_VES = {"spring-damper K 50": SD, "spring K 10": VirtualEnvironment("spring", K=10.0),
            "damper B 1.5": VirtualEnvironment("damper", B=1.5, w0=200.0)}
PLACEMENTS = {"VE path 1.75": (0.0, 1.75), "device 1.5": (1.5, 0.0), "both 1.3 + 2.7": (1.3, 2.7)}
RIGHT_MODEL = {"VE path 1.75": "ve-path", "device 1.5": "common", "both 1.3 + 2.7": "both"}
LOOP_NOISES = {"sensor 0.05 N": {"force_noise": 0.05}, "process 0.1 N": {"process_noise": 0.1},
               "process 0.005 N": {"process_noise": 0.005}, "process 0.002 N": {"process_noise": 0.002}}


def _near_limit():
    """A spring at 0.9 of the K_max the 1.5-sample device delay leaves."""
    k = linear.k_max(Plant(PAPER_M, PAPER_B), VirtualEnvironment("spring", K=1.0), latency=1.5 * T)
    return VirtualEnvironment("spring", K=round(0.9 * k, 1))


LOOP_EXTRA = {  # name -> (VE, placement, noise, samples)
    "spring at 0.9 K_max, device 1.5, process 0.1 N": ("near-limit", "device 1.5", "process 0.1 N", 20000),
    "spring-damper K 50, both, sensor 0.05 N, 60 s": ("spring-damper K 50", "both 1.3 + 2.7", "sensor 0.05 N",
                                                      60000),
    # where it holds to every target: little noise
    "spring-damper K 50, device 1.5, process 0.005 N, 60 s": ("spring-damper K 50", "device 1.5",
                                                              "process 0.005 N", 60000),
    "spring-damper K 50, both, process 0.002 N, 20 s": ("spring-damper K 50", "both 1.3 + 2.7", "process 0.002 N",
                                                        20000),
}


def loop_cells():
    cells = [(v, p, nz, 20000) for v in LOOP_VES for p in PLACEMENTS for nz in ("sensor 0.05 N", "process 0.1 N")]
    return cells + list(LOOP_EXTRA.values())


def loop_task(ve_name, place, noise, n, seed):
    ve = _near_limit() if ve_name == "near-limit" else LOOP_VES[ve_name]
    lat, tv = PLACEMENTS[place]
    rec = delayed_loop_recording(ve, n=n, latency=lat * T, ve_delay=tv * T, seed=100 + seed, **LOOP_NOISES[noise])
    fit = fit_loop(etfe(rec), compare.ve_from_meta(rec.meta, rec.fs), START)
    truth = {"m": PAPER_M, "b": PAPER_B, "td_s": lat * T, "tv_s": tv * T}
    value = {"m": fit.m, "b": fit.b, "td_s": fit.td_s, "tv_s": fit.tv_s}
    beyond = [k for k in truth if abs(value[k] - truth[k]) > LOOP_TARGETS[k]]
    miss = [k for k in beyond if not _holds(value[k], fit.ci95.get(k), truth[k], LOOP_TARGETS[k])]
    covers = {k: bool(fit.ci95[k][0] <= truth[k] <= fit.ci95[k][1]) for k in fit.ci95}
    return {"cell": (ve_name if ve_name != "near-limit" else f"spring K {ve.K:g} (0.9 K_max)", place, noise,
                     f"{n / 1000:g} s"), "seed": seed, "model": fit.delay_model,
            "right": fit.delay_model == RIGHT_MODEL[place], "miss": miss, "beyond": beyond, "covers": covers,
            "level": fit.verdict.level, "why": _why(fit.verdict)}


def _holds(value, ci, truth, target) -> bool:
    """``labbench.readout.verdict.holds``; a number stated without an interval holds only its target."""
    return holds(value, ci, truth, target) if ci is not None else abs(value - truth) <= target


def _why(v) -> list[str]:
    """The verdict's reasons by their first words (a flag name, or 'b not pinned', ...)."""
    return _names(v.reasons)


def _why_text(text: str) -> list[str]:
    """``_why`` of reasons joined by "; " (a sweep table's verdict_reasons)."""
    return _names([r for r in text.split("; ") if r])


def _names(reasons) -> list[str]:
    return [r.split(":")[0] if ":" in r[:40] else " ".join(r.split()[:3]) for r in reasons]


# reasons that say a number is imprecise, not that its interval may miss (every other reason
# names a bias or a misfit the interval need not hold)
IMPRECISE = ("m not pinned", "b not pinned", "td_s not pinned", "tv_s not pinned", "wide-interval",
             "short-record", "b is not", "low-coherence", "little-excitation")


def _unbiased(row) -> bool:
    """The verdict names no bias: the intervals are meant to hold the truth at 95 %."""
    return all(w.startswith(IMPRECISE) for w in row["why"])


# ----------------------------------------------------------------------------- tables
def _pct(hits, n):
    return f"{100 * hits / n:.0f} % ({n})" if n else "-"


def _levels(rows):
    c = Counter(r["level"] for r in rows)
    return " / ".join(str(c.get(k, 0)) for k in ("ok", "doubtful", "failed"))


def _reasons(rows, top=3):
    c = Counter(w for r in rows for w in set(r["why"]))
    ranked = sorted(c.items(), key=lambda kv: (-kv[1], kv[0]))[:top]  # ties by name: a rerun diffs clean
    return "; ".join(f"{k} ({v})" for k, v in ranked) or "-"


def id_table(rows):
    params = ("m", "b", "coulomb", "offset")
    lines = ["| record | method | fits | outside target | silent | false alarms | "
             + " | ".join(f"{p} cov" for p in params)
             + " | ok / doubtful / failed | main reasons |", "|---" * (8 + len(params)) + "|"]
    groups = {}
    for r in rows:
        groups.setdefault((r["cell"], r["method"]), []).append(r)
    for (cell, method), rs in groups.items():
        cov = [_pct(sum(r["covers"][p] for r in rs if p in r["covers"]), sum(p in r["covers"] for r in rs))
               for p in params]
        lines.append(f"| {cell} | {method} | {len(rs)} | {sum(bool(r['miss']) for r in rs)} | "
                     f"{sum(bool(r['miss']) and r['level'] == 'ok' for r in rs)} | {_alarms(rs, 'miss')} | "
                     + " | ".join(cov)
                     + f" | {_levels(rs)} | {_reasons(rs)} |")
    return "\n".join(lines), _totals(rows, params)


def etfe_table(rows):
    lines = ["| VE | noise | length | estimator | records | band coverage | median error | far off | silent | "
             "false alarms | ok / doubtful / failed | main reasons |", "|---" * 12 + "|"]
    groups = {}
    for r in rows:
        groups.setdefault(r["cell"], []).append(r)
    for (ve, noise, length, est), rs in groups.items():
        lines.append(f"| {ve} | {noise} | {length} | {est} | {len(rs)} | "
                     f"{_pct(sum(r['inside'] for r in rs), sum(r['n'] for r in rs))} | "
                     f"{100 * np.median([r['median_err'] for r in rs]):.2g} % | {sum(r['far'] for r in rs)} | "
                     f"{sum(r['far'] and r['level'] == 'ok' for r in rs)} | {_alarms(rs, 'far')} | "
                     f"{_levels(rs)} | {_reasons(rs)} |")
    lpm = [r for r in rows if r["cell"][3] == "lpm"]
    clean = [r for r in lpm if _unbiased(r)]
    total = {"bands (lpm)": (sum(r["inside"] for r in lpm), sum(r["n"] for r in lpm)),
             "bands (lpm, no bias named)": (sum(r["inside"] for r in clean), sum(r["n"] for r in clean)),
             "silent": sum(r["far"] and r["level"] == "ok" for r in rows), "results": len(rows),
             "outside": sum(r["far"] for r in rows), "alarms": _alarm_count(rows, "far")}
    return "\n".join(lines), total


def loop_table(rows):
    params = ("m", "b", "td_s", "tv_s")
    lines = ["| VE | delays (samples) | noise | length | fits | model right | outside target | silent | "
             "false alarms | " + " | ".join(f"{p} cov" for p in params) + " | ok / doubtful / failed | main reasons |",
             "|---" * (11 + len(params)) + "|"]
    groups = {}
    for r in rows:
        groups.setdefault(r["cell"], []).append(r)
    for (ve, place, noise, length), rs in groups.items():
        cov = [_pct(sum(r["covers"][p] for r in rs if p in r["covers"]), sum(p in r["covers"] for r in rs))
               for p in params]
        lines.append(f"| {ve} | {place} | {noise} | {length} | {len(rs)} | {sum(r['right'] for r in rs)} | "
                     f"{sum(bool(r['miss']) for r in rs)} | {sum(bool(r['miss']) and r['level'] == 'ok' for r in rs)} | "
                     f"{_alarms(rs, 'miss')} | " + " | ".join(cov) + f" | {_levels(rs)} | {_reasons(rs)} |")
    return "\n".join(lines), _totals(rows, params)


def _alarm_count(rows, key) -> tuple[int, int]:
    """(false alarms, results within target): within target yet not ok (``key``: "far" for
    the ETFE, whose target is its band; else the fixed targets, "beyond")."""
    within = [r for r in rows if not r["beyond" if key == "miss" else key]]
    return sum(r["level"] != "ok" for r in within), len(within)


def _alarms(rows, key) -> str:
    bad, n = _alarm_count(rows, key)
    return f"{bad} of {n}"


def _totals(rows, params):
    out = {p: (sum(r["covers"][p] for r in rows if p in r["covers"]), sum(p in r["covers"] for r in rows))
           for p in params}
    clean = [r for r in rows if _unbiased(r)]
    out.update({f"{p} (no bias named)": (sum(r["covers"][p] for r in clean if p in r["covers"]),
                                          sum(p in r["covers"] for r in clean)) for p in params})
    out["silent"] = sum(bool(r["miss"]) and r["level"] == "ok" for r in rows)
    out["alarms"] = _alarm_count(rows, "miss")
    out["outside"] = sum(bool(r["miss"]) for r in rows)
    out["results"] = len(rows)
    return out


# ----------------------------------------------------------------------------- running
def _run(tasks, jobs):
    """(fn, args) tasks, in order; on ``jobs`` processes (each its own seeds: no shared state)."""
    if jobs <= 1:
        return [fn(*args) for fn, args in tasks]
    with ProcessPoolExecutor(jobs) as pool:
        futures = [pool.submit(fn, *args) for fn, args in tasks]
        return [f.result() for f in futures]


def id_tasks(seeds):
    return [(id_task, (name, method, s)) for name, (_, _, methods) in ID_CELLS.items() for method in methods
            for s in range(seeds)]


def etfe_tasks(seeds, quick):
    tasks = []
    for length in ETFE_LENGTHS:
        count = seeds if length == "30 s" else max(seeds // 2, 2)
        for ve in ETFE_VES:
            for noise in ETFE_NOISES:
                tasks += [(etfe_task, (ve, noise, length, "lpm", s)) for s in range(count)]
        if not quick:
            for est in OTHER_ESTIMATORS:
                for ve in ("spring-damper K 50", "damper B 1"):
                    tasks += [(etfe_task, (ve, "process 0.1 N", length, est, s)) for s in range(count)]
    return tasks


def loop_tasks(seeds):
    return [(loop_task, (*cell, s)) for cell in loop_cells() for s in range(seeds)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20, help="records per cell (ETFE 120 s: half)")
    ap.add_argument("--loop-seeds", type=int, default=12, help="records per loop-fit cell (each ~3 s)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes")
    ap.add_argument("--only", default="id,etfe,loop", help="comma-separated: id, etfe, loop")
    ap.add_argument("--quick", action="store_true", help="3 seeds, no other ETFE estimators (a smoke run)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "method-map-tables.md"))
    ap.add_argument("--save-rows", metavar="FILE",
                    help="also write every result as JSON (bench_verdicts.py --grid-rows reads it)")
    args = ap.parse_args()
    seeds = 3 if args.quick else args.seeds
    parts = [p.strip() for p in args.only.split(",")]
    t0 = time.perf_counter()
    sections, summary, saved = [], [], []
    for part in parts:
        t1 = time.perf_counter()
        if part == "id":
            rows = _run(id_tasks(seeds), args.jobs)
            table, tot = id_table(rows)
            title = "Identification (`analyze id`, model auto, 30 s chirps 0.1-20 Hz of 1 N at 1 kHz)"
        elif part == "etfe":
            rows = _run(etfe_tasks(seeds, args.quick), args.jobs)
            table, tot = etfe_table(rows)
            title = "ETFE bands (`analyze etfe`, closed loop, white-noise force of 1 N rms at 1 kHz)"
        elif part == "loop":
            rows = _run(loop_tasks(3 if args.quick else args.loop_seeds), args.jobs)
            table, tot = loop_table(rows)
            title = "Loop fit (`analyze etfe --fit`, white-noise force of 1 N rms, delays undeclared)"
        else:
            raise SystemExit(f"unknown part {part!r}: id, etfe or loop")
        saved += rows
        dt = time.perf_counter() - t1
        sections.append(f"## {title}\n\n{table}\n\n({tot['results']} results, {dt:.0f} s)\n")
        cov = ", ".join(f"{k} {_pct(*v)}" for k, v in tot.items() if isinstance(v, tuple) and k != "alarms")
        summary.append(f"| {part} | {tot['results']} | {tot.get('outside', '-')} | {tot['silent']} | "
                       f"{tot['alarms'][0]} of {tot['alarms'][1]} | {cov} |")
        print(sections[-1], flush=True)
    head = ["# Method map tables (generated by bench/bench_coverage.py)", "",
            f"Seeds per cell: {seeds} (ETFE 120 s records: {max(seeds // 2, 2)}; loop fit: "
            f"{3 if args.quick else args.loop_seeds}); "
            f"{time.perf_counter() - t0:.0f} s on {args.jobs} worker(s). Definitions: the bench's module doc; "
            "reading: docs/method-map.md.", "",
            "| part | results | outside target | silent failures | false alarms (of those within target) | "
            "coverage of the 95 % intervals |",
            "|---|---|---|---|---|---|", *summary, ""]
    Path(args.out).write_text("\n".join(head + sections))
    if args.save_rows:
        Path(args.save_rows).write_text(json.dumps(saved))
    print("\n".join(head[4:]))
    print(f"wrote {args.out} in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
