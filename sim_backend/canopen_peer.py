"""A simulated CiA 402 servo drive on python-can's ``virtual`` bus, and ``open_sim_canopen``.

The drive is built from the EDS/DCF the rig names (``[canopen] eds``; our own
``drive.eds`` otherwise), read as leniently as the driver reads it, so a
technician can rehearse a drive's dictionary before connecting the drive. It
is a canopen ``LocalNode`` (the library's SDO server enforces object
existence, access types and data sizes) run by one thread of its own that
reads its bus and acts like a drive:

* the rules of the dictionary: value limits (LowLimit/HighLimit, abort
  0x06090031/32), PDO mappability (0x06040041), mapping length (0x06040042)
  and the CiA 301 mapping procedure (a mapping is changed only with its PDO
  invalid and sub-index 0 at zero, else abort 0x08000022; the COB-ID of a
  valid PDO is not changed, 0x06090030);
* NMT, the heartbeat producer 0x1017, node guarding answers (any RTR on
  0x700 + id, toggle bit per CiA 301) and life guarding 0x100C x 0x100D;
* SYNC: advance the plant one period with the torque held over it, then
  sample and send the TPDOs as mapped (every n-th SYNC, their transmission
  type); RPDOs of transmission type 254/255 apply on arrival, synchronous
  ones (0-240) at the next SYNC, i.e. over the period after it (one period
  later than on arrival, CiA 301 7.2.2); controlword through the pure CiA 402
  table of ``labbench.drivers.cia402``;
* the heartbeat consumer 0x1016, life guarding and RPDO event timers with the
  reaction of 0x6007 (fault when absent), with CANopenNode's rules: each
  starts with the first host frame after it is set (a write restarts it); an
  RPDO's deadline is watched whenever the node is OPERATIONAL and the PDO
  valid, whatever the CiA 402 state, and leaving OPERATIONAL ends it
  (``CO_PDO.c`` ``CO_RPDO_process``); the torque limit 0x6072 and the
  software position limits 0x607D when present; error register 0x1001 and
  error history 0x1003 when present (an entry above the count 0x1003:00 is
  abort 0x08000024, "no data available", as CANopenNode answers).

Only objects the dictionary has exist. ``LocalNode`` reacts neither to SYNC
nor (through write callbacks) to RPDOs, hence the thread. Timers run on
wall-clock time; the plant on SYNC time.

Fault hooks for tests: ``mute`` (stop answering), ``ignore_sdo_write``,
``abort_sdo_write`` and ``abort_sdo_read``, ``inject_emcy``, ``send_error_frame``, and on the host's bus
(``FaultyVirtualBus``) ``fail_tx_for`` and ``go_bus_off``. A frozen host loop needs no hook: stop
calling ``read()`` and the drive's watch fires.
"""
from __future__ import annotations

import math
import struct
import threading
import time
import uuid
from dataclasses import replace
from pathlib import Path

import can
import canopen
from can.interfaces.virtual import VirtualBus
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from labbench.drivers import cia402, eds_values, emcy
from labbench.drivers.canopen_config import (STANDARD_MODES, TARGET_TORQUE, UNITS, CanopenConfig,
                                             ref)
from labbench.drivers.canopen_drive import CanopenDrive, probe_drive
from labbench.drivers.canopen_objects import (RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP, TYPE_FMT,
                                              read_eds)
from labbench.drivers.cia402 import State
from labbench.sim_backend.canopen_process import start_process_drive
from labbench.sim_backend.sim_device import SimDevice, open_sim, paced_by_rig

EDS_PATH = Path(__file__).with_name("drive.eds")
SIM_DEVICE_TYPE = 0x00020192  # CiA 402 (0x192), servo drive (0x02 in bits 16-23)
ABORT_RANGE, ABORT_HIGH, ABORT_LOW = 0x06090030, 0x06090031, 0x06090032
ABORT_NOT_MAPPABLE, ABORT_PDO_LENGTH = 0x06040041, 0x06040042
ABORT_PARAMETER, ABORT_STATE, ABORT_NO_OBJECT = 0x06040043, 0x08000022, 0x06020000
ABORT_NO_DATA = 0x08000024


