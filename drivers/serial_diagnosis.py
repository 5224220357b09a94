"""Why a serial port would not open or a board's stream was refused, in one line that names
the change.

``open_failure``: a port pyserial would not open, by the OS's reason (not there,
permission, busy, not a serial device), once (pyserial nests the reason in its own text).

Pure functions over what the driver's handshake saw (``Seen``: the first bytes, the
text and rejected lines, every sample line's board time, count and arrival). Each
message names the cause, quotes what came beside what was expected, and says which rig
field or which sketch line to change; docs/serial-protocol.md ("Troubleshooting") lists
them. The order of the checks matters: a silent port, then another protocol (text where
frames were expected, labbench frames where text was), then a wrong baud rate (bytes
that are not text), then lines of another layout, then the timing of good lines.
"""
from __future__ import annotations

import errno
import os
import re
import statistics
from dataclasses import dataclass, field

from labbench.drivers import framing

HEAD_BYTES = 4096  # the first bytes kept for the diagnosis
KEPT_SAMPLES = 512  # sample lines kept (board time, count, arrival)
NOISE_SHARE = 0.1  # more bytes than this not text (control, 8-bit): not a text stream
PERIOD_TOLERANCE = 0.1  # relative mismatch allowed between board period and rig sample time
STEADY = 0.25  # a step more than this many periods off a whole number is unsteady
# The board's time field against the host's clock: a factor beyond this is another unit
# (a thousand); an emulator at 0.4 to 2x real time, a USB latency, stay far inside it.
CLOCK_RATIO, CLOCK_SPAN_S = 30.0, 0.05
_TEXT_BYTES = frozenset(range(0x20, 0x7F)) | {0x09, 0x0A, 0x0D}
_BANNER = re.compile(rb"#labbench encoder v\d+")
_NUMBER = re.compile(rb"-?\d+")


@dataclass
class Seen:
    """What arrived while the driver waited for the stream."""

    port: str
    head: bytearray = field(default_factory=bytearray)
    nbytes: int = 0
    samples: list = field(default_factory=list)  # (board time [us] or None, raw count, arrival)
    text: list = field(default_factory=list)  # the first text and '#' lines
    rejected: list = field(default_factory=list)  # the first lines of no accepted form
    seconds: float = 0.0

    def add(self, data: bytes) -> None:
        self.nbytes += len(data)
        room = HEAD_BYTES - len(self.head)
        if room > 0:
            self.head += data[:room]


_OS_REASON = re.compile(r"\[Errno (\d+)\] ([^:\]]+)")  # pyserial's nested '[Errno 2] No such ...'
_LIST_PORTS = "`labbench devices --serial` lists the ports seen"


def open_failure(port: str, exc: Exception) -> str:
    """One line for a port pyserial would not open: which, why, what to check. pyserial says
    the OS's reason twice ('[Errno 2] could not open port X: [Errno 2] No such file or
    directory: X') and a URL's only in its text, so the reason is read from its errno or the
    innermost '[Errno N] reason' of the text."""
    code = getattr(exc, "errno", None)
    nested = _OS_REASON.findall(str(exc))
    if code is None and nested:
        code = int(nested[-1][0])
    if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
        why = f"it is not there (the board unplugged, or under another name: {_LIST_PORTS})"
    elif code in (errno.EACCES, errno.EPERM):
        group = _group_of(port)
        why = (f"permission denied (the port belongs to group '{group}': add your user to it, "
               f"`sudo usermod -aG {group} $USER`, then log in again)")
    elif code == errno.EBUSY:
        why = ("it is busy (another program has it open: a serial monitor, another labbench, "
               "ModemManager; close it and connect again)")
    elif code in (errno.EISDIR, errno.ENOTTY) or "Could not configure port" in str(exc):
        why = f"it is not a serial device (choose the board's port: {_LIST_PORTS})"
    elif code is not None:
        why = f"{os.strerror(code).lower()} (check the port's name or address)"
    else:  # a URL pyserial does not know, or a reason without errno: its text, once
        why = f"{str(exc).strip() or type(exc).__name__} (check the port's name or address)"
    return f"cannot open serial port {port}: {why}"


def _group_of(path: str) -> str:
    """The group owning ``path`` ('dialout' where it cannot be read: Debian's serial group)."""
    try:
        import grp

        return grp.getgrgid(os.stat(path).st_gid).gr_name
    except (ImportError, OSError, KeyError):
        return "dialout"


