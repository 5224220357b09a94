"""labbench sweep: specs, points, the table, the engine on Dask, stop and resume, the CLI.

Timing is never asserted: the time columns (wall_s, loop_s, analysis_s) are the only
ones allowed to differ between two computations of a point, and the tests say so by
leaving exactly those out of every comparison.
"""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labbench.errors import UserError
from labbench.sweep import table as tables
from labbench.sweep.engine import run_sweep
from labbench.sweep.point import TIME_COLUMNS, compute_row, flatten, verdict_columns
from labbench.sweep.spec import load_spec, spec_from_dict

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "docs" / "examples"
LABBENCH = [sys.executable, "-m", "labbench"]

# 12 short ETFE runs: two stiffnesses and one the precheck refuses (K_max = 1212 N/m),
# two estimators, with and without a device delay of 1.5 samples.
SMALL = {
    "sweep": {"name": "small", "protocol": "etfe"},
    "fixed": {"duration_s": 5.0, "seed": 3},
    "grid": {"K": [20.0, 50.0, 5000.0], "estimator": ["lpm", "paper"],
             "device_delay_s": [0.0, 0.0015]},
}


def rows_without_times(directory) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIME_COLUMNS}
            for r in tables.read_table(directory).to_pylist()]


@pytest.fixture(scope="module")
def small_inline(tmp_path_factory):
    out = tmp_path_factory.mktemp("inline") / "small.sweep"
    summary = run_sweep(spec_from_dict(SMALL), out, workers=0)
    return summary, rows_without_times(out)


# ----------------------------------------------------------------------------- specs
def test_grid_cases_and_keys():
    spec = spec_from_dict({
        "sweep": {"protocol": "etfe"}, "fixed": {"duration_s": 5.0},
        "grid": {"K": [10, 20, 30], "seed": [1, 2]},
        "cases": {"noise": [{"label": "clean"}, {"label": "noisy", "force_noise_n": 0.01}]}})
    points = spec.points()
    assert len(points) == spec.count() == 12
    assert [p.index for p in points] == list(range(12))
    assert points[0].params == {"duration_s": 5.0, "K": 10, "seed": 1}
    assert points[1].tags == {"noise": "noisy"} and points[1].params["force_noise_n"] == 0.01
    keys = [p.key(spec) for p in points]
    assert len(set(keys)) == 12
    # the key is the point, not its place: another order of values gives the same keys,
    # and 50 and 50.0 are one point
    spec2 = spec_from_dict({
        "sweep": {"protocol": "etfe"}, "fixed": {"duration_s": 5},
        "grid": {"seed": [2, 1], "K": [30.0, 10.0, 20.0]},
        "cases": {"noise": [{"label": "noisy", "force_noise_n": 0.01}, {"label": "clean"}]}})
    assert {p.key(spec2) for p in spec2.points()} == set(keys)


def test_random_and_latin_hypercube_draws():
    base = {"sweep": {"protocol": "etfe", "points": 50, "sample_seed": 7},
            "ranges": {"K": {"lo": 10.0, "hi": 1000.0, "log": True},
                       "duration_s": {"lo": 2.0, "hi": 30.0, "integer": True},
                       "estimator": ["lpm", "paper"]}}
    for sample in ("random", "lhs"):
        d = json.loads(json.dumps(base))
        d["sweep"]["sample"] = sample
        pts = spec_from_dict(d).points()
        assert len(pts) == 50
        assert pts == spec_from_dict(d).points()  # the draw is the seed's
        K = np.array([p.params["K"] for p in pts])
        assert K.min() >= 10 and K.max() <= 1000
        assert all(isinstance(p.params["duration_s"], int) for p in pts)
        assert {p.params["estimator"] for p in pts} == {"lpm", "paper"}
        if sample == "lhs":  # one point in each of the 50 strata of log K
            u = np.log(K / 10) / np.log(100)
            assert sorted(np.floor(u * 50).astype(int)) == list(range(50))


