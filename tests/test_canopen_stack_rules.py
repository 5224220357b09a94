"""The driver against the rules a real CiA 301 stack (CANopenNode v4) enforces, as the
simulated drive now enforces them: error-history entries above the count are abort
0x08000024; the RPDO event timer is watched whenever the node is OPERATIONAL and the
PDO valid, whatever the CiA 402 state; reads a drive refuses; a torque RPDO the drive
applies at the next SYNC; SYNCs the host sends late."""
import time

import numpy as np
import pytest

import eds_family as F
from labbench.drivers.cia402 import State
from labbench.errors import DeviceFault, UserError
from labbench.rig import rig_from_dict
from labbench.sim_backend.canopen_peer import connect_driver, sim_config, start_sim_drive
from labbench.sim_backend.plant import MassDamperPlant
from can_fixtures import FAST, make_rig, no_bus_left_open  # noqa: F401

# The drive's watch longer than any stall of a loaded machine during a lock-step run
# (can_fixtures.FAST); after a run the tests wait longer than every one of them.
QUIET_S = 1.5
GUARDED = {"watchdog": "guarding", "guard_time_ms": 20, "life_time_factor": 30}  # 600 ms
# How the drive watches the host: heartbeat consumer, guard time, RPDO1 event timer.
WATCH = [(0x1016, 1), (0x100C, 0), (0x1400, 5)]
# A drive whose torque RPDO is synchronous and fixed so: the torque takes effect at the
# next SYNC, one period after the host sends it (CiA 301 7.2.2).
SYNC_TORQUE = dict(access={(0x1400, 2): "ro"}, default={(0x1400, 2): "1"})


def rig_for(path=None, sim=None, **canopen):
    tables = {"canopen": {**FAST, **({"eds": str(path)} if path else {}), **canopen},
              "safety": {"watchdog_s": 2.0}}  # lock-step on a shared machine
    if sim:
        tables["sim"] = sim
    return rig_from_dict(tables, source="test-rig")


def opened(rig, drive_rig=None):
    """The driver for ``rig`` against a simulated drive built from ``drive_rig`` (default
    the same rig: its EDS)."""
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, sim_config(drive_rig or rig))
    return connect_driver(rig, config, peer, bus)


def assert_quiet_after(drive):
    """Nothing the driver armed fires once the host is quiet: no EMCY, no lost host."""
    time.sleep(QUIET_S)
    peer = drive.peer
    assert peer.emcy_sent == [] and peer.events == [], (peer.emcy_sent, peer.events)
    assert peer.state is State.SWITCH_ON_DISABLED and peer.torque_permille == 0
    assert peer.nmt_state == 127  # PRE-OPERATIONAL: no RPDO deadline is watched
    return peer


# ----------------------------------------------------------------- the survey
@pytest.mark.parametrize("with_eds", [True, False])
def test_error_history_is_read_only_up_to_its_count(tmp_path, with_eds):
    """CANopenNode answers 0x1003:n above 0x1003:00 with 0x08000024: open reads the count,
    the history reader entries 1..count only."""
    path = F.write(tmp_path / "base.eds")  # 0x1003:00..02, no error yet
    drive_rig = rig_for(path)
    d = opened(rig_for(path) if with_eds else rig_for(), drive_rig)
    try:
        with pytest.raises(Exception, match="0x08000024"):
            d._sdo.upload(0x1003, 1)  # the rule is enforced: no entry above the count 0
        assert d._error_history() == []
        d.peer.inject_emcy(0x4310, "too hot")
        assert d._error_history() == [0x4310]  # 0x1003:02 is above the count: not read
        d.peer.abort_sdo_read(0x1003, 1)  # the count changed between the two reads
        assert d._error_history() == []
        assert "0x4310" in d._error_code()
    finally:
        d.close()


