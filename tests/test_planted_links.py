"""No writer ever writes through a planted link (issue 34).

For each writer (sessions, exports, reports, figures, rig edits, sweep tables with their
charts and CSV, the GUI's settings store) the names it uses are found by running it once
in a fresh folder: every file there afterwards, and every new file it made on the way
(``labbench.safe_write.create_new``, whose random part is made repeatable here). Then in
another fresh folder a link is planted at each of those names, pointing at a file of its
own outside the folder (or at a missing one), and the writer runs again: it may replace a
link or refuse in one line, never write into what a link points at.
"""
from __future__ import annotations

import itertools
import os
from pathlib import Path

import pytest
from session_recorder import synthetic_stream

from labbench import safe_write
from labbench.cli import main
from labbench.errors import LabbenchError

RIG = "# bench\n[rig]\nname = \"bench\"\n"
SWEEP = """[sweep]
kind = "analysis"
analysis = "etfe"
[fixed]
n = 2000
[grid]
seed = [1, 2, 3]
[[chart]]
kind = "map"
x = "seed"
y = "truth.max_rel"
"""


def _session(folder: Path, name: str = "run") -> Path:
    from labbench.sessions.session_format import SessionWriter

    with SessionWriter(folder, name=name) as w:
        for rec in synthetic_stream(1500, status="success"):
            w(rec)
    return w.path


def write_session(work: Path) -> None:
    _session(work / "s")


def export_csv(work: Path, src: Path) -> None:
    assert main(["export", str(src), "--csv", str(work / "out.csv"), "--force"]) == 0


def export_hdf5(work: Path, src: Path) -> None:
    assert main(["export", str(src), "--hdf5", str(work / "out.h5"), "--force"]) == 0


def report(work: Path, src: Path) -> None:
    assert main(["report", str(src), "-o", str(work / "rep"), "--force"]) == 0


def figure(work: Path) -> None:
    assert main(["theory", "--ve", "spring", "--m", "0.1", "--b", "0.1", "--K", "50",
                 "--plot", str(work / "fig.png"), "--force"]) == 0


def rig_edit(work: Path) -> None:
    from labbench.commissioning import write_rig

    rig = work / "rig.toml"
    if not rig.exists():
        rig.write_text(RIG)
    assert write_rig(rig, {"measured_td_s": 0.001}) is not None


def sweep(work: Path) -> None:
    spec = work / "spec.toml"
    if not spec.exists():
        spec.write_text(SWEEP)
    assert main(["sweep", str(spec), "--out", str(work / "t.sweep"), "--workers", "0",
                 "--csv", str(work / "t.csv"), "--force", "--flush-rows", "2"]) == 0


CAMPAIGN = """[sweep]
protocol = "etfe"
[fixed]
ve = "spring"
duration_s = 1.0
[grid]
K = [10.0, 20.0]
[[chart]]
kind = "lines"
x = "K"
y = "acc.ed_median"
"""


def campaign(work: Path) -> None:
    spec = work / "spec.toml"
    if not spec.exists():
        spec.write_text(CAMPAIGN)
    assert main(["campaign", str(spec), "--device", "sim", "--table", str(work / "t.sweep"),
                 "--out", str(work / "s"), "--report"]) == 0


WRITERS = {"session": write_session, "export csv": export_csv, "export hdf5": export_hdf5,
           "report": report, "figure": figure, "rig edit": rig_edit, "sweep": sweep,
           "campaign": campaign}
NEEDS_SOURCE = {export_csv, export_hdf5, report}


class Names:
    """Repeatable random names, and every new file ``create_new`` makes."""

    def __init__(self, monkeypatch):
        self.made: list[Path] = []
        counter = itertools.count()
        monkeypatch.setattr(safe_write, "_token", lambda: f"t{next(counter):05d}")
        real = safe_write.create_new

        def create_new(folder, prefix, suffix, mode=None):
            fd, p = real(folder, prefix, suffix, mode)
            self.made.append(Path(p))
            return fd, p

        monkeypatch.setattr(safe_write, "create_new", create_new)


def _files(root: Path) -> set[Path]:
    return {p.relative_to(root) for p in root.rglob("*") if p.is_file() or p.is_symlink()}


