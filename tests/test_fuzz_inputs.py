"""Fuzz: rig files and analysis CSVs, and the memory of reading a long CSV.

Rig files: a valid rig mutated by a seeded generator (hostile values for every
field, misspelt fields and tables, tables that are numbers or arrays, arrays
of tables, deep nesting, invalid UTF-8, binary, oversized files) go through
``labbench run stability --rig``. CSVs: a valid export mutated the same way
(hostile metadata values, fs against the time column, missing or repeated
columns, bad cells, non-uniform or decreasing time, control characters, huge
lines and comment floods) go through ``analyze id`` and ``analyze etfe``.
Property: tests/fuzzing.py.
"""
from __future__ import annotations

import os
import random
import tracemalloc

import numpy as np
import pytest
from fuzzing import HOSTILE_NUMBERS, Tally, run_cli
from fuzzing import scratch_cwd  # noqa: F401 - autouse fixture
from session_recorder import synthetic_stream

from labbench.analysis import dataio
from labbench import records
from labbench.errors import UserError
from labbench.sessions.session_format import SessionWriter

RIG = """[rig]
name = "bench"
sample_time_s = 0.001
force_limit_n = 5.0
position_limits_m = [-0.1, 0.1]
velocity_limit_m_s = 2.0
nominal_mass_kg = 0.094
nominal_damping_ns_m = 0.1

[safety]
watchdog_s = 0.5
energy_limit_j = 0.05
force_rate_limit_n_per_s = 10000.0

[sim]
m = 0.094
b = 0.1
"""
TOML_VALUES = ["1e308", "-1e308", "nan", "inf", "-inf", "0", "-1", "1e-320", '"text"', "[]",
               "[1, 2, 3]", "{ a = 1 }", "true", "1979-05-27", '"' + "x" * 5000 + '"',
               '"$\\\\frac{x$"', '"line\\nbreak"', "9" * 30, "0.0000001"]


def _rig_cases(rng: random.Random, n: int):
    lines = RIG.splitlines()
    keyed = [i for i, x in enumerate(lines) if "=" in x]
    tables = [i for i, x in enumerate(lines) if x.startswith("[")]
    for _ in range(n):
        out = list(lines)
        what = rng.random()
        if what < 0.5:
            i = rng.choice(keyed)
            out[i] = out[i].split("=")[0] + "= " + rng.choice(TOML_VALUES)
        elif what < 0.6:
            i = rng.choice(keyed)
            key = out[i].split("=")[0].strip()
            j = rng.randrange(len(key))
            out[i] = key[:j] + key[j + 1:] + " =" + out[i].split("=", 1)[1]  # a typo
        elif what < 0.7:
            i = rng.choice(tables)
            out[i] = rng.choice(("[saftey]", "[rigg]", "[[rig]]", "[sim.extra]", "[Safety]"))
        elif what < 0.8:
            out.insert(0, rng.choice(("rig = 5", "safety = [1, 2]", "sim = \"x\"",
                                      "deep = " + "[" * 5000 + "]" * 5000, "x = 1")))
        else:
            yield rng.choice((b"", b"\xff\xfe\x00garbage", bytes(range(256)) * 10,
                              RIG.encode() + b"\n# " + b"x" * (2 << 20),
                              RIG.replace("bench", "b\udcff", 1).encode("utf-8", "surrogateescape"),
                              RIG.encode() + b"\n[rig]\nname = 'again'\n"))
            continue
        yield "\n".join(out).encode()


@pytest.mark.parametrize("n_cases,seed", [pytest.param(40, 15),
                                          pytest.param(400, 1, marks=pytest.mark.slow)])
def test_rig_files(tmp_path, n_cases, seed):
    tally = Tally()
    for k, text in enumerate(_rig_cases(random.Random(seed), n_cases)):
        rig = tmp_path / f"rig{k}.toml"
        rig.write_bytes(text)
        o = run_cli(["run", "stability", "--rig", rig, "--K", "30", "--td-s", "0.002",
                     "--plant-from", "nominal", "--out", tmp_path / "runs", "--json"])
        tally.add("run --rig", o, allow_failed_run=True)
    print("\n" + tally.report())
    assert tally.failures == [], "\n".join(tally.failures)


@pytest.fixture(scope="module")
def csv_text(tmp_path_factory):
    from labbench.cli import main

    d = tmp_path_factory.mktemp("fuzzcsv")
    with SessionWriter(d, name="s") as w:
        records.fan_out(synthetic_stream(3000, page_size=500, status="success"), [w])
    assert main(["export", str(w.path), "--csv", str(d / "good.csv")]) == 0
    return (d / "good.csv").read_text()


META_KEYS = ["fs", "ve", "K", "B", "w0", "td", "m", "b", "force_hold", "protocol"]


def _csv_cases(rng: random.Random, text: str, n: int):
    lines = text.splitlines()
    n_meta = sum(x.startswith("#") for x in lines)
    for _ in range(n):
        out = list(lines)
        what = rng.random()
        if what < 0.35:
            out.insert(0, f"# {rng.choice(META_KEYS)}={rng.choice(HOSTILE_NUMBERS + ['sample', 'x'])}")
        elif what < 0.45:
            out[n_meta] = rng.choice(("t,force", "t,t,force,position", "T,FORCE,POSITION",
                                      "position,force,t", "", "t;force;position"))
        elif what < 0.65:
            i = rng.randrange(n_meta + 1, len(out))
            cells = out[i].split(",")
            cells[rng.randrange(3)] = rng.choice(HOSTILE_NUMBERS)
            out[i] = ",".join(cells)
        elif what < 0.75:
            i = rng.randrange(n_meta + 1, len(out))
            out[i] = rng.choice(("", "1,2", "1,2,3,4,5,6,7,8,9,10,11", "\x00,\x00,\x00", ",,,"))
        elif what < 0.85:
            head, rows = out[:n_meta + 1], out[n_meta + 1:]
            choice = rng.random()
            if choice < 0.3:
                rows = rows[::-1]  # decreasing time
            elif choice < 0.6:
                rows = rows[:rng.choice((1, 10, 63, 64, 65))]
            else:
                rows = rows[::2] + rows[1::2]
            out = head + rows
        else:
            yield rng.choice((b"", b"\xef\xbb\xbf" + text.encode(), text.replace("\n", "\r\n").encode(),
                              b"\xff\xfe" + text.encode()[:500], b"#" + b"x" * 100_000 + b"\n" + text.encode(),
                              b"# a=b\n" * 20_000 + text.encode()))
            continue
        yield ("\n".join(out) + "\n").encode()


