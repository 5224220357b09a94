"""Fuzz: the command line of every command, with hostile values in every option.

Each entry point starts from a valid command line; a seeded generator replaces
one or two option values with hostile ones (numbers at and past the limits of
a double, NaN, text, empty, mathtext, control characters; for file arguments:
a FIFO, /dev/zero, a directory, a missing file, the input itself), drops a
token or adds an unknown flag. The property is tests/fuzzing.py's. The
default suite runs a fixed number of cases per entry point; ``-m slow`` runs
many more with other seeds.
"""
from __future__ import annotations

import os
import random

import pytest
from fuzzing import HOSTILE_NUMBERS, Tally, run_cli
from fuzzing import scratch_cwd  # noqa: F401 - autouse fixture
from session_recorder import synthetic_stream

from labbench.registry import protocol_class
from labbench import records
from labbench.sessions.session_format import SessionWriter

CI_CASES = 12  # per entry point
SLOW_CASES = 150


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzzcli")
    with SessionWriter(d, name="good") as w:
        records.fan_out(synthetic_stream(3000, page_size=500, status="success"), [w])
    csv = d / "good.csv"
    from labbench.cli import main

    assert main(["export", str(w.path), "--csv", str(csv)]) == 0
    fifo = d / "fifo"
    os.mkfifo(fifo)
    (d / "folder").mkdir()
    spec = d / "k.toml"
    spec.write_text('[sweep]\nprotocol = "etfe"\n[fixed]\nduration_s = 0.5\nve = "spring"\n'
                    '[grid]\nK = [10.0, 20.0]\n')
    return {"session": w.path, "csv": csv, "fifo": fifo, "dir": d, "spec": spec}


def _paths(f):
    d = f["dir"]
    return [str(f["fifo"]), "/dev/zero", str(d / "folder"), str(d / "missing"), "", "/proc",
            str(f["session"]), str(f["csv"]), "/proc/self/mem", str(d / "no" / "such" / "x")]


def _entries(f):
    d = f["dir"]
    out = str(d / "runs")
    run_flags = {}
    for name in ("etfe", "chirp-id", "stability"):
        cfg = protocol_class(name).Config
        run_flags[name] = ["--" + fl.name.replace("_", "-") for fl in cfg.__dataclass_fields__.values()
                           if fl.name != "sample_time_s" and str(fl.type) != "bool"]
    theory = ["theory", "--ve", "spring-damper", "--m", "0.094", "--b", "0.1", "--K", "50",
              "--B", "1", "--w0", "125"]
    return {
        # entry: (base argv, options whose values are fuzzed, options taking a file)
        "theory": (theory, ["--m", "--b", "--K", "--B", "--w0", "--T", "--td", "--w", "--ve",
                            "--model"], ["--plot"]),
        "theory --model sampled": (theory + ["--model", "sampled", "--td", "0.002"],
                                   ["--m", "--b", "--K", "--B", "--w0", "--T", "--td"], []),
        "analyze id": (["analyze", "id", str(f["csv"])],
                       ["--model", "--method", "--cutoff", "--force-hold"], ["FILE"]),
        "analyze etfe": (["analyze", "etfe", str(f["csv"]), "--m", "0.094", "--b", "0.1"],
                         ["--estimator", "--window", "--m", "--b"], ["FILE", "--plot"]),
        "run etfe": (["run", "etfe", "--duration-s", "2", "--out", out, "--json",
                      "--plant-from", "nominal"], run_flags["etfe"], ["--rig", "--out"]),
        "run chirp-id": (["run", "chirp-id", "--duration-s", "4", "--f0-hz", "0.5", "--out", out,
                          "--json"], run_flags["chirp-id"], ["--rig", "--out"]),
        "run stability": (["run", "stability", "--K", "30", "--td-s", "0.002", "--out", out,
                           "--json", "--plant-from", "nominal"], run_flags["stability"], ["--rig"]),
        "replay": (["replay", str(f["session"]), "--speed", "1000"], ["--speed"], ["FILE"]),
        "export": (["export", str(f["session"]), "--csv", str(d / "x.csv"), "--force"], [],
                   ["FILE", "--csv", "--hdf5"]),
        "report": (["report", str(f["session"]), "-o", str(d / "rep"), "--force"], [],
                   ["FILE", "-o"]),
        "devices": (["devices", "--json"], [], ["--rig"]),
        "design": (["design", "--K", "50", "--B", "0,1", "--w0", "60,125", "--out", out,
                    "--noise-limit-n", "0.004", "--json"],
                   ["--K", "--B", "--w0", "--T", "--noise-limit-n", "--plant-m-kg", "--plant-b",
                    "--coulomb-n", "--device-delay-s", "--quantum-m", "--force-noise-n",
                    "--band-hz", "--at-w", "--motion-m-s", "--excitation-n", "--objective",
                    "--noise-of"],
                   ["--rig", "--out", "--plot", "--compare"]),
        "campaign": (["campaign", str(f["spec"]), "--device", "sim", "--table",
                      str(d / "c.sweep"), "--out", out, "--json", "--plant-from", "nominal"],
                     ["--plant-m-kg", "--plant-b", "--rt-priority", "--device"],
                     ["FILE", "--rig", "--table", "--out"]),
    }


def _set_value(argv: list, flag: str, value: str) -> None:
    """The value after ``flag`` becomes ``value`` (the flag is added when absent)."""
    if flag in argv:
        j = argv.index(flag) + 1
        argv[j:j + 1] = [value]  # the flag may be last (its value deleted before)
    else:
        argv += [flag, value]


def _mutate(rng: random.Random, base, numeric, paths, hostile_paths):
    argv = list(base)
    for _ in range(rng.choice((1, 1, 2))):
        what = rng.random()
        if what < 0.55 and numeric:
            flag, value = rng.choice(numeric), rng.choice(HOSTILE_NUMBERS)
            _set_value(argv, flag, value)
        elif what < 0.8 and paths:
            flag, value = rng.choice(paths), rng.choice(hostile_paths)
            if flag == "FILE":
                i = 2 if argv[0] == "analyze" else 1
                argv[i:i + 1] = [value]  # (a token may have been deleted before)
            else:
                _set_value(argv, flag, value)
        elif what < 0.9 and len(argv) > 1:
            del argv[rng.randrange(1, len(argv))]
        else:
            argv.insert(rng.randrange(1, len(argv) + 1), rng.choice(("--bogus", "-x", "--K", "--")))
    return argv


def _fuzz(files, n_cases: int, seed: int) -> Tally:
    tally = Tally()
    hostile_paths = _paths(files)
    for entry, (base, numeric, paths) in _entries(files).items():
        rng = random.Random(f"{seed}:{entry}")
        for _ in range(n_cases):
            argv = _mutate(rng, base, numeric, paths, hostile_paths)
            tally.add(entry, run_cli(argv),
                      allow_failed_run=argv[0] in ("run", "devices", "campaign"))
    print("\n" + tally.report())
    return tally


def test_cli_arguments_of_every_command(files):
    failures = _fuzz(files, CI_CASES, seed=15).failures
    assert failures == [], "\n".join(failures)
    # nothing was written outside the folders the cases named
    assert sorted(p.name for p in files["dir"].iterdir()) >= ["fifo", "folder", "good.csv"]
    assert not (files["dir"] / "no").exists()


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_cli_arguments_soak(files, seed):
    assert _fuzz(files, SLOW_CASES, seed).failures == []
