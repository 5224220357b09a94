"""A sweep table shared: sweeps at once, ordinary Parquet readers, damaged parts, a full disk,
a 10^6-point spec (labbench.sweep.sharing, table, engine; docs/sweep.md)."""
from __future__ import annotations

import errno
import json
import os
import stat
import subprocess
import sys
import tracemalloc
from pathlib import Path

import pytest

from labbench.cli import main
from labbench.sweep import engine, sharing
from labbench.sweep import table as tables
from labbench.sweep.point import TIME_COLUMNS, typed_row
from labbench.sweep.spec import spec_from_dict

LABBENCH = [sys.executable, "-m", "labbench"]

SPEC = """[sweep]
name = "shared"
kind = "analysis"
analysis = "etfe"

[fixed]
n = {n}

[grid]
seed = {seeds}
estimator = ["paper", "lpm"]

[[chart]]
kind = "map"
x = "seed"
y = "truth.max_rel"
"""


def spec_file(tmp_path, seeds, n=2000, name="spec.toml") -> Path:
    p = tmp_path / name
    p.write_text(SPEC.format(n=n, seeds=list(seeds)))
    return p


def rows(directory) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIME_COLUMNS}
            for r in tables.read_table(directory).to_pylist()]


def one_line(capsys) -> str:
    err = [x for x in capsys.readouterr().err.splitlines() if "error" in x]
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