def test_a_spec_is_the_same_spec_once_sent_to_a_worker():
    """compute_row reads the spec back from Spec.as_dict(): every shipped example and a sample
    with a list of choices give the same spec and points again."""
    specs = [load_spec(p) for p in sorted(EXAMPLES.glob("*.toml")) if p.name != "example-rig.toml"]
    specs.append(spec_from_dict({"sweep": {"protocol": "etfe", "sample": "lhs", "points": 5},
                                 "ranges": {"K": {"lo": 10.0, "hi": 100.0},
                                            "estimator": ["lpm", "paper"]}}))
    for spec in specs:
        again = spec_from_dict(spec.as_dict())
        assert again.as_dict() == spec.as_dict() and again.points() == spec.points()


def test_a_point_drawn_twice_is_computed_once_and_the_sweep_completes(tmp_path):
    """A random draw over few choices repeats points (same key): one row each, and the
    sweep is complete, not stopped (on Dask one task per key)."""
    d = {"sweep": {"kind": "analysis", "analysis": "etfe", "sample": "random", "points": 6},
         "fixed": {"n": 2000}, "ranges": {"seed": [1, 2]}}
    spec = spec_from_dict(d)
    assert len({p.key(spec) for p in spec.points()}) == 2
    first = run_sweep(spec, tmp_path / "d.sweep", workers=1)
    assert (first.total, first.computed, first.stopped) == (2, 2, False)
    again = run_sweep(spec, tmp_path / "d.sweep", workers=0)
    assert (again.total, again.before, again.computed, again.stopped) == (2, 2, 0, False)
    assert sorted(r["seed"] for r in tables.read_table(first.table).to_pylist()) == [1, 2]


@pytest.mark.parametrize("bad, words", [
    ({"sweep": {"protocol": "etfe"}, "grids": {}}, "unknown table 'grids'"),
    ({"sweep": {"protocol": "etfe", "sampel": "grid"}}, "did you mean 'sample'"),
    ({"sweep": {"protocol": "nope"}}, "protocol must be one of"),
    ({"sweep": {"protocol": "etfe", "device": "canopen"}}, "simulators only"),
    ({"sweep": {}}, "protocol is missing"),
    ({"sweep": {"kind": "analysis", "analysis": "etfe", "protocol": "etfe"}}, "for kind run"),
    ({"sweep": {"protocol": "etfe"}, "grid": {"K": []}}, "non-empty list"),
    ({"sweep": {"protocol": "etfe"}, "grid": {"K": [1, 1]}}, "twice"),
    ({"sweep": {"protocol": "etfe"}, "fixed": {"K": 1}, "grid": {"K": [2]}}, "both"),
    ({"sweep": {"protocol": "etfe"}, "ranges": {"K": {"lo": 1, "hi": 2}}}, "random"),
    ({"sweep": {"protocol": "etfe", "sample": "lhs", "points": 3},
      "ranges": {"K": {"lo": 0, "hi": 2, "log": True}}}, "lo > 0"),
    ({"sweep": {"protocol": "etfe"}, "grid": {"K": [[1]]}}, "values are numbers"),
    ({"sweep": {"protocol": "etfe"}, "chart": [{"kind": "pie"}]}, "kind must be one of"),
    ({"sweep": {"protocol": "etfe"}, "chart": [{"kind": "map", "x": "K"}]}, "needs y"),
    ({"sweep": {"protocol": "etfe"}, "cases": {"K": [{"label": "a", "B": 1}]},
      "grid": {"K": [1]}}, "name of a parameter"),
    ({"sweep": {"protocol": "etfe"}, "grid": {"K": list(range(1001)), "B": list(range(1001))}},
     "at most"),
])
def test_bad_specs_are_one_line(bad, words):
    with pytest.raises(UserError) as e:
        spec_from_dict(bad, source="s.toml")
    assert words in str(e.value) and "\n" not in str(e.value)


_scalar = st.one_of(st.integers(-5, 5), st.floats(allow_nan=True, allow_infinity=True),
                    st.text(max_size=8), st.booleans())
_value = st.recursive(_scalar, lambda inner: st.one_of(
    st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=8)
_tables = st.sampled_from(["sweep", "fixed", "grid", "cases", "ranges", "chart", "x"])
_fields = st.sampled_from(["kind", "protocol", "analysis", "sample", "points", "repeat", "K", "n",
                           "lo", "hi", "log", "label", "x", "y", "name", "record", "device"])


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(_tables, st.one_of(_value, st.dictionaries(_fields, _value, max_size=4)),
                       max_size=4))
