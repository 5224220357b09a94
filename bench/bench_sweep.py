"""labbench sweep on this machine: 2 workers against 1 on a 200-point sweep, and a 10 000-point
sweep in bounded memory, stopped and resumed without losing a row.

Throughput. The 200-point sweep docs/examples/etfe-near-k-max.toml (per point a
2-minute simulated ETFE run and its analysis, ~0.5 s) runs on a LocalCluster of 1
worker and of 2, alternated (1, 2 | 2, 1 | ...), each into a new table. A round's
ratio is its 1-worker wall time over its 2-worker one, cluster start and shutdown
included (what a user waits for). The machine is shared, so each arm also says what
it got: the CPU time of its processes (driver and workers, psutil) per wall second,
the CPU the rest of the machine used meanwhile (/proc/stat busy less ours), the time
the hypervisor stole and the load average. Since wall = CPU / cores got, a round's
ratio is (cores 2 workers got / cores 1 worker got) x (CPU of 1 worker / CPU of 2
workers for the same points): the first is the machine's, the second the sweep's;
2 x the second is the ratio with two free cores. The two arms' rows are compared too
(bit-identical, times aside).

Big sweep. 10 000 one-second ETFE runs (K x seed, ~0.1 s each) by the CLI on 2
workers, as a user runs it: SIGTERM once ~40 % of the rows are in the table, Ctrl-C
(SIGINT to the whole process group, as a terminal sends it) at ~75 %, then run to the
end. For each run: the rows it found and computed, and whether all it computed reached
the table; at the end the table's keys against the spec's, duplicates, and 20 rows
recomputed in this process against the table's (times aside). Memory: the peak resident
set (VmHWM) of the driver and of each worker process, and the driver's RSS at a quarter,
half, three quarters and the last of its run's rows (before the end: the stop, or the
compaction that reads the finished table).

Writes docs/sweep-bench.md, its numbers as docs/sweep-bench.json (a part not rerun,
--no-big or --no-throughput, keeps its numbers from there) and the spec's map,
docs/etfe-near-k-max.png.

    .venv/bin/python bench/bench_sweep.py [--rounds 2] [--big 10000] [--no-big] [--no-throughput]
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import pyarrow.parquet as pq

from labbench.sweep import charts
from labbench.sweep import table as tables
from labbench.sweep.engine import run_sweep
from labbench.sweep.point import TIME_COLUMNS, compute_row
from labbench.sweep.spec import load_spec

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "docs" / "examples" / "etfe-near-k-max.toml"
CORES = os.cpu_count() or 1
MB = 1 << 20
GOAL_RATIO = 1.8


# ----------------------------------------------------------------------------- measuring
def machine_cpu() -> tuple[float, float]:
    """(busy, stolen) CPU seconds of the whole machine since boot (/proc/stat)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:9]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = v
    tick = os.sysconf("SC_CLK_TCK")
    return (user + nice + system + irq + softirq) / tick, steal / tick


