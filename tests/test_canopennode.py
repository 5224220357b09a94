"""The real chain against CANopenNode v4, the most used open-source CiA 301 slave stack.

A CiA 402 torque drive is built from ``../shared/third_party/CANopenNode`` with our object
dictionary, transport and application (``tests/canopennode``) and runs as a process of its
own on python-can's ``udp_multicast``; the driver reaches it through the public surface
only: a rig with ``[canopen] interface = "udp_multicast"``, ``labbench.registry.open_device``
+ ``labbench.runner.run`` (lock-step, so that results do not depend on this machine's
speed) and the ``labbench`` command line.

Truth is the exact plant: the drive steps the simulated drive's mass-damper once per SYNC
with the exact zero-order hold, so the recorded positions must equal that plant under the
recorded commands count for count (``oracle_counts``), and the protocols' results must meet
the exact sampled theory (their own accuracy, measured on the plain simulator, is well
inside each tolerance: see each test).
"""
import contextlib
import io
import json
import time

import can
import numpy as np
import pytest

import canopennode
from canopennode import build, dictionary
from labbench.errors import DeviceFault
from labbench.records import concat_pages
from labbench.registry import device_names, make_protocol, open_device
from labbench.runner import run
from labbench.loop.safety import GATED
from test_canopen_process import _children
from test_canopen_vendor import FORCES, oracle_counts, run_forces

# Lock-step runs on a shared machine: the drive's monitors (wall clock, in its own process)
# well above a loaded machine's stalls (a host held off the CPU for a second must not
# fault a run); the tests of the monitors set their own.
CALM = {"canopen": {"heartbeat_consumer_ms": 2000, "rpdo_timeout_ms": 2000,
                    "life_time_factor": 100, "lockstep_timeout_s": 2.0, "sdo_timeout_s": 2.0}}
RATED_MNM = dictionary.RATED_TORQUE_MNM


@pytest.fixture(scope="module", autouse=True)
def stack():
    """Both variants built once (cached across runs); a missing stack is one clear line."""
    try:
        return {v: build.build(v) for v in dictionary.VARIANTS}
    except build.StackMissing as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture(autouse=True)
def no_process_left():
    before = _children()
    yield
    assert _children() - before == set(), "a drive process outlived its test"


@pytest.fixture
def drive():
    """Factory: a running CANopenNode drive (``canopennode.start``); all closed after."""
    started = []

    def make(variant="event", tables=None, **kw):
        merged = {k: {**CALM.get(k, {}), **(tables or {}).get(k, {})}
                  for k in {*CALM, *(tables or {})}}
        started.append(canopennode.start(variant, merged, **kw))
        return started[-1]

    yield make
    for r in started:
        r.close()


def cli(*argv) -> tuple[int, str]:
    from labbench.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(list(argv))
    return code, out.getvalue()


def canopen_answer(rig_file) -> dict:
    """The CANopen drive's row of ``labbench devices --json``."""
    code, out = cli("devices", "--rig", str(rig_file), "--json")
    assert code == 0, out
    return {row["device"]: row for row in json.loads(out)["devices"]}["canopen"]["answer"]


def counts_of(data, rig) -> np.ndarray:
    return np.round(data["position"] / rig.metres_per_count).astype(int)


def oracle(rig, forces, late: int = 0) -> np.ndarray:
    """The exact plant's counts under ``forces`` taking effect ``late`` periods later."""
    forces = np.concatenate([np.zeros(late), np.asarray(forces, float)])[:len(forces)]
    return np.array(oracle_counts(rig, forces, RATED_MNM))


def emcy_codes(r) -> list[int]:
    return [int.from_bytes(m.data[:2], "little") for m in r.watch.seen(0x81)]


