"""A drive's object dictionary as the driver sees it: from an EDS/DCF, from the drive, or both.

``read_eds`` reads an EDS or DCF leniently: common defects (a duplicated key
or section, a sub-object without its parent, an unreadable number, a missing
DataType) give a warning and the rest of the file is used. ``survey`` asks the
drive itself, read-only, which of the objects the driver may use exist and
what they hold; given a ``Dictionary`` from a file it confirms each object
against the drive (the drive wins), otherwise it probes PDO slots one
subindex at a time. It never stops on a refused read: a write-only object
(the file's ``AccessType=wo``, or abort 0x06010001) is known to exist and
never read; any other refusal (e.g. 0x08000024 "no data available") is
recorded in ``Dictionary.refused`` with a warning and the object is taken as
absent, so the assessment names it as an obstacle only if the driver cannot
do without it. Without a file, access types and PDO mappability are
unknown (``access == ""``, ``mappable is None``): the drive's answer to the
write decides, and a refusal names the object.

Data type codes and object meanings: CiA 301 (communication objects) and
CiA 402-2 (drive objects).
"""
from __future__ import annotations

import io
import re
import struct
from dataclasses import dataclass, field, replace

from canopen.objectdictionary import ODVariable
from canopen.objectdictionary.eds import import_eds

from labbench.drivers import eds_values
from labbench.drivers.canopen_sdo import ABSENT, WRITE_ONLY, abort_text, where
from labbench.errors import UserError

# CiA 301 data type codes -> struct code (integers only: nothing else is mapped or compared).
TYPE_FMT = {0x1: "B", 0x2: "b", 0x3: "h", 0x4: "i", 0x5: "B", 0x6: "H", 0x7: "I",
            0x15: "q", 0x1B: "Q"}
U8, I8, U16, I16, U32, I32 = 0x5, 0x2, 0x6, 0x3, 0x7, 0x4

# Objects the driver may use: index -> (name, {subindex: data type}).
STANDARD = {
    0x1000: ("device type", {0: U32}),
    0x1001: ("error register", {0: U8}),
    # The count only: entries above it need not exist (CANopenNode answers 0x08000024);
    # the driver's history reader reads 1..count when it needs them.
    0x1003: ("pre-defined error field", {0: U8}),
    0x100C: ("guard time", {0: U16}),
    0x100D: ("life time factor", {0: U8}),
    0x1016: ("consumer heartbeat time", {0: U8, 1: U32}),
    0x1017: ("producer heartbeat time", {0: U16}),
    0x1018: ("identity", {0: U8, 1: U32, 2: U32, 3: U32, 4: U32}),
    0x603F: ("error code", {0: U16}),
    0x6007: ("abort connection option code", {0: I16}),
    0x6040: ("controlword", {0: U16}),
    0x6041: ("statusword", {0: U16}),
    0x605A: ("quick stop option code", {0: I16}),
    0x605E: ("fault reaction option code", {0: I16}),
    0x6060: ("modes of operation", {0: I8}),
    0x6061: ("modes of operation display", {0: I8}),
    0x6064: ("position actual value", {0: I32}),
    0x606C: ("velocity actual value", {0: I32}),
    0x6071: ("target torque", {0: I16}),
    0x6072: ("max torque", {0: U16}),
    0x6075: ("motor rated current", {0: U32}),
    0x6076: ("motor rated torque", {0: U32}),
    0x6077: ("torque actual value", {0: I16}),
    0x607D: ("software position limit", {0: U8, 1: I32, 2: I32}),
    0x6502: ("supported drive modes", {0: U32}),
}
RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
MAX_PDOS = 8  # per direction: the driver needs at most four; more is never probed
MAX_SLOTS = 8  # 8 bytes hold at most 8 mapped objects of 8 bits
_PDO_COMM_TYPES = {1: U32, 2: U8, 3: U16, 5: U16}


def object_name(index: int) -> str:
    if index in STANDARD:
        return STANDARD[index][0]
    for base, what in ((RPDO_COMM, "RPDO{} communication"), (RPDO_MAP, "RPDO{} mapping"),
                       (TPDO_COMM, "TPDO{} communication"), (TPDO_MAP, "TPDO{} mapping")):
        if base <= index < base + 0x200:
            return what.format(index - base + 1)
    return ""


