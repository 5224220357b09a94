"""The CANopen driver against the simulated CiA 402 drive on python-can's virtual bus."""
import math
import struct

import numpy as np
import pytest

from labbench.drivers import emcy
from labbench.drivers.canopen_drive import CanopenConfig, open_canopen
from labbench.drivers.cia402 import State
from labbench.device import Device
from labbench.errors import DeviceConnectionError, DeviceError, UserError
from labbench.rig import Rig
from labbench.sim_backend.plant import MassDamperPlant
from can_fixtures import connect, drive, make_rig, no_bus_left_open, sim_parts  # noqa: F401


# ------------------------------------------------------------------ config
@pytest.mark.parametrize("section,field", [
    ({"node_id": 0}, "node_id"), ({"node_id": 128}, "node_id"), ({"node_id": "1"}, "node_id"),
    ({"bitrate": True}, "bitrate"), ({"mode": "csp"}, "mode"),
    ({"sdo_timeout_s": -1}, "sdo_timeout_s"),
    ({"heartbeat_consumer_ms": 10, "host_heartbeat_ms": 20}, "heartbeat_consumer_ms"),
    ({"host_node_id": 1}, "host_node_id"), ({"nodeid": 3}, "nodeid"),
    ({"eds": "/no/such/file.eds"}, "eds"), ({"interface": 3}, "interface"),
])
def test_config_errors_name_the_field(section, field):
    with pytest.raises(UserError, match=rf"\[canopen\] (unknown field .)?{field}"):
        CanopenConfig.from_section(section, source="r.toml")


def test_config_defaults_are_valid_and_eds_is_checked(tmp_path):
    cfg = CanopenConfig.from_section({"eds": "sim_backend/drive.eds", "node_id": 5})
    assert cfg.node_id == 5 and cfg.mode == "auto"
    from labbench.drivers.canopen_check import check_eds

    a = check_eds("sim_backend/drive.eds", cfg)  # our own EDS: usable, nothing missing
    assert a.warnings == [] and a.modes[0].code == 10
    bad = tmp_path / "bad.eds"
    bad.write_text("[1000]\nParameterName=Device type\nObjectType=0x7\nDataType=0x0007\n"
                   "AccessType=ro\nDefaultValue=0x00020192\n")
    with pytest.raises(UserError, match=r"cannot be used, \d+ obstacle\(s\): \(1\) .*0x6060"):
        check_eds(str(bad))


def test_hardware_factory_reports_a_missing_interface_in_one_line():
    rig = make_rig(interface="no-such-interface", channel="x")
    with pytest.raises(DeviceConnectionError, match="cannot open CAN bus"):
        open_canopen(rig)


# ---------------------------------------------------------------- bring-up
def test_bring_up_observes_nmt_maps_pdos_and_selects_cst(drive):
    assert isinstance(drive, Device)
    peer = drive.peer
    assert peer.nmt_state == 127  # OPERATIONAL only in the cyclic phase (enable starts it)
    ident = drive.identity()
    assert ident["device_type"] & 0xFFFF == 402
    assert ident["vendor_id"] == 0x4C4200AB and ident["supported_modes"] == 0x208
    d = drive.describe()
    assert d.kind == "canopen" and d.details["mode"] == "cyclic synchronous torque"
    assert peer.mode == 10
    store = peer.node.data_store
    u32 = lambda idx, sub: struct.unpack("<I", store[idx][sub])[0]  # noqa: E731
    assert [u32(0x1A00, s) for s in (1, 2, 3)] == [0x60640020, 0x60410010, 0x60770010]
    assert u32(0x1A01, 1) == 0x606C0020
    assert [u32(0x1600, s) for s in (1, 2)] == [0x60710010, 0x60400010]
    assert u32(0x1400, 1) == 0x201 and store[0x1400][5] == struct.pack("<H", 0)  # not armed
    enabled(drive)  # the watch armed, then NMT start seen in the drive's heartbeat
    assert peer.nmt_state == 5 and store[0x1400][5] == struct.pack("<H", 600)
    assert u32(0x1016, 1) == 127 << 16 | 800
    drive.disable()  # each watch off, the node back to PRE-OPERATIONAL
    assert peer.nmt_state == 127 and peer.state is State.SWITCH_ON_DISABLED
    assert store[0x1400][5] == struct.pack("<H", 0) and u32(0x1016, 1) == 0


