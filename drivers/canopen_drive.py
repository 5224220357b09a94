"""CiA 402 servo amplifier over CANopen as a ``labbench.device.Device``.

Two phases, one receiver at a time:

* **service phase** (open, enable, disable, fault reset): a python-can
  ``Notifier`` thread feeds canopen's SDO client; every state change is made by
  an SDO write of the controlword 0x6040 and confirmed by a fresh SDO read of
  the statusword 0x6041 (never a cached value); NMT state is taken from the
  drive's heartbeat, never assumed from the command sent.
* **cyclic phase** (between ``enable`` and ``disable``): no thread. Each
  ``read()`` sends SYNC (and the host heartbeat when due) and pumps the bus
  itself until the TPDO of that SYNC arrives; ``command()`` sends the RPDO.
  SYNC and heartbeat therefore exist only while the loop runs: a frozen loop
  stops both, and the drive's heartbeat consumer (0x1016) and RPDO event timer
  (0x1400:05) remove torque on their own. No python-can periodic task is used
  (they stop silently after one TX error, python-can #743).

Any fault (EMCY, TX error, error frame, bus-off, stale TPDO, drive leaving
OPERATION ENABLED, NMT state other than OPERATIONAL) zeroes the force as far as
the bus allows, latches, and raises ``DeviceFault`` with the explanation; the
latch clears only through ``reset_fault()`` (an operator action), which takes
the drive out of FAULT to SWITCH ON DISABLED and no further.

Units: position 0x6064 in encoder counts (``Rig.metres_per_count``); torque
0x6071/0x6077/0x6072 in per-mille of the motor rated torque 0x6076 (mN m,
read from the drive), force = torque / ``Rig.lever_arm_m``.
"""
from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import can
import canopen
from canopen.sdo import SdoAbortedError, SdoClient, SdoCommunicationError

from labbench.drivers import cia402, emcy
from labbench.drivers.cia402 import Command, State
from labbench.device import DeviceDescription, DeviceFault, DeviceStatus, Sample
from labbench.errors import DeviceConnectionError, DeviceError, UserError

# canopen logs SDO timeouts as errors; the driver turns them into one-line
# messages, so without logging configured they must not also reach stderr.
logging.getLogger("canopen").addHandler(logging.NullHandler())

# CiA 402 operation modes (0x6060) and their bits in supported drive modes (0x6502).
MODE_CST, MODE_PT = 10, 4
MODE_BITS = {MODE_CST: 1 << 9, MODE_PT: 1 << 3}
MODE_NAMES = {MODE_CST: "cyclic synchronous torque", MODE_PT: "profile torque"}
# NMT states as coded in heartbeat frames (CiA 301).
NMT_NAMES = {0: "INITIALISING", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}
NMT_START, NMT_PRE_OPERATIONAL = 0x01, 0x80
SYNC_ID = 0x080

# The PDO mapping (index, subindex, bits) and the matching struct layouts.
RPDO1_MAP = ((0x6071, 0, 16), (0x6040, 0, 16))  # target torque, controlword
TPDO1_MAP = ((0x6064, 0, 32), (0x6041, 0, 16), (0x6077, 0, 16))  # position, status, torque
TPDO2_MAP = ((0x606C, 0, 32),)  # velocity actual
RPDO1 = struct.Struct("<hH")
TPDO1 = struct.Struct("<iHh")
TPDO2 = struct.Struct("<i")

# SocketCAN error-frame classes (linux/can/error.h), carried in arbitration_id.
ERROR_CLASSES = {
    0x001: "TX timeout", 0x002: "lost arbitration", 0x004: "controller problem",
    0x008: "protocol violation", 0x010: "transceiver problem", 0x020: "no ACK on transmission",
    0x040: "bus off", 0x080: "bus error", 0x100: "controller restarted",
}

# Sample.flags bits of this device.
FLAG_WARNING = 1  # statusword bit 7
FLAG_INTERNAL_LIMIT = 2  # statusword bit 11 (e.g. torque limited by 0x6072)