@dataclass
class Entry:
    """One subindex. ``access``: "ro", "rw", "wo", "const", ... or "" (unknown)."""

    index: int
    sub: int
    data_type: int
    access: str = ""
    mappable: bool | None = None
    low: int | None = None
    high: int | None = None
    value: int | None = None  # the drive's, else a DCF's ParameterValue, else the default
    from_dcf: bool = False
    name: str = ""  # the file's ParameterName ("" when surveyed without a file)

    @property
    def fmt(self) -> str | None:
        return TYPE_FMT.get(self.data_type)

    @property
    def bits(self) -> int:
        return 8 * struct.calcsize(self.fmt) if self.fmt else 0

    @property
    def writable(self) -> bool:
        return self.access == "" or "w" in self.access

    @property
    def readable(self) -> bool:
        return self.access != "wo"

    @property
    def fixed(self) -> bool:
        """Known to be not writable."""
        return not self.writable


@dataclass
class Dictionary:
    """Entries by (index, subindex); ``source`` says where they come from."""

    entries: dict = field(default_factory=dict)
    source: str = "drive"
    warnings: list = field(default_factory=list)
    od: object = None  # the canopen ObjectDictionary read from the file (the simulated drive's)
    from_file: bool = False
    refused: dict = field(default_factory=dict)  # (index, sub) -> SDO abort code of its read

    def gone(self, index: int, sub: int = 0) -> str:
        """Why an object is not there: "absent", or the abort with which its read was refused."""
        code = self.refused.get((index, sub))
        return "absent" if code is None else f"unreadable ({abort_text(code)})"

    def has(self, index: int, sub: int | None = None) -> bool:
        if sub is not None:
            return (index, sub) in self.entries
        return any(i == index for i, _ in self.entries)

    def get(self, index: int, sub: int = 0) -> Entry | None:
        return self.entries.get((index, sub))

    def value(self, index: int, sub: int = 0, default=None):
        e = self.entries.get((index, sub))
        return default if e is None or e.value is None else e.value

    def subs(self, index: int) -> list[int]:
        return sorted(s for i, s in self.entries if i == index)

    def name(self, index: int, sub: int = 0) -> str:
        """What the object is: CiA's name of a standard object, else the file's name."""
        e = self.entries.get((index, sub))
        return object_name(index) or (e.name if e is not None else "")


# ------------------------------------------------------------------ EDS / DCF
_INDEX = re.compile(r"^([0-9A-Fa-f]{4})$")
_SUB = re.compile(r"^([0-9A-Fa-f]{4})[Ss][Uu][Bb]([0-9A-Fa-f]+)$")
_NUMERIC_KEYS = ("DefaultValue", "ParameterValue", "LowLimit", "HighLimit")


def _canonical(section: str) -> str:
    if m := _INDEX.match(section):
        return m.group(1).upper()
    if m := _SUB.match(section):
        return f"{m.group(1).upper()}sub{int(m.group(2), 16):X}"
    return section


def _number(text: str) -> bool:
    try:
        eds_values.parse(text, U32, 0)
        return True
    except ValueError:
        return False


