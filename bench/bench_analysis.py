"""Speed against accuracy of the analysis, on data with known truth.

ETFE: every estimator x record length x noise (clean, encoder quantisation,
position noise, force-sensor noise) on the exact sampled loop of the paper's
spring-damper (K = 50, B = 1, w0 = 125, m = 0.094, b = 0.10) and a pure damper;
median and max complex relative error of Z over 2-100 rad/s and compute time.
Goal: default ETFE + effective impedances of 120 000 samples within 3x the
time of two real FFTs of the same data (the floor, measured in the same run).

Identification: solver (l2, fast l1, cvxpy l1) x record length x force
outliers x unmodelled Coulomb friction on exact simulated chirps; worst
relative error of m and b and the identification's time. Goal: fast l1 >= 20x
faster than cvxpy's default solver on 60 000 samples with the objective within 1e-6.

Also Table 1 of the paper on simulated chirps (m = 94 g, b = 0.10, five runs).
The three tables are the sweeps docs/examples/speed-vs-accuracy.toml,
identification.toml and paper-table1.toml (``labbench sweep``, analysis kind),
run here in this process. Writes docs/analysis-bench.md (tables) and
docs/analysis-bench.png (error vs time, one point per method and setting).
ETFE times are best of --repeat; identification times one run each.

    .venv/bin/python bench/bench_analysis.py [--repeat 5] [--quick]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import fft

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "docs" / "examples"

from labbench.analysis.etfe import DEFAULT_ESTIMATOR, ESTIMATORS, etfe
from labbench.model.effective import effective_impedances
from labbench.sweep.engine import run_sweep
from labbench.sweep.exact import closed_loop_recording
from labbench.sweep.spec import load_spec, spec_from_dict
from labbench.sweep.table import read_table
from labbench.model.ve import VirtualEnvironment

NOISES = ("clean", "quantised 3e-5 m", "position noise 1e-5 m", "force noise 5 %")
SOLVERS = ("l2", "l1 fast", "l1 cvxpy")


def best_time(fn, repeat):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def sweep(name: str, quick_n: list[int] | None = None, repeat: int | None = None) -> list[dict]:
    """Rows of the example spec ``name`` (docs/examples), run on one worker in this process
    (the times are the analysis' own, not shared with a second worker)."""
    spec = load_spec(EXAMPLES / name)
    if quick_n or repeat:
        d = spec.as_dict()
        if quick_n:
            d["grid"]["n"] = quick_n
        if repeat:
            d["sweep"]["repeat"] = repeat
        spec = spec_from_dict(d, source=f"{name} (adjusted)")
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_sweep(spec, Path(tmp) / "t.sweep", workers=0)
        rows = read_table(summary.table).to_pylist()
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:
        raise RuntimeError(f"{name}: {bad[0]['error']}")
    return rows


def bench_etfe(repeat, quick):
    rows = sweep("speed-vs-accuracy.toml", [30_000] if quick else None, repeat)
    rows.sort(key=lambda r: (r["environment"] != "spring-damper", r["n"],
                             NOISES.index(r["noise"]), ESTIMATORS.index(r["estimator"])))
    return [{"ve": r["environment"], "n": int(r["n"]), "noise": r["noise"],
             "estimator": r["estimator"], "time_s": r["analysis_s"],
             "median": r["truth.median_rel"], "max": r["truth.max_rel"],
             "flags": r["res.flags"].split("; ") if r["res.flags"] else []} for r in rows]


def bench_etfe_speed(repeat):
    """Floor and candidate measured alternately (a shared machine drifts in load), best of each."""
    rec = closed_loop_recording(VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0),
                                n=120_000, seed=3)
    f, x = rec.force, rec.position

    def full():
        res = etfe(rec)
        return effective_impedances(res.w, res.Z)

    floor = t = np.inf
    for _ in range(10 * repeat):
        floor = min(floor, best_time(lambda: (fft.rfft(f), fft.rfft(x)), 1)[0])
        t = min(t, best_time(full, 1)[0])
    return {"floor_s": floor, "etfe_s": t, "ratio": t / floor}


