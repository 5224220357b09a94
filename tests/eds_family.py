"""A family of synthetic CiA 402 object dictionaries (EDS text written here, not copied).

``eds_text(**variant)`` starts from a complete torque drive and applies the
variant: objects dropped, access types or PDO-mapping flags changed, values
and limits set, the number of PDOs and their mapping slots, fixed (read-only)
mappings, node guarding instead of heartbeat, a DCF's ParameterValues. Each
variant is one obstacle (or one missing optional object) of a real drive.
"""
from __future__ import annotations

from pathlib import Path

U8, I8, U16, I16, U32, I32 = 0x5, 0x2, 0x6, 0x3, 0x7, 0x4

# (index, sub, name, data type, access, default, PDO-mappable); sub None: a plain variable.
BASE = [
    (0x1000, None, "Device type", U32, "ro", "0x00020192", 0),
    (0x1001, None, "Error register", U8, "ro", "0", 1),
    (0x1003, 0, "Number of errors", U8, "rw", "0", 0),
    (0x1003, 1, "Standard error field", U32, "ro", "0", 0),
    (0x1003, 2, "Standard error field", U32, "ro", "0", 0),
    (0x100C, None, "Guard time", U16, "rw", "0", 0),
    (0x100D, None, "Life time factor", U8, "rw", "0", 0),
    (0x1016, 0, "Highest sub-index", U8, "const", "1", 0),
    (0x1016, 1, "Consumer heartbeat time", U32, "rw", "0", 0),
    (0x1017, None, "Producer heartbeat time", U16, "rw", "0", 0),
    (0x1018, 0, "Highest sub-index", U8, "const", "4", 0),
    (0x1018, 1, "Vendor-ID", U32, "ro", "0x00ABCDEF", 0),
    (0x1018, 2, "Product code", U32, "ro", "0x00000011", 0),
    (0x1018, 3, "Revision number", U32, "ro", "0x00020003", 0),
    (0x1018, 4, "Serial number", U32, "ro", "0x00000042", 0),
    (0x603F, None, "Error code", U16, "ro", "0", 1),
    (0x6007, None, "Abort connection option code", I16, "rw", "1", 0),
    (0x6040, None, "Controlword", U16, "rw", "0", 1),
    (0x6041, None, "Statusword", U16, "ro", "0", 1),
    (0x605A, None, "Quick stop option code", I16, "rw", "2", 0),
    (0x605E, None, "Fault reaction option code", I16, "rw", "2", 0),
    (0x6060, None, "Modes of operation", I8, "rw", "0", 1),
    (0x6061, None, "Modes of operation display", I8, "ro", "0", 1),
    (0x6064, None, "Position actual value", I32, "ro", "0", 1),
    (0x606C, None, "Velocity actual value", I32, "ro", "0", 1),
    (0x6071, None, "Target torque", I16, "rw", "0", 1),
    (0x6072, None, "Max torque", U16, "rw", "1000", 1),
    (0x6075, None, "Motor rated current", U32, "rw", "0", 0),
    (0x6076, None, "Motor rated torque", U32, "rw", "100", 0),
    (0x6077, None, "Torque actual value", I16, "ro", "0", 1),
    (0x607D, 0, "Highest sub-index", U8, "const", "2", 0),
    (0x607D, 1, "Min position limit", I32, "rw", "-2147483648", 0),
    (0x607D, 2, "Max position limit", I32, "rw", "2147483647", 0),
    (0x6502, None, "Supported drive modes", U32, "ro", "0x00000208", 0),
]


def _pdos(tx: bool, count: int, slots: int, timer: bool, fixed: dict) -> list:
    """Communication and mapping objects of ``count`` PDOs with ``slots`` slots each.

    ``fixed``: PDO number (1-based) -> mapping entries, read-only.
    """
    comm, mapping = (0x1800, 0x1A00) if tx else (0x1400, 0x1600)
    out = []
    for n in range(count):
        cob = f"$NODEID+0x{(0x180 if tx else 0x200) + 0x100 * n:X}" if n < 4 else "0x80000000"
        out += [(comm + n, 0, "Highest sub-index", U8, "const", "5" if timer else "2", 0),
                (comm + n, 1, "COB-ID", U32, "rw", cob, 0),
                (comm + n, 2, "Transmission type", U8, "rw", "1" if tx else "255", 0)]
        if timer:
            out += [(comm + n, 3, "Inhibit time", U16, "rw", "0", 0),
                    (comm + n, 5, "Event timer", U16, "rw", "0", 0)]
        entries = fixed.get(n + 1)
        access = "ro" if entries is not None else "rw"
        entries = entries or []
        out.append((mapping + n, 0, "Number of mapped objects", U8, access, str(len(entries)), 0))
        for s in range(1, slots + 1):
            value = f"0x{entries[s - 1]:08X}" if s <= len(entries) else "0"
            out.append((mapping + n, s, f"Mapping entry {s}", U32, access, value, 0))
    return out


