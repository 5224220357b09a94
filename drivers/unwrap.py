"""Unwrapping of fixed-width board counters: encoder counts, micros(), sequence numbers.

A ``bits``-wide counter seen at least once per half range is recovered exactly
from modular differences: the true step is the representative of
``(new - old) mod 2**bits`` in ``[-2**(bits-1), 2**(bits-1))``. micros() is 32
bits wide and wraps every 2**32 us = 71.6 min; a 16-bit encoder counter wraps
every 65536 counts.
"""

from __future__ import annotations


def wrap_delta(new: int, old: int, bits: int) -> int:
    """Signed step from ``old`` to ``new`` of a ``bits``-wide counter."""
    half = 1 << (bits - 1)
    return ((new - old + half) & ((1 << bits) - 1)) - half


class Unwrapper:
    """Running unwrapped value of a ``bits``-wide counter.

    ``signed``: the first raw value is read as two's complement (encoder counts
    around zero) rather than unsigned (micros(), sequence numbers). Raw values
    are reduced to their low ``bits`` first, so a 16-bit board may send its
    counter sign-extended or not.
    """

    def __init__(self, bits: int, signed: bool):
        if bits not in (16, 32):
            raise ValueError("bits must be 16 or 32")
        self.bits = bits
        self.signed = signed
        self._mask = (1 << bits) - 1
        self.value: int | None = None
        self._raw = 0
        self.last_step = 0

    def reset(self) -> None:
        self.value = None
        self.last_step = 0

    def update(self, raw: int) -> int:
        """Unwrapped value after ``raw``; ``last_step`` holds the signed step."""
        raw &= self._mask
        if self.value is None:
            self.value = raw - (1 << self.bits) if self.signed and raw >> (self.bits - 1) else raw
            self.last_step = 0
        else:
            self.last_step = wrap_delta(raw, self._raw, self.bits)
            self.value += self.last_step
        self._raw = raw
        return self.value