def shows_pre_operational(r, ask: bool, within_s: float = 2.0) -> bool:
    """The drive's heartbeat (or, ``ask``: its answers to guarding requests of the test's
    own) shows PRE-OPERATIONAL within ``within_s`` from now."""
    n_seen = len(r.watch.seen(0x701))
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        if ask:
            r.monitor.send(can.Message(arbitration_id=0x701, is_remote_frame=True, dlc=1,
                                       is_extended_id=False))
        time.sleep(0.05)
        if any(m.data[0] & 0x7F == 127 for m in r.watch.seen(0x701)[n_seen:]):
            return True
    return False


@contextlib.contextmanager
def remote_node(r, eds=None):
    """canopen's own ``RemoteNode`` of the drive on the test's bus (its SDO client)."""
    import canopen

    net = canopen.Network(r.monitor)
    node = canopen.RemoteNode(1, str(eds) if eds else canopen.ObjectDictionary())
    net.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    r.notifier.add_listener(net.listeners[0])
    try:
        yield node
    finally:
        r.notifier.remove_listener(net.listeners[0])


def run_protocol(r, name, **options):
    d = open_device("canopen", r.rig, realtime=False)  # lock-step: SYNC when the loop asks
    records = []
    # simulated: the plant behind the real stack is, stepped per SYNC (a host stall stalls
    # nothing: the loop records it)
    result = run(d, make_protocol(name, **options), [records.append], rig=r.rig, simulated=True)
    assert result.status == "success", result.reason
    return result, concat_pages(records), records


# -------------------------------------------------------------- the drive as built
def test_the_drive_serves_its_eds_and_the_stack_answers_as_cia_301_says(drive):
    """Every object of the served EDS reads back its default over SDO (canopen's own client
    on the bus); the stack's own answers: 0x1003 above its count is abort 0x08000024,
    a read-only object refuses a write (0x06010002), a mode 0x6502 lacks is 0x06090030."""
    import canopen
    from canopen.objectdictionary import ODVariable

    r = drive("sync")
    with remote_node(r, r.eds) as node:
        for obj in node.object_dictionary.values():
            for v in [obj] if isinstance(obj, ODVariable) else obj.values():
                if v.index == 0x1003 and v.subindex > 0:
                    with pytest.raises(canopen.SdoAbortedError) as info:
                        node.sdo.upload(v.index, v.subindex)
                    assert info.value.code == 0x08000024  # no error yet: no data
                    continue
                if v.index in (0x6041, 0x6061):  # the application's live values
                    continue
                assert v.decode_raw(node.sdo.upload(v.index, v.subindex)) == v.default, \
                    f"0x{v.index:04X}:{v.subindex:02X}"
        for index, sub, raw in ((0x1400, 2, b"\xff"), (0x6502, 0, bytes(4)), (0x1018, 1, bytes(4))):
            with pytest.raises(canopen.SdoAbortedError) as info:
                node.sdo.download(index, sub, raw)
            assert info.value.code == 0x06010002, (hex(index), sub)  # read-only
        with pytest.raises(canopen.SdoAbortedError) as info:
            node.sdo.download(0x6060, 0, b"\x04")  # profile torque: 0x6502 offers CST only
        assert info.value.code == 0x06090030
        node.sdo.download(0x6060, 0, b"\x0a")
        assert node.sdo.upload(0x6061, 0) == b"\x0a"
        node.sdo.download(0x6040, 0, b"\x06\x00")  # shutdown: READY TO SWITCH ON
        assert int.from_bytes(node.sdo.upload(0x6041, 0), "little") & 0x6F == 0x21


def test_labbench_devices_reports_the_drive(drive, tmp_path):
    r = drive()
    code, out = cli("devices", "--rig", str(r.write_rig(tmp_path / "rig.toml")), "--json")
    assert code == 0, out
    rows = {row["device"]: row for row in json.loads(out)["devices"]}
    assert set(rows) == set(device_names())  # every backend has its row
    a = rows["canopen"]["answer"]
    assert (a["vendor_id"], a["product_code"], a["device_type"], a["supported_modes"]) == (
        dictionary.VENDOR_ID, dictionary.PRODUCT_CODE, dictionary.DEVICE_TYPE,
        dictionary.SUPPORTED_MODES)
    assert a["state"] == "SWITCH ON DISABLED" and a["error_history"] == [] and not a["obstacles"]
    assert a["torque_modes"] == ["cyclic synchronous torque"]


