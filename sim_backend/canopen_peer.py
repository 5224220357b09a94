"""A simulated CiA 402 servo drive on python-can's ``virtual`` bus, and ``open_sim_canopen``.

The drive is a canopen ``LocalNode`` (object dictionary from ``drive.eds``, the
library's SDO server) run by one thread of its own that reads its bus and
handles, like a drive would: NMT commands and the heartbeat producer (0x1017),
SYNC (advance the plant one period with the torque held since the last RPDO,
then sample and send the TPDOs as mapped in 0x1A00/0x1A01), the RPDO (target
torque, controlword through the pure CiA 402 table of ``labbench.drivers.cia402``), the
heartbeat consumer (0x1016) and RPDO event timer (0x1400:05) with the reaction
of 0x6007, the torque limit 0x6072 and software position limits 0x607D.
``LocalNode`` reacts neither to SYNC nor (through write callbacks) to RPDOs,
hence the thread. Timers run on wall-clock time; the plant on SYNC time.

Fault hooks for tests: ``mute`` (stop answering), ``ignore_sdo_write`` and
``abort_sdo_write``, ``inject_emcy``, ``send_error_frame``, and on the host's bus
(``FaultyVirtualBus``) ``fail_tx_for`` and ``go_bus_off``. A frozen host loop needs no hook: stop
calling ``read()`` and the heartbeat consumer fires.
"""
from __future__ import annotations

import math
import struct
import threading
import time
import uuid
from pathlib import Path

import can
import canopen
from can.interfaces.virtual import VirtualBus
from canopen.sdo import SdoAbortedError

from labbench.drivers import cia402, emcy
from labbench.drivers.canopen_drive import MODE_BITS, CanopenConfig, CanopenDrive
from labbench.drivers.cia402 import State
from labbench.sim_backend.sim_device import SimDevice, open_sim

EDS_PATH = Path(__file__).with_name("drive.eds")
# Struct codes of the OD data types the drive can map into a PDO.
_PDO_TYPES = {0x2: "b", 0x3: "h", 0x4: "i", 0x5: "B", 0x6: "H", 0x7: "I"}
SDO_ABORT_VALUE_RANGE = 0x06090030


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
    """LocalNode whose SDO writes can be ignored (acknowledged, not stored) or aborted."""

    def __init__(self, node_id, od):
        super().__init__(node_id, od)
        self.ignored: set[tuple[int, int]] = set()
        self.aborted: dict[tuple[int, int], int] = {}

    def set_data(self, index, subindex, data, check_writable=False):
        if (index, subindex) in self.aborted:
            raise SdoAbortedError(self.aborted[(index, subindex)])
        if (index, subindex) in self.ignored:
            return
        super().set_data(index, subindex, data, check_writable)


