"""The ``[canopen]`` table of a rig file, validated (see docs/canopen.md).

Every field is checked with one ``UserError`` naming it; an unknown one is refused with
the nearest field's name, as ``[rig]`` does. Options of python-can's ``can.Bus`` (``fd``,
``data_bitrate``, ``app_name``, ``serial``, ``receive_own_messages``, ...) go in the
sub-table ``[canopen.bus]`` and pass through unchanged (before, any unknown key of
``[canopen]`` was one, so a misspelt field far from every name, ``zzzzzz = 3``, passed
silently). The torque scale's numbers (``rated_torque_mnm``, ``torque_constant_nm_per_a``,
``rated_current_ma``) lie within ``labbench.scales``' physical ranges (0: not given). When
the rig names no ``interface``/``channel``, python-can's own configuration (``~/.canrc``,
``CAN_INTERFACE``, ``CAN_CHANNEL``) applies. The ``eds`` path is relative to the rig file.

Vendor modes: ``[canopen.modes]`` maps a name to ``{code = -3, bit = 16}``:
the value written to 0x6060 and, if the drive advertises it, its bit in
0x6502; a mode whose set point is not 0x6071 names it, ``command =
"0x2030:00"``, with its unit (``unit = "mA"``: mA, A, mNm, Nm, or permille of
the motor's rated torque, CiA 402's unit and the default) and optionally its
data type (``type = "INTEGER16"``, checked against the drive's dictionary).
``mode = "auto"`` tries CST, then profile torque, then the table in order.
``position`` and ``velocity`` name the objects the drive reports them in
(default 0x6064:00 and 0x606C:00), in encoder counts.
"""
from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from labbench import scales
from labbench.errors import UserError, unknown_name

TABLE = "canopen"
BUS = "bus"  # [canopen.bus]: python-can's own options

# CiA 402 operation modes (0x6060) with a torque set point, and their bits in 0x6502.
MODE_CST, MODE_PT = 10, 4
STANDARD_MODES = {"cst": (MODE_CST, 9, "cyclic synchronous torque"),
                  "pt": (MODE_PT, 3, "profile torque")}
TARGET_TORQUE, POSITION_ACTUAL, VELOCITY_ACTUAL = (0x6071, 0), (0x6064, 0), (0x606C, 0)
# Set point units: joint torque [N m] per unit, "A": per ampere (x the torque constant);
# "permille": of the motor's rated torque (CiA 402's unit of 0x6071), resolved by the check.
UNITS = {"permille": None, "mNm": (1e-3, ""), "Nm": (1.0, ""), "mA": (1e-3, "A"),
         "A": (1.0, "A")}
# CiA 301 integer data type names (the ones a set point or a position can have).
TYPE_NAMES = {"INTEGER8": 0x2, "INTEGER16": 0x3, "INTEGER32": 0x4, "UNSIGNED8": 0x5,
              "UNSIGNED16": 0x6, "UNSIGNED32": 0x7}

# python-can's interfaces with no adapter behind them: a bus inside this computer (or its
# network), on which only programs of this computer answer
SOFTWARE_BUSES = ("virtual", "udp_multicast")


def type_name(code: int) -> str:
    return next((n for n, c in TYPE_NAMES.items() if c == code), f"data type 0x{code:04X}")


_REF = re.compile(r"^0[xX]([0-9a-fA-F]{4})(?::(?:0[xX])?([0-9a-fA-F]{1,2}))?$")


def ref(text: str) -> tuple[int, int]:
    """``"0x2030:00"`` (or ``"0x2030"``, sub-index 0) -> ``(0x2030, 0)``; ValueError if not
    (hex, as an EDS writes them)."""
    m = _REF.match(str(text))
    if m is None:
        raise ValueError(text)
    return int(m.group(1), 16), int(m.group(2) or "0", 16)


def ref_text(r: tuple[int, int]) -> str:
    return f"0x{r[0]:04X}:{r[1]:02X}"


@dataclass(frozen=True)
class Mode:
    """A torque mode: 0x6060 code, its 0x6502 bit (None: not advertised), a name, its set
    point object and unit, and the data type the rig declares for it (None: not declared)."""

    name: str
    code: int
    bit: int | None
    text: str
    command: tuple[int, int] = TARGET_TORQUE
    unit: str = "permille"
    data_type: int | None = None


