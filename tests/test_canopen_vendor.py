"""The driver against a family of synthetic drive dictionaries (``eds_family``): each
variant is one thing real drives do differently; the simulated drive is built from
the same file and enforces it."""
import time

import numpy as np
import pytest

import eds_family as F
from labbench.drivers.canopen_check import check_eds
from labbench.drivers.canopen_config import CanopenConfig
from labbench.drivers.cia402 import State
from labbench.errors import DeviceError, DeviceFault, UserError
from labbench.rig import rig_from_dict
from labbench.sim_backend.canopen_peer import connect_driver, sim_config, start_sim_drive
from labbench.sim_backend.plant import MassDamperPlant
from can_fixtures import FAST, no_bus_left_open  # noqa: F401


def rig_for(path, **canopen):
    return rig_from_dict({"canopen": {**FAST, "eds": str(path), **canopen}}, source="test-rig")


def variant(tmp_path, name, **canopen):
    """(rig, config, peer, host_bus) for the dictionary variant ``name`` of eds_family."""
    path = F.write(tmp_path / f"{name.lower()}.eds", **getattr(F, name))
    rig = rig_for(path, **canopen)
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    return rig, config, peer, bus


@pytest.fixture
def opened(tmp_path):
    """Factory: an opened driver on a variant; all closed after the test."""
    drives = []

    def make(name, **canopen):
        d = connect_driver(*variant(tmp_path, name, **canopen))
        drives.append(d)
        return d

    yield make
    for d in drives:
        d.close()


def refused(tmp_path, name, **canopen) -> tuple[str, object]:
    """The one message of a refused open, and the peer (closed)."""
    parts = variant(tmp_path, name, **canopen)
    with pytest.raises(UserError) as info:
        connect_driver(*parts)
    return str(info.value), parts[2]


def run_forces(drive, forces):
    """enable, then one read+command per force; positions in counts."""
    drive.enable()
    for _ in range(3):
        drive.read(1.0)
        drive.command(0.0)
    counts = []
    for f in forces:
        counts.append(round(drive.read(1.0).position_m / drive.rig.metres_per_count))
        drive.command(f)
    return counts


def oracle_counts(rig, forces, rated_mnm=100.0, per_newton=None):
    """The same forces on the exact plant, torque quantised to per-mille of ``rated_mnm``
    (or to ``per_newton`` set point units per newton)."""
    ref = MassDamperPlant(rig.nominal_mass_kg, rig.nominal_damping_ns_m, rig.sample_time_s)
    held, out = 0.0, []
    per_newton = per_newton or rig.lever_arm_m / (rated_mnm * 1e-3) * 1000.0
    for k, f in enumerate(forces):
        if k:
            ref.step(held)
        out.append(round(ref.position / rig.metres_per_count))
        held = round(f * per_newton) / per_newton
    return out


FORCES = 0.8 * np.random.default_rng(5).standard_normal(300)


# ------------------------------------------------- a drive lacking only optional objects
def test_optional_objects_missing_open_enable_run_disable_with_warnings(tmp_path):
    """Done-when: opens, enables, runs a protocol and disables as it is; the session says
    what is missing and what replaces it."""
    from labbench.records import concat_pages
    from labbench.registry import make_protocol
    from labbench.runner import run

    path = F.write(tmp_path / "optional.eds", **F.OPTIONAL_MISSING)
    # A generous loop watchdog: lock-step runs on a shared machine (see test_canopen_drive).
    rig = rig_from_dict({"canopen": {"eds": str(path), **FAST}, "sim": {"quantize": True},
                         "safety": {"watchdog_s": 2.0}}, source="test-rig")
    config = sim_config(rig)
    drive = connect_driver(rig, config, *start_sim_drive(rig, config))
    peer = drive.peer
    records = []
    result = run(drive, make_protocol("etfe", duration_s=2.0, seed=3), [records.append],
                 rig=rig, simulated=True)
    assert result.status == "success", result.reason
    warnings = [r["reason"] for r in records if r.get("name") == "device_warning"]
    for obj in ("0x1400:05", "0x603F:00", "0x605A:00", "0x605E:00", "0x6007:00", "0x6072:00",
                "0x607D:01", "0x6061:00", "0x1018:02", "0x1018:04"):
        assert any(w.startswith(obj) for w in warnings), (obj, warnings)
    assert any("host clamps" in w for w in warnings)
    assert len(concat_pages(records)["t"]) == 2000
    assert peer.state is State.SWITCH_ON_DISABLED and peer.torque_permille == 0
    ident = records[0]["device"]["details"]["identity"]
    assert ident["vendor_id"] == 0x00ABCDEF and ident["serial"] is None  # absent, not 0


