"""A CiA 402 torque drive on CANopenNode v4, in a process of its own on python-can's
``udp_multicast`` bus (as a lab's drive is: the host's stalls do not stall it).

Why a shared library in this Python process (``ctypes``), not a C program bridged over
stdin/stdout: each frame then crosses one process boundary (the bus) instead of two (the
bus, then a pipe to the C program), which matters on a 2-core machine where every hop is
a context switch in each lock-step period; and the CiA 402 application, written in Python,
reuses the project's pure state-machine tables (``labbench.drivers.cia402``) and the
simulated drive's exact plant (``canopen_peer.plant_for``), so its positions can be
compared with the same oracle as the simulated drive's. The stack itself (``drive.c``,
``CO_driver.c``, the generated dictionary) is C, as on a drive.

Process contract (``labbench.sim_backend.canopen_process.spawn``): one JSON line on stdin
(the library, node id, rig, plant seed and options, UDP port), ``ready`` on stdout once
the node listens, then a JSON command per line (``{"fault": code}``: an internal drive
fault, e.g. 0x2310 over-current), until stdin closes.

The application per processing step (after every received frame, and every
``IDLE_S`` otherwise): the stack's mainline, SYNC, then (on a SYNC) the plant steps one
period under the torque applied so far, then the stack's RPDO processing (synchronous RPDO
data take effect here, at the SYNC: CiA 301), the controlwords written meanwhile through
the state machine, the torque now applied, the reaction to a lost host (0x6007), and (on
a SYNC) the position sampled for the TPDOs the stack then sends.
"""
from __future__ import annotations

import ctypes
import json
import queue
import struct
import sys
import threading
import time

import can

from labbench.drivers import cia402
from labbench.drivers.cia402 import State
from labbench.rig import Rig
from labbench.sim_backend.canopen_peer import plant_for
from labbench.sim_backend.canopen_process import multicast_bus

IDLE_S = 0.002  # the stack's timers (heartbeat, guarding, RPDO event timer) run this often at least
NMT_OPERATIONAL = 5
# CANopenNode's error status bits (301/CO_Emergency.h) and the application's own.
EM_RPDO_TIME_OUT, EM_HEARTBEAT_CONSUMER = 0x17, 0x1B  # the latter also life guarding
EM_DRIVE_FAULT = 0x40  # first manufacturer-critical bit: an internal fault of the drive
MODES = (10, 4)  # torque modes the application runs (CST, profile torque)
FMT = {0x603F: "<H", 0x6007: "<h", 0x6041: "<H", 0x605A: "<h", 0x6061: "<b", 0x6064: "<i",
       0x606C: "<i", 0x6071: "<h", 0x6072: "<H", 0x6076: "<I", 0x6077: "<h"}


def load(path: str) -> ctypes.CDLL:
    lib = ctypes.CDLL(path)
    u8, u16, u32, p = ctypes.c_uint8, ctypes.c_uint16, ctypes.c_uint32, ctypes.c_void_p
    for name, args in (("cod_init", [u8, ctypes.POINTER(u32)]), ("cod_process", [u32]),
                       ("cod_sync", [u32]), ("cod_rpdo", [ctypes.c_int, u32]),
                       ("cod_tpdo", [ctypes.c_int, u32]),
                       ("cod_controlword", [ctypes.POINTER(u16)]),
                       ("cod_nmt_state", []), ("cod_is_error", [u8]),
                       ("cod_error", [ctypes.c_int, u8, u16, u32]),
                       ("cod_read", [u16, u8, p, u32]), ("cod_write", [u16, u8, p, u32]),
                       ("cod_rx", [u16, u8, u8, ctypes.c_char_p]),
                       ("cod_tx", [ctypes.POINTER(u16), ctypes.POINTER(u8), ctypes.POINTER(u8), p]),
                       ("cod_close", [])):
        getattr(lib, name).argtypes = args
    lib.cod_close.restype = None
    return lib


