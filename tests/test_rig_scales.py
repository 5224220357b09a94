"""Every rig number that scales a command has a physical range (``labbench.scales``), and no
value within the ranges lets a command past the rig's force limit (issue 44).

Before: ``[canopen] torque_constant_nm_per_a = 1e-300`` (or 1e308) passed ``labbench
devices`` and ``run etfe --device sim-canopen`` ended "success" with forces up to 1.7 N
recorded while the handle never moved (every nonzero force would have been the drive's
largest current on a real motor); an unknown ``[canopen]`` field far from every name passed
silently.

The largest command is derived here from the scale's own definition (a per-mille of the
rated torque is rated x 1e-3 N m, a mA is 1e-3 x the torque constant, ...), not read back from
the driver, and converted back to newtons at the handle: the driver's assessment either
refuses the combination in its one message, for a reason this derivation confirms (one unit
above the force limit, or a force limit beyond the set point's range), or clamps at the
force limit to within half a unit.
"""
from __future__ import annotations

import itertools

import pytest

import eds_family as F
from labbench import scales
from labbench.drivers.canopen_check import assess
from labbench.drivers.canopen_config import CanopenConfig
from labbench.drivers.canopen_objects import read_eds
from labbench.errors import UserError
from labbench.rig import rig_from_dict


def test_each_scale_and_its_bound(capsys):
    """The table of scales, printed; each bound itself accepted, a step beyond it and every
    hostile value refused when the rig is read, in one line naming the table, the field and
    the range."""
    lines = []
    for (table, name), b in scales.SCALES.items():
        lines.append(f"[{table}] {name}: {b.lo:g} .. {b.hi:g} {b.unit}"
                     + (f" (or {b.unset:g}: not given)" if b.unset is not None else ""))
        for good in (b.lo, b.hi, (b.lo * b.hi) ** 0.5):
            assert rig_from_dict({table: {name: good}}, "r.toml").section(table) or table == "rig"
        bad = [b.lo / 1.01, b.hi * 1.01, 1e-300, 1e308, -b.hi, float("nan"), float("inf"),
               True, "1"] + ([] if b.unset == 0 else [0])
        for value in bad:
            with pytest.raises(UserError) as info:
                rig_from_dict({table: {name: value}}, "r.toml")
            text = str(info.value)
            assert "\n" not in text and f"[{table}] {name} must be a number in " \
                   f"[{b.lo:g}, {b.hi:g}] {b.unit}" in text, text
    with capsys.disabled():
        print("\nrig scales and their physical ranges:\n  " + "\n  ".join(lines))
    assert {name for _, name in scales.SCALES} >= {
        "lever_arm_m", "counts_per_rev", "rated_torque_mnm", "torque_constant_nm_per_a",
        "rated_current_ma"}


@pytest.mark.parametrize("table, field, near", [
    ("canopen", "zzzzzz", None), ("canopen", "node_idd", "node_id"),
    ("canopen", "torque_constant", "torque_constant_nm_per_a"), ("sim", "zzzzzz", None),
    ("sim", "lever_arm", "lever_arm_m"), ("serial", "zzzzzz", None),
    ("serial", "baud_rate", "baudrate"), ("rig", "zzzzzz", None), ("rig", "lever_arm", "lever_arm_m"),
    ("safety", "zzzzzz", None), ("campaign", "zzzzzz", None), ("realtime", "zzzzzz", None),
    ("preflight", "zzzzzz", None)])
def test_an_unknown_field_is_refused_in_every_table_alike(table, field, near):
    """Every table a rig file may hold refuses a field it does not know when the file is read,
    naming it (and the nearest known one where there is a near one)."""
    with pytest.raises(UserError) as info:
        rig_from_dict({table: {field: 3}}, "r.toml")
    text = str(info.value)
    assert f"[{table}]" in text and field in text and "\n" not in text, text
    if near:
        assert near in text, text


def test_python_can_options_go_in_their_own_table():
    cfg = CanopenConfig.from_rig(rig_from_dict(
        {"canopen": {"node_id": 3, "bus": {"fd": True, "data_bitrate": 2_000_000}}}, "r.toml"))
    assert cfg.bus_kwargs() == {"fd": True, "data_bitrate": 2_000_000} and cfg.node_id == 3
    with pytest.raises(UserError, match=r"unknown field 'fd'.*go in \[canopen.bus\]"):
        rig_from_dict({"canopen": {"fd": True}}, "r.toml")
    with pytest.raises(UserError, match=r"\[canopen\] bus must be a table"):
        rig_from_dict({"canopen": {"bus": {"filters": [1, 2]}}}, "r.toml")


# -------------------------------------------------- the largest command of every scale
# A drive's set point per unit [N m at the joint], from the scale's definition (CiA 402: 0x6071
# is per-mille of the motor's rated torque 0x6076 in mN m; a current set point times the
# motor's torque constant).
def nm_per_unit(unit: str, rated_mnm: float, kt: float) -> float:
    return {"permille": rated_mnm * 1e-3 * 1e-3, "mNm": 1e-3, "Nm": 1.0,
            "mA": 1e-3 * kt, "A": kt}[unit]


