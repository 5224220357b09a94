"""Nothing overwritten, nothing lost, nothing written outside: exports, reports and figures.

Every command that writes a file goes through ``labbench.safe_write``; these
drive the real commands (``labbench export``, ``report``, ``theory --plot``,
``analyze etfe --plot``) and look at the disk afterwards.
"""
from __future__ import annotations

import os

import pytest
from session_recorder import synthetic_stream

from labbench.cli import main
from labbench.errors import UserError
from labbench.safe_write import free_name, replacing
from labbench.session_format import SessionWriter, read_session

THEORY = ["theory", "--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "50"]


def _write_session(directory, name=None, rig_name="synthetic test rig"):
    stream = synthetic_stream(1500, status="success")
    stream[0]["rig"]["name"] = rig_name
    with SessionWriter(directory, name=name) as w:
        for rec in stream:
            w(rec)
    return w.path


@pytest.fixture
def session(tmp_path):
    return _write_session(tmp_path / "s")


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return err


@pytest.mark.parametrize("fmt", ["--csv", "--hdf5"])
def test_export_never_writes_onto_its_input(session, capsys, fmt):
    before = session.read_bytes()
    link = session.with_name("alias.h5")
    os.link(session, link)  # the same file under another name
    for target in (session, link):
        for force in ([], ["--force"]):
            assert main(["export", str(session), fmt, str(target), *force]) == 2
            assert "is an input" in _one_error_line(capsys)
    assert session.read_bytes() == before
    assert len(list(read_session(session))) > 3


def test_existing_output_needs_force(session, tmp_path, capsys):
    out = tmp_path / "run.csv"
    out.write_text("keep me\n")
    assert main(["export", str(session), "--csv", str(out)]) == 2
    assert "exists; give --force" in _one_error_line(capsys)
    assert out.read_text() == "keep me\n"
    assert main(["export", str(session), "--csv", str(out), "--force"]) == 0
    assert out.read_text().startswith("# protocol=etfe")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.csv", "s"]  # no temp left


def test_interrupted_export_leaves_no_partial_file(session, tmp_path, monkeypatch):
    """The writer dies half-way: the old file stays as it was, no temporary is left."""
    from labbench import export

    out = tmp_path / "run.csv"
    out.write_text("old\n")

    def dies_half_way(fname, *a, **kw):
        with open(fname, "w") as f:
            f.write("t,force,position\n0,0,0\n")
        raise KeyboardInterrupt

    monkeypatch.setattr(export.np, "savetxt", dies_half_way)
    with pytest.raises(KeyboardInterrupt):
        export.export_csv(session, out, force=True)
    assert out.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.csv", "s"]


def test_report_replaces_a_planted_symlink_never_its_target(session, tmp_path, capsys):
    out = tmp_path / "report"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (out / f"{session.stem}.html").symlink_to(victim)
    assert main(["report", str(session), "-o", str(out)]) == 2
    assert "exists; give --force" in _one_error_line(capsys)
    assert main(["report", str(session), "-o", str(out), "--force"]) == 0
    html = out / f"{session.stem}.html"
    assert not html.is_symlink() and html.read_text().startswith("<!DOCTYPE html>")
    assert victim.read_text() == "precious\n"


def test_no_folder_is_created_that_was_not_named(session, tmp_path, capsys):
    missing = tmp_path / "no" / "such"
    assert main([*THEORY, "--plot", str(missing / "fig.png")]) == 2
    assert "does not exist" in _one_error_line(capsys)
    assert main(["report", str(session), "-o", str(missing)]) == 2
    assert "does not exist" in _one_error_line(capsys)
    assert main(["export", str(session), "--csv", str(missing / "x.csv")]) == 2
    _one_error_line(capsys)
    assert not (tmp_path / "no").exists()
    # the one folder named is created
    assert main(["report", str(session), "-o", str(tmp_path / "new")]) == 0
    assert (tmp_path / "new" / f"{session.stem}.pdf").read_bytes()[:5] == b"%PDF-"


def test_plot_refused_before_the_work_and_never_onto_the_input(session, tmp_path, capsys):
    fig = tmp_path / "fig.png"
    assert main([*THEORY, "--plot", str(fig)]) == 0
    first = fig.read_bytes()
    assert main([*THEORY, "--K", "60", "--plot", str(fig)]) == 2
    assert fig.read_bytes() == first
    capsys.readouterr()
    assert main([*THEORY, "--K", "60", "--plot", str(fig), "--force"]) == 0
    assert fig.read_bytes() != first
    csv = tmp_path / "run.csv"
    assert main(["export", str(session), "--csv", str(csv)]) == 0
    before = csv.read_bytes()
    capsys.readouterr()
    assert main(["analyze", "etfe", str(csv), "--plot", str(csv), "--force"]) == 2
    assert "is an input" in _one_error_line(capsys)
    assert csv.read_bytes() == before


def test_user_text_escaped_for_csv_header_and_matplotlib(tmp_path, capsys):
    """A rig name with a line break and mathtext: the CSV header stays one line per key,
    the PDF report draws it as typed."""
    from labbench.analysis.dataio import load_recording

    name = "rig\nwith $\\frac{bad$ math and\r\x00 controls"
    path = _write_session(tmp_path / "s", rig_name=name)
    csv = tmp_path / "run.csv"
    assert main(["export", str(path), "--csv", str(csv)]) == 0
    lines = csv.read_text().splitlines()
    rig_lines = [x for x in lines if x.startswith("# rig=")]
    assert rig_lines == ["# rig=rig\\nwith $\\frac{bad$ math and\\r\\x00 controls"]
    assert lines[len([x for x in lines if x.startswith("#")])].startswith("t,force,position")
    rec = load_recording(csv)
    assert len(rec) == 1500
    assert main(["report", str(path), "-o", str(tmp_path / "r")]) == 0
    assert (tmp_path / "r" / f"{path.stem}.pdf").read_bytes()[:5] == b"%PDF-"
    assert main([*THEORY, "--plot", str(tmp_path / "$x$^{.png")]) == 0


def test_replacing_and_free_name(tmp_path):
    target = tmp_path / "a.txt"
    with replacing(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".txt" and tmp != target
        tmp.write_text("one")
    assert target.read_text() == "one"
    with pytest.raises(UserError, match="exists"):
        with replacing(target) as tmp:
            pass
    assert free_name(target) == tmp_path / "a-2.txt"
    (tmp_path / "a-2.txt").write_text("")
    assert free_name(target) == tmp_path / "a-3.txt"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-2.txt", "a.txt"]
    assert target.read_text() == "one"