class Drive:
    """The CiA 402 application on the node (see the module docstring)."""

    def __init__(self, lib, plant, metres_per_count: float, lever_arm_m: float):
        self.lib, self.plant = lib, plant
        self.mpc, self.lever = metres_per_count, lever_arm_m
        self.state = State.SWITCH_ON_DISABLED  # transition 1, at power-up
        self.controlword = 0
        self.applied = 0  # per-mille of the rated torque, on the plant now
        self._cw = ctypes.c_uint16()
        self._buf = ctypes.create_string_buffer(8)
        self._tx = (ctypes.c_uint16(), ctypes.c_uint8(), ctypes.c_uint8(),
                    ctypes.create_string_buffer(8))
        self._set_status()

    # ---------------------------------------------------------------- the dictionary
    def get(self, index: int) -> int:
        fmt = FMT[index]
        size = struct.calcsize(fmt)
        self.lib.cod_read(index, 0, self._buf, size)
        return struct.unpack(fmt, self._buf.raw[:size])[0]

    def put(self, index: int, value: int) -> None:
        data = struct.pack(FMT[index], value)
        self.lib.cod_write(index, 0, data, len(data))

    # -------------------------------------------------------------------- CiA 402
    def _set_status(self) -> None:
        extra = cia402.SW_REMOTE
        if self.state in (State.SWITCHED_ON, *cia402.TORQUE_STATES):
            extra |= cia402.SW_VOLTAGE_ENABLED
        if self.state is State.OPERATION_ENABLED and abs(self.get(0x6071)) > self.get(0x6072):
            extra |= cia402.SW_INTERNAL_LIMIT
        self.put(0x6041, cia402.encode_status(self.state, extra))

    def _go(self, state: State) -> None:
        if state is State.OPERATION_ENABLED and self.get(0x6061) not in MODES:
            return self.fault(0x6320, report=True)  # enabled without a torque mode
        if state is State.QUICK_STOP_ACTIVE and self.get(0x605A) in range(5):
            state = State.SWITCH_ON_DISABLED  # these quick-stop options end there
        if self.state is State.FAULT and state is State.SWITCH_ON_DISABLED:  # transition 15
            self.put(0x603F, 0)
            if self.lib.cod_is_error(EM_DRIVE_FAULT):
                self.lib.cod_error(0, EM_DRIVE_FAULT, 0, 0)
        self.state = state

    def fault(self, code: int, report: bool) -> None:
        """Fault reaction (immediate: torque off), FAULT, 0x603F; ``report``: this drive's
        own fault, told by EMCY and the error history (a lost host the stack told already)."""
        self.state = State.FAULT
        self.put(0x603F, code)
        if report:
            self.lib.cod_error(1, EM_DRIVE_FAULT, code, 0)

    def _controlwords(self) -> None:
        while self.lib.cod_controlword(ctypes.byref(self._cw)):
            cw = self._cw.value
            command = cia402.decode_controlword(cw, self.controlword)
            self.controlword = cw
            new = cia402.next_state(self.state, command)
            if new is not self.state:
                self._go(new)

    def _watch_host(self) -> None:
        """A lost host while torque may flow: the reaction 0x6007 asks for."""
        if self.state not in cia402.TORQUE_STATES:
            return
        lib = self.lib
        if lib.cod_is_error(EM_RPDO_TIME_OUT):
            code = 0x8250
        elif lib.cod_is_error(EM_HEARTBEAT_CONSUMER):
            code = 0x8130
        elif lib.cod_nmt_state() != NMT_OPERATIONAL:
            code = 0x8100
        else:
            return
        option = self.get(0x6007)
        if option == 1:
            self.fault(code, report=False)
        elif option == 2:
            self._go(State.SWITCH_ON_DISABLED)
        elif option == 3:
            self._go(cia402.next_state(self.state, cia402.Command.QUICK_STOP))

    def _torque(self) -> None:
        if self.state is State.OPERATION_ENABLED:
            limit = self.get(0x6072)
            self.applied = max(-limit, min(limit, self.get(0x6071)))
        else:
            self.applied = 0
        self.put(0x6077, self.applied)

    # -------------------------------------------------------------------- a step
    def step(self, dt_us: int) -> None:
        lib = self.lib
        lib.cod_process(dt_us)
        sync = lib.cod_sync(dt_us)
        if sync:  # one period has passed under the torque applied so far
            self.plant.command(self.applied * 1e-6 * self.get(0x6076) / self.lever)
            self.plant.read_raw(1.0)
        lib.cod_rpdo(sync, dt_us)
        self._controlwords()
        self._watch_host()
        self._torque()
        self._set_status()
        if sync:
            self.put(0x6064, round(self.plant.x / self.mpc))
            self.put(0x606C, round(self.plant.v / self.mpc))
        lib.cod_tpdo(sync, dt_us)

    def frames(self):
        """Frames the stack sent since the last call."""
        ident, rtr, dlc, data = self._tx
        while self.lib.cod_tx(ctypes.byref(ident), ctypes.byref(rtr), ctypes.byref(dlc), data):
            n = dlc.value
            yield can.Message(arbitration_id=ident.value, is_remote_frame=bool(rtr.value), dlc=n,
                              data=b"" if rtr.value else data.raw[:n], is_extended_id=False)


def serve(drive: Drive, bus, commands: queue.SimpleQueue, stop: threading.Event,
          answer_delay_s: float = 0.0) -> None:
    """Frames in, processing steps, frames out, until ``stop``. ``answer_delay_s``: a slow
    drive (the timing preflight's tests): a SYNC is taken that long after it arrived."""
    lib = drive.lib
    last = time.monotonic_ns() // 1000
    while not stop.is_set():
        msg = bus.recv(IDLE_S)
        if msg is not None and not msg.is_error_frame and not msg.is_extended_id:
            if answer_delay_s and msg.arbitration_id == 0x080:
                time.sleep(answer_delay_s)
            lib.cod_rx(msg.arbitration_id, msg.is_remote_frame, msg.dlc, bytes(msg.data))
        while not commands.empty():
            drive.fault(int(commands.get()["fault"]), report=True)
        now = time.monotonic_ns() // 1000
        drive.step(min(now - last, 0xFFFFFFFF))
        last = now
        for frame in drive.frames():
            bus.send(frame)


def main() -> int:
    spec = json.loads(sys.stdin.readline())
    r = spec["rig"]
    rig = Rig(**{**r, "position_limits_m": tuple(r["position_limits_m"])})
    plant = plant_for(rig, spec["seed"], **spec["options"])
    geo = plant.geometry  # the encoder's count direction as the signed metres per count
    lib = load(spec["lib"])
    info = ctypes.c_uint32()
    err = lib.cod_init(spec["node_id"], ctypes.byref(info))
    if err:
        print(f"CANopenNode initialisation failed: error {err}, OD entry 0x{info.value:X}",
              file=sys.stderr)
        return 1
    drive = Drive(lib, plant, geo.sign * geo.metres_per_count, geo.lever_arm_m)
    bus = multicast_bus(spec["port"])
    commands, stop = queue.SimpleQueue(), threading.Event()
    worker = threading.Thread(target=serve, args=(drive, bus, commands, stop,
                                                  spec.get("answer_delay_s", 0.0)), daemon=True)
    worker.start()
    try:
        print("ready", flush=True)
        for line in sys.stdin:  # until EOF: the host closed the pipe or died
            commands.put(json.loads(line))
    finally:
        stop.set()
        worker.join(timeout=2.0)
        bus.shutdown()
        lib.cod_close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