# ------------------------------------------------------------------ protocols
@pytest.mark.parametrize("variant, late", [("event", 0), ("sync", 1)])
def test_chirp_id_identifies_the_plant(drive, variant, late):
    """m within 0.1 %, b within 1 % (the same chirp on the plain quantised simulator:
    -0.025 %, -0.02 %), with the torque applied on arrival and at the next SYNC; positions
    equal to the exact plant count for count, one period later for the synchronous RPDO."""
    r = drive(variant)
    result, data, records = run_protocol(r, "chirp-id", duration_s=5.0, amplitude_n=2.0,
                                         x_max_m=0.04, f0_hz=0.5)
    counts = counts_of(data, r.rig)
    assert np.array_equal(counts, oracle(r.rig, data["command"], late))
    if late:
        assert not np.array_equal(counts, oracle(r.rig, data["command"]))  # the delay is real
    assert records[0]["device_delay"]["s"] == pytest.approx(late * r.rig.sample_time_s)
    m, b = result.results["m"], result.results["b"]
    assert m == pytest.approx(r.rig.nominal_mass_kg, rel=1e-3)
    assert b == pytest.approx(r.rig.nominal_damping_ns_m, rel=1e-2)


def test_white_noise_etfe_meets_the_exact_sampled_theory(drive):
    """Median |Z - Z_sampled| / |Z_sampled| over 2-100 rad/s below 0.1 % (20 s at 1 N:
    0.02-0.04 % on the plain quantised simulator over four seeds)."""
    r = drive()
    result, data, _ = run_protocol(r, "etfe", duration_s=20.0, std_n=1.0, seed=11)
    # Seed 11's first force (0.03 N) opens the enable gate at once; the driver holds the
    # torque at zero until a TPDO shows OPERATION ENABLED and the loop records those
    # samples as gated (labbench.device.Enabling), so the record is what the plant felt.
    assert data["command"][0] == 0.0 and data["flags"][0] & GATED
    assert np.array_equal(counts_of(data, r.rig), oracle(r.rig, data["command"]))
    assert result.results["deviation_vs_sampled"]["median_rel"] < 1e-3


def test_stability_probe_finds_the_exact_boundary(drive):
    """The spring's boundary within 1 % of the exact sampled one (this probe on the plain
    quantised simulator: -0.04 %); each step its own enable and disable of the drive."""
    r = drive()
    result, _, _ = run_protocol(r, "stability", K=175.0, ratio=1.03, K_stop=230.0,
                                cycles=12.0, pulse_n=2.0)
    res = result.results
    assert len(res["steps"]) >= 3
    assert abs(res["rel_error_vs_exact"]) < 0.01, res


# -------------------------------------------------------------- monitors, faults
def test_disable_leaves_no_rpdo_timer_running(drive):
    """After a run the drive's RPDO event timer (0x1400:05, enforced by the stack) must not
    fire: no EMCY in three times its period after the driver disabled the drive."""
    r = drive(tables={"canopen": {"rpdo_timeout_ms": 400}})
    run_protocol(r, "etfe", duration_s=1.0, seed=2)
    time.sleep(1.2)
    assert emcy_codes(r) == []


@pytest.mark.parametrize("watch, code", [("rpdo", 0x8250), ("heartbeat", 0x8130),
                                         ("guarding", 0x8130)])