def eds_text(*, drop=(), access=None, mappable=None, default=None, limits=None,
             rpdos: int = 1, tpdos: int = 2, slots: int = 4, timers: bool = True,
             fixed_rpdo=None, fixed_tpdo=None, dcf_values=None, objects=(),
             extra_lines: str = "") -> str:
    """EDS (or, with ``dcf_values``, DCF) text of one variant.

    ``drop``: indices or (index, sub) to leave out; ``access``/``mappable``/
    ``default``: by index or (index, sub); ``limits``: index -> (low, high);
    ``dcf_values``: (index, sub) -> ParameterValue; ``objects``: more rows as
    in ``BASE`` (a vendor's own objects); ``extra_lines`` is appended as it is
    (to plant defects).
    """
    access, mappable, default = access or {}, mappable or {}, default or {}
    limits, dcf_values = limits or {}, dcf_values or {}
    rows = BASE + list(objects) + _pdos(False, rpdos, slots, timers, fixed_rpdo or {}) + _pdos(
        True, tpdos, slots, timers, fixed_tpdo or {})
    rows = [r for r in rows if r[0] not in drop and (r[0], r[1] or 0) not in drop]

    def pick(table, r, value):
        return table.get((r[0], r[1] or 0), table.get(r[0], value))

    out = ["[FileInfo]", "FileName=synthetic.eds", "EDSVersion=4.0",
           "Description=synthetic drive of the labbench tests", "",
           "[DeviceInfo]", "VendorName=nobody", f"NrOfRXPDO={rpdos}", f"NrOfTXPDO={tpdos}", ""]
    parents = {}
    for r in rows:
        if r[1] is not None:
            parents.setdefault(r[0], []).append(r[1])
    done = set()
    for index, sub, name, dtype, acc, dflt, pdo in rows:
        if sub is not None and index not in done:
            done.add(index)
            kind = "0x9" if index in (0x1018,) or 0x1400 <= index < 0x1600 or \
                0x1800 <= index < 0x1A00 else "0x8"
            out += [f"[{index:04X}]", f"ParameterName=object {index:04X}", f"ObjectType={kind}",
                    f"SubNumber={len(parents[index])}", ""]
        out.append(f"[{index:04X}]" if sub is None else f"[{index:04X}sub{sub:X}]")
        value = pick(default, (index, sub), dflt)
        out += [f"ParameterName={name}", "ObjectType=0x7", f"DataType=0x{dtype:04X}",
                f"AccessType={pick(access, (index, sub), acc)}"]
        out += [f"DefaultValue={value}"] if value is not None else []  # None: no default
        out.append(f"PDOMapping={int(pick(mappable, (index, sub), pdo))}")
        if (index, sub or 0) in dcf_values:
            out.append(f"ParameterValue={dcf_values[(index, sub or 0)]}")
        if index in limits and sub is None:
            out += [f"LowLimit={limits[index][0]}", f"HighLimit={limits[index][1]}"]
        out.append("")
    return "\n".join(out) + extra_lines


def write(path: Path, **variant) -> Path:
    path.write_text(eds_text(**variant))
    return path


def entry(index: int, bits: int, sub: int = 0) -> int:
    """A PDO mapping entry (CiA 301)."""
    return index << 16 | sub << 8 | bits


OPTIONAL_MISSING = dict(drop=[(0x1018, 2), (0x1018, 3), (0x1018, 4), 0x603F, 0x605A, 0x605E,
                              0x6007, 0x6072, 0x607D, 0x6061, 0x1003, 0x100C, 0x100D],
                        timers=False, default={(0x1018, 0): "1"})
ONE_SLOT = dict(rpdos=4, tpdos=4, slots=1)
FIXED = dict(fixed_rpdo={1: [entry(0x6040, 16), entry(0x6071, 16)]},
             fixed_tpdo={1: [entry(0x6041, 16), entry(0x6064, 32)],
                         2: [entry(0x6061, 8)]}, tpdos=3)
GUARDING_ONLY = dict(drop=[0x1016, 0x1017])
RATED_TORQUE_ZERO = dict(default={0x6076: "0"})
VENDOR_MODES = dict(default={0x6502: "0x00010000"}, limits={0x6060: (-3, 10)})
NOT_402 = dict(default={0x1000: "0x00000191", 0x6502: "0x00000000"},
               drop=[0x6071, 0x6060, 0x6040, 0x6041, 0x6064, 0x6076, 0x1016, 0x100C, 0x100D])

# Traits of real vendors' files (facts from 13 public EDS files; none copied).
NO_DEFAULTS = dict(default={0x1000: None, 0x6502: None, (0x1018, 4): None, 0x605A: None,
                            0x6075: None, (0x1400, 1): None, (0x1600, 1): None, 0x1017: None})