def force_zero(peer, timeout=2.0):
    """The drive applies no torque (polled: the drive's thread takes the frame)."""
    deadline = time.monotonic() + timeout
    while peer.torque_permille != 0:
        assert time.monotonic() < deadline, (peer.torque_permille, peer.state, peer.events)
        time.sleep(0.01)
    return True


def test_optional_missing_host_clamps_the_torque_and_keeps_the_window(opened):
    d = opened("OPTIONAL_MISSING")
    run_forces(d, [50.0] * 3)  # ten times the force limit; the drive has no 0x6072
    assert d.peer.torque_permille == d.assessment.max_permille == 5000
    with pytest.raises(DeviceFault, match=r"outside the rig's window .* no software position "
                                          r"limit 0x607D"):
        for _ in range(2000):
            d.read(1.0)
            d.command(5.0)
    assert abs(d.peer.plant.x) > 0.1  # it ran out of the window, and was stopped
    assert force_zero(d.peer)


@pytest.mark.parametrize("drop_history,words", [
    (True, "error register 0x1001 = 0x01"),
    (False, "latest error 0x1003:01 = 0x2310 (continuous over-current)")])
def test_without_0x603F_a_drive_in_fault_is_reported_as_fault(tmp_path, drop_history, words):
    """The drive was in FAULT before the host connected (no EMCY heard)."""
    spec = dict(F.OPTIONAL_MISSING)
    if not drop_history:
        spec["drop"] = [o for o in spec["drop"] if o != 0x1003]
    path = F.write(tmp_path / "nofault.eds", **spec)
    rig = rig_for(path)
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    peer.mute()  # its EMCY went out before the host listened
    peer.inject_emcy(0x2310, "over-current")
    peer.mute(False)
    d = connect_driver(rig, config, peer, bus)
    try:
        assert d.probe()["state"] == "FAULT"
        with pytest.raises(DeviceFault) as info:
            d.enable()
        text = str(info.value)
        assert "drive is in FAULT: " in text and words in text, text
    finally:
        d.close()


def test_optional_missing_frozen_loop_stopped_by_the_heartbeat_consumer(opened):
    """No RPDO event timer: the heartbeat consumer alone removes the torque."""
    d = opened("OPTIONAL_MISSING", heartbeat_consumer_ms=500)
    run_forces(d, [0.3] * 5)
    assert d.peer.torque_permille == 300
    time.sleep(1.5)
    assert d.peer.torque_permille == 0 and d.peer.state is State.FAULT
    assert any("no host heartbeat" in e for e in d.peer.events), d.peer.events


# --------------------------------------------------------------- PDO layouts
def test_one_slot_pdos_split_the_mapping_and_match_the_exact_plant(opened):
    d = opened("ONE_SLOT")
    plan = d.assessment.plan
    assert [p.roles() for p in plan.rpdos] == [["torque"], ["control"]]
    assert [p.roles() for p in plan.tpdos] == [["position"], ["status"], ["torque"],
                                               ["velocity"]]
    assert run_forces(d, FORCES) == oracle_counts(d.rig, FORCES)
    load = d.assessment.bus_load(d.config, d.T)["load_nominal"]
    assert 0.40 < load < 0.50  # 7 frames per ms instead of 4


