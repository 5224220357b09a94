"""docs/notebook.md is a worked example: its code blocks run here, in order, in a fresh folder.

``console`` blocks are ``$ labbench ...`` lines run through the CLI's ``main``;
``python`` blocks run in one shared namespace, as notebook cells do. Afterwards
the namespace is checked against the simulator's truth.
"""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from labbench.cli.main import main
from labbench.model.ve import DEFAULT_PLANT

DOC = Path(__file__).resolve().parents[1] / "docs" / "notebook.md"
FENCE = re.compile(r"^```(\w+)\n(.*?)^```", re.S | re.M)


def blocks(text: str) -> list[tuple[str, str]]:
    return [(m.group(1), m.group(2)) for m in FENCE.finditer(text)]


def test_the_page_has_both_kinds_of_block():
    kinds = [k for k, _ in blocks(DOC.read_text())]
    assert kinds[0] == "console" and kinds.count("python") >= 5


def test_notebook_page_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    ns: dict = {"__name__": "__notebook__"}
    for kind, code in blocks(DOC.read_text()):
        if kind == "console":
            for line in code.splitlines():
                assert line.startswith("$ labbench "), line
                assert main(shlex.split(line)[2:]) == 0, line
        else:
            assert kind == "python"
            exec(compile(code, f"{DOC.name} block", "exec"), ns)  # noqa: S102 - our own docs
    out = capsys.readouterr().out
    # the simulator's plant is the truth; 20 s of noise-free chirp pins it to 0.1 %
    assert ns["fit"].m == pytest.approx(DEFAULT_PLANT.m, rel=1e-3)
    assert ns["fit"].b == pytest.approx(DEFAULT_PLANT.b, rel=1e-2)
    lo, hi = ns["fit"].ci95["m"]
    assert lo <= ns["fit"].m <= hi
    # the sampled theory on the identified plant is what the ETFE follows (docs/protocols.md: 5 %)
    assert float(ns["np"].median(ns["dev"])) < 0.05
    assert (tmp_path / "chirp.png").stat().st_size > 10_000
    assert (tmp_path / "etfe.png").stat().st_size > 10_000
    assert "True" in out.splitlines()[-1]  # the CSV gives the session's numbers
    assert len(ns["df"]) == len(ns["run"].data["t"])