class SimCanopenDrive:
    """The simulated drive; ``start()`` runs its thread, ``close()`` stops it (idempotent)."""

    def __init__(self, channel: str, node_id: int, plant: SimDevice,
                 metres_per_count: float, lever_arm_m: float, sample_time_s: float):
        self.node_id = node_id
        self.plant = plant
        self.mpc = metres_per_count
        self.lever = lever_arm_m
        self.T = sample_time_s
        self.bus = VirtualBus(channel=channel)
        self.network = canopen.Network(self.bus)
        self.node = _DriveNode(node_id, canopen.import_od(str(EDS_PATH), node_id))
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
        self.target_permille = 0
        self.torque_permille = 0  # applied now (0 unless the power stage is enabled)
        self.error_code = 0
        self.mode = 0
        self.muted = False
        self.sync_count = 0
        self.events: list[str] = []  # what the drive did on its own, for tests and docs
        self._hb_next = math.inf
        self._host_hb_last: float | None = None
        self._rpdo_last: float | None = None
        self._tpdos: list = []
        self._rpdo: tuple | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-canopen-drive", daemon=True)

    # ---------------------------------------------------------------- OD access
    def _get(self, index: int, sub: int = 0) -> int:
        """A stored parameter (cached; the write callback keeps the cache current)."""
        key = (index, sub)
        if key not in self._params:
            obj = self.node._find_object(index, sub)
            raw = self.node.data_store.get(index, {}).get(sub)
            self._params[key] = obj.decode_raw(raw) if raw is not None else obj.default
        return self._params[key]

    def _live(self, index: int) -> int | None:
        """Process values (None for stored parameters)."""
        if index == 0x6064:
            return round(self.plant.x / self.mpc)
        if index == 0x6041:
            return self._statusword()
        if index == 0x6077:
            return self.torque_permille
        if index == 0x606C:
            return round(self.plant.v / self.mpc)
        return {0x6061: self.mode, 0x603F: self.error_code, 0x6071: self.target_permille,
                0x6040: self.controlword,
                0x1001: 0x01 if self.state is State.FAULT else 0}.get(index)

    def _on_sdo_read(self, index, subindex, od):
        return self._live(index)

    def _on_sdo_write(self, index, subindex, od, data):
        if index == 0x6060:
            mode = struct.unpack("<b", data)[0]
            if not (mode in (10, 4) and self._get(0x6502) & MODE_BITS[mode]):
                raise SdoAbortedError(SDO_ABORT_VALUE_RANGE)  # not stored, not cached
            self.mode = mode
        self._params[(index, subindex)] = od.decode_raw(data)
        if index == 0x6040:
            self._controlword(struct.unpack("<H", data)[0])
        elif index == 0x6071:
            self.target_permille = struct.unpack("<h", data)[0]
            self._apply_torque()
        elif index == 0x1017:
            ms = struct.unpack("<H", data)[0]
            self._hb_next = time.monotonic() + ms * 1e-3 if ms else math.inf

    def _statusword(self) -> int:
        extra = cia402.SW_REMOTE
        if self.state in cia402.TORQUE_STATES or self.state is State.SWITCHED_ON:
            extra |= cia402.SW_VOLTAGE_ENABLED
        if self.state is State.OPERATION_ENABLED and abs(self.target_permille) > self._get(0x6072):
            extra |= cia402.SW_INTERNAL_LIMIT
        return cia402.encode_status(self.state, extra)

    # ------------------------------------------------------------ 402 behaviour
    def _controlword(self, cw: int) -> None:
        cmd = cia402.decode_controlword(cw, self.controlword)
        self.controlword = cw
        new = cia402.next_state(self.state, cmd)
        if new is State.QUICK_STOP_ACTIVE and self._get(0x605A) in (0, 1, 2, 3, 4):
            new = State.SWITCH_ON_DISABLED  # these options end in SWITCH ON DISABLED
        if new is State.OPERATION_ENABLED and self.mode not in (10, 4):
            return self._fault(0x6320, "enabled without a torque mode")
        if new is State.SWITCH_ON_DISABLED and self.state is State.FAULT:
            self.error_code = 0
        self.state = new
        if new is not State.OPERATION_ENABLED:
            self._rpdo_last = None  # RPDO monitoring is armed in OPERATION ENABLED only
        self._apply_torque()

    def _apply_torque(self) -> None:
        if self.state is State.OPERATION_ENABLED:
            lim = self._get(0x6072)
            self.torque_permille = max(-lim, min(lim, self.target_permille))
        else:
            self.torque_permille = 0

    def _fault(self, code: int, why: str) -> None:
        """Fault reaction (instantaneous here): torque off, FAULT, EMCY."""
        self.torque_permille = 0
        self.state = State.FAULT
        self.error_code = code
        self._rpdo_last = None
        self.events.append(f"fault 0x{code:04X}: {why}")
        register = 0x01 | (0x10 if code >> 8 == 0x81 else 0)  # generic (+ communication)
        self._send(0x80 + self.node_id, emcy.encode(code, register))

    def _abort_connection(self, code: int, why: str) -> None:
        """Reaction of 0x6007 to a lost host (heartbeat or RPDO timeout)."""
        option = self._get(0x6007)
        self.events.append(f"connection lost ({why}), 0x6007 = {option}")
        if option == 1:
            self._fault(code, why)
        elif option in (2, 3) and self.state is State.OPERATION_ENABLED:
            self._controlword(0x00 if option == 2 else 0x02)  # disable voltage / quick stop

    # ------------------------------------------------------------------ the bus
    def _send(self, can_id: int, data: bytes) -> None:
        if not self.muted:
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def _load_pdos(self) -> None:
        """Read the PDO configuration the host wrote (on entering OPERATIONAL)."""
        self._tpdos = []
        for comm, mapping in ((0x1800, 0x1A00), (0x1801, 0x1A01)):
            cob_id = self._get(comm, 1)
            if cob_id & 0x8000_0000:
                continue
            entries = [self._get(mapping, s) for s in range(1, self._get(mapping, 0) + 1)]
            fmt = "<" + "".join(_PDO_TYPES[self.node._find_object(e >> 16, e >> 8 & 0xFF).data_type]
                                for e in entries)
            self._tpdos.append((cob_id, self._get(comm, 2), [e >> 16 for e in entries],
                                struct.Struct(fmt)))
        cob_id = self._get(0x1400, 1)
        entries = [self._get(0x1600, s) for s in range(1, self._get(0x1600, 0) + 1)]
        fmt = "<" + "".join(_PDO_TYPES[self.node._find_object(e >> 16, e >> 8 & 0xFF).data_type]
                            for e in entries)
        self._rpdo = None if cob_id & 0x8000_0000 else (
            cob_id, [e >> 16 for e in entries], struct.Struct(fmt), self._get(0x1400, 5))

    def _on_nmt(self, data: bytes) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        cs = data[0]
        if cs == 0x01:
            self._load_pdos()
            self.nmt_state = 5
        elif cs == 0x02:
            self.nmt_state = 4
        elif cs == 0x80:
            self.nmt_state = 127
        elif cs in (0x81, 0x82):
            self.nmt_state = 127
            self._send(0x700 + self.node_id, b"\x00")  # boot-up

    def _on_sync(self) -> None:
        if self.nmt_state != 5:
            return
        # SYNC k samples x[k]; from the second SYNC on the plant first advances one
        # period under the torque held since the last RPDO (as sim_backend.sim_device).
        self.plant.command(self.torque_permille * 1e-3 * self._get(0x6076) * 1e-3 / self.lever)
        self.plant.read_raw(1.0)
        self.sync_count += 1
        lo, hi = self._get(0x607D, 1), self._get(0x607D, 2)
        counts = round(self.plant.x / self.mpc)
        if self.state is State.OPERATION_ENABLED and not lo <= counts <= hi:
            self._fault(0x8612, f"position {counts} counts outside 0x607D [{lo}, {hi}]")
        for cob_id, every, indices, st in self._tpdos:
            if self.sync_count % every == 0:
                self._send(cob_id, st.pack(*[self._live(i) for i in indices]))

    def _on_rpdo(self, data: bytes, now: float) -> None:
        _, indices, st, _ = self._rpdo
        values = dict(zip(indices, st.unpack_from(data)))
        if 0x6071 in values:
            self.target_permille = values[0x6071]
        if 0x6040 in values:
            self._controlword(values[0x6040])  # also applies the torque
        else:
            self._apply_torque()
        if self.state is State.OPERATION_ENABLED:
            self._rpdo_last = now

    def _dispatch(self, msg: can.Message, now: float) -> None:
        cid = msg.arbitration_id
        if msg.is_error_frame or msg.is_remote_frame:
            return
        if cid == 0x080:
            self._on_sync()
        elif self._rpdo is not None and cid == self._rpdo[0] and self.nmt_state == 5:
            self._on_rpdo(msg.data, now)
        elif cid == 0x600 + self.node_id:
            if not self.muted:
                self.node.sdo.on_request(cid, msg.data, msg.timestamp)
        elif cid == 0:
            self._on_nmt(msg.data)
        elif (cid & 0x780) == 0x700:
            host = self._get(0x1016, 1) >> 16 & 0x7F
            if cid == 0x700 + host:
                self._host_hb_last = now

    def _timers(self, now: float) -> None:
        if now >= self._hb_next:
            self._send(0x700 + self.node_id, bytes([self.nmt_state]))
            self._hb_next = now + self._get(0x1017) * 1e-3
        consumer = self._get(0x1016, 1)
        limit_ms = consumer & 0xFFFF
        last = self._host_hb_last
        if limit_ms and last is not None and now - last > limit_ms * 1e-3:
            self._host_hb_last = None  # re-armed by the next host heartbeat
            self._abort_connection(0x8130, f"no host heartbeat for {limit_ms} ms")
        if (self._rpdo is not None and self._rpdo[3] and self._rpdo_last is not None
                and now - self._rpdo_last > self._rpdo[3] * 1e-3):
            self._rpdo_last = None
            self._abort_connection(0x8250, f"no RPDO for {self._rpdo[3]} ms")

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
    (mass, damping, friction, noise, delay), stepped once per SYNC."""
    plant = open_sim(rig, realtime=False, seed=seed, **options)
    plant.enable()
    return plant


# The simulated drive's monitors run on wall-clock time in a process that is not
# real-time (a shared machine stalls it for tens of ms now and then): defaults
# that survive such stalls. A rig's [canopen] table still overrides them.
SIM_MONITOR_DEFAULTS = {"heartbeat_consumer_ms": 1000, "rpdo_timeout_ms": 500,
                        "stale_periods": 20}  # paced (--realtime) runs only


def sim_config(rig) -> CanopenConfig:
    """The rig's ``[canopen]`` table minus the hardware fields the simulation defines itself."""
    section = {**SIM_MONITOR_DEFAULTS, **rig.section("canopen")}
    for hardware_field in ("interface", "channel", "eds"):
        section.pop(hardware_field, None)
    return CanopenConfig.from_section(section, source=rig.source)