def _clean(text: str, name: str, node_id: int) -> tuple[str, list[str]]:
    """INI text a strict parser accepts, and a warning for each defect repaired."""
    warnings: list[str] = []
    sections: dict[str, dict[str, str]] = {}
    current = None
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split(";", 1)[0].strip() if not raw.lstrip().startswith(";") else ""
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            if not line.endswith("]"):
                warnings.append(f"{name} line {n}: unterminated section header ignored")
                current = None
                continue
            sec = _canonical(line[1:-1].strip())
            if sec in sections:
                warnings.append(f"{name} line {n}: section [{sec}] appears twice (merged)")
            current = sections.setdefault(sec, {})
            continue
        if "=" not in line or current is None:
            warnings.append(f"{name} line {n}: not a key=value line of a section, ignored")
            continue
        key, value = (s.strip() for s in line.split("=", 1))
        if key in current and current[key] != value:
            warnings.append(f"{name} line {n}: duplicated key {key} (later value {value} used)")
        current[key] = value
    for sec, keys in list(sections.items()):
        if m := _SUB.match(sec):
            parent = sections.get(m.group(1).upper())
            if parent is None or int(parent.get("ObjectType", "7"), 0) not in (8, 9):
                warnings.append(f"{name}: [{sec}] has no array/record [{m.group(1)}]: ignored")
                del sections[sec]
                continue
        elif not _INDEX.match(sec):
            continue
        try:
            object_type = int(keys.get("ObjectType", "7"), 0)
        except ValueError:
            warnings.append(f"{name}: [{sec}] ObjectType {keys['ObjectType']} unreadable: ignored")
            del sections[sec]
            continue
        keys.setdefault("ParameterName", sec)
        if object_type in (8, 9) and not _SUB.match(sec):
            continue
        if not _number(keys.get("DataType", "x")):
            warnings.append(f"{name}: [{sec}] has no DataType: ignored")
            del sections[sec]
            continue
        access = keys.get("AccessType", "").lower()
        if access not in ("ro", "wo", "rw", "rwr", "rww", "const"):
            warnings.append(f"{name}: [{sec}] AccessType {keys.get('AccessType', '(none)')} "
                            "not understood: taken as ro")
            access = "ro"
        keys["AccessType"] = access
        warnings += _values(keys, name, sec, node_id)
    if "DeviceInfo" not in sections:
        warnings.append(f"{name}: no [DeviceInfo] section (mandatory): taken as empty")
        sections["DeviceInfo"] = {}
    out = io.StringIO()
    for sec, keys in sections.items():
        out.write(f"[{sec}]\n" + "".join(f"{k}={v}\n" for k, v in keys.items()) + "\n")
    return out.getvalue(), warnings


def _values(keys: dict, name: str, sec: str, node_id: int) -> list[str]:
    """Rewrite the values of one variable section as plain numbers read by its data type
    (``eds_values``); a warning for each value that means nothing, which is dropped."""
    dtype = eds_values.parse(keys["DataType"], U16)
    warnings = []
    for key in _NUMERIC_KEYS:
        if key not in keys or not eds_values.known(dtype):
            continue
        if keys[key] == "":
            del keys[key]  # "DefaultValue=": no value
            continue
        try:
            keys[key] = eds_values.canonical(eds_values.parse(keys[key], dtype, node_id))
        except ValueError as exc:
            warnings.append(f"{name}: [{sec}] {key}={keys[key]} ({exc}): ignored")
            del keys[key]
    return warnings