@pytest.mark.parametrize("n_cases,seed", [pytest.param(40, 15),
                                          pytest.param(400, 1, marks=pytest.mark.slow)])
def test_analysis_csvs(tmp_path, csv_text, n_cases, seed):
    tally = Tally()
    for k, data in enumerate(_csv_cases(random.Random(seed), csv_text, n_cases)):
        path = tmp_path / f"c{k}.csv"
        path.write_bytes(data)
        for entry in ("id", "etfe"):
            tally.add(f"analyze {entry}", run_cli(["analyze", entry, path]))
    print("\n" + tally.report())
    assert tally.failures == [], "\n".join(tally.failures)


def _long_csv(path, n_rows: int) -> None:
    t = np.arange(n_rows) * 1e-3
    rng = np.random.default_rng(1)
    with open(path, "w") as f:
        f.write("# fs=1000\nt,force,position,extra\n")
        for lo in range(0, n_rows, 1 << 20):
            hi = min(lo + (1 << 20), n_rows)
            block = np.column_stack([t[lo:hi], rng.normal(size=hi - lo), rng.normal(size=hi - lo),
                                     np.zeros(hi - lo)])
            np.savetxt(f, block, delimiter=",", fmt="%.9g")


@pytest.mark.parametrize("n_rows", [pytest.param(600_000),
                                    pytest.param(10_000_000, marks=pytest.mark.slow)])
def test_a_long_csv_is_read_in_chunks(tmp_path, n_rows):
    """Peak memory of reading: the three arrays twice (chunks, then joined) plus one chunk of
    text lines, whatever the length (it was the whole file as a list of lines)."""
    path = tmp_path / "long.csv"
    _long_csv(path, n_rows)
    tracemalloc.start()
    try:
        rec = dataio.load_recording(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(rec) == n_rows and rec.fs == pytest.approx(1000.0)
    arrays = 3 * 8 * n_rows
    line_bytes = path.stat().st_size / n_rows
    chunk = dataio.CHUNK_ROWS * (line_bytes + 80)  # one chunk of str lines (+ object overhead)
    print(f"\n{n_rows} rows: peak {peak / 2**20:.1f} MiB = {peak / arrays:.2f} x the arrays "
          f"({arrays / 2**20:.1f} MiB); file {path.stat().st_size / 2**20:.0f} MiB")
    assert peak <= 2 * arrays + chunk


# ----- what a CSV holds, bounded (issue 44) ---------------------------------------------------
def _rows(n: int) -> str:
    return "# fs=1000\nt,force,position\n" + "".join(
        f"{k * 1e-3:.6f},{np.sin(k):.6f},{1e-3 * np.cos(k):.6f}\n" for k in range(n))


def _refused_within(path, words: str, budget: float = 64e6) -> float:
    """The CSV at ``path`` refused in one line with ``words``, reading it under tracemalloc:
    the peak [bytes] it took."""
    tracemalloc.start()
    try:
        with pytest.raises(UserError) as info:
            dataio.load_recording(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert words in str(info.value) and "\n" not in str(info.value), str(info.value)
    assert peak < budget, peak
    return peak


def test_a_gigabyte_csv_ending_in_nuls_is_refused_at_its_first_nul(tmp_path):
    """A sparse file: 200 rows, then zeros to 1 GiB (no disk used). Before: read as one line,
    30.7 s and 2.2 GB before a MemoryError traceback under a 3 GB cap."""
    path = tmp_path / "nul.csv"
    path.write_text(_rows(200))
    os.truncate(path, 1 << 30)
    peak = _refused_within(path, "line 203 holds a NUL byte")
    print(f"\n1 GiB ending in NULs: refused, peak {peak / 2**20:.1f} MiB traced")
    o = run_cli(["analyze", "etfe", path])
    assert o.code == 2 and o.crash is None and "NUL" in o.err, o.err


def test_a_long_line_blank_lines_and_too_many_rows_are_refused_as_they_come(tmp_path,
                                                                         monkeypatch):
    long = tmp_path / "long.csv"
    long.write_text(_rows(100) + "1," * (dataio.MAX_LINE_CHARS // 2 + 10) + "\n" + _rows(10))
    _refused_within(long, "line 103 is longer than 65536 characters")
    blank = tmp_path / "blank.csv"
    blank.write_text(_rows(100) + "\n" * (dataio.MAX_BLANK_LINES + 1) + "0.1,0,0\n")
    _refused_within(blank, f"more than {dataio.MAX_BLANK_LINES} blank lines")
    monkeypatch.setattr(dataio, "MAX_ROWS", 1000)
    many = tmp_path / "many.csv"
    many.write_text(_rows(1500))
    _refused_within(many, "more than 1000 rows")
    few = tmp_path / "few.csv"
    few.write_text(_rows(800) + "\n\n")  # within the bounds, trailing blank lines: read
    assert len(dataio.load_recording(few)) == 800
