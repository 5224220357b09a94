"""Can the driver use this drive? Every obstacle at once, capabilities first; the fallbacks.

``assess`` looks at a ``Dictionary`` (a drive's EDS/DCF, what the drive
reported, or both) and the rig, and returns an ``Assessment``: the obstacles
(each a reason the driver cannot run this drive), the warnings (each an
optional object that is missing and what replaces it), the torque mode, the
torque scale, how the drive watches the host and the PDO plan. Nothing is
written to the drive for this. Order of the obstacles: capabilities (is it
CiA 402, has it a torque mode, a torque object and scale, a way to be
watched), then objects, access types, PDO mapping, value limits. Values are
given in hex.

The optional objects and their fallbacks are the table ``OPTIONAL``
(docs/canopen.md shows it).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace

from labbench.drivers.canopen_config import (POSITION_ACTUAL, TARGET_TORQUE, UNITS,
                                             VELOCITY_ACTUAL, CanopenConfig, Mode, ref_text,
                                             type_name)
from labbench.drivers.canopen_objects import STANDARD, TYPE_FMT, Dictionary, read_eds
from labbench.drivers.canopen_pdo import PdoPlan, bus_load, needs, plan_pdos
from labbench.drivers.canopen_sdo import hexval, where
from labbench.errors import UserError

# (index, sub): what the driver uses it for, and what it does without it.
OPTIONAL = {
    (0x1018, 2): ("identity: product code", "reported as absent"),
    (0x1018, 3): ("identity: revision number", "reported as absent"),
    (0x1018, 4): ("identity: serial number", "reported as absent"),
    (0x1400, 5): ("RPDO event timer: the drive's deadline for the next torque",
                  "the heartbeat consumer or life guarding watches the host instead"),
    (0x1800, 5): ("TPDO event timer (set to 0)", "not written: synchronous TPDOs need none"),
    (0x603F, 0): ("error code of a FAULT", "the last EMCY, error register 0x1001 and error "
                  "history 0x1003 explain it; a FAULT is reported as FAULT"),
    (0x605A, 0): ("quick stop option (0: no torque)",
                  "not written: the drive's own quick-stop reaction applies"),
    (0x605E, 0): ("fault reaction option (0: motor free)",
                  "not written: the drive's own fault reaction applies"),
    (0x6007, 0): ("abort connection option (1: fault on a lost host)",
                  "not written: the drive's own reaction to a lost host applies"),
    (0x6072, 0): ("max torque: the drive clamps the torque", "the host clamps it only"),
    (0x607D, 1): ("software position limits: the drive faults outside them",
                  "host-side position window: leaving it while enabled is a fault"),
    (0x6061, 0): ("modes of operation display: confirms the mode",
                  "0x6060 is read back instead"),
    (0x6077, 0): ("torque actual value (recorded on the driver)", "not recorded"),
    (0x606C, 0): ("velocity actual value (recorded on the driver)", "not recorded"),
    (0x1017, 0): ("producer heartbeat: how the host sees the NMT state",
                  "node guarding (0x100C/0x100D) instead"),
    (0x1016, 1): ("heartbeat consumer: the drive watches the host's heartbeat",
                  "life guarding (0x100C/0x100D) instead"),
    (0x6076, 0): ("motor rated torque: the unit of 0x6071/0x6077/0x6072",
                  "the rig's rated_torque_mnm (or torque constant x rated current)"),
}


@dataclass
class Assessment:
    node_id: int
    source: str
    obstacles: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    capabilities: dict = field(default_factory=dict)
    modes: list = field(default_factory=list)  # usable torque modes, in the order to try
    rated_mnm: float = 0.0  # the motor's rated torque (unit of 0x6071/0x6072/0x6077), 0: unknown
    command: tuple = TARGET_TORQUE  # the set point object of the modes (index, sub)
    unit: str = "permille"  # of the set point (canopen_config.UNITS)
    watchdog: str | None = None  # how the drive watches the host: heartbeat, guarding
    nmt_by: str | None = None  # how the host sees the drive's NMT state
    plan: PdoPlan = field(default_factory=PdoPlan)
    writes: list = field(default_factory=list)  # safety objects: (index, sub, fmt, value)
    max_permille: int = 0  # 0x6072 written (per-mille of the rated torque; 0: not written)
    force_to_command: float = 0.0  # set point units per newton at the handle
    max_command: int = 0  # the host's clamp, in set point units
    has: dict = field(default_factory=dict)  # optional object present? by (index, sub)
    rig_lines: list = field(default_factory=list)  # TOML lines that would make it usable
    lever_m: float = 0.1  # the rig's lever arm (handle force = joint torque / lever)

    def refuse(self) -> None:
        """One ``UserError`` listing every obstacle (nothing if there is none), and the rig
        lines that would make the drive usable when there are such lines."""
        if self.obstacles:
            items = "; ".join(f"({k}) {o}" for k, o in enumerate(self.obstacles, 1))
            hint = (f"; rig lines that would make it usable: {one_line(self.rig_lines)}"
                    if self.rig_lines else "")
            raise UserError(f"node {self.node_id} ({self.source}): cannot be used, "
                            f"{len(self.obstacles)} obstacle(s): {items}{hint}")

    @property
    def torque_per_permille_n(self) -> float:
        """Newtons at the handle per per-mille of the rated torque (0x6077), 0 if unknown."""
        return self.rated_mnm * 1e-6 / self.lever_m if self.rated_mnm else 0.0

    def traffic(self, config: CanopenConfig, sample_time_s: float) -> list:
        out = self.plan.traffic(sample_time_s)
        if self.watchdog == "heartbeat":
            out.append(("host heartbeat", 1, 1000.0 / config.host_heartbeat_ms))
        if self.watchdog == "guarding" or self.nmt_by == "guarding":
            rate = 1000.0 / config.guard_time_ms
            out += [("guarding request (remote)", 0, rate), ("guarding answer", 1, rate)]
        if self.nmt_by == "heartbeat":
            out.append(("drive heartbeat", 1, 1000.0 / config.drive_heartbeat_ms))
        return out

    def bus_load(self, config: CanopenConfig, sample_time_s: float,
                 bitrate: int = 1_000_000) -> dict:
        return bus_load(self.traffic(config, sample_time_s), bitrate)


def _missing(a: Assessment, index: int, sub: int, present: bool) -> bool:
    """Record whether an optional object is there; warn (once) with its fallback if not."""
    seen = (index, sub) in a.has and not a.has[(index, sub)]
    a.has[(index, sub)] = present and not seen
    if not present and not seen and (index, sub) in OPTIONAL:
        used, instead = OPTIONAL[(index, sub)]
        a.warnings.append(f"0x{index:04X}:{sub:02X} absent ({used}): {instead}")
    return not present


def _what(index: int, sub: int = 0, d: Dictionary | None = None) -> str:
    name = d.name(index, sub) if d is not None else Dictionary().name(index, sub)
    return f"{where(index, sub)} ({name or 'vendor object'})"


def one_line(lines: list[str]) -> str:
    """TOML lines (each table's header first) in one line: '[t] a = 1, b = 2; [u] c = 3'."""
    tables: list[list[str]] = []
    for line in lines:
        if line.startswith("["):
            tables.append([line])
        else:
            tables[-1].append(line)
    return "; ".join(f"{t[0]} {', '.join(t[1:])}" for t in tables)


def _fmt(d: Dictionary, index: int, sub: int) -> str:
    e = d.get(index, sub)
    if e is not None and e.fmt:
        return "<" + e.fmt
    return "<" + TYPE_FMT.get(STANDARD.get(index, ("", {}))[1].get(sub), "I")


def _writable(a: Assessment, d: Dictionary, index: int, sub: int, required: bool) -> bool:
    e = d.get(index, sub)
    if e is None:
        if required:
            a.obstacles.append(f"{_what(index, sub, d)} {d.gone(index, sub)}")
        return False
    if not e.writable:
        (a.obstacles if required else a.warnings).append(
            f"{_what(index, sub, d)} is {e.access}" + ("" if required else ": not written"))
        return False
    return True


def _in_range(a: Assessment, d: Dictionary, index: int, sub: int, value: int) -> bool:
    e = d.get(index, sub)
    lo, hi = (e.low, e.high) if e is not None else (None, None)
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        fmt = _fmt(d, index, sub)
        a.obstacles.append(f"{hexval(value, fmt)} for {_what(index, sub, d)} is outside its range "
                           f"[{hexval(lo, fmt) if lo is not None else '-'}, "
                           f"{hexval(hi, fmt) if hi is not None else '-'}]")
        return False
    return True


def _modes(a: Assessment, d: Dictionary, config: CanopenConfig) -> None:
    if not _writable(a, d, 0x6060, 0, True):
        a.capabilities["torque mode"] = "none (0x6060 cannot be written)"
        return
    supported = d.value(0x6502)
    e6060 = d.get(0x6060)
    if not e6060.readable and not d.has(0x6061, 0):
        a.warnings.append("0x6060:00 (modes of operation) is write-only and 0x6061 (modes of "
                          "operation display) absent: the drive's acknowledgment of the mode "
                          "write is its only confirmation")
    lo = e6060.low if e6060.low is not None else -128
    hi = e6060.high if e6060.high is not None else 127
    why = []
    for m in config.torque_modes():
        if not lo <= m.code <= hi:
            why.append(f"{m.text}: code {m.code} outside the range of 0x6060 [{lo}, {hi}]")
        elif supported is not None and m.bit is not None and not supported >> m.bit & 1:
            why.append(f"{m.text}: bit {m.bit} of 0x6502 is not set")
        else:
            a.modes.append(m)
    if supported is None:
        state = "listed without a value" if d.has(0x6502, 0) else "absent"
        _missing(a, 0x6502, 0, False)
        a.warnings.append(f"0x6502:00 {state} (supported drive modes): the modes are tried in "
                          "order and confirmed by the drive")
    # The modes whose set point the dictionary has first; then only those sharing the
    # first one's set point (one object is mapped).
    a.modes.sort(key=lambda m: not d.has(*m.command))
    a.modes = [m for m in a.modes if m.command == a.modes[0].command]
    if a.modes:
        a.capabilities["torque mode"] = " then ".join(m.text for m in a.modes)
    else:
        shown = f"0x{supported:08X}" if supported is not None else "absent"
        a.capabilities["torque mode"] = "none"
        a.obstacles.append(f"no torque mode: supported drive modes 0x6502 = {shown}; "
                           + "; ".join(why))


def _rig_key(config: CanopenConfig, m: Mode | None, role: str) -> str:
    """The rig line that named a vendor object ("" for CiA 402's own object)."""
    if role == "command":
        return "" if m is None or m.command == TARGET_TORQUE else \
            f'[canopen.modes.{m.name}] command = "{ref_text(m.command)}"'
    value = getattr(config, role)
    default = ref_text(POSITION_ACTUAL if role == "position" else VELOCITY_ACTUAL)
    return "" if value == default else f'[canopen] {role} = "{value}"'


def _command(a: Assessment, d: Dictionary, config: CanopenConfig) -> bool:
    """The set point object of the modes: there, writable, a signed integer of the rig's
    declared type. A rig line that the dictionary contradicts is named beside it."""
    m = a.modes[0] if a.modes else (config.torque_modes() or [None])[0]
    a.command = m.command if m is not None else TARGET_TORQUE
    a.unit = m.unit if m is not None else "permille"
    index, sub = a.command
    key = _rig_key(config, m, "command")
    said = f"the rig's {key} but in {d.source} " if key else ""
    before = len(a.obstacles)
    e = d.get(index, sub)
    if e is None or not e.writable:
        if key:
            a.obstacles.append(f"{said}{_what(index, sub, d)} is "
                               + (d.gone(index, sub) if e is None else e.access))
        else:
            _writable(a, d, index, sub, True)
    elif m is not None and m.data_type is not None and e.data_type != m.data_type:
        a.obstacles.append(f"{said}{_what(index, sub, d)} is {type_name(e.data_type)}, not "
                           f"the rig's type = {type_name(m.data_type)}")
    elif e.fmt not in ("b", "h", "i"):
        a.obstacles.append(f"{_what(index, sub, d)} is {type_name(e.data_type)}: a set point "
                           "must be a signed integer of 8, 16 or 32 bit")
    ok = len(a.obstacles) == before
    shown = f"{ref_text(a.command)} {d.name(index, sub) or 'vendor object'}"
    unit = "per-mille of the rated torque" if a.unit == "permille" else a.unit
    a.capabilities["torque object"] = f"{shown} ({unit})" if ok else "none"
    return ok


def _scale(a: Assessment, d: Dictionary, config: CanopenConfig) -> float:
    """Joint torque [N m] per unit of the set point (0: no scale, an obstacle): per-mille of
    the rated torque (``_torque_scale``), or the rig's unit (x the torque constant for a
    current)."""
    if a.unit == "permille":
        _torque_scale(a, d, config, required=True)
        return a.rated_mnm * 1e-6
    _torque_scale(a, d, config, required=False)  # 0x6072 and 0x6077 use it when known
    factor, per = UNITS[a.unit]
    kt = config.torque_constant_nm_per_a
    if per == "A" and not kt:
        a.capabilities["torque scale"] = "none"
        a.obstacles.append(f"no torque scale: the set point {ref_text(a.command)} is a current "
                           f"in {a.unit}; set [canopen] torque_constant_nm_per_a (the motor's)")
        return 0.0
    a.capabilities["torque scale"] = (f"{ref_text(a.command)} in {a.unit}" + (
        f" x torque constant {kt:g} N m/A" if per == "A" else ""))
    return factor * (kt if per == "A" else 1.0)


def _torque_scale(a: Assessment, d: Dictionary, config: CanopenConfig,
                  required: bool = True) -> None:
    """The rated torque (``a.rated_mnm``): 0x6076, else the rig's; without it an obstacle
    (``required``: the set point is per-mille of it) or nothing."""
    drive = d.value(0x6076)
    rig_value = config.rated_torque_mnm
    if not required:
        current = d.value(0x6075) or config.rated_current_ma
        a.rated_mnm = float(drive or rig_value or config.torque_constant_nm_per_a * current)
        a.has[(0x6076, 0)] = bool(drive)
        return
    if drive:
        a.rated_mnm, a.has[(0x6076, 0)] = float(drive), True
        a.capabilities["torque scale"] = f"0x6076 motor rated torque = {drive} mN m (drive)"
        if rig_value and not math.isclose(rig_value, drive):
            a.warnings.append(f"the rig's rated_torque_mnm {rig_value:g} is not used: the "
                              f"drive's 0x6076 = {drive} mN m applies")
        return
    state = "is 0" if d.has(0x6076, 0) else "absent"
    current = d.value(0x6075) or config.rated_current_ma
    if rig_value:
        a.rated_mnm, how = rig_value, f"the rig's rated_torque_mnm = {rig_value:g} mN m"
    elif config.torque_constant_nm_per_a and current:
        a.rated_mnm = config.torque_constant_nm_per_a * current  # N m/A x mA = mN m
        src = "0x6075" if d.value(0x6075) else "the rig's rated_current_ma"
        how = (f"torque constant {config.torque_constant_nm_per_a:g} N m/A x rated current "
               f"{current:g} mA ({src}) = {a.rated_mnm:g} mN m")
    else:
        a.capabilities["torque scale"] = "none"
        a.obstacles.append(f"no torque scale: motor rated torque 0x6076 {state}; set [canopen] "
                           "rated_torque_mnm (or torque_constant_nm_per_a, with 0x6075 or "
                           "rated_current_ma)")
        return
    a.has[(0x6076, 0)] = False
    a.capabilities["torque scale"] = how
    a.warnings.append(f"0x6076:00 {state} (motor rated torque): per-mille torque of {how}")


def _force_limit_fits(a: Assessment, rig, top: int) -> None:
    """The host clamps a command at the rig's force limit before converting it: that clamp
    holds only when the limit is at least one unit of the set point (else the smallest
    nonzero command is beyond it) and within the set point's range (else a wrong scale
    saturates it: every force the drive's largest value, whatever the motor truly makes).
    Either is an obstacle naming the numbers the scale is made of (labbench.scales)."""
    units = rig.force_limit_n * a.force_to_command
    if 1 - 1e-9 <= units <= top * (1 + 1e-9):  # (rounding of the scale's product)
        return
    per_unit = 1 / a.force_to_command  # N at the handle
    made_of = ("[rig] lever_arm_m and " + (
        "the motor's rated torque (0x6076, or [canopen] rated_torque_mnm, or "
        "torque_constant_nm_per_a x rated current)" if a.unit == "permille" else
        "[canopen] torque_constant_nm_per_a" if UNITS[a.unit][1] == "A" else
        f"the unit {a.unit}"))
    shown = f"{ref_text(a.command)} ({'per-mille' if a.unit == 'permille' else a.unit})"
    if units < 1:
        a.obstacles.append(f"one unit of {shown} is {per_unit:.3g} N at the handle, above "
                           f"[rig] force_limit_n = {rig.force_limit_n:g} N: the host could not "
                           f"clamp a command; check {made_of}")
    else:
        a.obstacles.append(f"[rig] force_limit_n = {rig.force_limit_n:g} N is {units:.3g} units "
                           f"of {shown}, beyond its largest value {top} ({top * per_unit:.3g} N "
                           f"at the handle): a command would saturate the drive; check "
                           f"{made_of}, or lower force_limit_n to {top * per_unit:.3g} N")


def _watch(a: Assessment, d: Dictionary, config: CanopenConfig) -> None:
    hb = d.has(0x1016, 1) and d.get(0x1016, 1).writable
    guard = all(d.has(i, 0) and d.get(i, 0).writable for i in (0x100C, 0x100D))
    want = config.watchdog
    a.watchdog = ("heartbeat" if hb and want in ("auto", "heartbeat") else
                  "guarding" if guard and want in ("auto", "guarding") else None)
    producer = d.has(0x1017, 0) and d.get(0x1017, 0).writable
    a.nmt_by = ("heartbeat" if producer and a.watchdog != "guarding" else
                "guarding" if guard else None)
    life = config.guard_time_ms * config.life_time_factor
    if a.watchdog is None:
        a.capabilities["watched by"] = "nothing"
        a.obstacles.append(
            "no way to be watched: " + ("no writable heartbeat consumer 0x1016:01 and no node "
                                        "guarding 0x100C/0x100D" if want == "auto" else
                                        f"watchdog = {want} but the drive has no "
                                        + ("heartbeat consumer 0x1016:01" if want == "heartbeat"
                                           else "node guarding 0x100C/0x100D"))
            + " (a frozen loop would leave the torque on)")
    elif a.watchdog == "heartbeat":
        a.capabilities["watched by"] = (f"heartbeat consumer 0x1016 ({config.heartbeat_consumer_ms}"
                                        f" ms on the host's {config.host_heartbeat_ms} ms)")
    else:
        a.capabilities["watched by"] = (f"life guarding 0x100C/0x100D (guard time "
                                        f"{config.guard_time_ms} ms from the loop, life time "
                                        f"{life} ms)")
        if not hb:
            _missing(a, 0x1016, 1, False)
    if a.nmt_by is None:
        a.obstacles.append("no way to see the NMT state: no writable producer heartbeat 0x1017 "
                           "and no node guarding 0x100C/0x100D")
    elif a.nmt_by == "guarding" and not producer:
        _missing(a, 0x1017, 0, False)
    a.capabilities["NMT state from"] = a.nmt_by or "nothing"


def assess(d: Dictionary, config: CanopenConfig, rig, file: Dictionary | None = None
           ) -> Assessment:
    """Everything that stands in the way of ``d`` on ``rig``, and what the driver will do;
    for a refused drive, the rig lines that would make it usable (``suggest``; ``file``:
    the drive's EDS/DCF, whose vendor objects a survey of the drive does not read)."""
    a = _assess(d, config, rig)
    if a.obstacles:
        if file is not None:
            vendor = {k: e for k, e in file.entries.items()
                      if 0x2000 <= k[0] < 0x6000 and k not in d.entries}
            d = replace(d, entries={**d.entries, **vendor})
        a.rig_lines = suggest(d, config, rig, a)
    return a


def _assess(d: Dictionary, config: CanopenConfig, rig) -> Assessment:
    a = Assessment(config.node_id, d.source, warnings=list(d.warnings), lever_m=rig.lever_arm_m)
    # Capabilities.
    device_type = d.value(0x1000)
    if device_type is None and d.has(0x1000, 0):
        a.capabilities["CiA 402"] = "unknown (listed without a value)"
        a.warnings.append("0x1000:00 (device type) listed without a value: whether it is a "
                          "CiA 402 drive is the drive's answer")
    elif device_type is None:
        a.capabilities["CiA 402"] = "unknown"
        a.obstacles.append(f"device type 0x1000 {d.gone(0x1000)}: not known to be a CiA 402 "
                           "drive")
    elif device_type & 0xFFFF != 402:
        a.capabilities["CiA 402"] = f"no (profile {device_type & 0xFFFF})"
        a.obstacles.append(f"not a CiA 402 drive: device type 0x1000 = 0x{device_type:08X} "
                           f"(profile {device_type & 0xFFFF})")
    else:
        a.capabilities["CiA 402"] = f"yes (device type 0x{device_type:08X})"
    _modes(a, d, config)
    has_command = _command(a, d, config)
    nm_per_unit = _scale(a, d, config)
    _watch(a, d, config)
    # Objects the loop cannot do without, of the size it decodes.
    _writable(a, d, 0x6040, 0, True)
    position = config.position_ref
    for index, sub in ((0x6041, 0), position):
        if not d.has(index, sub):
            key = _rig_key(config, None, "position") if (index, sub) == position else ""
            said = f"the rig's {key} but in {d.source} " if key else ""
            a.obstacles.append(f"{said}{_what(index, sub, d)} {d.gone(index, sub)}")
    for (index, sub), bits in (((0x6040, 0), 16), ((0x6041, 0), 16), (position, 32)):
        e = d.get(index, sub)
        if e is not None and e.bits and e.bits != bits:
            a.obstacles.append(f"{_what(index, sub, d)} is {e.bits} bit (data type "
                               f"0x{e.data_type:04X}), CiA 402 makes it {bits}")
    velocity = config.velocity_ref
    if velocity != VELOCITY_ACTUAL and not d.has(*velocity):
        a.obstacles.append(f"the rig's {_rig_key(config, None, 'velocity')} but in {d.source} "
                           f"{_what(*velocity, d)} {d.gone(*velocity)}")
    # PDOs.
    a.plan = plan_pdos(d, config.node_id, config.rpdo_timeout_ms, config.velocity_tpdo_every,
                       needs(a.command, position, velocity, torque_actual=bool(a.rated_mnm)))
    for text in a.plan.obstacles:  # name the rig line beside a vendor object it refuses
        for ref, key in ((a.command, _rig_key(config, a.modes[0] if a.modes else None,
                                              "command")),
                         (position, _rig_key(config, None, "position"))):
            if key and text.startswith(f"0x{ref[0]:04X}" + (f":{ref[1]:02X}" if ref[1] else "")
                                       + " "):
                text = f"the rig's {key} but in {d.source} {text}"
        a.obstacles.append(text)
    a.warnings += a.plan.warnings
    a.capabilities["PDOs"] = (f"{len(a.plan.rpdos)} RPDO(s), {len(a.plan.tpdos)} TPDO(s)")
    if not any(p.event_timer_ms for p in a.plan.rpdos):
        _missing(a, 0x1400, 5, False)
    if any(p.event_timer_ms is None for p in a.plan.tpdos):
        _missing(a, 0x1800, 5, False)
    if not a.plan.carries("torque", tx=True):
        if d.has(0x6077, 0) and not a.rated_mnm:
            a.warnings.append("0x6077:00 (torque actual value) not recorded: its unit, the "
                              "motor's rated torque, is not known")
        else:
            _missing(a, 0x6077, 0, False)
    if not a.plan.carries("velocity", tx=True):
        _missing(a, *velocity, False)
    # Optional objects and the safety values written.
    for key in ((0x1018, 2), (0x1018, 3), (0x1018, 4), (0x603F, 0), (0x6061, 0)):
        _missing(a, *key, d.has(*key))
    if nm_per_unit:
        a.force_to_command = rig.lever_arm_m / nm_per_unit
        e = d.get(*a.command)
        top = (1 << (e.bits - 1)) - 1 if e is not None and e.bits else 32767
        _force_limit_fits(a, rig, top)
        a.max_command = min(top, max(1, round(rig.force_limit_n * a.force_to_command)))
    if a.rated_mnm:
        limit = round(rig.force_limit_n * rig.lever_arm_m / (a.rated_mnm * 1e-6))
        a.max_permille = min(32767, max(1, limit))
    elif d.has(0x6072, 0):
        a.warnings.append("0x6072:00 (max torque) not written: its unit, the motor's rated "
                          "torque, is not known; the host clamps the set point")
    mpc = rig.position_per_count  # signed: a flipped position_sign mirrors the window
    lo, hi = sorted(x / mpc for x in rig.position_limits_m)
    wanted = [(0x607D, 1, math.floor(lo)), (0x607D, 2, math.ceil(hi)),
              (0x605A, 0, config.quick_stop_option), (0x605E, 0, config.fault_reaction_option),
              (0x6007, 0, config.abort_connection_option)]
    if a.max_permille or not d.has(0x6072, 0):
        wanted.insert(0, (0x6072, 0, a.max_permille))
    for index, sub, value in wanted:
        if _missing(a, index, 1 if index == 0x607D else sub, d.has(index, sub)):
            continue
        if not _writable(a, d, index, sub, False):
            a.has[(index, 1 if index == 0x607D else sub)] = False
            continue
        e = d.get(index, sub)
        if index == 0x6072 and e.high is not None and value > e.high:
            a.warnings.append(f"{_what(index)}: the rig's limit {hexval(value, 'H')} is above "
                              f"the drive's maximum {hexval(e.high, 'H')}: the maximum is used")
            value = e.high
        if _in_range(a, d, index, sub, value):
            a.writes.append((index, sub, _fmt(d, index, sub), value))
    if has_command:
        a.writes.append((*a.command, _fmt(d, *a.command), 0))
    for index, sub, value in _timing_values(a, config):
        if d.has(index, sub):
            _in_range(a, d, index, sub, value)
    return a


# Names of vendor objects that may be a torque or current set point, or a position (a
# hint only: the rig lines it leads to are checked like any others).
_SET_POINT = re.compile(r"current|torque", re.IGNORECASE)
_POSITION = re.compile(r"position", re.IGNORECASE)
_NOT_SET_POINT = re.compile(r"actual|limit|max|min|offset|gain|constant|rated|peak|contin|"
                            r"filter|slope|window|display|average|demand|time", re.IGNORECASE)
_NOT_POSITION = re.compile(r"limit|target|demand|window|offset|set|follow|home|factor|range",
                           re.IGNORECASE)
PLACEHOLDER_RE = re.compile(r"<[^>]*>")  # what the person fills in (values the file lacks)


def _candidates(d: Dictionary, standard: tuple, want, avoid, writable: bool) -> list:
    """CiA 402's object when mappable, then vendor objects (0x2000-0x5FFF) named so."""
    out = []
    e = d.get(*standard)
    if e is not None and e.mappable is not False and (e.writable or not writable):
        out.append((standard, e))
    for key, e in sorted(d.entries.items()):
        if (0x2000 <= key[0] < 0x6000 and e.mappable and (e.writable if writable else
                                                            e.readable)
                and want.search(e.name) and not avoid.search(e.name)):
            out.append((key, e))
    return out


def suggest(d: Dictionary, config: CanopenConfig, rig, a: Assessment) -> list[str]:
    """TOML lines of ``[canopen]`` that would make the refused drive ``d`` usable, or [].

    Tried in order: the rig's own set point and position, then each mappable torque or
    current set point of the dictionary with each mappable position (CiA 402's object,
    then vendor objects whose names say so), each with a torque scale when one is
    missing; the first whose assessment has no obstacle is the answer. What the file
    cannot tell (the vendor mode's 0x6060 value, the unit, the motor's constants) is a
    ``<placeholder>`` to fill in from the drive's and the motor's manuals.
    """
    e6060 = d.get(0x6060, 0)
    lo = e6060.low if e6060 is not None and e6060.low is not None else -128
    hi = e6060.high if e6060 is not None and e6060.high is not None else 127
    name = next(n for n in ("vendor", "vendor2", "vendor3") if n not in config.modes)
    commands = [None] + [c for c in _candidates(d, TARGET_TORQUE, _SET_POINT, _NOT_SET_POINT,
                                                 True) if c[1].fmt in ("b", "h", "i")]
    positions = [None] + [p for p in _candidates(d, POSITION_ACTUAL, _POSITION, _NOT_POSITION,
                                                  False) if p[1].bits == 32]
    for command in commands:
        for position in positions:
            changes, canopen, modes = {}, [], []
            if command is not None:
                (index, sub), e = command
                current = _SET_POINT.search(e.name) and "current" in e.name.lower()
                unit = "permille" if (index, sub) == TARGET_TORQUE else "mA" if current else "mNm"
                changes.update(mode=name, modes={**config.modes, name: {
                    "code": max(lo, min(hi, -3)), "bit": None, "command": ref_text((index, sub)),
                    "unit": unit, "type": type_name(e.data_type)}})
                canopen.append(f'mode = "{name}"')
                what = (f"the 0x6060 value that makes {ref_text((index, sub))} the set point "
                        "(its manual; CiA 402: 10 or 4)" if unit == "permille" else
                        f"the 0x6060 value of the mode whose set point is "
                        f"{ref_text((index, sub))} (its manual)")
                fields = [f"code = <{what}>"]
                if unit != "permille":
                    units = '"mA" or "A"' if unit == "mA" else '"mNm", "Nm" or "permille"'
                    fields += [f'command = "{ref_text((index, sub))}"',
                               f'type = "{type_name(e.data_type)}"', f"unit = <{units}>"]
                modes.append(f"{name} = {{{', '.join(fields)}}}")
            if position is not None and position[0] != config.position_ref:
                changes["position"] = ref_text(position[0])
                canopen.append(f'position = "{ref_text(position[0])}"')
            trial = replace(config, **changes)
            t = _assess(d, trial, rig)
            if any(o.startswith("no torque scale") for o in t.obstacles):
                if UNITS[t.unit] is not None and UNITS[t.unit][1] == "A":
                    trial = replace(trial, torque_constant_nm_per_a=1.0)
                    canopen.append("torque_constant_nm_per_a = <the motor's torque constant, "
                                   "N m/A>")
                else:
                    trial = replace(trial, rated_torque_mnm=100.0)
                    canopen.append("rated_torque_mnm = <the motor's rated torque, mN m>")
                t = _assess(d, trial, rig)
            if not t.obstacles and (canopen or modes):
                return (["[canopen]", *canopen] if canopen else []) + (
                    ["[canopen.modes]", *modes] if modes else [])
    return []


def _timing_values(a: Assessment, config: CanopenConfig) -> list[tuple[int, int, int]]:
    out = []
    if a.nmt_by == "heartbeat":
        out.append((0x1017, 0, config.drive_heartbeat_ms))
    if a.watchdog == "heartbeat":
        out.append((0x1016, 1, config.host_node_id << 16 | config.heartbeat_consumer_ms))
    if "guarding" in (a.watchdog, a.nmt_by):
        out += [(0x100C, 0, config.guard_time_ms), (0x100D, 0, config.life_time_factor)]
    for p in a.plan.rpdos:
        if p.event_timer_ms:
            out.append((p.comm, 5, p.event_timer_ms))
    return out


def check_eds(path: str, config: CanopenConfig | None = None, rig=None) -> Assessment:
    """Can the driver use the drive this EDS/DCF describes? ``UserError`` listing every obstacle.

    The file's values (ParameterValue, else DefaultValue) stand in for what the
    drive would report. Returns the assessment (warnings, plan) when usable.
    """
    from labbench.rig import Rig

    config = config or CanopenConfig()
    a = assess(read_eds(path, config.node_id), config, rig or Rig())
    a.refuse()
    return a
