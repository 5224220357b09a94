"""Serial encoder stream (Arduino-style board) behind ``labbench.device.Device``.

The board streams ``micros,count`` lines or COBS-framed binary samples
(``labbench.drivers.framing``; spec in docs/serial-protocol.md) and may take framed
force commands back. The driver reads whatever bytes are waiting in one call
(never byte-by-byte ``readline()``), resynchronises after garbage, counts link
errors, drops and reboots, and fails safe: once enabled, a stream silent for
``stale_periods`` sample periods, a reboot of the board (its time goes back),
more lost samples in a row than ``tolerate_drops``, bytes discarded on the
link (unless ``tolerate_link_errors``), or a lost port zero the
commanded force, latch, and raise ``DeviceFault`` with the reason. Only
``enable()`` (the operator) clears the latch.

Units: position = ``direction * count * rig.metres_per_count`` [m] at the
handle; the force command is sent in N at the handle (``command_units = "N"``)
or as joint torque ``F * lever_arm_m`` in N m (``"N*m"``).
"""

from __future__ import annotations

import itertools
import math
import os
import statistics
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import NamedTuple

from labbench.drivers import framing
from labbench.drivers.unwrap import Unwrapper
from labbench.device import ESTOP_STATE, DeviceDescription, DeviceFault, DeviceStatus, Sample
from labbench.errors import DeviceConnectionError, UserError, unknown_name

# Sample.flags bits of this device (0 = healthy).
FLAG_LOST = 1  # samples were lost right before this one (seq / time gap)
FLAG_LINK_ERRORS = (
    2  # bytes were discarded (CRC, framing, malformed line) since the previous sample
)
FLAG_BOARD_WATCHDOG = 4  # the board reports it zeroed its output (no command in time)
FLAG_BOARD_BAD_COMMAND = 8  # the board discarded a corrupt command frame
FLAG_BACKLOG = 16  # more samples were already waiting behind this one (host is late)
FLAG_BOARD_MISSED_TICK = 32  # protocol v2: the board latched a sample it could not send
FLAG_BOARD_LATE = 64  # protocol v2: the board queued this frame late after its tick
FLAG_BOARD_ENCODER = 128  # protocol v2: the board's encoder skipped a state (count lost)
FLAG_BOARD_RENDERING = 256  # protocol v2: the board renders the VE (command = excitation)
FLAG_BOARD_RENDER_LATE = 512  # protocol v2: a rendered force came late (the last one held)
_STATUS_FLAGS = (
    (framing.STATUS_WATCHDOG, FLAG_BOARD_WATCHDOG),
    (framing.STATUS_BAD_COMMAND, FLAG_BOARD_BAD_COMMAND),
    (framing.STATUS_MISSED_TICK, FLAG_BOARD_MISSED_TICK),
    (framing.STATUS_LATE, FLAG_BOARD_LATE),
    (framing.STATUS_ENCODER, FLAG_BOARD_ENCODER),
    (framing.STATUS_RENDERING, FLAG_BOARD_RENDERING),
    (framing.STATUS_RENDER_LATE, FLAG_BOARD_RENDER_LATE),
)

SYNC_SAMPLES = 5  # consecutive good samples that make a stream "in sync"
PERIOD_TOLERANCE = 0.1  # relative mismatch allowed between board period and rig sample time


