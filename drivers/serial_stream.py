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
from labbench.drivers import serial_diagnosis as diagnosis
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
SYNC_LINES = 12  # ASCII: good lines that make it, and show their timing
HOST_TIMED_S = 0.25  # an untimed ASCII board: the host's clock measures its period this long
PERIOD_TOLERANCE = diagnosis.PERIOD_TOLERANCE


@dataclass(frozen=True)
class SerialConfig:
    """The ``[serial]`` table of a rig file (see docs/serial-protocol.md)."""

    port: str = ""
    baudrate: int = 500_000
    format: str = "binary"  # "binary" | "ascii"
    # ASCII: the columns of a line in order (framing.ascii_line): a time field ("micros" or
    # "millis"; none: the host numbers lines at the rig's period), "count", other names ignored
    fields: tuple = framing.DEFAULT_FIELDS
    on_change: bool = False  # ASCII: the board prints only when its count changes (held)
    count_bits: int = 32  # width of the board's encoder counter: 16 | 32
    count_signed: bool = True  # the counter is signed (int, long) or unsigned
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
            "fields": (_fields_ok, 'a list of 1 to 8 distinct names in line order, with '
                                   '"count" once and at most one time field ("micros" or '
                                   '"millis"), e.g. ["millis", "count"]'),
            "on_change": (lambda v: isinstance(v, bool), "true or false"),
            "count_bits": (lambda v: _is_int(v) and v in (16, 32), "16 or 32"),
            "count_signed": (lambda v: isinstance(v, bool), "true or false"),
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
        if "fields" in table:
            table["fields"] = tuple(table["fields"])
        fmt = table.get("format", cls.format)
        for name in ("fields", "on_change"):
            if fmt == "binary" and name in table and table[name] != getattr(cls, name):
                raise UserError(f"{rig.source}: [serial] {name} is for text lines (format = "
                                '"ascii"); a binary board sends the frames of '
                                "docs/serial-protocol.md")
        if table.get("on_change") and table.get("force_command"):
            raise UserError(f"{rig.source}: [serial] on_change = true cannot take force commands: "
                            "a board that prints only on change looks the same dead or still, so "
                            "no stale limit can stop the force: print at a fixed rate, or set "
                            "force_command = false")
        return cls(**table)


def _fields_ok(v) -> bool:
    names = list(v) if isinstance(v, (list, tuple)) else []
    return (1 <= len(names) <= 8 and all(isinstance(n, str) and n.isidentifier() for n in names)
            and len(set(names)) == len(names) and names.count("count") == 1
            and sum(n in framing.TIME_FIELDS for n in names) <= 1)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class Decoded(NamedTuple):
    sample: Sample
    lost: int  # samples missing right before this one


class Reboot(NamedTuple):
    reason: str


class Mismatch(NamedTuple):
    """A count the rig's counter cannot have printed: the line naming the change."""

    reason: str


