"""What a UART receiver set to the wrong baud rate makes of a byte stream.

A pty carries no baud rate, so the simulated boards cannot show a baud mismatch by
themselves; this puts the bytes on an 8N1 wire at the sender's rate and samples them
as a receiver at another rate does: it waits for a falling edge (a start bit), samples
each of the 10 bits at its middle, and delivers the 8 data bits LSB first. A stop bit
read low is a framing error, which a Linux tty in raw mode (no IGNPAR, no PARMRK;
termios(3)) hands to the program as a 0x00 byte; the receiver then waits for the line
to go high before it looks for the next start bit. Bytes are sent back to back, the
line idles high between bursts (``gaps``).
"""
from __future__ import annotations

import numpy as np


def wire_bits(data: bytes, gaps: dict[int, float] | None = None) -> np.ndarray:
    """The line level per sender bit time: per byte a start bit (0), 8 data bits LSB
    first, a stop bit (1); ``gaps`` {byte index: idle bit times before it}."""
    out = []
    gaps = gaps or {}
    for i, b in enumerate(data):
        idle = int(round(gaps.get(i, 0)))
        out.extend([1] * idle)
        out.append(0)
        out.extend((b >> k) & 1 for k in range(8))
        out.append(1)
    out.extend([1] * 12)  # the line rests high after the last byte
    return np.array(out, dtype=np.uint8)


def received(data: bytes, sent_baud: float, read_baud: float,
             gaps: dict[int, float] | None = None) -> bytes:
    """The bytes a receiver at ``read_baud`` reads from ``data`` sent at ``sent_baud``."""
    level = wire_bits(data, gaps)
    n = len(level)
    step = sent_baud / read_baud  # one receiver bit, in sender bit times
    # falling edges: where the level goes from 1 to 0 (time of the edge in sender bits)
    falls = np.flatnonzero((level[1:] == 0) & (level[:-1] == 1)) + 1
    if level[0] == 0:
        falls = np.r_[0, falls]
    out = bytearray()
    t = 0.0  # the receiver looks for a start bit from here on
    i = 0
    while i < len(falls):
        edge = falls[i]
        if edge < t:
            i += 1
            continue
        samples = edge + (np.arange(10) + 0.5) * step
        if samples[-1] >= n:
            break
        bits = level[samples.astype(int)]
        if bits[0] != 0:  # a glitch shorter than half a bit: no start bit
            t = edge + 1
            i += 1
            continue
        stop_at = samples[-1]
        if bits[9] == 1:
            out.append(int(sum(int(bits[1 + k]) << k for k in range(8))))
            t = stop_at
        else:  # framing error: read as 0x00, then wait for the line to go high
            out.append(0)
            high = np.flatnonzero(level[int(stop_at):] == 1)
            if not high.size:
                break
            t = int(stop_at) + high[0]
        i += 1
    return bytes(out)
