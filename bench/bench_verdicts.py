"""Do the verdicts cry wolf, and do they stay silent? (issue 30) The false-alarm rate beside the
silent failures, on known truth, with the definitions of ``bench/bench_coverage.py``
(a result is within target when its numbers lie within their fixed accuracy targets, issue
24's; it misleads when they lie beyond both the targets and their own 99.9 % intervals,
``labbench.readout.verdict.holds``; ETFE: a frequency in 2-100 rad/s beyond 1 % of |Z| and its band's
1 - 1e-6 tail misleads, none within; a sweep or run row: its worst error against the exact
sampled theory over 2-100 rad/s within 5 %, the spec's own failure line, or not). A false
alarm is a result within target whose verdict is not ``ok``; a silent failure, a misleading
one said ``ok``.

Sources:

* ``grid``: the method-map grid (bench_coverage's id, ETFE and loop-fit cells, ``--seeds``);
* ``sweep``: the shipped ETFE sweep docs/examples/etfe-near-k-max.toml, ``--points`` new
  points (the issue's 60 of 60 "doubtful");
* ``runs``: ``labbench run etfe`` as a technician runs it: the demo's ETFE (K = 50), K = 200 for
  30 and 120 s, and 20 s records at T = 0.5, 2 and 4 ms on sim, sim-canopen and sim-serial.

Writes docs/verdicts-bench.md.

    .venv/bin/python bench/bench_verdicts.py [--seeds 20] [--points 60] [--jobs 2] [--only grid,sweep,runs]
        [--grid-rows FILE]   # the grid as bench_coverage.py --save-rows FILE left it
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))

import bench_coverage as grid  # noqa: E402

SWEEP = ROOT / "docs" / "examples" / "etfe-near-k-max.toml"
ROW_TARGET = 0.05  # worst |dZ| / |Z| over 2-100 rad/s that a sweep row or a run may show


def _tally(rows) -> dict:
    """rows: (within target, misleads, level, reasons) -> counts."""
    held = [r for r in rows if r[0]]
    return {"results": len(rows), "hold": len(held),
            "false_alarms": sum(r[2] != "ok" for r in held),
            "silent": sum(r[1] and r[2] == "ok" for r in rows),
            "reasons": Counter(w for r in held if r[2] != "ok" for w in r[3])}


def grid_rows(seeds: int, jobs: int, saved: str | None = None) -> list:
    """The grid's results: run here, or ``saved`` by ``bench_coverage.py --save-rows`` (one
    run of the grid for both documents)."""
    if saved:
        results = json.loads(Path(saved).read_text())
    else:
        tasks = grid.id_tasks(seeds) + grid.etfe_tasks(seeds, quick=False) + grid.loop_tasks(max(seeds * 3 // 5, 3))
        results = grid._run(tasks, jobs)
    out = []
    for r in results:
        if "far" in r:
            out.append((not r["far"], r["far"], r["level"], r["why"]))
        else:
            out.append((not r["beyond"], bool(r["miss"]), r["level"], r["why"]))
    return out


def sweep_rows(points: int) -> list:
    from labbench.sweep import table
    from labbench.sweep.engine import run_sweep
    from labbench.sweep.spec import load_spec, spec_from_dict

    d = load_spec(SWEEP).as_dict()
    d["sweep"]["points"] = points
    d["sweep"]["sample_seed"] = 1234  # points the shipped table does not hold
    d.pop("chart", None)
    with tempfile.TemporaryDirectory() as tmp:
        s = run_sweep(spec_from_dict(d, source="etfe-near-k-max (new points)"), Path(tmp) / "v.sweep", workers=0)
        rows = table.read_table(s.table).to_pylist()
    out = []
    for r in rows:
        within = r["truth.max_rel"] is not None and r["truth.max_rel"] <= ROW_TARGET
        out.append((within, not within, r["verdict"] or "ok", grid._why_text(r["verdict_reasons"] or "")))
    return out


RUNS = [  # (label, device, sample time, argv)
    ("demo ETFE K 50, 120 s", "sim", 0.001, ["--K", "50", "--B", "1", "--duration-s", "120"]),
    ("K 200, 30 s", "sim", 0.001, ["--K", "200", "--B", "1", "--duration-s", "30"]),
    ("K 200, 120 s", "sim", 0.001, ["--K", "200", "--B", "1", "--duration-s", "120"]),
    *[(f"K 50, 20 s, T {1e3 * T:g} ms, {dev}", dev, T, ["--K", "50", "--B", "1", "--duration-s", "20"])
      for dev in ("sim", "sim-canopen", "sim-serial") for T in (0.0005, 0.002, 0.004)],
]


def run_rows(out_dir: Path) -> list:
    rows = []
    for label, dev, T, argv in RUNS:
        rig = out_dir / f"T{T}.toml"
        rig.write_text(f"[rig]\nsample_time_s = {T}\n")
        cmd = [sys.executable, "-m", "labbench", "run", "etfe", "--device", dev, "--rig", str(rig),
               "--seed", "7", "--out", str(out_dir / "sessions"), "--json", *argv]
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        if p.returncode != 0:
            print(f"  {label}: exit {p.returncode}: {p.stderr.strip().splitlines()[-1:]}", flush=True)
            continue
        d = json.loads(p.stdout)
        dev_max = d["results"]["deviation_vs_sampled"]["max_rel"]
        verdicts = d["readout"]["verdicts"]
        level = max((v["level"] for v in verdicts), key=("ok", "doubtful", "failed").index)
        why = [r.split(":")[0] for v in verdicts for r in v["reasons"]]
        within = dev_max is not None and dev_max <= ROW_TARGET
        rows.append((within, not within, level, why))
        print(f"  {label}: max error {100 * dev_max:.3g} %, {level} {why or ''}", flush=True)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--points", type=int, default=60)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--only", default="grid,sweep,runs")
    ap.add_argument("--grid-rows", metavar="FILE", help="the grid's results saved by bench_coverage.py "
                    "--save-rows (else the grid runs here)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "verdicts-bench.md"))
    args = ap.parse_args()
    t0 = time.perf_counter()
    parts = {}
    for part in args.only.split(","):
        t1 = time.perf_counter()
        if part == "grid":
            rows = grid_rows(args.seeds, args.jobs, args.grid_rows)
        elif part == "sweep":
            rows = sweep_rows(args.points)
        elif part == "runs":
            with tempfile.TemporaryDirectory() as tmp:
                rows = run_rows(Path(tmp))
        else:
            raise SystemExit(f"unknown part {part!r}: grid, sweep or runs")
        parts[part] = _tally(rows)
        print(f"{part}: {parts[part]} ({time.perf_counter() - t1:.0f} s)", flush=True)
    lines = ["# Verdicts: false alarms and silent failures (generated by bench/bench_verdicts.py)", "",
             f"Definitions: the bench's module doc. {time.perf_counter() - t0:.0f} s; grid "
             + ("as bench_coverage.py left it (--grid-rows; its seeds: docs/method-map-tables.md)"
                if args.grid_rows else f"seeds {args.seeds}") + f", sweep points {args.points}.", "",
             "| source | results | within target | ok among those | false alarms | silent failures | "
             "false alarms' reasons |", "|---|---|---|---|---|---|---|"]
    total = Counter()
    for part, t in parts.items():
        total.update({k: t[k] for k in ("results", "hold", "false_alarms", "silent")})
        ok = t["hold"] - t["false_alarms"]
        reasons = "; ".join(f"{k} ({v})" for k, v in t["reasons"].most_common(4)) or "-"
        lines.append(f"| {part} | {t['results']} | {t['hold']} | {ok} ({100 * ok / max(t['hold'], 1):.1f} %) | "
                     f"{t['false_alarms']} | {t['silent']} | {reasons} |")
    ok = total["hold"] - total["false_alarms"]
    lines.append(f"| **all** | {total['results']} | {total['hold']} | **{ok} ({100 * ok / max(total['hold'], 1):.1f} %)** "
                 f"| {total['false_alarms']} | **{total['silent']}** | |")
    Path(args.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
