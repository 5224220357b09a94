"""A campaign's table as safe as a sweep's (issue 44): one kind of rows per table, claims and
repair, everything checked before the first point, planning bounded.

Before (measured on this machine): ``sweep --repair`` on a damaged campaign table recomputed its
points on a simulator and the next campaign added its own (4 rows for 2 points); a campaign
into a sweep's table doubled every point (8 rows for 4); two campaigns into one table each ran
every point (8 sessions for 4 points); a 1000-point spec waited 62 s silently before its first
point and a 10^6-point one printed nothing for over 60 s at 718 MB; a chart naming a missing
column was refused after every point had run, an unknown name in a case when its first point
started, and ``--strict`` exited 0 with a point the pre-check skipped.
"""
from __future__ import annotations

import contextlib
import io
import json
import subprocess
import sys
import tracemalloc
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from labbench.campaign import engine
from labbench.campaign.plan import Context, describe, make_plan
from labbench.rig import CampaignSettings
from labbench.errors import UserError
from labbench.loop.interrupts import StopRequest
from labbench.rig import Rig
from labbench.runner import RunResult
from labbench.sweep import table as tables
from labbench.sweep.spec import Spec, spec_from_dict
from labbench.model.ve import Plant

LABBENCH = [sys.executable, "-m", "labbench"]
SPEC = """[sweep]
name = "k"
protocol = "etfe"
[fixed]
ve = "spring"
duration_s = 1.0
seed = 3
[grid]
K = {ks}
"""


def spec_file(tmp_path, ks=(10.0, 20.0), extra="", name="k.toml") -> Path:
    p = tmp_path / name
    p.write_text(SPEC.format(ks=list(ks)) + extra)
    return p


def cli(*argv) -> tuple[int, str, str]:
    from labbench.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def error_line(err: str) -> str:
    """The one error line among warnings and progress lines ("n/N points, ...")."""
    lines = [x for x in err.strip().splitlines()
             if ": warning: " not in x and " points, " not in x.split(":", 2)[1]]
    assert len(lines) == 1 and ": error: " in lines[0] and "Traceback" not in err, err
    return lines[0]


def campaign(spec, table, sessions, *more):
    return cli("campaign", spec, "--device", "sim", "--table", table, "--out", sessions, "--json",
               *more)


def rows(table) -> list[dict]:
    return tables.read_table(table).to_pylist()


def sessions_in(folder) -> list[Path]:
    return sorted(Path(folder).glob("*.lbsession"))


# ------------------------------------------------------------------ one kind of rows
def test_a_damaged_campaign_table_is_repaired_on_its_device_never_on_a_simulator(tmp_path):
    spec, table, s = spec_file(tmp_path), tmp_path / "t.sweep", tmp_path / "s"
    assert campaign(spec, table, s)[0] == 0
    [part] = tables.parts(table)
    part.write_bytes(b"")
    code, out, err = campaign(spec, table, s)
    assert code == 2 and "damaged part file" in error_line(err) and "--repair" in err
    # a sweep would add simulated rows to the measured ones: refused, nothing written
    code, out, err = cli("sweep", spec, "--out", table, "--repair", "--workers", "0")
    line = error_line(err)
    assert code == 2 and "holds a campaign's points measured on sim" in line
    assert "labbench campaign SPEC --device sim" in line and part.exists()
    code, out, err = campaign(spec, table, s, "--repair")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["ran"] == 2 and summary["repaired"] == [str(table / tables.DAMAGED / part.name)]
    got = rows(table)
    assert len(got) == 2 and all(Path(r["session"]).is_file() for r in got)
    assert sum(pq.read_table(p).num_rows for p in tables.parts(table)) == 2
    assert len(sessions_in(s)) == 4  # two before the damage, two now: none on a simulator's behalf


