"""``labbench campaign SPEC.toml --device DEV``: a sweep spec's points run one after another on
one device (real or simulated), each as ``labbench run`` runs it, one row each in a table.

The plan is checked whole before anything moves (settings, the commissioning gate, the
pre-check of every point); on real hardware it is printed (points, estimated time, the
largest force and stiffness commanded) and the operator asked once (``--yes`` for
scripts), and ``--confirm`` asks before each point. Force zero and the rig's
``[campaign] pause_s`` between points. Ctrl-C, SIGTERM, a closed terminal or a device
fault end the campaign with the finished points kept; the same command again runs the
rest (the interrupted point again, no finished one twice). docs/campaign.md.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from labbench.cli.progress import ProgressBar, clock_text, warner
from labbench.errors import UserError
from labbench.readout.escape import one_line
from labbench.readout.numfmt import fmt
from labbench.loop.interrupts import StopRequest, stopping

EXIT_STRICT = 3
_warn = warner("campaign")


def register(subparsers) -> None:
    from labbench.registry import device_names

    p = subparsers.add_parser("campaign", help="run a sweep spec's points on one device, "
                              "one after another, resumable", description=__doc__.splitlines()[0])
    p.add_argument("spec", metavar="SPEC.toml", help="the spec (docs/campaign.md, docs/sweep.md)")
    p.add_argument("--device", choices=device_names(), required=True, help="the device")
    p.add_argument("--rig", metavar="FILE", help="rig TOML file (default: simulated Phantom-like)")
    p.add_argument("--table", metavar="DIR",
                   help="table folder (default campaigns/<spec>-<device>.sweep)")
    p.add_argument("--out", metavar="DIR", default="sessions",
                   help="session directory, one session per point (./sessions); also where the "
                        "rig's last chirp-ID and commissioning are looked for")
    p.add_argument("--plant-from", choices=("last-id", "nominal"), default="last-id",
                   help="plant of the pre-checks and predictions: the rig's newest chirp-ID in "
                        "--out (default), else its nominal; or always the nominal")
    p.add_argument("--plant-m-kg", type=float, metavar="M", help="plant mass (with --plant-b)")
    p.add_argument("--plant-b", type=float, metavar="B", help="plant damping [N s/m]")
    p.add_argument("--yes", action="store_true",
                   help="real hardware: start without asking (the plan is still printed)")
    p.add_argument("--confirm", action="store_true", help="ask before each point")
    p.add_argument("--realtime", action="store_true", help="pace a simulator in real time")
    p.add_argument("--no-rt", dest="rt", action="store_false", default=None,
                   help="do not ask for real-time scheduling")
    p.add_argument("--rt-priority", type=int, metavar="N", help="SCHED_FIFO priority (default 80)")
    p.add_argument("--port", metavar="PORT", help="with --device serial: the serial port")
    p.add_argument("--skip-commissioning", action="store_true",
                   help="render springs and dampers on real hardware before the rig passed "
                        "`labbench run commission`")
    p.add_argument("--report", action="store_true",
                   help="when complete, write the campaign's report (HTML and PDF) in the table")
    p.add_argument("--repair", action="store_true", help="move damaged part files of the "
                   "table aside (NAME.sweep/_damaged) and run their points again on the device")
    p.add_argument("--strict", action="store_true",
                   help=f"exit {EXIT_STRICT} when a point's status is not ok (skipped by the "
                        "pre-check and refused included)")
    p.add_argument("--json", action="store_true", help="print one JSON object: the summary")
    p.set_defaults(func=cmd_campaign)


def cmd_campaign(args) -> int:
    from labbench.campaign.engine import CampaignTable
    from labbench.campaign.plan import make_plan
    from labbench.sweep import table as tables
    from labbench.sweep.spec import load_spec

    spec = load_spec(args.spec)
    context = make_context(args)
    plan = make_plan(spec, context)
    out = Path(args.table) if args.table else (
        Path("campaigns") / f"{Path(args.spec).stem}-{args.device}{tables.SUFFIX}")
    if not args.table:
        out.parent.mkdir(exist_ok=True)
    asking = not context.simulated and not args.yes
    if asking and not (sys.stdin and sys.stdin.isatty()):
        raise UserError(f"{args.device} is real hardware and stdin is not a terminal to ask "
                        "on: give --yes to start without asking (the plan is printed)")
    stop = StopRequest()
    progress = CampaignProgress(spec.name)
    confirm = _confirm if args.confirm else None
    try:
        with CampaignTable(plan, out, args.repair, progress, _warn) as table:
            print_plan(plan, out, table.index)
            if asking:
                ask(f"start on {args.device} (real hardware)?")
            with stopping(stop):
                summary = table.run(point_runner(args), stop, progress, confirm)
    finally:
        progress.close()
    result = summary.as_dict()
    result["charts"] = []
    if summary.repaired:
        _warn(f"{len(summary.repaired)} damaged part file{'s' * (len(summary.repaired) > 1)} "
              f"moved to {summary.repaired[0].parent}; their points ran again")
    tab = tables.read_table(out)
    if summary.complete:
        result["charts"] = [str(p) for p in write_charts(spec, out)]
        if args.report:
            from labbench.campaign.report import write_campaign_report

            html, pdf = write_campaign_report(out)
            result["report"] = {"html": str(html), "pdf": str(pdf)}
    result["not_ok_in_table"] = _not_ok(tab)
    print_summary(args, spec, summary, result)
    if summary.exit_code:
        return summary.exit_code
    if summary.interrupted:
        return 1
    return EXIT_STRICT if args.strict and result["not_ok_in_table"] else 0


def _not_ok(tab) -> int:
    """Rows of the table whose status is not ok (skipped and refused ones included)."""
    return sum(s != "ok" for s in tab["status"].to_pylist()) if tab.num_rows else 0


def make_context(args):
    """The campaign's device, rig, plant and commissioning facts (``labbench.campaign.plan.Context``)."""
    from labbench.campaign.plan import Context, commission_facts, is_simulator
    from labbench.rig import CampaignSettings
    from labbench.rig import load_rig
    from labbench.sessions.session_catalogue import last_identified
    from labbench.model.ve import Plant

    rig = load_rig(args.rig)
    simulated = is_simulator(args.device)

    def skipped(path, reason):
        print(f"labbench campaign: warning: skipped {path}: {reason}", file=sys.stderr)

    if (args.plant_m_kg is None) != (args.plant_b is None):
        raise UserError("give --plant-m-kg and --plant-b together")
    found = None
    if args.plant_m_kg is not None:
        plant, source = Plant(args.plant_m_kg, args.plant_b), "given"
    else:
        found = last_identified(args.out, rig.name, on_skip=skipped) \
            if args.plant_from == "last-id" else None
        plant = Plant(found["m"], found["b"]) if found else rig.nominal_plant
        source = str(found["session"]) if found else "nominal"
    commission = commission_facts(args.out, rig.name, on_skip=skipped)
    return Context(args.device, rig, plant, source, simulated,
                   CampaignSettings.from_rig(rig, simulated), commission,
                   args.skip_commissioning, found.get("coulomb_n") if found else None)


