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
from dataclasses import dataclass, field

from labbench.drivers.canopen_config import CanopenConfig
from labbench.drivers.canopen_objects import (STANDARD, TYPE_FMT, Dictionary, object_name,
                                              read_eds)
from labbench.drivers.canopen_pdo import PdoPlan, bus_load, plan_pdos
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
    rated_mnm: float = 0.0
    watchdog: str | None = None  # how the drive watches the host: heartbeat, guarding
    nmt_by: str | None = None  # how the host sees the drive's NMT state
    plan: PdoPlan = field(default_factory=PdoPlan)
    writes: list = field(default_factory=list)  # safety objects: (index, sub, fmt, value)
    max_permille: int = 0
    force_to_permille: float = 0.0
    has: dict = field(default_factory=dict)  # optional object present? by (index, sub)

    def refuse(self) -> None:
        """One ``UserError`` listing every obstacle (nothing if there is none)."""
        if self.obstacles:
            items = "; ".join(f"({k}) {o}" for k, o in enumerate(self.obstacles, 1))
            raise UserError(f"node {self.node_id} ({self.source}): cannot be used, "
                            f"{len(self.obstacles)} obstacle(s): {items}")

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


def _what(index: int, sub: int = 0) -> str:
    return f"{where(index, sub)} ({object_name(index)})"


def _fmt(d: Dictionary, index: int, sub: int) -> str:
    e = d.get(index, sub)
    if e is not None and e.fmt:
        return "<" + e.fmt
    return "<" + TYPE_FMT.get(STANDARD.get(index, ("", {}))[1].get(sub), "I")


def _writable(a: Assessment, d: Dictionary, index: int, sub: int, required: bool) -> bool:
    e = d.get(index, sub)
    if e is None:
        if required:
            a.obstacles.append(f"{_what(index, sub)} {d.gone(index, sub)}")
        return False
    if not e.writable:
        (a.obstacles if required else a.warnings).append(
            f"{_what(index, sub)} is {e.access}" + ("" if required else ": not written"))
        return False
    return True


def _in_range(a: Assessment, d: Dictionary, index: int, sub: int, value: int) -> bool:
    e = d.get(index, sub)
    lo, hi = (e.low, e.high) if e is not None else (None, None)
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        fmt = _fmt(d, index, sub)
        a.obstacles.append(f"{hexval(value, fmt)} for {_what(index, sub)} is outside its range "
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
    if a.modes:
        a.capabilities["torque mode"] = " then ".join(m.text for m in a.modes)
    else:
        shown = f"0x{supported:08X}" if supported is not None else "absent"
        a.capabilities["torque mode"] = "none"
        a.obstacles.append(f"no torque mode: supported drive modes 0x6502 = {shown}; "
                           + "; ".join(why))


def _torque_scale(a: Assessment, d: Dictionary, config: CanopenConfig) -> None:
    drive = d.value(0x6076)
    rig_value = config.rated_torque_mnm
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


def assess(d: Dictionary, config: CanopenConfig, rig) -> Assessment:
    """Everything that stands in the way of ``d`` on ``rig``, and what the driver will do."""
    a = Assessment(config.node_id, d.source, warnings=list(d.warnings))
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
    has_target = _writable(a, d, 0x6071, 0, True)
    a.capabilities["torque object"] = "0x6071 target torque" if has_target else "none"
    _torque_scale(a, d, config)
    _watch(a, d, config)
    # Objects the loop cannot do without, of the size it decodes.
    _writable(a, d, 0x6040, 0, True)
    for index in (0x6041, 0x6064):
        if not d.has(index, 0):
            a.obstacles.append(f"{_what(index)} {d.gone(index)}")
    for index, bits in ((0x6040, 16), (0x6041, 16), (0x6064, 32)):
        e = d.get(index, 0)
        if e is not None and e.bits and e.bits != bits:
            a.obstacles.append(f"{_what(index)} is {e.bits} bit (data type 0x{e.data_type:04X})"
                               f", CiA 402 makes it {bits}")
    # PDOs.
    a.plan = plan_pdos(d, config.node_id, config.rpdo_timeout_ms, config.velocity_tpdo_every)
    a.obstacles += a.plan.obstacles
    a.warnings += a.plan.warnings
    a.capabilities["PDOs"] = (f"{len(a.plan.rpdos)} RPDO(s), {len(a.plan.tpdos)} TPDO(s)")
    if not any(p.event_timer_ms for p in a.plan.rpdos):
        _missing(a, 0x1400, 5, False)
    if any(p.event_timer_ms is None for p in a.plan.tpdos):
        _missing(a, 0x1800, 5, False)
    for index, role in ((0x6077, "torque"), (0x606C, "velocity")):
        if not a.plan.carries(role, tx=True):
            _missing(a, index, 0, False)
    # Optional objects and the safety values written.
    for key in ((0x1018, 2), (0x1018, 3), (0x1018, 4), (0x603F, 0), (0x6061, 0)):
        _missing(a, *key, d.has(*key))
    if a.rated_mnm:
        a.force_to_permille = rig.lever_arm_m / (a.rated_mnm * 1e-3) * 1000.0
        limit = round(rig.force_limit_n * a.force_to_permille)
        a.max_permille = min(32767, max(1, limit))
    mpc = rig.position_per_count  # signed: a flipped position_sign mirrors the window
    lo, hi = sorted(x / mpc for x in rig.position_limits_m)
    wanted = [(0x6072, 0, a.max_permille), (0x607D, 1, math.floor(lo)),
              (0x607D, 2, math.ceil(hi)), (0x605A, 0, config.quick_stop_option),
              (0x605E, 0, config.fault_reaction_option),
              (0x6007, 0, config.abort_connection_option)]
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
    if has_target:
        a.writes.append((0x6071, 0, _fmt(d, 0x6071, 0), 0))
    for index, sub, value in _timing_values(a, config):
        if d.has(index, sub):
            _in_range(a, d, index, sub, value)
    return a


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
