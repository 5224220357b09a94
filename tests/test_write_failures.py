"""A write the system refuses: one line, the documented exit code, the JSON summary, and
everything written before it kept and readable.

The faults are injected where the bytes go: the session writer's ``os`` is a stand-in
whose ``write`` takes N bytes and then refuses with the errno a full disk (ENOSPC), a
file size limit (EFBIG), a permission change (EACCES) or a file system turned read-only
(EROFS) gives; a folder that refuses a new file is ``os.open`` refusing in it. (The
closing note of issue 34 has the same cases on a real full tmpfs, ``ulimit -f`` and a
read-only bind mount.)
"""
from __future__ import annotations

import errno
import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from labbench import records
from labbench.cli import main
from labbench.sessions.session_format import read_session

RUN = ["run", "etfe", "--device", "sim", "--duration-s", "3", "--json"]
T = 0.001


class FaultyOS:
    """``os`` for one module, whose ``write`` accepts ``limit`` bytes in all, then writes
    what still fits and refuses with ``code`` (as a disk that fills does)."""

    def __init__(self, limit: int, code: int):
        self.limit, self.code, self.written, self.refused = limit, code, 0, 0

    def __getattr__(self, name):
        return getattr(os, name)

    def write(self, fd, data):
        room = self.limit - self.written
        if room <= 0:
            self.refused += 1
            raise OSError(self.code, os.strerror(self.code))
        n = os.write(fd, bytes(data[:room]))
        self.written += n
        return n


def _run(capsys, argv):
    code = main(argv)
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    return code, json.loads(cap.out), err


def _session(path):
    reader = read_session(path)
    recs = list(reader)
    return recs, reader.problem


WORDS = {errno.ENOSPC: "the disk filling", errno.EFBIG: "the file size limit",
         errno.EACCES: "permission being refused", errno.EROFS: "the file system turning read-only"}


@pytest.mark.parametrize("code", list(WORDS), ids=[errno.errorcode[c] for c in WORDS])
def test_a_write_refused_mid_run_is_one_line_json_and_a_readable_session(tmp_path, capsys,
                                                                        monkeypatch, code):
    from labbench.loop import chain
    from labbench.sessions import session_format

    faulty = FaultyOS(200_000, code)  # about 1.5 s of pages, then refused mid-record
    monkeypatch.setattr(session_format, "os", faulty)
    forces = []  # every command the device got, and when the writer first refused
    real_loop = chain.run_loop

    def watched_loop(device, *a, **kw):
        command = device.command
        device.command = lambda f: (forces.append((faulty.refused, f)), command(f))[1]
        return real_loop(device, *a, **kw)

    monkeypatch.setattr(chain, "run_loop", watched_loop)
    rc, out, err = _run(capsys, [*RUN, "--out", str(tmp_path)])
    assert rc == 1
    assert len(err) == 1 and err[0].startswith("labbench run: error: ")
    assert f"recorded up to {WORDS[code]}" in err[0] and "readable, marked incomplete" in err[0]
    assert out["status"] == "failed" and out["cause"] == "recording"
    assert out["reason"] in err[0] and out["session"] in err[0]
    # the device: zero force from the refusal on (the loop's way out), never more
    after = [f for refused, f in forces if refused]
    assert after and all(f == 0.0 for f in after)
    # the data before the refusal: whole records, no damaged tail, no stop record
    recs, problem = _session(out["session"])
    assert problem is None
    assert [r["kind"] for r in recs[:2]] == [records.START, records.DESCRIPTOR]
    assert records.STOP not in [r["kind"] for r in recs]
    t = np.concatenate([r["data"]["t"] for r in recs if r["kind"] == records.PAGE])
    seconds = float(err[0].split("error: ")[1].split(" s recorded")[0])
    assert len(t) * T == pytest.approx(seconds, abs=0.05) and 1.0 < seconds < 3.0
    assert np.all(np.diff(t) > 0)
    assert os.path.getsize(out["session"]) <= faulty.limit  # cut back to the whole records


def test_a_session_file_that_cannot_be_created_is_one_line_and_json(tmp_path, capsys,
                                                                   monkeypatch):
    from labbench.sessions import session_format

    class NoNewSession(FaultyOS):
        def open(self, path, *a, **kw):
            if str(path).endswith(".lbsession"):
                raise PermissionError(errno.EACCES, "Permission denied", str(path))
            return os.open(path, *a, **kw)

    monkeypatch.setattr(session_format, "os", NoNewSession(1 << 40, errno.ENOSPC))
    rc, out, err = _run(capsys, [*RUN, "--out", str(tmp_path)])
    assert rc == 1 and out["status"] == "failed" and out["cause"] == "recording"
    assert len(err) == 1 and "nothing recorded: cannot create session file" in err[0]
    assert err[0].endswith("Permission denied")
    assert out["session"] is None and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("code", [errno.EACCES, errno.EROFS])