def enabled(drive):
    """enable() as the loop does it: the RPDO of each cycle carries the next controlword."""
    drive.enable()
    for _ in range(3):
        drive.read(1.0)
        drive.command(0.0)
    assert drive.peer.state is State.OPERATION_ENABLED
    return drive


def test_enable_from_switch_on_disabled_takes_the_cia402_route(drive):
    drive.enable()
    states = []
    for _ in range(3):
        drive.read(1.0)
        drive.command(0.0)
        states.append(drive._state_seen)
    assert states == [State.READY_TO_SWITCH_ON, State.OPERATION_ENABLED,
                      State.OPERATION_ENABLED]


def test_enable_writes_and_reads_back_the_safety_objects(drive):
    enabled(drive)
    peer = drive.peer
    assert peer.state is State.OPERATION_ENABLED
    rig = drive.rig
    # 5 N at 0.1 m = 0.5 N m = 5000 per-mille of the 100 mN m rated torque.
    assert peer._get(0x6072) == 5000
    assert peer._get(0x607D, 1) == math.floor(-0.1 / rig.metres_per_count)
    assert peer._get(0x607D, 2) == math.ceil(0.1 / rig.metres_per_count)
    assert peer._get(0x1016, 1) == (127 << 16 | 800)
    assert (peer._get(0x605A), peer._get(0x605E), peer._get(0x6007)) == (0, 0, 1)
    drive.disable()
    assert peer.state is State.SWITCH_ON_DISABLED and peer._get(0x1016, 1) == 0


def test_profile_torque_fallback_when_cst_is_missing(sim_parts):
    peer = sim_parts[2]
    peer.node.data_store[0x6502] = {0: struct.pack("<I", 1 << 3)}  # profile torque only
    d = connect(sim_parts)
    try:
        assert d.describe().details["mode"] == "profile torque" and peer.mode == 4
    finally:
        d.close()


def test_no_torque_mode_is_refused(sim_parts):
    peer = sim_parts[2]
    peer.node.data_store[0x6502] = {0: struct.pack("<I", 1 << 7)}  # CSP only
    with pytest.raises(UserError, match="0x6502"):
        connect(sim_parts)


def test_not_a_402_device_is_refused(sim_parts):
    sim_parts[2].node.data_store[0x1000] = {0: struct.pack("<I", 0x00000191)}  # CiA 401 I/O
    with pytest.raises(UserError, match="not a CiA 402 drive"):
        connect(sim_parts)


# ----------------------------------------------------------------- cycling
def test_positions_match_the_exact_plant_count_for_count(drive):
    """Oracle: the same torques on MassDamperPlant, quantised as the drive does.

    SYNC k advances the plant one period with the torque of the last RPDO, then
    samples; torque is in per-mille of 100 mN m, position in counts.
    """
    rig = drive.rig
    enabled(drive)
    forces = 0.8 * np.random.default_rng(1).standard_normal(600)
    ref = MassDamperPlant(rig.nominal_mass_kg, rig.nominal_damping_ns_m, rig.sample_time_s)
    held = 0.0
    got, want = [], []
    for k, f in enumerate(forces):
        if k:
            ref.step(held)
        want.append(round(ref.position / rig.metres_per_count))
        got.append(round(drive.read(1.0).position_m / rig.metres_per_count))
        drive.command(f)
        held = round(f * 1000) * 1e-3 * 100 * 1e-3 / rig.lever_arm_m
    assert got == want
    assert max(abs(c) for c in got) > 20  # the test moved the handle
    assert drive.peer.sync_count == len(forces) + 3  # 3 cycles of enabled()