def test_fixed_mappings_are_used_as_they_are(opened):
    d = opened("FIXED")
    plan = d.assessment.plan
    (rpdo,) = plan.rpdos
    assert rpdo.origin == "fixed" and rpdo.roles() == ["control", "torque"]
    assert plan.tpdos[0].origin == "fixed" and plan.tpdos[0].roles() == ["status", "position"]
    assert (0x1801, 0x281) in plan.disable  # the fixed TPDO2 carries nothing needed: off
    assert d.peer._get(0x1801, 1) & 0x8000_0000
    assert run_forces(d, FORCES) == oracle_counts(d.rig, FORCES)


def test_dcf_mapping_is_used(opened, tmp_path):
    dcf = tmp_path / "drive.dcf"
    dcf.write_text(F.eds_text(dcf_values={(0x1A00, 0): "2", (0x1A00, 1): "0x60410010",
                                          (0x1A00, 2): "0x60640020"}))
    rig = rig_for(dcf)
    config = sim_config(rig)
    d = connect_driver(rig, config, *start_sim_drive(rig, config))
    try:
        assert d.assessment.plan.tpdos[0].origin == "dcf"
        assert d.assessment.plan.tpdos[0].roles() == ["status", "position"]
        assert run_forces(d, FORCES[:50]) == oracle_counts(d.rig, FORCES[:50])
    finally:
        d.close()


def test_position_not_mappable_is_refused_naming_the_object(tmp_path):
    path = F.write(tmp_path / "nomap.eds", mappable={0x6064: 0, 0x606C: 0})
    with pytest.raises(UserError) as info:
        check_eds(str(path))
    text = str(info.value)
    assert "0x6064 (position actual value) is not PDO-mappable" in text
    assert "0x606C" not in text  # velocity is optional: a warning, not an obstacle
    assert "1 obstacle(s)" in text


def test_position_of_the_wrong_size_is_refused(tmp_path):
    path = tmp_path / "size.eds"
    path.write_text(F.eds_text().replace("ParameterName=Position actual value\nObjectType=0x7\n"
                                         "DataType=0x0004", "ParameterName=Position actual "
                                         "value\nObjectType=0x7\nDataType=0x0003"))
    with pytest.raises(UserError, match=r"0x6064:00 \(position actual value\) is 16 bit \(data "
                                        r"type 0x0003\), CiA 402 makes it 32"):
        check_eds(str(path))


def test_mapping_refusal_names_the_object_not_the_slot(tmp_path):
    """The file says 0x6071 is mappable, the drive (built from a stricter copy) refuses."""
    lax = F.write(tmp_path / "lax.eds")
    strict = F.write(tmp_path / "strict.eds", mappable={0x6071: 0})
    rig = rig_for(lax)
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, sim_config(rig_for(strict)))
    with pytest.raises(UserError, match=r"refused mapping 0x6071 \(target torque\) into RPDO1 "
                                        r"\(0x1600:01\).*0x06040041"):
        connect_driver(rig, config, peer, bus)


# ------------------------------------------------------------------ guarding
def test_guarding_only_drive_runs_and_a_frozen_loop_is_stopped_within_the_life_time(opened):
    d = opened("GUARDING_ONLY", life_time_factor=25)  # 20 ms x 25 = 500 ms
    a = d.assessment
    assert a.watchdog == "guarding" and a.nmt_by == "guarding"
    time.sleep(0.7)  # longer than the life time: guarding starts with the run, not at open
    assert run_forces(d, FORCES[:200]) == oracle_counts(d.rig, FORCES[:200])
    assert d.peer._get(0x100C) == 20 and d.peer._get(0x100D) == 25
    d.command(0.3)
    time.sleep(1.5)  # the loop freezes: no guarding request
    assert d.peer.torque_permille == 0 and d.peer.state is State.FAULT
    assert any("life guarding" in e for e in d.peer.events), d.peer.events


