"""Vendor objects named in the rig (issue 33): a vendor mode's own set point with its unit,
the position and velocity objects; checked against the drive's dictionary in the one-message
assessment, suggested in the refusal of a drive that has them, and rehearsed on the
simulated drive built from the same profile (``eds_family``)."""
import re
import tomllib

import numpy as np
import pytest

import eds_family as F
from labbench.drivers.canopen_check import PLACEHOLDER_RE, check_eds
from labbench.drivers.canopen_config import CanopenConfig
from labbench.errors import UserError
from labbench.registry import make_protocol, open_device
from labbench.rig import rig_from_dict
from labbench.runner import run
from labbench.sim_backend.canopen_peer import connect_driver, sim_config, start_sim_drive
from can_fixtures import FAST, no_bus_left_open  # noqa: F401
from test_canopen_vendor import FORCES, opened, oracle_counts, run_forces  # noqa: F401

# What the person fills in from the manuals, by pattern (the values eds_family's rigs use).
MANUAL = {"CURRENT_MODE": {"code": -3, "unit": "mA", "kt": 0.03},
          "TORQUE_UNADVERTISED": {"code": -5},
          "VENDOR_MODES": {"code": -3},
          "RATED_TORQUE_ZERO": {"rated": 100.0},
          "NO_DEFAULTS_RIG_TORQUE": {"rated": 100.0}}
# The family's drives without a PDO-mappable torque or current set point and a mappable
# position: refused whatever the rig says. (NO_DEFAULTS_NO_TORQUE is refused for want of a
# torque scale only: its rig line is NO_DEFAULTS_RIG_TORQUE's.)
NO_SET_POINT = ["NOT_402", "POSITION_ONLY", "CURRENT_NOT_MAPPABLE"]
USABLE = [n for n, (_, _, refusal) in F.FAMILY.items() if refusal is None]


def rig_for(path, **canopen):
    return rig_from_dict({"canopen": {**FAST, "eds": str(path), **canopen},
                          "sim": {"quantize": True}, "safety": {"watchdog_s": 2.0}},
                         source="test-rig")


def refusal(path, **canopen) -> str:
    with pytest.raises(UserError) as info:
        check_eds(str(path), CanopenConfig.from_section({"eds": str(path), **canopen}),
                  rig_for(path, **canopen))
    return str(info.value)


def filled(lines: list[str], manual: dict) -> dict:
    """The suggested rig lines with each <placeholder> filled from the manuals: a
    [canopen] table."""
    def fill(m):
        text = m.group(0)
        if "0x6060" in text:
            return str(manual["code"])
        if "torque constant" in text:
            return repr(manual["kt"])
        if "rated torque" in text:
            return repr(manual["rated"])
        if '"mA"' in text:
            return f'"{manual["unit"]}"'
        raise AssertionError(f"a placeholder the test cannot fill: {text}")

    return tomllib.loads("\n".join(PLACEHOLDER_RE.sub(fill, line) for line in lines))["canopen"]


def suggested(path, name) -> dict:
    """The [canopen] lines the refusal of the bare dictionary names, filled in."""
    a = _assessment(path)
    assert a.obstacles and a.rig_lines, name
    text = refusal(path)
    assert text.count("\n") == 0 and "rig lines that would make it usable: [canopen]" in text
    return filled(a.rig_lines, MANUAL[name])


def _assessment(path, **canopen):
    from labbench.drivers.canopen_check import assess
    from labbench.drivers.canopen_objects import read_eds

    config = CanopenConfig.from_section({"eds": str(path), **canopen})
    return assess(read_eds(str(path), 1), config, rig_for(path, **canopen))


def lines_for(tmp_path, name):
    """(path, [canopen] fields) that make the pattern usable: none, or the refusal's own
    suggestion filled in from the manuals."""
    spec, canopen, _ = F.FAMILY[name]
    path = F.write(tmp_path / f"{name.lower()}.eds", **spec)
    if name in MANUAL:
        return path, suggested(path, name)
    return path, canopen


