"""Injected faults on the serial stream: each ends with force zero and a recorded, explained event.

Faults are scheduled on the simulated board by sample index (boot = 0; the
driver's sync at open takes the first samples), so every run is repeatable.
The whole chain runs: real driver on a pty, labbench.runner, labbench.loop.chain.
"""

import math
import time

import numpy as np
import pytest

from labbench.drivers.serial_stream import FLAG_LINK_ERRORS, FLAG_LOST, SerialConfig, SerialStream
from labbench import records
from labbench.device import DeviceFault
from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.rig import rig_from_dict
from labbench.runner import run
from labbench.loop.safety import DEVICE
from labbench.model.ve import VirtualEnvironment
from labbench.registry import make_protocol
from labbench.platform.serial_peer import SocketTransport
from labbench.sim_backend import arduino_peer
from labbench.sim_backend.arduino_peer import Fault, connect_sim_serial
from test_serial_stream import no_board_left_running  # noqa: F401

FAULT_AT = 400  # board sample index: well inside the run, after the enable gate


def make_rig(T=0.001, **serial_table):
    # A lock-step board's time is virtual: the loop watchdog must not judge this
    # shared machine's scheduling hiccups (tens of ms under load) as a frozen loop.
    return rig_from_dict(
        {"rig": {"sample_time_s": T}, "serial": serial_table, "safety": {"watchdog_s": 2.0}},
        source="test.toml",
    )


def run_etfe(drv, rig, duration_s=1.0, seed=5):
    protocol = make_protocol(
        "etfe", duration_s=duration_s, seed=seed, sample_time_s=rig.sample_time_s
    )
    stream = []
    result = run(drv, protocol, [stream.append], rig=rig)
    return result, stream


@pytest.mark.parametrize(
    "fault, explained, transport",
    [
        (Fault("flip", FAULT_AT), "1 serial sample(s) lost before seq", "pty"),
        (Fault("drop", FAULT_AT, n=3), "3 serial sample(s) lost before seq", "pty"),
        (Fault("garbage", FAULT_AT, n=40), "serial link error: bytes discarded before seq", "pty"),
        (Fault("reboot", FAULT_AT), "board rebooted: time went from", "pty"),
        (Fault("stall", FAULT_AT, seconds=0.8), "serial stream stale: no sample for", "pty"),
        (Fault("unplug", FAULT_AT), "serial port lost", "pty"),
        # the transport where there is no pty (Windows): the host's socket:// port fails too
        (Fault("unplug", FAULT_AT), "serial port lost", "socket"),
    ],
)
def test_fault_during_a_run_zeroes_force_and_is_recorded(fault, explained, transport, monkeypatch):
    if transport == "socket":
        monkeypatch.setattr(arduino_peer, "open_transport", lambda warn=None: SocketTransport())
    rig = make_rig()
    drv, peer = connect_sim_serial(rig, seed=11, faults=[fault])
    result, stream = run_etfe(drv, rig)
    assert result.status == "failed"
    faults = [r for r in stream if r["kind"] == records.EVENT and r["name"] == "device_fault"]
    assert len(faults) == 1 and explained in faults[0]["reason"]
    assert "force zeroed" in faults[0]["reason"]
    assert stream[-1]["kind"] == records.STOP and stream[-1]["status"] == "failed"
    # Host side: nothing but zero is commanded now. Board side: zero from the fault on.
    assert drv.commanded_force_n == 0.0 and drv.fault
    # A lost sample cannot be answered: the board holds its last command over
    # its period (at most 3, then its watchdog zeroes), as a free-running board would.
    applied = np.array(peer.applied)
    held = fault.n if fault.kind == "drop" else 1
    assert len(applied) >= FAULT_AT
    assert np.all(applied[FAULT_AT + held :] == 0.0)
    assert np.any(applied[:FAULT_AT] != 0.0)  # the run really pushed before the fault
    assert peer.error is None


