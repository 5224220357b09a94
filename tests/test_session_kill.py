"""SIGKILL a real recording process at random moments: the file opens, nothing before the kill is lost or altered."""
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from session_recorder import synthetic_stream

from labbench import records
from labbench.sessions.session_format import read_session

RECORDER = Path(__file__).with_name("session_recorder.py")
SECONDS = 5.0
T = 0.001


def _record_and_kill(directory: Path, after_s: float):
    """Start the recorder, SIGKILL it ``after_s`` seconds into the recording."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(RECORDER.parent), *sys.path]))
    proc = subprocess.Popen(
        [sys.executable, str(RECORDER), str(directory), "--seconds", str(SECONDS)],
        stdout=subprocess.PIPE, text=True, env=env)
    lines: list[tuple[float, str]] = []
    started = threading.Event()

    def pump():
        for line in proc.stdout:
            lines.append((time.monotonic(), line.strip()))
            started.set()

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        assert started.wait(timeout=30), "recorder did not start"
        t_start = lines[0][0]
        time.sleep(max(0.0, t_start + after_s - time.monotonic()))
        proc.send_signal(signal.SIGKILL)
        t_kill = time.monotonic()
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        reader.join(timeout=10)
    emitted = [int(text.split()[1]) for _, text in lines if text.startswith("emitted")]
    return Path(lines[0][1]), t_kill - t_start, (emitted[-1] if emitted else 0)


def test_sigkill_loses_at_most_a_second(tmp_path):
    rng = random.Random(int(time.time()))
    # always one kill right at the start, then random moments during the run
    moments = [0.0] + [rng.uniform(0.05, SECONDS - 1.0) for _ in range(3)]
    truth = synthetic_stream(int(SECONDS / T), 100, status=None, events=False)
    for i, after in enumerate(moments):
        directory = tmp_path / f"kill{i}"
        path, elapsed_s, acknowledged = _record_and_kill(directory, after)
        reader = read_session(path)
        back = list(reader)
        assert back, f"kill at {after:.2f} s: no record survived"
        assert [r["kind"] for r in back[:2]] == [records.START, records.DESCRIPTOR][:len(back)]
        for key in ("rig", "protocol", "seed", "software"):
            assert back[0][key] == truth[0][key]
        pages = [r for r in back if r["kind"] == records.PAGE]
        for page in pages:
            want = truth[2 + page["index"]]["data"]
            for name in records.CHANNELS:
                np.testing.assert_array_equal(page["data"][name], want[name])
        n_back = sum(len(p["data"]["t"]) for p in pages)
        # everything the recorder reported as written is there
        assert n_back >= acknowledged, (after, n_back, acknowledged)
        # what was acquired by the kill minus what survived: <= 1 s (plus scheduling slack)
        lost_s = elapsed_s - n_back * T
        assert lost_s <= 1.0 + 0.25, f"kill at {after:.2f} s lost {lost_s:.3f} s"
        print(f"kill at {after:5.2f} s: {n_back} samples kept, {lost_s * 1e3:6.1f} ms lost, "
              f"tail: {reader.problem or 'clean'}")


def test_sigkill_of_labbench_run_realtime(tmp_path):
    """The real chain: ``labbench run chirp-id --realtime`` killed mid-run; what survived
    equals the same run done to completion without pacing (the simulator is deterministic)."""
    from labbench.rig import Rig
    from labbench.runner import run
    from labbench.registry import make_protocol
    from labbench.sim_backend.sim_device import open_sim

    ref = []
    run(open_sim(Rig()), make_protocol("chirp-id", duration_s=6.0, f0_hz=0.5), [ref.append])
    want = records.concat_pages(ref)
    rng = random.Random(int(time.time()))
    for i in range(2):
        out = tmp_path / f"run{i}"
        proc = subprocess.Popen(
            [sys.executable, "-m", "labbench.cli", "run", "chirp-id", "--realtime", "--out",
             str(out), "--duration-s", "6", "--f0-hz", "0.5"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 60
            while not (out.is_dir() and any(out.iterdir())):
                assert time.monotonic() < deadline and proc.poll() is None, "no session file"
                time.sleep(0.01)
            t_file = time.time()
            time.sleep(rng.uniform(0.5, 4.5))
            proc.send_signal(signal.SIGKILL)
            t_kill = time.time()
            proc.wait(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)
        path = next(out.iterdir())
        reader = read_session(path)
        back = list(reader)
        assert back[0]["kind"] == records.START and back[-1]["kind"] != records.STOP
        got = records.concat_pages(back)
        n = got["t"].size
        for name in records.CHANNELS:
            if name != "flags":  # flags carry the loop's timing bits (overruns), not physics
                np.testing.assert_array_equal(got[name], want[name][:n], err_msg=name)
        # acquisition starts just after the start record: counting from it overstates the loss
        lost_s = (t_kill - back[0]["time"]) - n * T
        assert lost_s <= 1.0 + 0.5, f"lost {lost_s:.3f} s"
        print(f"labbench run killed after {t_kill - t_file:.2f} s: {n} samples kept, "
              f"~{lost_s * 1e3:.0f} ms lost, tail: {reader.problem or 'clean'}")
