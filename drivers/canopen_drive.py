"""CiA 402 servo amplifier over CANopen as a ``labbench.device.Device``.

Vendor-neutral: what the drive has is surveyed read-only first (from the
drive, and from its EDS/DCF when the rig names one, ``canopen_objects``),
assessed (``canopen_check``: every obstacle at once, before any write; the
fallbacks for missing optional objects as warnings, which the session
records) and the PDO layout planned (``canopen_pdo``). Then two phases, one
receiver at a time:

* **service phase** (open, enable, disable, fault reset): a python-can
  ``Notifier`` thread feeds canopen's SDO client (``canopen_sdo``); every
  state change is an SDO write of the controlword 0x6040 confirmed by a fresh
  SDO read of the statusword 0x6041; NMT state is taken from the drive's
  heartbeat or its node-guarding answers, never assumed from the command sent.
* **cyclic phase** (between ``enable`` and ``disable``): no thread. Each
  ``read()`` sends SYNC (and the host heartbeat or guarding request when due)
  and pumps the bus itself until every TPDO of that SYNC arrives, within
  ``stale_periods`` of the moment the SYNC actually went out (a SYNC the host
  sends late is the host's overrun, counted in ``late_syncs``, not a silent
  drive); ``command()`` sends the RPDO(s). SYNC and heartbeat/guarding exist
  only while the loop runs: a frozen loop stops them, and the drive's
  heartbeat consumer 0x1016 or life guarding 0x100C/0x100D, and its RPDO
  event timer 0x1400:05 if it has one, remove torque on their own. No
  python-can periodic task is used (they stop silently after one TX error,
  python-can #743).

The drive is NMT OPERATIONAL and watches the host only in the cyclic phase:
``enable`` arms the watch (0x1016:01, 0x100C, 0x14xx:05) in PRE-OPERATIONAL,
then starts the node; ``disable`` winds down in the reverse order, each watch
fed until it is off (``disable`` says how), so no run ends in an EMCY; ``close``
writes back the values the survey found in the objects the driver set.

Any fault (EMCY, TX error, error frame, bus-off, stale TPDO, drive leaving
OPERATION ENABLED, NMT state other than OPERATIONAL, leaving the host-side
position window) zeroes the force as far as the bus allows, latches, and
raises ``DeviceFault`` with the explanation; the latch clears only through
``reset_fault()`` (an operator action), which takes the drive out of FAULT to
SWITCH ON DISABLED and no further.

Units: position 0x6064 (or the rig's ``position`` object) in encoder counts
(``Rig.metres_per_count``); the set point 0x6071 in per-mille of the motor rated
torque (0x6076 in mN m from the drive, else from the rig), or a vendor mode's
own object in its unit (``[canopen.modes]``: mA x the torque constant, ...);
force at the handle = joint torque / ``Rig.lever_arm_m``. The record is SI at
the handle whatever the set point's unit.
"""
from __future__ import annotations

import logging
import math
import struct
import threading
import time

import can
import canopen

from labbench.device import (ESTOP_STATE, DeviceDescription, DeviceFault, DeviceStatus,
                             Sample)
from labbench.drivers import cia402, emcy
from labbench.drivers.can_echo import EchoFreeBus
from labbench.drivers.can_trace import TracedBus
from labbench.drivers.canopen_check import Assessment, assess
from labbench.drivers.canopen_config import SOFTWARE_BUSES, CanopenConfig
from labbench.drivers.canopen_objects import object_name, read_eds, survey
from labbench.drivers.canopen_pdo import SYNC_ID
from labbench.drivers.canopen_sdo import MatchingSdoClient, NoAnswer, Sdo, hexval, where
from labbench.drivers.cia402 import Command, State
from labbench.errors import DeviceConnectionError, DeviceError, UserError
from labbench.loop.realtime import sleep_until

# canopen logs SDO timeouts as errors; the driver turns them into one-line
# messages, so without logging configured they must not also reach stderr.
logging.getLogger("canopen").addHandler(logging.NullHandler())

# NMT states as coded in heartbeat and node-guarding frames (CiA 301).
NMT_NAMES = {0: "INITIALISING", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}
NMT_START, NMT_PRE_OPERATIONAL = 0x01, 0x80
NMT_TIMEOUT_S = 3.0  # for a heartbeat or guarding answer showing the NMT state asked for
AFTER_FAULT_SDO_S = 0.1  # an answer after a fault: a drive that answers does so in ms

# SocketCAN error-frame classes (linux/can/error.h), carried in arbitration_id.
ERROR_CLASSES = {
    0x001: "TX timeout", 0x002: "lost arbitration", 0x004: "controller problem",
    0x008: "protocol violation", 0x010: "transceiver problem", 0x020: "no ACK on transmission",
    0x040: "bus off", 0x080: "bus error", 0x100: "controller restarted",
}

ESTOP_REASON = "emergency stop"  # the latched fault of emergency_stop()

# Sample.flags bits of this device.
FLAG_WARNING = 1  # statusword bit 7
FLAG_INTERNAL_LIMIT = 2  # statusword bit 11 (e.g. torque limited by 0x6072)