def test_guarding_disarmed_after_disable(opened):
    d = opened("GUARDING_ONLY", life_time_factor=10)
    run_forces(d, [0.0] * 10)
    d.disable()
    time.sleep(0.5)  # no requests while disabled, and no life-guarding event
    assert d.peer.state is State.SWITCH_ON_DISABLED and d.peer._get(0x100C) == 0
    assert not any("life guarding" in e for e in d.peer.events)


# --------------------------------------------------------------- torque scale
def test_rated_torque_zero_needs_the_rig(tmp_path):
    text, _ = refused(tmp_path, "RATED_TORQUE_ZERO")
    assert "no torque scale: motor rated torque 0x6076 is 0" in text


@pytest.mark.parametrize("canopen,rated", [
    ({"rated_torque_mnm": 250.0}, 250.0),
    ({"torque_constant_nm_per_a": 0.05, "rated_current_ma": 4000.0}, 200.0)])
def test_rated_torque_from_the_rig(opened, canopen, rated):
    d = opened("RATED_TORQUE_ZERO", **canopen)
    assert d.assessment.rated_mnm == pytest.approx(rated)
    assert any(w.startswith("0x6076:00 is 0") for w in d.assessment.warnings)
    assert run_forces(d, FORCES[:200]) == oracle_counts(d.rig, FORCES[:200], rated)


# --------------------------------------------------------------------- modes
def test_vendor_mode_from_the_rig_table(opened):
    d = opened("VENDOR_MODES", modes={"current": {"code": -3, "bit": 16}})
    assert d.describe().details["mode"] == "vendor mode current (-3)" and d.peer.mode == -3
    assert run_forces(d, FORCES[:50]) == oracle_counts(d.rig, FORCES[:50])


def test_vendor_drive_without_a_mode_table_is_refused(tmp_path):
    text, _ = refused(tmp_path, "VENDOR_MODES")
    assert "no torque mode: supported drive modes 0x6502 = 0x00010000" in text
    assert "bit 9 of 0x6502 is not set" in text and "bit 3 of 0x6502 is not set" in text


def test_vendor_mode_outside_the_range_of_0x6060_is_refused(tmp_path):
    text, _ = refused(tmp_path, "VENDOR_MODES", modes={"current": {"code": -5, "bit": 16}})
    assert "code -5 outside the range of 0x6060 [-3, 10]" in text


def test_mode_auto_falls_back_to_profile_torque(tmp_path):
    path = F.write(tmp_path / "pt.eds", default={0x6502: "0x00000008"})
    rig = rig_for(path)
    config = sim_config(rig)
    d = connect_driver(rig, config, *start_sim_drive(rig, config))
    try:
        assert d.peer.mode == 4 and d.describe().details["mode"] == "profile torque"
    finally:
        d.close()


# ------------------------------------------------------ every obstacle at once
def test_not_402_is_refused_before_any_write_listing_every_obstacle(tmp_path):
    text, peer = refused(tmp_path, "NOT_402")
    assert peer.node.writes == []  # nothing was written to the drive
    assert text.count("\n") == 0 and "8 obstacle(s)" in text
    # capabilities first
    assert text.index("(1) not a CiA 402 drive: device type 0x1000 = 0x00000191") < \
        text.index("0x6071:00 (target torque) absent") < text.index("no way to be watched") < \
        text.index("0x6064:00 (position actual value) absent")


def test_several_obstacles_are_reported_together_in_check_eds_and_open(tmp_path):
    kw = dict(default={0x6502: "0x00000080"}, mappable={0x6041: 0},
              drop=[0x1016, 0x100C, 0x100D], access={0x6040: "ro"},
              limits={0x605A: (1, 7)})
    path = F.write(tmp_path / "bad.eds", **kw)
    with pytest.raises(UserError) as info:
        check_eds(str(path))
    offline = str(info.value)
    for words in ("no torque mode: supported drive modes 0x6502 = 0x00000080",
                  "no way to be watched", "0x6040:00 (controlword) is ro",
                  "0x6041 (statusword) is not PDO-mappable",
                  "0x0000 for 0x605A:00 (quick stop option code) is outside its range "
                  "[0x0001, 0x0007]"):
        assert words in offline, (words, offline)
    rig = rig_for(path)
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    with pytest.raises(UserError) as info:
        connect_driver(rig, config, peer, bus)
    assert str(info.value).split(": cannot be used")[1] == offline.split(": cannot be used")[1]
    assert peer.node.writes == []