def read_eds(path: str, node_id: int) -> Dictionary:
    """The EDS/DCF at ``path`` for node ``node_id`` ($NODEID resolved)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read()
    except OSError as exc:
        raise UserError(f"cannot read EDS {path}: {exc}") from None
    clean, warnings = _clean(text, str(path), node_id)
    try:
        od = import_eds(io.StringIO(clean), node_id)
    except Exception as exc:  # the parser raises many types on what the cleaner lets through
        raise UserError(f"cannot read EDS {path}: {exc}") from None
    d = Dictionary(source=str(path), warnings=warnings, od=od, from_file=True)
    unset = []
    for obj in od.values():
        members = [obj] if isinstance(obj, ODVariable) else list(obj.values())
        for v in members:
            if not isinstance(v, ODVariable):
                continue
            value = v.value if v.value is not None else v.default
            d.entries[(v.index, v.subindex)] = Entry(
                v.index, v.subindex, v.data_type, v.access_type, bool(v.pdo_mappable),
                v.min, v.max, value if isinstance(value, int) else None,
                from_dcf=v.value is not None, name=v.name)
            if value is None:
                unset.append(where(v.index, v.subindex))
    if unset:
        d.warnings.append(f"{path}: {len(unset)} object(s) listed without a value "
                          f"({eds_values.listing(unset)}): the drive's own values apply; "
                          "a rehearsal (sim-canopen) holds a neutral value there")
    return d


# ------------------------------------------------------------------ the drive
def _attempt(sdo, out: Dictionary, index: int, sub: int):
    """The raw value, or None; a refusal other than "does not exist" or "write-only" is
    recorded in ``out`` with a warning (the object is then taken as absent)."""
    raw, code = sdo.attempt(index, sub)
    if code is not None and code not in ABSENT and code != WRITE_ONLY:
        out.refused[(index, sub)] = code
        name = object_name(index)
        out.warnings.append(f"{where(index, sub)}{f' ({name})' if name else ''}: the drive "
                            f"refused the read ({abort_text(code)}): taken as absent")
    return raw, code


def _pdo_indices(d: Dictionary | None, comm_base: int, sdo, out: Dictionary) -> list[int]:
    """PDO numbers (0-based) whose communication object exists."""
    if d is not None:
        return [n for n in range(MAX_PDOS) if d.has(comm_base + n, 1)]
    found = []
    for n in range(MAX_PDOS):
        if _attempt(sdo, out, comm_base + n, 1)[0] is None:
            break
        found.append(n)
    return found


def _wanted(d: Dictionary | None, sdo, out: Dictionary, extra=()):
    """(index, sub, data type) of everything to read from the drive, device type first,
    then ``extra`` (the rig's vendor objects; PDOs are found as they are read)."""
    yield from ((i, s, t) for i, (_, subs) in STANDARD.items() for s, t in subs.items())
    yield from ((i, s, t) for i, s, t in extra if i not in STANDARD)
    for comm, mapping in ((RPDO_COMM, RPDO_MAP), (TPDO_COMM, TPDO_MAP)):
        for n in _pdo_indices(d, comm, sdo, out):
            yield from ((comm + n, s, t) for s, t in _PDO_COMM_TYPES.items())
            subs = range(MAX_SLOTS + 1) if d is None else d.subs(mapping + n)
            yield from ((mapping + n, s, U8 if s == 0 else U32) for s in subs)


def survey(sdo, d: Dictionary | None = None, extra=()) -> Dictionary:
    """Read-only: what the drive has and holds, as a ``Dictionary`` (a new one).

    With ``d`` (from the drive's file) every object it lists is confirmed on the
    drive; one the drive says does not exist is dropped with a warning. Without,
    mapping slots are probed up to the first missing subindex. No refused read
    stops it (module doc); only a drive that does not answer does. ``extra``:
    (index, sub, data type) of vendor objects the rig names (without a file, the
    rig's type, else the signed type of the answer's size).
    """
    out = Dictionary(source=d.source if d else "drive", warnings=list(d.warnings) if d else [],
                     od=d.od if d else None, from_file=d is not None)
    gone_mapping = set()
    for index, sub, dtype in _wanted(d, sdo, out, extra):
        known = d.get(index, sub) if d is not None else None
        if d is not None and known is None:
            continue
        if index in gone_mapping:
            continue
        if known is not None and not known.readable:
            out.entries[(index, sub)] = replace(known, value=None)
            continue  # write-only: known to exist, never read
        raw, code = _attempt(sdo, out, index, sub)
        if code == WRITE_ONLY:  # the drive says what its file did not
            out.entries[(index, sub)] = replace(known or Entry(index, sub, dtype or I32),
                                                access="wo", value=None)
            continue
        if raw is None:
            if known is not None and code in ABSENT:
                out.warnings.append(f"{d.source} lists 0x{index:04X}:{sub:02X} but the drive "
                                    "says it does not exist: taken as absent")
            if (index & 0xFF00) in (RPDO_MAP, TPDO_MAP) and sub > 0:
                gone_mapping.add(index)  # slots are contiguous: stop at the first gap
            continue
        if known is None and dtype is None:  # a vendor object without a file or a rig type
            dtype = {1: I8, 2: I16}.get(len(raw), I32)
        entry = replace(known) if known is not None else Entry(index, sub, dtype)
        fmt = entry.fmt
        if fmt and len(raw) >= 1:
            size = struct.calcsize(fmt)
            entry.value = struct.unpack(fmt, raw[:size].ljust(size, b"\0"))[0]
        out.entries[(index, sub)] = entry
    return out