class StreamDecoder:
    """Bytes -> calibrated samples, with unwrapping and gap/reboot detection (no I/O).

    ``seq`` of a sample: binary, the unwrapped board sequence number; an ASCII line with
    a time field, the previous line's seq plus its board-time step in periods (rounded: a
    step under half a period is a second line in one period, a duplicate, dropped), so a
    gap in ``seq`` is a loss in both forms; an ASCII line without a time field (or printed
    on change), its number: a lost line cannot be seen. ``t_s``: binary, the board's
    time; ASCII, ``seq * T`` (the loop and the analyses take samples a period apart: what
    the board's own stamps say of its timing is in ``seen``). Board time going backwards,
    a binary sequence number not advancing, or an untimed board's banner coming again
    (``framing.BANNER_AGAIN``) is a reboot: the unwrappers restart. A count the rig's
    counter cannot have printed is a ``Mismatch`` (``serial_diagnosis.count_problem``).
    """

    def __init__(self, config: SerialConfig, sample_time_s: float, metres_per_count: float):
        self.binary = config.format == "binary"
        self.parser = (framing.BinarySampleParser() if self.binary
                       else framing.AsciiSampleParser(config.fields))
        self._T, self._T_us = sample_time_s, sample_time_s * 1e6
        field = next((f for f in config.fields if f in framing.TIME_FIELDS), None)
        self.time_field = "micros" if self.binary else None if config.on_change else field
        self._unit_us = framing.TIME_FIELDS.get(self.time_field or "", 0)
        self._scale = config.direction * metres_per_count
        self._bits, self._signed = config.count_bits, config.count_signed
        self._count = Unwrapper(config.count_bits, signed=config.count_signed)
        self._time = Unwrapper(32, signed=False)
        self._seq = Unwrapper(16, signed=False)
        self._last_seq: int | None = None
        self._raw_count: int | None = None
        self.samples = self.lost = self.reboots = self.duplicates = 0
        self._base: dict = {}  # the counters when the stream was established
        # (board time [us] or None, raw count, arrival) of the first lines or frames
        self.seen: list = []

    def reset(self) -> None:
        """Forget the stream position (after a reboot or before a new sync)."""
        self._count.reset()
        self._time.reset()
        self._seq.reset()
        self._last_seq = self._raw_count = None

    def _place(self, raw) -> tuple[int | None, bool, str]:
        """(seq, went back, what went back) of ``raw``; seq None: a duplicate line."""
        if self.binary:
            t_prev = self._time.value
            self._time.update(raw.t_us)
            seq = self._seq.update(raw.seq)
            back = self._time.last_step < 0 or (self._last_seq is not None and seq <= self._last_seq)
            return seq, back, (f"time went from {t_prev} us to {raw.t_us} us, sequence to "
                               f"{raw.seq}")
        if self.time_field is None:
            seq = 0 if self._last_seq is None else self._last_seq + 1
            return seq, bool(raw.status & framing.BANNER_AGAIN), "its banner came again"
        unit = "us" if self._unit_us == 1 else "ms"
        t_prev = self._time.value
        t = self._time.update(raw.t_us)
        if self._last_seq is None:
            return round(t * self._unit_us / self._T_us), False, ""
        step = self._time.last_step * self._unit_us / self._T_us
        if step < 0:
            return None, True, f"time went from {t_prev} {unit} to {raw.t_us} {unit}"
        return (None if step < 0.5 else self._last_seq + round(step)), False, ""

    def feed(self, data: bytes, arrival: float | None = None) -> list[Decoded | Reboot | Mismatch]:
        out: list[Decoded | Reboot | Mismatch] = []
        for raw in self.parser.feed(data):
            if len(self.seen) < diagnosis.KEPT_SAMPLES:
                t = None if raw.t_us is None or not self._unit_us else raw.t_us * self._unit_us
                self.seen.append((t, raw.count, arrival))
            problem = diagnosis.count_problem(raw.count, self._raw_count, self._bits,
                                              self._signed)
            if problem:
                out.append(Mismatch(problem))
                continue
            seq, back, why = self._place(raw)
            if back:
                self.reboots += 1
                out.append(Reboot(f"board rebooted: {why}"))
                self.reset()
                seq = self._place(raw)[0]
            elif seq is None:
                self.duplicates += 1  # two lines in one period: keep the first
                continue
            self._raw_count = raw.count
            lost = 0 if self._last_seq is None else seq - self._last_seq - 1
            self._last_seq = seq
            count = self._count.update(raw.count)
            flags = (FLAG_LOST if lost else 0) | (FLAG_LINK_ERRORS if raw.skipped else 0)
            for status_bit, flag in _STATUS_FLAGS:
                if raw.status & status_bit:
                    flags |= flag
            self.samples += 1
            self.lost += lost
            t_s = self._time.value * 1e-6 if self.binary else seq * self._T
            out.append(Decoded(Sample(seq, t_s, count * self._scale, flags), lost))
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
    board is known to add to every command (``labbench.model.device_delay``); ``warnings``
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
        self.seen: diagnosis.Seen | None = None  # what arrived during the handshake
        # on_change: the newest line's sample, held; sampled every T of the host's clock
        self._held: Sample | None = None
        self._held_flags, self._tick0, self._k = 0, 0.0, 0
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
                "stream": self.stream_info(),
                # the board's sketch fixes its period: a host tool never rewrites it alone
                **({} if c.on_change else {"period_fixed_by": "the board's sketch"}),
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

    def stream_info(self) -> dict:
        """How samples are timed and what the handshake measured: ``time`` (the board's
        micros or millis field, or the host: lines numbered at the rig's period, or the
        count held and sampled every T), ``period_s`` (median step of the board's time
        field, or the host's clock over the handshake's lines; None on change), the
        handshake's step range ``steps_s`` and ``lines``."""
        c, field = self.config, self._decoder.time_field
        time_from = (f"board {field}" if field else "host: the count held and sampled every T"
                     if c.on_change else "host: lines numbered at the rig's period")
        info = {"format": c.format, "fields": list(c.fields) if c.format == "ascii" else None,
                "time": time_from, "period_s": None, "steps_s": None,
                "lines": len(self.seen.samples) if self.seen else 0}
        samples = self.seen.samples if self.seen else []
        steps = diagnosis.periods(samples)
        if steps:
            info.update(period_s=statistics.median(steps), steps_s=[min(steps), max(steps)])
        elif len(samples) > 1 and not c.on_change and samples[0][2] is not None:
            info["period_s"] = (samples[-1][2] - samples[0][2]) / (len(samples) - 1)
        return info

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

    def sync_lines(self) -> int:
        """Good samples in a row that establish the stream: ``SYNC_SAMPLES`` frames; ASCII,
        ``SYNC_LINES`` lines (an untimed board's over ``HOST_TIMED_S`` at least, its period
        measured by the host's clock); one line of a board that prints on change."""
        c = self.config
        if c.format == "binary":
            return SYNC_SAMPLES
        if c.on_change:
            return 1
        if self._decoder.time_field is None:
            return max(SYNC_LINES, math.ceil(HOST_TIMED_S / self.T))
        return SYNC_LINES

    def wait_for_stream(self, timeout: float) -> None:
        """Block until the board streams ``sync_lines()`` good samples in a row.

        Boot noise, banners and garbage before them are discarded (and counted). A stream
        that is not what the rig says (silent, another protocol, another baud rate, lines
        of another layout, another time unit or period, no steady rate, a count the rig's
        counter cannot have) is a ``UserError`` naming the cause and the change
        (``labbench.drivers.serial_diagnosis``); ``seen`` keeps what arrived.
        """
        self._check_open()
        start = self._clock()
        deadline = start + timeout
        c, decoder = self.config, self._decoder
        seen = self.seen = diagnosis.Seen(getattr(self.port, "port", None) or c.port)
        good: list[Sample] = []
        need = self.sync_lines()
        self._ready.clear()
        while len(good) < need:
            now = self._clock()
            if now >= deadline:
                raise UserError(diagnosis.refusal(self._seen(now - start), c, self.T, timeout,
                                                  decoder.counters()))
            data = self._read_chunk()
            seen.add(data)
            for item in decoder.feed(data, self._clock()):
                if isinstance(item, Mismatch):
                    raise UserError(item.reason)
                if isinstance(item, Reboot) or (item.lost and decoder.binary):
                    good.clear()
                if isinstance(item, Decoded):
                    good.append(item.sample)
                    self._last_seq = item.sample.seq
                    self._send(0.0)  # keeps a lock-step board moving and its watchdog fed
            if not decoder.binary and len(decoder.seen) > need:  # enough to judge the lines
                problem = diagnosis.timing(self._seen(self._clock() - start), c, self.T)
                if problem:
                    raise UserError(problem)
        self._seen(self._clock() - start)
        problem = diagnosis.timing(seen, c, self.T)
        if problem:
            raise UserError(problem)
        if decoder.binary:
            period = statistics.median(b.t_s - a.t_s for a, b in itertools.pairwise(good))
            if abs(period - self.T) > PERIOD_TOLERANCE * self.T:
                raise UserError(
                    f"the board streams every {period * 1e3:.3f} ms but the rig's sample_time_s "
                    f"is {self.T * 1e3:.3f} ms: set [rig] sample_time_s to the sketch's period "
                    "(PERIOD_US of the reference sketch)")
        self.handshake = decoder.start_counting()
        self._last_arrival = self._clock()
        if c.on_change:
            self._held, self._held_flags = good[-1], 0
            self._tick0, self._k = self._clock(), 0

    def _seen(self, seconds: float) -> diagnosis.Seen:
        """``seen`` with what the parser and decoder kept so far."""
        seen, parser = self.seen, self._decoder.parser
        seen.seconds = seconds
        seen.samples = list(self._decoder.seen)
        seen.text = list(getattr(parser, "text", ()))
        seen.rejected = list(getattr(parser, "rejected", ()))
        return seen

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
        while (not self.config.on_change and not self._ready
               and self._clock() - self._last_arrival > self._stale_s):
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
        if self.config.on_change:
            return self._read_held(timeout)
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

    def _read_held(self, timeout: float) -> Sample:
        """on_change: the count of the newest line, held, sampled at the next tick of the
        host's clock (every T). Silence is no fault: a still handle prints nothing. A host
        late by whole periods skips their ticks (a gap in seq)."""
        due = self._tick0 + self._k * self.T
        deadline = self._clock() + timeout
        while True:
            self._ingest(self._read_chunk())
            while self._ready:
                s = self._ready.popleft()
                self._held, self._held_flags = s, self._held_flags | s.flags
            now = self._clock()
            if now >= due:
                break
            if now >= deadline:
                raise TimeoutError(f"no serial sample within {timeout:g} s")
        k = max(self._k, int((now - self._tick0) / self.T))
        self._k = k + 1
        flags, self._held_flags = self._held_flags, 0
        self._last_seq = k
        return Sample(k, k * self.T, self._held.position_m, flags)

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
        for item in self._decoder.feed(data, arrival):
            if isinstance(item, Mismatch):  # the samples are wrong from here on, enabled or not
                self._latch(item.reason)
                reason = reason or item.reason
                continue
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