def bench_identify(quick):
    """Solver x length x outliers x Coulomb (docs/examples/identification.toml); time of the
    whole identification (fit, jackknife intervals, flags), one run each."""
    rows = sweep("identification.toml", [15_000] if quick else None)
    rows.sort(key=lambda r: (r["n"], r["coulomb_n"], r["case"] != "clean",
                             SOLVERS.index(r["fit"])))
    out = [{"n": int(r["n"]), "friction": r["coulomb_n"], "case": r["case"], "solver": r["fit"],
            "time_s": r["analysis_s"], "m": r["res.m"], "b": r["res.b"],
            "err": r["truth.worst_rel"], "obj": r["res.l1_objective"]} for r in rows]
    cvx = {(r["n"], r["friction"], r["case"]): r["obj"] for r in out if r["solver"] == "l1 cvxpy"}
    for r in out:
        r["obj_rel_vs_cvxpy"] = ((r["obj"] - cvx[key]) / cvx[key]
                                 if r["solver"].startswith("l1") and (key := (r["n"], r["friction"], r["case"])) in cvx
                                 else None)
    return out


def table1():
    out = {"l2": [], "l1": []}
    for r in sweep("paper-table1.toml"):
        out[r["method"]].append((r["res.m"], r["res.b"], (r["res.ci95.m.0"], r["res.ci95.m.1"]),
                                 (r["res.ci95.b.0"], r["res.ci95.b.1"])))
    return out


def write_docs(etfe_rows, speed, id_rows, t1, path_md, path_png):
    lines = ["# Analysis benchmark (generated by bench/bench_analysis.py)", ""]
    lines += [(f"ETFE speed (120 000 samples, default `{DEFAULT_ESTIMATOR}` + effective impedances): "
               f"{1e3 * speed['etfe_s']:.2f} ms against two real FFTs {1e3 * speed['floor_s']:.2f} ms "
               f"= **{speed['ratio']:.2f}x** (goal <= 3x)."), ""]
    lines += ["## ETFE: complex relative error of Z over 2-100 rad/s", "",
              "| VE | samples | noise | estimator | median % | max % | time ms | flags |",
              "|---|---|---|---|---|---|---|---|"]
    for r in etfe_rows:
        lines.append(f"| {r['ve']} | {r['n']} | {r['noise']} | {r['estimator']} | {100 * r['median']:.3f} "
                     f"| {100 * r['max']:.2f} | {1e3 * r['time_s']:.1f} | {', '.join(r['flags'])} |")
    lines += ["", "## Identification (model mb): worst relative error of m, b", "",
              ("Chirp 0.1-20 Hz, 1 N, force noise 0.01 N; Coulomb friction, when present, is not in the "
               "fitted model (what a user fitting mb to a rubbing device gets). Time: the whole "
               "identification (the fit, its ten jackknife refits for the intervals, the flags)."), "",
              ("| samples | Coulomb N | case | solver | m g | b N s/m | worst error % | time ms | "
               "l1 objective vs cvxpy |"), "|---|---|---|---|---|---|---|---|---|"]
    for r in id_rows:
        rel = "" if r["obj_rel_vs_cvxpy"] is None else f"{r['obj_rel_vs_cvxpy']:+.1e}"
        lines.append(f"| {r['n']} | {r['friction']:g} | {r['case']} | {r['solver']} | {1e3 * r['m']:.3f} | "
                     f"{r['b']:.4f} | {100 * r['err']:.3f} | {1e3 * r['time_s']:.1f} | {rel} |")
    big = [r for r in id_rows if r["n"] == max(x["n"] for x in id_rows)]
    ratios = []
    for key in {(r["friction"], r["case"]) for r in big}:
        t = {r["solver"]: r["time_s"] for r in big if (r["friction"], r["case"]) == key}
        ratios.append(t["l1 cvxpy"] / t["l1 fast"])
    lines += ["", (f"Fast l1 vs cvxpy (default solver) on {big[0]['n']} samples: "
                   f"{min(ratios):.0f}x to {max(ratios):.0f}x faster (goal >= 20x); objective column above."), ""]
    lines += ["## Table 1 of the paper, simulated", "",
              ("Chirp 0.1-20 Hz, 30 s at 1 kHz, m = 94 g, b = 0.10 N s/m, force noise 0.02 N, "
               "encoder step 1e-5 m; mean of five runs (paper: l2 94 g / 0.10, l1 88 g / 0.09)."), "",
              "| Objective | m (g) | b (N s/m) | m 95 % (run 1) | b 95 % (run 1) |", "|---|---|---|---|---|"]
    for method, name in (("l2", "l2, sum of squares"), ("l1", "l1, sum of absolute values")):
        v = t1[method]
        m = np.mean([a[0] for a in v])
        b = np.mean([a[1] for a in v])
        lines.append(f"| {name} | {1e3 * m:.2f} | {b:.4f} | [{1e3 * v[0][2][0]:.2f}, {1e3 * v[0][2][1]:.2f}] "
                     f"| [{v[0][3][0]:.4f}, {v[0][3][1]:.4f}] |")
    path_md.write_text("\n".join(lines) + "\n")
    _chart(etfe_rows, id_rows, path_png)