def test_sample_sequence_time_and_torque_clamp(drive):
    enabled(drive)
    samples = []
    for _ in range(5):
        samples.append(drive.read(1.0))
        drive.command(50.0)  # ten times the force limit
    assert [s.seq for s in samples] == [3, 4, 5, 6, 7]
    assert [s.t_s for s in samples] == pytest.approx([0.003, 0.004, 0.005, 0.006, 0.007])
    assert drive.peer.torque_permille == 5000
    assert drive.torque_actual_n == pytest.approx(5.0)
    drive.disable()
    assert drive.peer.torque_permille == 0


def test_close_twice_and_context_manager(sim_parts):
    with connect(sim_parts) as d:
        enabled(d)
        d.command(0.1)
    assert d.peer.torque_permille == 0 and d.peer.state is State.SWITCH_ON_DISABLED
    d.close()


# -------------------------------------------------------------------- EMCY
def test_emcy_decoding():
    e = emcy.decode(emcy.encode(0x8130, 0x11, b"\x01\x02"))
    assert e.code == 0x8130 and "heartbeat" in e.text
    assert e.register_bits() == ["generic", "communication"]
    assert "0x8130" in str(e) and not e.is_reset
    assert emcy.decode(bytes(8)).is_reset
    assert emcy.code_text(0x2311) == "current" and emcy.code_text(0x8F00) == "monitoring"
    assert emcy.code_text(0x8199) == "communication"
    with pytest.raises(ValueError):
        emcy.decode(b"\x00")


def test_default_rig_has_no_canopen_table():
    assert Rig().section("canopen") == {}