def vm_hwm(pid: int) -> int | None:
    """The peak resident set of a process so far (/proc/PID/status VmHWM), bytes."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


class Watch:
    """A process and its descendants sampled every ``period_s`` on a thread: CPU seconds
    (the last seen of each; the root's counted from the start), peak RSS of each, the
    root's RSS over time; and the machine's busy and stolen CPU over the whole watch."""

    def __init__(self, pid: int, period_s: float = 0.2):
        self.root = psutil.Process(pid)
        self.period_s = period_s
        self.cpu0: dict[int, float] = {}
        self.cpu: dict[int, float] = {}
        self.peak: dict[int, int] = {}
        self.root_rss: list[tuple[float, int]] = []
        self.loads: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="bench-watch", daemon=True)

    def __enter__(self):
        self.t0, self.machine0 = time.monotonic(), machine_cpu()
        self.sample(first=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(timeout=10)
        self.sample()
        self.wall = time.monotonic() - self.t0
        self.machine1 = machine_cpu()

    def _loop(self):
        while not self._stop.wait(self.period_s):
            self.sample()

    def sample(self, first: bool = False) -> None:
        self.loads.append(os.getloadavg()[0])
        try:
            procs = [self.root, *self.root.children(recursive=True)]
        except psutil.Error:
            return
        for p in procs:
            try:
                t = p.cpu_times()
                rss = p.memory_info().rss
            except psutil.Error:
                continue
            cpu = t.user + t.system
            self.cpu0.setdefault(p.pid, cpu if first else 0.0)
            self.cpu[p.pid] = cpu
            self.peak[p.pid] = max(self.peak.get(p.pid, 0), vm_hwm(p.pid) or rss)
            if p.pid == self.root.pid:
                self.root_rss.append((time.monotonic(), rss))

    @property
    def ours_s(self) -> float:
        return sum(self.cpu[p] - self.cpu0[p] for p in self.cpu)

    def cores(self) -> dict:
        """Cores' worth of CPU over the watch: ours, the other tenants', stolen; our CPU
        seconds and the mean 1-minute load average."""
        busy = self.machine1[0] - self.machine0[0]
        return {"ours": self.ours_s / self.wall, "cpu_s": self.ours_s,
                "others": max(busy - self.ours_s, 0.0) / self.wall,
                "stolen": (self.machine1[1] - self.machine0[1]) / self.wall,
                "load": float(np.mean(self.loads))}

    def worker_peak(self) -> int:
        return max((v for p, v in self.peak.items() if p != self.root.pid), default=0)


def rows_without_times(directory) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIME_COLUMNS}
            for r in tables.read_table(directory).to_pylist()]


# ----------------------------------------------------------------------------- throughput
def throughput(spec, rounds: int, tmp: Path) -> tuple[list[dict], Path]:
    arms = []
    last = None
    for r in range(rounds):
        for n in ((1, 2) if r % 2 == 0 else (2, 1)):
            out = tmp / f"round{r}-w{n}.sweep"
            with Watch(os.getpid()) as w:
                s = run_sweep(spec, out, workers=n)
            if s.computed != s.total or s.stopped:
                raise RuntimeError(f"{n} workers: {s.computed}/{s.total} points computed")
            arm = {"round": r, "workers": n, "wall": w.wall, "points": s.computed,
                   "not_ok": s.failed, "table": out, **w.cores()}
            arms.append(arm)
            print(f"round {r} {n} worker{'s' if n > 1 else ' '}: {w.wall:6.1f} s, "
                  f"{s.computed / w.wall:5.2f} points/s; cores: ours {arm['ours']:.2f}, others "
                  f"{arm['others']:.2f}, stolen {arm['stolen']:.2f}; load {arm['load']:.1f}",
                  flush=True)
            if n == 2:
                last = out
    return arms, last


def round_ratios(arms: list[dict]) -> list[dict]:
    out = []
    for r in sorted({a["round"] for a in arms}):
        one = next(a for a in arms if a["round"] == r and a["workers"] == 1)
        two = next(a for a in arms if a["round"] == r and a["workers"] == 2)
        cpu = one["cpu_s"] / two["cpu_s"]
        out.append({"round": r, "one": strip(one), "two": strip(two),
                    "ratio": one["wall"] / two["wall"], "got": two["ours"] / one["ours"],
                    "cpu": cpu, "free": 2 * cpu, "load": (one["load"] + two["load"]) / 2})
    return out


def strip(arm: dict) -> dict:
    return {k: v for k, v in arm.items() if k != "table"}


def near_k_max_answer(rows: list[dict], threshold: float = 0.05) -> str:
    """The map's answer in words: where the worst error crosses ``threshold``."""
    ok = [r for r in rows if r["status"] == "ok" and r.get("truth.max_rel") is not None]
    within = [r["K_frac_k_max"] for r in ok if r["truth.max_rel"] <= threshold]
    beyond = [r["K_frac_k_max"] for r in ok if r["truth.max_rel"] > threshold]
    if not beyond:
        return f"every point within {threshold:.0%}"
    return (f"{len(within)} of {len(ok)} points within {threshold:.0%}; every point with "
            f"K < {min(beyond):.2f} K_max is within it, every point above "
            f"{max(within):.2f} K_max exceeds it" if within else "no point within it")


# ----------------------------------------------------------------------------- big sweep
def big_spec_text(n: int) -> str:
    """``n`` (a multiple of 100) one-second ETFE runs: 100 stiffnesses x n/100 seeds."""
    ks = ", ".join(f"{k:.6g}" for k in np.geomspace(5.0, 500.0, 100))
    seeds = ", ".join(str(s) for s in range(1, n // 100 + 1))
    return (f'[sweep]\nname = "bench {n}"\nprotocol = "etfe"\n[fixed]\nduration_s = 1.0\n'
            f"[grid]\nK = [{ks}]\nseed = [{seeds}]\n")


class RowCount:
    """Rows in a table's parts, from each part's footer (a part is whole once it exists)."""

    def __init__(self, directory: Path):
        self.directory, self._known = directory, {}

    def __call__(self) -> int:
        n = 0
        for p in tables.parts(self.directory):
            if p.name not in self._known:
                try:
                    self._known[p.name] = pq.ParquetFile(p).metadata.num_rows
                except (OSError, ValueError):  # removed by a compaction meanwhile
                    continue
            n += self._known[p.name]
        return n


def cli_run(spec_path: Path, out: Path, total: int, stop_at: float | None, sig: int | None,
            group: bool, log: Path) -> dict:
    """One ``labbench sweep`` on 2 workers, stopped by ``sig`` once ``stop_at`` of ``total``
    rows are in the table (None: run to the end)."""
    cmd = [sys.executable, "-m", "labbench", "sweep", str(spec_path), "--out", str(out),
           "--workers", "2", "--json"]
    count = RowCount(out)
    trace = []
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True,
                                start_new_session=True, cwd=out.parent)
        try:
            with Watch(proc.pid, period_s=0.5) as w:
                sent = False
                while proc.poll() is None:
                    time.sleep(2.0)
                    n = count()
                    rss = w.root_rss[-1][1] if w.root_rss else 0
                    trace.append((n, rss))
                    if stop_at is not None and not sent and n >= stop_at * total:
                        (os.killpg if group else os.kill)(proc.pid, sig)
                        sent = True
                stdout = proc.communicate(timeout=600)[0]
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    summary = json.loads(stdout.strip().splitlines()[-1])
    rows = tables.read_table(out).num_rows
    return {"code": proc.returncode, "summary": summary, "rows_after": rows,
            "raw_rows": count(), "wall": w.wall, "driver_peak": w.peak.get(proc.pid, 0),
            "worker_peak": w.worker_peak(), "trace": trace, **w.cores()}


QUARTERS = (0.25, 0.5, 0.75)


def rss_milestones(trace: list[tuple[int, int]]) -> list[float]:
    """The driver's RSS [MB] when a quarter, half and three quarters of its run's rows were
    in, and at the last sample while rows still came (before the end's own work)."""
    n0, n1 = trace[0][0], trace[-1][0]
    steady = [(n, r) for n, r in trace if n < n1 and r]
    if not steady:
        return [float("nan")] * (len(QUARTERS) + 1)
    out = [next((r for n, r in steady if n >= n0 + q * (n1 - n0)), steady[-1][1]) / MB
           for q in QUARTERS]
    return out + [steady[-1][1] / MB]


def big(n: int, tmp: Path) -> dict:
    spec_path = tmp / "big.toml"
    spec_path.write_text(big_spec_text(n))
    spec = load_spec(spec_path)
    out = tmp / "big.sweep"
    runs = []
    plan = (("SIGTERM", 0.4, signal.SIGTERM, False), ("Ctrl-C to the group", 0.75, signal.SIGINT,
                                                        True), ("to the end", None, None, False))
    for how, at, sig, group in plan:
        r = cli_run(spec_path, out, n, at, sig, group, tmp / f"big-{len(runs)}.log")
        r["how"] = how
        s = r["summary"]
        r["rss"] = rss_milestones(r.pop("trace"))
        print(f"big sweep, {how}: exit {r['code']}, found {s['already']}, computed "
              f"{s['computed']}, table {r['rows_after']} rows ({r['raw_rows']} in parts), "
              f"{r['wall']:.0f} s; peak RSS driver {r['driver_peak'] / MB:.0f} MB, worker "
              f"{r['worker_peak'] / MB:.0f} MB; driver RSS at 1/4, 1/2, 3/4, last of its rows "
              f"{' '.join(f'{x:.0f}' for x in r['rss'])} MB; cores ours {r['ours']:.2f} "
              f"others {r['others']:.2f}", flush=True)
        runs.append(r)
    keys = {p.key(spec) for p in spec.points()}
    final = tables.read_table(out)
    got = final["key"].to_pylist()
    sample = random.Random(0).sample(range(final.num_rows), 20)
    d = spec.as_dict()
    rows = final.to_pylist()
    same, differ = 0, set()
    for i in sample:
        r = rows[i]
        again = compute_row(d, {"index": r["index"], **json.loads(r["params_json"])})
        cols = {k for k, v in r.items() if k not in TIME_COLUMNS and again.get(k) != v}
        same += not cols
        differ |= cols
    statuses = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    return {"n": n, "runs": runs, "rows": final.num_rows, "unique": len(set(got)),
            "missing": len(keys - set(got)), "extra": len(set(got) - keys), "same": same,
            "sampled": len(sample), "differ": sorted(differ), "statuses": statuses,
            "lost": [r["summary"]["already"] + r["summary"]["computed"] - r["rows_after"]
                     for r in runs]}


# ----------------------------------------------------------------------------- the page
def write_docs(res: dict, path_md: Path) -> None:
    t, b = res.get("throughput"), res.get("big")
    lines = ["# labbench sweep on this machine (generated by bench/bench_sweep.py)", "",
             f"A shared {CORES}-core virtual machine: other engineers' work runs beside every "
             "measurement, so each arm says how many cores' worth of CPU the sweep's processes "
             "got (driver and workers), what the rest of the machine used, what the "
             "hypervisor stole, and the mean 1-minute load average.", ""]
    if t:
        rounds = t["rounds"]
        lines += [f"## Throughput: 200 points of `docs/examples/etfe-near-k-max.toml` "
                  f"({t['date']}, at {t.get('commit', '?')})", "",
                  "Each point a 2-minute simulated ETFE run and its analysis; a LocalCluster "
                  "of 1 worker against 2, alternated, cluster start and shutdown included. "
                  "Wall time = CPU / cores got, so the ratio is (cores 2 workers got / cores 1 "
                  "got) x (CPU 1 worker spent / CPU 2 spent): the machine's part and the "
                  "sweep's. 'two free cores' is 2 x the CPU ratio: the ratio if 2 workers got "
                  "twice the CPU of 1.", "",
                  "| round | 1 worker s | 2 workers s | **ratio** | cores got 1 / 2 | got ratio "
                  "| CPU s 1 / 2 | two free cores | others' cores | stolen | load |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in rounds:
            one, two = r["one"], r["two"]
            lines.append(f"| {r['round']} | {one['wall']:.1f} | {two['wall']:.1f} | "
                         f"**{r['ratio']:.2f}x** | {one['ours']:.2f} / {two['ours']:.2f} | "
                         f"{r['got']:.2f}x | {one['cpu_s']:.0f} / {two['cpu_s']:.0f} | "
                         f"{r['free']:.2f}x | {(one['others'] + two['others']) / 2:.2f} | "
                         f"{(one['stolen'] + two['stolen']) / 2:.2f} | {r['load']:.1f} |")

        def span(key, fmt="{:.2f}"):
            lo, hi = min(r[key] for r in rounds), max(r[key] for r in rounds)
            return fmt.format(lo) if fmt.format(lo) == fmt.format(hi) else \
                f"{fmt.format(lo)}-{fmt.format(hi)}"

        lines += ["", f"Goal: >= {GOAL_RATIO}x. Measured {span('ratio')}x at a load average "
                  f"of {span('load', '{:.1f}')}: the machine gave 2 workers {span('got')}x the "
                  f"CPU of 1; with two free cores {span('free')}x. Rows of every table "
                  f"bit-identical (times aside): {'yes' if t['identical'] else 'NO'}.", "",
                  f"The sweep's answer (its rows and map at {t.get('answer_at', t.get('commit', '?'))})"
                  f": {t['answer']}.", "",
                  "![ETFE near K_max: worst error of Z over 2-100 rad/s](etfe-near-k-max.png)",
                  ""]
    if b:
        lines += [f"## {b['n']} points, stopped twice and resumed ({b['date']}, at "
                  f"{b.get('commit', '?')})", "",
                  "One-second ETFE runs (100 stiffnesses x seeds) by `labbench sweep --workers 2`."
                  " Peak RSS is each process's VmHWM (for a complete run it includes the end: "
                  "the compaction reads the finished table); the driver's RSS is read when a "
                  "quarter, half, three quarters and the last of its run's rows were in.", "",
                  "| run | exit | rows found | computed | rows in table after | lost | wall s "
                  "| peak RSS driver MB | peak RSS worker MB | driver RSS MB at 1/4, 1/2, 3/4, "
                  "last |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
        for r, lost in zip(b["runs"], b["lost"]):
            s = r["summary"]
            lines.append(f"| {r['how']} | {r['code']} | {s['already']} | {s['computed']} | "
                         f"{r['rows_after']} | {lost} | {r['wall']:.0f} | "
                         f"{r['driver_peak'] / MB:.0f} | {r['worker_peak'] / MB:.0f} | "
                         f"{', '.join(f'{x:.0f}' for x in r['rss'])} |")
        lines += ["", f"Final table: {b['rows']} rows, {b['unique']} distinct keys, "
                  f"{b['missing']} of the spec's keys missing, {b['extra']} not the spec's; "
                  f"statuses {b['statuses']}; {b['same']} of {b['sampled']} rows recomputed in "
                  "one process equal the table's (times aside; columns differing: "
                  f"{', '.join(b.get('differ', [])) or 'none'}).", ""]
    path_md.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2, help="throughput rounds (1 and 2 workers)")
    ap.add_argument("--big", type=int, default=10_000, help="points of the big sweep (x100)")
    ap.add_argument("--no-big", action="store_true")
    ap.add_argument("--no-throughput", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "docs"), help="folder of the page and chart")
    args = ap.parse_args()
    if args.big % 100 or args.big < 100:
        ap.error("--big must be a multiple of 100")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    saved = out / "sweep-bench.json"
    res = json.loads(saved.read_text()) if saved.is_file() else {}
    spec = load_spec(SPEC)
    today = time.strftime("%Y-%m-%d")
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True, timeout=30).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if not args.no_throughput:
            arms, last = throughput(spec, args.rounds, tmp)
            first = rows_without_times(arms[0]["table"])
            identical = all(rows_without_times(a["table"]) == first for a in arms[1:])
            cols = charts.columns(tables.read_table(last))
            charts.write(cols, spec.charts[0], out / spec.charts[0]["file"], force=True)
            res["throughput"] = t = {"date": today, "commit": commit, "rounds": round_ratios(arms),
                                     "identical": identical,
                                     "answer": near_k_max_answer(tables.read_table(last)
                                                                 .to_pylist())}
            for r in t["rounds"]:
                print(f"round {r['round']}: 2 workers / 1 = {r['ratio']:.2f}x (goal >= "
                      f"{GOAL_RATIO}x) = cores got {r['got']:.2f}x (load {r['load']:.1f}) x "
                      f"CPU per point {r['cpu']:.2f}; with 2 free cores {r['free']:.2f}x")
            print(f"rows identical on 1 and 2 workers (times aside): {identical}")
            print(f"answer: {t['answer']}")
            save(res, out)
        if not args.no_big:
            res["big"] = b = {"date": today, "commit": commit, **big(args.big, tmp)}
            print(f"big sweep: {b['rows']} rows, {b['unique']} keys, missing {b['missing']}, "
                  f"lost at the stops {b['lost']}, recomputed equal {b['same']}/{b['sampled']} "
                  f"(columns differing: {b['differ'] or 'none'}), "
                  f"statuses {b['statuses']}")
    save(res, out)
    return 0


def save(res: dict, out: Path) -> None:
    """The numbers so far and their page (a part done survives a later part's failure)."""
    (out / "sweep-bench.json").write_text(json.dumps(res, indent=1))
    write_docs(res, out / "sweep-bench.md")
    print(f"wrote {out / 'sweep-bench.md'} and {out / 'sweep-bench.json'}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
