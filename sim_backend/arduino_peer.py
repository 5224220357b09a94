"""A simulated Arduino encoder board, so the REAL serial driver runs in tests and demos.

The board side of docs/serial-protocol.md in Python: it samples a simulated
plant, sends ``micros,count`` lines or framed binary samples, takes framed
force commands back, and has the sketch's watchdog (output zeroed after 3
periods without a command). Transports: the platform's serial peer
(``labbench.platform.serial_peer``: a pty pair the host opens by path, or a local
socket it opens as ``socket://`` where there is no pty) or a pyserial ``loop://``
port for unit tests (board -> host only; the test calls ``emit``).

Pacing and delay (sample k = position at the start of period k):

* lock-step (default, as fast as possible): emit sample k, wait for the
  command answering k (``lockstep_timeout_s``; none -> zero force, watchdog
  bit), apply it during period k. Zero extra delay: the sampled model is the
  plain simulator's. ``delay_samples`` = n applies the answer to sample k in
  period k+n instead, to mimic a board. A sample the board corrupted or
  dropped on purpose (a fault) gets no answer: the board holds the last
  command for that period and goes on at once. Board time is virtual here, so
  the host's stale limit is ``lockstep_timeout_s / 2`` of wall time, not a
  few periods; the 3-period limit is a property of the free-running board.
* free-running (``realtime=True``): a tick every T of wall time; at tick k the
  board latches the newest command received, sends sample k and applies the
  latched force during period k. The answer to sample k arrives during period
  k and is applied in period k+1: one whole sample of extra delay (td = T), as
  on the reference sketch, provided the host answers within one period.

Faults are scheduled by sample index (``schedule``) so tests are repeatable.

Lab sketches (docs/serial-protocol.md, "What your sketch must do"): ``fields`` prints
the columns a rig's ``[serial] fields`` names (``micros``, ``millis`` = micros // 1000,
``count``, extra fields as 0), ``on_change`` prints a line only when the count changed,
``count_signed = False`` prints the counter unsigned, ``banner`` is its first line, and
``wire`` maps every write (``labbench.sim_backend.uart_wire``: the bytes a receiver at the
wrong baud rate reads).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from labbench.drivers import framing
from labbench.platform.serial_peer import open_transport

BANNER = b"#labbench encoder v1\r\n"
APPLIED_KEPT = 1_000_000  # periods of applied force kept (about 17 min at 1 kHz)
FAULT_KINDS = ("garbage", "flip", "drop", "stall", "unplug", "reboot")


@dataclass(frozen=True)
class Fault:
    """``kind`` at sample ``at``: garbage (``n`` random bytes before the sample), flip (one
    bit of the frame), drop (``n`` samples not sent), stall (board silent ``seconds``),
    unplug (port gone), reboot (time, sequence and count restart, boot noise)."""

    kind: str
    at: int
    n: int = 1
    seconds: float = 0.0

    def __post_init__(self):
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {self.kind!r}; choose one of {', '.join(FAULT_KINDS)}")


class ArduinoPeer:
    """The simulated board. ``plant`` has ``step(force)`` and ``position``.

    ``unit``: command value per newton at the handle (1 for "N", ``lever_arm_m``
    for "N*m"). ``t0_us``/``count0`` start micros() and the counter elsewhere
    than zero (e.g. just before a wrap).
    """

    def __init__(
        self,
        plant,
        T: float,
        metres_per_count: float,
        *,
        fmt: str = "binary",
        count_bits: int = 32,
        direction: int = 1,
        unit: float = 1.0,
        realtime: bool = False,
        delay_samples: int = 0,
        lockstep_timeout_s: float = 1.0,
        boot_noise: bool = True,
        t0_us: int = 0,
        count0: int = 0,
        seed: int | None = None,
        faults=(),
        fields: tuple = framing.DEFAULT_FIELDS,
        on_change: bool = False,
        count_signed: bool = True,
        banner: bytes = BANNER,
        wire=None,
    ):
        self.plant, self.T = plant, T
        self.fields, self.on_change, self.count_signed = tuple(fields), on_change, count_signed
        self.banner, self._wire = banner, wire
        self._printed: int | None = None  # on_change: the count last printed
        self.fmt, self.count_bits, self.direction = fmt, count_bits, direction
        self._mpc, self._unit = metres_per_count, unit
        self.realtime, self.lockstep_timeout_s = realtime, lockstep_timeout_s
        self.boot_noise = boot_noise
        self._rng = np.random.default_rng(seed)
        self._t0_us, self._count0 = t0_us, count0
        self._zero_x = 0.0  # plant position at the board's last boot (count 0 there)
        self.k = 0  # periods simulated (the plant's clock; survives a reboot)
        self._k_boot = 0  # k at the last boot: sequence numbers count from there
        self.samples_sent = 0
        self._pending = deque([0.0] * delay_samples)
        self._latest = 0.0  # newest command [N at the handle]
        self._latest_at = -(10**9)  # sample index when it arrived
        self._status = 0
        self._intact = False
        self.commands = framing.CommandParser()
        self.watchdog_zeroed = 0  # periods the watchdog forced zero
        # Force applied in each period since start (tests index it by k); bounded
        # so a board left running for hours does not grow without limit.
        self.applied: deque[float] = deque(maxlen=APPLIED_KEPT)
        self._faults: dict[int, list[Fault]] = {}
        for f in faults:
            self.schedule(f)
        self._write = None
        self._transport = None  # labbench.platform.serial_peer's, once opened
        self.url: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self.unplugged = False

    # -- transports -------------------------------------------------------------------
    def open_port(self, warn=None) -> str:
        """Open the platform's transport; returns what the host opens with
        ``serial.serial_for_url`` (a pty's path or a ``socket://`` URL)."""
        self._transport = open_transport(warn)
        self._write = self._wired(self._transport.write)
        self.url = self._transport.url
        return self.url

    def attach_loop(self, port) -> None:
        """Board -> host over a pyserial ``loop://`` port (no command channel)."""
        self._write = self._wired(port.write)

    def _wired(self, write):
        wire = self._wire
        return write if wire is None else (lambda data: write(wire(data)))

    # -- the board --------------------------------------------------------------------
    def schedule(self, fault: Fault) -> None:
        self._faults.setdefault(fault.at, []).append(fault)

    def boot(self) -> None:
        """What a board sends after reset: bootloader noise, then the banner."""
        if self.boot_noise:
            noise = self._rng.integers(
                0, 256, int(self._rng.integers(8, 64)), dtype=np.uint8
            ).tobytes()
            self._write(noise + b"\r\n")
        # A zero after the banner ends whatever frame the noise started (binary form).
        if self.banner:
            self._write(self.banner + (b"\x00" if self.fmt == "binary" else b""))

    def frame(self, k: int) -> bytes:
        """Bytes of sample k (position now, time and count as the board holds them)."""
        t_us = (self._t0_us + round(k * self.T * 1e6)) % (1 << 32)
        seq = k - self._k_boot
        count = self._count0 + self.direction * math.floor(
            (self.plant.position - self._zero_x) / self._mpc + 0.5
        )
        bits = self.count_bits
        count &= (1 << bits) - 1
        if count >> (bits - 1) and (self.count_signed or self.fmt == "binary"):
            count -= 1 << bits  # the board's signed int of that width
        if self.fmt == "ascii":
            if self.on_change:
                if count == self._printed:
                    return b""
                self._printed = count
            if self.fields == framing.DEFAULT_FIELDS:
                return framing.format_ascii(t_us, count)
            values = {"micros": t_us, "millis": t_us // 1000, "count": count}
            return (",".join(str(values.get(f, 0)) for f in self.fields) + "\r\n").encode()
        return framing.encode_sample(seq, t_us, count, self._status)

    def emit(self, n: int = 1, force_n: float = 0.0) -> None:
        """Send n samples, each followed by one period under ``force_n`` (loop:// tests)."""
        for _ in range(n):
            if self._send_sample():
                self._advance(force_n)

    def _send_sample(self) -> bool:
        """Send sample k with its scheduled faults; False once unplugged.

        Sets ``_intact``: whether the host can decode sample k (a lock-step
        board waits for an answer only then).
        """
        k = self.k
        data = self.frame(k)
        intact = True
        for f in self._faults.pop(k, ()):
            if f.kind == "garbage":
                junk = self._rng.integers(0, 256, f.n, dtype=np.uint8).tobytes()
                self._write(junk)
                # The host cuts junk off the front of a frame; a line it merges into is lost.
                intact = intact and (self.fmt == "binary" or junk.endswith(b"\n"))
            elif f.kind == "flip":
                buf = bytearray(data)
                i = int(self._rng.integers(0, len(buf) - 1))  # not the delimiter
                buf[i] ^= 1 << int(self._rng.integers(0, 8))
                data = bytes(buf)
                intact = False
            elif f.kind == "drop":
                for j in range(1, f.n):
                    self._faults.setdefault(k + j, []).append(Fault("drop", k + j))
                data = b""
                intact = False
            elif f.kind == "stall":
                self._stop.wait(f.seconds)
            elif f.kind == "unplug":
                self.unplug()
                return False
            elif f.kind == "reboot":
                self._reboot()
                data = self.frame(self.k)
        if data:
            self._write(data)
            self.samples_sent += 1
            self._status = 0  # a sample reports what happened since the previous one
        self._intact = intact
        return True

    def _reboot(self) -> None:
        self._zero_x = self.plant.position
        self._t0_us = 300_000 - round(self.k * self.T * 1e6)  # micros() ~0.3 s after reset
        self._count0 = 0
        self._k_boot = self.k  # the sequence number restarts too
        self._status = 0
        self.boot()

    def _advance(self, force_n: float) -> None:
        self._pending.append(force_n)
        f = self._pending.popleft()
        self.plant.step(f)
        self.applied.append(f)
        self.k += 1

    def _take_commands(self, data: bytes) -> list[tuple[int, float]]:
        before = self.commands.errors
        cmds = self.commands.feed(data)
        if self.commands.errors != before:
            self._status |= framing.STATUS_BAD_COMMAND
        for _, value in cmds:
            self._latest, self._latest_at = value / self._unit, self.k
        return cmds

    def _watchdog_force(self) -> float:
        if self.k - self._latest_at > 3:
            self.watchdog_zeroed += 1
            self._status |= framing.STATUS_WATCHDOG
            return 0.0
        return self._latest

    def _lockstep_period(self) -> None:
        if not self._send_sample():
            return
        force = None
        want = self.k & 0xFFFF
        if not self._intact:
            force = self._watchdog_force()  # no answer can come: the latch, as a free-running board
        else:
            deadline = time.monotonic() + self.lockstep_timeout_s
            while force is None and not self._stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                for seq, value in self._take_commands(self._transport.read(min(left, 0.02))):
                    if self.fmt == "ascii" or seq == want:
                        force = value / self._unit
        if force is None:
            self.watchdog_zeroed += 1
            self._status |= framing.STATUS_WATCHDOG
            force = 0.0
        self._advance(force)

    def _realtime_period(self) -> None:
        self._take_commands(self._transport.read(0))
        force = self._watchdog_force()
        if self._send_sample():
            self._advance(force)

    def _run(self) -> None:
        try:
            self.boot()
            period = self._realtime_period if self.realtime else self._lockstep_period
            next_tick = time.monotonic()
            while not self._stop.is_set() and not self.unplugged:
                period()
                if self.realtime:
                    next_tick += self.T
                    delay = next_tick - time.monotonic()
                    if delay > 0:
                        self._stop.wait(delay)
        except BaseException as exc:  # noqa: BLE001 - reported to the test through .error
            self.error = exc

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="arduino-peer", daemon=True)
        self._thread.start()

    def unplug(self) -> None:
        """The cable is pulled: the host's port fails from now on."""
        self.unplugged = True
        if self._transport is not None:
            self._transport.close()

    def close(self, timeout: float = 2.0) -> None:
        """Stop the board thread and release the transport (safe to call twice)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
        if self._transport is not None:
            self._transport.close()


def connect_sim_serial(
    rig,
    realtime: bool = False,
    seed: int | None = None,
    faults=(),
    plant=None,
    delay_samples: int = 0,
    t0_us: int = 0,
    count0: int = 0,
    boot_noise: bool = True,
    lockstep_timeout_s: float = 1.0,
    sim: dict | None = None,
):
    """The real ``SerialStream`` on a pty (or local socket) to a started ``ArduinoPeer``:
    ``(driver, peer)``.

    Driver settings come from ``rig``'s ``[serial]`` table (port and
    ``force_command = true`` are forced: the simulated plant needs the force).
    The plant is the plain simulator's physics (``SimPlant``: ``[sim]`` table,
    overridden by ``sim``) unless ``plant`` is given. Closing the driver stops
    the board.
    """
    import serial

    from labbench.drivers.serial_stream import SerialConfig, SerialStream, synced

    from labbench.sim_backend.sim_device import sim_options, true_geometry

    config = SerialConfig.from_rig(rig, port="pty", force_command=True)
    T = rig.sample_time_s
    if plant is None:
        plant = SimPlant(rig, seed=seed, **(sim or {}))
    # the board counts the true way (sim_device.true_geometry): as the driver believes
    # unless [sim] says otherwise
    geo = true_geometry(rig, sim_options(rig, **(sim or {})), rig.position_sign * config.direction)
    unit = geo.lever_arm_m if config.command_units == "N*m" else 1.0
    peer = ArduinoPeer(
        plant,
        T,
        geo.metres_per_count,
        fmt=config.format,
        count_bits=config.count_bits,
        direction=geo.sign,
        unit=unit,
        realtime=realtime,
        delay_samples=delay_samples,
        lockstep_timeout_s=lockstep_timeout_s,
        boot_noise=boot_noise,
        t0_us=t0_us,
        count0=count0,
        seed=seed,
        faults=faults,
        fields=config.fields,
        count_signed=config.count_signed,
    )
    url = peer.open_port()
    try:
        ser = serial.serial_for_url(url, baudrate=config.baudrate, timeout=0)
    except BaseException:
        peer.close()
        raise
    # A lock-step board's time is virtual (its plant waits for the host), so a few
    # periods of wall time mean nothing there: the host's stale limit is half the
    # board's own wait for a command instead.
    # free-running, the answer to sample k is applied in period k + 1 (module doc)
    late = delay_samples + (1 if realtime else 0)
    driver = SerialStream(
        ser,
        config,
        rig,
        on_close=peer.close,
        paced=realtime,
        stale_s=None if realtime else lockstep_timeout_s / 2,
        kind="sim-serial",
        simulated="simulated encoder board (a Python peer of docs/serial-protocol.md) on "
                  + ("a pty" if url.startswith("/") else url.split(":", 1)[0]),
        device_delay_s=late * T,
        device_delay_why=(f"the simulated board applies each answer {late} sample(s) late"
                          + (" (free-running: the answer to sample k acts in period k + 1)"
                             if realtime else "")) if late else "",
    )
    peer.start()
    return synced(driver), peer


def connect_lab_stream(rig, motion, *, prints=None, wire=None, banner: bytes = b"",
                       board_T: float | None = None, seed: int | None = None):
    """A free-running board that streams its count as ``prints`` (a rig; default ``rig``)
    says in its ``[serial]`` table (format, fields, on_change, count_bits, count_signed,
    direction), read by the driver as ``rig`` says; its handle moved by ``motion(t) ->
    metres``, a line every ``board_T`` (default the rig's period). ``wire`` maps its bytes
    (``uart_wire``); ``banner`` is its first line. Returns ``(driver, peer)`` once the
    driver has the stream (``wait_for_stream``)."""
    import serial

    from labbench.drivers.serial_stream import SerialConfig, SerialStream, synced
    from labbench.sim_backend.plant import PrescribedMotion

    config = SerialConfig.from_rig(rig, port="pty")
    board = SerialConfig.from_rig(prints or rig, port="pty")
    T = board_T or rig.sample_time_s
    peer = ArduinoPeer(PrescribedMotion(motion, T), T, rig.metres_per_count, fmt=board.format,
                       count_bits=board.count_bits, direction=board.direction, realtime=True,
                       boot_noise=False, seed=seed, fields=board.fields,
                       on_change=board.on_change, count_signed=board.count_signed,
                       banner=banner, wire=wire)
    url = peer.open_port()
    try:
        ser = serial.serial_for_url(url, baudrate=config.baudrate, timeout=0)
    except BaseException:
        peer.close()
        raise
    driver = SerialStream(ser, config, rig, on_close=peer.close, kind="sim-serial",
                          simulated="a lab's encoder sketch (a Python peer) on a pty")
    peer.start()
    return synced(driver), peer


class SimPlant:
    """The plain simulator's physics as a board's plant (``step(force)``, ``position``).

    Friction, force noise, actuator delay and initial state come from
    ``labbench.sim_backend.sim_device`` with the same options and seed, so a run through
    the board matches a run on ``--device sim``; the board adds its encoder's
    quantisation.
    """

    def __init__(self, rig, seed: int | None = None, **options):
        from labbench.sim_backend.sim_device import SimDevice

        self._sim = SimDevice(rig, seed=seed, as_plant=True, **options)  # true handle units
        self._sim.enable()
        self.position = self._sim.read_raw(1.0)[2]

    def step(self, force: float) -> None:
        self._sim.command(force)
        self.position = self._sim.read_raw(1.0)[2]


def default_plant(rig):
    """The rig's nominal mass-damper, exact over each ZOH step."""
    from labbench.sim_backend.plant import MassDamperPlant

    return MassDamperPlant(rig.nominal_mass_kg, rig.nominal_damping_ns_m, rig.sample_time_s)


def open_sim_serial(rig, realtime: bool | None = None, seed: int | None = None,
                    **sim_options):
    """Device registry factory for ``--device sim-serial``.

    ``sim_options`` are those of ``--device sim`` (``labbench.sim_backend.sim_device``);
    ``realtime`` None: the rig's ``[sim] paced`` (default lock-step).
    """
    from labbench.sim_backend.sim_device import paced_by_rig

    return connect_sim_serial(rig, realtime=paced_by_rig(rig, realtime), seed=seed,
                              sim=sim_options)[0]