def synced(driver: SerialStream) -> SerialStream:
    """``driver`` once its board streams (``wait_for_stream``, the table's sync_timeout_s);
    closed (its board stopped) when it never does."""
    try:
        driver.wait_for_stream(driver.config.sync_timeout_s)
    except BaseException:
        driver.close()
        raise
    return driver


def open_port(config: SerialConfig, rig):
    """The pyserial port of ``config`` (a path or any pyserial URL), opened."""
    import serial

    if not config.port:
        raise UserError(f'{rig.source}: [serial] port is not set (e.g. port = "/dev/ttyACM0")')
    try:
        return serial.serial_for_url(config.port, baudrate=config.baudrate, timeout=0)
    except (serial.SerialException, ValueError) as exc:
        raise DeviceConnectionError(diagnosis.open_failure(config.port, exc)) from None


def open_serial(
    rig, realtime: bool = True, seed: int | None = None, port: str | None = None
) -> SerialStream:
    """Open the board of ``rig``'s ``[serial]`` table and wait for its stream.

    ``port`` overrides the table's port.

    ``realtime`` and ``seed`` are accepted (and unused: hardware is always real
    time) so that every device opens with the same call.
    """
    config = SerialConfig.from_rig(rig, **({"port": port} if port else {}))
    return synced(SerialStream(open_port(config, rig), config, rig))