class FaultyVirtualBus(VirtualBus):
    """A virtual bus whose transmit can fail (a cable pulled at the host) and whose
    controller can report bus-off, as python-can interfaces do through ``state``."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.tx_fail_until = 0.0
        self.tx_failures = 0
        self._controller_state = can.BusState.ACTIVE

    def fail_tx_for(self, seconds: float) -> None:
        self.tx_fail_until = time.monotonic() + seconds

    def go_bus_off(self) -> None:
        """From now on the controller is bus-off: state ERROR, nothing transmits."""
        self._controller_state = can.BusState.ERROR

    @property
    def state(self) -> can.BusState:
        return self._controller_state

    def send(self, msg, timeout=None):
        if self._controller_state is can.BusState.ERROR:
            raise can.CanOperationError("controller is bus-off")
        if self.tx_fail_until and time.monotonic() < self.tx_fail_until:
            self.tx_failures += 1
            raise can.CanOperationError("simulated transmit failure (no ACK)")
        super().send(msg, timeout)


class _DriveNode(canopen.LocalNode):
    """LocalNode whose SDO writes can be ignored (acknowledged, not stored) or aborted,
    and which keeps a log of the SDO writes it accepted (tests: "nothing written")."""

    def __init__(self, node_id, od):
        super().__init__(node_id, od)
        self.ignored: set[tuple[int, int]] = set()
        self.aborted: dict[tuple[int, int], int] = {}
        self.read_aborted: dict[tuple[int, int], int] = {}
        self.writes: list[tuple[int, int]] = []

    def set_data(self, index, subindex, data, check_writable=False):
        if (index, subindex) in self.aborted:
            raise SdoAbortedError(self.aborted[(index, subindex)])
        if (index, subindex) in self.ignored:
            return
        super().set_data(index, subindex, data, check_writable)
        if check_writable:  # an SDO write (the drive's own stores pass False)
            self.writes.append((index, subindex))

    def _find_object(self, index, subindex):
        """Only declared subindices exist (canopen's arrays make up any 1-255)."""
        obj = super()._find_object(index, subindex)
        parent = self.object_dictionary[index]
        if not isinstance(parent, ODVariable) and subindex not in parent.subindices:
            raise SdoAbortedError(0x06090011)
        return obj


def _is_dummy(index: int) -> bool:
    return 1 <= index <= 7


class SimCanopenDrive:
    """The simulated drive; ``start()`` runs its thread, ``close()`` stops it (idempotent).

    ``config``: the rig's ``[canopen]`` table, for what a dictionary may lack
    (the rated torque when 0x6076 is absent or 0) and the vendor torque modes
    of ``[canopen.modes]``, which this drive then offers. ``bus``: the drive's
    bus (``canopen_process`` gives a ``udp_multicast`` one); else a ``virtual``
    bus on ``channel``.
    """

    def __init__(self, channel: str, node_id: int, plant: SimDevice,
                 metres_per_count: float, lever_arm_m: float, sample_time_s: float,
                 eds: str | Path = EDS_PATH, config: CanopenConfig | None = None,
                 bus: can.BusABC | None = None):
        self.node_id = node_id
        self.plant = plant
        self.mpc = metres_per_count
        self.lever = lever_arm_m
        self.T = sample_time_s
        self.config = config or CanopenConfig()
        self.dictionary = read_eds(str(eds), node_id)
        self.od = self.dictionary.od
        self._stand_in_values()
        self.bus = bus if bus is not None else VirtualBus(channel=channel)
        self.network = canopen.Network(self.bus)
        self.node = _DriveNode(node_id, self.od)
        self.network.add_node(self.node)
        # Heartbeat is produced by the drive thread, not by a periodic task.
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        self.node.add_read_callback(self._on_sdo_read)
        self.node.add_write_callback(self._on_sdo_write)
        self._params: dict[tuple[int, int], int] = {}
        self.lock = threading.RLock()
        self.nmt_state = 127
        self.state = State.SWITCH_ON_DISABLED
        self.controlword = 0
        # Set point objects by mode (0x6060 code -> (index, sub), unit): 0x6071 per-mille of
        # the rated torque in CiA 402's modes, the rig's vendor objects in theirs.
        self._set_point = {c: (TARGET_TORQUE, "permille") for c, _, _ in STANDARD_MODES.values()}
        self._set_point.update({m["code"]: (ref(m["command"]), m["unit"])
                                for m in self.config.modes.values()})
        self.targets = {obj: 0 for obj, _ in self._set_point.values()}  # last value of each
        self.applied = 0  # the set point applied now (0 unless the power stage is enabled)
        self._position = {(0x6064, 0), ref(self.config.position)}
        self._velocity = {(0x606C, 0), ref(self.config.velocity)}
        self.error_code = 0
        self.history: list[int] = []  # error history 0x1003, newest first
        self.mode = 0
        self.muted = False
        self.sync_count = 0
        self.events: list[str] = []  # what the drive did on its own, for tests and docs
        self.emcy_sent: list[int] = []  # error codes of the EMCYs it sent
        self._torque_modes = set(self._set_point)
        self._hb_next = math.inf
        self._host_hb_last: float | None = None
        self._guard_last: float | None = None  # last guarding request (life guarding)
        self._toggle = 0
        self._tpdos: list = []
        self._rpdos: dict = {}  # COB-ID -> [indices, struct, timer ms, synchronous, last, n]
        self._pending: list = []  # synchronous RPDO values, applied at the next SYNC
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-canopen-drive", daemon=True)

    def _stand_in_values(self) -> None:
        """A value wherever the file lists an object without one (a real drive has its
        own there): the neutral value of its type, except what this drive is, a CiA 402
        servo drive (0x1000) with the torque modes it simulates (0x6502)."""
        own = {0x1000: SIM_DEVICE_TYPE, 0x6502: self._supported_modes()}
        for obj in self.od.values():
            for v in [obj] if isinstance(obj, ODVariable) else obj.values():
                if v.value is None and v.default is None:
                    v.default = own.get(v.index, eds_values.neutral(v.data_type))

    def _supported_modes(self) -> int:
        bits = [b for _, b, _ in STANDARD_MODES.values()] + [
            m["bit"] for m in self.config.modes.values() if m["bit"] is not None]
        return sum(1 << b for b in set(bits))

    # ---------------------------------------------------------------- OD access
    def has(self, index: int, sub: int = 0) -> bool:
        return self.dictionary.has(index, sub)

    def _get(self, index: int, sub: int = 0, default: int | None = None) -> int:
        """A stored parameter (cached; the write callback keeps the cache current);
        ``default`` for an object the dictionary does not have."""
        key = (index, sub)
        if key not in self._params:
            if not self.has(index, sub):
                return default
            obj = self.node._find_object(index, sub)
            raw = self.node.data_store.get(index, {}).get(sub)
            value = obj.decode_raw(raw) if raw is not None else (
                obj.value if obj.value is not None else obj.default)
            self._params[key] = value if value is not None else 0
        return self._params[key]

    @property
    def torque_permille(self) -> int:
        """The set point applied now, in its mode's unit (per-mille of the rated torque in
        CiA 402's torque modes)."""
        return self.applied

    def rated_mnm(self) -> float:
        """The torque unit: 0x6076, else what the rig declares (as the driver resolves it)."""
        cfg = self.config
        return (self._get(0x6076, 0, 0) or cfg.rated_torque_mnm
                or cfg.torque_constant_nm_per_a * (self._get(0x6075, 0, 0) or cfg.rated_current_ma))

    def _mode_set_point(self) -> tuple[tuple[int, int], str]:
        """The set point object of the mode in force, and its unit."""
        return self._set_point.get(self.mode, (TARGET_TORQUE, "permille"))

    def torque_nm(self) -> float:
        """The joint torque applied now: the set point in its unit (module doc)."""
        unit = self._mode_set_point()[1]
        if unit == "permille":
            return self.applied * self.rated_mnm() * 1e-6
        factor, per = UNITS[unit]
        return self.applied * factor * (self.config.torque_constant_nm_per_a if per else 1.0)

    def _live(self, index: int, sub: int) -> int | None:
        """Process values (None for stored parameters)."""
        if (index, sub) in self._position:
            return round(self.plant.x / self.mpc)
        if index == 0x6041:
            return self._statusword()
        if index == 0x6077:
            rated = self.rated_mnm()
            return round(self.torque_nm() / (rated * 1e-6)) if rated else 0
        if (index, sub) in self._velocity:
            return round(self.plant.v / self.mpc)
        if (index, sub) in self.targets:
            return self.targets[(index, sub)]
        if index == 0x1003:
            if sub > len(self.history):
                raise SdoAbortedError(ABORT_NO_DATA)  # CANopenNode's answer above the count
            return len(self.history) if sub == 0 else self.history[sub - 1]
        if index == 0x1001:
            return 0x01 if self.state is State.FAULT else 0
        return {0x6061: self.mode, 0x603F: self.error_code, 0x6040: self.controlword}.get(index)

    def _on_sdo_read(self, index, subindex, od):
        if (index, subindex) in self.node.read_aborted:
            raise SdoAbortedError(self.node.read_aborted[(index, subindex)])
        return self._live(index, subindex)

    def _on_sdo_write(self, index, subindex, od, data):
        value = od.decode_raw(data)
        if isinstance(value, int):
            if od.min is not None and value < od.min:
                raise SdoAbortedError(ABORT_LOW)
            if od.max is not None and value > od.max:
                raise SdoAbortedError(ABORT_HIGH)
        if index & 0xFE00 in (RPDO_MAP, TPDO_MAP):
            self._check_mapping(index, subindex, value)
        elif index & 0xFE00 in (RPDO_COMM, TPDO_COMM) and subindex == 1:
            now = self._get(index, 1, 0x8000_0000)
            if not (now | value) & 0x8000_0000 and (now ^ value) & 0x7FF:
                raise SdoAbortedError(ABORT_RANGE)  # the COB-ID of a valid PDO stays
        if index == 0x6060:
            if value not in self._torque_modes or not self._mode_supported(value):
                raise SdoAbortedError(ABORT_RANGE)  # not stored, not cached
            self.mode = value
        self._params[(index, subindex)] = value
        if index == 0x6040:
            self._controlword(value)
        elif (index, subindex) in self.targets:
            self.targets[(index, subindex)] = value
            self._apply_torque()
        elif index == 0x1017:
            self._hb_next = time.monotonic() + value * 1e-3 if value else math.inf
        elif index == 0x1016:
            self._host_hb_last = None  # the consumer (re)starts with the next heartbeat
        elif index in (0x100C, 0x100D):
            self._guard_last = None  # life guarding (re)starts with the next request
        elif index & 0xFE00 == RPDO_COMM and subindex in (1, 2, 5) and self.nmt_state == 5:
            self._load_rpdo(index - RPDO_COMM)  # CANopenNode: a write restarts the watch

    def _mode_supported(self, code: int) -> bool:
        bits = {c: b for c, b, _ in STANDARD_MODES.values()}
        bits.update({m["code"]: m["bit"] for m in self.config.modes.values()})
        bit = bits.get(code)
        supported = self._get(0x6502, 0, None)
        return bit is None or supported is None or bool(supported >> bit & 1)

    def _check_mapping(self, index: int, sub: int, value: int) -> None:
        """CiA 301 PDO mapping rules (see the module docstring)."""
        comm = index - (RPDO_MAP - RPDO_COMM if index < TPDO_COMM else TPDO_MAP - TPDO_COMM)
        if not self._get(comm, 1, 0x8000_0000) & 0x8000_0000:
            raise SdoAbortedError(ABORT_STATE)  # the PDO is valid: invalidate it first
        if sub == 0:
            slots = [s for s in self.dictionary.subs(index) if s >= 1]
            if value > len(slots):
                raise SdoAbortedError(ABORT_PDO_LENGTH)
            total = 0
            for s in range(1, value + 1):
                total += self._entry_bits(self._get(index, s, 0))
            if total > 64:
                raise SdoAbortedError(ABORT_PDO_LENGTH)
            return
        if self._get(index, 0, 0) != 0:
            raise SdoAbortedError(ABORT_STATE)  # sub-index 0 must be 0 while entries change
        if value:
            self._entry_bits(value)

    def _entry_bits(self, entry: int) -> int:
        index, sub, bits = entry >> 16, entry >> 8 & 0xFF, entry & 0xFF
        if _is_dummy(index):
            return bits
        e = self.dictionary.get(index, sub)
        if e is None:
            raise SdoAbortedError(ABORT_NO_OBJECT)
        if not e.mappable:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        if bits != e.bits:
            raise SdoAbortedError(ABORT_PARAMETER)
        return bits

    def _statusword(self) -> int:
        extra = cia402.SW_REMOTE
        if self.state in cia402.TORQUE_STATES or self.state is State.SWITCHED_ON:
            extra |= cia402.SW_VOLTAGE_ENABLED
        if (self.state is State.OPERATION_ENABLED and self._mode_set_point()[1] == "permille"
                and abs(self.targets[TARGET_TORQUE]) > self._get(0x6072, 0, 32767)):
            extra |= cia402.SW_INTERNAL_LIMIT
        return cia402.encode_status(self.state, extra)

    # ------------------------------------------------------------ 402 behaviour
    def _controlword(self, cw: int) -> None:
        cmd = cia402.decode_controlword(cw, self.controlword)
        self.controlword = cw
        new = cia402.next_state(self.state, cmd)
        if new is State.QUICK_STOP_ACTIVE and self._get(0x605A, 0, 2) in (0, 1, 2, 3, 4):
            new = State.SWITCH_ON_DISABLED  # these options end in SWITCH ON DISABLED
        if new is State.OPERATION_ENABLED and self.mode not in self._torque_modes:
            return self._fault(0x6320, "enabled without a torque mode")
        if new is State.SWITCH_ON_DISABLED and self.state is State.FAULT:
            self.error_code = 0
        self.state = new
        self._apply_torque()

    def _apply_torque(self) -> None:
        """The mode's set point on the motor when enabled: 0x6072 clamps a per-mille set
        point (a vendor mode's own limits are not simulated)."""
        if self.state is State.OPERATION_ENABLED:
            obj, unit = self._mode_set_point()
            lim = self._get(0x6072, 0, 32767) if unit == "permille" else 1 << 31
            self.applied = max(-lim, min(lim, self.targets[obj]))
        else:
            self.applied = 0

    def _fault(self, code: int, why: str) -> None:
        """Fault reaction (instantaneous here): torque off, FAULT, EMCY, error history."""
        self.applied = 0
        self.state = State.FAULT
        self.error_code = code
        self.history.insert(0, code)
        del self.history[8:]
        self.events.append(f"fault 0x{code:04X}: {why}")
        register = 0x01 | (0x10 if code >> 8 == 0x81 else 0)  # generic (+ communication)
        self._emcy(code, register)

    def _emcy(self, code: int, register: int) -> None:
        self.emcy_sent.append(code)
        self._send(0x80 + self.node_id, emcy.encode(code, register))

    def _abort_connection(self, code: int, why: str) -> None:
        """Reaction of 0x6007 to a lost host (heartbeat, life guarding or RPDO timeout);
        without 0x6007 this drive faults (its manufacturer's choice)."""
        option = self._get(0x6007, 0, 1)
        self.events.append(f"connection lost ({why}), 0x6007 = {option}")
        if option == 1:
            self._fault(code, why)
        elif option in (2, 3) and self.state is State.OPERATION_ENABLED:
            self._controlword(0x00 if option == 2 else 0x02)  # disable voltage / quick stop

    # ------------------------------------------------------------------ the bus
    def _send(self, can_id: int, data: bytes) -> None:
        if not self.muted:
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def _pdo_layout(self, mapping: int) -> tuple[list, struct.Struct]:
        """Mapped objects (index, sub) and the frame layout of one PDO (dummies skipped)."""
        indices, fmt = [], "<"
        for s in range(1, self._get(mapping, 0, 0) + 1):
            entry = self._get(mapping, s, 0)
            index, sub, bits = entry >> 16, entry >> 8 & 0xFF, entry & 0xFF
            if _is_dummy(index):
                fmt += f"{bits // 8}x"
                continue
            indices.append((index, sub))
            fmt += TYPE_FMT[self.dictionary.get(index, sub).data_type]
        return indices, struct.Struct(fmt)

    def _load_pdos(self) -> None:
        """Read the PDO configuration (on entering OPERATIONAL)."""
        self._tpdos, self._rpdos = [], {}
        for n in range(512):
            comm = TPDO_COMM + n
            if self.has(comm, 1) and not self._get(comm, 1) & 0x8000_0000:
                indices, st = self._pdo_layout(TPDO_MAP + n)
                every = self._get(comm, 2, 255)
                if indices and every <= 240:
                    self._tpdos.append((self._get(comm, 1) & 0x7FF, max(every, 1), indices, st))
            self._load_rpdo(n)

    def _load_rpdo(self, n: int) -> None:
        """RPDO ``n`` (0-based) as configured now, its deadline not yet watched (it is from
        its first frame on); dropped while invalid."""
        comm = RPDO_COMM + n
        for cob_id in [c for c, r in self._rpdos.items() if r[5] == n]:
            del self._rpdos[cob_id]
        if self.has(comm, 1) and not self._get(comm, 1) & 0x8000_0000:
            indices, st = self._pdo_layout(RPDO_MAP + n)
            self._rpdos[self._get(comm, 1) & 0x7FF] = [
                indices, st, self._get(comm, 5, 0), self._get(comm, 2, 255) <= 240, None, n]

    def _on_nmt(self, data: bytes) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        cs = data[0]
        if cs != 0x01:
            for r in self._rpdos.values():
                r[4] = None  # not OPERATIONAL: no PDO, no RPDO deadline (CO_RPDO_process)
        if cs == 0x01:
            self._load_pdos()
            self.nmt_state = 5
        elif cs == 0x02:
            self.nmt_state = 4
        elif cs == 0x80:
            self.nmt_state = 127
        elif cs in (0x81, 0x82):
            self.nmt_state = 127
            self._toggle = 0
            self._send(0x700 + self.node_id, b"\x00")  # boot-up

    def _on_sync(self) -> None:
        if self.nmt_state != 5:
            return
        # SYNC k samples x[k]; from the second SYNC on the plant first advances one
        # period under the torque held over it (as sim_backend.sim_device).
        self.plant.command(self.torque_nm() / self.lever)
        self.plant.read_raw(1.0)
        # Synchronous RPDOs received since the last SYNC take effect now: held from here.
        for values in self._pending:
            self._take(values)
        self._pending = []
        self.sync_count += 1
        counts = round(self.plant.x / self.mpc)
        if self.state is State.OPERATION_ENABLED and self.has(0x607D, 1):
            lo, hi = self._get(0x607D, 1), self._get(0x607D, 2)
            if not lo <= counts <= hi:
                self._fault(0x8612, f"position {counts} counts outside 0x607D [{lo}, {hi}]")
        if self.config.sim_answer_delay_ms:  # a slow drive (the timing preflight's tests)
            time.sleep(self.config.sim_answer_delay_ms * 1e-3)
        for cob_id, every, indices, st in self._tpdos:
            if self.sync_count % every == 0:
                self._send(cob_id, st.pack(*[self._live(*i) for i in indices]))

    def _take(self, values: dict) -> None:
        for obj in self.targets.keys() & values.keys():
            self.targets[obj] = values[obj]
        if (0x6040, 0) in values:
            self._controlword(values[(0x6040, 0)])  # also applies the torque
        else:
            self._apply_torque()

    def _on_rpdo(self, rpdo: list, data: bytes, now: float) -> None:
        indices, st, _, synchronous, _, _ = rpdo
        if len(data) < st.size:
            self._emcy(0x8210, 0x11)  # length error
            return
        values = dict(zip(indices, st.unpack_from(data)))
        if synchronous:
            self._pending.append(values)
        else:
            self._take(values)
        rpdo[4] = now  # the deadline is watched from the first RPDO on, in any 402 state

    def _on_guard(self) -> None:
        """Node guarding request: answer state + toggle; life guarding starts with it."""
        if not self.has(0x100C):
            return  # this drive has no node guarding
        self._guard_last = time.monotonic()
        self._send(0x700 + self.node_id, bytes([self._toggle | self.nmt_state]))
        self._toggle ^= 0x80

    def _dispatch(self, msg: can.Message, now: float) -> None:
        cid = msg.arbitration_id
        if msg.is_error_frame:
            return
        if msg.is_remote_frame:
            if cid == 0x700 + self.node_id:
                self._on_guard()
            return
        if cid == 0x080:
            self._on_sync()
        elif cid in self._rpdos and self.nmt_state == 5:
            self._on_rpdo(self._rpdos[cid], msg.data, now)
        elif cid == 0x600 + self.node_id:
            if not self.muted and self.nmt_state != 4:  # no SDO in STOPPED (CiA 301)
                self.node.sdo.on_request(cid, msg.data, msg.timestamp)
        elif cid == 0:
            self._on_nmt(msg.data)
        elif (cid & 0x780) == 0x700:
            host = self._get(0x1016, 1, 0) >> 16 & 0x7F
            if cid == 0x700 + host:
                self._host_hb_last = now

    def _timers(self, now: float) -> None:
        if now >= self._hb_next:
            self._send(0x700 + self.node_id, bytes([self.nmt_state]))
            self._hb_next = now + self._get(0x1017) * 1e-3
        limit_ms = self._get(0x1016, 1, 0) & 0xFFFF
        last = self._host_hb_last
        if limit_ms and last is not None and now - last > limit_ms * 1e-3:
            self._host_hb_last = None  # re-armed by the next host heartbeat
            self._abort_connection(0x8130, f"no host heartbeat for {limit_ms} ms")
        life_ms = self._get(0x100C, 0, 0) * self._get(0x100D, 0, 0)
        if life_ms and self._guard_last is not None and now - self._guard_last > life_ms * 1e-3:
            self._guard_last = None  # re-armed by the next request
            self._abort_connection(0x8130, f"life guarding: no request for {life_ms} ms")
        for rpdo in list(self._rpdos.values()):
            timer, last = rpdo[2], rpdo[4]
            if timer and last is not None and now - last > timer * 1e-3:
                rpdo[4] = None  # fires once; the next RPDO watches again
                self._abort_connection(0x8250, f"no RPDO for {timer} ms")

    def _run(self) -> None:
        recv = self.bus.recv
        while not self._stop.is_set():
            msg = recv(0.002)
            now = time.monotonic()
            with self.lock:
                if msg is not None:
                    self._dispatch(msg, now)
                self._timers(now)

    # ------------------------------------------------------------ fault hooks
    def mute(self, on: bool = True) -> None:
        """Stop (or resume) answering: no SDO, PDO, heartbeat or EMCY leaves the drive."""
        self.muted = on

    def ignore_sdo_write(self, index: int, sub: int = 0) -> None:
        """Acknowledge writes to this object but keep the old value."""
        self.node.ignored.add((index, sub))

    def abort_sdo_write(self, index: int, sub: int = 0, code: int = 0x08000020) -> None:
        """Answer writes to this object with an SDO abort (default: cannot store)."""
        self.node.aborted[(index, sub)] = code

    def abort_sdo_read(self, index: int, sub: int = 0, code: int = ABORT_NO_DATA) -> None:
        """Answer reads of this object with an SDO abort (default: no data available)."""
        self.node.read_aborted[(index, sub)] = code

    def inject_emcy(self, code: int = 0x2310, why: str = "injected fault") -> None:
        """An internal drive fault: torque off, FAULT, EMCY sent."""
        with self.lock:
            self._fault(code, why)

    def send_error_frame(self, error_class: int = 0x080) -> None:
        """An error frame on the bus (0x040 = bus off, 0x080 = bus error; SocketCAN classes)."""
        self.bus.send(can.Message(arbitration_id=error_class, is_error_frame=True,
                                  is_extended_id=False, data=bytes(8)))

    # ------------------------------------------------------------------ life
    def start(self) -> "SimCanopenDrive":
        self._thread.start()
        return self

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        self.bus.shutdown()


def plant_for(rig, seed=None, **options) -> SimDevice:
    """The handle behind the drive: the plain simulator of ``[sim]`` and ``options``
    (mass, damping, friction, noise, delay), stepped once per SYNC, in true handle units
    (the drive applies the true geometry, ``sim_device.true_geometry``)."""
    plant = open_sim(rig, realtime=False, seed=seed, as_plant=True, **options)
    plant.enable()
    return plant


# The simulated drive's monitors run on wall-clock time in a process that is not
# real-time (a shared machine stalls it for tens of ms now and then): defaults
# that survive such stalls. A rig's [canopen] table still overrides them.
SIM_MONITOR_DEFAULTS = {"heartbeat_consumer_ms": 1000, "rpdo_timeout_ms": 500,
                        "life_time_factor": 50,  # 1 s at the default 20 ms guard time
                        "stale_periods": 20,  # paced (--realtime) runs only
                        "sdo_timeout_s": 2.0}  # the peer answers at once unless descheduled


def sim_config(rig) -> CanopenConfig:
    """The rig's ``[canopen]`` table without the bus: the simulation brings its own.

    The ``eds`` stays: the simulated drive is built from it.
    """
    section = {**SIM_MONITOR_DEFAULTS, **rig.section("canopen")}
    for hardware_field in ("interface", "channel", "bitrate"):
        section.pop(hardware_field, None)
    return replace(CanopenConfig.from_section(section, source=rig.source), bus_options={})


def start_sim_drive(rig, config: CanopenConfig, seed=None,
                    **options) -> tuple[SimCanopenDrive, FaultyVirtualBus]:
    """A running simulated drive on a fresh ``virtual`` channel, and the host's bus to it."""
    # no trailing digits: trace writers read them as the channel number (BLF's is 16-bit)
    channel = f"labbench-{uuid.uuid4().hex[:8]}-sim"
    plant = plant_for(rig, seed, **options)
    geo = plant.geometry  # the encoder's count direction as the signed metres per count
    peer = SimCanopenDrive(channel, config.node_id, plant, geo.sign * geo.metres_per_count,
                           geo.lever_arm_m, rig.sample_time_s, eds=config.eds or EDS_PATH,
                           config=config).start()
    try:
        return peer, FaultyVirtualBus(channel=channel)
    except Exception:
        peer.close()
        raise


def driver_for(rig, config, peer, host_bus, realtime: bool = False,
               can_log: str | None = None) -> CanopenDrive:
    """The real driver on ``host_bus``, not yet opened; closing it stops ``peer``."""
    where = ("in its own process on python-can's udp_multicast bus" if config.sim_drive ==
             "process" else "in a thread of this process on python-can's virtual bus")
    try:
        drive = CanopenDrive(rig, config, bus=host_bus, realtime=realtime, can_log=can_log,
                             simulated=f"simulated CiA 402 drive {where}")
    except BaseException:
        host_bus.shutdown()
        peer.close()
        raise
    drive.peer = peer
    drive.add_close_hook(peer.close)
    return drive


def connect_driver(rig, config, peer, host_bus, realtime: bool = False,
                   can_log: str | None = None) -> CanopenDrive:
    """The real driver, opened against ``peer``; closing the driver stops the peer."""
    drive = driver_for(rig, config, peer, host_bus, realtime, can_log)
    drive.open()  # closes the bus and the peer if it fails
    return drive


def open_sim_canopen(rig, realtime: bool | None = None, seed=None, can_log: str | None = None,
                     **options) -> CanopenDrive:
    """Registry factory (``--device sim-canopen``): the real driver connected to a simulated drive.

    ``seed`` and ``options`` are those of the plain simulator (``labbench.sim_backend.sim_device``),
    applied to the handle behind the drive; ``can_log`` records every frame. With
    ``[canopen] sim_drive = "process"`` the drive runs in its own process
    (``canopen_process``), on ``udp_multicast``. ``realtime``: the driver paces SYNC at
    the sample time, as on hardware (None: the rig's ``[sim] paced``; default lock-step).
    """
    realtime = paced_by_rig(rig, realtime)
    config = sim_config(rig)
    if config.sim_drive == "process":
        peer, host_bus = start_process_drive(rig, config, seed, paced=realtime, **options)
    else:
        peer, host_bus = start_sim_drive(rig, config, seed, **options)
    return connect_driver(rig, config, peer, host_bus, realtime, can_log)


def probe_sim_canopen(rig, fault_reset: bool = False) -> dict:
    """Registry probe (``labbench devices``): the same report from a fresh simulated drive."""
    config = sim_config(rig)
    return probe_drive(driver_for(rig, config, *start_sim_drive(rig, config)), fault_reset)
