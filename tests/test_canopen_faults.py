"""Injected faults on the CANopen path: each must end with zero force at the (simulated)
drive and a recorded, explained event from the loop."""
import time

import can
import numpy as np
import pytest

from labbench.drivers.cia402 import State
from labbench.device import DeviceFault
from labbench.errors import DeviceError, LabbenchError, UserError
from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.model.ve import VirtualEnvironment
from can_fixtures import FAST, connect, drive, no_bus_left_open, sim_parts  # noqa: F401

N = 1500
FAULT_AT = 400  # sample index (a page boundary) where the fault is injected


def run_with_fault(drive, inject, n=N, at=FAULT_AT):
    """Run a spring-damper loop on ``drive`` and call ``inject(peer)`` once at sample ``at``."""
    rig = drive.rig
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=rig.sample_time_s)
    records = []
    fired = []

    def progress(done, total):
        if done >= at and not fired:
            fired.append(done)
            inject(drive.peer)

    exc = 0.3 * np.random.default_rng(3).standard_normal(n)
    # The loop's sample watchdog above the stalls of a loaded machine (tens of ms): these
    # tests are about the faults injected at sample ``at``, not about a late answer before it.
    safety = SafetyConfig.from_rig(rig, watchdog_s=0.3)
    outcome = run_loop(drive, HapticLoop(ve, safety), exc, records.append,
                       progress=progress)
    events = [r for r in records if r["kind"] == "event"]
    return outcome, events


def assert_force_zero(peer, timeout=10.0):
    """The drive applies no torque (polled: its own timers may be what removes it; the
    bound is far above them because a loaded machine can hold the drive's thread off the
    CPU for seconds: seen at load 9)."""
    deadline = time.monotonic() + timeout
    while peer.torque_permille != 0 or peer.state is State.OPERATION_ENABLED:
        assert time.monotonic() < deadline, (peer.torque_permille, peer.state, peer.events)
        time.sleep(0.01)


def assert_fault_event(outcome, events, *words):
    assert outcome.status == "fault", outcome
    assert FAULT_AT <= outcome.n_done < N
    faults = [e for e in events if e["name"] == "device_fault"]
    assert len(faults) == 1, events
    for w in words:
        assert w in faults[0]["reason"], faults[0]["reason"]
    return faults[0]["reason"]


def test_clean_run_has_no_fault(drive):
    outcome, events = run_with_fault(drive, lambda peer: None)
    assert outcome.status == "completed" and outcome.n_done == N
    from labbench.loop.timing import EVENTS as TIMING  # a loaded host's overruns are recorded too

    assert [e["name"] for e in events if e["name"] not in TIMING] == ["enabled"]
    assert drive.peer.state is State.SWITCH_ON_DISABLED  # disabled on the way out
    assert drive.peer._get(0x1016, 1) == 0  # and no longer watching the host heartbeat


def test_emcy_from_the_drive(drive):
    outcome, events = run_with_fault(drive, lambda p: p.inject_emcy(0x2310, "over-current"))
    assert_fault_event(outcome, events, "EMCY 0x2310", "continuous over-current")
    assert_force_zero(drive.peer)
    assert drive.peer.state is State.FAULT


def test_drive_stops_answering(drive):
    outcome, events = run_with_fault(drive, lambda p: p.mute())
    assert_fault_event(outcome, events, "stale TPDO", "no answer to SYNC")
    assert_force_zero(drive.peer)  # the host's disable-voltage RPDO still reaches it


def test_transmit_failure_at_the_host(drive):
    outcome, events = run_with_fault(drive, lambda p: drive._bus.fail_tx_for(1.0))
    assert_fault_event(outcome, events, "CAN transmit error")
    # Nothing from the host gets through: the drive's RPDO timer removes the torque.
    assert_force_zero(drive.peer)
    assert any("no RPDO" in e for e in drive.peer.events), drive.peer.events


@pytest.mark.parametrize("error_class,words", [(0x080, "bus error"), (0x040, "bus off")])
def test_error_frames(drive, error_class, words):
    outcome, events = run_with_fault(drive, lambda p: p.send_error_frame(error_class))
    assert_fault_event(outcome, events, "CAN error frame", words)
    assert_force_zero(drive.peer)


def test_controller_reports_bus_off(drive):
    outcome, events = run_with_fault(drive, lambda p: drive._bus.go_bus_off())
    assert_fault_event(outcome, events, "bus-off")
    # The host cannot talk any more; the drive's own RPDO timer removes the torque.
    assert_force_zero(drive.peer)
    assert any("no RPDO" in e for e in drive.peer.events), drive.peer.events


def test_drive_leaves_operational(drive):
    def stop_node(peer):
        with peer.lock:
            peer._on_nmt(bytes([0x02, peer.node_id]))  # as if another master sent NMT stop

    outcome, events = run_with_fault(drive, stop_node)
    reason = assert_fault_event(outcome, events)
    # A STOPPED node sends no PDOs: whichever comes first, its heartbeat or the
    # missing TPDO, explains the fault.
    assert "NMT state is STOPPED" in reason or "stale TPDO" in reason, reason
    assert_force_zero(drive.peer)


def test_frozen_host_loop_is_stopped_by_the_drive(drive):
    """The loop thread itself stalls (no SYNC, no RPDO, no heartbeat) for 1.5 s."""
    seen = {}

    def freeze(peer):
        time.sleep(1.5)
        seen["torque"], seen["state"] = peer.torque_permille, peer.state

    outcome, events = run_with_fault(drive, freeze)
    # While the host was frozen the drive removed the torque on its own.
    assert seen == {"torque": 0, "state": State.FAULT}
    assert any("connection lost" in e for e in drive.peer.events)
    assert_fault_event(outcome, events, "EMCY 0x8")  # 0x8250 RPDO timeout or 0x8130 heartbeat
    assert_force_zero(drive.peer)