@dataclass(frozen=True)
class SerialConfig:
    """The ``[serial]`` table of a rig file (see docs/serial-protocol.md)."""

    port: str = ""
    baudrate: int = 500_000
    format: str = "binary"  # "binary" | "ascii"
    count_bits: int = 32  # width of the board's encoder counter: 16 | 32
    direction: int = 1  # +1 | -1: sign of counts at the handle
    force_command: bool = False  # send framed force commands to the board
    command_units: str = "N"  # "N" at the handle | "N*m" joint torque via lever_arm_m
    stale_periods: float = 2.5  # silent periods before force is zeroed (1..3)
    tolerate_drops: int = 0  # lost samples in a row accepted (flagged) while enabled
    tolerate_link_errors: bool = False  # discarded bytes only flagged while enabled
    sync_timeout_s: float = 3.0  # wait for the first samples after opening (board boot)

    @classmethod
    def from_rig(cls, rig, **overrides) -> SerialConfig:
        table = {**rig.section("serial"), **overrides}
        for name in table:
            if name not in cls.__dataclass_fields__:
                raise UserError(f"{rig.source}: [serial] "
                                f"{unknown_name('field', name, cls.__dataclass_fields__)}")
        checks = {
            "port": (lambda v: isinstance(v, str), "a string (device path or pyserial URL)"),
            "baudrate": (lambda v: _is_int(v) and v > 0, "a positive integer"),
            "format": (lambda v: v in ("binary", "ascii"), '"binary" or "ascii"'),
            "count_bits": (lambda v: _is_int(v) and v in (16, 32), "16 or 32"),
            "direction": (lambda v: _is_int(v) and v in (1, -1), "1 or -1"),
            "force_command": (lambda v: isinstance(v, bool), "true or false"),
            "command_units": (lambda v: v in ("N", "N*m"), '"N" or "N*m"'),
            "stale_periods": (lambda v: _is_num(v) and 1 <= v <= 3, "a number from 1 to 3"),
            "tolerate_drops": (lambda v: _is_int(v) and v >= 0, "an integer >= 0"),
            "tolerate_link_errors": (lambda v: isinstance(v, bool), "true or false"),
            "sync_timeout_s": (
                lambda v: _is_num(v) and 0 < v <= 60,
                "a number of seconds in (0, 60]",
            ),
        }
        for name, value in table.items():
            ok, what = checks[name]
            if not ok(value):
                raise UserError(f"{rig.source}: [serial] {name} must be {what}, got {value!r}")
        return cls(**table)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class Decoded(NamedTuple):
    sample: Sample
    lost: int  # samples missing right before this one


class Reboot(NamedTuple):
    reason: str


class StreamDecoder:
    """Bytes -> calibrated samples, with unwrapping and gap/reboot detection (no I/O).

    ``seq`` of a sample is the unwrapped board sequence number (binary) or
    ``round(micros / T)`` (ASCII, which carries no sequence number), so a gap
    in ``seq`` is a loss in both forms. Board time going backwards (or a
    binary sequence number not advancing) is a reboot: the unwrappers restart.
    """

    def __init__(self, config: SerialConfig, sample_time_s: float, metres_per_count: float):
        self.binary = config.format == "binary"
        self.parser = framing.BinarySampleParser() if self.binary else framing.AsciiSampleParser()
        self._T_us = sample_time_s * 1e6
        self._scale = config.direction * metres_per_count
        self._count = Unwrapper(config.count_bits, signed=True)
        self._time = Unwrapper(32, signed=False)
        self._seq = Unwrapper(16, signed=False)
        self._last_seq: int | None = None
        self.samples = self.lost = self.reboots = self.duplicates = 0
        self._base: dict = {}  # the counters when the stream was established

    def reset(self) -> None:
        """Forget the stream position (after a reboot or before a new sync)."""
        self._count.reset()
        self._time.reset()
        self._seq.reset()
        self._last_seq = None

    def feed(self, data: bytes) -> list[Decoded | Reboot]:
        out: list[Decoded | Reboot] = []
        for raw in self.parser.feed(data):
            t_prev = self._time.value
            t_us = self._time.update(raw.t_us)
            if self.binary:
                seq = self._seq.update(raw.seq)
                went_back = self._last_seq is not None and seq <= self._last_seq
            else:
                seq = round(t_us / self._T_us)
                went_back = False
                if (
                    self._last_seq is not None
                    and seq <= self._last_seq
                    and self._time.last_step >= 0
                ):
                    self.duplicates += 1  # two lines in one period: keep the first
                    continue
            if self._time.last_step < 0 or went_back:
                self.reboots += 1
                out.append(
                    Reboot(
                        f"board rebooted: time went from {t_prev} us to {raw.t_us} us"
                        + (f", sequence to {raw.seq}" if self.binary else "")
                    )
                )
                self.reset()
                t_us = self._time.update(raw.t_us)
                seq = self._seq.update(raw.seq) if self.binary else round(t_us / self._T_us)
            lost = 0 if self._last_seq is None else seq - self._last_seq - 1
            self._last_seq = seq
            count = self._count.update(raw.count)
            flags = (FLAG_LOST if lost else 0) | (FLAG_LINK_ERRORS if raw.skipped else 0)
            for status_bit, flag in _STATUS_FLAGS:
                if raw.status & status_bit:
                    flags |= flag
            self.samples += 1
            self.lost += lost
            out.append(Decoded(Sample(seq, t_us * 1e-6, count * self._scale, flags), lost))
        return out

    def _raw_counters(self) -> dict:
        p = self.parser
        link = (
            {"crc_errors": p.crc_errors, "bad_frames": p.bad_frames}
            if self.binary
            else {"malformed_lines": p.malformed, "comment_lines": p.comments}
        )
        return {
            "samples": self.samples,
            "lost": self.lost,
            "reboots": self.reboots,
            "duplicates": self.duplicates,
            "garbage_bytes": p.garbage_bytes,
            **link,
        }

    def counters(self) -> dict:
        """Since the stream was established (``start_counting``), or since the start."""
        return {k: v - self._base.get(k, 0) for k, v in self._raw_counters().items()}

    def start_counting(self) -> dict:
        """The link counters count from now on (the connection): what was seen before (a
        board's boot text, the partial frame it was in when the port opened, the
        handshake's samples) is no link error. Returns those counts."""
        before = self.counters()
        self._base = self._raw_counters()
        return before