# --------------------------------------------------------- lenient reading
def test_common_eds_defects_give_warnings_not_failures(tmp_path):
    text = F.eds_text().replace("[6072]\nParameterName=Max torque\n",
                                "[6072]\nParameterName=Max torque\nDefaultValue=5\n")
    text += ("\n[2100]\nParameterName=vendor thing without a data type\nAccessType=rw\n"
             "\n[2200sub1]\nParameterName=orphan\nDataType=0x0007\nAccessType=rw\n"
             "\n[6076]\nPDOMapping=0\n")
    path = tmp_path / "defects.eds"
    path.write_text(text)
    a = check_eds(str(path))
    w = "\n".join(a.warnings)
    assert "duplicated key DefaultValue" in w and "[2100] has no DataType" in w
    assert "[2200sub1] has no array/record" in w and "section [6076] appears twice" in w


# ------------------------------------------------ the simulated drive's rules
@pytest.fixture
def sdo(tmp_path):
    """The driver's SDO channel to a drive built from a dictionary with limits (not opened)."""
    from labbench.sim_backend.canopen_peer import driver_for

    path = F.write(tmp_path / "rules.eds", limits={0x6072: (0, 4000)})
    rig = rig_for(path)
    config = sim_config(rig)
    d = driver_for(rig, config, *start_sim_drive(rig, config))
    d.connect()
    yield d._sdo
    d.close()


@pytest.mark.parametrize("index,sub,fmt,value,code", [
    (0x6072, 0, "<H", 4001, "0x06090031"),  # above HighLimit
    (0x6041, 0, "<H", 0, "0x06010002"),  # read-only
    (0x2000, 0, "<H", 0, "0x06020000"),  # no such object
    (0x1A00, 1, "<I", F.entry(0x6064, 32), "0x08000022"),  # TPDO1 still valid
    (0x607D, 3, "<i", 0, "0x06090011"),  # no such subindex
    (0x1800, 1, "<I", 0x182, "0x06090030"),  # another COB-ID while TPDO1 is valid
])
def test_simulated_drive_enforces_its_dictionary(sdo, index, sub, fmt, value, code):
    with pytest.raises(DeviceError, match=code):
        sdo.write(index, sub, fmt, value)


def test_simulated_drive_enforces_the_mapping_procedure(sdo):
    sdo.write(0x1800, 1, "<I", 0x8000_0181)  # 1. PDO invalid
    sdo.write(0x1A00, 1, "<I", F.entry(0x6041, 16))
    sdo.write(0x1A00, 0, "<B", 1)
    with pytest.raises(DeviceError, match="0x08000022"):  # 2. count still non-zero
        sdo.write(0x1A00, 2, "<I", F.entry(0x6064, 32))
    sdo.write(0x1A00, 0, "<B", 0)
    with pytest.raises(DeviceError, match="0x06040041"):  # not mappable
        sdo.write(0x1A00, 1, "<I", F.entry(0x6076, 32))
    with pytest.raises(DeviceError, match="0x06040043"):  # wrong size
        sdo.write(0x1A00, 1, "<I", F.entry(0x6064, 16))
    for k, e in enumerate([F.entry(0x6064, 32), F.entry(0x606C, 32), F.entry(0x6041, 16)], 1):
        sdo.write(0x1A00, k, "<I", e)
    with pytest.raises(DeviceError, match="0x06040042"):  # 80 bits > 8 bytes
        sdo.write(0x1A00, 0, "<B", 3)
    with pytest.raises(DeviceError, match="0x06040042"):  # more entries than slots
        sdo.write(0x1A00, 0, "<B", 5)
    sdo.write(0x1A00, 0, "<B", 2)
    sdo.write(0x1800, 1, "<I", 0x181)  # 5. valid again
    assert sdo.read(0x1A00, 0, "<B") == 2