@pytest.mark.parametrize("first, second, words", [
    ("sweep", "campaign sim", "holds a sweep's runs on the simulator sim"),
    ("campaign sim", "sweep", "holds a campaign's points measured on sim"),
    ("campaign sim", "campaign sim-canopen", "would add a campaign's points measured on sim-canopen"),
    ("campaign sim", "campaign other rig", "would add a campaign's points measured on sim, rig 'other'"),
])
def test_no_command_mixes_kinds_devices_or_rigs_in_one_table(tmp_path, first, second, words):
    spec, table, s = spec_file(tmp_path, (10.0, 20.0, 30.0, 40.0)), tmp_path / "t.sweep", tmp_path / "s"
    rig = tmp_path / "rig.toml"
    rig.write_text('[rig]\nname = "other"\n')

    def do(what):
        if what == "sweep":
            return cli("sweep", spec, "--out", table, "--workers", "0")
        device = "sim" if what.endswith("other rig") else what.split()[1]
        more = ["--rig", rig] if what.endswith("other rig") else []
        return cli("campaign", spec, "--device", device, "--table", table, "--out", s, *more)

    assert do(first)[0] == 0
    before = rows(table)
    code, out, err = do(second)
    assert code == 2 and words in error_line(err) and "one table holds one kind of rows" in err
    assert rows(table) == before and len(before) == 4  # not 8


def test_two_campaigns_into_one_table_run_every_point_once(tmp_path):
    spec, table, s = spec_file(tmp_path, (10.0, 20.0, 30.0, 40.0)), tmp_path / "t.sweep", tmp_path / "s"
    s.mkdir()
    cmd = [*LABBENCH, "campaign", str(spec), "--device", "sim", "--realtime", "--table",
           str(table), "--out", str(s), "--json"]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              cwd=tmp_path) for _ in range(2)]
    results = []
    for p in procs:
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-2000:]
        results.append(json.loads(out))
    assert all(r["complete"] for r in results)
    assert sum(r["ran"] for r in results) == 4  # each point once
    got = rows(table)
    assert len(got) == 4 and len(sessions_in(s)) == 4
    assert sorted(r["session"] for r in got) == sorted(str(p) for r in results for p in r["sessions"])
    assert sum(pq.read_table(p).num_rows for p in tables.parts(table)) == 4


def test_a_campaign_waits_for_points_another_claimed_and_takes_over_a_dead_ones(tmp_path):
    """Two shares of one table in this process: a live claim is left to its owner and waited
    for; once its campaign is gone (killed: its lock goes, its claim file stays) the points
    are run here. Nothing runs twice: every point's run_point call once."""
    import os
    import threading

    from labbench.sweep import sharing

    plan = make_plan(spec_from_dict({"sweep": {"protocol": "etfe"},
                                     "fixed": {"duration_s": 1.0, "ve": "spring"},
                                     "grid": {"K": [10.0, 20.0, 30.0, 40.0]}}), context())
    out = tables.open_table(tmp_path / "t.sweep")
    keys = [plan.key(p) for p in plan.spec.iter_points()]
    other = sharing.Share(out)
    with other.locked():
        other.claim(keys[:2])
    ran = []

    def run_point(pp, stop_, progress, consumers):
        ran.append(pp.key)
        return RunResult("success", "completed", n_samples=10), None

    def die():  # the other campaign killed while this one waits for its points
        os.close(other._fd)
        other._fd = None
        os.close(other._lock_fd)

    threading.Timer(1.0, die).start()
    summary = engine.run_campaign(plan, out, run_point, StopRequest())
    assert summary.complete and sorted(ran) == sorted(keys) and len(ran) == 4
    assert len(rows(out)) == 4 and list((out / sharing.CLAIMS).iterdir()) == []


def context(simulated=True, device="sim", rig=None) -> Context:
    rig = rig or Rig(direction_checked="2026-01-01")
    return Context(device, rig, Plant(0.094, 0.1), "nominal", simulated,
                   CampaignSettings.from_rig(rig, simulated))


