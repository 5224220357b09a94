"""The CLI and the GUI's acquisition process on a Python without the POSIX-only names.

A Windows Python has no ``signal.SIGHUP``, ``os.sched_*``, ``os.openpty``, ``termios``,
``fcntl`` or ``resource``: a module that names one at import, or a command that calls one
unguarded, crashes there. ``tests/posixless/sitecustomize.py`` deletes them in a child
process before labbench is imported (and in the processes it spawns); each command must
then succeed, with no traceback and exactly one warning line per ability it would use and
the platform lacks (``labbench.platform.missing``).
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from labbench.sessions.session_content import load_session

ROOT = Path(__file__).resolve().parents[1]
MISSING = re.compile(r"labbench: (.+?) not available on this platform \(")
SIGHUP = "the hang-up signal (SIGHUP)"
SCHED = "real-time scheduling"
PTY = "a pseudo-terminal (os.openpty, termios)"


def _env() -> dict:
    path = os.pathsep.join(p for p in (str(ROOT / "tests" / "posixless"),
                                       os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "LABBENCH_POSIXLESS": "1", "PYTHONPATH": path,
            "QT_QPA_PLATFORM": "offscreen"}


def _python(args, cwd, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=cwd,
                          env=_env(), timeout=timeout, check=False)


def _labbench(args, cwd) -> subprocess.CompletedProcess:
    return _python(["-m", "labbench", *args], cwd)


def _warned(text: str) -> list[str]:
    return sorted(MISSING.findall(text))


def test_the_child_really_lacks_the_posix_only_names(tmp_path):
    code = ("import os, signal, importlib\n"
            "gone = [n for n in ('sched_setscheduler', 'sched_getaffinity', 'openpty') "
            "if not hasattr(os, n)] + (['SIGHUP'] if not hasattr(signal, 'SIGHUP') else [])\n"
            "for m in ('termios', 'fcntl', 'resource', 'tty'):\n"
            "    try:\n        importlib.import_module(m)\n"
            "    except ImportError:\n        gone.append(m)\n"
            "print(' '.join(gone))\n")
    out = _python(["-c", code], tmp_path)
    assert out.stdout.split() == ["sched_setscheduler", "sched_getaffinity", "openpty", "SIGHUP",
                                  "termios", "fcntl", "resource", "tty"], out.stderr


RUNS = {  # name -> (arguments, the abilities it uses that the child lacks)
    "sim": (["run", "etfe", "--device", "sim", "--duration-s", "2", "--seed", "1"], [SIGHUP]),
    "sim paced": (["run", "etfe", "--device", "sim", "--realtime", "--duration-s", "1",
                   "--seed", "1"], [SCHED, SIGHUP]),
    "sim-serial": (["run", "etfe", "--device", "sim-serial", "--duration-s", "2", "--seed", "1"],
                   [PTY, SIGHUP]),
    "sim-canopen": (["run", "etfe", "--device", "sim-canopen", "--duration-s", "1", "--seed", "1"],
                    [SIGHUP]),
    "chirp-id": (["run", "chirp-id", "--device", "sim", "--duration-s", "12"], [SIGHUP]),
}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """``run(name)``: the finished process of that run and its session (each run once)."""
    out, done = tmp_path_factory.mktemp("posixless"), {}

    def get(name):
        if name not in done:
            folder = out / name.replace(" ", "-")
            p = _labbench([*RUNS[name][0], "--out", str(folder), "--json"], out)
            sessions = json.loads(p.stdout)["sessions"] if p.returncode == 0 else [None]
            done[name] = p, sessions[0]
        return done[name]

    return get


@pytest.mark.parametrize("name", RUNS)
def test_runs_on_each_simulated_device_succeed_with_one_line_per_missing_ability(run, name):
    p, session = run(name)
    assert p.returncode == 0 and "Traceback" not in p.stderr, p.stderr
    assert _warned(p.stderr) == RUNS[name][1], p.stderr
    _start, _desc, ch, _events, stop, problem = load_session(session)
    assert problem is None and stop["status"] == "success", stop
    assert len(ch["t"]) > 500


def _session(run, name) -> str:
    p, session = run(name)
    assert session is not None, p.stderr
    return session


@pytest.mark.parametrize("command", [
    lambda s, d: ["theory", "--ve", "spring-damper", "--K", "50", "--B", "1", "--m", "0.1",
                  "--b", "0.5", "--json"],
    lambda s, d: ["analyze", "etfe", s("sim"), "--json"],
    lambda s, d: ["analyze", "id", s("chirp-id"), "--json"],
    lambda s, d: ["report", "-o", str(d / "report"), s("chirp-id"), s("sim-serial")],
    lambda s, d: ["export", "--csv", str(d / "a.csv"), s("sim-canopen")],
    lambda s, d: ["export", "--hdf5", str(d / "a.h5"), s("sim paced")],
], ids=["theory", "analyze etfe", "analyze id", "report", "export csv", "export hdf5"])
def test_commands_on_the_sessions_succeed_with_one_line_for_sighup(run, tmp_path, command):
    p = _labbench(command(lambda name: _session(run, name), tmp_path), tmp_path)
    assert p.returncode == 0 and "Traceback" not in p.stderr, p.stderr
    assert _warned(p.stderr) == [SIGHUP], p.stderr


GUI_SCRIPT = """
import functools, sys, time
from labbench.gui.acquisition import Acquisition
from labbench.gui.worker import Mailbox
from labbench.registry import open_device
from labbench.rig import Rig

mailbox = Mailbox()
acq = Acquisition(mailbox)
acq.connect(functools.partial(open_device, "sim"), Rig(), {"realtime": True})
acq.run("etfe", {"duration_s": 1.0, "seed": 1}, Rig(), sys.argv[1], None, simulated=True)
seen, deadline = [], time.monotonic() + 120
while not any(k == "result" and p[0] == "run" or k == "error" for k, p in seen):
    assert time.monotonic() < deadline, seen
    seen += [(k, p) for k, p in mailbox.drain() if k in ("result", "error", "warning")]
    time.sleep(0.05)
acq.shutdown()
for kind, payload in seen:
    print(kind, payload if kind == "warning" else payload[0], flush=True)
print("exit", acq.process.exitcode)
"""


def test_the_gui_acquisition_process_runs_with_one_line_per_missing_ability(tmp_path):
    p = _python(["-c", GUI_SCRIPT, str(tmp_path)], tmp_path)
    assert p.returncode == 0 and "Traceback" not in p.stderr, p.stderr
    lines = p.stdout.splitlines()
    assert "result run" in lines and "exit 0" in lines and not any(
        x.startswith("error") for x in lines), p.stdout + p.stderr
    # SIGHUP from the child's signal handlers (its stderr); scheduling as a window warning
    assert _warned(p.stderr + p.stdout) == [SCHED, SIGHUP], p.stdout + p.stderr
    (session,) = tmp_path.glob("*.lbsession")
    assert load_session(session)[4]["status"] == "success"