def test_config_passes_bus_options_and_catches_typos(tmp_path):
    cfg = CanopenConfig.from_section({"bus": {"fd": True, "data_bitrate": 2_000_000,
                                              "app_name": "x"}})
    assert cfg.bus_kwargs() == {"fd": True, "data_bitrate": 2_000_000, "app_name": "x"}
    with pytest.raises(UserError, match="did you mean 'node_id'"):
        CanopenConfig.from_section({"node_idd": 3})
    with pytest.raises(UserError, match=r"\[canopen\] modes.current.code"):
        CanopenConfig.from_section({"modes": {"current": {"code": 300}}})
    (tmp_path / "drives").mkdir()
    F.write(tmp_path / "drives" / "mine.eds")
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text('[canopen]\neds = "drives/mine.eds"\n')
    from labbench.rig import load_rig

    rig = load_rig(rig_file)  # the eds is found beside the rig file, from any folder
    cfg = CanopenConfig.from_section(rig.section("canopen"), source=rig.source)
    assert cfg.eds == str(tmp_path / "drives" / "mine.eds")


# ------------------------------------------- the hardware path on a named channel
@pytest.fixture
def node_on_channel(tmp_path):
    """Factory: a simulated drive of a variant on a named virtual channel (closed after)."""
    import uuid

    from labbench.sim_backend.canopen_peer import SimCanopenDrive, plant_for

    peers = []

    def make(name, node_id=5, **canopen):
        path = F.write(tmp_path / f"{name.lower()}.eds", **getattr(F, name))
        channel = f"node-{uuid.uuid4().hex[:6]}"
        rig = rig_for(path, **canopen)
        peer = SimCanopenDrive(channel, node_id, plant_for(rig), rig.metres_per_count,
                               rig.lever_arm_m, rig.sample_time_s, eds=path,
                               config=sim_config(rig)).start()
        peers.append(peer)
        return peer, channel, path

    yield make
    for p in peers:
        p.close()


def test_python_can_configuration_applies_when_the_rig_names_no_bus(node_on_channel, tmp_path,
                                                                   monkeypatch):
    from labbench.drivers.canopen_drive import open_canopen

    peer, channel, path = node_on_channel("GUARDING_ONLY")
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", channel)
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(f'[canopen]\nnode_id = 5\neds = "{path.name}"\nsdo_timeout_s = 2.0\n'
                        '[canopen.bus]\nreceive_own_messages = false\n')  # python-can's, passed on
    from labbench.rig import load_rig

    with open_canopen(load_rig(rig_file), realtime=False) as d:
        assert d.config.interface == "" and d.config.bus_options == {
            "receive_own_messages": False}
        assert run_forces(d, FORCES[:20]) == oracle_counts(d.rig, FORCES[:20])
    assert peer.state is State.SWITCH_ON_DISABLED


def test_devices_prints_the_capability_report_and_tells_absent_from_no_answer(
        node_on_channel, tmp_path, capsys):
    from labbench.cli import main

    peer, channel, path = node_on_channel("OPTIONAL_MISSING")
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(f'[canopen]\ninterface = "virtual"\nchannel = "{channel}"\nnode_id = 5\n'
                        f'eds = "{path}"\nsdo_timeout_s = 2.0\n')
    assert main(["devices", "--rig", str(rig_file)]) == 0
    out = capsys.readouterr().out.split("canopen      configured")[1]
    assert "node 5 answered" in out and "serial absent" in out and "vendor 0x00ABCDEF" in out
    for words in ("CiA 402: yes", "torque mode: cyclic synchronous torque then profile torque",
                  "watched by: heartbeat consumer 0x1016", "PDO plan:",
                  "RPDO1 COB-ID 0x205", "bus load at 1 Mbit/s: 31.9 % nominal",
                  "error history 0x1003: empty or absent", "warning: 0x603F:00 absent"):
        assert words in out, (words, out)
    assert "no answer" not in out and peer.node.writes == []  # the probe wrote nothing