def _q(line: bytes, limit: int = 40) -> str:
    """A line as quoted in a message: printable ASCII as it is, other bytes escaped."""
    text = "".join(chr(b) if 0x20 <= b < 0x7F else f"\\x{b:02x}" for b in line[:limit])
    return f"`{text}`" + ("..." if len(line) > limit else "")


def _fields(fields) -> str:
    return "[" + ", ".join(f'"{f}"' for f in fields) + "]"


def noise_share(data: bytes) -> float:
    """The share of bytes that are not text (control characters, 8-bit bytes)."""
    return sum(b not in _TEXT_BYTES for b in data) / len(data) if data else 0.0


def _frames_in(data: bytes) -> int:
    parser = framing.BinarySampleParser()
    parser.feed(bytes(data))
    return parser.frames


def _numbers(line: bytes) -> list[int]:
    return [int(m) for m in _NUMBER.findall(line)]


def silent(seen: Seen, cfg, timeout: float) -> str:
    if cfg.on_change:
        return (f"no line from {seen.port} within {timeout:g} s: a board that prints only when "
                "its count changes is silent while the handle is still: move the handle while "
                "it connects (or check the port with `labbench devices --serial`)")
    return (f"no bytes from {seen.port} within {timeout:g} s: the board is silent: check the "
            f"port (`labbench devices --serial`), the cable, and that the sketch calls "
            f"Serial.begin and prints")


def baud(seen: Seen, cfg, what: str) -> str:
    return (f"{seen.nbytes} bytes from {seen.port} never formed a {what} "
            f"({100 * noise_share(bytes(seen.head)):.0f} % not text, e.g. "
            f"{_q(bytes(seen.head[:12]))}): the board sends at another baud rate: set [serial] "
            f"baudrate to the rate in the sketch's Serial.begin(...) (now {cfg.baudrate})")


def binary_read_as_text(seen: Seen, banner: bytes | None) -> str:
    said = (f"its banner {_q(banner)}" if banner else
            f"{_frames_in(bytes(seen.head))} valid sample frames")
    return (f"the board sends labbench binary frames ({said}), not text lines: set [serial] "
            'format = "binary" (or build the reference sketch with -DLABBENCH_ASCII=1 for '
            "text lines)")


def text_read_as_binary(line: bytes) -> str:
    fields = _guess_fields(_numbers(line))
    return (f"the board sends text lines ({_q(line)}), not binary frames: set [serial] "
            f'format = "ascii"' + (f" and fields = {_fields(fields)}" if fields else ""))


def _guess_fields(numbers: list[int]) -> tuple | None:
    """A first guess at a line's columns: a count alone, a time and a count, then extras."""
    if len(numbers) == 1:
        return ("count",)
    if len(numbers) >= 2:
        return ("micros", "count", *(f"field{i + 3}" for i in range(len(numbers) - 2)))
    return None


def layout(seen: Seen, cfg, T: float) -> str:
    """A line of another layout than the rig's ``fields``: quoted beside the expected form,
    and what the line itself suggests."""
    line = seen.rejected[0]
    numbers = [_numbers(r) for r in seen.rejected]
    n = len(numbers[0])
    example = ",".join("-42" if f == "count" else "120000" if f == "micros" else "120"
                       if f == "millis" else "0" for f in cfg.fields)
    said = (f"lines do not match [serial] fields = {_fields(cfg.fields)}: got {_q(line)}, "
            f"expected `{framing.ascii_form(cfg.fields)}` (e.g. `{example}`)")
    same = [len(x) == n for x in numbers]
    if n == 1 and all(same):
        values = [x[0] for x in numbers]
        steps = {abs(b - a) for a, b in zip(values, values[1:])}
        on_change = len(values) > 1 and steps == {1}
        return (f"{said}: a count alone: set fields = [\"count\"]"
                + (" and on_change = true (each line is one count from the last: it prints "
                   "on change)" if on_change else ""))
    if n >= 2 and all(same) and n != len(cfg.fields):
        guess = _guess_fields(numbers[0])
        return (f"{said}: the lines have {n} fields: name them in order, e.g. fields = "
                f"{_fields(_with_time_unit(guess, numbers, T))} (other names are ignored)")
    if n != len(_NUMBER.findall(line)) or b"." in line:
        return f"{said}: the time and the count must be whole numbers"
    return said


