"""``labbench devices --rig RIG``: open the rig's serial board and say what it sends.

Read-only: the port is opened as a run opens it (an Arduino resets on it), the stream
is waited for with the rig's ``[serial]`` table exactly as ``labbench run`` waits for it
(``SerialStream.wait_for_stream``), nothing is ever commanded; then ``PROBE_S`` more
of samples show whether the count moves. The answer says what arrived (bytes, the
first lines), how the samples are timed (period, steps), the counts, and either that
the rig reads this board or the one-line refusal ``labbench run`` would give.
"""
from __future__ import annotations

import time

from labbench.drivers import framing
from labbench.drivers.serial_stream import SerialConfig, SerialStream, open_port
from labbench.errors import LabbenchError, UserError

PROBE_S = 1.0  # samples read after the handshake, to see the count move
FIRST_LINES = 5


def probe_serial(rig, fault_reset: bool = False) -> dict:
    """What the board on the rig's port sends (module doc); ``{"no_answer": why}`` when it
    sends nothing; ``refused`` in the answer when the rig's table cannot read it."""
    if fault_reset:
        raise UserError("--fault-reset is for a CANopen drive; a serial board has no fault state")
    config = SerialConfig.from_rig(rig)
    # force_command off: a probe never sends a force, whatever the table says
    dev = SerialStream(open_port(config, rig), SerialConfig.from_rig(rig, force_command=False), rig)
    answer: dict = {"kind": "serial", "port": config.port, "baudrate": config.baudrate}
    try:
        try:
            dev.wait_for_stream(config.sync_timeout_s)
        except UserError as exc:
            answer["refused"] = str(exc)
        else:
            answer["counts"] = _counts(dev, rig)
    finally:
        dev.close()
    seen = dev.seen
    answer.update(bytes=seen.nbytes, seconds=round(seen.seconds, 3),
                  first_lines=first_lines(bytes(seen.head), config.format),
                  stream=dev.stream_info(), counters=dev.counters())
    if not seen.nbytes:
        return {"no_answer": answer["refused"], **answer}
    return answer


def _counts(dev: SerialStream, rig) -> dict:
    """The counts of ``PROBE_S`` of samples (all of them: the driver is armed at zero force,
    which on a position-only board sends nothing)."""
    mpc = rig.metres_per_count * dev.config.direction
    counts = []
    end = time.monotonic() + PROBE_S
    dev.stale_limit_s = max(dev.stale_limit_s, PROBE_S)  # reading only: a late host is no fault
    try:
        dev.enable()
        while time.monotonic() < end:
            counts.append(round(dev.read(max(PROBE_S, 1.0)).position_m / mpc))
    except (LabbenchError, TimeoutError) as exc:
        return {"n": len(counts), "error": str(exc), **_span(counts)}
    return {"n": len(counts), "seconds": PROBE_S, **_span(counts)}


def _span(counts: list[int]) -> dict:
    if not counts:
        return {"moving": False}
    return {"first": counts[0], "last": counts[-1], "min": min(counts), "max": max(counts),
            "moving": max(counts) != min(counts)}


def first_lines(head: bytes, fmt: str) -> list[str]:
    """The first lines as they came (bytes that are not text escaped), or, for a binary
    stream, its first bytes in hex."""
    if fmt == "binary" and framing.BinarySampleParser().feed(head):
        return [head[:32].hex(" ")]
    lines = head.split(b"\n")[:FIRST_LINES]
    return ["".join(chr(b) if 0x20 <= b < 0x7F else f"\\x{b:02x}" for b in ln.rstrip(b"\r")[:60])
            for ln in lines if ln.strip()]