def test_an_object_the_file_lists_but_the_drive_lacks_is_absent(tmp_path):
    """The drive is asked: its answer wins over its EDS (here 0x6072, 0x605A gone)."""
    listed = F.write(tmp_path / "listed.eds")
    actual = F.write(tmp_path / "actual.eds", drop=[0x6072, 0x605A])
    rig = rig_for(listed)
    config = sim_config(rig)
    d = connect_driver(rig, config, *start_sim_drive(rig, sim_config(rig_for(actual))))
    try:
        w = d.assessment.warnings
        assert any("lists 0x6072:00 but the drive says it does not exist" in x for x in w), w
        assert any(x.startswith("0x6072:00 absent") for x in w)
        assert any(x.startswith("0x605A:00 absent") for x in w)
        assert (0x6072, 0) not in d.peer.node.writes  # not written: host clamp only
    finally:
        d.close()


def test_devices_shows_the_error_history_of_a_faulted_drive(node_on_channel, tmp_path, capsys):
    from labbench.cli import main

    peer, channel, path = node_on_channel("ONE_SLOT")  # has 0x603F and 0x1003
    peer.inject_emcy(0x4310, "too hot")
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(f'[canopen]\ninterface = "virtual"\nchannel = "{channel}"\nnode_id = 5\n'
                        'sdo_timeout_s = 2.0\n')  # no eds: everything from the drive itself
    assert main(["devices", "--rig", str(rig_file)]) == 0
    out = capsys.readouterr().out.split("canopen      configured")[1]
    assert "node 5 answered (drive)" in out
    assert "FAULT; NMT" in out and "error code 0x603F = 0x4310" in out
    assert "error history 0x1003: 0x00004310" in out
    assert "TPDO4 COB-ID 0x485 (planned, 1 slot(s))" in out  # slots probed on the drive


def test_a_stopped_node_is_woken_by_open_but_not_by_the_probe(tmp_path):
    """STOPPED answers no SDO: open sends NMT pre-operational once; the probe does not."""
    import can

    from labbench.drivers.canopen_drive import CanopenDrive, probe_drive

    rig, config, peer, bus = variant(tmp_path, "ONE_SLOT")
    with peer.lock:
        peer._on_nmt(bytes([0x02, peer.node_id]))  # another master stopped it
        peer._params[(0x1017, 0)], peer._hb_next = 50, 0.0  # with its heartbeat on
    other = can.Bus(interface="virtual", channel=peer.bus.channel_id)
    probed = probe_drive(CanopenDrive(rig, config, bus=other))
    assert probed["no_answer"].startswith("node 1: no answer to SDO read of 0x1000:00")
    assert probed["no_answer"].endswith("; its heartbeat shows STOPPED")
    assert peer.nmt_state == 4 and peer.node.writes == []  # the probe changed nothing
    d = connect_driver(rig, config, peer, bus)
    try:
        assert peer.nmt_state == 127 and len(d.assessment.plan.rpdos) == 2  # woken: answers
    finally:
        d.close()


# ------------------------------------------- rehearsal from any file (the vendors' traits)
@pytest.mark.parametrize("name", list(F.FAMILY))
def test_the_check_and_the_rehearsal_agree_on_every_family_file(tmp_path, name):
    """The file-alone check and the driver surveying a simulated drive built from the
    same file refuse with the same obstacles, or both go on; a file that goes on runs
    the exact plant's trajectory and ends disabled."""
    spec, canopen, refusal = F.FAMILY[name]
    path = F.write(tmp_path / f"{name.lower()}.eds", **spec)
    rig = rig_for(path, **canopen)
    config = sim_config(rig)
    try:
        check_eds(str(path), config, rig)
        offline = None
    except UserError as exc:
        offline = str(exc).split(": cannot be used")[1]
    peer, bus = start_sim_drive(rig, config)
    try:
        d = connect_driver(rig, config, peer, bus)
    except UserError as exc:
        assert str(exc).split(": cannot be used")[1] == offline
        assert refusal is not None and refusal in offline, offline
        assert peer.node.writes == []
        return
    try:
        assert offline is None and refusal is None
        per_newton = d.assessment.force_to_command
        assert run_forces(d, FORCES[:100]) == oracle_counts(d.rig, FORCES[:100],
                                                            per_newton=per_newton)
        d.disable()
        assert peer.state is State.SWITCH_ON_DISABLED and peer.torque_permille == 0
    finally:
        d.close()


