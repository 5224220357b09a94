"""Campaigns on every device the tests have: the five-point Z-width and rate vs accuracy.

`labbench campaign` (docs/campaign.md) with docs/examples/z-width.toml at w0 = 125 rad/s
and B = 0, 0.25, 0.5, 1, 2 N s/m on `sim`, `sim-canopen`, `avr-sim` (the reference
firmware on the emulated board, its rig docs/arduino/avr-sim.toml) and the CANopenNode
drive of the test suite (tests/canopennode: torque applied on arrival, and at the next
SYNC with the rig stating that period), each K_max against the exact sampled boundary of
that rig; then docs/examples/rate-vs-accuracy.toml (2-minute records) on `sim` and
`sim-canopen`. Writes docs/campaign-bench.md, docs/campaign-zwidth.png and
docs/campaign-rate.png, and prints the tables.

    .venv/bin/python bench/bench_campaign.py [--devices sim,sim-canopen,...] [--rate-s 120]
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
import tomllib
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the CANopenNode drive lives with the tests

from labbench.campaign.engine import run_campaign
from labbench.campaign.figures import write_figures
from labbench.campaign.plan import Context, is_simulator, make_plan
from labbench.rig import CampaignSettings
from labbench.cli.campaign import point_runner
from labbench.loop.interrupts import StopRequest
from labbench.readout.numfmt import fmt
from labbench.rig import load_rig, rig_from_dict
from labbench.sweep import table as tables
from labbench.sweep.spec import spec_from_dict

DEVICES = ("sim", "sim-canopen", "avr-sim", "canopennode-event", "canopennode-sync")
B_VALUES = [0.0, 0.25, 0.5, 1.0, 2.0]
# the drive's own monitors above a loaded machine's stalls, as the tests set them
CALM = {"canopen": {"heartbeat_consumer_ms": 2000, "rpdo_timeout_ms": 2000,
                    "life_time_factor": 100, "lockstep_timeout_s": 2.0, "sdo_timeout_s": 2.0},
        "safety": {"watchdog_s": 2.0}, "campaign": {"pause_s": 0.2}}


def spec(name: str, **changes) -> dict:
    d = tomllib.loads((ROOT / "docs" / "examples" / name).read_text())
    for table, values in changes.items():
        d[table] = values if table == "grid" else {**d.get(table, {}), **values}
    return d


def campaign(device: str, rig, d: dict, work: Path, lockstep: bool = False):
    """One campaign in ``work``: (summary, rows, wall seconds, a note on an interruption:
    stopped early, it is run again once, as a lab would)."""
    simulated = is_simulator(device)
    ctx = Context(device, rig, rig.nominal_plant, "nominal", simulated,
                  CampaignSettings.from_rig(rig, simulated), skip_commissioning=not simulated)
    plan = make_plan(spec_from_dict(d, source=d["sweep"]["name"]), ctx)
    (work / "s").mkdir(parents=True, exist_ok=True)
    args = argparse.Namespace(device=device, rig=None, out=str(work / "s"), realtime=False,
                               rt=None, rt_priority=None, port=None, can_log=None,
                               plant_from="nominal", skip_commissioning=not simulated)
    run_point = point_runner(args)
    if lockstep:  # the CANopen driver paces SYNC by default; the test drive runs lock-step
        inner = run_point

        def run_point(pp, *rest):
            return inner(replace(pp, device_options={**pp.device_options, "realtime": False}),
                         *rest)

    t0 = time.perf_counter()
    summary = run_campaign(plan, work / "t.sweep", run_point, StopRequest())
    note = ""
    if summary.interrupted:  # as a lab would: the same campaign again runs the rest
        note = f"stopped ({summary.interrupted}), then resumed: "
        summary = run_campaign(plan, work / "t.sweep", run_point, StopRequest())
        note += f"stopped again ({summary.interrupted})" if summary.interrupted else \
            f"{summary.ran} point(s) run, {summary.already} kept"
    return summary, tables.read_table(work / "t.sweep").to_pylist(), time.perf_counter() - t0, note


def zwidth_on(device: str, work: Path):
    d = spec("z-width.toml", fixed={"w0_rad_s": 125.0}, grid={"B": B_VALUES})
    if device.startswith("canopennode"):
        import canopennode

        variant = device.split("-")[1]
        tables_ = {**CALM, **({"rig": {"measured_td_s": 0.001}} if variant == "sync" else {})}
        running = canopennode.start(variant, tables_)
        try:
            return campaign("canopen", running.rig, d, work, lockstep=True)
        finally:
            running.close()
    rig = load_rig(ROOT / "docs" / "arduino" / "avr-sim.toml") if device == "avr-sim" else \
        rig_from_dict({})
    return campaign(device, rig, d, work)


def pct(v) -> str:
    return "-" if v is None else f"{100 * v:+.3f} %"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", default=",".join(DEVICES))
    ap.add_argument("--rate-s", type=float, default=120.0, help="ETFE record length [s]")
    ap.add_argument("--rate-devices", default="sim,sim-canopen")
    ap.add_argument("--out", default=str(ROOT / "docs" / "campaign-bench.md"),
                    help="the page written (default docs/campaign-bench.md)")
    args = ap.parse_args()
    lines = ["# Campaigns on every device: the Z-width and rate vs accuracy", "",
             "Generated by `bench/bench_campaign.py` (docs/campaign.md). Z-width: "
             "docs/examples/z-width.toml at w0 = 125 rad/s, B = 0-2 N s/m; measured = the "
             "stability probe's refined boundary with its 95 % interval; exact = the exact sampled "
             "boundary of that rig's plant (m = 0.094 kg, b = 0.1 N s/m) with its delay; device "
             "time = the samples the point ran x T (what it costs on a real device); wall = this "
             "shared 2-core machine's time.", ""]
    worst = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for device in [d for d in args.devices.split(",") if d]:
            summary, rows, wall, note = zwidth_on(device, tmp / device)
            if device == "sim-canopen":
                for f in write_figures(tmp / device / "t.sweep"):
                    shutil.copy(f, ROOT / "docs" / "campaign-zwidth.png")
            delay = rows[0].get("rig.device_delay_s") if rows else None
            lines += [f"## Z-width on {device} (device delay {fmt(1e3 * (delay or 0.0))} ms)", "",
                      "| B (N s/m) | measured K_max (N/m) | 95 % interval | exact (N/m) | "
                      "measured / exact - 1 | device time (s) | wall (s) | largest force (N) |",
                      "|---:|---:|---:|---:|---:|---:|---:|---:|"]
            for r in rows:
                lines.append(f"| {fmt(r['ve.B'])} | {fmt(r.get('zw.k_max'), 6)} | "
                             f"{fmt(r.get('zw.ci_lo'), 6)} to {fmt(r.get('zw.ci_hi'), 6)} | "
                             f"{fmt(r.get('pred.k_max'), 6)} | {pct(r.get('zw.rel_error'))} | "
                             f"{r.get('device_s', 0):.0f} | {r.get('wall_s', 0):.0f} | "
                             f"{fmt(r.get('max_command_n'))} |")
            for r in rows:  # a point without a boundary: its steps, to see why
                if r.get("zw.k_max") is None and r.get("session"):
                    shutil.copy(r["session"], Path(tempfile.gettempdir()) / Path(r["session"]).name)
                    print(f"no boundary at B = {r['ve.B']}: session kept in "
                          f"{tempfile.gettempdir()}", flush=True)
            errs = [abs(r["zw.rel_error"]) for r in rows if r.get("zw.rel_error") is not None]
            worst[device] = (max(errs) if len(errs) == len(rows) else None,
                             max(r.get("device_s", 0) for r in rows), summary.complete)
            lines += ["", f"Complete: {summary.complete}"
                      + (f" ({note})" if note else "")
                      + "; largest |error| "
                      f"{pct(worst[device][0])}; longest point {worst[device][1]:.0f} s of device "
                      f"time; campaign wall time {wall:.0f} s.", ""]
            print("\n".join(lines[-len(rows) - 6:]), flush=True)
        for device in [d for d in args.rate_devices.split(",") if d]:
            d = spec("rate-vs-accuracy.toml", fixed={"duration_s": args.rate_s})
            summary, rows, wall, note = campaign(device, rig_from_dict({}), d,
                                                 tmp / f"rate-{device}")
            if device == "sim-canopen":
                for f in write_figures(tmp / f"rate-{device}" / "t.sweep"):
                    shutil.copy(f, ROOT / "docs" / "campaign-rate.png")
            lines += [f"## Rate vs accuracy on {device} ({fmt(args.rate_s)} s records)", "",
                      "| T (ms) | ED error median meas. / pred. | ED max meas. / pred. | "
                      "ES error median meas. / pred. | in the 95 % band ED / ES | "
                      "w_s* meas. / pred. (rad/s) | w_b* meas. / pred. (rad/s) | "
                      "K_max fit / pred. (N/m) |", "|---:|---:|---:|---:|---:|---:|---:|---:|"]
            for r in rows:
                b = "res.bandwidths."
                lines.append(
                    f"| {fmt(1e3 * r['rig.sample_time_s'])} | {pct(r.get('acc.ed_median'))[1:]} / "
                    f"{pct(r.get('pred.ed_median'))[1:]} | {pct(r.get('acc.ed_max'))[1:]} / "
                    f"{pct(r.get('pred.ed_max'))[1:]} | {pct(r.get('acc.es_median'))[1:]} / "
                    f"{pct(r.get('pred.es_median'))[1:]} | {fmt(100 * r['acc.ed_in_band'], 3)} % / "
                    f"{fmt(100 * r['acc.es_in_band'], 3)} % | {fmt(r.get(b + 'ws_star_measured'))} / "
                    f"{fmt(r.get(b + 'ws_star_predicted'))} | {fmt(r.get(b + 'wb_star_measured'))} / "
                    f"{fmt(r.get(b + 'wb_star_predicted'))} | {fmt(r.get('acc.k_max_fit'))} / "
                    f"{fmt(r.get('pred.k_max'))} |")
            lines += ["", f"Campaign wall time {wall:.0f} s" + (f"; {note}" if note else "") + ".",
                      ""]
            print("\n".join(lines[-len(rows) - 5:]), flush=True)
    lines += ["## Summary", "", "| device | largest K_max error (abs.) | longest point (device s) |",
              "|---|---:|---:|"]
    lines += [f"| {d} | {pct(e)} | {s:.0f} |" for d, (e, s, _) in worst.items()]
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0 if all(e is not None and e < 0.01 and s <= 180 and c
                    for e, s, c in worst.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
