"""``labbench sweep SPEC.toml``: every point of a sweep spec, one row each in a Parquet table.

Points already in the table are skipped, so a stopped sweep is resumed by running
it again; sweeps running at once into one table share its points. Progress and an
ETA go to stderr. The spec's charts are drawn beside the table (NAME.charts) when
the sweep is complete (docs/sweep.md).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from labbench.cli.progress import ProgressBar, clock_text
from labbench.errors import UserError
from labbench.readout.escape import one_line
from labbench.loop.interrupts import StopRequest, stopping

EXIT_STRICT = 3


def register(subparsers) -> None:
    p = subparsers.add_parser("sweep", help="run a sweep spec: many simulated runs, one table",
                              description=__doc__.splitlines()[0])
    p.add_argument("spec", metavar="SPEC.toml", help="the sweep spec (docs/sweep.md)")
    p.add_argument("--out", metavar="DIR", help="table folder (default sweeps/<spec name>.sweep)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="local Dask worker processes (default: one per CPU; 0: in this process)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask cluster's scheduler, e.g. tcp://10.0.0.5:8786")
    p.add_argument("--keep-sessions", metavar="DIR",
                   help="record every run's session in DIR (default: none kept)")
    p.add_argument("--flush-rows", type=int, default=64, metavar="N",
                   help="rows per part file written (default 64; at least every 10 s)")
    p.add_argument("--csv", metavar="FILE", help="also write the table as CSV")
    p.add_argument("--charts", metavar="DIR", help="folder of the spec's charts (default: "
                   "NAME.charts beside the table NAME.sweep)")
    p.add_argument("--chart", metavar="FILE", help="one more chart: a map of --x, --y [--color]")
    p.add_argument("--x", metavar="COLUMN", help="with --chart: the table column across")
    p.add_argument("--y", metavar="COLUMN", help="with --chart: the table column up")
    p.add_argument("--color", metavar="COLUMN", help="with --chart: the column that colours "
                   "the points (default: none)")
    p.add_argument("--force", action="store_true", help="replace existing CSV and chart files")
    p.add_argument("--repair", action="store_true", help="move damaged part files of the table "
                   "aside (NAME.sweep/_damaged) and compute their points again")
    p.add_argument("--strict", action="store_true",
                   help=f"exit {EXIT_STRICT} when a point failed (status not ok, or verdict failed)")
    p.add_argument("--json", action="store_true", help="print one JSON object: the summary")
    p.set_defaults(func=cmd_sweep)


class SweepProgress:
    """Points done, failures and the ETA on stderr: a bar on a terminal, else a line every
    ``interval_s`` (and the last one)."""

    def __init__(self, name: str, stream=None, interval_s: float = 10.0):
        self.stream = stream if stream is not None else sys.stderr
        self.bar = ProgressBar(f"sweep {name}", self.stream)
        self.interval_s, self._last = interval_s, -float("inf")
        self.name = name

    def __call__(self, p) -> None:
        text = f"{p.done}/{p.total} points, {p.failed} not ok"
        if p.waiting:
            text += f", waiting for {p.waiting} that other sweeps of the table compute"
        if self.bar.enabled:
            self.bar(p.done / max(p.total, 1), text)
            return
        now = time.monotonic()
        if now - self._last >= self.interval_s or p.done == p.total:
            self._last = now
            eta = "?" if p.eta_s is None else clock_text(p.eta_s)
            print(f"labbench sweep: {one_line(self.name)}: {text}, {clock_text(p.elapsed_s)} elapsed, "
                  f"ETA {eta}", file=self.stream, flush=True)

    def close(self) -> None:
        self.bar.close()


def cmd_sweep(args) -> int:
    from labbench.sweep import table
    from labbench.sweep.engine import run_sweep
    from labbench.sweep.spec import load_spec

    spec = load_spec(args.spec)
    if args.flush_rows < 1:
        raise UserError(f"--flush-rows must be at least 1, got {args.flush_rows}")
    if args.chart and not (args.x and args.y):
        raise UserError("--chart needs --x and --y")
    out = Path(args.out) if args.out else Path("sweeps") / f"{Path(args.spec).stem}{table.SUFFIX}"
    if not args.out:
        out.parent.mkdir(exist_ok=True)
    if spec.charts and not args.charts:  # before the work: the charts go there at the end
        from labbench.safe_write import usable_folder

        usable_folder(table.charts_folder(out))
    stop = StopRequest()
    progress = SweepProgress(spec.name)
    try:
        with stopping(stop):
            summary = run_sweep(spec, out, workers=args.workers, scheduler=args.scheduler,
                                keep_sessions=args.keep_sessions, progress=progress, stop=stop,
                                flush_rows=args.flush_rows, repair=args.repair)
    finally:
        progress.close()
    result = {"spec": args.spec, "table": str(summary.table), "points": summary.total,
              "already": summary.before, "computed": summary.computed,
              "not_ok": summary.failed, "workers": summary.workers,
              "wall_s": summary.wall_s, "stopped": summary.stopped, "charts": [],
              "repaired": [str(p) for p in summary.repaired], "error": summary.error}
    if summary.repaired:
        print(f"labbench sweep: {len(summary.repaired)} damaged part file"
              f"{'s' * (len(summary.repaired) > 1)} moved to {summary.repaired[0].parent}; "
              "their points were computed again", file=sys.stderr)
    tab = table.read_table(summary.table)
    if not summary.stopped and tab.num_rows:
        try:
            _charts_and_csv(args, spec, summary, tab, result)
        except UserError as exc:  # e.g. a full disk: the table is whole, the summary said
            result["error"] = str(exc)
    if result["error"]:
        print(f"labbench sweep: error: {result['error']}", file=sys.stderr)
    bad = _not_ok(tab)
    result["failed_points"] = bad
    if args.json:
        print(json.dumps(result, allow_nan=False))
    else:
        state = "stopped" if summary.stopped else "complete"
        print(f"sweep {one_line(spec.name)}: {state}, {summary.before + summary.computed}/"
              f"{summary.total} points in {one_line(summary.table)} ({summary.computed} computed now"
              + (f" on {summary.workers} workers" if summary.workers else " in this process")
              + f", {summary.failed} not ok, {summary.wall_s:.1f} s)")
        for path in result["charts"]:
            print(f"  chart {one_line(path)}")
        if "csv" in result:
            print(f"  csv {one_line(result['csv'])}")
        if summary.stopped:
            print("  run the same command again to compute the rest")
    if stop.exit_code:
        return stop.exit_code
    if result["error"]:
        return 2
    return EXIT_STRICT if args.strict and bad else 0


def _charts_and_csv(args, spec, summary, tab, result: dict) -> None:
    """The spec's charts (beside the table: Parquet readers take every file inside it for a
    part), the --chart map and the --csv table."""
    from labbench.safe_write import output_folder
    from labbench.sweep import charts, table

    default = table.charts_folder(summary.table)
    where = Path(args.charts) if args.charts else default
    wanted = [(c, where / charts.default_file(c, i)) for i, c in enumerate(spec.charts, 1)]
    if wanted and not args.charts:
        output_folder(default)
    if args.chart:
        extra = {"kind": "map", "x": args.x, "y": args.y,
                 **({"color": args.color} if args.color else {})}
        wanted.append((extra, Path(args.chart)))
    rows = charts.columns(tab) if wanted else {}  # as Python lists: only to draw
    for chart, path in wanted:
        charts.write(rows, chart, path, force=args.force or path.parent == default)
        result["charts"].append(str(path))
    if args.csv:
        result["csv"] = str(table.to_csv(summary.table, args.csv, force=args.force))


def _not_ok(tab) -> int:
    """Rows whose status is not ok or whose verdict is failed."""
    if not tab.num_rows:
        return 0
    status = tab["status"].to_pylist()
    verdict = tab["verdict"].to_pylist() if "verdict" in tab.column_names else [None] * len(status)
    return sum(s != "ok" or v == "failed" for s, v in zip(status, verdict))