def point_runner(args):
    """Each point through ``labbench run``'s own path (``labbench.cli.run._run_one``)."""
    from labbench.cli.run import _run_one

    def run_point(pp, stop, progress, consumers):
        ns = argparse.Namespace(**{**vars(args), "protocol": pp.protocol_name, "can_log": None,
                                   "plant_from": "nominal"})
        return _run_one(ns, pp.rig, pp.protocol_name, dict(pp.options), stop, progress=progress,
                        consumers=consumers, device_options=pp.device_options,
                        plant_from=pp.plant_from)

    return run_point


def print_plan(plan, out: Path, done) -> None:
    """On real hardware the whole plan (every point planned, the progress said every 2 s:
    ``labbench.campaign.plan.describe``; ``done``: the keys in the table); on a simulator
    its first line (the points are planned as they run, the progress says the rest)."""
    from labbench.campaign.plan import describe

    c = plan.context
    if c.simulated:
        lines = [f"campaign {one_line(plan.spec.name)} on {c.device} (simulator), rig "
                 f"{one_line(repr(c.rig.name))}: {plan.spec.count()} points into "
                 f"{one_line(out)}; plant m = {fmt(c.plant.m)} kg, b = {fmt(c.plant.b)} N s/m "
                 f"({one_line(c.plant_label)})"]
    else:
        lines = describe(plan, done, out, PlanProgress())
    for line in lines:
        print(f"labbench campaign: {line}", file=sys.stderr)


