"""The simulated drive in a process of its own, on python-can's ``udp_multicast`` bus.

As a real drive is: the host's stalls do not stall it. It answers each SYNC
when the SYNC arrives, and during a host stall its answer waits in the host's
socket; a late answer is then the drive's only if the SYNC went out on time.

The host starts ``python -m labbench.sim_backend.canopen_process`` and writes
one JSON line on its stdin (the rig, the ``[canopen]`` table, the plant's seed
and options, the multicast group and port); the child prints ``ready`` once its
drive listens. The child runs until its stdin closes: the host closing it, or
the host dying (the pipe closes with it), so no drive outlives its host. Each
drive gets a UDP port of its own, so drives of concurrent runs do not meet.
Both ends drop their own frames, which the group hands back (``EchoFreeBus``).

A paced run's drive stands in for hardware, which has a CPU of its own: the child
asks SCHED_FIFO one level below the rig's loop priority (``[realtime] priority``)
on the first CPU this process may use (the loop takes the last: ``labbench.loop.realtime``),
so the machine's other load does not make it answer late. Its thread blocks on the
bus between frames, so it never spins. Refused (no CAP_SYS_NICE, not Linux): one line
on its stderr, and it runs as an ordinary process.
"""
from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time

import can

from labbench.drivers.can_echo import EchoFreeBus
from labbench.drivers.canopen_config import CanopenConfig
from labbench.errors import DeviceConnectionError, UserError

GROUP = "239.74.163.2"  # python-can's IPv4 default group
START_TIMEOUT_S = 30.0  # the child imports numpy, scipy and canopen first


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return s.getsockname()[1]


def multicast_bus(port: int) -> EchoFreeBus:
    return EchoFreeBus(can.Bus(interface="udp_multicast", channel=GROUP, port=port))


class ProcessDrive:
    """The host's handle of a drive process; ``close()`` ends it (idempotent)."""

    def __init__(self, proc: subprocess.Popen, log, port: int):
        self.proc, self._log, self.port = proc, log, port
        self.pid = proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self) -> None:
        """Tests: the drive dies at once (SIGKILL), as a power cut."""
        if self.alive():
            os.kill(self.pid, signal.SIGKILL)

    def stderr(self) -> str:
        self._log.seek(0)
        return self._log.read().decode(errors="replace")

    def close(self) -> None:
        if self.proc.stdin and not self.proc.stdin.closed:
            try:
                self.proc.stdin.close()  # the child's signal to stop
            except OSError:
                pass
        try:
            self.proc.wait(timeout=3.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdout:
            self.proc.stdout.close()
        self._log.close()


def start_process_drive(rig, config: CanopenConfig, seed=None, paced: bool = False,
                        **options) -> tuple[ProcessDrive, EchoFreeBus]:
    """A drive process for ``rig``/``config`` that answers, and the host's bus to it;
    ``paced``: a real-time run's drive, scheduled as hardware (module doc)."""
    from labbench.loop.realtime import RealtimeConfig

    port = _free_port()
    rt = RealtimeConfig.from_rig(rig)
    try:
        spec = json.dumps({"rig": rig.as_dict(), "config": config.as_dict(), "seed": seed,
                           "options": options, "port": port,
                           "rt_priority": rt.priority - 1 if paced and rt.enabled else None})
    except TypeError as exc:
        raise UserError(f"sim-canopen in a process: an option cannot be passed on: {exc}") \
            from None
    return spawn([sys.executable, "-m", "labbench.sim_backend.canopen_process"], spec, port)


def spawn(argv: list[str], spec: str, port: int) -> tuple[ProcessDrive, EchoFreeBus]:
    """Start the drive program ``argv``, hand it ``spec`` (one JSON line) and wait for its
    ``ready``; the drive and the host's bus on ``port``. Any drive program that follows
    this module's contract (its own port, ``ready``, runs until stdin closes) can be
    started so: the tests start a CANopenNode drive this way."""
    log = tempfile.TemporaryFile()
    proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log,
                            start_new_session=True)  # a terminal's Ctrl-C goes to the host
    drive = ProcessDrive(proc, log, port)
    try:
        host_bus = multicast_bus(port)
    except BaseException:
        drive.close()
        raise
    try:
        proc.stdin.write(spec.encode() + b"\n")
        proc.stdin.flush()
        end = time.monotonic() + START_TIMEOUT_S
        line = b""
        while not line.endswith(b"\n") and time.monotonic() < end:
            ready, _, _ = select.select([proc.stdout], [], [], max(0.0, end - time.monotonic()))
            chunk = os.read(proc.stdout.fileno(), 64) if ready else b""
            if ready and not chunk:
                break  # the child is gone
            line += chunk
        if line.strip() != b"ready":
            drive.close()
            last = (drive.stderr().strip().splitlines() or ["no output"])[-1]
            raise DeviceConnectionError(f"the simulated drive process did not start: {last}")
    except BaseException:
        host_bus.shutdown()
        drive.close()
        raise
    return drive, host_bus


def _as_hardware(priority: int) -> None:
    """SCHED_FIFO ``priority`` on the first allowed CPU for this thread and the ones it
    starts (module doc); one line on stderr where refused."""
    from labbench.platform import scheduling

    if scheduling.kind() != "linux":
        print("labbench drive process: no real-time scheduling on this platform", file=sys.stderr)
        return
    cpus, refused = scheduling.allowed_cpus(), []
    cpu = cpus[0] if len(cpus) >= 2 else None
    if not scheduling.set_fifo(threading.get_native_id(), cpu, priority, [], refused):
        print(f"labbench drive process: real-time scheduling refused ({'; '.join(refused)})",
              file=sys.stderr)


def main() -> int:
    """The child: build the drive, say ``ready``, run until stdin closes."""
    from labbench.rig import Rig
    from labbench.sim_backend.canopen_peer import EDS_PATH, SimCanopenDrive, plant_for

    spec = json.loads(sys.stdin.readline())
    if spec.get("rt_priority"):
        _as_hardware(spec["rt_priority"])  # before the drive's thread starts: it inherits
    r = spec["rig"]
    rig = Rig(**{**r, "position_limits_m": tuple(r["position_limits_m"])})
    config = CanopenConfig(**spec["config"])
    plant = plant_for(rig, spec["seed"], **spec["options"])
    peer = SimCanopenDrive("", config.node_id, plant, rig.metres_per_count, rig.lever_arm_m,
                           rig.sample_time_s, eds=config.eds or EDS_PATH, config=config,
                           bus=multicast_bus(spec["port"])).start()
    try:
        print("ready", flush=True)
        while sys.stdin.buffer.read(4096):
            pass  # until EOF: the host closed the pipe or died
    finally:
        peer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