def test_a_tolerated_drop_is_flagged_counted_and_the_run_goes_on():
    rig = make_rig(tolerate_drops=1, tolerate_link_errors=True)
    drv, _peer = connect_sim_serial(rig, seed=11, faults=[Fault("flip", FAULT_AT)])
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=rig.sample_time_s)
    excitation = np.random.default_rng(1).normal(0.0, 0.5, 1000)
    stream = []
    with drv:
        outcome = run_loop(
            drv, HapticLoop(ve, SafetyConfig.from_rig(rig)), excitation, stream.append
        )
        counters = drv.counters()
    assert outcome.status == "completed" and outcome.n_done == 1000
    data = records.concat_pages(stream)
    gaps = [r for r in stream if r["kind"] == records.EVENT and r["name"] == "seq_gap"]
    assert len(gaps) == 1  # the loop records the gap as an event too
    assert np.count_nonzero(np.diff(data["seq"]) == 2) == 1
    assert np.count_nonzero(data["flags"] & DEVICE) == 1  # the flagged sample after the loss
    assert counters["lost"] == 1 and counters["crc_errors"] + counters["bad_frames"] >= 1


def test_stale_limit_is_within_three_periods_on_a_fake_clock():
    """Silence after the last sample trips at the first poll past stale_periods (<= 3 T)."""
    rig = make_rig(T=0.001)
    now = [0.0]

    class SilentPort:
        port = "fake"
        in_waiting = 0
        timeout = write_timeout = None

        def read(self, n):
            now[0] += self.timeout  # a blocking read that waited its whole timeout
            return b""

        def close(self):
            pass

    for stale_periods in (1, 2.5, 3):
        cfg = SerialConfig.from_rig(rig, stale_periods=stale_periods)
        drv = SerialStream(SilentPort(), cfg, rig, clock=lambda: now[0])
        drv._ready.append(None)  # one sample queued: the stream was live at t = 0
        drv._last_arrival = now[0]
        drv.enable(0.1)
        drv._ready.clear()
        with pytest.raises(DeviceFault, match="stale") as exc:
            drv.read(1.0)
        silent = now[0] - drv._last_arrival
        assert (
            stale_periods * rig.sample_time_s
            <= silent
            <= stale_periods * rig.sample_time_s + drv._poll_s
        )
        assert silent <= 3.25 * rig.sample_time_s
        assert "force zeroed" in str(exc.value) and drv.commanded_force_n == 0.0


def test_a_host_stalled_past_the_stale_limit_reads_what_the_board_sent_and_goes_on():
    """The stall is the host's: the board's next sample waits in the port; reading it
    is no stale trip (the same rule as the CANopen driver's late SYNC)."""
    rig = make_rig()
    drv, peer = connect_sim_serial(rig, seed=4, lockstep_timeout_s=4.0)  # host stale: 2 s
    with drv:
        drv.enable(0.5)
        for _ in range(5):
            drv.read(0.5)
            drv.command(0.1)
        time.sleep(2.3)  # a host held off the CPU past its stale limit
        seqs = []
        for _ in range(5):
            seqs.append(drv.read(0.5).seq)
            drv.command(0.1)
        assert drv.stale_trips == 0 and np.all(np.diff(seqs) == 1)


def test_realtime_board_stall_trips_the_host_and_the_host_freeze_trips_the_board():
    # 50 ms periods keep a Python board on a shared machine on time: its stale limit (3
    # periods, 150 ms) is above the stalls a loaded 2-core machine gives a thread (one of
    # 61 ms ended a run with 20 ms periods beside a loaded suite).
    rig = make_rig(T=0.05, stale_periods=3)
    drv, peer = connect_sim_serial(
        rig, realtime=True, seed=3, faults=[Fault("stall", 60, seconds=0.5)]
    )
    with drv:
        drv.enable(0.5)
        with pytest.raises(DeviceFault, match="stale") as exc:
            for _ in range(200):
                drv.read(0.5)
                drv.command(0.3)
        silent_ms = float(str(exc.value).split("no sample for ")[1].split(" ms")[0])
        # At least 3 periods; how much later is scheduling (bench_serial measures it).
        assert silent_ms >= 150.0
    # Board watchdog: a host that stops answering gets zero force after 3 periods
    # (counted from the tick at which its last command arrived: k_last or the next).
    drv, peer = connect_sim_serial(rig, realtime=True, seed=3)
    with drv:
        drv.enable(0.5)
        for _ in range(30):
            drv.read(0.5)
            drv.command(0.3)
        k_last = peer.k
        for _ in range(10):
            drv.read(0.5)  # reading on, commanding nothing: a frozen control thread
        applied = np.array(peer.applied)
    assert np.all(applied[k_last + 5 :] == 0.0) and applied[k_last - 1] == pytest.approx(0.3)
    assert peer.watchdog_zeroed >= 5


