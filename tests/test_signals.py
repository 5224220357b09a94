"""SIGINT, SIGTERM and SIGHUP stop a run safely whatever disposition the process inherited.

Real processes, paced in real time: ``labbench run`` and the GUI's acquisition
process, each started with the three signals explicitly ignored (as under
``nohup`` or a background job) and explicitly default, then sent each signal
mid-run. Every case must end with force zeroed by the loop (its ``stop``
event), a session closed by an ``aborted`` stop record naming the signal, and
exit status 128 + n. The combinations run concurrently to keep the suite short.
"""
from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from labbench.platform.signals import ending_signals
from labbench.sessions.session_content import load_session

ROOT = Path(__file__).resolve().parents[1]
SIGNALS = ending_signals()
DISPOSITIONS = {"ignored": signal.SIG_IGN, "default": signal.SIG_DFL}
CASES = [(d, s) for d in DISPOSITIONS for s in SIGNALS]
# On this shared machine a paced loop can stall for tens of ms: a lenient watchdog, since
# these tests are about signals, not pacing.
RIG = "[safety]\nwatchdog_s = 2.0\n"


def _caught(pid: int) -> int:
    """The process's caught-signal mask (/proc/<pid>/status SigCgt)."""
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1], 16) for line in f if line.startswith("SigCgt:"))


def _catches_all(pid: int) -> bool:
    mask = _caught(pid)
    return all(mask >> (s - 1) & 1 for s in SIGNALS)


def _wait(predicate, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _check_session(path: Path, signum: int) -> None:
    name = signal.Signals(signum).name
    _start, _desc, ch, events, stop, problem = load_session(path)
    assert problem is None, problem
    assert stop is not None and stop["status"] == "aborted", stop
    assert name in stop["reason"], stop["reason"]
    assert any(e.get("name") == "stop" for e in events)  # the loop's way out: zero, disable
    assert 0 < len(ch["t"]) < 30_000


def _set_dispositions(disposition) -> None:
    for s in SIGNALS:
        signal.signal(s, disposition)


def test_cli_run_ends_aborted_on_each_signal_whatever_was_inherited(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    procs = []
    for disp, signum in CASES:
        out = tmp_path / f"{disp}-{signum}"
        p = subprocess.Popen(
            [sys.executable, "-m", "labbench.cli", "run", "etfe", "--realtime", "--rig", str(rig),
             "--duration-s", "30", "--seed", "1", "--out", str(out), "--json"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env,
            preexec_fn=functools.partial(_set_dispositions, DISPOSITIONS[disp]))
        procs.append((disp, signum, out, p))
    try:
        for disp, signum, out, p in procs:
            _wait(lambda: list(out.glob("*.lbsession")) or p.poll() is not None, 120,
                  f"a session file ({disp}, {signum})")
            assert p.poll() is None, p.communicate()
            assert _catches_all(p.pid)  # its own handlers replaced what it inherited
        time.sleep(0.5)  # samples on record in every run
        for _disp, signum, _out, p in procs:
            p.send_signal(signum)
        for disp, signum, _out, p in procs:
            stdout, stderr = p.communicate(timeout=60)
            assert p.returncode == 128 + signum, (disp, signum, stderr)
            assert "Traceback" not in stderr
            result = json.loads(stdout)
            assert result["status"] == "aborted"
            assert signal.Signals(signum).name in result["reason"]
            _check_session(Path(result["session"]), signum)
    finally:
        for *_, p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()


def test_cli_outside_a_run_exits_128_plus_n(tmp_path):
    """Outside a run (a replay paced at real time) a signal ends the command with one line."""
    from labbench.cli import main

    assert main(["run", "etfe", "--duration-s", "3", "--out", str(tmp_path)]) == 0
    (session,) = tmp_path.glob("*.lbsession")
    procs = []
    for disp, signum in (("ignored", signal.SIGINT), ("default", signal.SIGTERM)):
        p = subprocess.Popen([sys.executable, "-m", "labbench.cli", "replay", str(session),
                              "--speed", "0.05"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, cwd=ROOT,
                             preexec_fn=functools.partial(_set_dispositions, DISPOSITIONS[disp]))
        procs.append((disp, signum, p))
    try:
        for disp, signum, p in procs:
            _wait(lambda: p.poll() is not None or _catches_all(p.pid), 60, f"handlers ({disp})")
            assert p.poll() is None
        time.sleep(0.3)
        for disp, signum, p in procs:
            p.send_signal(signum)
            _stdout, stderr = p.communicate(timeout=30)
            assert p.returncode == 128 + signum, (disp, signum, stderr)
            assert stderr.strip() == f"labbench replay: interrupted by {signal.Signals(signum).name}" \
                + (" (Ctrl-C)" if signum == signal.SIGINT else "")
    finally:
        for *_, p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()


@pytest.mark.parametrize("disp", DISPOSITIONS)
def test_acquisition_process_ends_aborted_on_each_signal(tmp_path, disp):
    from labbench.gui.acquisition import Acquisition
    from labbench.gui.worker import Mailbox
    from labbench.registry import open_device
    from labbench.rig import rig_from_dict

    rig = rig_from_dict({"safety": {"watchdog_s": 2.0}})
    runs = []
    saved = {s: signal.getsignal(s) for s in SIGNALS}
    try:
        _set_dispositions(DISPOSITIONS[disp])  # what the spawned children inherit
        for signum in SIGNALS:
            mailbox = Mailbox()
            acq = Acquisition(mailbox)
            acq.connect(functools.partial(open_device, "sim"), rig, {"realtime": True})
            out = tmp_path / str(signum)
            acq.run("etfe", {"duration_s": 30.0, "seed": 1}, rig, out, None, simulated=True)
            runs.append((signum, acq, mailbox, out))
    finally:
        for s, h in saved.items():
            signal.signal(s, h)
    try:
        for signum, acq, mailbox, out in runs:
            seen = []

            def streaming(mailbox=mailbox, seen=seen):
                seen.extend(mailbox.drain())
                errors = [p for k, p in seen if k == "error"]
                assert not errors, errors
                return sum(k == "record" for k, _ in seen) >= 5

            _wait(streaming, 120, f"records from the acquisition process ({signum})")
            assert _catches_all(acq.process.pid)
        time.sleep(0.5)
        for signum, acq, _mailbox, _out in runs:
            os.kill(acq.process.pid, signum)
        for signum, acq, _mailbox, out in runs:
            acq.process.join(30)
            assert acq.process.exitcode == 128 + signum
            (path,) = out.glob("*.lbsession")
            _check_session(path, signum)
    finally:
        for _signum, acq, _mailbox, _out in runs:
            acq.shutdown(timeout=2.0)