def start_sim_drive(rig, config: CanopenConfig, seed=None,
                    **options) -> tuple[SimCanopenDrive, FaultyVirtualBus]:
    """A running simulated drive on a fresh ``virtual`` channel, and the host's bus to it."""
    channel = f"labbench-sim-{uuid.uuid4().hex[:8]}"
    plant = plant_for(rig, seed, **options)
    peer = SimCanopenDrive(channel, config.node_id, plant, rig.metres_per_count,
                           rig.lever_arm_m, rig.sample_time_s).start()
    try:
        return peer, FaultyVirtualBus(channel=channel)
    except Exception:
        peer.close()
        raise


def connect_driver(rig, config, peer, host_bus, realtime: bool = False) -> CanopenDrive:
    """The real driver, opened against ``peer``; closing the driver stops the peer."""
    drive = CanopenDrive(rig, config, bus=host_bus, realtime=realtime)
    drive.peer = peer
    drive.add_close_hook(peer.close)
    try:
        return drive.open()
    except BaseException:
        host_bus.shutdown()
        peer.close()
        raise


def open_sim_canopen(rig, realtime: bool = False, seed=None, **options) -> CanopenDrive:
    """Registry factory (``--device sim-canopen``): the real driver connected to a simulated drive.

    ``seed`` and ``options`` are those of the plain simulator (``labbench.sim_backend.sim_device``),
    applied to the handle behind the drive.
    """
    config = sim_config(rig)
    peer, host_bus = start_sim_drive(rig, config, seed, **options)
    return connect_driver(rig, config, peer, host_bus, realtime)