def test_a_refused_optional_read_is_a_warning_and_the_drive_runs(tmp_path):
    """Any abort on an object the driver can do without: a warning naming object and
    abort, the object taken as absent (its fallback applies), and the drive runs."""
    path = F.write(tmp_path / "base.eds")
    rig = rig_for(path)
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    refusals = {(0x6072, 0): 0x08000000, (0x1018, 2): 0x08000024, (0x603F, 0): 0x060A0023,
                (0x605A, 0): 0x08000021, (0x6061, 0): 0x08000022}
    for (index, sub), code in refusals.items():
        peer.abort_sdo_read(index, sub, code)
    d = connect_driver(rig, config, peer, bus)
    try:
        w = d.assessment.warnings
        for (index, sub), code in refusals.items():
            key = f"0x{index:04X}:{sub:02X}"
            assert any(x.startswith(key) and f"SDO abort 0x{code:08X}" in x for x in w), (key, w)
            assert any(x.startswith(f"{key} absent") for x in w), (key, w)  # and its fallback
        assert (0x6072, 0) not in peer.node.writes  # not written: the host clamps
        forces = [0.5] * 20
        d.enable()
        for f in forces:
            d.read(1.0)
            d.command(f)
        d.disable()
        assert peer.state is State.SWITCH_ON_DISABLED
    finally:
        d.close()


def test_refused_required_reads_are_obstacles_in_one_message_and_nothing_is_written(tmp_path):
    path = F.write(tmp_path / "base.eds")
    rig = rig_for(path)
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    peer.abort_sdo_read(0x6041, 0, 0x08000000)
    peer.abort_sdo_read(0x6064, 0, 0x08000024)
    peer.abort_sdo_read(0x6076, 0, 0x08000024)  # optional, but no rig value replaces it
    with pytest.raises(UserError) as info:
        connect_driver(rig, config, peer, bus)
    text = str(info.value)
    assert "cannot be used, 3 obstacle(s)" in text, text
    assert "no torque scale: motor rated torque 0x6076 absent" in text
    assert "0x6041:00 (statusword) unreadable (SDO abort 0x08000000 (general error))" in text
    assert "0x6064:00 (position actual value) unreadable (SDO abort 0x08000024 (no data " \
           "available))" in text
    assert peer.node.writes == []


def test_a_drive_refusing_to_read_its_mode_object_is_write_only_to_the_driver(tmp_path):
    """Abort 0x06010001 on a read: the object exists and is never read again; without a
    0x6061 the drive's acknowledgment of the mode write is the confirmation."""
    path = F.write(tmp_path / "no6061.eds", drop=[0x6061])  # the file says 0x6060 is rw
    rig = rig_for(path)
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    peer.abort_sdo_read(0x6060, 0, 0x06010001)
    d = connect_driver(rig, config, peer, bus)
    try:
        assert d.dictionary.get(0x6060).access == "wo" and 0x6060 not in d.dictionary.refused
        assert any("0x6060:00 (modes of operation) is write-only and 0x6061" in w
                   for w in d.assessment.warnings)
        assert peer.mode == 10  # cyclic synchronous torque, taken
        d.enable()
        for _ in range(20):
            d.read(1.0)
            d.command(0.2)
        assert peer.state is State.OPERATION_ENABLED
        d.disable()
    finally:
        d.close()


# ------------------------------------------------- leave the drive as it was found
def _run(drive, protocol, rig):
    from labbench.runner import run

    records = []
    result = run(drive, protocol, [records.append], rig=rig, simulated=True, close=False)
    assert result.status == "success", result.reason
    return records


@pytest.mark.parametrize("variant,canopen,K", [
    ("drive.eds", {}, 150.0),  # heartbeat consumer + RPDO event timer
    ("GUARDING_ONLY", GUARDED, 150.0),  # life guarding + RPDO event timer
    ("SYNC_TORQUE", {}, 45.0),  # the RPDOs take effect at the next SYNC (K_max 67 N/m)
])
def test_no_emcy_after_a_run_a_disable_or_a_stability_probe_of_several_segments(
        tmp_path, variant, canopen, K):
    from labbench.registry import make_protocol

    path = None if variant == "drive.eds" else F.write(
        tmp_path / f"{variant.lower()}.eds", **(SYNC_TORQUE if variant == "SYNC_TORQUE"
                                                else getattr(F, variant)))
    rig = rig_for(path, **canopen)
    d = opened(rig)
    peer = d.peer
    watch = [k for k in WATCH if peer.has(*k)]
    try:
        found = {k: peer._get(*k) for k in watch}
        # a clean run
        _run(d, make_protocol("etfe", duration_s=1.0, seed=3), rig)
        assert_quiet_after(d)
        assert {k: peer._get(*k) for k in watch} == found == dict.fromkeys(watch, 0)  # off
        # enable and disable alone
        d.enable()
        for _ in range(10):
            d.read(1.0)
            d.command(0.0)
        assert peer._get(0x1400, 5) == FAST["rpdo_timeout_ms"]  # armed while running
        d.disable()
        assert_quiet_after(d)
        # the stability probe: several segments, each its own enable/disable
        records = _run(d, make_protocol("stability", K=K, ratio=1.3, min_step_s=0.3,
                                        cycles=3.0), rig)
        segments = [r for r in records if r.get("name") == "segment"]
        assert len(segments) >= 3, segments
        assert_quiet_after(d)
    finally:
        d.close()


