"""Decoding of CANopen EMCY frames (CiA 301 sec. 7.2.7, codes from CiA 301 and CiA 402).

Frame layout: error code (u16, little-endian), error register (0x1001, u8),
5 manufacturer-specific bytes. Code 0x0000 means "error reset / no error".
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

# Exact codes first (CiA 402-2 annex and CiA 301 communication codes), then
# classes by their high nibble / byte, as the standards group them.
_EXACT = {
    0x0000: "error reset or no error",
    0x2310: "continuous over-current",
    0x2320: "short circuit at the output stage",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "excess temperature of the device",
    0x4310: "excess temperature of the drive",
    0x5441: "enable input missing (safe torque off)",
    0x6320: "parameter error",
    0x7305: "incremental sensor 1 fault",
    0x7500: "communication error",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8250: "RPDO timeout",
    0x8611: "following error",
    0x8612: "reference limit",
    0xFF00: "device specific",
}
_CLASSES = [  # (code, mask, text)
    (0x1000, 0xFF00, "generic error"),
    (0x2000, 0xF000, "current"),
    (0x3000, 0xF000, "voltage"),
    (0x4000, 0xF000, "temperature"),
    (0x5000, 0xFF00, "device hardware"),
    (0x6000, 0xF000, "device software"),
    (0x7000, 0xFF00, "additional modules"),
    (0x8100, 0xFF00, "communication"),
    (0x8200, 0xFF00, "protocol error"),
    (0x8000, 0xF000, "monitoring"),
    (0x9000, 0xFF00, "external error"),
    (0xF000, 0xFF00, "additional functions"),
    (0xFF00, 0xFF00, "device specific"),
]
# Error register 0x1001 bits (CiA 301).
_REGISTER_BITS = ("generic", "current", "voltage", "temperature", "communication",
                  "device profile", "reserved", "manufacturer")


def code_text(code: int) -> str:
    """Plain-language meaning of an EMCY error code."""
    if code in _EXACT:
        return _EXACT[code]
    for value, mask, text in _CLASSES:
        if code & mask == value:
            return text
    return "unknown error code"


@dataclass(frozen=True)
class Emcy:
    code: int
    register: int
    data: bytes
    text: str

    @property
    def is_reset(self) -> bool:
        return self.code == 0

    def register_bits(self) -> list[str]:
        return [name for i, name in enumerate(_REGISTER_BITS) if self.register >> i & 1]

    def __str__(self) -> str:
        bits = ", ".join(self.register_bits()) or "none"
        return (f"EMCY 0x{self.code:04X} ({self.text}); error register 0x{self.register:02X}"
                f" ({bits}); data {self.data.hex() or '-'}")


def decode(data: bytes) -> Emcy:
    """Decode an EMCY payload; short frames (< 3 bytes) raise ``ValueError``."""
    if len(data) < 3:
        raise ValueError(f"EMCY frame too short ({len(data)} bytes)")
    code, register = struct.unpack_from("<HB", data)
    return Emcy(code, register, bytes(data[3:8]), code_text(code))


def encode(code: int, register: int = 0, data: bytes = b"") -> bytes:
    """EMCY payload (8 bytes) for a simulated device."""
    return struct.pack("<HB5s", code, register, data)