def _current_mode(unit: str) -> dict:
    return {"mode": "current", "modes": {"current": {"code": -3, "command": "0x2030:00",
                                                     "type": "INTEGER16", "unit": unit}}}


# (drive variant, its rated torque in the file [mN m] or None, the [canopen] lines) per path
# a force takes to a set point
PATHS = {
    "per-mille of the drive's 0x6076": ({}, 100.0, {}),
    "per-mille of rated_torque_mnm": (F.RATED_TORQUE_ZERO, None, {"rated_torque_mnm": None}),
    "per-mille of kt x rated_current_ma": (F.RATED_TORQUE_ZERO, None,
                                           {"torque_constant_nm_per_a": 0.03,
                                            "rated_current_ma": None}),
    "mA x torque_constant": (F.CURRENT_MODE, None, {**_current_mode("mA"),
                                                   "torque_constant_nm_per_a": None}),
    "A x torque_constant": (F.CURRENT_MODE, None, {**_current_mode("A"),
                                                  "torque_constant_nm_per_a": None}),
    "mN m": (F.CURRENT_MODE, None, _current_mode("mNm")),
    "N m": (F.CURRENT_MODE, None, _current_mode("Nm")),
}
SCALE_OF = {"rated_torque_mnm": "per-mille of rated_torque_mnm",
            "torque_constant_nm_per_a": "mA x torque_constant",
            "rated_current_ma": "per-mille of kt x rated_current_ma"}
FORCE_LIMITS = (0.01, 5.0, 1000.0)  # [rig] force_limit_n: near its lowest, the default, its highest


def _cases():
    """Every path, with its own scale (None in PATHS) at its two bounds and a middle value,
    crossed with the lever arm and the counts per revolution at theirs, and three force limits."""
    def spread(b):
        return (b.lo, (b.lo * b.hi) ** 0.5, b.hi)

    levers = spread(scales.SCALES[("rig", "lever_arm_m")])
    counts = (scales.SCALES[("rig", "counts_per_rev")].lo,
              scales.SCALES[("rig", "counts_per_rev")].hi)
    for path, (variant, rated, canopen) in PATHS.items():
        own = [k for k, v in canopen.items() if v is None]
        values = spread(scales.SCALES[("canopen", own[0])]) if own else (None,)
        for v, lever, cpr, limit in itertools.product(values, levers, counts, FORCE_LIMITS):
            yield path, variant, rated, {**canopen, **({own[0]: v} if own else {})}, lever, cpr, limit


def test_the_largest_command_of_every_scale_is_the_force_limit_or_refused(tmp_path, capsys):
    files, dicts = {}, {}
    seen = {"clamped": 0, "one unit above the limit": 0, "limit beyond the range": 0}
    worst = 0.0  # largest (commanded force at the clamp - force limit) / one unit
    for path, variant, rated, canopen, lever, cpr, limit in _cases():
        name = repr(sorted(variant.items()))
        if name not in files:
            files[name] = str(F.write(tmp_path / f"d{len(files)}.eds", **variant))
        rig = rig_from_dict({"rig": {"lever_arm_m": lever, "counts_per_rev": cpr,
                                     "force_limit_n": limit},
                             "canopen": {"eds": files[name], **canopen}}, "r.toml")
        config = CanopenConfig.from_rig(rig)
        if config.eds not in dicts:
            dicts[config.eds] = read_eds(config.eds, config.node_id)
        a = assess(dicts[config.eds], config, rig)
        unit = a.unit
        kt = canopen.get("torque_constant_nm_per_a", 0.0)
        rated_mnm = rated or canopen.get("rated_torque_mnm") or kt * canopen.get(
            "rated_current_ma", 0.0)
        per_unit_n = nm_per_unit(unit, rated_mnm, kt) / lever  # N at the handle per unit
        assert a.force_to_command == pytest.approx(1 / per_unit_n, rel=1e-12), (path, canopen)
        units = limit / per_unit_n  # the force limit in set point units
        ours = [o for o in a.obstacles if "force_limit_n" in o]
        if abs(units - 1) < 1e-6 or abs(units / 32767 - 1) < 1e-6:
            continue  # at a boundary itself: either outcome is right
        if units < 1:
            assert ours and "one unit of" in ours[0] and "above [rig] force_limit_n" in ours[0]
            seen["one unit above the limit"] += 1
        elif units > 32767:  # every set point of the family is 16 bit
            assert ours and "beyond its largest value 32767" in ours[0], (path, canopen, ours)
            seen["limit beyond the range"] += 1
        else:
            assert not ours, ours
            top_force = a.max_command * per_unit_n
            assert abs(top_force - limit) <= 0.5 * per_unit_n * (1 + 1e-9), (path, canopen)
            worst = max(worst, (top_force - limit) / per_unit_n)
            seen["clamped"] += 1
    with capsys.disabled():
        print(f"\nlargest command of every scale: {seen}; at most {worst:.3f} unit above the "
              "force limit where clamped")
    assert all(seen.values())  # each outcome met: the derivation above is exercised both ways