def _with_flags(s: Sample, bits: int) -> Sample:
    return Sample(s.seq, s.t_s, s.position_m, s.flags | bits)


class SerialStream:
    """``Device`` over an open pyserial port (a real port, a pty path or ``loop://``).

    ``on_close`` runs once after the port is closed (``open_sim_serial`` stops
    its simulated board there). A lock-step simulated board's time is not wall
    time: it passes ``paced=False`` (the loop then does not judge its periods)
    and ``stale_s``, which overrides ``stale_periods * T``; ``kind`` names it
    in ``describe()``, ``simulated`` says what stands in for the board ("" for a
    real one) and ``device_delay_s`` (with ``device_delay_why``) the delay the
    board is known to add to every command (``labbench.device_delay``); ``warnings``
    go into the session. ``clock`` is injectable for tests.

    Before ``enable()`` a read returns the newest sample waiting (older ones are
    dropped: nothing is driven yet, and a stale backlog would only add latency);
    after it, every sample in order.
    """

    def __init__(
        self,
        port,
        config: SerialConfig,
        rig,
        on_close: Callable[[], None] | None = None,
        stale_s: float | None = None,
        paced: bool = True,
        kind: str = "serial",
        clock: Callable[[], float] = time.monotonic,
        simulated: str = "",
        device_delay_s: float = 0.0,
        device_delay_why: str = "",
        warnings: tuple = (),
    ):
        self.port = port
        self.config = config
        self.rig = rig
        self.T = rig.sample_time_s
        self._on_close = on_close
        self._paced, self._kind = paced, kind
        self._simulated, self._warnings = simulated, list(warnings)
        self._delay = (device_delay_s, device_delay_why)
        self.handshake: dict = {}  # what the handshake discarded (``wait_for_stream``)
        self._estopped = False
        self.timing_log: list | None = None  # labbench.device.TimingProbe (preflight)
        self._arrivals: dict = {}  # seq -> (silence began, arrival), while timing_log is on
        self._clock = clock
        self._decoder = StreamDecoder(config, self.T, rig.position_per_count)
        self._ready: deque[Sample] = deque()
        self._stale_s = config.stale_periods * self.T if stale_s is None else stale_s
        # Poll granularity of a blocking read: bounds how late a stale stream is seen.
        self._poll_s = self.T / 4
        port.timeout = self._poll_s
        port.write_timeout = 0.02  # loop:// and other non-posix ports only (see _write)
        # A posix port is written with one non-blocking os.write: pyserial's write
        # timeout also fires when the thread is merely descheduled after writing.
        try:
            self._fd = port.fileno()
        except (AttributeError, OSError):  # io.UnsupportedOperation is an OSError
            self._fd = None
        self._unit = rig.lever_arm_m if config.command_units == "N*m" else 1.0
        self._enabled = False
        self._fault: str | None = None
        self._closed = False
        self._last_arrival = clock()
        self._last_seq = 0
        self._force = 0.0
        self.stale_trips = 0

    # -- Device protocol ---------------------------------------------------------------
    def describe(self) -> DeviceDescription:
        c = self.config
        return DeviceDescription(
            kind=self._kind,
            name=f"serial encoder stream on {c.port or getattr(self.port, 'port', '?')}",
            sample_time_s=self.T,
            force_limit_n=self.rig.force_limit_n if c.force_command else 0.0,
            position_limits_m=tuple(self.rig.position_limits_m),
            details={
                "config": asdict(c),
                "counters": self.counters(),
                "handshake": dict(self.handshake),
                "paced": self._paced,
                "stale_s": self._stale_s,
                "metres_per_count": self.rig.metres_per_count,
                **({"warnings": list(self._warnings)} if self._warnings else {}),
            },
            device_delay_s=self._delay[0],
            device_delay_why=self._delay[1],
            simulated=self._simulated,
            cannot_act="" if c.force_command else (
                f"{self.rig.source}: [serial] force_command = false: this board takes no force "
                "commands (it only streams its count); set force_command = true once its sketch "
                "reads the 'F' frames of docs/serial-protocol.md"),
        )

    def counters(self) -> dict:
        return {**self._decoder.counters(), "stale_trips": self.stale_trips}

    stale_periods_max = 3  # SerialConfig's bound: the sketch's own watchdog is 3 periods

    @property
    def stale_limit_s(self) -> float:
        """The longest silence between frames that never faults while enabled
        (``TimingProbe``): the stale limit and one poll, since what arrives during the poll
        that crosses the limit is read before silence is judged (``read``)."""
        return self._stale_s + self._poll_s

    @stale_limit_s.setter
    def stale_limit_s(self, seconds: float) -> None:
        self._stale_s = seconds - self._poll_s

    def wait_for_stream(self, timeout: float) -> None:
        """Block until the board streams ``SYNC_SAMPLES`` good samples in a row.

        Boot noise and garbage before them are discarded (and counted). A board
        period that does not match the rig's sample time is a ``UserError``.
        """
        self._check_open()
        deadline = self._clock() + timeout
        good: list[Sample] = []
        self._ready.clear()
        duplicates = self._decoder.duplicates
        while len(good) < SYNC_SAMPLES:
            if self._clock() >= deadline:
                raise UserError(
                    f"no {self.config.format} sample stream on "
                    f"{self.port.port or self.config.port} within {timeout:g} s (got {len(good)} "
                    f"good samples; counters {self._decoder.counters()}): "
                    "check port, baudrate, format and that the board runs the labbench sketch"
                )
            for item in self._decoder.feed(self._read_chunk()):
                # An ASCII "loss" is a time gap measured in the rig's T: with a
                # mismatched period every line is one, and the check below says so.
                if isinstance(item, Reboot) or (item.lost and self._decoder.binary):
                    good.clear()
                if isinstance(item, Decoded):
                    good.append(item.sample)
                    self._last_seq = item.sample.seq
                    self._send(0.0)  # keeps a lock-step board moving and its watchdog fed
            if self._decoder.duplicates != duplicates:
                raise UserError(
                    "the board sends more than one line per sample period: its period is "
                    f"shorter than the rig's sample_time_s of {self.T * 1e3:.3f} ms"
                )
        period = statistics.median(b.t_s - a.t_s for a, b in itertools.pairwise(good))
        if abs(period - self.T) > PERIOD_TOLERANCE * self.T:
            raise UserError(
                f"the board streams every {period * 1e3:.3f} ms but the rig's "
                f"sample_time_s is {self.T * 1e3:.3f} ms"
            )
        self.handshake = self._decoder.start_counting()
        self._last_arrival = self._clock()

    def enable(self, timeout: float = 1.0) -> None:
        """Arm the driver: nonzero forces pass, and stale, lost or rebooted streams fault.

        Takes no sample away from the caller. The stream must be live: a sample
        within ``stale_s`` or one arriving within ``timeout`` (kept for the next
        ``read``). After a latched fault (operator re-enable) only the newest
        waiting sample is kept; after a reboot that is one counted from the
        board's new zero.
        """
        self._check_open()
        if self._fault:
            while len(self._ready) > 1:
                self._ready.popleft()
        deadline = self._clock() + timeout
        while not self._ready and self._clock() - self._last_arrival > self._stale_s:
            if self._clock() >= deadline:
                raise DeviceFault(
                    f"cannot enable: no serial sample within {timeout:g} s "
                    f"(counters {self.counters()})"
                )
            self._ingest(self._read_chunk())
        self._fault = None
        self._estopped = False
        self._force = 0.0
        self._enabled = True

    def disable(self, timeout: float = 1.0) -> None:
        self._enabled = False
        self._force = 0.0
        self._send(0.0)

    def emergency_stop(self) -> None:
        self._estopped = True
        self._latch("emergency stop")

    def read(self, timeout: float) -> Sample:
        self._check_open()
        if self._fault:
            raise DeviceFault(self._fault)
        if not self._paced:
            # A lock-step board's time is virtual: a caller's wall-time timeout (the
            # loop's watchdog) means nothing there; the board's own stale limit rules.
            timeout = max(timeout, self._stale_s)
        deadline = self._clock() + timeout
        while not self._ready:
            # What is waiting is read before silence is judged: a host held off the
            # CPU past the limit finds the board's samples queued; the stall is the
            # host's (the loop's watchdog counts it), not the board's.
            self._ingest(self._read_chunk())
            if self._ready:
                break
            now = self._clock()
            if self._enabled and now - self._last_arrival >= self._stale_s:
                self.stale_trips += 1
                self._trip(
                    f"serial stream stale: no sample for {(now - self._last_arrival) * 1e3:.2f} ms "
                    f"({self._stale_s * 1e3:.2f} ms allowed) after seq {self._last_seq}"
                )
            if now >= deadline:
                if self._enabled:
                    self._trip(
                        f"no serial sample within the read timeout of {timeout * 1e3:.1f} ms"
                    )
                raise TimeoutError(f"no serial sample within {timeout:g} s")
        if not self._enabled:
            while len(self._ready) > 1:
                self._ready.popleft()
        s = self._ready.popleft()
        if self._ready:
            s = _with_flags(s, FLAG_BACKLOG)
        self._last_seq = s.seq
        if self.timing_log is not None and s.seq in self._arrivals:
            began, arrival = self._arrivals.pop(s.seq)
            self.timing_log.append((math.nan, began, arrival, math.nan))
        return s

    def command(self, force_n: float) -> None:
        if not math.isfinite(force_n):
            self._trip(f"non-finite force command {force_n!r}")
        if self._fault or not self._enabled:
            force_n = 0.0
        lim = self.rig.force_limit_n
        self._force = min(max(force_n, -lim), lim)
        self._send(self._force)
        if self._fault is not None and self._force:
            # emergency_stop() from another thread raced this command: undo it at once.
            self._force = 0.0
            self._send(0.0)

    def render_on_board(self, ve, on: bool = True) -> None:
        """Have a protocol-v2 board render ``ve`` (spring, damper, spring-damper: K, B,
        w0) from its own encoder at its render rate, clamped to the rig's force limit;
        ``command()`` values are then the excitation added to it. ``on=False``: back to
        the host loop. Samples carry ``FLAG_BOARD_RENDERING`` while it renders."""
        if not self.config.force_command:
            raise UserError("on-board rendering needs [serial] force_command = true")
        if ve.td:
            raise UserError(f"the board renders with its own delay (one render tick), not td = {ve.td:g} s")
        u = self._unit  # values in command units: N, or N m at the joint
        scale = self.config.direction * self.rig.position_per_count
        frame = framing.encode_params(on, ve.K * u, ve.B * u, ve.w0, self.rig.force_limit_n * u,
                                      scale)
        self._write_frame(frame)

    @property
    def commanded_force_n(self) -> float:
        """The force last sent (0 after any fault)."""
        return self._force

    @property
    def fault(self) -> str | None:
        return self._fault

    def status(self) -> DeviceStatus:
        state = ("closed" if self._closed else ESTOP_STATE if self._estopped
                 else "fault" if self._fault else "enabled" if self._enabled else "disabled")
        return DeviceStatus(state, self._fault, self.counters())

    def close(self) -> None:
        if self._closed:
            return
        self._enabled = False
        self._force = 0.0
        self._send(0.0)
        self._closed = True
        try:
            self.port.close()
        finally:
            if self._on_close is not None:
                self._on_close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals ---------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise DeviceFault("serial device is closed")

    def _read_chunk(self) -> bytes:
        """Whatever is waiting, or block up to one poll interval for the first byte."""
        try:
            n = self.port.in_waiting
            data = self.port.read(n or 1)
            if data and not n:
                n = self.port.in_waiting
                if n:
                    data += self.port.read(n)
            return data
        except Exception as exc:  # noqa: BLE001 - SerialException, OSError, ...: the port is gone
            self._trip(f"serial port lost: {exc}")

    def _ingest(self, data: bytes) -> None:
        """Decode ``data`` into the queue; a fault latches at once and raises after the
        whole chunk is decoded (counters stay right, later samples stay queued)."""
        if not data:
            return
        arrival = self._clock()
        reason = None
        for item in self._decoder.feed(data):
            if isinstance(item, Reboot):
                self._ready.clear()  # positions before a reboot belong to another zero
                if self._enabled:
                    reason = reason or item.reason + " (encoder zero lost)"
                    self._latch(reason)
                continue
            if self._enabled and item.lost > self.config.tolerate_drops:
                reason = reason or (
                    f"{item.lost} serial sample(s) lost before seq {item.sample.seq} "
                    f"({self.config.tolerate_drops} tolerated)"
                )
                self._latch(reason)
            elif (
                self._enabled
                and item.sample.flags & FLAG_LINK_ERRORS
                and not self.config.tolerate_link_errors
            ):
                reason = reason or (
                    f"serial link error: bytes discarded before seq {item.sample.seq} "
                    f"(garbage, CRC or framing; counters {self._decoder.counters()})"
                )
                self._latch(reason)
            self._ready.append(item.sample)
            if self.timing_log is not None:
                self._arrivals[item.sample.seq] = (self._last_arrival, arrival)
            self._last_arrival = arrival
        if reason is not None:
            raise DeviceFault(self._fault)

    def _send(self, force_n: float) -> None:
        if not self.config.force_command or self._closed:
            return
        try:
            self._write_frame(framing.encode_command(self._last_seq, force_n * self._unit))
        except Exception as exc:  # noqa: BLE001 - full buffer, write timeout or lost port
            if force_n != 0.0:
                self._trip(f"cannot send force command: {exc}")

    def _write_frame(self, frame: bytes) -> None:
        if self._fd is None:
            self.port.write(frame)
        elif os.write(self._fd, frame) != len(frame):
            raise BlockingIOError("output buffer full")

    def _latch(self, reason: str) -> None:
        """Zero the force and latch ``reason`` (never raises)."""
        self._enabled = False
        self._force = 0.0
        if self._fault is None:
            self._fault = f"{reason}; force zeroed"
        self._send(0.0)  # best effort (never raises for zero): the board's watchdog zeroes too

    def _trip(self, reason: str):
        self._latch(reason)
        raise DeviceFault(self._fault)


def open_serial(
    rig, realtime: bool = True, seed: int | None = None, port: str | None = None
) -> SerialStream:
    """Open the board of ``rig``'s ``[serial]`` table and wait for its stream.

    ``port`` overrides the table's port.

    ``realtime`` and ``seed`` are accepted (and unused: hardware is always real
    time) so that every device opens with the same call.
    """
    import serial

    config = SerialConfig.from_rig(rig, **({"port": port} if port else {}))
    if not config.port:
        raise UserError(f'{rig.source}: [serial] port is not set (e.g. port = "/dev/ttyACM0")')
    try:
        ser = serial.serial_for_url(config.port, baudrate=config.baudrate, timeout=0)
    except (serial.SerialException, ValueError) as exc:
        raise DeviceConnectionError(f"cannot open serial port {config.port}: {exc}") from None
    dev = SerialStream(ser, config, rig)
    try:
        dev.wait_for_stream(config.sync_timeout_s)
    except BaseException:
        dev.close()
        raise
    return dev