def test_fuzzed_specs_give_a_spec_or_one_user_error(d):
    try:
        spec = spec_from_dict(d)
    except UserError as exc:
        assert "\n" not in str(exc)
        return
    assert spec.count() >= 1


def test_spec_file_errors(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text("[sweep\n")
    with pytest.raises(UserError, match="not valid TOML"):
        load_spec(p)
    with pytest.raises(UserError, match="not found"):
        load_spec(tmp_path / "none.toml")
    for example in sorted(EXAMPLES.glob("*.toml")):
        if example.name != "example-rig.toml":
            assert load_spec(example).count() > 0


# ----------------------------------------------------------------------------- points
def test_rows_of_runs_against_the_exact_theory(small_inline):
    summary, rows = small_inline
    assert summary.computed == 12 and not summary.stopped
    by = {(r["K"], r["estimator"], r["device_delay_s"]): r for r in rows}
    for (K, est, delay), r in by.items():
        if K == 5000.0:  # beyond K_max = 1212 N/m: the precheck refuses it, the row says so
            assert r["status"] == "refused" and "refusing unstable" in r["error"]
            continue
        assert r["status"] == "ok", r["error"]
        assert r["truth.device_delay_s"] == pytest.approx(delay)
        assert r["truth.stable"] is True
        assert r["n_samples"] == 5000 and r["res.etfe.estimator"] == est
        # the simulator equals the exact sampled model with its delay: lpm recovers Z within
        # 1 % on 5 s (0.4-0.9 % measured: a short record's resolution; 7e-5 on 20 s)
        if est == "lpm":
            assert r["truth.median_rel"] < 1e-2
            # and the closed-loop fit finds the simulator's delay
            assert r["res.loop_fit.td_s"] == pytest.approx(delay, abs=2e-6)
            # the run's own deviation used the same truth (the rig knew the delay)
            assert r["res.deviation_vs_sampled.median_rel"] == pytest.approx(
                r["truth.median_rel"], rel=1e-9)
        if delay == 0:  # docs/stability-map.md: 1212 N/m for this VE at td = 0
            assert r["truth.k_max"] == pytest.approx(1212, abs=0.5)
    # the device delay lowers K_max
    assert by[(20.0, "lpm", 0.0015)]["truth.k_max"] < by[(20.0, "lpm", 0.0)]["truth.k_max"]


def test_a_point_that_crashes_is_a_row(monkeypatch):
    import labbench.sweep.point as point

    def boom(*a, **k):
        raise ZeroDivisionError("bug")

    monkeypatch.setattr(point, "_run_point", boom)
    spec = spec_from_dict(SMALL)
    p = spec.points()[0]
    row = compute_row(spec.as_dict(), {"index": 0, "params": p.params, "tags": {}})
    assert row["status"] == "error" and row["error"] == "ZeroDivisionError: bug"
    assert row["key"] == p.key(spec)


def test_unknown_names_stop_the_sweep_before_it_runs(tmp_path):
    for where, name in (("protocol", "estimatr"), ("device", "force_nois_n")):
        d = json.loads(json.dumps(SMALL))
        d["fixed"][name] = 1.0
        with pytest.raises(UserError, match="unknown"):
            run_sweep(spec_from_dict(d), tmp_path / f"{where}.sweep", workers=0)
        assert not tables.parts(tmp_path / f"{where}.sweep")
    bad = {"sweep": {"kind": "analysis", "analysis": "etfe"}, "fixed": {"estimatr": "lpm"}}
    with pytest.raises(UserError, match="estimatr"):
        run_sweep(spec_from_dict(bad), tmp_path / "a.sweep", workers=0)


def test_flatten_and_verdict():
    flat = flatten({"a": {"b": 1.5, "w": np.arange(3)}, "flags": ["drift: x", "low: y"],
                    "ci": [0.1, 0.2], "steps": [{"K": 1}, {"K": 2}]}, "res.")
    assert flat == {"res.a.b": 1.5, "res.flags.n": 2, "res.flags": "drift; low",
                    "res.ci.n": 2, "res.ci.0": 0.1, "res.ci.1": 0.2, "res.steps.n": 2}
    v = verdict_columns({"x": {"verdict": {"level": "ok", "reasons": []}},
                         "y": {"verdict": {"level": "doubtful", "reasons": ["wide"]}}})
    assert v == {"verdict": "doubtful", "verdict_reasons": "wide"}
    assert verdict_columns({})["verdict"] is None


# ----------------------------------------------------------------------------- engine
def test_rows_are_bit_identical_for_any_number_of_workers(tmp_path, small_inline):
    """In this process, on one Dask worker and on two: the same rows, every column but the
    measured times (rows come back in another order: the table sorts them)."""
    _, inline = small_inline
    for n in (1, 2):
        summary = run_sweep(spec_from_dict(SMALL), tmp_path / f"w{n}.sweep", workers=n)
        assert summary.workers == n and summary.computed == 12
        assert rows_without_times(summary.table) == inline


def test_an_existing_cluster(tmp_path, small_inline):
    """--scheduler: a dask scheduler and worker started as a user would, on this machine."""
    port = _free_port()
    dask = str(Path(sys.executable).with_name("dask"))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, env=env)]
    try:
        procs.append(subprocess.Popen([dask, "worker", f"tcp://127.0.0.1:{port}", "--nthreads", "1",
                                       "--nworkers", "2", "--no-dashboard"],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      env=env))
        _wait_for_workers(f"tcp://127.0.0.1:{port}", 2)  # both registered, as a user waits
        summary = _retry_cluster(lambda: run_sweep(spec_from_dict(SMALL), tmp_path / "c.sweep",
                                                   scheduler=f"tcp://127.0.0.1:{port}"))
        assert summary.workers == 2
        assert rows_without_times(summary.table) == small_inline[1]
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    with pytest.raises(UserError, match="no Dask scheduler answers"):
        run_sweep(spec_from_dict(SMALL), tmp_path / "none.sweep", scheduler=f"tcp://127.0.0.1:{port}")


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for_workers(address: str, n: int, timeout_s: float = 120.0) -> None:
    """On a loaded machine the second worker process can register well after the first."""
    from distributed import Client

    t0 = time.monotonic()
    while True:
        try:
            with Client(address, timeout=10) as client:
                client.wait_for_workers(n, timeout=max(1.0, timeout_s - (time.monotonic() - t0)))
                return
        except OSError:  # the scheduler not listening yet
            if time.monotonic() - t0 > timeout_s:
                raise
            time.sleep(0.5)