def test_the_rules_are_enforced_the_timer_fires_when_the_host_leaves_the_node_operational():
    """The peer's side of the test above: a host that stops sending RPDOs while the node
    is OPERATIONAL gets EMCY 0x8250 though the drive is SWITCH ON DISABLED."""
    d = opened(rig_for())
    try:
        d.enable()
        for _ in range(10):
            d.read(1.0)
            d.command(0.0)
        peer = d.peer
        with peer.lock:
            peer._controlword(0x00)  # DISABLE VOLTAGE; the node stays OPERATIONAL
        assert peer.state is State.SWITCH_ON_DISABLED and peer.nmt_state == 5
        deadline = time.monotonic() + 5.0
        while 0x8250 not in peer.emcy_sent:
            assert time.monotonic() < deadline, (peer.emcy_sent, peer.events)
            time.sleep(0.05)
    finally:
        d.close()


def test_close_writes_back_what_the_survey_found(tmp_path):
    path = F.write(tmp_path / "found.eds", default={0x1017: "250", (0x1400, 5): "700"})
    d = opened(rig_for(path))
    peer = d.peer
    d.enable()
    for _ in range(5):
        d.read(1.0)
        d.command(0.0)
    d.disable()
    assert peer._get(0x1017) == 100 and peer._get(0x1400, 5) == 0  # the driver's settings
    d.close()
    assert peer._get(0x1017) == 250 and peer._get(0x1400, 5) == 700  # as found


# ------------------------------------------------------------- honest timing
def paced(**canopen):
    """The driver in paced mode at a coarse 100 ms period (3 periods: 300 ms to answer, above
    the stalls a loaded 2-core machine gives the in-process drive's thread: 150 ms was not)."""
    from labbench.sim_backend.canopen_peer import open_sim_canopen

    rig = rig_from_dict({"rig": {"sample_time_s": 0.1},
                         # the drive's watches above the injected stalls: not what is tested here
                         "canopen": {"sdo_timeout_s": 2.0, "stale_periods": 3,
                                     "rpdo_timeout_ms": 2000, "heartbeat_consumer_ms": 2000,
                                     **canopen}},
                        source="paced-rig")
    return open_sim_canopen(rig, realtime=True)


def stall_sync(drive, seconds, nth=1):
    """Inject a host stall between the SYNC's deadline and its sending: the ``nth`` SYNC
    from now leaves the host ``seconds`` late (a preempted host thread inside ``send``).
    Returns the SYNCs still to go before the stall (0: it happened)."""
    bus = drive._bus
    real_send = bus.send
    left = [nth]

    def send(msg, timeout=None):
        if left[0] and msg.arbitration_id == 0x080:
            left[0] -= 1
            if not left[0]:
                time.sleep(seconds)
        return real_send(msg, timeout)

    bus.send = send
    return left


def test_a_sync_the_host_sends_late_is_the_hosts_overrun_not_a_silent_drive():
    from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
    from labbench.model.ve import VirtualEnvironment

    with paced() as d:
        rig = d.rig
        ve = VirtualEnvironment("spring-damper", K=5.0, B=0.1, w0=60.0, T=rig.sample_time_s)
        left = stall_sync(d, 0.5, nth=8)  # 5 periods, more than the 3 allowed
        outcome = run_loop(d, HapticLoop(ve, SafetyConfig.from_rig(rig, watchdog_s=2.0)),
                           np.zeros(24), lambda rec: None)
        assert left == [0]  # the stall happened
        assert outcome.status == "completed", outcome.reason  # the drive answered in time
        assert d.counters["late_syncs"] >= 1  # the host's overrun, counted...
        assert outcome.timing["overruns"] >= 1  # ...and in the loop's timing summary
        # A drive that does not answer a late SYNC is still the drive's fault, and the
        # message says the host was late too.
        d.enable()
        for _ in range(3):
            d.read(1.0)
            d.command(0.0)
        d.peer.mute()
        stall_sync(d, 0.5)
        with pytest.raises(DeviceFault, match=r"stale TPDO: no answer to SYNC \d+ within 300 ms "
                                              r"of sending it \(the host sent the SYNC [5-9]\d\d ms "
                                              r"late\)"):
            d.read(1.0)