@dataclass(frozen=True)
class CanopenConfig:
    """The ``[canopen]`` table of a rig file (see docs/canopen.md)."""

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = 1_000_000
    node_id: int = 1
    eds: str = ""  # the drive's EDS/DCF: checked for the objects used, if given
    mode: str = "auto"  # "cst", "pt" or "auto" (CST, else profile torque)
    host_node_id: int = 127  # heartbeat id of this host, watched by the drive (0x1016)
    host_heartbeat_ms: int = 20
    heartbeat_consumer_ms: int = 100
    drive_heartbeat_ms: int = 100  # 0x1017 of the drive
    rpdo_timeout_ms: int = 50  # RPDO1 event timer 0x1400:05
    quick_stop_option: int = 0  # 0x605A; 0 = disable drive function (no torque)
    fault_reaction_option: int = 0  # 0x605E; 0 = disable drive, motor free
    abort_connection_option: int = 1  # 0x6007; 1 = fault signal
    stale_periods: int = 3  # a TPDO later than this many periods is a fault
    sdo_timeout_s: float = 0.5
    lockstep_timeout_s: float = 1.0  # simulated drive: wait for the TPDO of a SYNC
    enable_timeout_s: float = 0.5  # OPERATION ENABLED must show in a TPDO within this
    velocity_tpdo_every: int = 1  # TPDO2 (0x606C) transmission type: every n-th SYNC

    _RANGES = {
        "bitrate": (10_000, 1_000_000), "node_id": (1, 127), "host_node_id": (1, 127),
        "host_heartbeat_ms": (1, 1000), "heartbeat_consumer_ms": (1, 65535),
        "drive_heartbeat_ms": (1, 65535), "rpdo_timeout_ms": (1, 65535),
        "quick_stop_option": (-32768, 32767), "fault_reaction_option": (-32768, 32767),
        "abort_connection_option": (0, 3), "stale_periods": (1, 100),
        "velocity_tpdo_every": (1, 240),
    }

    @classmethod
    def from_section(cls, section: dict, source: str = "rig") -> "CanopenConfig":
        """Validate ``rig.section("canopen")``: one ``UserError`` naming the bad field."""
        known = {f.name: f for f in fields(cls)}
        for name in section:
            if name not in known:
                raise UserError(f"{source}: unknown field [canopen] {name}")
        values = {}
        for name, value in section.items():
            default = known[name].default
            where = f"{source}: [canopen] {name}"
            if isinstance(default, str):
                if not isinstance(value, str):
                    raise UserError(f"{where} must be a string, got {value!r}")
            elif isinstance(default, float):
                ok = isinstance(value, (int, float)) and not isinstance(value, bool)
                if not ok or not math.isfinite(value) or value <= 0:
                    raise UserError(f"{where} must be a positive number, got {value!r}")
                value = float(value)
            else:
                if not isinstance(value, int) or isinstance(value, bool):
                    raise UserError(f"{where} must be an integer, got {value!r}")
                lo, hi = cls._RANGES[name]
                if not lo <= value <= hi:
                    raise UserError(f"{where} must be in [{lo}, {hi}], got {value}")
            values[name] = value
        cfg = cls(**values)
        if cfg.mode not in ("auto", "cst", "pt"):
            raise UserError(f"{source}: [canopen] mode must be auto, cst or pt, got {cfg.mode!r}")
        if cfg.host_node_id == cfg.node_id:
            raise UserError(f"{source}: [canopen] host_node_id must differ from node_id")
        if cfg.heartbeat_consumer_ms < 2 * cfg.host_heartbeat_ms:
            raise UserError(f"{source}: [canopen] heartbeat_consumer_ms must be at least "
                            "twice host_heartbeat_ms")
        if cfg.eds and not Path(cfg.eds).is_file():
            raise UserError(f"{source}: [canopen] eds file not found: {cfg.eds}")
        return cfg

    def as_dict(self) -> dict:
        return asdict(self)


# Objects the driver reads or writes; an EDS given in the rig must list them all.
REQUIRED_OBJECTS = (0x1000, 0x1016, 0x1017, 0x1018, 0x1400, 0x1600, 0x1800, 0x1801, 0x1A00,
                    0x1A01, 0x603F, 0x6007, 0x6040, 0x6041, 0x605A, 0x605E, 0x6060, 0x6061,
                    0x6064, 0x606C, 0x6071, 0x6072, 0x6076, 0x6077, 0x607D, 0x6502)


def check_eds(path: str, node_id: int) -> None:
    """The drive's EDS/DCF must describe every object the driver uses."""
    try:
        od = canopen.import_od(path, node_id)
    except Exception as exc:  # the parser raises many types on a bad file
        raise UserError(f"cannot read EDS {path}: {exc}") from None
    missing = [f"0x{i:04X}" for i in REQUIRED_OBJECTS if i not in od]
    if missing:
        raise UserError(f"EDS {path} lacks object(s) {', '.join(missing)} needed by the driver")