@dataclass(frozen=True)
class CanopenConfig:
    """The ``[canopen]`` table of a rig file."""

    interface: str = ""  # "": python-can's own configuration
    channel: str = ""
    bitrate: int = 0  # 0: not passed (python-can's configuration or the interface's)
    node_id: int = 1
    eds: str = ""  # the drive's EDS/DCF (relative to the rig file)
    mode: str = "auto"  # "cst", "pt", "auto" or a name of [canopen.modes]
    modes: dict = field(default_factory=dict)  # vendor modes: name -> {code, bit, command...}
    position: str = ref_text(POSITION_ACTUAL)  # object of the position, in counts
    velocity: str = ref_text(VELOCITY_ACTUAL)  # object of the velocity (optional, recorded)
    watchdog: str = "auto"  # how the drive watches the host: heartbeat, guarding or auto
    host_node_id: int = 127  # heartbeat id of this host, watched by the drive (0x1016)
    host_heartbeat_ms: int = 20
    heartbeat_consumer_ms: int = 100
    drive_heartbeat_ms: int = 100  # 0x1017 of the drive
    guard_time_ms: int = 20  # 0x100C: node guarding period (sent by the loop)
    life_time_factor: int = 5  # 0x100D: the drive's life time = guard time x factor
    rpdo_timeout_ms: int = 50  # RPDO event timer 0x1400:05
    quick_stop_option: int = 0  # 0x605A; 0 = disable drive function (no torque)
    fault_reaction_option: int = 0  # 0x605E; 0 = disable drive, motor free
    abort_connection_option: int = 1  # 0x6007; 1 = fault signal
    rated_torque_mnm: float = 0.0  # used when 0x6076 is absent or 0
    torque_constant_nm_per_a: float = 0.0  # or: per-mille of rated current x this constant
    rated_current_ma: float = 0.0  # used with the constant when 0x6075 is absent or 0
    stale_periods: int = 3  # a TPDO later than this many periods is a fault
    sdo_timeout_s: float = 0.5
    lockstep_timeout_s: float = 1.0  # simulated drive: wait for the TPDOs of a SYNC
    enable_timeout_s: float = 0.5  # OPERATION ENABLED must show in a TPDO within this
    velocity_tpdo_every: int = 1  # a TPDO carrying only 0x606C: every n-th SYNC
    sim_drive: str = "thread"  # sim-canopen: the drive in a "thread" or its own "process"
    sim_answer_delay_ms: float = 0.0  # sim-canopen: its TPDOs leave this long after the SYNC
    bus_options: dict = field(default_factory=dict)  # passed on to can.Bus

    _RANGES = {
        "bitrate": (0, 8_000_000), "node_id": (1, 127), "host_node_id": (1, 127),
        "host_heartbeat_ms": (1, 1000), "heartbeat_consumer_ms": (1, 65535),
        "drive_heartbeat_ms": (1, 65535), "guard_time_ms": (1, 65535),
        "life_time_factor": (1, 255), "rpdo_timeout_ms": (1, 65535),
        "quick_stop_option": (-32768, 32767), "fault_reaction_option": (-32768, 32767),
        "abort_connection_option": (0, 3), "stale_periods": (1, 100),
        "velocity_tpdo_every": (1, 240),
    }
    _CHOICES = {"watchdog": ("auto", "heartbeat", "guarding"), "sim_drive": ("thread", "process")}
    _NON_NEGATIVE = ("sim_answer_delay_ms",)

    @classmethod
    def from_section(cls, section: dict, source: str = "rig") -> "CanopenConfig":
        """Validate ``rig.section("canopen")``: one ``UserError`` naming the bad field."""
        known = {f.name: f for f in fields(cls) if f.name != "bus_options"}
        values, bus = {}, {}
        for name, value in section.items():
            where = f"{source}: [canopen] {name}"
            if name == BUS:
                bus = _bus(value, where)
                continue
            if name not in known:
                raise UserError(f"{source}: [canopen] "
                                f"{unknown_name('field', name, [*known, BUS])} (python-can's "
                                f"own bus options go in [canopen.{BUS}])")
            if name == "modes":
                values[name] = _modes(value, where)
                continue
            if name in ("position", "velocity"):
                values[name] = _object(value, where)
                continue
            default = known[name].default
            if isinstance(default, str):
                if not isinstance(value, str):
                    raise UserError(f"{where} must be a string, got {value!r}")
                if name in cls._CHOICES and value not in cls._CHOICES[name]:
                    raise UserError(f"{where} must be one of {', '.join(cls._CHOICES[name])}, "
                                    f"got {value!r}")
            elif (TABLE, name) in scales.SCALES:
                value = scales.check(TABLE, name, value, source)
            elif isinstance(default, float):
                ok = isinstance(value, (int, float)) and not isinstance(value, bool)
                positive = name not in cls._NON_NEGATIVE
                if not ok or not math.isfinite(value) or value < 0 or (positive and value == 0):
                    kind = "a positive number" if positive else "a number >= 0"
                    raise UserError(f"{where} must be {kind}, got {value!r}")
                value = float(value)
            else:
                if not isinstance(value, int) or isinstance(value, bool):
                    raise UserError(f"{where} must be an integer, got {value!r}")
                lo, hi = cls._RANGES[name]
                if not lo <= value <= hi:
                    raise UserError(f"{where} must be in [{lo}, {hi}], got {value}")
            values[name] = value
        if values.get("eds"):
            values["eds"] = str(_beside(source, values["eds"]))
        cfg = cls(**values, bus_options=bus)
        if cfg.mode not in ("auto", *STANDARD_MODES, *cfg.modes):
            raise UserError(f"{source}: [canopen] mode must be auto, cst, pt or a name of "
                            f"[canopen.modes], got {cfg.mode!r}")
        if cfg.host_node_id == cfg.node_id:
            raise UserError(f"{source}: [canopen] host_node_id must differ from node_id")
        if cfg.heartbeat_consumer_ms < 2 * cfg.host_heartbeat_ms:
            raise UserError(f"{source}: [canopen] heartbeat_consumer_ms must be at least "
                            "twice host_heartbeat_ms")
        if cfg.eds and not Path(cfg.eds).is_file():
            raise UserError(f"{source}: [canopen] eds file not found: {cfg.eds}")
        return cfg

    @classmethod
    def from_rig(cls, rig) -> "CanopenConfig":
        """The rig's ``[canopen]`` table validated (``from_section``)."""
        return cls.from_section(rig.section(TABLE), source=rig.source)

    def torque_modes(self) -> list[Mode]:
        """The modes to try, in order (one unless ``mode = "auto"``)."""
        table = [Mode(n, c, b, t) for n, (c, b, t) in STANDARD_MODES.items()] + [
            Mode(n, m["code"], m.get("bit"), f"vendor mode {n} ({m['code']})",
                 ref(m.get("command") or ref_text(TARGET_TORQUE)), m.get("unit") or "permille",
                 TYPE_NAMES.get(m.get("type")))
            for n, m in self.modes.items()]
        return table if self.mode == "auto" else [m for m in table if m.name == self.mode]

    @property
    def position_ref(self) -> tuple[int, int]:
        return ref(self.position)

    @property
    def velocity_ref(self) -> tuple[int, int]:
        return ref(self.velocity)

    def bus_kwargs(self) -> dict:
        """Keyword arguments of ``can.Bus``: only what the rig names."""
        kw = dict(self.bus_options)
        for name in ("interface", "channel", "bitrate"):
            if getattr(self, name):
                kw[name] = getattr(self, name)
        return kw

    def as_dict(self) -> dict:
        return asdict(self)