# ------------------------------------------------------------ the device's delay
def oracle_counts_one_period_late(rig, forces, rated_mnm=100.0):
    """The forces on the exact plant, torque quantised, each held one period later."""
    ref = MassDamperPlant(rig.nominal_mass_kg, rig.nominal_damping_ns_m, rig.sample_time_s)
    per_newton = rig.lever_arm_m / (rated_mnm * 1e-3) * 1000.0
    held, pending, out = 0.0, 0.0, []
    for k, f in enumerate(forces):
        if k:
            ref.step(held)
            held = pending
        out.append(round(ref.position / rig.metres_per_count))
        pending = round(f * per_newton) / per_newton
    return out


def test_a_drive_taking_the_torque_at_the_next_sync_is_one_period_late_and_says_so(tmp_path):
    path = F.write(tmp_path / "sync.eds", **SYNC_TORQUE)
    d = opened(rig_for(path))
    try:
        desc = d.describe()
        assert desc.device_delay_s == d.T and "RPDO1 is synchronous" in desc.device_delay_why
        (w,) = [x for x in d.assessment.warnings if "transmission type is fixed" in x]
        assert "the device's own delay is one sample period" in w
        assert "protocol's td_s" not in w  # the old advice, which left the analyses wrong
        forces = 0.8 * np.random.default_rng(5).standard_normal(200)
        d.enable()
        for _ in range(3):
            d.read(1.0)
            d.command(0.0)
        counts = []
        for f in forces:
            counts.append(round(d.read(1.0).position_m / d.rig.metres_per_count))
            d.command(f)
        assert counts == oracle_counts_one_period_late(d.rig, forces)
    finally:
        d.close()


def test_chirp_id_of_a_drive_taking_the_torque_at_the_next_sync_uses_its_declared_delay(
        tmp_path):
    """No rig value: the driver's declaration is the run's device delay, and the
    identification regresses with it (b was -101 % without)."""
    from labbench.registry import make_protocol

    path = F.write(tmp_path / "sync.eds", **SYNC_TORQUE)
    rig = rig_for(path, sim={"quantize": True})
    assert rig.measured_td_s is None
    d = opened(rig)
    try:
        records = _run(d, make_protocol("chirp-id", duration_s=20.0), rig)
    finally:
        d.close()
    start, stop = records[0], records[-1]
    assert start["device_delay"]["origin"] == "device"
    assert start["device_delay"]["s"] == rig.sample_time_s
    m, b = stop["results"]["m"], stop["results"]["b"]  # measured: -0.08 %, -0.26 %
    assert abs(m / rig.nominal_mass_kg - 1) < 1e-3, m
    assert abs(b / rig.nominal_damping_ns_m - 1) < 1e-2, b


# ------------------------------------------------------------------ counters
def test_device_counters_through_the_run_and_in_the_stop_record():
    """Stray frames on the bus mid-run: the stop record carries the counters as they
    stand after the run, each segment event as they stood at its start (the start
    record's are the ones before the run)."""
    import can

    from labbench.registry import make_protocol
    from labbench.runner import run

    rig = rig_for()
    d = opened(rig)
    stray = can.Message(arbitration_id=0x3F0, data=b"\x01", is_extended_id=False)
    records = []

    def consumer(rec):
        records.append(rec)
        # another node's frame, not the driver's business: on every page of the first two
        # segments (a segment's first page may be handed over between segments, when frames
        # are the enabling's, not the cyclic phase's)
        if rec["kind"] == "page" and len(records) < 14:
            d.peer.bus.send(stray)

    try:
        result = run(d, make_protocol("stability", K=150.0, ratio=1.3, min_step_s=0.3,
                                      cycles=3.0), [consumer], rig=rig, simulated=True)
    finally:
        d.close()
    assert result.status == "success", result.reason
    start, stop = records[0], records[-1]
    assert start["device"]["details"]["counters"]["stray_frames"] == 0
    final = stop["device_counters"]
    assert final["stray_frames"] >= 1 and {"emcy", "late_syncs", "late_ticks"} <= set(final)
    seen = [r["device_counters"]["stray_frames"] for r in records if r.get("name") == "segment"]
    assert len(seen) >= 3 and seen[0] == 0 and seen == sorted(seen)  # through the run
    assert 1 <= seen[-1] <= final["stray_frames"]