class CanopenDrive:
    """The driver. ``open()`` brings the node up; see the module docstring.

    ``bus``: an open python-can bus to use instead of opening one from the
    config (the simulated drive passes its virtual bus); the driver shuts it
    down on ``close()``. ``realtime``: pace SYNC at the sample time (hardware);
    otherwise SYNC goes out as soon as ``read()`` is called and the drive
    advances one period per SYNC (lock-step simulation). ``can_log``: a file
    that receives every frame (``drivers/can_trace.py``). ``simulated``: what stands in
    for the drive ("" on hardware), said by ``describe()``.
    """

    def __init__(self, rig, config: CanopenConfig, bus: can.BusABC | None = None,
                 realtime: bool = True, can_log: str | None = None, simulated: str = ""):
        self.rig, self.config, self.realtime, self.can_log = rig, config, realtime, can_log
        self.simulated = simulated
        self.T = rig.sample_time_s
        self._bus = bus
        self._network: canopen.Network | None = None
        self._sdo: Sdo | None = None
        self.dictionary = None  # what the drive has (canopen_objects.Dictionary), after survey()
        self.assessment: Assessment | None = None
        self._close_hooks: list = []
        self._closed = False
        self._cyclic = False
        self._enable_deadline: float | None = None  # set by enable(), until disable()
        self._after_fault_for: str | None = None  # the fault _after_fault last handled
        self._confirmed = False  # a TPDO showed OPERATION ENABLED since enable()
        self._state_seen = State.NOT_READY_TO_SWITCH_ON  # from the latest statusword
        self._controlword = cia402.CONTROLWORD[Command.DISABLE_VOLTAGE]  # sent with each RPDO
        self._next_tick = 0.0  # paced mode: perf_counter time of the next SYNC
        self._watch_armed = False  # the drive watches our heartbeat / guarding / RPDOs
        self._operational = False  # NMT OPERATIONAL as this host last set and saw it
        self._found: dict = {}  # (index, sub) -> the survey's value of an object the driver sets
        self._fault: str | None = None
        self._last_emcy: emcy.Emcy | None = None
        self._hb = threading.Condition()
        self._nmt_state: int | None = None
        self._identity: dict = {}
        self._mode = None
        self._seq = -1
        self._mpc = rig.position_per_count  # signed: [rig] position_sign
        self._tpdo_wait = (config.stale_periods * self.T if realtime
                           else config.lockstep_timeout_s)
        self.timing_log: list | None = None  # labbench.device.TimingProbe (preflight)
        self._sync_wall = 0.0  # time.time() of the last SYNC sent while timing_log is on
        self._window: tuple[int, int] | None = None  # host-side position window [counts]
        self._guard_life = 0.0  # guarding answers expected within [s] (0: not guarded)
        self._last_answer = 0.0  # perf_counter time of the last node-guarding answer
        self.velocity_m_s = 0.0
        self.torque_actual_n = math.nan
        # late_syncs: SYNCs the host sent more than half a period after their time (its
        # overrun); late_ticks: of those, the ones after which the pacing re-phased.
        self.counters = {"error_frames": 0, "emcy": 0, "stray_frames": 0, "late_ticks": 0,
                         "late_syncs": 0}
        id_ = config.node_id
        self._emcy_id, self._hb_id = 0x80 + id_, 0x700 + id_
        self._sync_msg = can.Message(arbitration_id=SYNC_ID, data=b"", is_extended_id=False)
        self._periodic: list = []  # [message, period s, last sent] of the cyclic phase
        self._decoders: dict = {}  # TPDO COB-ID -> (struct, roles, bit of the SYNC set or 0)
        self._all_sync = 0
        self._rpdos: list = []  # (message, struct, roles)
        self._vals: dict = {}

    # ---------------------------------------------------------------- bring-up
    def open(self, timeout: float = 3.0) -> "CanopenDrive":
        """Connect, survey and assess (no write), then configure and start the node."""
        self.connect()
        try:
            self._bring_up(timeout)
        except NoAnswer as exc:  # every other hardware error says what to check: so does this
            self.close()
            raise NoAnswer(f"{exc}: {self._what_to_check()}") from None
        except BaseException:
            self.close()
            raise
        return self

    def _what_to_check(self) -> str:
        """Where a drive that answers nothing is usually lost, for the bus opened."""
        cfg = self.config
        bus = ", ".join(f"{k} {v}" for k, v in cfg.bus_kwargs().items()
                        if k in ("interface", "channel", "bitrate")) or "python-can's own configuration"
        if cfg.interface in SOFTWARE_BUSES:
            return (f"{cfg.interface} is a software bus (no adapter, no wire): only a program on "
                    "this computer, such as labbench's simulated drive, answers on it; choose the "
                    "drive's adapter as the CAN bus")
        return (f"check that the drive is powered and wired to this bus ({bus}), that its node "
                f"id is {cfg.node_id} ([canopen] node_id), that its bitrate is the bus's, that "
                "the bus is terminated (120 ohm at each end), and that the CAN bus chosen on the "
                "Device panel (or [canopen] interface and channel) is the drive's")

    def connect(self) -> "CanopenDrive":
        """Bus, SDO client and receive thread only: nothing is sent to the drive."""
        cfg = self.config
        self._file = read_eds(cfg.eds, cfg.node_id) if cfg.eds else None
        if self._bus is None:
            kwargs = cfg.bus_kwargs()
            try:
                self._bus = can.Bus(**kwargs)
            except (can.CanError, OSError, ValueError, ImportError, TypeError) as exc:
                if "interface" not in kwargs and "None" in str(exc):
                    raise DeviceConnectionError(
                        "no CAN interface: [canopen] names none and python-can's own "
                        "configuration (~/.canrc, CAN_INTERFACE) has none") from None
                shown = ", ".join(f"{k}={v!r}" for k, v in kwargs.items())
                raise DeviceConnectionError(f"cannot open CAN bus ({shown}): {exc}") from None
            if type(self._bus).__name__ == "UdpMulticastBus":  # hands its frames back
                self._bus = EchoFreeBus(self._bus)  # else each is a stray frame
        if self.can_log:
            self._bus = TracedBus(self._bus, self.can_log)
        self._network = canopen.Network(self._bus)
        client = MatchingSdoClient(0x600 + cfg.node_id, 0x580 + cfg.node_id,
                                   canopen.ObjectDictionary())
        client.RESPONSE_TIMEOUT = cfg.sdo_timeout_s
        client.network = self._network
        self._sdo = Sdo(client, cfg.node_id, self._check_receiver, object_name)
        self._network.subscribe(0x580 + cfg.node_id, client.on_response)
        self._network.subscribe(self._hb_id, self._on_heartbeat)
        self._network.subscribe(self._emcy_id, self._on_emcy)
        self._start_receiver()
        return self

    def survey(self, wake: bool = False) -> Assessment:
        """Read-only: what the drive has (and its file says), and the assessment.

        ``wake`` (bring-up only): a node that does not answer may be STOPPED,
        which answers no SDO: NMT pre-operational and one more try.
        """
        extra = self._rig_objects()
        try:
            d = survey(self._sdo, self._file, extra)
        except DeviceConnectionError:
            if not wake:
                raise
            self._nmt(NMT_PRE_OPERATIONAL)
            d = survey(self._sdo, self._file, extra)
        self.dictionary = d
        self.assessment = assess(d, self.config, self.rig, self._file)
        return self.assessment

    def _rig_objects(self) -> list[tuple[int, int, int | None]]:
        """(index, sub, the rig's data type or None) of the objects the rig names: the set
        points of its modes, the position and velocity objects."""
        cfg = self.config
        out = [(*m.command, m.data_type) for m in cfg.torque_modes()]
        return out + [(*cfg.position_ref, None), (*cfg.velocity_ref, None)]

    def probe(self, wait_s: float = 0.3) -> dict:
        """Read-only capability report: identity, device type, modes, 402 state, NMT
        state, error history 0x1003, PDO plan, watchdog, bus load, obstacles, warnings."""
        a = self.survey()
        d = self.dictionary
        nmt = self._observe_nmt(wait_s)
        info = {"node_id": self.config.node_id, "source": d.source, **self._ident(),
                "torque_modes": [m.text for m in a.modes],
                "nmt_state": NMT_NAMES.get(nmt, f"0x{nmt:02X}") if nmt is not None
                else "no heartbeat or guarding answer",
                "capabilities": dict(a.capabilities), "plan": a.plan.lines(),
                "bus_load": a.bus_load(self.config, self.T),
                "error_history": self._error_history(),
                "obstacles": list(a.obstacles), "warnings": list(a.warnings),
                "rig_lines": list(a.rig_lines)}
        if d.has(0x6041, 0):
            state = self.drive_state()
            info["state"] = state.value
            if state is State.FAULT:
                info["error_code"] = self._error_code()
        else:
            info["state"] = "absent (no statusword 0x6041)"
        return info

    def _ident(self) -> dict:
        d = self.dictionary
        return {"device_type": d.value(0x1000), "vendor_id": d.value(0x1018, 1),
                "product_code": d.value(0x1018, 2), "revision": d.value(0x1018, 3),
                "serial": d.value(0x1018, 4), "supported_modes": d.value(0x6502)}

    def _bring_up(self, timeout: float) -> None:
        a = self.survey(wake=True)
        a.refuse()  # every obstacle in one message, before any write
        self._identity = self._ident()
        self._mode = None
        self._nmt(NMT_PRE_OPERATIONAL)
        self._operational = False
        d = self.dictionary
        for index, sub, value in self._service_values() + self._watch_values(armed=False):
            e = d.get(index, sub)
            if e is not None and e.value is not None and e.writable:
                self._found[(index, sub)] = e.value
            self._write_checked(index, sub, self._fmt(index, sub), value)
        self._wait_nmt(127, timeout)
        self._map_pdos()
        self._select_mode()
        for index, sub, fmt, value in a.writes:
            self._write_checked(index, sub, fmt, value)
        lo, hi = self.rig.position_limits_m
        ends = sorted((lo / self._mpc, hi / self._mpc))  # a negative position_sign mirrors it
        self._window = None if a.has.get((0x607D, 1)) else (math.floor(ends[0]), math.ceil(ends[1]))
        self._setup_cyclic()

    def _fmt(self, index: int, sub: int) -> str:
        e = self.dictionary.get(index, sub)
        return "<" + (e.fmt if e is not None and e.fmt else "I")

    def _service_values(self) -> list[tuple[int, int, int]]:
        """What the host needs from the drive in every phase: its heartbeat 0x1017 (how the
        host sees the NMT state) and the life time factor 0x100D of guarding.

        Guarded, a drive whose heartbeat producer is on gets it off: a node with a producer
        heartbeat time other than 0 uses the heartbeat, not node guarding (CiA 301), and
        answers and watches nothing (CANopenNode's guarding slave is off then)."""
        a, cfg = self.assessment, self.config
        out = []
        if a.nmt_by == "heartbeat":
            out.append((0x1017, 0, cfg.drive_heartbeat_ms))
        elif "guarding" in (a.watchdog, a.nmt_by) and self.dictionary.value(0x1017):
            out.append((0x1017, 0, 0))
        if "guarding" in (a.watchdog, a.nmt_by):
            out.append((0x100D, 0, cfg.life_time_factor))
        return out

    def _watch_values(self, armed: bool) -> list[tuple[int, int, int]]:
        """The drive's watch on the host: heartbeat consumer 0x1016:01, guard time 0x100C
        (life guarding), RPDO event timers 0x14xx:05; all 0 (off) unless ``armed``.

        Each starts watching only with the host's first frame after it is set (CiA 301:
        heartbeat consumer, life guarding, RPDO deadline monitoring), so arming them before
        the cyclic phase starts is safe.
        """
        a, cfg = self.assessment, self.config
        out = []
        if a.watchdog == "heartbeat":
            out.append((0x1016, 1, cfg.host_node_id << 16 | cfg.heartbeat_consumer_ms
                        if armed else 0))
        if "guarding" in (a.watchdog, a.nmt_by):
            guard = cfg.guard_time_ms if armed and a.watchdog == "guarding" else 0
            out.append((0x100C, 0, guard))
        out += [(p.comm, 5, p.event_timer_ms if armed else 0)
                for p in a.plan.rpdos if p.event_timer_ms]
        return out

    def _map_pdos(self) -> None:
        """CiA 301 procedure: PDO invalid, count 0, entries, count, type, timer, valid."""
        plan = self.assessment.plan
        for comm, cob_id in plan.disable:
            self._write_checked(comm, 1, "<I", cob_id | 0x8000_0000)
        for p in plan.rpdos + plan.tpdos:
            if p.write_mapping:
                if not p.cob_fixed:
                    self._write(p.comm, 1, "<I", p.cob_id | 0x8000_0000)
                self._write(p.mapping, 0, "<B", 0)
                for k, e in enumerate(p.entries, 1):
                    try:
                        self._write_checked(p.mapping, k, "<I", e.code)
                    except (DeviceError, UserError) as exc:
                        raise UserError(f"node {self.config.node_id}: drive refused mapping "
                                        f"0x{e.index:04X} ({object_name(e.index)}) into {p.name}"
                                        f" ({where(p.mapping, k)}): {exc}") from None
                self._write_checked(p.mapping, 0, "<B", len(p.entries))
            if p.write_trans:
                self._write_checked(p.comm, 2, "<B", p.trans_type)
            if p.tx and p.event_timer_ms is not None:  # an RPDO's is the watch (enable arms it)
                self._write_checked(p.comm, 5, "<H", p.event_timer_ms)
            if not p.cob_fixed:
                self._write_checked(p.comm, 1, "<I", p.cob_id)
            elif self._read(p.comm, 1, "<I") & 0x8000_0000:
                raise UserError(f"node {self.config.node_id}: {p.name} is switched off and its "
                                f"COB-ID {where(p.comm, 1)} is read-only")

    def _select_mode(self) -> None:
        """The first torque mode the drive takes (``auto``: CST, profile torque, vendor)."""
        refusals = []
        display = self._mode_display()
        for m in self.assessment.modes:
            try:
                self._write(0x6060, 0, "<b", m.code)
            except DeviceError as exc:
                refusals.append(exc)
                continue
            deadline = time.monotonic() + self.config.sdo_timeout_s * 4
            while display is not None and (shown := self._read(display, 0, "<b")) != m.code:
                if time.monotonic() > deadline:
                    raise UserError(f"node {self.config.node_id}: 0x{display:04X}:00 "
                                    f"({object_name(display)}) shows {shown}, expected "
                                    f"{m.code} ({m.text}): refusing to enable")
                time.sleep(0.005)
            self._mode = m
            return
        if len(refusals) == 1:
            raise refusals[0]
        raise DeviceError(f"node {self.config.node_id}: no torque mode accepted: "
                          + "; ".join(str(r) for r in refusals))

    def _mode_display(self) -> int | None:
        """Where the drive shows its mode: 0x6061, else 0x6060 read back, else nowhere (a
        write-only 0x6060 and no 0x6061: the write's acknowledgment is all there is)."""
        for index in (0x6061, 0x6060):
            e = self.dictionary.get(index, 0)
            if e is not None and e.readable:
                return index
        return None

    def _setup_cyclic(self) -> None:
        """Per-cycle tables from the plan: TPDO decoders, RPDO frames, periodic frames."""
        plan, cfg = self.assessment.plan, self.config
        self._torque_n = self.assessment.torque_per_permille_n  # 0x6077's newtons per unit
        self._decoders, self._all_sync = {}, 0
        for k, p in enumerate(plan.tpdos):
            bit = 1 << k if p.trans_type == 1 else 0
            self._all_sync |= bit
            self._decoders[p.cob_id] = (p.struct(), tuple(p.roles()), bit)
        self._rpdos = [(can.Message(arbitration_id=p.cob_id, data=bytes(p.n_bytes),
                                    is_extended_id=False), p.struct(), tuple(p.roles()))
                       for p in plan.rpdos]
        self._periodic = []
        a = self.assessment
        if a.watchdog == "heartbeat":
            self._periodic.append([can.Message(arbitration_id=0x700 + cfg.host_node_id,
                                               data=bytes([5]), is_extended_id=False),
                                   cfg.host_heartbeat_ms * 1e-3, -math.inf])
        if "guarding" in (a.watchdog, a.nmt_by):
            self._periodic.append([self._guard_request(), cfg.guard_time_ms * 1e-3, -math.inf])
        self._guard_life = (cfg.guard_time_ms * cfg.life_time_factor * 1e-3
                            if a.nmt_by == "guarding" else 0.0)

    def _guard_request(self) -> can.Message:
        return can.Message(arbitration_id=self._hb_id, is_remote_frame=True, dlc=1,
                           is_extended_id=False)

    # ----------------------------------------------------------------- SDO/NMT
    def _read(self, index: int, sub: int, fmt: str) -> int:
        return self._sdo.read(index, sub, fmt)

    def _write(self, index: int, sub: int, fmt: str, value: int) -> None:
        self._sdo.write(index, sub, fmt, value)

    def _write_checked(self, index: int, sub: int, fmt: str, value: int) -> None:
        """Write and read back; a write-only object is only written (nothing to read)."""
        e = self.dictionary.get(index, sub) if self.dictionary is not None else None
        if e is not None and not e.readable:
            self._sdo.write(index, sub, fmt, value)
        else:
            self._sdo.write_checked(index, sub, fmt, value)

    def _nmt_msg(self, command: int) -> can.Message:
        return can.Message(arbitration_id=0, data=bytes([command, self.config.node_id]),
                           is_extended_id=False)

    def _nmt(self, command: int) -> None:
        self._send(self._nmt_msg(command))

    def _on_heartbeat(self, can_id, data, timestamp) -> None:
        with self._hb:
            self._nmt_state = data[0] & 0x7F if data else None
            self._hb.notify_all()

    def _observe_nmt(self, timeout: float) -> int | None:
        """The NMT state shown by a heartbeat or guarding answer from now on, or None."""
        guarding = self.assessment is not None and self.assessment.nmt_by == "guarding"
        deadline = time.monotonic() + timeout
        with self._hb:
            self._nmt_state = None  # only a frame sent from now on counts
            while self._nmt_state is None:
                if guarding:
                    self._send(self._guard_request())
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._hb.wait(min(left, 0.05) if guarding else left)
            return self._nmt_state

    def _wait_nmt(self, state: int, timeout: float) -> None:
        """Wait for a heartbeat or guarding answer that shows ``state`` (observed, not assumed)."""
        deadline = time.monotonic() + timeout
        seen = None
        while (seen := self._observe_nmt(max(0.0, deadline - time.monotonic()))) != state:
            if time.monotonic() >= deadline:
                shown = NMT_NAMES.get(seen, "no heartbeat or guarding answer")
                raise UserError(f"node {self.config.node_id}: NMT state not "
                                f"{NMT_NAMES[state]} within {timeout:g} s (seen: {shown})")

    def _on_emcy(self, can_id, data, timestamp) -> None:
        try:
            e = emcy.decode(data)
        except ValueError as exc:
            self._latch(f"malformed EMCY frame: {exc}")
            return
        self.counters["emcy"] += 1
        if not e.is_reset:
            self._last_emcy = e
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
        """What explains a FAULT: 0x603F, else the last EMCY, 0x1001 and 0x1003."""
        d = self.dictionary
        if d is None or d.has(0x603F, 0):
            raw, _ = self._sdo.attempt(0x603F, 0)
            if raw:
                code = struct.unpack("<H", raw[:2].ljust(2, b"\0"))[0]
                return f"error code 0x603F = 0x{code:04X} ({emcy.code_text(code)})"
        parts = [f"last EMCY 0x{self._last_emcy.code:04X} ({self._last_emcy.text})"] \
            if self._last_emcy else []
        register, _ = self._sdo.attempt(0x1001, 0)
        if register:
            parts.append(f"error register 0x1001 = 0x{register[0]:02X}")
        history = self._error_history()
        if history:
            parts.append(f"latest error 0x1003:01 = 0x{history[0] & 0xFFFF:04X} "
                         f"({emcy.code_text(history[0] & 0xFFFF)})")
        return "; ".join(parts) or "no error code (0x603F and 0x1003 absent, no EMCY heard)"

    def _error_history(self) -> list[int]:
        """Pre-defined error field 0x1003, newest first (empty when absent or unreadable).

        Entries 1..count (0x1003:00) only: above the count a drive may answer abort
        0x08000024 "no data available" (CiA 301; CANopenNode does). A refused entry (the
        count changed meanwhile) ends the list.
        """
        count, _ = self._sdo.attempt(0x1003, 0)
        if not count:
            return []
        out = []
        for sub in range(1, min(count[0], 8) + 1):
            raw, _ = self._sdo.attempt(0x1003, sub)
            if raw is None:
                break
            out.append(struct.unpack("<I", raw[:4].ljust(4, b"\0"))[0])
        return out

    # ------------------------------------------------------------------ Device
    def describe(self) -> DeviceDescription:
        a = self.assessment
        ftc = a.force_to_command if a is not None else 0.0
        limit = a.max_command / ftc if ftc else self.rig.force_limit_n
        details = {"config": self.config.as_dict(), "identity": dict(self._identity),
                   "mode": self._mode.text if self._mode else "", "paced": self.realtime,
                   "counters": dict(self.counters)}
        if a is not None:
            details.update(host_silence_limit=self._watch_limit(),
                rated_torque_mnm=a.rated_mnm, torque_scale=a.capabilities.get("torque scale"),
                set_point=a.capabilities.get("torque object"), max_set_point=a.max_command,
                position_object=self.config.position,
                max_torque_permille=a.max_permille, watchdog=a.capabilities.get("watched by"),
                pdo_plan=a.plan.lines(), bus_load=a.bus_load(self.config, self.T)["load_nominal"],
                warnings=list(a.warnings), dictionary=a.source)
        if self.can_log:
            details["can_log"] = self.can_log
        delay, why = self._own_delay()
        return DeviceDescription(
            kind="canopen", name=f"{'simulated ' if self.simulated else ''}CiA 402 drive, "
                                 f"node {self.config.node_id}", simulated=self.simulated,
            sample_time_s=self.T, force_limit_n=limit,
            position_limits_m=self.rig.position_limits_m, details=details,
            device_delay_s=delay, device_delay_why=why)

    def _watch_limit(self) -> tuple[str, float] | None:
        """The drive's shortest watch on the host (what a host stall that long trips): its
        RPDO event timer, heartbeat consumer or life time, as the run arms them."""
        a, cfg = self.assessment, self.config
        limits = [(f"the drive's RPDO event timer ({p.name}:05)", p.event_timer_ms * 1e-3)
                  for p in a.plan.rpdos if p.event_timer_ms]
        if a.watchdog == "heartbeat":
            limits.append(("the drive's heartbeat consumer 0x1016:01",
                           cfg.heartbeat_consumer_ms * 1e-3))
        elif a.watchdog == "guarding":
            limits.append(("the drive's life guarding (0x100C x 0x100D)",
                           cfg.guard_time_ms * cfg.life_time_factor * 1e-3))
        return min(limits, key=lambda x: x[1]) if limits else None

    def _own_delay(self) -> tuple[float, str]:
        """The delay the drive adds to every command (``labbench.model.device_delay``): one
        period when the torque RPDO is synchronous, none known otherwise."""
        p = self.assessment.plan.torque_at_sync() if self.assessment is not None else None
        if p is None:
            return 0.0, ""
        return self.T, (f"{p.name} is synchronous (transmission type {p.trans_type}, fixed by "
                        "the drive): the torque takes effect at the next SYNC, one sample "
                        "period after it is sent (CiA 301 7.2.2)")

    def _start_cyclic(self) -> None:
        """Service -> cyclic phase: re-verify the drive, arm its watch on the host (still
        PRE-OPERATIONAL), NMT start, seen OPERATIONAL."""
        if self._fault:
            raise self._latched()
        a = self.assessment
        try:
            state = self.drive_state()
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                self._latch(f"drive is in {state.value}: {self._error_code()}")
                raise self._latched()
            display = self._mode_display()
            checks = list(a.writes) + ([(display, 0, "<b", self._mode.code)]
                                       if display is not None else [])
            for index, sub, fmt, value in checks:
                e = self.dictionary.get(index, sub)
                if e is not None and not e.readable:
                    continue  # write-only: as written at open
                if (back := self._read(index, sub, fmt)) != value:
                    raise UserError(f"node {self.config.node_id}: object {where(index, sub)} "
                                    f"({object_name(index)}) is {hexval(back, fmt)}, expected "
                                    f"{hexval(value, fmt)}: refusing to enable")
            self._watch_armed = True
            for index, sub, value in self._watch_values(armed=True):
                self._write_checked(index, sub, self._fmt(index, sub), value)
            self._nmt(NMT_START)
            self._wait_nmt(5, NMT_TIMEOUT_S)
            self._operational = True
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
        self._last_answer = self._next_tick
        for entry in self._periodic:
            entry[2] = -math.inf

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
        self._send_rpdos(0)

    def disable(self, timeout: float = 1.0) -> None:
        """Zero torque, SWITCH ON DISABLED, the drive's watch on the host off and the node
        PRE-OPERATIONAL: nothing the driver armed is left to fire when the host goes quiet.

        The order feeds each watch until it is off: (1) still cyclic, RPDOs with zero
        torque and DISABLE VOLTAGE, SYNC by SYNC with the heartbeat/guarding due, until a
        TPDO shows the power stage off (at most ``timeout``); (2) the heartbeat/guarding
        request once more, then NMT PRE-OPERATIONAL, which ends the RPDO deadline
        monitoring (PDOs exist in OPERATIONAL only, CiA 301; CANopenNode clears its RPDO
        timers there); (3) over SDO, first the heartbeat consumer and guard time (they
        run in PRE-OPERATIONAL too and were just fed), then the RPDO event timers, to 0;
        (4) SWITCH ON DISABLED confirmed over SDO. After a fault: ``_after_fault``.
        """
        if self._closed or self._network is None:
            return
        self._zero_force(Command.DISABLE_VOLTAGE)
        if self._cyclic:
            if not self._fault:
                self._wind_down(timeout)
            self._cyclic = False
            if not self._fault:
                self._end_cyclic_traffic()
            self._start_receiver()
        elif self._operational and not self._fault:  # started, the cyclic phase never began
            self._end_cyclic_traffic()
        if self._fault:
            self._after_fault()
            return
        try:
            if self._watch_armed:
                for index, sub, value in self._watch_values(armed=False):
                    self._write_checked(index, sub, self._fmt(index, sub), value)
                self._watch_armed = False
            self._drive_to(State.SWITCH_ON_DISABLED, timeout)
        except (UserError, DeviceError) as exc:
            self._latch(f"disable failed: {exc}")
            raise DeviceFault(self._fault) from None

    def _after_fault(self) -> None:
        """Disable after a fault: one attempt, perhaps on a drive that no longer answers,
        to switch the power stage off over SDO; only once the drive shows no torque, NMT
        PRE-OPERATIONAL and its watch off (until then its watch is what removes the
        torque). The fault already says what went wrong. Once per fault, each answer
        awaited at most AFTER_FAULT_SDO_S: a drive that died must not hold the command for
        the full SDO timeout on every disable and close (it took 6 s to exit)."""
        if self._after_fault_for == self._fault:
            return
        self._after_fault_for = self._fault
        client, timeout = self._sdo.client, self._sdo.client.RESPONSE_TIMEOUT
        client.RESPONSE_TIMEOUT = min(timeout, AFTER_FAULT_SDO_S)
        try:
            self._sdo.write(0x6040, 0, "<H", cia402.CONTROLWORD[Command.DISABLE_VOLTAGE])
            if self.drive_state() in cia402.TORQUE_STATES:
                return
            self._end_cyclic_traffic()
            if self._watch_armed:
                for index, sub, value in self._watch_values(armed=False):
                    self._write(index, sub, self._fmt(index, sub), value)
                self._watch_armed = False
        except (UserError, DeviceError):
            pass
        finally:
            client.RESPONSE_TIMEOUT = timeout

    def _wind_down(self, timeout: float) -> None:
        """Disable step (1): cyclic exchanges with zero torque and DISABLE VOLTAGE until a
        TPDO shows a state without torque. A fault on the way is latched, not raised."""
        self._controlword = cia402.CONTROLWORD[Command.DISABLE_VOLTAGE]
        end = time.perf_counter() + timeout
        try:
            while True:
                self._send_rpdos(0)
                status = self._exchange(self._pace(), min(self._tpdo_wait, timeout))["status"]
                try:
                    off = cia402.decode_status(status) not in cia402.TORQUE_STATES
                except cia402.UnknownStatusword:
                    off = False
                if off or time.perf_counter() > end:
                    return
        except DeviceFault:
            pass  # latched: disable goes on as after any fault

    def _end_cyclic_traffic(self) -> None:
        """Disable step (2): the heartbeat/guarding request once more, then NMT
        PRE-OPERATIONAL. Plain sends that never raise: the bus may be what failed."""
        try:
            for entry in self._periodic:
                self._bus.send(entry[0], timeout=self.T)
            self._bus.send(self._nmt_msg(NMT_PRE_OPERATIONAL), timeout=self.T)
            self._operational = False
        except can.CanError:
            pass

    def emergency_stop(self) -> None:
        """Zero torque and power stage off at once; latch. Never raises."""
        self._zero_force(Command.DISABLE_VOLTAGE)
        self._latch(ESTOP_REASON)

    def _send_rpdos(self, set_point: int) -> None:
        cw = self._controlword
        for msg, st, roles in self._rpdos:
            msg.data = st.pack(*[set_point if r == "torque" else cw for r in roles])
            self._send(msg)

    def _zero_force(self, cmd: Command) -> None:
        try:
            self._controlword = cia402.CONTROLWORD[cmd]
            if self._cyclic:
                cw = self._controlword
                for msg, st, roles in self._rpdos:
                    msg.data = st.pack(*[0 if r == "torque" else cw for r in roles])
                    self._bus.send(msg)
            elif self._sdo is not None and self._network.notifier is not None and not self._fault:
                index, sub = self.assessment.command if self.assessment else (0x6071, 0)
                if self.dictionary is None or self.dictionary.has(index, sub):
                    size = self.dictionary.get(index, sub).bits // 8 if self.dictionary else 2
                    self._sdo.client.download(index, sub, bytes(size or 2))
                self._sdo.client.download(0x6040, 0, struct.pack("<H", self._controlword))
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
        self._last_emcy = None
        return state

    def status(self) -> DeviceStatus:
        state = ("closed" if self._closed else ESTOP_STATE if self._fault == ESTOP_REASON
                 else "fault" if self._fault else "enabled" if self._cyclic else "disabled")
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

    def _pace(self) -> float | None:
        """Paced mode: wait for the next SYNC's time and return it (None: lock-step)."""
        if not self.realtime:
            return None
        due = self._next_tick
        now = time.perf_counter()
        if now < due:
            sleep_until(due)  # a plain sleep wakes up to ~100 us late
        elif now > due + self.T:
            self.counters["late_ticks"] += 1
            self._next_tick = now  # re-phase instead of bursting SYNCs to catch up
        self._next_tick += self.T
        return due

    stale_periods_max = CanopenConfig._RANGES["stale_periods"][1]

    @property
    def stale_limit_s(self) -> float:
        """How long the TPDOs of a SYNC may take (``TimingProbe``; lock-step: its timeout)."""
        return self._tpdo_wait

    @stale_limit_s.setter
    def stale_limit_s(self, seconds: float) -> None:
        self._tpdo_wait = seconds

    def _exchange(self, due: float | None, wait: float) -> dict:
        """SYNC (and the heartbeat/guarding request when due), then every TPDO of that SYNC.

        The TPDOs are the drive's to deliver within ``wait`` of the moment the SYNC went
        out, not of when it was ``due``: a SYNC sent more than half a period late is the
        host's overrun (``late_syncs``; the loop's timing counts the long period too).
        """
        bus = self._bus
        if bus.state is can.BusState.ERROR:
            self._fail("CAN controller is bus-off (error state)")
        self._send(self._sync_msg)
        sent = time.perf_counter()
        if self.timing_log is not None:
            self._sync_wall = time.time()
        late = sent - due if due is not None else 0.0
        if late > 0.5 * self.T:
            self.counters["late_syncs"] += 1
        for entry in self._periodic:
            if sent - entry[2] >= entry[1]:
                self._send(entry[0])
                entry[2] = sent
        if self._guard_life and sent - self._last_answer > self._guard_life:
            self._fail(f"no node guarding answer for {self._guard_life * 1e3:.0f} ms")
        deadline = sent + wait
        decoders, vals, seen = self._decoders, self._vals, 0
        while True:
            left = deadline - time.perf_counter()
            msg = bus.recv(left if left > 0 else 0.0)
            if msg is None:
                host = (f" (the host sent the SYNC {late * 1e3:.3g} ms late)"
                        if late > 0.5 * self.T else "")
                self._fail(f"stale TPDO: no answer to SYNC {self._seq + 1} within "
                           f"{wait * 1e3:.3g} ms of sending it{host}")
            dec = decoders.get(msg.arbitration_id)
            if dec is not None and not msg.is_error_frame:
                try:
                    vals.update(zip(dec[1], dec[0].unpack_from(msg.data)))
                except struct.error:
                    self._fail(f"TPDO 0x{msg.arbitration_id:03X} of {len(msg.data)} bytes, "
                               f"expected {dec[0].size}")
                seen |= dec[2]
                if seen == self._all_sync:
                    if self.timing_log is not None:
                        self._log_cycle(due, sent, msg)
                    return vals
                continue
            self._dispatch(msg)
            if self._fault:  # EMCY, error frame or NMT change seen while waiting
                self._fail(self._fault)

    def _log_cycle(self, due: float | None, sent: float, last: can.Message) -> None:
        """One ``TimingProbe`` row: the round trip on the wire from the last TPDO's own
        timestamp (the interface's; python-can's clock is ``time.time``) and the SYNC's
        sending, on that clock."""
        now = time.perf_counter()
        sync_wall = self._sync_wall
        wire = last.timestamp - sync_wall if last.timestamp and sync_wall else math.nan
        self.timing_log.append((math.nan if due is None else due, sent, now,
                                wire if 0 <= wire < 60 else math.nan))

    def read(self, timeout: float) -> Sample:
        return Sample(*self.read_raw(timeout))

    def read_raw(self, timeout: float) -> tuple:
        """SYNC, then the TPDOs of that SYNC: ``(seq, t_s, position_m, flags)``.

        The position is the drive's at the SYNC, i.e. at the start of the period.
        """
        if self._fault:
            raise DeviceFault(self._fault) if self._cyclic else self._latched()
        if not self._cyclic:
            self._start_cyclic()
        vals = self._exchange(self._pace(), min(self._tpdo_wait, timeout))
        status, counts = vals["status"], vals["position"]
        if status & 0x6F != 0x27:  # CiA 402 coding of OPERATION ENABLED
            self._not_enabled(status)
        elif self._enable_deadline is not None and not self._confirmed:
            self._confirmed = True
            self._state_seen = State.OPERATION_ENABLED
        if self._window is not None and self._confirmed and not (
                self._window[0] <= counts <= self._window[1]):
            self._fail(f"position {counts * self._mpc:.4g} m outside the rig's window "
                       f"{list(self.rig.position_limits_m)} (host-side: the drive has no "
                       "software position limit 0x607D)")
        self._seq += 1
        if "torque" in vals:
            self.torque_actual_n = vals["torque"] * self._torque_n
        if "velocity" in vals:
            self.velocity_m_s = vals["velocity"] * self._mpc
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
        """Everything but the TPDOs in the cyclic phase."""
        if msg.is_error_frame:
            self.counters["error_frames"] += 1
            cls = [t for bit, t in ERROR_CLASSES.items() if msg.arbitration_id & bit]
            self._latch(f"CAN error frame ({', '.join(cls) or 'unspecified'})")
            return
        cid = msg.arbitration_id
        if cid == self._emcy_id:
            self._on_emcy(cid, msg.data, msg.timestamp)
        elif cid == self._hb_id and not msg.is_remote_frame:
            state = msg.data[0] & 0x7F if msg.data else None
            self._last_answer = time.perf_counter()
            if state != 5:
                self._latch(f"drive NMT state is {NMT_NAMES.get(state, state)}, not OPERATIONAL")
        else:
            self.counters["stray_frames"] += 1

    def command(self, force_n: float) -> None:
        """RPDO(s): torque held by the drive from now until the next command.

        Outside a run (or after a fault) only zero is accepted, and sends nothing.
        The torque is clamped here too (the only clamp when the drive has no 0x6072).
        """
        if self._fault or not self._cyclic:
            if force_n != 0.0:
                raise DeviceFault(self._fault or "command() outside a run (no read() yet)")
            return
        if not self._confirmed:  # still enabling: no torque before the drive shows it is on
            self._send_rpdos(0)
            return
        a = self.assessment
        p = round(force_n * a.force_to_command)
        m = a.max_command
        self._send_rpdos(m if p > m else (-m if p < -m else p))

    def holding(self) -> bool:
        """``labbench.device.Enabling``: from ``enable()`` until a TPDO shows OPERATION
        ENABLED, ``command()`` sends zero torque (a command in that window would be
        recorded but not applied: the drive takes it only once enabled)."""
        return self._enable_deadline is not None and not self._confirmed

    def identity(self) -> dict:
        return dict(self._identity)

    def add_close_hook(self, hook) -> None:
        """Called after the bus is shut down (the simulated drive stops here)."""
        self._close_hooks.append(hook)

    def close(self) -> None:
        """Disable if still running, write back what the survey found, shut the bus down."""
        if self._closed:
            return
        try:
            if self._cyclic or self._operational:
                self.disable()
        except Exception:  # closing must not fail; the drive's own timers remove torque
            pass
        try:
            self._restore()
        except Exception:  # as above: a drive gone by now keeps what it has
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

    def _restore(self) -> None:
        """The objects the driver set for its own use (producer heartbeat, life time factor,
        the watch) back to the values the survey found, where they differ from what the
        driver left; only when the drive is disabled and answers."""
        if self._cyclic or self._operational or self._network is None \
                or self._network.notifier is None or self.assessment is None:
            return
        left = {(i, s): v for i, s, v in self._service_values() + self._watch_values(False)}
        for (index, sub), value in self._found.items():
            if left.get((index, sub)) != value:
                try:
                    self._write(index, sub, self._fmt(index, sub), value)
                except DeviceConnectionError:
                    return
                except DeviceError:
                    continue  # refused now: what the driver left stays

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_canopen(rig, realtime: bool = True, seed=None, can_log: str | None = None,
                 **options) -> CanopenDrive:
    """Registry factory (``--device canopen``): the drive described by ``rig``'s ``[canopen]``.

    ``seed`` is accepted (and unused) so that every device opens with the same call.
    """
    if options:
        raise UserError(f"canopen device takes no option(s) {', '.join(sorted(options))}")
    config = CanopenConfig.from_rig(rig)
    return CanopenDrive(rig, config, realtime=realtime, can_log=can_log).open()