def test_a_second_campaign_on_real_hardware_into_the_table_is_refused(tmp_path):
    plan = make_plan(spec_from_dict({"sweep": {"protocol": "etfe"}, "fixed": {"duration_s": 1.0},
                                     "grid": {"K": [10.0, 20.0]}}), context(False, "serial"))
    with engine.CampaignTable(plan, tmp_path / "t.sweep"):
        with pytest.raises(UserError, match="another campaign on real hardware is running into "
                                            "this table: one rig runs one campaign at a time"):
            engine.CampaignTable(plan, tmp_path / "t.sweep")
    engine.CampaignTable(plan, tmp_path / "t.sweep").close()  # free again once it ends


# ------------------------------------------------------------------ checked before the first point
def test_a_chart_naming_a_missing_column_is_refused_before_any_point(tmp_path):
    chart = '[[chart]]\nkind = "lines"\nx = "K"\ny = "acc.ed_medain"\n'
    spec, table, s = spec_file(tmp_path, extra=chart), tmp_path / "t.sweep", tmp_path / "s"
    code, out, err = campaign(spec, table, s)
    line = error_line(err)
    assert code == 2 and "[[chart]] 1 names column 'acc.ed_medain'" in line
    assert "did you mean 'acc.ed_median'?" in line
    assert sessions_in(s) == [] and not tables.parts(table)  # no point ran
    good = spec_file(tmp_path, extra=chart.replace("medain", "median"), name="good.toml")
    code, out, err = campaign(good, tmp_path / "g.sweep", s)
    assert code == 0 and len(json.loads(out)["charts"]) == 1, err


def test_an_unknown_name_or_a_bad_fixed_value_is_refused_before_any_point(tmp_path):
    cases = ('[[cases.x]]\nlabel = "a"\nB = 0.0\n[[cases.x]]\nlabel = "b"\nB = 0.0\n'
             'zzz_unknown = 1.0\n')
    s = tmp_path / "s"
    code, out, err = campaign(spec_file(tmp_path, extra=cases), tmp_path / "t.sweep", s)
    assert code == 2 and "zzz_unknown" in error_line(err) and "unknown" in err
    bad = spec_file(tmp_path, name="bad.toml")
    bad.write_text(bad.read_text().replace("duration_s = 1.0", "duration_s = -1.0"))
    code, out, err = campaign(bad, tmp_path / "b.sweep", s)
    assert code == 2 and "duration_s must be" in error_line(err)
    assert sessions_in(s) == []


def test_strict_exits_3_for_any_point_not_ok_a_precheck_skip_included(tmp_path):
    spec, table, s = spec_file(tmp_path, (50.0, 400.0)), tmp_path / "t.sweep", tmp_path / "s"
    code, out, err = campaign(spec, table, s, "--strict")
    assert code == 3, err
    summary = json.loads(out)
    assert summary["skipped"] == 1 and summary["ran"] == 1 and summary["complete"]
    assert campaign(spec, table, s, "--strict")[0] == 3  # the table still holds it
    assert campaign(spec, table, s)[0] == 0


def test_a_point_whose_settings_cannot_be_made_is_a_row_not_a_late_refusal(tmp_path):
    """Only the first value of an axis is planned before the first point: a later one that
    cannot be made is its row (status refused, no device time), as a sweep's."""
    spec, table, s = spec_file(tmp_path), tmp_path / "t.sweep", tmp_path / "s"
    spec.write_text(spec.read_text().replace("duration_s = 1.0\n", "")
                    + "duration_s = [1.0, -1.0]\n")
    code, out, err = campaign(spec, table, s, "--strict")
    assert code == 3, err
    by = {r["duration_s"]: r for r in rows(table)}
    assert by[1.0]["status"] == "ok" and by[-1.0]["status"] == "refused"
    assert "duration_s must be" in by[-1.0]["error"] and by[-1.0]["session"] is None


# ------------------------------------------------------------------ planning bounded
def _spec(n: int, **fixed) -> Spec:
    return spec_from_dict({"sweep": {"name": "m", "protocol": "etfe", "sample": "random",
                                     "points": n},
                           "fixed": {"ve": "spring", "duration_s": 1.0, **fixed},
                           "ranges": {"K": {"lo": 5.0, "hi": 50.0}}})


