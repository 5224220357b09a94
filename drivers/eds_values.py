"""Values of an EDS/DCF, read by data type (CiA 306), and the neutral value of a type.

An EDS writes an integer in decimal, in hex (``0x`` prefix) or in octal (a
leading ``0``), with an optional sign, and may add the node id
(``$NODEID+0x180`` or ``0x180+$NODEID``). A signed value written as a hex or
octal bit pattern is two's complement in the width of its type: ``0xFFFF8000``
is -32768 for an INTEGER32 (vendor files do this). Anything outside the range
of its type is refused with the reason, never wrapped silently.

Data type codes: CiA 301, table 44.
"""
from __future__ import annotations

import re

BOOLEAN, REAL32, REAL64 = 0x01, 0x08, 0x11
STRINGS = (0x09, 0x0B)  # VISIBLE_STRING, UNICODE_STRING
BYTES = (0x0A, 0x0F)  # OCTET_STRING, DOMAIN
# Integer types: code -> (bits, signed).
INTEGERS = {
    0x01: (1, False), 0x02: (8, True), 0x03: (16, True), 0x04: (32, True),
    0x05: (8, False), 0x06: (16, False), 0x07: (32, False), 0x10: (24, True),
    0x12: (40, True), 0x13: (48, True), 0x14: (56, True), 0x15: (64, True),
    0x16: (24, False), 0x18: (40, False), 0x19: (48, False), 0x1A: (56, False),
    0x1B: (64, False),
}
_NODEID = re.compile(r"\+?\$NODEID\+?", re.IGNORECASE)
_INTEGER = re.compile(r"^([+-]?)(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)$")


def known(data_type: int) -> bool:
    """A type whose values this module reads (others are left to the caller)."""
    return data_type in INTEGERS or data_type in (REAL32, REAL64, *STRINGS, *BYTES)


def parse(text: str, data_type: int, node_id: int | None = None):
    """The value ``text`` means for ``data_type``; ``ValueError`` saying why it means none.

    ``node_id`` None: a ``$NODEID`` term is refused (the node is not known).
    """
    if data_type in STRINGS:
        return text
    if data_type in BYTES:
        return bytes.fromhex(text.replace(" ", ""))
    if data_type in (REAL32, REAL64):
        return float(text)
    if data_type not in INTEGERS:
        raise ValueError(f"data type 0x{data_type:04X} not read")
    t = text.replace(" ", "")
    offset = 0
    if _NODEID.search(t):
        if node_id is None:
            raise ValueError("$NODEID without a node id")
        t, offset = _NODEID.sub("", t, count=1), node_id
    m = _INTEGER.match(t or "0")
    if not m:
        raise ValueError("not a number")
    sign, digits = m.groups()
    base = 16 if digits[:2].lower() == "0x" else 8 if len(digits) > 1 and digits[0] == "0" else 10
    value = int(digits[2:] if base == 16 else digits, base) + offset
    bits, signed = INTEGERS[data_type]
    if signed and not sign and base != 10 and (1 << (bits - 1)) <= value < (1 << bits):
        value -= 1 << bits  # a bit pattern: two's complement
    value = -value if sign == "-" else value
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    if not lo <= value <= hi:
        raise ValueError(f"outside the range of its type [{lo}, {hi}]")
    return value


def canonical(value) -> str:
    """``value`` as the text a plain reader takes unchanged (decimal for integers)."""
    if isinstance(value, bytes):
        return value.hex()
    return repr(value) if isinstance(value, float) else str(value)


def neutral(data_type: int):
    """The value standing for "nothing set" in a type: 0, 0.0, an empty string or bytes."""
    if data_type in STRINGS:
        return ""
    if data_type in BYTES:
        return b""
    return 0.0 if data_type in (REAL32, REAL64) else 0


def listing(keys: list[str], shown: int = 12) -> str:
    """``keys`` comma-separated, the first ``shown`` and how many more."""
    more = len(keys) - shown
    return ", ".join(keys[:shown]) + (f" and {more} more" if more > 0 else "")