# ----------------------------------------------------------------------------- sweeps at once
def test_four_sweeps_of_one_spec_at_once_compute_every_point_once(tmp_path):
    import pyarrow.parquet as pq

    spec = spec_file(tmp_path, range(1, 13), n=8000)  # 24 points
    out = tmp_path / "t.sweep"
    procs = [subprocess.Popen([*LABBENCH, "sweep", str(spec), "--out", str(out), "--workers", "0",
                               "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, cwd=tmp_path) for _ in range(4)]
    results = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=600)
        assert p.returncode == 0, stderr[-2000:]
        results.append(json.loads(stdout))
    assert all(not r["stopped"] and r["points"] == 24 for r in results)
    assert sum(r["computed"] for r in results) == 24  # each point once
    got = rows(out)
    assert len(got) == 24 and len({r["key"] for r in got}) == 24
    assert sum(pq.read_table(p).num_rows for p in tables.parts(out)) == 24  # no duplicates
    assert list((out / sharing.CLAIMS).iterdir()) == []  # every claim gone with its sweep


def test_a_sweep_waits_for_the_points_another_claimed_and_takes_over_a_dead_ones(tmp_path):
    """In one process, two shares of one table: a live claim is left to its owner, the claim
    of a sweep that died (its lock gone, its file left) is removed and its points computed."""
    spec = spec_from_dict({"sweep": {"kind": "analysis", "analysis": "etfe"},
                           "fixed": {"n": 2000}, "grid": {"seed": [1, 2, 3, 4]}})
    out = tables.open_table(tmp_path / "t.sweep")
    keys = [p.key(spec) for p in spec.points()]
    other = sharing.Share(out)
    with other.locked():
        other.claim(keys[:2])
    mine = sharing.Share(out)
    with mine.locked():
        assert mine.others() == set(keys[:2])
    mine.close()
    os.close(other._fd)  # killed: the lock goes with the process, the file stays
    other._fd = None
    os.close(other._lock_fd)
    assert len(list((out / sharing.CLAIMS).iterdir())) == 1
    summary = engine.run_sweep(spec, out, workers=0)
    assert summary.computed == 4 and not summary.stopped
    assert list((out / sharing.CLAIMS).iterdir()) == []


# ----------------------------------------------------------------------------- readers, charts
def test_pandas_and_pyarrow_read_a_finished_table_with_its_charts(tmp_path, capsys):
    import pandas as pd
    import pyarrow.parquet as pq

    spec = spec_file(tmp_path, range(1, 5))
    out = tmp_path / "t.sweep"
    old = os.umask(0o022)
    try:
        assert main(["sweep", str(spec), "--out", str(out), "--workers", "0", "--json",
                     "--flush-rows", "3"]) == 0
    finally:
        os.umask(old)
    result = json.loads(capsys.readouterr().out)
    chart = tmp_path / "t.charts" / "map-1.png"
    assert result["charts"] == [str(chart)] and chart.read_bytes()[:4] == b"\x89PNG"
    assert not list(out.glob("*.png"))
    ours = tables.read_table(out).to_pylist()
    by_pyarrow = pq.read_table(out).sort_by("index").to_pylist()
    by_pandas = pd.read_parquet(out).sort_values("index").to_dict("records")
    assert len(ours) == len(by_pyarrow) == len(by_pandas) == 8
    for column in ("key", "truth.max_rel", "estimator"):
        assert ([r[column] for r in by_pyarrow] == [r[column] for r in by_pandas]
                == [r[column] for r in ours])
    for p in [*tables.parts(out), out / tables.SPEC_FILE, chart]:  # the umask's, not 0600
        assert stat.S_IMODE(p.stat().st_mode) == 0o644, p


# ----------------------------------------------------------------------------- damaged parts
def _damage(part: Path, how: str) -> None:
    data = part.read_bytes()
    if how == "truncated":
        part.write_bytes(data[: len(data) // 2])
    elif how == "empty":
        part.write_bytes(b"")
    else:  # garbled: bytes inside the data pages changed, the file's frame intact
        b = bytearray(data)
        for i in range(8, len(b) // 2, 7):
            b[i] ^= 0x5A
        part.write_bytes(bytes(b))


@pytest.mark.parametrize("how", ["truncated", "empty", "garbled"])
def test_a_damaged_part_is_named_in_one_line_and_repair_recomputes_its_points(tmp_path, capsys,
                                                                            how):
    import pandas as pd

    spec = spec_file(tmp_path, [1, 2, 3])
    out = tmp_path / "t.sweep"
    assert main(["sweep", str(spec), "--out", str(out), "--workers", "0"]) == 0
    first = rows(out)
    [part] = tables.parts(out)
    _damage(part, how)
    grown = spec_file(tmp_path, [1, 2, 3, 4], name="grown.toml")
    capsys.readouterr()
    assert main(["sweep", str(grown), "--out", str(out), "--workers", "0", "--json"]) == 2
    line = one_line(capsys)
    assert f"damaged part file: {part.name}" in line and "--repair" in line
    assert part.exists()  # nothing moved without asking
    assert main(["sweep", str(grown), "--out", str(out), "--workers", "0", "--json",
                 "--repair"]) == 0
    cap = capsys.readouterr()
    result = json.loads(cap.out)
    assert result["repaired"] == [str(out / tables.DAMAGED / part.name)]
    assert result["computed"] == 8 and not result["stopped"]  # its 6 points again, and 2 new
    assert "moved to" in cap.err
    assert (out / tables.DAMAGED / part.name).exists()
    again = {r["key"]: r for r in rows(out)}
    assert all(again[r["key"]] == r for r in first)  # the same rows: the task is pure
    assert len(pd.read_parquet(out)) == 8  # readers skip _damaged


def test_the_gui_reader_names_a_damaged_part_in_one_line(tmp_path):
    out = tmp_path / "t.sweep"
    engine.run_sweep(spec_from_dict({"sweep": {"kind": "analysis", "analysis": "etfe"},
                                     "fixed": {"n": 2000}, "grid": {"seed": [1, 2]}}),
                     out, workers=0)
    _damage(tables.parts(out)[0], "empty")
    with pytest.raises(tables.DamagedTable, match="1 damaged part file: part-.*empty.*--repair"):
        tables.read_table(out)


# ----------------------------------------------------------------------------- full disk
def test_a_part_the_disk_refuses_is_one_line_json_and_a_rerun_completes(tmp_path, capsys,
                                                                       monkeypatch):
    spec = spec_file(tmp_path, range(1, 6))
    out = tmp_path / "t.sweep"
    real = tables.pq.write_table
    calls = []

    def fills(table, where, **kw):
        calls.append(where)
        if len(calls) > 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(table, where, **kw)

    monkeypatch.setattr(tables.pq, "write_table", fills)
    assert main(["sweep", str(spec), "--out", str(out), "--workers", "0", "--json",
                 "--flush-rows", "4"]) == 2
    cap = capsys.readouterr()
    line = [x for x in cap.err.splitlines() if "error" in x]
    assert len(line) == 1 and "the disk is full (No space left on device)" in line[0]
    assert "4 rows written, the 4 after them not: run the same command again" in line[0]
    result = json.loads(cap.out)
    assert result["stopped"] and result["error"] in line[0]
    assert len(rows(out)) == 4 and not list(out.glob(".*"))  # no temporary left
    monkeypatch.undo()
    assert main(["sweep", str(spec), "--out", str(out), "--workers", "0", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["already"] == 4 and result["computed"] == 6 and not result["stopped"]


def test_a_spec_or_a_chart_the_disk_refuses_is_one_line(tmp_path, capsys, monkeypatch):
    spec = spec_file(tmp_path, [1])
    out = tmp_path / "t.sweep"

    def full(self, *a, **kw):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with monkeypatch.context() as m:
        m.setattr(Path, "write_text", full)  # _table.json, the first of the table's own files
        assert main(["sweep", str(spec), "--out", str(out), "--workers", "0"]) == 2
        assert "_table.json: the disk is full (No space left on device)" in one_line(capsys)
    from matplotlib.figure import Figure

    with monkeypatch.context() as m:
        m.setattr(Figure, "savefig", lambda self, *a, **kw: full(self))
        assert main(["sweep", str(spec), "--out", str(out), "--workers", "0", "--json"]) == 2
        cap = capsys.readouterr()
        line = [x for x in cap.err.splitlines() if "error" in x]
        assert len(line) == 1 and "map-1.png: the disk is full" in line[0]
        assert json.loads(cap.out)["error"] in line[0]
    assert len(rows(out)) == 2  # the table is whole


# ----------------------------------------------------------------------------- 10^6 points
def test_a_million_point_spec_starts_at_once_in_bounded_memory(tmp_path, monkeypatch):
    """Before, the list of 10^6 points (806 MB, 22 s) was made before the first one ran. The
    points are now made as asked for: a few dozen before the first is computed."""
    from labbench.loop.interrupts import StopRequest
    from labbench.sweep.spec import Spec, point_key

    spec = spec_from_dict({"sweep": {"kind": "analysis", "analysis": "etfe", "sample": "random",
                                     "points": 1_000_000},
                           "fixed": {"n": 2000},
                           "ranges": {"seed": {"lo": 1, "hi": 10**9, "integer": True}}})
    made = []
    real_iter = Spec.iter_points

    def counted(self):
        for p in real_iter(self):
            made.append(p.index)
            yield p

    monkeypatch.setattr(Spec, "iter_points", counted)
    stop = StopRequest()
    at_first = {}

    def compute_row(spec_d, task, keep):  # stands in for the point's own work
        if not at_first:
            at_first["made"] = len(made)
            at_first["peak"] = tracemalloc.get_traced_memory()[1]
        if len(at_first) and task["index"] >= 2:
            stop.set()
        return typed_row({"key": point_key(spec.target, task["params"], task["tags"]),
                          "index": task["index"], **task["params"], "status": "ok"})

    monkeypatch.setattr(engine, "compute_row", compute_row)
    tracemalloc.start()
    try:
        summary = engine.run_sweep(spec, tmp_path / "m.sweep", workers=0, stop=stop)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert summary.computed == 3 and summary.stopped
    assert at_first["made"] <= 64 and len(made) <= 64  # a chunk or two, not 10^6
    assert at_first["peak"] < 100e6 and peak < 100e6  # the draws' numbers (16 MB), no list
