"""A device that dies mid-run: the simulated drive in its own process (``[canopen]
sim_drive = "process"``), killed with SIGKILL. The run ends at once with one line naming
the fault, the session's stop record says the device was the cause, and nothing after the
fault waits out the SDO timeout (it did, three times: 6 s to exit; the closing note of
issue 34 has the times, which a unit test does not assert).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

from labbench.registry import make_protocol, open_device
from labbench.rig import rig_from_dict
from labbench.sessions.session_format import read_session

RIG = {"canopen": {"sim_drive": "process"}}


def test_a_killed_drive_ends_the_run_with_one_wait_at_most_and_the_device_as_cause():
    from labbench.drivers.canopen_drive import AFTER_FAULT_SDO_S
    from labbench.runner import run

    d = open_device("sim-canopen", rig_from_dict(RIG, source="test-rig"), realtime=True)
    client = d._sdo.client
    killed = threading.Event()
    after = []  # (SDO request, the answer timeout in force) once the drive is dead
    request = client.request_response

    def watched(req):
        if killed.is_set():
            after.append((bytes(req[:4]), client.RESPONSE_TIMEOUT))
        return request(req)

    client.request_response = watched
    records = []

    def killer():
        while sum(r["kind"] == "page" for r in records) < 5:
            time.sleep(0.01)
        killed.set()
        os.kill(d.peer.pid, signal.SIGKILL)
        killed_at.append(time.perf_counter())

    killed_at = []
    threading.Thread(target=killer, daemon=True).start()
    result = run(d, make_protocol("etfe", duration_s=20.0, seed=3), [records.append], rig=d.rig,
                 simulated=True)
    took = time.perf_counter() - killed_at[0]
    assert result.status == "failed" and result.cause == "device"
    assert "stale TPDO" in result.reason
    stop = records[-1]
    assert stop["kind"] == "stop" and stop["cause"] == "device" and stop["status"] == "failed"
    assert len(after) <= 1 and all(t <= AFTER_FAULT_SDO_S for _, t in after), after
    assert not d.peer.alive()
    print(f"run returned {took:.2f} s after the kill, {len(after)} SDO request after it")


def test_the_cli_says_it_in_one_line_with_the_json(tmp_path):
    import psutil

    rig = tmp_path / "rig.toml"
    rig.write_text('[canopen]\nsim_drive = "process"\n')
    out = tmp_path / "s"
    proc = subprocess.Popen([sys.executable, "-m", "labbench", "run", "etfe", "--device",
                             "sim-canopen", "--rig", str(rig), "--realtime", "--duration-s", "30",
                             "--out", str(out), "--json"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (list(out.glob("*.lbsession")) and list(out.glob("*.lbsession"))[0]
                   .stat().st_size > 200_000):  # the loop is running
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.1)
        drive = [c for c in psutil.Process(proc.pid).children()
                 if "canopen_process" in " ".join(c.cmdline())]
        assert len(drive) == 1
        killed = time.monotonic()
        drive[0].kill()
        stdout, stderr = proc.communicate(timeout=60)
        took = time.monotonic() - killed
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 1
    errors = [line for line in stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and "Traceback" not in stderr
    assert errors[0].startswith("labbench run: error: device fault after ")
    assert "stale TPDO" in errors[0] and "force zeroed, the session" in errors[0]
    summary = json.loads(stdout)
    assert summary["status"] == "failed" and summary["cause"] == "device"
    stop = list(read_session(summary["session"]))[-1]
    assert stop["kind"] == "stop" and stop["cause"] == "device"
    print(f"the command ended {took:.2f} s after the kill")