def test_a_sessions_folder_that_takes_no_file_is_refused_before_the_device_opens(
        tmp_path, capsys, monkeypatch, code):
    from labbench import registry, safe_write

    opened = []
    monkeypatch.setattr(registry, "open_device", lambda *a, **kw: opened.append(a))

    class NoProbe(FaultyOS):
        def open(self, path, *a, **kw):
            raise OSError(code, os.strerror(code), str(path))

    monkeypatch.setattr(safe_write, "os", NoProbe(0, code))
    assert main([*RUN, "--out", str(tmp_path / "s")]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and len(cap.err.strip().splitlines()) == 1
    assert "cannot write into sessions folder" in cap.err and os.strerror(code) in cap.err
    assert opened == []


def test_a_flush_refused_at_the_end_fails_the_run(tmp_path, capsys, monkeypatch):
    """fsync is where a network file system says the disk is full."""
    from labbench.sessions import session_format

    class NoSync(FaultyOS):
        def fsync(self, fd):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(session_format, "os", NoSync(1 << 40, errno.ENOSPC))
    rc, out, err = _run(capsys, [*RUN, "--out", str(tmp_path)])
    assert rc == 1 and out["status"] == "failed" and out["cause"] == "recording"
    assert len(err) == 1 and "recorded up to the disk filling" in err[0]


def test_a_report_on_a_full_disk_leaves_no_folder(tmp_path, capsys, monkeypatch):
    from session_recorder import synthetic_stream

    from labbench.sessions.session_format import SessionWriter

    with SessionWriter(tmp_path / "s") as w:
        for rec in synthetic_stream(1500, status="success"):
            w(rec)

    def full(self, *a, **kw):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))

    monkeypatch.setattr(Path, "write_text", full)
    assert main(["report", str(w.path), "-o", str(tmp_path / "rep")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the disk is full (No space left on device)" in err[0]
    assert not (tmp_path / "rep").exists()
    monkeypatch.undo()
    (tmp_path / "rep").mkdir()  # a folder that was there stays, and only what was in it
    (tmp_path / "rep" / "notes.txt").write_text("mine")
    monkeypatch.setattr(Path, "write_text", full)
    assert main(["report", str(w.path), "-o", str(tmp_path / "rep")]) == 2
    assert [p.name for p in (tmp_path / "rep").iterdir()] == ["notes.txt"]


def test_an_export_on_a_full_disk_keeps_the_old_file(tmp_path, capsys, monkeypatch):
    from session_recorder import synthetic_stream

    from labbench.sessions import export
    from labbench.sessions.session_format import SessionWriter

    with SessionWriter(tmp_path / "s") as w:
        for rec in synthetic_stream(1500, status="success"):
            w(rec)
    out = tmp_path / "run.csv"
    out.write_text("old\n")

    def fills(fname, *a, **kw):
        with open(fname, "w") as f:
            f.write("t,force\n")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(export.np, "savetxt", fills)
    assert main(["export", str(w.path), "--csv", str(out), "--force"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"cannot write {out}: the disk is full" in err[0]
    assert out.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.csv", "s"]


# ----------------------------------------------------------------------------- --write-rig
RIG = "# my bench\n[rig]\nname = \"bench\"\n\n[sim]\nextra_delay_samples = 1\n"
COMMISSION = ["run", "commission", "--write-rig", "--json"]


def test_a_read_only_rig_is_refused_before_the_run(tmp_path, capsys, monkeypatch):
    from labbench import registry

    opened = []
    monkeypatch.setattr(registry, "open_device", lambda *a, **kw: opened.append(a))
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    rig.chmod(0o444)
    assert main([*COMMISSION, "--rig", str(rig), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is read-only: make it writable" in err[0]
    assert opened == [] and rig.read_text() == RIG and stat.S_IMODE(rig.stat().st_mode) == 0o444


@pytest.mark.parametrize("code", [errno.EACCES, errno.EROFS])
def test_a_rig_in_a_read_only_folder_is_refused_before_the_run(tmp_path, capsys, monkeypatch,
                                                               code):
    from labbench import registry, safe_write

    opened = []
    monkeypatch.setattr(registry, "open_device", lambda *a, **kw: opened.append(a))
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    real_create = safe_write.create_new

    def refused_in_rig_folder(folder, *a, **kw):
        if Path(folder) == tmp_path:
            raise OSError(code, os.strerror(code), str(folder))
        return real_create(folder, *a, **kw)

    monkeypatch.setattr(safe_write, "create_new", refused_in_rig_folder)
    assert main([*COMMISSION, "--rig", str(rig), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"cannot write into the folder of rig file {rig}" in err[0]
    assert os.strerror(code) in err[0] and opened == [] and rig.read_text() == RIG


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS])
def test_a_rig_write_refused_after_the_run_is_one_line_and_json(tmp_path, capsys, monkeypatch,
                                                                code):
    from labbench import safe_write

    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    real_write = safe_write.write_file
    calls = []

    def refused(path, data, mode=None):  # the backup is written, the rig is refused
        calls.append(Path(path).name)
        if len(calls) == 2:
            raise OSError(code, os.strerror(code), str(path))
        return real_write(path, data, mode)

    monkeypatch.setattr(safe_write, "write_file", refused)
    rc, out, err = _run(capsys, [*COMMISSION, "--rig", str(rig), "--out", str(tmp_path / "s")])
    assert rc == 2 and calls == ["rig.toml.bak", "rig.toml"]
    assert len(err) == 1 and f"cannot write rig file {rig}" in err[0]
    assert "it is unchanged; the measured values are in the session" in err[0]
    assert out["status"] == "success" and out["rig_written"]["error"] in err[0]
    assert out["results"]["changes"] == {"measured_td_s": pytest.approx(0.001, abs=1e-4)}
    assert rig.read_text() == RIG
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.toml", "rig.toml.bak", "s"]


def test_devices_timing_refuses_a_read_only_rig_before_measuring(tmp_path, capsys):
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    rig.chmod(0o444)
    assert main(["devices", "--timing", "1", "--device", "sim-canopen", "--rig", str(rig),
                 "--write-rig"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is read-only: make it writable" in err[0]  # no "measuring" line
    assert rig.read_text() == RIG
