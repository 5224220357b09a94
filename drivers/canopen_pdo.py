"""PDO layout planned from the drive's dictionary, before anything is written; bus load.

What the loop needs each period: to the drive, target torque 0x6071 and the
controlword 0x6040 (RPDOs, applied on arrival); from the drive at each SYNC,
position 0x6064 and statusword 0x6041, and if there is room torque actual
0x6077 and velocity actual 0x606C (TPDOs). The planner:

1. uses a PDO whose mapping the drive fixes (read-only) or a DCF sets, as it
   is, when it carries something needed (an RPDO only if it carries nothing
   but what the driver sends and dummy entries);
2. puts what is left, in that order, first-fit into the configurable PDOs,
   within each one's mapping slots and 64 bits, so that one-slot PDOs split
   the entries over several PDOs;
3. refuses (an obstacle naming the object, not the slot) what is not mappable
   or finds no room; optional entries that find none are left out, with a
   warning.

PDO numbering, default COB-IDs and the mapping entry layout (index << 16 |
subindex << 8 | bits): CiA 301.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field

from labbench.drivers.canopen_objects import (RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP, MAX_PDOS,
                                              Dictionary, object_name)

SYNC_ID = 0x080


@dataclass(frozen=True)
class Need:
    index: int
    role: str
    required: bool
    sub: int = 0


def needs(command=(0x6071, 0), position=(0x6064, 0), velocity=(0x606C, 0),
          torque_actual: bool = True) -> tuple[tuple, tuple]:
    """(RPDO, TPDO) entries the loop needs, in the order they are placed: the set point
    (0x6071 or the rig's vendor object), the controlword; the position (0x6064 or the
    rig's), the statusword, then if there is room torque actual and the velocity."""
    rx = (Need(command[0], "torque", True, command[1]), Need(0x6040, "control", True))
    tx = (Need(position[0], "position", True, position[1]), Need(0x6041, "status", True),
          *((Need(0x6077, "torque", False),) if torque_actual else ()),
          Need(velocity[0], "velocity", False, velocity[1]))
    return rx, tx


@dataclass
class Mapped:
    index: int
    sub: int
    bits: int
    role: str | None  # None: carried but unused (or a dummy entry)
    signed: bool = False
    name: str = ""  # what the object is (the dictionary's name)

    @property
    def code(self) -> int:
        return self.index << 16 | self.sub << 8 | self.bits

    @property
    def fmt(self) -> str:
        if self.role is None:
            return f"{self.bits // 8}x"
        return {8: "b", 16: "h", 32: "i"}[self.bits] if self.signed else \
            {8: "B", 16: "H", 32: "I"}[self.bits]

    def text(self) -> str:
        if 1 <= self.index <= 7:
            return f"dummy ({self.bits} bit)"
        name = self.name or object_name(self.index)
        at = f"0x{self.index:04X}" + (f":{self.sub:02X}" if self.sub else "")
        return f"{at} {name} ({self.bits} bit)" + ("" if self.role else ", unused")


@dataclass
class PlannedPdo:
    tx: bool
    number: int  # 1-based
    cob_id: int
    slots: int
    entries: list = field(default_factory=list)
    origin: str = "planned"  # "fixed" (the drive's, read-only), "dcf", "planned"
    cob_fixed: bool = False  # the COB-ID cannot be written (the PDO stays as the drive has it)
    trans_type: int = 255
    write_trans: bool = True
    event_timer_ms: int | None = None  # written to :05 when not None

    @property
    def comm(self) -> int:
        return (TPDO_COMM if self.tx else RPDO_COMM) + self.number - 1

    @property
    def mapping(self) -> int:
        return (TPDO_MAP if self.tx else RPDO_MAP) + self.number - 1

    @property
    def name(self) -> str:
        return f"{'T' if self.tx else 'R'}PDO{self.number}"

    @property
    def bits(self) -> int:
        return sum(e.bits for e in self.entries)

    @property
    def n_bytes(self) -> int:
        return (self.bits + 7) // 8

    @property
    def write_mapping(self) -> bool:
        return self.origin != "fixed"

    @property
    def synchronous(self) -> bool:
        """An RPDO of types 0-240: its data take effect at the next SYNC (CiA 301 7.2.2)."""
        return not self.tx and self.trans_type <= 240

    def struct(self) -> struct.Struct:
        return struct.Struct("<" + "".join(e.fmt for e in self.entries))

    def roles(self) -> list[str]:
        return [e.role for e in self.entries if e.role]

    def line(self) -> str:
        when = (f"every {self.trans_type} SYNC" if 1 <= self.trans_type <= 240 and self.tx
                else "on arrival" if self.trans_type >= 254 else f"type {self.trans_type}")
        timer = f", event timer {self.event_timer_ms} ms" if self.event_timer_ms else ""
        return (f"{self.name} COB-ID 0x{self.cob_id:03X} ({self.origin}, {self.slots} slot(s)) "
                f"{when}{timer}: " + ", ".join(e.text() for e in self.entries))


@dataclass
class PdoPlan:
    rpdos: list = field(default_factory=list)
    tpdos: list = field(default_factory=list)
    disable: list = field(default_factory=list)  # (comm index, COB-ID) of TPDOs switched off
    obstacles: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    def carries(self, role: str, tx: bool) -> bool:
        return any(role in p.roles() for p in (self.tpdos if tx else self.rpdos))

    def torque_at_sync(self) -> PlannedPdo | None:
        """The synchronous RPDO that carries the torque (the drive applies it one period
        after the host sends it), or None."""
        return next((p for p in self.rpdos if p.synchronous and "torque" in p.roles()), None)

    def lines(self) -> list[str]:
        return [p.line() for p in self.rpdos + self.tpdos]

    def traffic(self, sample_time_s: float) -> list[tuple[str, int, float]]:
        """(frame, data bytes, frames per second) of SYNC and the PDOs."""
        rate = 1.0 / sample_time_s
        out = [("SYNC", 0, rate)]
        for p in self.tpdos:
            out.append((p.name, p.n_bytes, rate / p.trans_type))
        out += [(p.name, p.n_bytes, rate) for p in self.rpdos]
        return out


def _default_cob(tx: bool, n: int, node_id: int) -> int:
    """Predefined connection set: PDOs 1-4 only (CiA 301)."""
    return ((0x180 if tx else 0x200) + 0x100 * n + node_id) if n < 4 else 0


@dataclass
class _Pdo:
    n: int  # 0-based
    cob_id: int  # 11-bit id to use (0: none available)
    cob_fixed: bool
    valid: bool  # bit 31 clear now
    slots: int
    fixed: bool
    dcf: bool
    current: list
    trans: object  # Entry of :02 or None
    timer: object  # Entry of :05 or None


def _available(d: Dictionary, tx: bool, node_id: int) -> list[_Pdo]:
    comm_base, map_base = (TPDO_COMM, TPDO_MAP) if tx else (RPDO_COMM, RPDO_MAP)
    out = []
    for n in range(MAX_PDOS):
        cob, count = d.get(comm_base + n, 1), d.get(map_base + n, 0)
        if cob is None or count is None:
            continue
        slots = [s for s in d.subs(map_base + n) if s >= 1]
        fixed = count.fixed or any(d.get(map_base + n, s).fixed for s in slots)
        value = cob.value if cob.value is not None else 0x8000_0000
        cob_id = value & 0x7FF or _default_cob(tx, n, node_id)
        current = [d.value(map_base + n, s, 0) for s in range(1, (count.value or 0) + 1)]
        out.append(_Pdo(n, cob_id, cob.fixed, not value & 0x8000_0000, len(slots), fixed,
                        count.from_dcf, [c for c in current if c], d.get(comm_base + n, 2),
                        d.get(comm_base + n, 5)))
    return out


def _mapped(d: Dictionary, code: int, role: str | None) -> Mapped:
    index, sub, bits = code >> 16, code >> 8 & 0xFF, code & 0xFF
    e = d.get(index, sub)
    signed = e is not None and e.fmt in ("b", "h", "i")
    return Mapped(index, sub, bits, role, signed, d.name(index, sub))


def _sync_ok(p: _Pdo, want: int) -> bool:
    """The TPDO can be sent at every ``want``-th SYNC: writable type, or fixed at a SYNC type."""
    return p.trans is None or p.trans.writable or 1 <= (p.trans.value or 0) <= 240


def plan_pdos(d: Dictionary, node_id: int, rpdo_timeout_ms: int,
              velocity_every: int = 1, wanted: tuple | None = None) -> PdoPlan:
    """The PDO layout for drive ``d`` (see the module docstring); ``wanted``: the (RPDO,
    TPDO) ``needs`` (default: CiA 402's objects)."""
    plan = PdoPlan()
    for tx, needed in zip((False, True), wanted or needs()):
        pdos = _available(d, tx, node_id)
        planned: list[PlannedPdo] = []
        claimed: set[tuple[int, int]] = set()
        owners: dict[int, _Pdo] = {}
        # 1. fixed or DCF mappings, used as they are.
        for p in pdos:
            if not (p.fixed or p.dcf) or not p.current or not p.cob_id:
                continue
            roles = {(n.index, n.sub): n.role for n in needed if (n.index, n.sub) not in claimed}
            entries = [_mapped(d, c, roles.get((c >> 16, c >> 8 & 0xFF))) for c in p.current]
            if not any(e.role for e in entries):
                continue
            foreign = [e for e in entries if e.role is None and not 1 <= e.index <= 7]
            if not tx and foreign:
                plan.warnings.append(
                    f"RPDO{p.n + 1} has a {'fixed' if p.fixed else 'DCF'} mapping with "
                    f"{', '.join(f'0x{e.index:04X}' for e in foreign)}, which the driver does "
                    "not send: not used")
                continue
            if tx and not _sync_ok(p, 1):
                plan.warnings.append(f"TPDO{p.n + 1} carries what the driver needs but its "
                                     f"transmission type is fixed at {p.trans.value} (not "
                                     "synchronous): not used")
                continue
            pp = _planned(p, tx, "fixed" if p.fixed else "dcf", rpdo_timeout_ms)
            pp.entries = entries
            planned.append(pp)
            owners[id(pp)] = p
            claimed |= {(e.index, e.sub) for e in entries if e.role}
        # 2. the rest, first-fit into configurable PDOs.
        free = [p for p in pdos if not p.fixed and p.cob_id and p.slots
                and not any(owners.get(id(q)) is p for q in planned)
                and (not tx or _sync_ok(p, 1))]
        for need in needed:
            if (need.index, need.sub) in claimed:
                continue
            e = d.get(need.index, need.sub)
            if e is None:
                continue  # an absent object is the capability check's to report
            at = f"0x{need.index:04X}" + (f":{need.sub:02X}" if need.sub else "")
            what = f"{at} ({d.name(need.index, need.sub)})"
            problem = None
            if e.mappable is False:
                problem = f"{what} is not PDO-mappable"
            elif e.bits not in (8, 16, 32):
                problem = f"{what} has data type 0x{e.data_type:04X}, which cannot be mapped"
            if problem:
                (plan.obstacles if need.required else plan.warnings).append(
                    problem + ("" if need.required else ": not recorded"))
                continue
            own_pdo = need.role == "velocity" and velocity_every > 1
            target = None
            if not own_pdo:
                target = next((q for q in planned if q.origin == "planned"
                               and len(q.entries) < q.slots and q.bits + e.bits <= 64
                               and "velocity" not in q.roles()), None)
            if target is None and free:
                p = free.pop(0)
                target = _planned(p, tx, "planned", rpdo_timeout_ms)
                if own_pdo:
                    target.trans_type = velocity_every
                planned.append(target)
                owners[id(target)] = p
            if target is None:
                have = ", ".join(f"{q.name} ({q.slots} slot(s), {q.origin})" for q in planned)
                text = (f"no {'TPDO' if tx else 'RPDO'} room for {what}, {e.bits} bit "
                        f"(in use: {have or 'none'}; configurable PDOs left: none)")
                (plan.obstacles if need.required else plan.warnings).append(
                    text + ("" if need.required else ": not recorded"))
                continue
            target.entries.append(Mapped(need.index, need.sub, e.bits, need.role,
                                         e.fmt in ("b", "h", "i"), d.name(need.index, need.sub)))
            claimed.add((need.index, need.sub))
        if tx:
            plan.tpdos = planned
            used = {owners[id(q)].n for q in planned}
            for p in pdos:
                if p.n in used or not p.valid:
                    continue
                if p.cob_fixed:
                    plan.warnings.append(f"TPDO{p.n + 1} stays on (its COB-ID is read-only): its "
                                         "frames are ignored")
                else:
                    plan.disable.append((TPDO_COMM + p.n, p.cob_id))
        else:
            plan.rpdos = planned
    for q in plan.rpdos:
        if not q.synchronous:
            continue
        what = "torque" if "torque" in q.roles() else "controlword"
        later = (": the device's own delay is one sample period, which the driver declares "
                 "(labbench.model.device_delay: every analysis uses it; a measured [rig] "
                 "measured_td_s takes precedence)" if what == "torque" else "")
        plan.warnings.append(f"{q.name} transmission type is fixed at {q.trans_type}: the drive "
                             f"takes the {what} at the next SYNC, one period later{later}")
    return plan


def _planned(p: _Pdo, tx: bool, origin: str, rpdo_timeout_ms: int) -> PlannedPdo:
    pp = PlannedPdo(tx, p.n + 1, p.cob_id, p.slots, origin=origin, cob_fixed=p.cob_fixed)
    if p.trans is not None and not p.trans.writable:
        pp.trans_type, pp.write_trans = p.trans.value or 0, False
    else:
        pp.trans_type, pp.write_trans = (1 if tx else 255), p.trans is not None
    if p.timer is not None and p.timer.writable:
        pp.event_timer_ms = 0 if tx else rpdo_timeout_ms
    return pp


def frame_bits(n_bytes: int) -> tuple[int, int]:
    """(nominal, worst-case) bits on the wire of a CAN 2.0A data frame with ``n_bytes``.

    47 + 8n bits: SOF, 11-bit id, RTR, IDE, r0, DLC, data, CRC 15 + delimiter, ACK
    slot + delimiter, EOF 7, intermission 3 (ISO 11898-1); bit stuffing adds at
    most one bit per four after the first in the 34 + 8n bits from SOF to CRC.
    A remote frame (node guarding request) has no data field: ``n_bytes`` = 0.
    """
    nominal = 47 + 8 * n_bytes
    return nominal, nominal + (34 + 8 * n_bytes - 1) // 4


def bus_load(traffic: list[tuple[str, int, float]], bitrate: int = 1_000_000) -> dict:
    """Load of ``traffic`` ((frame, data bytes, frames per second)) at ``bitrate``."""
    nominal = sum(frame_bits(n)[0] * f for _, n, f in traffic)
    worst = sum(frame_bits(n)[1] * f for _, n, f in traffic)
    return {"bitrate": bitrate, "frames": list(traffic),
            "bits_per_s_nominal": nominal, "bits_per_s_worst": worst,
            "load_nominal": nominal / bitrate, "load_worst": worst / bitrate}
