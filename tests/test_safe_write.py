"""Nothing overwritten, nothing lost, nothing written outside: exports, reports and figures.

Every command that writes a file goes through ``labbench.safe_write``; these
drive the real commands (``labbench export``, ``report``, ``theory --plot``,
``analyze etfe --plot``) and look at the disk afterwards.
"""
from __future__ import annotations

import itertools
import os
import stat

import pytest
from session_recorder import synthetic_stream

from labbench.cli import main
from labbench.errors import UserError
from labbench.safe_write import free_name, replacing
from labbench.sessions.session_format import SessionWriter, read_session

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
    from labbench.sessions import export

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


RIG_CRLF = b"# my bench\r\n[rig]\r\nname = \"bench\"\r\n\r\n[sim]\r\nsign = 1\r\n"


def test_a_rig_edit_goes_to_the_real_file_keeping_mode_and_line_breaks(tmp_path, monkeypatch):
    """A rig that is a link is edited where it lives (an editor writes through a link); the
    file keeps its mode and CRLF; links planted at the backup's and the new file's names
    are replaced or passed over, never followed."""
    from labbench import safe_write
    from labbench.commissioning import write_rig

    real = tmp_path / "shared" / "rig.toml"
    real.parent.mkdir()
    real.write_bytes(RIG_CRLF)
    real.chmod(0o640)
    link = tmp_path / "rig.toml"
    link.symlink_to(real)
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    tokens = itertools.chain(["a"] * 10, map(str, itertools.count()))  # "a" is taken
    monkeypatch.setattr(safe_write, "_token", lambda: next(tokens))
    for name in ("rig.toml.bak", ".rig.toml.bak.a.tmp", ".rig.toml.a.tmp"):
        (real.parent / name).symlink_to(victim)
    backup = write_rig(link, {"measured_td_s": 0.001})
    assert victim.read_text() == "precious\n"
    assert link.is_symlink() and link.resolve() == real
    assert backup == real.with_name("rig.toml.bak") and not backup.is_symlink()
    assert backup.read_bytes() == RIG_CRLF
    data = real.read_bytes()
    assert b"measured_td_s = 0.001\r\n" in data and data.count(b"\r\n") == data.count(b"\n")
    assert data.startswith(b"# my bench\r\n")
    assert stat.S_IMODE(real.stat().st_mode) == stat.S_IMODE(backup.stat().st_mode) == 0o640
    assert write_rig(link, {"measured_td_s": 0.001}) is None  # nothing to change: untouched
    assert real.read_bytes() == data


@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_new_files_get_the_umask_replaced_ones_keep_their_mode(session, tmp_path, umask):
    """tempfile.mkstemp's 0600 made reports and sweep parts unreadable to a supervisor
    logged in as another user; a session was 0644 whatever the umask."""
    old = os.umask(umask)
    try:
        assert main(["report", str(session), "-o", str(tmp_path / "rep")]) == 0
        csv = tmp_path / "run.csv"
        assert main(["export", str(session), "--csv", str(csv)]) == 0
        new_session = _write_session(tmp_path / "s2")
    finally:
        os.umask(old)
    for p in [*(tmp_path / "rep").iterdir(), csv, new_session]:
        assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask, p
    csv.chmod(0o600)
    assert main(["export", str(session), "--csv", str(csv), "--force"]) == 0
    assert stat.S_IMODE(csv.stat().st_mode) == 0o600