def test_a_frozen_host_is_caught_by_the_drive(drive, tmp_path, watch, code):
    """The host stops (no SYNC, RPDO, heartbeat or guarding request): the stack's monitor
    (RPDO event timer, heartbeat consumer, life guarding) sends its EMCY and leaves
    OPERATIONAL, the drive faults (0x6007 = 1: no torque), the driver's next read is a
    one-line device fault and ``labbench devices`` shows the FAULT and its code.

    Guarded, the drive comes with its heartbeat producer on (as many ship): a node whose
    producer heartbeat time is not 0 uses the heartbeat, not node guarding (CiA 301;
    CANopenNode's guarding slave then answers nothing and watches nothing), so the driver
    must turn it off."""
    canopen = {"rpdo": {"rpdo_timeout_ms": 400, "heartbeat_consumer_ms": 10000},
               "heartbeat": {"rpdo_timeout_ms": 10000, "heartbeat_consumer_ms": 400},
               "guarding": {"rpdo_timeout_ms": 10000, "watchdog": "guarding",
                            "guard_time_ms": 20, "life_time_factor": 20}}[watch]
    r = drive(tables={"canopen": canopen})
    if watch == "guarding":
        with remote_node(r) as node:
            node.sdo.download(0x1017, 0, (100).to_bytes(2, "little"))
    d = open_device("canopen", r.rig, realtime=False)
    try:
        assert d.assessment.watchdog == ("guarding" if watch == "guarding" else "heartbeat")
        run_forces(d, [0.0] * 200)
        deadline = time.monotonic() + 3.0
        while code not in emcy_codes(r):
            assert time.monotonic() < deadline, emcy_codes(r)
            time.sleep(0.02)
        # the stack's own reaction to a communication error: PRE-OPERATIONAL (no PDOs)
        assert shows_pre_operational(r, ask=watch == "guarding")
        with pytest.raises(DeviceFault) as info:
            d.read(1.0)
        assert "\n" not in str(info.value)
    finally:
        d.close()
    if watch == "guarding":  # its own heartbeat back
        with remote_node(r) as node:
            assert node.sdo.upload(0x1017, 0) == (100).to_bytes(2, "little")
    a = canopen_answer(r.write_rig(tmp_path / "rig.toml"))
    assert a["state"] == "FAULT" and f"0x{code:04X}" in a["error_code"], a


def test_a_drive_fault_is_reported_and_reset_by_the_operator(drive, tmp_path):
    """An internal fault of the drive in a run (over-current): EMCY, the run ends on the
    fault, ``labbench devices`` shows FAULT, 0x603F and the error history, and the
    operator's ``--fault-reset`` takes it to SWITCH ON DISABLED."""
    r = drive()
    rig_file = r.write_rig(tmp_path / "rig.toml")
    d = open_device("canopen", r.rig, realtime=False)
    injected = []

    def progress(fraction, _label):
        if fraction > 0.3 and not injected:
            injected.append(fraction)
            r.inject_fault(0x2310)  # over-current

    result = run(d, make_protocol("etfe", duration_s=3.0, seed=4), [], rig=r.rig,
                 simulated=True, progress=progress)
    assert result.status == "failed" and result.reason.startswith("fault: "), result.reason
    assert "EMCY 0x2310" in result.reason
    assert 0x2310 in emcy_codes(r)
    a = canopen_answer(rig_file)
    assert a["state"] == "FAULT" and "0x2310" in a["error_code"], a
    assert 0x2310 in [e & 0xFFFF for e in a["error_history"]], a["error_history"]
    code, out = cli("devices", "--rig", str(rig_file), "--fault-reset")
    assert code == 0 and out.strip() == "node 1: FAULT -> SWITCH ON DISABLED", out
    assert canopen_answer(rig_file)["state"] == "SWITCH ON DISABLED"


def test_without_an_eds_the_drive_is_surveyed_alone(drive):
    """No EDS in the rig: the driver finds the dictionary and the PDO slots by asking, maps
    and runs; positions equal to the exact plant count for count."""
    r = drive(use_eds=False)
    d = open_device("canopen", r.rig, realtime=False)
    try:
        assert d.dictionary.source == "drive" and not d.dictionary.from_file
        assert d.dictionary.subs(0x1600) == [0, 1, 2, 3, 4]
        assert run_forces(d, FORCES) == oracle_counts(r.rig, FORCES, RATED_MNM)
    finally:
        d.close()