def _with_time_unit(guess: tuple, numbers: list[list[int]], T: float) -> tuple:
    """The guess with its first column named millis when it grows by about T in ms."""
    firsts = [x[0] for x in numbers]
    steps = [b - a for a, b in zip(firsts, firsts[1:]) if b > a]
    if steps and abs(statistics.median(steps) - T * 1e3) <= PERIOD_TOLERANCE * T * 1e3:
        return ("millis", *guess[1:])
    return guess


def periods(samples: list) -> list[float]:
    """Board time between consecutive sample lines [s] (None where a line had no time)."""
    return [(b[0] - a[0]) * 1e-6 for a, b in zip(samples, samples[1:])
            if a[0] is not None and b[0] is not None]


def timing(seen: Seen, cfg, T: float) -> str | None:
    """The one-line refusal of good lines whose timing does not fit the rig, or None.

    Time field: its unit (steps a thousand times off the rig's period, or the field a
    thousand times off the host's clock), then the steadiness (steps off a whole number of
    their median), then the period. No time field: the period by the
    host's clock."""
    time_field = next((f for f in cfg.fields if f in framing.TIME_FIELDS), None)
    if cfg.format == "binary" or cfg.on_change:
        return None
    samples = seen.samples
    if time_field is None:
        if len(samples) < 2:
            return None
        span = samples[-1][2] - samples[0][2]
        period = span / (len(samples) - 1)
        if abs(period - T) > PERIOD_TOLERANCE * T:
            return (f"the board prints every {period * 1e3:.3f} ms (by the host's clock over "
                    f"{len(samples)} lines) but the rig's sample_time_s is {T * 1e3:.3f} ms: "
                    f"set [rig] sample_time_s = {_nice(period)} (the sketch fixes its period) "
                    "or change the sketch's period" + _on_change_hint(samples))
        return None
    steps = periods(samples)
    if not steps:
        return None
    unit = framing.TIME_FIELDS[time_field]
    period = statistics.median(steps)
    other = {"micros": ("millis", 1000), "millis": ("micros", 1e-3)}[time_field]
    if period > 0 and abs(period * other[1] - T) <= PERIOD_TOLERANCE * T:
        counted = "milliseconds" if other[0] == "millis" else "microseconds"
        apart = period * 1e6 / unit
        return (f"the board's time field counts {counted}, not {_unit_name(time_field)}: its "
                f"lines are {apart:g} apart for a period of {T * 1e3:g} ms: set [serial] fields "
                f"= {_fields(tuple(other[0] if f == time_field else f for f in cfg.fields))}"
                + (" (or print micros() in the sketch)" if other[0] == "millis" else ""))
    rate = _clock_rate(samples)  # board seconds per host second: about 1 when declared right
    if rate is not None and (rate < 1 / CLOCK_RATIO if time_field == "micros"
                             else rate > CLOCK_RATIO):
        counted = "milliseconds" if time_field == "micros" else "microseconds"
        return (f"the board's time field counts {counted}, not {_unit_name(time_field)}: it "
                f"advances {rate:.3g} s per second of the host's clock: set [serial] fields = "
                f"{_fields(tuple(other[0] if f == time_field else f for f in cfg.fields))} "
                "(and [rig] sample_time_s to the sketch's period)")
    frac = [s / period for s in steps]
    bad = [f for f in frac if f < 1 - STEADY or abs(f - round(f)) > STEADY]
    if len(bad) > max(1, len(frac) // 4):
        return (f"the board prints at no steady rate: its lines are {min(steps) * 1e3:.3g} to "
                f"{max(steps) * 1e3:.3g} ms apart over {len(samples)} lines (rig: "
                f"{T * 1e3:g} ms): if it prints only when the count changes, set [serial] "
                "on_change = true; else schedule its print on a timer (`due += PERIOD`, not "
                "`delay()`)")
    if abs(period - T) > PERIOD_TOLERANCE * T:
        return (f"the board prints every {period * 1e3:.3f} ms (by its {time_field} field) but "
                f"the rig's sample_time_s is {T * 1e3:.3f} ms: set [rig] sample_time_s = "
                f"{_nice(period)} (the sketch fixes its period) or change the sketch's period")
    return None


def _clock_rate(samples: list) -> float | None:
    """The board's time over the host's across the lines (None: too short to tell)."""
    if len(samples) < 2 or samples[0][2] is None or samples[0][0] is None:
        return None
    host = samples[-1][2] - samples[0][2]
    board = (samples[-1][0] - samples[0][0]) * 1e-6
    return board / host if host >= CLOCK_SPAN_S and board > 0 else None


def _unit_name(time_field: str) -> str:
    return "microseconds" if time_field == "micros" else "milliseconds"


def _on_change_hint(samples: list) -> str:
    counts = [s[1] for s in samples]
    steps = {abs(b - a) for a, b in zip(counts, counts[1:])}
    return ("; each line is one count from the last: if it prints only on change, set "
            "[serial] on_change = true") if steps == {1} else ""


def count_problem(raw: int, prev: int | None, bits: int, signed: bool) -> str | None:
    """A count the rig's ``count_bits``/``count_signed`` cannot have printed, or a step that
    is a 16-bit counter wrapping, read as 32 bits: the one line naming the change, or None."""
    lo, hi = (-(1 << bits - 1), (1 << bits - 1) - 1) if signed else (0, (1 << bits) - 1)
    if not lo <= raw <= hi:
        if bits == 16 and -(1 << 15) <= raw <= 0xFFFF:
            other = "false" if raw > 0 else "true"
            return (f"the board printed the count {raw}, beyond a {'signed' if signed else 'unsigned'} "
                    f"16-bit counter: set [serial] count_signed = {other}")
        if bits == 16:
            return (f"the board printed the count {raw}, beyond 16 bits: its counter is wider: set "
                    "[serial] count_bits = 32")
        if -(1 << 31) <= raw <= 0xFFFFFFFF:
            other = "false" if raw > 0 else "true"
            return (f"the board printed the count {raw}, beyond a {'signed' if signed else 'unsigned'} "
                    f"32-bit counter: set [serial] count_signed = {other}")
        return f"the board printed the count {raw}, beyond any 32-bit counter"
    if bits == 32 and prev is not None and all(-(1 << 15) <= v <= 0xFFFF for v in (prev, raw)):
        step = raw - prev
        if abs(step) > 1 << 15 and abs(abs(step) - (1 << 16)) < 1 << 15:
            kind = ("count_signed = false: it printed 0..65535" if max(prev, raw) > 0x7FFF
                    else "count_signed = true: it printed -32768..32767")
            return (f"the count jumped from {prev} to {raw} between two lines (a step of {step}): "
                    f"the board's counter is 16 bits wide and wrapped: set [serial] count_bits = "
                    f"16 ({kind})")
    return None


def _nice(seconds: float) -> str:
    return f"{float(f'{seconds:.3g}'):g}"


def refusal(seen: Seen, cfg, T: float, timeout: float, counters: dict) -> str:
    """Why no stream came within ``timeout``: one line naming the cause and the change."""
    head = bytes(seen.head)
    if not seen.nbytes:
        return silent(seen, cfg, timeout)
    if cfg.format == "binary":
        text = [ln.strip(b"\r") for ln in head.split(b"\n")[1:-1]]
        numeric = [ln for ln in text if _NUMBER.search(ln) and noise_share(ln) == 0]
        if len(numeric) >= 2 and not _frames_in(head):
            return text_read_as_binary(numeric[0])
        if noise_share(head) > NOISE_SHARE and not _frames_in(head):
            return baud(seen, cfg, "frame")
    else:
        banner = next((t for t in seen.text if _BANNER.fullmatch(t)), None)
        if banner or _frames_in(head) >= 2:
            return binary_read_as_text(seen, banner)
        if noise_share(head) > NOISE_SHARE or (b"\n" not in head and seen.nbytes > 2 *
                                               framing.ASCII_MAX_LINE):
            return baud(seen, cfg, "line")
        if seen.rejected:
            return layout(seen, cfg, T)
        if seen.text and not seen.samples:
            return (f"only text from {seen.port} within {timeout:g} s ({_q(seen.text[0])}), "
                    "no sample line"
                    + (": a board that prints only on change is silent while the handle is "
                       "still: move the handle while it connects" if cfg.on_change else
                       f": expected `{framing.ascii_form(cfg.fields)}` lines"))
    return (f"no {cfg.format} sample stream on {seen.port} within {timeout:g} s (counters "
            f"{counters}): check the port, baudrate and format")