def test_emergency_stop_latches_until_the_operator_enables_again():
    rig = make_rig()
    drv, _peer = connect_sim_serial(rig, seed=2)
    with drv:
        drv.enable(0.5)
        drv.read(0.5)
        drv.command(0.4)
        drv.emergency_stop()
        drv.emergency_stop()  # never raises, idempotent
        assert drv.commanded_force_n == 0.0
        with pytest.raises(DeviceFault, match="emergency stop; force zeroed"):
            drv.read(0.5)
        drv.command(1.0)
        assert drv.commanded_force_n == 0.0
        drv.enable(0.5)  # the operator's action clears it
        drv.read(0.5)
        drv.command(0.4)
        assert drv.commanded_force_n == 0.4


def test_non_finite_command_faults_with_zero_force():
    drv, _peer = connect_sim_serial(make_rig(), seed=2)
    with drv:
        drv.enable(0.5)
        drv.read(0.5)
        with pytest.raises(DeviceFault, match="non-finite force command nan"):
            drv.command(math.nan)
        assert drv.commanded_force_n == 0.0


def test_reboot_then_operator_re_enable_accepts_the_new_zero():
    rig = make_rig()
    drv, _peer = connect_sim_serial(rig, seed=2, faults=[Fault("reboot", FAULT_AT)])
    with drv:
        drv.enable(0.5)
        with pytest.raises(DeviceFault, match="rebooted"):
            for _ in range(2 * FAULT_AT):
                drv.read(0.5)
                drv.command(0.2)
        drv.enable(0.5)
        s = drv.read(0.5)
        assert drv.counters()["reboots"] == 1
        assert abs(s.position_m) < 1e-3  # counts restarted at the board's new zero
        assert s.t_s < 1.0  # micros() restarted


def test_link_errors_before_enable_are_counted_not_faults():
    rig = make_rig()
    drv, _peer = connect_sim_serial(
        rig, seed=2, faults=[Fault("flip", 20), Fault("garbage", 22, n=30)]
    )
    with drv:
        flags = []
        for _ in range(30):
            flags.append(drv.read(0.5).flags)
            drv.command(0.0)  # a lock-step board waits for an answer to every sample
        assert drv.fault is None
        assert any(f & FLAG_LOST for f in flags) and any(f & FLAG_LINK_ERRORS for f in flags)
        drv.enable(0.5)
        assert drv.read(0.5).flags == 0


def test_emergency_stop_from_another_thread_mid_run():
    import threading

    rig = make_rig()
    drv, peer = connect_sim_serial(rig, seed=4)
    ve = VirtualEnvironment("spring", K=50.0, T=rig.sample_time_s)
    excitation = 0.3 * np.sin(2 * np.pi * 2.0 * rig.sample_time_s * np.arange(20_000))
    stream = []
    timer = threading.Timer(0.3, drv.emergency_stop)
    with drv:
        timer.start()
        outcome = run_loop(
            drv, HapticLoop(ve, SafetyConfig.from_rig(rig)), excitation, stream.append
        )
        timer.join()
        k_stop = peer.k
    assert outcome.status == "fault" and "emergency stop; force zeroed" in outcome.reason
    events = [r for r in stream if r["kind"] == records.EVENT and r["name"] == "device_fault"]
    assert len(events) == 1 and "emergency stop" in events[0]["reason"]
    applied = np.array(peer.applied)
    assert 100 < outcome.n_done < 20_000 and np.any(applied != 0.0)
    assert np.all(applied[k_stop:] == 0.0) and drv.commanded_force_n == 0.0