_MODE_KEYS = ("code", "bit", "command", "unit", "type")


def _bus(table, where: str) -> dict:
    """``[canopen.bus]``: python-can's options, plain values passed on to ``can.Bus``."""
    if not isinstance(table, dict) or not all(
            isinstance(v, (str, int, float, bool)) for v in table.values()):
        raise UserError(f"{where} must be a table of python-can bus options with plain values "
                        "(fd = true, data_bitrate = 2000000, ...)")
    return dict(table)


def _object(value, where: str) -> str:
    """An object reference of the rig, normalised to ``0xIIII:SS``."""
    try:
        return ref_text(ref(value))
    except (ValueError, TypeError):
        raise UserError(f'{where} must name an object as "0xINDEX:SUB" (e.g. "0x2030:00"), '
                        f"got {value!r}") from None


def _modes(table, where: str) -> dict:
    """``[canopen.modes]``, each entry normalised (JSON-able: the drive process gets it)."""
    if not isinstance(table, dict):
        raise UserError(f"{where} must be a table of name = {{code = ..., bit = ...}}")
    out = {}
    for name, entry in table.items():
        at = f"{where}.{name}"
        if name in ("auto", *STANDARD_MODES):
            raise UserError(f"{at}: {name} is a built-in mode name")
        if not isinstance(entry, dict) or set(entry) - set(_MODE_KEYS) or "code" not in entry:
            raise UserError(f'{at} must be {{code = <0x6060 value>, bit = <0x6502 bit>, command '
                            f'= "0xINDEX:SUB", unit = "mA", type = "INTEGER16"}} (code alone '
                            "at least)")
        code, bit = entry["code"], entry.get("bit")
        if not isinstance(code, int) or isinstance(code, bool) or not -128 <= code <= 127:
            raise UserError(f"{at}.code must be an integer in [-128, 127] (0x6060 is INTEGER8)")
        if bit is not None and (not isinstance(bit, int) or isinstance(bit, bool)
                                or not 0 <= bit <= 31):
            raise UserError(f"{at}.bit must be an integer in [0, 31] (a bit of 0x6502)")
        unit = entry.get("unit", "permille")
        if unit not in UNITS:
            raise UserError(f"{at}.unit must be one of {', '.join(UNITS)}, got {unit!r}")
        dtype = entry.get("type")
        if dtype is not None and dtype not in TYPE_NAMES:
            raise UserError(f"{at}.type must be one of {', '.join(TYPE_NAMES)}, got {dtype!r}")
        command = _object(entry.get("command", ref_text(TARGET_TORQUE)), f"{at}.command")
        out[name] = {"code": code, "bit": bit, "command": command, "unit": unit, "type": dtype}
    return out


def _beside(source: str, path: str) -> Path:
    """``path`` relative to the folder of the rig file ``source`` (when it is a file)."""
    p = Path(path).expanduser()
    rig_file = Path(source)
    if not p.is_absolute() and rig_file.is_file():
        return rig_file.resolve().parent / p
    return p