def test_objects_without_a_value_get_one_warning_naming_them_not_blaming_the_drive(tmp_path):
    path = F.write(tmp_path / "nodefaults.eds", **F.NO_DEFAULTS)
    a = check_eds(str(path))
    (line,) = [w for w in a.warnings if "listed without a value" in w and w.startswith(str(path))]
    for key in ("0x1000:00", "0x6502:00", "0x1018:04", "0x605A:00", "0x6075:00", "0x1400:01",
                "0x1600:01", "0x1017:00"):
        assert key in line, (key, line)
    assert "8 object(s)" in line and "the drive's own values apply" in line
    assert a.capabilities["CiA 402"] == "unknown (listed without a value)"
    rig = rig_for(path)
    config = sim_config(rig)
    d = connect_driver(rig, config, *start_sim_drive(rig, config))
    try:
        assert d.peer._get(0x605A) == 0 and d.peer._get(0x6075) == 0  # neutral values
        assert d.peer._get(0x1000) == 0x00020192 and d.peer._get(0x6502) == 0x208
        assert line in d.assessment.warnings
    finally:
        d.close()


def test_dcf_parameter_values_win_over_defaults_and_are_read_by_type(tmp_path):
    dcf = tmp_path / "drive.dcf"
    dcf.write_text(F.eds_text(dcf_values={(0x6076, 0): "250", (0x607D, 1): "0xFFFF0000",
                                          (0x6072, 0): "0x7D0"}))
    d = check_eds(str(dcf))
    from labbench.drivers.canopen_objects import read_eds

    od = read_eds(str(dcf), 1)
    assert od.value(0x6076) == 250 and od.get(0x6076).from_dcf
    assert od.value(0x607D, 1) == -65536 and od.value(0x6072) == 2000
    assert od.value(0x607D, 2) == 2147483647  # no ParameterValue: the default
    assert d.rated_mnm == 250.0


def test_unreadable_values_are_named_and_dropped(tmp_path):
    path = F.write(tmp_path / "bad.eds", default={0x6072: "0x1FFFF", 0x605A: "-0x8001",
                                                  0x6075: "-1", 0x6007: "3 apples"})
    a = check_eds(str(path))
    w = "\n".join(a.warnings)
    assert "[6072] DefaultValue=0x1FFFF (outside the range of its type [0, 65535])" in w
    assert "[605A] DefaultValue=-0x8001 (outside the range of its type [-32768, 32767])" in w
    assert "[6075] DefaultValue=-1 (outside the range of its type" in w
    assert "[6007] DefaultValue=3 apples (not a number)" in w
    (unset,) = [x for x in a.warnings if "listed without a value" in x]
    assert all(k in unset for k in ("0x6072:00", "0x605A:00", "0x6075:00", "0x6007:00"))


def test_write_only_mode_object_is_known_to_exist_and_never_read(tmp_path):
    path = F.write(tmp_path / "wo.eds", **F.WRITE_ONLY_MODE)
    rig = rig_for(path)
    config = sim_config(rig)
    d = connect_driver(rig, config, *start_sim_drive(rig, config))
    try:
        e = d.assessment  # the survey kept 0x6060 without reading it
        assert e.modes and d.peer.mode == 10
        with pytest.raises(DeviceError, match="0x06010001"):
            d._sdo.read(0x6060, 0, "<b")  # the drive does refuse a read
    finally:
        d.close()