# ------------------------------------------------------------------------ the goal
@pytest.mark.parametrize("name", [n for n in MANUAL])
def test_a_refused_drive_names_the_rig_lines_that_make_it_usable(tmp_path, name):
    """Refused as it is, in one message that names rig lines; with those lines (the
    values only its manuals know filled in) it opens and follows the exact plant."""
    path, canopen = lines_for(tmp_path, name)
    rig = rig_for(path, **canopen)
    config = sim_config(rig)
    d = connect_driver(rig, config, *start_sim_drive(rig, config))
    try:
        assert run_forces(d, FORCES[:100]) == oracle_counts(
            d.rig, FORCES[:100], per_newton=d.assessment.force_to_command)
    finally:
        d.close()


def test_the_family_is_sorted_into_usable_and_refused():
    refused = {n for n, (_, _, refusal) in F.FAMILY.items() if refusal is not None}
    assert refused == {*NO_SET_POINT, "NO_DEFAULTS_NO_TORQUE"}
    assert set(MANUAL) <= set(USABLE)


@pytest.mark.parametrize("name", NO_SET_POINT)
def test_a_drive_without_a_mappable_set_point_stays_refused_naming_no_rig_lines(tmp_path, name):
    spec, canopen, words = F.FAMILY[name]
    path = F.write(tmp_path / f"{name.lower()}.eds", **spec)
    text = refusal(path, **canopen)
    assert words in text and "rig lines" not in text and text.count("\n") == 0


@pytest.mark.parametrize("name", [pytest.param(n, marks=() if n in MANUAL or n in (
    "BASE", "POSITION_VENDOR") else pytest.mark.slow) for n in USABLE])
def test_every_usable_family_drive_rehearses_chirp_id_and_etfe(tmp_path, name):
    """The issue's goal on the simulated drive built from each profile: chirp-ID (5 s) and
    white-noise ETFE (10 s, closed-loop fit) give m within 1 % and b within 5 %, the record
    in SI at the handle whatever the set point's unit."""
    path, canopen = lines_for(tmp_path, name)
    rig = rig_for(path, **canopen)
    for protocol, options in (("chirp-id", dict(duration_s=5.0, amplitude_n=2.0, x_max_m=0.04,
                                                f0_hz=0.5)),
                              ("etfe", dict(duration_s=10.0, std_n=1.0, seed=11))):
        records = []
        result = run(open_device("sim-canopen", rig), make_protocol(protocol, **options),
                     [records.append], rig=rig, simulated=True)
        assert result.status == "success", (protocol, result.reason)
        r = result.results
        m, b = (r["m"], r["b"]) if protocol == "chirp-id" else (r["loop_fit"]["m"],
                                                                r["loop_fit"]["b"])
        assert m == pytest.approx(rig.nominal_mass_kg, rel=0.01), (protocol, m)
        assert b == pytest.approx(rig.nominal_damping_ns_m, rel=0.05), (protocol, b)