class PlanProgress:
    """``planning: n/N points checked`` on stderr every 2 s while a plan is made whole."""

    def __init__(self, stream=None, interval_s: float = 2.0):
        self.stream = stream if stream is not None else sys.stderr
        self.interval_s, self.t0 = interval_s, time.monotonic()
        self._last = self.t0

    def __call__(self, n: int, total: int) -> None:
        now = time.monotonic()
        if now - self._last >= self.interval_s:
            self._last = now
            print(f"labbench campaign: planning: {n}/{total} points checked "
                  f"({100 * n / max(total, 1):.1f} %), {clock_text(now - self.t0)} elapsed",
                  file=self.stream, flush=True)


def ask(question: str) -> None:
    """One yes from the operator (on the terminal), or UserError."""
    print(f"labbench campaign: {question} [y/N] ", end="", file=sys.stderr, flush=True)
    if sys.stdin.readline().strip().lower() not in ("y", "yes"):
        raise UserError("not started: the operator said no")


def _confirm(pp) -> bool:
    print(f"labbench campaign: run {pp.label}? [y/N] ", end="", file=sys.stderr, flush=True)
    return sys.stdin.readline().strip().lower() in ("y", "yes")


class CampaignProgress:
    """Points done, the running point and the ETA: a bar on a terminal, else a line per point."""

    def __init__(self, name: str, stream=None):
        self.stream = stream if stream is not None else sys.stderr
        self.bar = ProgressBar(f"campaign {name}", self.stream)

    def __call__(self, p) -> None:
        point = one_line(p.point) if p.point else p.message
        if self.bar.enabled:
            self.bar((p.done + p.fraction) / max(p.total, 1), f"{p.done}/{p.total} {point}")
        elif p.phase != "run":
            eta = "?" if p.eta_s is None else clock_text(p.eta_s)
            what = f"{point}: {p.message}" if p.point else p.message
            print(f"labbench campaign: {p.done}/{p.total} points, {what}, "
                  f"{clock_text(p.elapsed_s)} elapsed, ETA {eta}", file=self.stream, flush=True)

    def close(self) -> None:
        self.bar.close()


def write_charts(spec, out: Path) -> list[Path]:
    """The campaign's own figures (``labbench.campaign.figures``: the Z-width, rate vs
    accuracy) and the spec's charts (as ``labbench sweep`` draws them) into the table's
    charts folder beside it, replacing its earlier ones."""
    from labbench.campaign.figures import write_figures
    from labbench.sweep import charts, table as tables

    written = write_figures(out)
    tab = tables.read_table(out)
    if not spec.charts or not tab.num_rows:
        return written
    cols = charts.columns(tab)
    from labbench.safe_write import output_folder

    where = output_folder(tables.charts_folder(out))
    return written + [charts.write(cols, c, where / charts.default_file(c, i), force=True)
                      for i, c in enumerate(spec.charts, 1)]


def print_summary(args, spec, summary, result: dict) -> None:
    if args.json:
        print(json.dumps(result, allow_nan=False))
        return
    state = "complete" if summary.complete else f"stopped ({one_line(summary.interrupted)})"
    others = f", {summary.by_others} by another campaign" if summary.by_others else ""
    print(f"campaign {one_line(spec.name)}: {state}; {summary.ran} run now in "
          f"{one_line(summary.table)} of {summary.total} points ({summary.already} there before"
          f"{others}; {summary.rerun} run again after an interruption, {summary.skipped} "
          f"skipped, {summary.refused} refused, {summary.not_ok} not ok, "
          f"{summary.wall_s:.1f} s)")
    for path in result["charts"]:
        print(f"  chart {one_line(path)}")
    if "report" in result:
        print(f"  report {one_line(result['report']['html'])}  {one_line(result['report']['pdf'])}")
    if not summary.complete:
        print("  run the same command again to run the rest")
    sys.stdout.flush()