def _retry_cluster(fn, timeout_s: float = 60.0):
    """The workers need a while to register on a loaded machine."""
    t0 = time.monotonic()
    while True:
        try:
            return fn()
        except UserError as exc:
            if "no workers" not in str(exc) and "answers" not in str(exc) \
                    or time.monotonic() - t0 > timeout_s:
                raise
            time.sleep(0.5)


def test_rerun_skips_points_and_a_grown_grid_computes_only_the_new(tmp_path, small_inline):
    out = tmp_path / "g.sweep"
    d = json.loads(json.dumps(SMALL))
    d["grid"]["K"] = [20.0, 50.0]
    first = run_sweep(spec_from_dict(d), out, workers=0)
    assert first.computed == 8
    again = run_sweep(spec_from_dict(d), out, workers=0)
    assert again.computed == 0 and again.before == 8
    grown = run_sweep(spec_from_dict(SMALL), out, workers=0)
    assert grown.before == 8 and grown.computed == 4
    assert sorted(rows_without_times(out), key=lambda r: r["key"]) == \
        sorted(small_inline[1], key=lambda r: r["key"])


def test_kept_sessions_are_named_wherever_the_table_is_read(tmp_path, monkeypatch):
    from labbench.sessions.session_format import looks_like_session

    monkeypatch.chdir(tmp_path)
    d = json.loads(json.dumps(SMALL))
    d["grid"] = {"K": [20.0]}
    s = run_sweep(spec_from_dict(d), "t.sweep", workers=0, keep_sessions="kept")
    [row] = tables.read_table(s.table).to_pylist()
    assert Path(row["session"]).is_absolute() and looks_like_session(row["session"])
    assert Path(row["session"]).parent == tmp_path / "kept"