def test_a_million_point_campaign_starts_at_once_in_bounded_memory(tmp_path, monkeypatch):
    """The points are planned as they come: a few dozen made before the first one runs (it
    was the whole plan: over 60 s without a word, 718 MB). The time to the first point is a
    bench's (bench/bench_campaign_start.py): here, what it is made of."""
    made = []
    real = Spec.iter_points

    def counted(self):
        for p in real(self):
            made.append(p.index)
            yield p

    monkeypatch.setattr(Spec, "iter_points", counted)
    stop, at_first = StopRequest(), {}

    def run_point(pp, stop_, progress, consumers):
        if not at_first:
            at_first.update(made=len(made), peak=tracemalloc.get_traced_memory()[1])
        if pp.point.index >= 2:
            stop.set("enough")
        return RunResult("success", "completed", n_samples=10), None

    tracemalloc.start()
    try:
        plan = make_plan(_spec(1_000_000), context())
        summary = engine.run_campaign(plan, tmp_path / "m.sweep", run_point, stop)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert summary.ran == 3 and summary.interrupted == "enough" and summary.total == 1_000_000
    assert at_first["made"] <= 2 * engine.CHUNK + 16  # name samples, a chunk, the charts' look
    assert at_first["peak"] < 300e6 and peak < 300e6
    print(f"\nfirst point after {at_first['made']} points made, peak {peak / 1e6:.1f} MB traced")


def test_a_bad_fixed_value_in_a_million_points_is_refused_at_once(monkeypatch):
    made = []
    real = Spec.iter_points

    def counted(self):
        for p in real(self):
            made.append(p.index)
            yield p

    monkeypatch.setattr(Spec, "iter_points", counted)
    with pytest.raises(UserError, match="duration_s must be >= 1 s, got -1"):
        make_plan(_spec(1_000_000, duration_s=-1.0), context())
    assert len(made) == 0  # the name sample alone (it was the whole list: 19.5 s, 719 MB)


def test_the_whole_plan_on_real_hardware_says_its_progress(tmp_path):
    heard = []
    plan = make_plan(_spec(300), context(False, "serial"))
    lines = describe(plan, None, tmp_path / "t.sweep", lambda n, total: heard.append((n, total)))
    assert heard[-1] == (300, 300) and len(heard) == 300
    assert "300 points" in lines[0] and "300 to run" in lines[0]
    assert any("largest force planned" in x for x in lines)


# ------------------------------------------------------------------ control characters
def test_control_characters_in_names_are_escaped_in_every_output(tmp_path):
    """A terminal escape in the spec's name, the rig's name and the table's folder name:
    shown as its escape on the terminal, in the HTML and in the PDF's text; the JSON output
    stays JSON (before, the raw ESC reached stdout, stderr and campaign.html)."""
    from labbench.campaign.report import build
    from labbench.report.render_pdf import _rl

    esc = "\x1b[31mRED\x1b[0m"
    spec = spec_file(tmp_path)
    spec.write_text(spec.read_text().replace('name = "k"', f'name = "evil{esc}"'.replace(
        "\x1b", "\\u001b")))
    rig = tmp_path / "rig.toml"
    rig.write_text('[rig]\nname = "bench\\u001b]0;pwned\\u0007"\n')
    table = tmp_path / f"t{esc}.sweep"
    for argv in ((), ("--json",)):
        code, out, err = cli("campaign", spec, "--device", "sim", "--rig", rig, "--table", table,
                             "--out", tmp_path / "s", "--report", *argv)
        assert code == 0, err
        assert "\x1b" not in out and "\x07" not in out and "\x1b" not in err, (out, err)
    assert json.loads(out)["table"] == str(table)  # JSON: the name exactly, escaped by JSON
    html = (tmp_path / f"t{esc}.charts" / "campaign.html").read_text()
    assert "\x1b" not in html and "\x07" not in html and "evil\\x1b[31mRED" in html
    title, subtitle, blocks = build(table)
    assert "\x1b" not in _rl(subtitle) and "\\x1b" in _rl(subtitle)