# ------------------------------------------------------------ labbench devices
def test_devices_command_probes_the_simulated_drive(capsys):
    import json

    from labbench.cli import main

    assert main(["devices", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    (row,) = [r for r in out["devices"] if r["device"] == "sim-canopen"]
    a = row["answer"]
    assert a["device_type"] & 0xFFFF == 402 and a["vendor_id"] == 0x4C4200AB
    assert a["torque_modes"] == ["cyclic synchronous torque", "profile torque"]
    assert a["state"] == "SWITCH ON DISABLED"
    assert [r["configured"] for r in out["devices"] if r["device"] == "canopen"] == [False]


def test_devices_command_reports_a_silent_drive_in_one_line(tmp_path, capsys):
    from labbench.cli import main

    rig = tmp_path / "rig.toml"
    rig.write_text('[canopen]\ninterface = "virtual"\nchannel = "nobody-here"\n'
                   'node_id = 3\nsdo_timeout_s = 0.05\n')
    assert main(["devices", "--rig", str(rig)]) == 1  # the configured hardware is silent
    captured = capsys.readouterr()
    assert "no answer: node 3: no answer to SDO read of 0x1000:00" in captured.out
    assert captured.err == ""


@pytest.mark.parametrize("exc,code", [
    (DeviceError("node 1: SDO read of 0x1003:01 (pre-defined error field) refused: SDO abort "
                 "0x08000024 (no data available)"), 1),  # as a drive's own words
    (RuntimeError("a bug\nin two lines"), 1),  # not ours: named by its type, on one line
    (UserError("[canopen] nodeid: unknown field"), 2),  # a bad setting
])
def test_devices_shows_every_row_whatever_one_probe_raises(monkeypatch, tmp_path, capsys, exc,
                                                           code):
    import json

    import labbench.registry as registry
    from labbench.cli import main

    real = registry.device_probe

    def probe_of(name):
        if name != "canopen":
            return real(name)

        def probe(rig, fault_reset=False):
            raise exc
        return probe

    monkeypatch.setattr(registry, "device_probe", probe_of)
    rig = tmp_path / "rig.toml"
    rig.write_text("[canopen]\nnode_id = 1\n")
    assert main(["devices", "--rig", str(rig)]) == code  # from every row
    out, err = capsys.readouterr()
    assert err == ""
    listed = [line.split()[0] for line in out.splitlines()[1:] if not line.startswith(" ")]
    assert listed == registry.device_names()  # every backend's row
    (error,) = [line.strip() for line in out.splitlines() if "error:" in line]
    words = " ".join(str(exc).split())
    assert error == "error: " + (words if code == 2 or isinstance(exc, DeviceError)
                                 else f"RuntimeError: {words}")
    assert "node 1 answered" in out.split("sim-canopen")[1]  # the simulated drive's answer
    assert main(["devices", "--rig", str(rig), "--json"]) == code
    rows = {r["device"]: r for r in json.loads(capsys.readouterr().out)["devices"]}
    assert rows["canopen"]["error"] == error[len("error: "):]
    assert "answer" in rows["sim-canopen"] and "error" not in rows["sim-canopen"]


def test_devices_fault_reset_on_the_simulated_drive(capsys):
    from labbench.cli import main

    assert main(["devices", "--fault-reset", "--sim"]) == 0
    assert "SWITCH ON DISABLED -> SWITCH ON DISABLED" in capsys.readouterr().out


def test_bus_load_of_the_mapping():
    from labbench.drivers.canopen_check import check_eds
    from labbench.drivers.canopen_pdo import frame_bits

    assert frame_bits(0) == (47, 47 + 8) and frame_bits(8) == (111, 111 + 24)
    load = check_eds("sim_backend/drive.eds").bus_load(CanopenConfig(), 0.001)
    # Per ms: SYNC 47, TPDO1 111, TPDO2 79, RPDO1 79 bits; heartbeats 55 bits at 50 + 10 Hz.
    assert load["bits_per_s_nominal"] == pytest.approx(316_000 + 55 * 60)
    assert 0.31 < load["load_nominal"] < load["load_worst"] < 0.40


# ------------------------------------------- the same protocol, two devices
def run_protocol(device, rig, **options):
    from labbench.registry import open_device
    from labbench.records import concat_pages
    from labbench.runner import run
    from labbench.registry import make_protocol

    records = []
    result = run(open_device(device, rig), make_protocol("etfe", **options), [records.append],
                 rig=rig, simulated=device.startswith("sim"))  # sim-canopen: a real driver, a simulated drive
    return result, concat_pages(records), records


def test_short_etfe_record_matches_the_plain_simulator_count_for_count(monkeypatch):
    """5 s of the white-noise protocol through the runner on ``sim-canopen``, against the
    plain simulator under the same loop and the excitation the drive was given.

    The drive applies no torque until a TPDO shows OPERATION ENABLED, a few periods after
    the gate first opens (``labbench.device.Enabling``): those samples are recorded as
    gated, with zero excitation, so the record replayed on ``sim`` must give the same run.
    Both quantise position to encoder counts; the CANopen path also quantises the torque
    to 1 per-mille of 100 mN m (1 mN at the handle). That error (at most 0.5 mN a sample)
    moves the handle by micrometres, so positions may differ by one count where the true
    position sits next to a count boundary, never more.
    """
    from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
    from labbench.protocols.white_noise import WhiteNoiseEtfe
    from labbench.records import concat_pages
    from labbench.registry import make_protocol, open_device
    from labbench.loop.safety import GATED

    monkeypatch.setattr(WhiteNoiseEtfe, "analyze", lambda self, data, meta: {})
    rig = make_rig(sim={"quantize": True})
    r_can, b, recs = run_protocol("sim-canopen", rig, duration_s=5.0, seed=11)
    assert r_can.status == "success", r_can.reason
    assert recs[0]["device"]["kind"] == "canopen"
    noise = make_protocol("etfe", duration_s=5.0, seed=11).excitation()
    gated = (b["flags"] & GATED) != 0
    k0 = int(np.argmin(gated))  # the drive confirmed enabled here
    assert 1 <= k0 <= 5 and not gated[k0:].any()  # gated through the enabling, then never
    assert np.all(b["excitation"][:k0] == 0) and np.all(b["command"][:k0] == 0)
    assert np.array_equal(b["excitation"][k0:], noise[k0:]) and len(b["t"]) == 5000
    plain = []
    with open_device("sim", rig) as sim:
        ve = make_protocol("etfe").ve
        out = run_loop(sim, HapticLoop(ve, SafetyConfig.from_rig(rig, watchdog_s=2.0)),
                       b["excitation"], plain.append)
    assert out.status == "completed", out.reason
    a = concat_pages(plain)
    assert np.array_equal(a["excitation"], b["excitation"])
    dc = np.round((a["position"] - b["position"]) / rig.metres_per_count)
    assert np.abs(dc).max() <= 1
    assert np.mean(dc != 0) < 0.10
    assert np.std(a["position"]) / rig.metres_per_count > 20  # the handle really moved


def test_a_late_answer_to_an_earlier_sdo_request_is_not_taken_for_the_next_ones():
    """Under load a request times out and its answer arrives during the next request (the
    flaky "device type 0x1000 absent" of a loaded machine): an abort or a value naming
    another object is skipped, the answer naming the requested one is taken."""
    import canopen

    from labbench.drivers.canopen_sdo import MatchingSdoClient

    client = MatchingSdoClient(0x601, 0x581, canopen.ObjectDictionary())
    late_abort = struct.pack("<BHBI", 0x80, 0x6502, 0, 0x06020000)  # for 0x6502:00
    late_value = struct.pack("<BHBI", 0x43, 0x6041, 0, 0x0237)  # for 0x6041:00

    class Network:  # answers each request late-first, as the bus did
        def send_message(self, cob_id, request):
            assert cob_id == 0x601
            index, sub = struct.unpack_from("<HB", request, 1)
            for frame in (late_abort, late_value):
                client.on_response(0x581, frame, 0.0)
            if request[0] & 0xE0 == 0x40:  # an upload initiate: the expedited value
                client.on_response(0x581, struct.pack("<BHBI", 0x43, index, sub, 0x20192), 0.0)
            else:  # a download initiate: the node's acknowledgement
                client.on_response(0x581, struct.pack("<BHBI", 0x60, index, sub, 0), 0.0)

    client.network = Network()
    assert struct.unpack("<I", client.upload(0x1000, 0))[0] == 0x20192
    client.download(0x6060, 0, b"\x0a")  # no SdoAbortedError from the late abort


def test_sim_canopen_takes_the_plain_simulator_options():
    from labbench.sim_backend.canopen_peer import open_sim_canopen

    with pytest.raises(UserError, match="sim option nonsense: unknown"):
        open_sim_canopen(make_rig(), nonsense=1)
    with open_sim_canopen(make_rig(), seed=4, coulomb_n=0.02, m=0.2) as d:
        assert d.peer.plant.options["coulomb_n"] == 0.02 and d.peer.plant.options["m"] == 0.2


def cli_etfe(tmp_path, device, duration_s):
    """``labbench run etfe --device DEVICE --json``: (JSON output, session channels, events)."""
    import contextlib
    import io
    import json

    from labbench.cli import main
    from labbench.sessions.session_content import load_session

    rig_file = tmp_path / "rig.toml"
    # Lock-step runs on a shared machine: a generous loop watchdog (the loop does
    # not time non-paced devices) and the simulated drive's own monitor defaults.
    rig_file.write_text("[sim]\nquantize = true\n[safety]\nwatchdog_s = 2.0\n")
    out = io.StringIO()
    argv = ["run", "etfe", "--device", device, "--rig", str(rig_file), "--seed", "11",
            "--duration-s", str(duration_s), "--out", str(tmp_path / device), "--json"]
    with contextlib.redirect_stdout(out):
        assert main(argv) == 0
    result = json.loads(out.getvalue())
    start, _, data, events, stop, problem = load_session(result["session"])
    assert problem is None and stop["status"] == "success", stop
    assert start["device"]["kind"] == ("canopen" if device == "sim-canopen" else "sim")
    return result, data, events


def compare_etfe_runs(tmp_path, duration_s):
    """The same ETFE from the CLI on ``sim`` and ``sim-canopen``: records and estimates."""
    (ra, a, _), (rb, b, events) = (cli_etfe(tmp_path, d, duration_s)
                                   for d in ("sim", "sim-canopen"))
    n = round(duration_s / 0.001)
    assert len(b["t"]) == n and np.all(np.diff(b["seq"]) == 1)
    from labbench.loop.timing import EVENTS as TIMING  # a loaded host's overruns are recorded too

    assert [e["name"] for e in events if e["name"] not in ("segment", *TIMING)] == ["enabled"]
    q = Rig().metres_per_count
    # The drive applies nothing until it shows OPERATION ENABLED (a few periods after the
    # gate opens): the plain simulator's first forces push the handle ~20 counts further,
    # a transient the loop damps by e^-(b+B)t/2m (0.3 % after 1 s). From then on the two
    # agree count for count (see the short runner test).
    steady = b["t"] >= 1.0
    dc = np.round((a["position"][steady] - b["position"][steady]) / q)
    assert np.abs(dc).max() <= 1 and np.mean(dc != 0) < 0.10
    za, zb = (np.asarray(r["results"]["etfe"]["Z_re"]) + 1j * np.asarray(r["results"]["etfe"]["Z_im"])
              for r in (ra, rb))
    w = np.asarray(ra["results"]["etfe"]["w"])
    band = (w >= 2.0) & (w <= 100.0)
    # "Within noise". Each estimate's distance from the exact sampled theory is its
    # noise: encoder quantisation for both, plus the drive's torque resolution for
    # the CANopen run (1 mN steps: an unrecorded force error of 0.29 mN rms). Both
    # runs must sit as close to theory, and differ from each other by no more than
    # twice that. (A one-period delay or a 1 % torque scale error would give 1e-2.)
    # Measured, seed 11: 10 s: between 6.5e-4, sim 2.0e-3, canopen 1.9e-3; 120 s:
    # 2.5e-4, 1.3e-4, 3.1e-4. With a 10x finer torque unit (0x6076 = 10 mN m) the
    # 120 s figures become 5.7e-5, 1.3e-4, 1.1e-4: the torque resolution is the
    # whole difference.
    between = float(np.median(np.abs(za[band] - zb[band]) / np.abs(za[band])))
    scatter = ra["results"]["deviation_vs_sampled"]["median_rel"]
    other = rb["results"]["deviation_vs_sampled"]["median_rel"]
    assert between < 2 * max(scatter, other), (between, scatter, other)
    assert other < 3 * scatter, (other, scatter)
    return between, scatter, other


def test_cli_etfe_through_the_canopen_driver_matches_the_plain_simulator(tmp_path):
    compare_etfe_runs(tmp_path, 10.0)


@pytest.mark.slow
def test_cli_full_etfe_through_the_canopen_driver_matches_the_plain_simulator(tmp_path):
    """The whole 2-minute white-noise ETFE protocol, analysis included, on both devices."""
    compare_etfe_runs(tmp_path, 120.0)


# ------------------------------- the hardware path, with the simulated drive as the node
@pytest.fixture
def drive_on_named_channel(tmp_path):
    """A simulated drive on a named virtual channel and a rig file that points at it."""
    import uuid

    from labbench.sim_backend.canopen_peer import EDS_PATH, SimCanopenDrive, plant_for

    channel = f"bench-{uuid.uuid4().hex[:6]}"
    rig = make_rig()
    peer = SimCanopenDrive(channel, 4, plant_for(rig), rig.metres_per_count, rig.lever_arm_m,
                           rig.sample_time_s).start()
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(f'[canopen]\ninterface = "virtual"\nchannel = "{channel}"\nnode_id = 4\n'
                        'sdo_timeout_s = 2.0\nheartbeat_consumer_ms = 800\nrpdo_timeout_ms = 600\n'
                        f'eds = "{EDS_PATH}"\n'
                        '[safety]\nwatchdog_s = 2.0\n')  # lock-step on a shared machine
    yield peer, rig_file
    peer.close()


def test_canopen_factory_opens_a_python_can_bus_and_runs(drive_on_named_channel):
    from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
    from labbench.rig import load_rig
    from labbench.model.ve import VirtualEnvironment

    peer, rig_file = drive_on_named_channel
    rig = load_rig(rig_file)
    ve = VirtualEnvironment("spring", K=50.0, T=rig.sample_time_s)
    exc = 0.2 * np.random.default_rng(2).standard_normal(300)
    with open_canopen(rig, realtime=False) as d:  # lock-step: the node is simulated
        assert d.describe().details["identity"]["vendor_id"] == 0x4C4200AB
        out = run_loop(d, HapticLoop(ve, SafetyConfig.from_rig(rig)), exc, lambda r: None)
    assert out.status == "completed" and out.n_done == 300, out
    assert peer.state is State.SWITCH_ON_DISABLED and peer.torque_permille == 0


def test_devices_command_shows_a_faulted_node_and_resets_it(drive_on_named_channel, capsys):
    from labbench.cli import main

    peer, rig_file = drive_on_named_channel
    peer.inject_emcy(0x7305, "encoder")
    assert main(["devices", "--rig", str(rig_file)]) == 0
    out = capsys.readouterr().out
    assert "node 4 answered" in out and "vendor 0x4C4200AB" in out and "FAULT; NMT" in out
    assert "error code 0x603F = 0x7305 (incremental sensor 1 fault)" in out
    assert main(["devices", "--rig", str(rig_file), "--fault-reset"]) == 0
    assert "node 4: FAULT -> SWITCH ON DISABLED" in capsys.readouterr().out
    assert peer.state is State.SWITCH_ON_DISABLED


def test_forced_cst_on_a_drive_without_it_is_refused_naming_0x6502(sim_parts):
    rig, _, peer, bus = sim_parts
    from labbench.drivers.canopen_drive import CanopenDrive

    peer.node.data_store[0x6502] = {0: struct.pack("<I", 1 << 3)}  # profile torque only
    with pytest.raises(UserError, match="0x6502 = 0x00000008; cyclic synchronous torque: bit 9 of 0x6502 is not set"):
        CanopenDrive(rig, CanopenConfig.from_section({"mode": "cst", "sdo_timeout_s": 2.0}),
                     bus=bus, realtime=False).open()
    assert peer.mode == 0


def test_drive_refusing_the_mode_write_is_reported_naming_0x6060(sim_parts):
    sim_parts[2].abort_sdo_write(0x6060, 0, code=0x06090030)
    with pytest.raises(DeviceError, match=r"refused writing 0x0A to 0x6060:00 .*value range"):
        connect(sim_parts)


# ------------------------------------------------------------------- CAN trace
@pytest.mark.parametrize("suffix", ["asc", "blf", "log", "trc", "csv"])
def test_can_log_records_every_frame_and_reads_back(tmp_path, suffix):
    import can

    from labbench.sim_backend.canopen_peer import open_sim_canopen

    path = tmp_path / f"trace.{suffix}"
    with open_sim_canopen(make_rig(), can_log=str(path)) as d:
        enabled(d)
        for _ in range(50):
            d.read(1.0)
            d.command(0.1)
        peer = d.peer
    n_sync = peer.sync_count  # 53 of the loop, and the one of disable's wind-down
    frames = list(can.LogReader(str(path)))
    ids = [m.arbitration_id for m in frames if not m.is_error_frame]
    assert ids.count(0x080) == n_sync == 54  # every SYNC the host sent
    assert ids.count(0x181) == ids.count(0x281) == n_sync  # every TPDO the drive sent
    assert ids.count(0x201) >= 54 and ids.count(0x601) > 20 and ids.count(0x581) > 20  # RPDO, SDO
    assert ids.count(0x000) == 3  # NMT pre-operational (open), start (enable), pre-op (disable)
    if suffix == "asc":  # directions are kept where the format has them
        assert {m.is_rx for m in frames if m.arbitration_id == 0x080} == {False}
        assert {m.is_rx for m in frames if m.arbitration_id == 0x181} == {True}


def test_cli_run_notes_the_can_log_in_the_session(tmp_path):
    import can

    from labbench.cli import main
    from labbench.sessions.session_content import load_session

    out, log = tmp_path / "s", tmp_path / "run.asc"
    argv = ["run", "etfe", "--device", "sim-canopen", "--duration-s", "1", "--out", str(out),
            "--can-log", str(log), "--json"]
    import contextlib
    import io
    import json

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    start = load_session(json.loads(buf.getvalue())["session"])[0]
    assert start["device"]["details"]["can_log"] == str(log)
    assert sum(m.arbitration_id == 0x080 for m in can.LogReader(str(log))) >= 1000
    assert main(["run", "etfe", "--device", "sim", "--can-log", str(log)]) == 2