def test_table_folder_rules(tmp_path):
    other = tmp_path / "other"
    other.mkdir()
    (other / "x.txt").write_text("mine")
    with pytest.raises(UserError, match="not a sweep table"):
        run_sweep(spec_from_dict(SMALL), other, workers=0)
    with pytest.raises(UserError, match="does not exist"):
        run_sweep(spec_from_dict(SMALL), tmp_path / "a" / "b.sweep", workers=0)


def test_parts_with_disagreeing_types_read_as_one_table(tmp_path):
    w = tables.TableWriter(tmp_path, flush_rows=1)
    w.append({"key": "a", "index": 1, "x": None, "y": 1})
    w.append({"key": "b", "index": 0, "x": 2.5, "y": "text", "z": True})
    w.append({"key": "a", "index": 1, "x": 9.0, "y": 2})  # a duplicate left by a compaction
    w.close()
    t = tables.read_table(tmp_path)
    assert t.to_pylist() == [{"key": "b", "index": 0, "x": 2.5, "y": "text", "z": True},
                             {"key": "a", "index": 1, "x": None, "y": "1", "z": None}]
    tables.compact(tmp_path)
    assert len(tables.parts(tmp_path)) == 1 and tables.read_table(tmp_path).equals(t)


# ----------------------------------------------------------------------------- stop, resume
RESUME = {
    "sweep": {"name": "resume", "protocol": "etfe"},
    "fixed": {"duration_s": 20.0},
    "grid": {"K": [10.0, 20.0, 30.0, 40.0, 50.0, 60.0], "seed": [1, 2, 3]},
}


@pytest.fixture(scope="module")
def resume_reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "ref.sweep"
    run_sweep(spec_from_dict(RESUME), out, workers=0)
    return rows_without_times(out)


def _spec_file(tmp_path) -> Path:
    import tomllib  # noqa: F401 - the file below must parse as the dict above

    p = tmp_path / "resume.toml"
    p.write_text('[sweep]\nname = "resume"\nprotocol = "etfe"\n[fixed]\nduration_s = 20.0\n'
                 "[grid]\nK = [10.0, 20.0, 30.0, 40.0, 50.0, 60.0]\nseed = [1, 2, 3]\n")
    assert load_spec(p).as_dict()["grid"] == RESUME["grid"]
    return p


def _stop_after_parts(cmd, out: Path, n_parts: int, sig: int, timeout_s: float = 240.0,
                      group: bool = False):
    """Start ``cmd``, send ``sig`` once ``n_parts`` part files exist (``group``: to its whole
    process group, as a terminal does); (returncode, stderr, the pids of its children seen
    while it ran)."""
    import psutil

    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT, start_new_session=group)
    children = set()
    t0 = time.monotonic()
    try:
        while len(tables.parts(out)) < n_parts:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() - t0 < timeout_s, "no rows written"
            with_children = psutil.Process(proc.pid).children(recursive=True)
            children.update(c.pid for c in with_children)
            time.sleep(0.05)
        if group:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
        _out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, err, children