# ------------------------------------------------------------- the rig against the file
@pytest.mark.parametrize("canopen,words", [
    ({**F.CURRENT_MODE_RIG, "modes": {"current": {**F.CURRENT_MODE_RIG["modes"]["current"],
                                                  "type": "INTEGER32"}}},
     r'the rig\'s \[canopen.modes.current\] command = "0x2030:00" but in \S+ 0x2030:00 '
     r"\(Current mode setting value\) is INTEGER16, not the rig's type = INTEGER32"),
    ({**F.CURRENT_MODE_RIG, "modes": {"current": {**F.CURRENT_MODE_RIG["modes"]["current"],
                                                  "command": "0x2027:00"}}},
     r'the rig\'s \[canopen.modes.current\] command = "0x2027:00" but in \S+ 0x2027:00 '
     r"\(Current actual value averaged\) is ro"),
    ({**F.CURRENT_MODE_RIG, "position": "0x3064:00"},
     r'the rig\'s \[canopen\] position = "0x3064:00" but in \S+ 0x3064:00 \(vendor object\) '
     "absent"),
    ({**F.CURRENT_MODE_RIG, "velocity": "0x2100:01"},
     r'the rig\'s \[canopen\] velocity = "0x2100:01" but in \S+ 0x2100:01 \(vendor object\) '
     "absent"),
    ({**F.CURRENT_MODE_RIG, "position": "0x2027:00"},
     r"0x2027:00 \(Current actual value averaged\) is 16 bit"),
    ({**F.CURRENT_MODE_RIG, "torque_constant_nm_per_a": 0.0},
     r"no torque scale: the set point 0x2030:00 is a current in mA; set \[canopen\] "
     "torque_constant_nm_per_a"),
])
def test_a_rig_contradicting_the_file_is_refused_at_open_naming_both(tmp_path, canopen, words):
    path = F.write(tmp_path / "current.eds", **F.CURRENT_MODE)
    offline = refusal(path, **canopen)
    assert re.search(words, offline), offline
    rig = rig_for(path, **canopen)
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, sim_config(rig_for(path, **F.CURRENT_MODE_RIG)))
    with pytest.raises(UserError) as info:
        connect_driver(rig, config, peer, bus)
    assert str(info.value).split(": cannot be used")[1] == offline.split(": cannot be used")[1]
    assert peer.node.writes == []


def test_a_set_point_the_file_says_is_not_mappable_is_refused_naming_the_rig_line(tmp_path):
    path = F.write(tmp_path / "nomap.eds", **F.CURRENT_NOT_MAPPABLE)
    text = refusal(path, **F.CURRENT_MODE_RIG)
    assert re.search(r'the rig\'s \[canopen.modes.current\] command = "0x2030:00" but in \S+ '
                     r"0x2030 \(Current mode setting value\) is not PDO-mappable", text), text
    assert "1 obstacle(s)" in text


@pytest.mark.parametrize("section,words", [
    ({"modes": {"c": {"code": -3, "unit": "mV"}}}, r"\[canopen\] modes.c.unit must be one of"),
    ({"modes": {"c": {"code": -3, "type": "REAL32"}}}, r"modes.c.type must be one of"),
    ({"modes": {"c": {"code": -3, "command": "2030"}}}, r'modes.c.command must name an object'),
    ({"modes": {"c": {"code": -3, "command": "0x20300"}}}, r"modes.c.command must name"),
    ({"modes": {"c": {"code": -3, "comand": "0x2030"}}}, r"modes.c must be \{code"),
    ({"position": 0x6064}, r"\[canopen\] position must name an object"),
    ({"velocity": "0x606C:100"}, r"\[canopen\] velocity must name an object"),
])
def test_bad_vendor_lines_are_one_line_errors(section, words):
    with pytest.raises(UserError, match=words):
        CanopenConfig.from_section(section)


def test_vendor_lines_are_normalised():
    cfg = CanopenConfig.from_section({"position": "0x3064", "modes": {
        "c": {"code": -3, "command": "0x2030:0", "unit": "mA"}}})
    assert cfg.position == "0x3064:00" and cfg.modes["c"] == {
        "code": -3, "bit": None, "command": "0x2030:00", "unit": "mA", "type": None}
    (mode,) = [m for m in cfg.torque_modes() if m.name == "c"]
    assert mode.command == (0x2030, 0) and mode.data_type is None


# ------------------------------------------------------------------- the whole chain
def test_current_mode_in_the_record_is_si_at_the_handle(opened):  # noqa: F811
    """The set point goes out in mA (the drive holds it), the record keeps newtons."""
    d = opened("CURRENT_MODE", **F.CURRENT_MODE_RIG)
    run_forces(d, [0.3] * 3)
    d.read(1.0)
    # 0.3 N x 0.1 m / 0.03 N m/A = 1 A
    assert d.peer.mode == -3 and d.peer.applied == 1000 and d.peer.targets[(0x2030, 0)] == 1000
    assert d.describe().details["set_point"] == "0x2030:00 Current mode setting value (mA)"
    assert d.describe().force_limit_n == pytest.approx(d.rig.force_limit_n, rel=1e-4)  # 1 mA
    run_forces(d, [50.0])  # the host clamps (no 0x6072 in a current mode): 5 N
    d.read(1.0)  # the drive's thread took the RPDO before it answers this SYNC
    assert d.peer.applied == round(d.rig.force_limit_n * 0.1 / 0.03 * 1000)
    d.disable()
    assert d.peer.applied == 0