@pytest.mark.parametrize("dangling", [False, True], ids=["to a file", "to a missing file"])
@pytest.mark.parametrize("name", list(WRITERS))
def test_no_writer_writes_through_a_link_planted_at_any_name_it_uses(tmp_path, monkeypatch,
                                                                   capsys, name, dangling):
    writer = WRITERS[name]
    src = _session(tmp_path / "src") if writer in NEEDS_SOURCE else None
    args = (src,) if src else ()
    first = tmp_path / "first"
    first.mkdir()
    with monkeypatch.context() as m:
        names = Names(m)
        writer(first, *args)
        used = _files(first) | {p.relative_to(first) for p in names.made
                                if p.is_relative_to(first)}
    used -= {Path("rig.toml"), Path("spec.toml")}  # the inputs, made by the writer's set-up
    assert used, "the writer wrote nothing"

    work = tmp_path / "work"
    victims = tmp_path / "victims"
    victims.mkdir()
    work.mkdir()
    planted = {}  # name -> (the file its link points at, what that file holds)
    for i, rel in enumerate(sorted(used)):
        victim = victims / f"v{i}"
        if not dangling:
            victim.write_text(f"victim {i}\n")
        (work / rel).parent.mkdir(parents=True, exist_ok=True)
        (work / rel).symlink_to(victim)
        planted[rel] = (victim, None if dangling else f"victim {i}\n")
    capsys.readouterr()
    with monkeypatch.context() as m:
        Names(m)  # the same names again, in the same order
        try:
            writer(work, *args)
        except (LabbenchError, AssertionError):
            err = capsys.readouterr().err.strip()
            assert "Traceback" not in err and err.count("\n") <= 3, err  # refused, in a line
    written_through = [rel for rel, (victim, text) in planted.items()
                       if (victim.read_text() != text if text else victim.exists())]
    assert written_through == [], f"{name}: wrote through {written_through}"
    assert sorted(p.name for p in victims.iterdir()) == (
        [] if dangling else sorted(v.name for v, _ in planted.values()))
    print(f"{name}: {len(planted)} links planted, 0 written through")


# The folders a writer makes and fills (a table, its charts and report beside it, a report's
# folder): a link planted at one is refused in one line, never written through (before, a
# link at NAME.charts had a campaign's campaign.html and .pdf written where it pointed).
FOLDERS = {"sweep": ("t.sweep", "t.charts"), "campaign": ("t.sweep", "t.charts"),
           "report": ("rep",)}


@pytest.mark.parametrize("name, folder", [(n, f) for n, fs in FOLDERS.items() for f in fs])
def test_no_writer_fills_a_folder_through_a_planted_link(tmp_path, capsys, name, folder):
    writer = WRITERS[name]
    src = _session(tmp_path / "src") if writer in NEEDS_SOURCE else None
    work, victim = tmp_path / "work", tmp_path / "victim"
    work.mkdir()
    victim.mkdir()
    (work / folder).symlink_to(victim, target_is_directory=True)
    capsys.readouterr()
    with pytest.raises(AssertionError):  # the writer's command did not exit 0
        writer(work, *((src,) if src else ()))
    err = capsys.readouterr().err.strip().splitlines()
    assert f"output folder {work / folder} is a link" in err[-1], err
    assert list(victim.iterdir()) == []
    assert not list((work / "s").glob("*.lbsession")) if name == "campaign" else True


def test_a_link_where_a_table_keeps_its_own_folder_is_refused(tmp_path, capsys):
    spec = tmp_path / "spec.toml"
    spec.write_text(SWEEP)
    table = tmp_path / "t.sweep"
    table.mkdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (table / "_claims").symlink_to(elsewhere)
    assert main(["sweep", str(spec), "--out", str(table), "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "is not a folder (a link or a file" in err
    assert list(elsewhere.iterdir()) == []


def test_the_gui_settings_store_passes_a_planted_lock_link_over(tmp_path):
    """QSettings writes as safe_write does (QSaveFile: a new file of a random name renamed
    into place, mode kept, umask applied; QLockFile: a stale lock, a planted link included,
    replaced): nothing in gui/settings.py needed changing. A link at the settings file
    itself is followed, as for a rig (an editor writes through it; it is the user's own)."""
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from labbench.gui.settings import open_settings

    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    conf = tmp_path / "labbench.conf"
    (tmp_path / "labbench.conf.lock").symlink_to(victim)
    old = os.umask(0o002)
    try:
        s = open_settings(conf)
        s.setValue("rig/file", "x.toml")
        s.sync()
    finally:
        os.umask(old)
    assert s.status() == s.Status.NoError
    assert victim.read_text() == "precious\n"
    assert conf.is_file() and not conf.is_symlink() and (conf.stat().st_mode & 0o777) == 0o664
    conf.chmod(0o600)
    s.setValue("rig/file", "y.toml")
    s.sync()
    assert (conf.stat().st_mode & 0o777) == 0o600 and "y.toml" in conf.read_text()