class CanopenDrive:
    """The driver. ``open()`` brings the node up; see the module docstring.

    ``bus``: an open python-can bus to use instead of opening one from the
    config (the simulated drive passes its virtual bus); the driver shuts it
    down on ``close()``. ``realtime``: pace SYNC at the sample time (hardware);
    otherwise SYNC goes out as soon as ``read()`` is called and the drive
    advances one period per SYNC (lock-step simulation).
    """

    def __init__(self, rig, config: CanopenConfig, bus: can.BusABC | None = None,
                 realtime: bool = True):
        self.rig, self.config, self.realtime = rig, config, realtime
        self.T = rig.sample_time_s
        self._bus = bus
        self._network: canopen.Network | None = None
        self._sdo: SdoClient | None = None
        self._close_hooks: list = []
        self._closed = False
        self._cyclic = False
        self._enable_deadline: float | None = None  # set by enable(), until disable()
        self._confirmed = False  # a TPDO showed OPERATION ENABLED since enable()
        self._state_seen = State.NOT_READY_TO_SWITCH_ON  # from the latest statusword
        self._controlword = cia402.CONTROLWORD[Command.DISABLE_VOLTAGE]  # sent with each RPDO
        self._next_tick = 0.0  # paced mode: perf_counter time of the next SYNC
        self._last_hb = -math.inf  # perf_counter time of the last host heartbeat
        self._consumer_armed = False  # 0x1016 set to watch our heartbeat
        self._fault: str | None = None
        self._hb = threading.Condition()
        self._nmt_state: int | None = None
        self._identity: dict = {}
        self._mode = 0
        self._rated_mnm = 0
        self._max_permille = 0
        self._force_to_permille = 0.0
        self._seq = -1
        # Per-cycle constants.
        self._mpc = rig.metres_per_count
        self._hb_period = config.host_heartbeat_ms * 1e-3
        self._tpdo_wait = (config.stale_periods * self.T if realtime
                           else config.lockstep_timeout_s)
        self.velocity_m_s = 0.0
        self.torque_actual_n = 0.0
        self.counters = {"error_frames": 0, "emcy": 0, "stray_frames": 0, "late_ticks": 0}
        id_ = config.node_id
        self._tpdo1_id, self._tpdo2_id, self._rpdo1_id = 0x180 + id_, 0x280 + id_, 0x200 + id_
        self._emcy_id, self._hb_id = 0x80 + id_, 0x700 + id_
        self._sync_msg = can.Message(arbitration_id=SYNC_ID, data=b"", is_extended_id=False)
        self._rpdo_msg = can.Message(arbitration_id=self._rpdo1_id, data=bytes(4),
                                     is_extended_id=False)
        self._host_hb_msg = can.Message(arbitration_id=0x700 + config.host_node_id,
                                        data=bytes([5]), is_extended_id=False)

    # ---------------------------------------------------------------- bring-up
    def open(self, timeout: float = 3.0) -> "CanopenDrive":
        """Connect, observe NMT, read identity, map PDOs, select the mode, start the node."""
        self.connect()
        try:
            self._bring_up(timeout)
        except BaseException:
            self.close()
            raise
        return self

    def connect(self) -> "CanopenDrive":
        """Bus, SDO client and receive thread only: nothing is written to the drive."""
        cfg = self.config
        if cfg.eds:
            check_eds(cfg.eds, cfg.node_id)
        if self._bus is None:
            try:
                self._bus = can.Bus(interface=cfg.interface, channel=cfg.channel,
                                    bitrate=cfg.bitrate)
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise DeviceConnectionError(f"cannot open CAN interface {cfg.interface!r} channel "
                                f"{cfg.channel!r}: {exc}") from None
        self._network = canopen.Network(self._bus)
        self._sdo = SdoClient(0x600 + cfg.node_id, 0x580 + cfg.node_id,
                              canopen.ObjectDictionary())
        self._sdo.RESPONSE_TIMEOUT = cfg.sdo_timeout_s
        self._sdo.network = self._network
        self._network.subscribe(0x580 + cfg.node_id, self._sdo.on_response)
        self._network.subscribe(self._hb_id, self._on_heartbeat)
        self._network.subscribe(self._emcy_id, self._on_emcy)
        self._start_receiver()
        return self

    def probe(self, wait_s: float = 0.3) -> dict:
        """What the node answers, read-only: identity 0x1018, device type 0x1000,
        supported modes 0x6502, state 0x6041 (error code 0x603F in FAULT) and the
        NMT state of a heartbeat heard within ``wait_s`` (if the drive sends any)."""
        with self._hb:
            self._nmt_state = None
            self._hb.wait_for(lambda: self._nmt_state is not None, wait_s)
            nmt = self._nmt_state
        info = {
            "node_id": self.config.node_id, "device_type": self._read(0x1000, 0, "<I"),
            "vendor_id": self._read(0x1018, 1, "<I"), "product_code": self._read(0x1018, 2, "<I"),
            "revision": self._read(0x1018, 3, "<I"), "serial": self._read(0x1018, 4, "<I"),
            "supported_modes": self._read(0x6502, 0, "<I"),
            "nmt_state": NMT_NAMES.get(nmt, "no heartbeat heard") if nmt is not None
            else "no heartbeat heard",
        }
        info["torque_modes"] = [MODE_NAMES[m] for m in (MODE_CST, MODE_PT)
                                if info["supported_modes"] & MODE_BITS[m]]
        state = self.drive_state()
        info["state"] = state.value
        if state is State.FAULT:
            info["error_code"] = self._error_code()
        return info

    def _bring_up(self, timeout: float) -> None:
        cfg = self.config
        self._nmt(NMT_PRE_OPERATIONAL)
        self._write(0x1017, 0, "<H", cfg.drive_heartbeat_ms)
        self._wait_nmt(127, timeout)
        device_type = self._read(0x1000, 0, "<I")
        if device_type & 0xFFFF != 402:
            raise UserError(f"node {cfg.node_id}: device type 0x1000 = 0x{device_type:08X}"
                            " is not a CiA 402 drive")
        self._identity = {
            "vendor_id": self._read(0x1018, 1, "<I"), "product_code": self._read(0x1018, 2, "<I"),
            "revision": self._read(0x1018, 3, "<I"), "serial": self._read(0x1018, 4, "<I"),
            "device_type": device_type, "supported_modes": self._read(0x6502, 0, "<I"),
        }
        self._rated_mnm = self._read(0x6076, 0, "<I")
        if self._rated_mnm <= 0:
            raise UserError(f"node {cfg.node_id}: motor rated torque 0x6076 is 0")
        # per-mille of rated torque per newton at the handle
        self._force_to_permille = self.rig.lever_arm_m / (self._rated_mnm * 1e-3) * 1000.0
        limit = round(self.rig.force_limit_n * self._force_to_permille)
        self._max_permille = min(32767, max(1, limit))
        self._map_pdos()
        self._select_mode()
        for index, sub, fmt, value in self._safety_objects():
            self._write_checked(index, sub, fmt, value)
        self._nmt(NMT_START)
        self._wait_nmt(5, timeout)

    def _map_pdos(self) -> None:
        """CiA 301 PDO mapping procedure, every object read back."""
        cfg = self.config
        pdos = (
            (0x1400, 0x1600, self._rpdo1_id, 255, cfg.rpdo_timeout_ms, RPDO1_MAP),
            (0x1800, 0x1A00, self._tpdo1_id, 1, 0, TPDO1_MAP),
            (0x1801, 0x1A01, self._tpdo2_id, cfg.velocity_tpdo_every, 0, TPDO2_MAP),
        )
        for comm, mapping, cob_id, trans_type, timer, entries in pdos:
            self._write(comm, 1, "<I", cob_id | 0x8000_0000)  # invalid while changing
            self._write(mapping, 0, "<B", 0)
            for sub, (index, subindex, bits) in enumerate(entries, start=1):
                self._write_checked(mapping, sub, "<I", index << 16 | subindex << 8 | bits)
            self._write_checked(mapping, 0, "<B", len(entries))
            self._write_checked(comm, 2, "<B", trans_type)
            self._write_checked(comm, 5, "<H", timer)
            self._write_checked(comm, 1, "<I", cob_id)

    def _select_mode(self) -> None:
        supported = self._identity["supported_modes"]
        wanted = {"cst": [MODE_CST], "pt": [MODE_PT], "auto": [MODE_CST, MODE_PT]}[self.config.mode]
        usable = [m for m in wanted if supported & MODE_BITS[m]]
        if not usable:
            names = " or ".join(MODE_NAMES[m] for m in wanted)
            raise UserError(f"node {self.config.node_id}: supported drive modes 0x6502 = "
                            f"0x{supported:08X} offers no {names} mode")
        self._mode = usable[0]
        self._write(0x6060, 0, "<b", self._mode)
        deadline = time.monotonic() + self.config.sdo_timeout_s * 4
        while (shown := self._read(0x6061, 0, "<b")) != self._mode:
            if time.monotonic() > deadline:
                raise UserError(f"node {self.config.node_id}: modes of operation display 0x6061"
                                f" shows {shown}, expected {self._mode} "
                                f"({MODE_NAMES[self._mode]}): refusing to enable")
            time.sleep(0.005)

    def _safety_objects(self) -> list[tuple[int, int, str, int]]:
        rig, cfg = self.rig, self.config
        lo, hi = rig.position_limits_m
        mpc = rig.metres_per_count
        return [
            (0x6072, 0, "<H", self._max_permille),
            (0x607D, 1, "<i", math.floor(lo / mpc)),
            (0x607D, 2, "<i", math.ceil(hi / mpc)),
            (0x605A, 0, "<h", cfg.quick_stop_option),
            (0x605E, 0, "<h", cfg.fault_reaction_option),
            (0x6007, 0, "<h", cfg.abort_connection_option),
            (0x6071, 0, "<h", 0),
        ]

    # ----------------------------------------------------------------- SDO/NMT
    def _read(self, index: int, sub: int, fmt: str) -> int:
        self._check_receiver()
        try:
            raw = self._sdo.upload(index, sub)
        except SdoAbortedError as exc:
            raise DeviceError(f"node {self.config.node_id}: SDO read of 0x{index:04X}:{sub:02X} "
                            f"refused: {exc}") from None
        except SdoCommunicationError as exc:
            self._check_receiver()
            raise DeviceConnectionError(f"node {self.config.node_id}: no answer to SDO read of "
                            f"0x{index:04X}:{sub:02X} ({exc})") from None
        size = struct.calcsize(fmt)
        return struct.unpack(fmt, bytes(raw[:size]).ljust(size, b"\0"))[0]

    def _write(self, index: int, sub: int, fmt: str, value: int) -> None:
        self._check_receiver()
        try:
            self._sdo.download(index, sub, struct.pack(fmt, value))
        except SdoAbortedError as exc:
            raise DeviceError(f"node {self.config.node_id}: drive refused writing {value} to "
                            f"0x{index:04X}:{sub:02X}: {exc}; refusing to enable") from None
        except SdoCommunicationError as exc:
            self._check_receiver()
            raise DeviceConnectionError(f"node {self.config.node_id}: no answer to SDO write of "
                            f"0x{index:04X}:{sub:02X} ({exc})") from None

    def _write_checked(self, index: int, sub: int, fmt: str, value: int) -> None:
        """Write, then read back: a drive that ignores a write is caught here."""
        self._write(index, sub, fmt, value)
        back = self._read(index, sub, fmt)
        if back != value:
            raise UserError(f"node {self.config.node_id}: object 0x{index:04X}:{sub:02X} reads "
                            f"back {back} after writing {value}: refusing to enable")

    def _nmt(self, command: int) -> None:
        self._send(can.Message(arbitration_id=0, data=bytes([command, self.config.node_id]),
                               is_extended_id=False))

    def _on_heartbeat(self, can_id, data, timestamp) -> None:
        with self._hb:
            self._nmt_state = data[0] & 0x7F if data else None
            self._hb.notify_all()

    def _wait_nmt(self, state: int, timeout: float) -> None:
        """Wait for a heartbeat that shows ``state`` (observed, not assumed)."""
        deadline = time.monotonic() + timeout
        with self._hb:
            self._nmt_state = None  # only a heartbeat sent from now on counts
            while self._nmt_state != state:
                left = deadline - time.monotonic()
                if left <= 0:
                    seen = NMT_NAMES.get(self._nmt_state, "no heartbeat")
                    raise UserError(f"node {self.config.node_id}: NMT state not "
                                    f"{NMT_NAMES[state]} within {timeout:g} s (seen: {seen})")
                self._hb.wait(left)

    def _on_emcy(self, can_id, data, timestamp) -> None:
        try:
            e = emcy.decode(data)
        except ValueError as exc:
            self._latch(f"malformed EMCY frame: {exc}")
            return
        self.counters["emcy"] += 1
        if not e.is_reset:
            self._latch(f"drive reported {e}")

    def _check_receiver(self) -> None:
        """A dead receive thread (service phase) is a latched fault, not a silent timeout."""
        notifier = self._network.notifier if self._network is not None else None
        exc = notifier.exception if notifier is not None else None
        if exc is not None:
            self._latch(f"CAN receive thread died: {exc!r}")
            raise DeviceFault(self._fault)

    def _start_receiver(self) -> None:
        # Short notifier cycle so the hand-over to the cyclic phase is quick.
        self._network.notifier = can.Notifier(self._bus, self._network.listeners, timeout=0.02)

    def _stop_receiver(self) -> None:
        if self._network is not None and self._network.notifier is not None:
            self._network.notifier.stop(timeout=1.0)
            self._check_receiver()
            self._network.notifier = None

    # ------------------------------------------------------------ state machine
    def drive_state(self) -> State:
        """Fresh statusword over SDO (service phase only)."""
        return cia402.decode_status(self._read(0x6041, 0, "<H"))

    def _drive_to(self, target: State, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        state = self.drive_state()
        while state is not target:
            cmd = cia402.command_toward(state, target)
            self._write(0x6040, 0, "<H", cia402.CONTROLWORD[cmd])
            while (new := self.drive_state()) is state:
                if time.monotonic() > deadline:
                    raise DeviceFault(f"drive stays in {state.value} after {cmd.value} "
                                      f"(target {target.value})")
                time.sleep(0.001)
            if new in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                self._latch(f"drive went to {new.value} on {cmd.value}: {self._error_code()}")
                raise DeviceFault(self._fault)
            state = new

    def _error_code(self) -> str:
        code = self._read(0x603F, 0, "<H")
        return f"error code 0x603F = 0x{code:04X} ({emcy.code_text(code)})"

    # ------------------------------------------------------------------ Device
    def describe(self) -> DeviceDescription:
        limit = (self._max_permille / self._force_to_permille if self._force_to_permille
                 else self.rig.force_limit_n)
        return DeviceDescription(
            kind="canopen", name=f"CiA 402 drive, node {self.config.node_id}",
            sample_time_s=self.T, force_limit_n=limit,
            position_limits_m=self.rig.position_limits_m,
            details={"config": self.config.as_dict(), "identity": dict(self._identity),
                     "mode": MODE_NAMES.get(self._mode, ""), "rated_torque_mnm": self._rated_mnm,
                     "max_torque_permille": self._max_permille, "paced": self.realtime,
                     "counters": dict(self.counters)},
        )

    def _start_cyclic(self) -> None:
        """Service -> cyclic phase: re-verify the drive, arm its heartbeat consumer."""
        if self._fault:
            raise self._latched()
        try:
            state = self.drive_state()
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                self._latch(f"drive is in {state.value}: {self._error_code()}")
                raise self._latched()
            for index, sub, fmt, value in self._safety_objects() + [
                    (0x1400, 5, "<H", self.config.rpdo_timeout_ms), (0x6061, 0, "<b", self._mode)]:
                if (back := self._read(index, sub, fmt)) != value:
                    raise UserError(f"node {self.config.node_id}: object 0x{index:04X}:{sub:02X}"
                                    f" is {back}, expected {value}: refusing to enable")
            cfg = self.config
            self._consumer_armed = True
            self._write_checked(0x1016, 1, "<I", cfg.host_node_id << 16 | cfg.heartbeat_consumer_ms)
        except UserError as exc:  # inside a run this is a device fault with the same words
            self._latch(str(exc))
            raise DeviceFault(self._fault) from None
        self._stop_receiver()
        self._state_seen = state
        self._controlword = cia402.CONTROLWORD[Command.SHUTDOWN]  # ready, no torque
        self._enable_deadline = None
        self._confirmed = False
        self._cyclic = True
        self._next_tick = time.perf_counter()
        self._last_hb = -math.inf

    def enable(self, timeout: float = 1.0) -> None:
        """Ask for OPERATION ENABLED (RPDO controlword); the next TPDOs must confirm it.

        Non-blocking so that the loop can enable at the sample where its gate
        opens; ``read()`` faults if the drive is not there within
        ``max(timeout, enable_timeout_s)``.
        """
        if self._fault:
            raise self._latched()
        if not self._cyclic:
            self._start_cyclic()
        if self._enable_deadline is None:
            self._enable_deadline = time.perf_counter() + max(timeout, self.config.enable_timeout_s)
        self._step_toward_enabled(self._state_seen)
        self._send(can.Message(arbitration_id=self._rpdo1_id,
                               data=RPDO1.pack(0, self._controlword), is_extended_id=False))

    def disable(self, timeout: float = 1.0) -> None:
        """Zero torque, SWITCH ON DISABLED (confirmed over SDO), heartbeat consumer off."""
        if self._closed or self._network is None:
            return
        self._zero_force(Command.DISABLE_VOLTAGE)
        if self._cyclic:
            self._cyclic = False
            self._start_receiver()
        if self._fault:
            # Perhaps unreachable: one attempt to stop the drive watching a heartbeat
            # the loop no longer sends; the fault already says what went wrong.
            if self._consumer_armed:
                self._consumer_armed = False
                try:
                    self._write(0x1016, 1, "<I", 0)
                except (UserError, DeviceError):
                    pass
            return
        try:
            self._drive_to(State.SWITCH_ON_DISABLED, timeout)
            self._write_checked(0x1016, 1, "<I", 0)
            self._consumer_armed = False
        except (UserError, DeviceError) as exc:
            self._latch(f"disable failed: {exc}")
            raise DeviceFault(self._fault) from None

    def emergency_stop(self) -> None:
        """Zero torque and power stage off at once; latch. Never raises."""
        self._zero_force(Command.DISABLE_VOLTAGE)
        self._latch("emergency stop")

    def _zero_force(self, cmd: Command) -> None:
        try:
            self._controlword = cia402.CONTROLWORD[cmd]
            if self._cyclic:
                self._bus.send(can.Message(arbitration_id=self._rpdo1_id,
                                           data=RPDO1.pack(0, self._controlword),
                                           is_extended_id=False))
            elif self._sdo is not None and self._network.notifier is not None and not self._fault:
                self._sdo.download(0x6071, 0, struct.pack("<h", 0))
                self._sdo.download(0x6040, 0, struct.pack("<H", self._controlword))
        except Exception:  # the bus may be what failed; the drive's timers take over
            pass

    def reset_fault(self, timeout: float = 1.0) -> State:
        """Operator fault reset: FAULT -> SWITCH ON DISABLED only, latch cleared."""
        if self._cyclic:
            raise DeviceFault("disable the drive before a fault reset")
        state = self.drive_state()
        if state is State.FAULT:
            self._write(0x6040, 0, "<H", 0x00)  # bit 7 low, so the next write is an edge
            self._write(0x6040, 0, "<H", cia402.CONTROLWORD[Command.FAULT_RESET])
            deadline = time.monotonic() + timeout
            while (state := self.drive_state()) is State.FAULT:
                if time.monotonic() > deadline:
                    raise DeviceFault(f"drive stays in FAULT after fault reset: "
                                      f"{self._error_code()}")
                time.sleep(0.002)
        self._fault = None
        return state

    def status(self) -> DeviceStatus:
        state = ("closed" if self._closed else "fault" if self._fault
                 else "enabled" if self._cyclic else "disabled")
        return DeviceStatus(state, self._fault, dict(self.counters))

    def _latched(self) -> DeviceFault:
        return DeviceFault(f"latched fault: {self._fault}; an operator must reset it "
                           "(labbench devices --fault-reset)")

    def _latch(self, reason: str) -> None:
        if not self._fault:
            self._fault = reason

    def _fail(self, reason: str):
        self._latch(reason)
        self._zero_force(Command.DISABLE_VOLTAGE)
        raise DeviceFault(self._fault)

    def _send(self, msg: can.Message) -> None:
        try:
            self._bus.send(msg, timeout=self.T)
        except can.CanError as exc:
            self._fail(f"CAN transmit error: {exc}")

    def read(self, timeout: float) -> Sample:
        return Sample(*self.read_raw(timeout))

    def read_raw(self, timeout: float) -> tuple:
        """SYNC, then the TPDO of that SYNC: ``(seq, t_s, position_m, flags)``.

        The position is the drive's at the SYNC, i.e. at the start of the period.
        """
        if self._fault:
            raise DeviceFault(self._fault) if self._cyclic else self._latched()
        if not self._cyclic:
            self._start_cyclic()
        now = time.perf_counter()
        if self.realtime:
            if now < self._next_tick:
                time.sleep(self._next_tick - now)
                now = time.perf_counter()
            elif now > self._next_tick + self.T:
                self.counters["late_ticks"] += 1
                self._next_tick = now  # re-phase instead of bursting SYNCs to catch up
            self._next_tick += self.T
        wait = min(self._tpdo_wait, timeout)
        bus = self._bus
        if bus.state is can.BusState.ERROR:
            self._fail("CAN controller is bus-off (error state)")
        self._send(self._sync_msg)
        if now - self._last_hb >= self._hb_period:
            self._send(self._host_hb_msg)
            self._last_hb = now
        deadline = now + wait
        while True:
            left = deadline - time.perf_counter()
            msg = bus.recv(left if left > 0 else 0.0)
            if msg is None:
                self._fail(f"stale TPDO: no answer to SYNC {self._seq + 1} within "
                           f"{wait * 1e3:.3g} ms")
            if msg.arbitration_id == self._tpdo1_id and not msg.is_error_frame:
                counts, status, torque = TPDO1.unpack_from(msg.data)
                break
            self._dispatch(msg)
            if self._fault:  # EMCY, error frame or NMT change seen while waiting
                self._fail(self._fault)
        if status & 0x6F != 0x27:  # CiA 402 coding of OPERATION ENABLED
            self._not_enabled(status)
        elif self._enable_deadline is not None and not self._confirmed:
            self._confirmed = True
            self._state_seen = State.OPERATION_ENABLED
        self._seq += 1
        self.torque_actual_n = torque / self._force_to_permille
        flags = (FLAG_WARNING if status & cia402.SW_WARNING else 0) | (
            FLAG_INTERNAL_LIMIT if status & cia402.SW_INTERNAL_LIMIT else 0)
        return self._seq, self._seq * self.T, counts * self._mpc, flags

    def _not_enabled(self, status: int) -> None:
        """A TPDO statusword other than OPERATION ENABLED: fault unless still on the way."""
        try:
            state = cia402.decode_status(status)
        except cia402.UnknownStatusword as exc:
            self._fail(str(exc))
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE) or self._confirmed:
            self._fail(f"drive left OPERATION ENABLED: now {state.value} "
                       f"(statusword 0x{status:04X})")
        self._state_seen = state
        if self._enable_deadline is not None:
            if time.perf_counter() > self._enable_deadline:
                self._fail(f"drive did not reach OPERATION ENABLED: still {state.value} "
                           f"(statusword 0x{status:04X})")
            self._step_toward_enabled(state)

    def _step_toward_enabled(self, state: State) -> None:
        """Controlword of the next step to OPERATION ENABLED (sent with the next RPDO)."""
        try:
            cmd = cia402.command_toward(state, State.OPERATION_ENABLED)
        except cia402.NoRoute as exc:
            self._fail(f"cannot enable: {exc}")
        self._controlword = cia402.CONTROLWORD[cmd or Command.ENABLE_OPERATION]

    def _dispatch(self, msg: can.Message) -> None:
        """Everything but TPDO1 in the cyclic phase."""
        if msg.is_error_frame:
            self.counters["error_frames"] += 1
            cls = [t for bit, t in ERROR_CLASSES.items() if msg.arbitration_id & bit]
            self._latch(f"CAN error frame ({', '.join(cls) or 'unspecified'})")
            return
        cid = msg.arbitration_id
        if cid == self._tpdo2_id:
            self.velocity_m_s = TPDO2.unpack_from(msg.data)[0] * self.rig.metres_per_count
        elif cid == self._emcy_id:
            self._on_emcy(cid, msg.data, msg.timestamp)
        elif cid == self._hb_id:
            state = msg.data[0] & 0x7F if msg.data else None
            if state != 5:
                self._latch(f"drive NMT state is {NMT_NAMES.get(state, state)}, not OPERATIONAL")
        else:
            self.counters["stray_frames"] += 1

    def command(self, force_n: float) -> None:
        """RPDO: torque held by the drive from now until the next command.

        Outside a run (or after a fault) only zero is accepted, and sends nothing.
        """
        if self._fault or not self._cyclic:
            if force_n != 0.0:
                raise DeviceFault(self._fault or "command() outside a run (no read() yet)")
            return
        p = round(force_n * self._force_to_permille)
        p = self._max_permille if p > self._max_permille else (
            -self._max_permille if p < -self._max_permille else p)
        msg = self._rpdo_msg  # reused: buses copy or serialise a frame when sending it
        msg.data = RPDO1.pack(p, self._controlword)
        self._send(msg)

    def identity(self) -> dict:
        return dict(self._identity)

    def add_close_hook(self, hook) -> None:
        """Called after the bus is shut down (the simulated drive stops here)."""
        self._close_hooks.append(hook)

    def close(self) -> None:
        if self._closed:
            return
        try:
            if self._cyclic:
                self.disable()
        except Exception:  # closing must not fail; the drive's own timers remove torque
            pass
        self._closed = True
        self._cyclic = False
        try:
            self._stop_receiver()
        except Exception:
            pass
        if self._bus is not None:
            self._bus.shutdown()
        for hook in self._close_hooks:
            hook()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def frame_bits(n_bytes: int) -> tuple[int, int]:
    """(nominal, worst-case) bits on the wire of a CAN 2.0A data frame with ``n_bytes``.

    47 + 8n bits: SOF, 11-bit id, RTR, IDE, r0, DLC, data, CRC 15 + delimiter, ACK
    slot + delimiter, EOF 7, intermission 3 (ISO 11898-1); bit stuffing adds at
    most one bit per four after the first in the 34 + 8n bits from SOF to CRC.
    """
    nominal = 47 + 8 * n_bytes
    return nominal, nominal + (34 + 8 * n_bytes - 1) // 4