def _chart(etfe_rows, id_rows, path):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    fig = Figure(figsize=(12, 5.5), layout="constrained")
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    markers = {"clean": "o", "quantised 3e-5 m": "s", "position noise 1e-5 m": "^", "force noise 5 %": "x"}
    for i, est in enumerate(ESTIMATORS):
        for noise, mk in markers.items():
            pts = [r for r in etfe_rows if r["estimator"] == est and r["noise"] == noise]
            ax1.loglog([1e3 * r["time_s"] for r in pts], [100 * r["median"] for r in pts], mk,
                       color=f"C{i}", label=est if noise == "clean" else None, mfc="none" if mk != "x" else None)
    ax1.axhline(1.0, color="k", ls="--", lw=0.8)
    ax1.set(xlabel="compute time (ms)", ylabel="median |dZ|/|Z| over 2-100 rad/s (%)",
            title="ETFE (marker: o clean, s quantised, ^ position noise, x force noise)")
    ax1.legend(title="estimator")
    solvers = ["l2", "l1 fast", "l1 cvxpy"]
    mk2 = {("clean", 0.0): "o", ("outliers 1 %", 0.0): "s", ("clean", 0.05): "^", ("outliers 1 %", 0.05): "D"}
    for i, s in enumerate(solvers):
        for (case, fr), mk in mk2.items():
            pts = [r for r in id_rows if r["solver"] == s and r["case"] == case and r["friction"] == fr]
            ax2.loglog([1e3 * r["time_s"] for r in pts], [max(100 * r["err"], 1e-4) for r in pts], mk,
                       color=f"C{i}", mfc="none", label=s if (case, fr) == ("clean", 0.0) else None)
    ax2.set(xlabel="identification time (ms)", ylabel="worst relative error of m, b (%)",
            title="identification (o clean, s outliers, ^ Coulomb, D both)")
    ax2.legend(title="solver")
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
        # times labelled 1, 2, 5 per decade as plain numbers (matplotlib's minor labels ran together)
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
    fig.savefig(path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="shorter records (a smoke run)")
    ap.add_argument("--out", default=str(ROOT / "docs"), help="directory for the table and chart")
    args = ap.parse_args()
    t0 = time.perf_counter()
    speed = bench_etfe_speed(args.repeat)
    print(f"ETFE+effective impedances, 120k samples: {1e3 * speed['etfe_s']:.2f} ms; two real FFTs "
          f"{1e3 * speed['floor_s']:.2f} ms; ratio {speed['ratio']:.2f}x (goal <= 3x)")
    etfe_rows = bench_etfe(args.repeat, args.quick)
    for r in etfe_rows:
        print(f"etfe {r['ve']:13s} n={r['n']:6d} {r['noise']:22s} {r['estimator']:9s} "
              f"median {100 * r['median']:7.3f} % max {100 * r['max']:8.2f} % {1e3 * r['time_s']:7.1f} ms")
    id_rows = bench_identify(args.quick)
    for r in id_rows:
        print(f"id n={r['n']:6d} Fc={r['friction']:.2f} {r['case']:13s} {r['solver']:8s} "
              f"err {100 * r['err']:8.3f} % {1e3 * r['time_s']:8.1f} ms obj {r['obj_rel_vs_cvxpy']}")
    t1 = table1()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_docs(etfe_rows, speed, id_rows, t1, out / "analysis-bench.md", out / "analysis-bench.png")
    print(f"wrote {out / 'analysis-bench.md'} and {out / 'analysis-bench.png'} "
          f"in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