def test_sigterm_on_dask_workers_then_resume_loses_no_row(tmp_path, resume_reference):
    import psutil

    spec = _spec_file(tmp_path)
    out = tmp_path / "r.sweep"
    cmd = [*LABBENCH, "sweep", str(spec), "--out", str(out), "--workers", "2", "--flush-rows", "1"]
    code, err, children = _stop_after_parts(cmd, out, 3, signal.SIGTERM)
    assert code == 128 + signal.SIGTERM, err
    assert children, "the sweep ran on worker processes"
    deadline = time.monotonic() + 30  # the workers end with the sweep
    while any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE
              for p in children) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [p for p in children if psutil.pid_exists(p)
                and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]
    partial = tables.read_table(out)
    assert 3 <= partial.num_rows < 18
    done = subprocess.run([*LABBENCH, "sweep", str(spec), "--out", str(out), "--workers", "0",
                           "--json"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["already"] == partial.num_rows
    assert summary["computed"] == 18 - partial.num_rows
    assert rows_without_times(out) == resume_reference


def test_ctrl_c_to_the_whole_process_group_loses_no_row(tmp_path, resume_reference):
    """A terminal's Ctrl-C reaches the workers too: they go on (the sweep stops them), no
    task cut short becomes an error row that a resume would skip, no traceback."""
    spec = _spec_file(tmp_path)
    out = tmp_path / "i.sweep"
    cmd = [*LABBENCH, "sweep", str(spec), "--out", str(out), "--workers", "2", "--flush-rows", "1"]
    code, err, _ = _stop_after_parts(cmd, out, 3, signal.SIGINT, group=True)
    assert code == 128 + signal.SIGINT, err
    assert all(line.startswith("labbench sweep: ") for line in err.splitlines()), err
    partial = tables.read_table(out).to_pylist()
    assert 3 <= len(partial) < 18 and {r["status"] for r in partial} == {"ok"}
    run_sweep(load_spec(spec), out, workers=0)
    assert rows_without_times(out) == resume_reference


def test_sigkill_loses_at_most_the_unwritten_rows(tmp_path, resume_reference):
    spec = _spec_file(tmp_path)
    out = tmp_path / "k.sweep"
    cmd = [*LABBENCH, "sweep", str(spec), "--out", str(out), "--workers", "0", "--flush-rows", "1"]
    code, _err, _ = _stop_after_parts(cmd, out, 2, signal.SIGKILL)
    assert code == -signal.SIGKILL
    kept = tables.read_table(out).num_rows  # whole parts only: each one readable
    assert kept >= 2
    run_sweep(load_spec(spec), out, workers=0)
    assert rows_without_times(out) == resume_reference


# ----------------------------------------------------------------------------- CLI
def test_cli_table_csv_chart_progress_and_strict(tmp_path):
    spec = tmp_path / "s.toml"
    spec.write_text('[sweep]\nprotocol = "etfe"\n[fixed]\nduration_s = 5.0\nseed = 1\n'
                    "[grid]\nK = [20.0, 5000.0]\n"
                    '[[chart]]\nkind = "failure"\nx = "K"\ny = "seed"\n'
                    'metric = "truth.median_rel"\nthreshold = 0.01\n')
    out = tmp_path / "s.sweep"
    r = subprocess.run([*LABBENCH, "sweep", str(spec), "--out", str(out), "--workers", "0",
                        "--csv", str(tmp_path / "s.csv"), "--chart", str(tmp_path / "m.png"),
                        "--x", "K", "--y", "truth.k_max", "--color", "truth.median_rel",
                        "--strict"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 3, r.stderr  # one point refused: not ok under --strict
    assert "ETA" in r.stderr and "2/2 points, 1 not ok" in r.stderr
    assert "complete, 2/2 points" in r.stdout
    head, *lines = (tmp_path / "s.csv").read_text().splitlines()
    assert len(lines) == 2 and '"truth.median_rel"' in head
    for png in (tmp_path / "m.png", tmp_path / "s.charts" / "failure-1.png"):  # beside the table
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    r = subprocess.run([*LABBENCH, "sweep", str(spec), "--out", str(out), "--workers", "0",
                        "--csv", str(tmp_path / "s.csv")], capture_output=True, text=True,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--force" in r.stderr
    r = subprocess.run([*LABBENCH, "sweep", str(spec), "--out", str(out), "--workers", "0",
                        "--chart", str(tmp_path / "x.png"), "--x", "nope", "--y", "K"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 2 and "no column 'nope'" in r.stderr and r.stderr.count("\n") == 1


# ----------------------------------------------------------------------------- the docs' numbers
def _md_rows(path: Path, first_cell: str) -> list[list[str]]:
    """Cells of the markdown table rows that follow the header starting with ``first_cell``."""
    out, on = [], False
    for line in path.read_text().splitlines():
        if line.startswith(f"| {first_cell}"):
            on = True
            continue
        if on and line.startswith("|---"):
            continue
        if on and line.startswith("|"):
            out.append([c.strip() for c in line.strip("|").split("|")])
        elif on:
            on = False
    return out


def _pct(a, b) -> str:
    return "-" if a is None or not b else f"{100 * (a / b - 1):+.2f} %"


def test_stability_map_spec_reproduces_its_page(tmp_path):
    """docs/examples/stability-map.toml on three delays x both VEs x both simulators against
    docs/stability-map.md, every printed digit (bench/bench_stability_map.py runs them all)."""
    d = load_spec(EXAMPLES / "stability-map.toml").as_dict()
    d["grid"]["td_s"] = [0.0, 0.005, 0.02]
    s = run_sweep(spec_from_dict(d), tmp_path / "m.sweep", workers=0)
    rows = {(r["case"], round(r["td_s"] * 1e3), r["sim"]): r
            for r in tables.read_table(s.table).to_pylist()}
    checked = 0
    for section in (ROOT / "docs" / "stability-map.md").read_text().split("\n## ")[1:]:
        case = section.splitlines()[0].strip()
        for cells in _md_rows_of(section):
            td = int(cells[0])
            if (case, td, "exact") not in rows:
                continue
            r, rough = rows[(case, td, "exact")], rows[(case, td, "rough")]
            exact = r["truth.k_max"]
            assert cells[1:] == [f"{r['res.measured_boundary']:.4g}", f"{exact:.4g}",
                                 f"{r['truth.k_max_approx']:.4g}",
                                 _pct(r["res.measured_boundary"], exact),
                                 _pct(r["truth.k_max_approx"], exact),
                                 _pct(rough["res.measured_boundary"], exact),
                                 str(r["res.steps.n"])], (case, td)
            checked += 1
    assert checked == 6


def _md_rows_of(section: str) -> list[list[str]]:
    """Cells of the data rows of the markdown table in ``section``."""
    return [[c.strip() for c in line.strip("|").split("|")] for line in section.splitlines()
            if line.startswith("|") and not line.startswith(("|-", "| td"))]


def test_speed_vs_accuracy_specs_reproduce_the_analysis_page(tmp_path):
    """docs/examples/speed-vs-accuracy.toml (30 000 samples, lpm and paper) and
    identification.toml (15 000 samples, l2 and fast l1) against docs/analysis-bench.md: the
    errors and fitted values to every printed digit, the flags word for word (the times are
    the machine's; bench/bench_analysis.py runs the whole grids)."""
    page = ROOT / "docs" / "analysis-bench.md"
    d = load_spec(EXAMPLES / "speed-vs-accuracy.toml").as_dict()
    d["grid"] = {"n": [30000], "estimator": ["lpm", "paper"]}
    d["sweep"]["repeat"] = 1
    s = run_sweep(spec_from_dict(d), tmp_path / "e.sweep", workers=0)
    doc = {(c[0], c[1], c[2], c[3]): c for c in _md_rows(page, "VE |")}
    rows = tables.read_table(s.table).to_pylist()
    assert len(rows) == 16
    for r in rows:
        c = doc[(r["environment"], str(int(r["n"])), r["noise"], r["estimator"])]
        assert [c[4], c[5], c[7]] == [f"{100 * r['truth.median_rel']:.3f}",
                                      f"{100 * r['truth.max_rel']:.2f}",
                                      ", ".join(r["res.flags"].split("; ")) if r["res.flags"] else ""]
    d = load_spec(EXAMPLES / "identification.toml").as_dict()
    d["grid"]["n"] = [15000]
    d["cases"]["fit"] = d["cases"]["fit"][:2]
    s = run_sweep(spec_from_dict(d), tmp_path / "i.sweep", workers=0)
    doc = {(c[0], c[1], c[2], c[3]): c for c in _md_rows(page, "samples | Coulomb")}
    rows = tables.read_table(s.table).to_pylist()
    assert len(rows) == 8
    for r in rows:
        c = doc[(str(int(r["n"])), f"{r['coulomb_n']:g}", r["case"], r["fit"])]
        assert c[4:7] == [f"{1e3 * r['res.m']:.3f}", f"{r['res.b']:.4f}",
                          f"{100 * r['truth.worst_rel']:.3f}"]
    assert math.isfinite(rows[0]["res.l1_objective"])
