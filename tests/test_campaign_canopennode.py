"""Campaigns on the CANopenNode drive (tests/canopennode): the real driver, the real C stack
in a process of its own, lock-step; the plant behind it is the exact one.

The drive is real hardware as far as a campaign knows (``canopen``): the commissioning gate
applies (skipped, as an operator who knows the rig would), its safety watchdog is the
hardware's (set to 2 s in the rig: a lock-step drive on a shared machine), the pause
between points the rig's.
"""
from dataclasses import replace

import pytest

from labbench.campaign import engine
from labbench.campaign.plan import Context, make_plan
from labbench.rig import CampaignSettings
from labbench.cli.campaign import point_runner
from labbench.loop.interrupts import StopRequest
from labbench.sweep import table as tables
from labbench.sweep.spec import spec_from_dict
from test_campaign import args_for, sessions_by_status
from test_canopennode import drive, no_process_left, stack  # noqa: F401 - fixtures

# the hardware watchdog above a loaded machine's stalls; a short pause between points
TABLES = {"safety": {"watchdog_s": 2.0}, "campaign": {"pause_s": 0.2}}


def campaign(r, spec: dict, tmp_path, stop=None, progress=None):
    ctx = Context("canopen", r.rig, r.rig.nominal_plant, "nominal", False,
                  CampaignSettings.from_rig(r.rig), skip_commissioning=True)
    plan = make_plan(spec_from_dict(spec), ctx)
    (tmp_path / "s").mkdir(exist_ok=True)
    args = args_for(tmp_path / "s", "canopen", skip_commissioning=True)
    run_point = point_runner(args)

    def lockstep(pp, *rest):  # SYNC when the loop asks (the driver's default is paced)
        return run_point(replace(pp, device_options={**pp.device_options, "realtime": False}),
                         *rest)

    summary = engine.run_campaign(plan, tmp_path / "t.sweep", lockstep, stop or StopRequest(),
                                  progress=progress)
    return summary, tables.read_table(tmp_path / "t.sweep").to_pylist()


def test_a_drive_fault_mid_point_ends_the_campaign_and_the_rerun_finishes_it(drive, tmp_path):
    """An over-current fault (EMCY 0x2310) injected into the drive 30 % into the second point:
    the run fails on the device, the campaign ends with one row and names the failed
    session; the operator resets the drive, the same campaign again runs points 2 and 3:
    3 rows, 0 lost, 0 run twice, point 2 with 2 attempts."""
    r = drive(tables=TABLES)
    spec = {"sweep": {"name": "fault", "protocol": "etfe"},
            "fixed": {"ve": "spring", "duration_s": 2.0, "seed": 4},
            "grid": {"K": [10.0, 20.0, 30.0]}}
    injected = []

    def progress(p):
        if p.done == 1 and p.phase == "run" and p.fraction > 0.3 and not injected:
            injected.append(p.fraction)
            r.inject_fault(0x2310)

    summary, rows = campaign(r, spec, tmp_path, progress=progress)
    assert injected and summary.ran == 1 and len(rows) == 1, summary.interrupted
    assert "fault" in summary.interrupted and "0x2310" in summary.interrupted
    import json

    attempts = json.loads((tmp_path / "t.sweep" / engine.ATTEMPTS_FILE).read_text())
    (tried,) = attempts.values()
    failed = tried[0]["session"]
    assert sessions_by_status(tmp_path / "s") == {"success": [rows[0]["session"]],
                                                   "failed": [failed]}
    from labbench.cli.main import main

    assert main(["devices", "--rig", str(r.write_rig(tmp_path / "rig.toml")),
                 "--fault-reset"]) == 0
    summary, rows = campaign(r, spec, tmp_path)
    assert (summary.ran, summary.already, summary.rerun, summary.complete) == (2, 1, 1, True)
    assert [r_["K"] for r_ in rows] == [10.0, 20.0, 30.0]
    assert [r_["attempts"] for r_ in rows] == [1, 2, 1] and rows[1]["earlier_sessions"] == failed
    assert all(r_["status"] == "ok" for r_ in rows)
    by = sessions_by_status(tmp_path / "s")
    assert sorted(by["success"]) == sorted(r_["session"] for r_ in rows)
    assert by["failed"] == [failed]
    assert all(r_["max_command_n"] <= r_["rig.force_limit_n"] for r_ in rows)


@pytest.mark.parametrize("variant, delay", [("event", 0.0), ("sync", 1e-3)])
def test_zwidth_on_the_canopennode_drive_within_1_percent(drive, tmp_path, variant, delay):
    """B = 0 and 1 N s/m (w0 = 125 rad/s), the torque applied on arrival and at the next
    SYNC (a period of delay: the rig states it as commissioning measured it, and the driver
    declares it too; the boundary is the rig's with it): K_max within 1 % of the exact
    sampled boundary. Shortened from the five-point Z-width (bench/bench_campaign.py runs
    all five on every device): the bracket starts at 80 % of the prediction, the refining
    steps last 6 s."""
    tables = {**TABLES, "rig": {"measured_td_s": delay}} if delay else TABLES
    r = drive(variant, tables=tables)
    spec = {"sweep": {"name": "zw", "protocol": "stability"},
            "fixed": {"ve": "spring-damper", "w0_rad_s": 125.0, "K_frac_k_max": 0.8,
                      "ratio": 1.08, "refine_s": 6.0},
            "grid": {"B": [0.0, 1.0]}}
    summary, rows = campaign(r, spec, tmp_path)
    assert summary.complete
    for row in rows:
        assert row["status"] == "ok", row["error"]
        assert row["rig.device_delay_s"] == pytest.approx(delay)
        assert row["zw.rel_error"] is not None and abs(row["zw.rel_error"]) < 0.01, (
            {k: v for k, v in row.items() if k.startswith(("zw.", "res.b", "res.me", "res.st", "pred.k_max", "session"))})
        assert row["max_command_n"] <= row["rig.force_limit_n"]