HEX_SIGNED = dict(default={(0x607D, 1): "0x80000000", (0x607D, 2): "0x7FFFFFFF",
                           0x605A: "0xFFFF", 0x6007: "0x0001", 0x6072: "01750"},
                  limits={0x6060: ("0x80", "0x7F"), 0x605A: ("0xFFFF", "0x0007")})
WRITE_ONLY_MODE = dict(access={0x6060: "wo"})
NO_6502 = dict(drop=[0x6502])
NODEID_FORMS = dict(default={(0x1800, 1): "0x180 + $NODEID", (0x1400, 1): "$NODEID+512",
                             (0x1801, 1): "0x280+$nodeid"})
# A drive whose torque path is its own current mode (as maxon's EPOS2): no 0x6071, 0x6072,
# 0x6076, 0x6077; 0x6502 lists position/velocity modes only; a vendor set point in mA
# (INTEGER16, mappable) and current actual values. Values are ours.
CURRENT_MODE = dict(drop=[0x6071, 0x6072, 0x6076, 0x6077], default={0x6502: "0x00000065"},
                    limits={0x6060: (-6, 8)},
                    objects=[(0x2030, None, "Current mode setting value", I16, "rw", "0", 1),
                             (0x2027, None, "Current actual value averaged", I16, "ro", "0", 1),
                             (0x6078, None, "Current actual value", I16, "ro", "0", 1)])
CURRENT_MODE_RIG = {"mode": "current", "torque_constant_nm_per_a": 0.03, "modes": {
    "current": {"code": -3, "command": "0x2030:00", "type": "INTEGER16", "unit": "mA"}}}
# 0x6071 there and mappable, but 0x6502 advertises no torque mode (as Technosoft's iPOS):
# a vendor mode number (from the manual) makes 0x6071 the set point.
TORQUE_UNADVERTISED = dict(default={0x6502: "0x00000065"}, limits={0x6060: (-5, 10)})
TORQUE_UNADVERTISED_RIG = {"mode": "torque", "modes": {"torque": {"code": -5}}}
# 0x6064 not PDO-mappable, a vendor position object that is (as Faulhaber's MCDC).
POSITION_VENDOR = dict(mappable={0x6064: 0},
                       objects=[(0x3064, None, "Actual position (internal)", I32, "ro", "0", 1)])
POSITION_VENDOR_RIG = {"position": "0x3064:00"}
# Refused whatever the rig says: a position-only drive (profile position alone, no torque
# or current set point), and a current mode whose set point cannot be mapped.
POSITION_ONLY = dict(drop=[0x6071, 0x6072, 0x6076, 0x6077], default={0x6502: "0x00000001"})
CURRENT_NOT_MAPPABLE = dict(CURRENT_MODE, mappable={0x2030: 0})
# name -> (variant, extra [canopen] fields the rig needs, obstacle words or None: rehearses)
FAMILY = {
    "BASE": ({}, {}, None),
    "NO_DEFAULTS": (NO_DEFAULTS, {}, None),
    "NO_DEFAULTS_NO_TORQUE": (dict(default={**NO_DEFAULTS["default"], 0x6076: None}), {},
                              "no torque scale: motor rated torque 0x6076 is 0"),
    "NO_DEFAULTS_RIG_TORQUE": (dict(default={**NO_DEFAULTS["default"], 0x6076: None}),
                               {"rated_torque_mnm": 100.0}, None),
    "HEX_SIGNED": (HEX_SIGNED, {}, None),
    "WRITE_ONLY_MODE": (WRITE_ONLY_MODE, {}, None),
    "NO_6502": (NO_6502, {}, None),
    "RATED_TORQUE_ZERO": (RATED_TORQUE_ZERO, {"rated_torque_mnm": 100.0}, None),
    "ONE_SLOT": (ONE_SLOT, {}, None),
    "FIXED": (FIXED, {}, None),
    "GUARDING_ONLY": (GUARDING_ONLY, {}, None),
    "OPTIONAL_MISSING": (OPTIONAL_MISSING, {}, None),
    "NODEID_FORMS": (NODEID_FORMS, {}, None),
    "VENDOR_MODES": (VENDOR_MODES, {"modes": {"current": {"code": -3, "bit": 16}}}, None),
    "NOT_402": (NOT_402, {}, "not a CiA 402 drive"),
    "CURRENT_MODE": (CURRENT_MODE, CURRENT_MODE_RIG, None),
    "TORQUE_UNADVERTISED": (TORQUE_UNADVERTISED, TORQUE_UNADVERTISED_RIG, None),
    "POSITION_VENDOR": (POSITION_VENDOR, POSITION_VENDOR_RIG, None),
    "POSITION_ONLY": (POSITION_ONLY, {}, "no torque mode"),
    "CURRENT_NOT_MAPPABLE": (CURRENT_NOT_MAPPABLE, CURRENT_MODE_RIG,
                             "0x2030 (Current mode setting value) is not PDO-mappable"),
}
