"""Fixtures for the CANopen tests: a simulated drive plus the real driver, and a
check that no test leaves a virtual CAN bus open."""
import pytest
from can.interfaces import virtual

from labbench.rig import rig_from_dict
from labbench.sim_backend.canopen_peer import connect_driver, sim_config, start_sim_drive

# Short lock-step timeout so a silent drive is detected quickly in tests.
# Drive monitors well above the stalls of a loaded machine (tens of ms). The SDO
# timeout is the simulated drive's own (2 s): an SDO answer is a thread of this
# process answering, which a loaded machine can keep off the CPU for longer than
# 0.2 s (the flaky test_sim_canopen_takes_the_plain_simulator_options); the tests
# of a silent drive fail on the NMT or the lock-step wait first.
FAST = {"lockstep_timeout_s": 0.3, "sdo_timeout_s": 2.0, "heartbeat_consumer_ms": 800,
        "rpdo_timeout_ms": 600}


def make_rig(sim: dict | None = None, **canopen):
    tables = {"canopen": {**FAST, **canopen}, **({"sim": sim} if sim else {})}
    return rig_from_dict(tables, source="test-rig")


@pytest.fixture(autouse=True)
def no_bus_left_open():
    before = {k: len(v) for k, v in virtual.channels.items()}
    yield
    left = {k: len(v) for k, v in virtual.channels.items() if len(v) > before.get(k, 0)}
    assert not left, f"virtual CAN bus(es) left open: {left}"


@pytest.fixture
def sim_parts():
    """(rig, config, peer, host_bus) not yet connected: tweak the peer first."""
    rig = make_rig()
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    yield rig, config, peer, bus
    bus.shutdown()
    peer.close()


@pytest.fixture
def drive():
    """An opened driver against a fresh simulated drive (closed after the test)."""
    rig = make_rig()
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    d = connect_driver(rig, config, peer, bus)
    yield d
    d.close()


def connect(parts, **kw):
    rig, config, peer, bus = parts
    return connect_driver(rig, config, peer, bus, **kw)