def test_fault_latches_until_operator_reset_which_stops_at_switch_on_disabled(drive):
    outcome, _ = run_with_fault(drive, lambda p: p.inject_emcy(0x4310, "too hot"))
    assert outcome.status == "fault"
    # A new run is refused while latched, with the reason and the way out.
    outcome, events = run_with_fault(drive, lambda p: None)
    reason = assert_fault_event_at_start(outcome, events)
    assert "0x4310" in reason and "operator" in reason
    with pytest.raises(DeviceFault, match="latched"):
        drive.enable()
    state = drive.reset_fault()
    assert state is State.SWITCH_ON_DISABLED
    assert drive.peer.state is State.SWITCH_ON_DISABLED  # not on to OPERATION ENABLED
    outcome, _ = run_with_fault(drive, lambda p: None)
    assert outcome.status == "completed"


def assert_fault_event_at_start(outcome, events):
    assert outcome.status == "fault" and outcome.n_done == 0
    (fault,) = [e for e in events if e["name"] == "device_fault"]
    return fault["reason"]


def test_drive_already_in_fault_at_start_is_not_reset_by_the_host(drive):
    drive.peer.inject_emcy(0x3210, "over-voltage")
    time.sleep(0.05)
    outcome, events = run_with_fault(drive, lambda p: None)
    reason = assert_fault_event_at_start(outcome, events)
    assert "0x3210" in reason
    assert drive.peer.state is State.FAULT


# --------------------------------------------------- refused configuration
def test_ignored_sdo_write_refuses_to_enable_naming_the_object(sim_parts):
    peer = sim_parts[2]
    peer.ignore_sdo_write(0x6072)
    with pytest.raises(UserError, match=r"0x6072:00 \(max torque\) reads back 0x0BB8 after writing 0x1388"):
        connect(sim_parts)
    assert peer.state is State.SWITCH_ON_DISABLED and peer.torque_permille == 0


def test_aborted_sdo_write_refuses_to_enable_naming_the_object(sim_parts):
    peer = sim_parts[2]
    peer.abort_sdo_write(0x607D, 1)
    with pytest.raises(DeviceError, match=r"refused writing .* to 0x607D:01"):
        connect(sim_parts)


def test_changed_safety_object_is_caught_before_the_next_run(drive):
    drive.peer.node.data_store[0x605A] = {0: (5).to_bytes(2, "little")}
    drive.peer._params.clear()
    outcome, events = run_with_fault(drive, lambda p: None)
    reason = assert_fault_event_at_start(outcome, events)
    assert "0x605A:00 (quick stop option code) is 0x0005, expected 0x0000" in reason


def test_silent_drive_at_bring_up(sim_parts):
    sim_parts[2].mute()
    t = time.monotonic()
    with pytest.raises(LabbenchError, match="NMT state not PRE-OPERATIONAL|no answer"):
        connect(sim_parts)
    # Given up, not hung: bring-up waits at most its 3 s for the NMT state and an SDO
    # timeout or two; 2 s more for a loaded machine (measured 4.0 s beside two CPU hogs).
    assert time.monotonic() - t < 3.0 + 2 * FAST["sdo_timeout_s"] + 2.0


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")  # the injected crash
def test_dead_receive_thread_in_service_phase(drive):
    """The Notifier thread dies: the next SDO exchange reports its exception."""
    class Crashing(can.Listener):
        def on_message_received(self, msg):
            raise RuntimeError("receive thread crashed")

    drive._network.notifier.add_listener(Crashing())
    drive.peer._hb_next = 0  # make the drive send a frame now
    time.sleep(0.2)
    with pytest.raises(DeviceFault, match="receive thread died: .*crashed"):
        drive.enable()
    assert drive.peer.torque_permille == 0


def test_emergency_stop_from_another_thread_mid_run(drive):
    import threading

    def estop(peer):
        t = threading.Thread(target=drive.emergency_stop)
        t.start()
        t.join(1.0)

    outcome, events = run_with_fault(drive, estop)
    assert_fault_event(outcome, events, "emergency stop")
    assert_force_zero(drive.peer)
    with pytest.raises(DeviceFault, match="latched fault: emergency stop"):
        drive.enable()


# ------------------------------------------------------ paced (hardware) mode
def paced_drive(**canopen):
    """The driver in paced mode at a coarse 50 ms period (timing is not asserted)."""
    from labbench.rig import rig_from_dict
    from labbench.sim_backend.canopen_peer import open_sim_canopen

    rig = rig_from_dict({"rig": {"sample_time_s": 0.05},
                         "canopen": {"sdo_timeout_s": 2.0, **canopen}}, source="paced-rig")
    return open_sim_canopen(rig, realtime=True)


def test_paced_mode_resyncs_after_a_late_tick_without_a_burst_of_syncs():
    with paced_drive() as d:
        assert d.describe().details["paced"] is True
        d.enable()
        for k in range(12):
            if k == 6:
                time.sleep(0.3)  # six periods late: re-phase, do not send the missed SYNCs
            d.read(1.0)
            d.command(0.0)
        assert d.counters["late_ticks"] >= 1  # (a stall of the machine may add one)
        assert d.peer.sync_count == 12  # one SYNC per read, none made up
        assert d.peer.state is State.OPERATION_ENABLED


def test_paced_mode_stale_tpdo_after_three_periods():
    with paced_drive(stale_periods=3) as d:
        d.enable()
        for _ in range(3):
            d.read(1.0)
            d.command(0.0)
        d.peer.mute()
        with pytest.raises(DeviceFault, match="stale TPDO: no answer to SYNC 3 within 150 ms"):
            d.read(1.0)
        assert_force_zero(d.peer)
