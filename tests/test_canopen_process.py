"""The simulated drive in its own process (``sim_drive = "process"``, udp_multicast)."""
import os

import pytest

from can_fixtures import FAST, no_bus_left_open  # noqa: F401
from labbench.errors import DeviceFault
from labbench.registry import make_protocol, open_device
from labbench.rig import rig_from_dict
from labbench.runner import run
from test_canopen_vendor import FORCES, oracle_counts, run_forces


def _children() -> set[int]:
    """Live processes whose parent is this test process."""
    out = set()
    for pid in os.listdir("/proc"):
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if pid.isdigit() and int(fields[1]) == os.getpid() and fields[0] != "Z":
            out.add(int(pid))
    return out


@pytest.fixture(autouse=True)
def no_process_left():
    before = _children()
    yield
    assert _children() - before == set(), "a drive process outlived its test"


def rig(**canopen):
    return rig_from_dict({"canopen": {**FAST, "sim_drive": "process", **canopen},
                          "safety": {"watchdog_s": 2.0}}, source="test-rig")


def test_process_drive_matches_the_exact_plant_and_leaves_no_process():
    r = rig()
    d = open_device("sim-canopen", r)
    try:
        assert d.peer.alive() and d.peer.pid != os.getpid()
        assert run_forces(d, FORCES) == oracle_counts(r, FORCES, d.assessment.rated_mnm)
        assert d.counters["stray_frames"] == 0 and d._bus.echoes > 0  # own frames dropped
    finally:
        d.close()
    assert not d.peer.alive()


def test_etfe_through_the_process_drive():
    records = []
    d = open_device("sim-canopen", rig())
    result = run(d, make_protocol("etfe", duration_s=2.0, seed=3), [records.append],
                 rig=d.rig, simulated=True)
    assert result.status == "success", result.reason
    assert not d.peer.alive()


def test_killed_drive_process_is_one_line_device_error():
    d = open_device("sim-canopen", rig())
    try:
        run_forces(d, [0.0] * 10)
        d.peer.kill()
        with pytest.raises(DeviceFault) as info:
            for _ in range(2000):
                d.read(1.0)
                d.command(0.0)
        assert "\n" not in str(info.value) and "stale TPDO" in str(info.value)
    finally:
        d.close()
    assert not d.peer.alive()


def test_a_datagram_send_gets_room_past_a_short_host_preemption():
    """The driver sends with its period as the timeout; over udp_multicast that timeout is a
    poll for room before the send, so the bus floors it (a late thread is not a TX fault)."""
    import can

    from labbench.drivers.can_echo import SEND_TIMEOUT_FLOOR_S, EchoFreeBus

    class Recording:
        timeouts = []

        def send(self, msg, timeout=None):
            self.timeouts.append(timeout)

    bus = EchoFreeBus(Recording())
    for t in (0.001, None, 0.2):
        bus.send(can.Message(arbitration_id=0x80, is_extended_id=False), t)
    assert Recording.timeouts == [SEND_TIMEOUT_FLOOR_S, None, 0.2]


def test_the_factory_on_a_udp_multicast_rig_drops_its_own_frames():
    """A rig naming python-can's udp_multicast (as a lab reaching a drive process does):
    the frames the group hands back are not stray frames."""
    from labbench.drivers.canopen_drive import open_canopen
    from labbench.sim_backend.canopen_peer import sim_config
    from labbench.sim_backend.canopen_process import GROUP, start_process_drive

    r = rig()
    peer, host_bus = start_process_drive(r, sim_config(r))
    host_bus.shutdown()  # the driver opens its own from the rig, as on hardware
    try:
        hw = rig_from_dict({"canopen": {**FAST, "interface": "udp_multicast", "channel": GROUP,
                                        "bus": {"port": peer.port}},
                            "safety": {"watchdog_s": 2.0}}, source="test-rig")
        with open_canopen(hw, realtime=False) as d:
            run_forces(d, FORCES[:50])
            assert d.counters["stray_frames"] == 0 and d._bus.echoes > 100
    finally:
        peer.close()