def bus_load(config: CanopenConfig, sample_time_s: float) -> dict:
    """Bus load of this driver's traffic at ``config.bitrate`` (fraction of capacity)."""
    rate = 1.0 / sample_time_s
    traffic = [  # (name, data bytes, frames per second)
        ("SYNC", 0, rate),
        ("TPDO1 0x6064+0x6041+0x6077", 8, rate),
        ("TPDO2 0x606C", 4, rate / config.velocity_tpdo_every),
        ("RPDO1 0x6071+0x6040", 4, rate),
        ("host heartbeat", 1, 1000.0 / config.host_heartbeat_ms),
        ("drive heartbeat", 1, 1000.0 / config.drive_heartbeat_ms),
    ]
    nominal = sum(frame_bits(n)[0] * f for _, n, f in traffic)
    worst = sum(frame_bits(n)[1] * f for _, n, f in traffic)
    return {"bitrate": config.bitrate, "frames": [(name, n, f) for name, n, f in traffic],
            "bits_per_s_nominal": nominal, "bits_per_s_worst": worst,
            "load_nominal": nominal / config.bitrate, "load_worst": worst / config.bitrate}


def open_canopen(rig, realtime: bool = True, seed=None, **options) -> CanopenDrive:
    """Registry factory (``--device canopen``): the drive described by ``rig``'s ``[canopen]``.

    ``seed`` is accepted (and unused) so that every device opens with the same call.
    """
    if options:
        raise UserError(f"canopen device takes no option(s) {', '.join(sorted(options))}")
    config = CanopenConfig.from_section(rig.section("canopen"), source=rig.source)
    return CanopenDrive(rig, config, realtime=realtime).open()