def probe_canopen(rig, fault_reset: bool = False) -> dict:
    """Registry probe (``labbench devices``): the read-only capability report of the rig's drive.

    ``fault_reset``: the operator's fault reset instead (FAULT -> SWITCH ON
    DISABLED only), reported as ``{"reset": (before, after)}``. A drive that
    does not answer gives ``{"no_answer": reason}``.
    """
    config = CanopenConfig.from_rig(rig)
    return probe_drive(CanopenDrive(rig, config), fault_reset)


def probe_drive(drive: CanopenDrive, fault_reset: bool = False) -> dict:
    """``probe()`` or ``reset_fault()`` on a driver not yet connected; closes it.

    A node that answers no SDO but sends a heartbeat (e.g. STOPPED) is named so.
    """
    with drive:
        try:
            drive.connect()
            if not fault_reset:
                return drive.probe()
            before = drive.drive_state()
            return {"node_id": drive.config.node_id,
                    "reset": (before.value, drive.reset_fault().value)}
        except DeviceConnectionError as exc:
            nmt = drive._observe_nmt(0.3) if drive._network is not None else None
            heard = f"; its heartbeat shows {NMT_NAMES.get(nmt, nmt)}" if nmt is not None else ""
            return {"no_answer": f"{exc}{heard}"}