def test_current_mode_drive_in_its_own_process(tmp_path):
    path = F.write(tmp_path / "current.eds", **F.CURRENT_MODE)
    rig = rig_for(path, **F.CURRENT_MODE_RIG, sim_drive="process")
    with open_device("sim-canopen", rig) as d:
        assert run_forces(d, FORCES[:100]) == oracle_counts(
            d.rig, FORCES[:100], per_newton=d.assessment.force_to_command)


def test_vendor_objects_are_surveyed_on_a_drive_without_its_file(tmp_path):
    """No EDS in the rig: the driver reads the rig's vendor objects from the drive itself
    (their type from the rig); mappability is the drive's answer when mapping."""
    path = F.write(tmp_path / "current.eds", **F.CURRENT_MODE)
    rig = rig_from_dict({"canopen": {**FAST, **F.CURRENT_MODE_RIG}}, source="test-rig")
    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, sim_config(rig_for(path, **F.CURRENT_MODE_RIG)))
    d = connect_driver(rig, config, peer, bus)
    try:
        assert d.dictionary.get(0x2030, 0).data_type == 0x3  # the rig's INTEGER16
        assert run_forces(d, FORCES[:50]) == oracle_counts(
            d.rig, FORCES[:50], per_newton=d.assessment.force_to_command)
    finally:
        d.close()


def test_vendor_position_object_is_mapped_and_used(opened):  # noqa: F811
    d = opened("POSITION_VENDOR", **F.POSITION_VENDOR_RIG)
    assert d.assessment.plan.tpdos[0].entries[0].index == 0x3064
    assert "0x3064 Actual position (internal) (32 bit)" in d.assessment.plan.lines()[1]
    assert run_forces(d, FORCES[:50]) == oracle_counts(d.rig, FORCES[:50])
    assert np.isfinite(d.torque_actual_n)


def test_devices_prints_the_suggested_rig_lines(tmp_path, capsys):
    from labbench.cli import main

    path = F.write(tmp_path / "current.eds", **F.CURRENT_MODE)
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(f'[canopen]\neds = "{path.name}"\nsdo_timeout_s = 2.0\n')
    main(["devices", "--rig", str(rig_file)])  # the canopen row finds no CAN interface
    out = capsys.readouterr().out.split("sim-canopen")[1].split("sim-serial")[0]
    assert "rig lines that would make it usable:" in out
    for line in ('  [canopen]', '  mode = "vendor"', "  [canopen.modes]",
                 '  vendor = {code = <the 0x6060 value'):
        assert "\n             " + line in out, (line, out)


def test_the_example_current_mode_rig_rehearses():
    """docs/examples/current-mode: its drive file is the family's CURRENT_MODE, its rig
    opens on the simulated drive and follows the exact plant."""
    from pathlib import Path

    from labbench.rig import load_rig

    folder = Path(__file__).parents[1] / "docs" / "examples" / "current-mode"
    assert (folder / "drive.eds").read_text().split("[DeviceInfo]")[1] == \
        F.eds_text(**F.CURRENT_MODE).split("[DeviceInfo]")[1]
    rig = load_rig(folder / "rig.toml")
    with open_device("sim-canopen", rig) as d:
        assert d.describe().details["torque_scale"] == "0x2030:00 in mA x torque constant " \
                                                       "0.03 N m/A"
        assert run_forces(d, FORCES[:50]) == oracle_counts(
            d.rig, FORCES[:50], per_newton=d.assessment.force_to_command)
