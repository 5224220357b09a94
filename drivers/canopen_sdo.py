"""SDO access to one node with one-line messages: objects and values in hex.

``Sdo.upload`` tells "the object does not exist" (abort 0x06020000 or
0x06090011, returned as ``None``) from "the node refused" (``DeviceError``)
and "the node did not answer" (``DeviceConnectionError``); ``Sdo.attempt``
returns any abort code instead of raising, for reads the caller can do
without. Abort codes and their meanings: CiA 301, "SDO abort codes".
"""
from __future__ import annotations

import queue
import struct
import time

from canopen.sdo import SdoAbortedError, SdoClient, SdoCommunicationError
from canopen.sdo.constants import (REQUEST_DOWNLOAD, REQUEST_UPLOAD, RESPONSE_ABORTED,
                                   RESPONSE_DOWNLOAD, RESPONSE_UPLOAD)

from labbench.errors import DeviceConnectionError, DeviceError, UserError


class NoAnswer(DeviceConnectionError):
    """The node did not answer an SDO request at all (no abort, no response)."""

ABSENT = (0x06020000, 0x06090011)  # object / subindex does not exist
WRITE_ONLY = 0x06010001  # the object exists and cannot be read
ABORT_TEXT = {
    0x06010000: "unsupported access", 0x06010001: "object is write-only",
    0x06010002: "object is read-only", 0x06020000: "object does not exist",
    0x06040041: "object cannot be mapped to a PDO",
    0x06040042: "mapping exceeds the PDO length", 0x06040043: "parameter incompatibility",
    0x06070010: "data type does not match (length)", 0x06090011: "subindex does not exist",
    0x06090030: "value range exceeded", 0x06090031: "value too high",
    0x06090032: "value too low", 0x060A0023: "resource not available",
    0x08000000: "general error", 0x08000020: "cannot store",
    0x08000021: "cannot store: local control", 0x08000022: "not in the present device state",
    0x08000024: "no data available",
}


def hexval(value: int, fmt: str) -> str:
    """``value`` as hex of the object's width; negatives also in decimal."""
    size = struct.calcsize(fmt)
    text = f"0x{value & ((1 << 8 * size) - 1):0{2 * size}X}"
    return f"{text} ({value})" if value < 0 else text


def where(index: int, sub: int) -> str:
    return f"0x{index:04X}:{sub:02X}"


def abort_text(code: int) -> str:
    return f"SDO abort 0x{code:08X} ({ABORT_TEXT.get(code, 'see CiA 301')})"


class MatchingSdoClient(SdoClient):
    """canopen's ``SdoClient`` that skips an answer naming another object than the request's.

    After a timed-out request the node's late answer (its value, or an abort such as
    "object does not exist") arrives during the next request, and canopen takes the first
    frame for the answer: an object then reads as absent, or as another's value. Initiate
    answers and aborts carry the object's index and subindex (CiA 301), so a mismatch is
    dropped and the wait goes on; segment answers carry none and pass.
    """

    _want: bytes | None = None  # index (LE) and subindex of the transfer under way

    def request_response(self, sdo_request):
        if sdo_request[0] & 0xE0 in (REQUEST_UPLOAD, REQUEST_DOWNLOAD):  # an initiate
            self._want = bytes(sdo_request[1:4])
        return super().request_response(sdo_request)

    def read_response(self):
        deadline = time.monotonic() + self.RESPONSE_TIMEOUT
        while True:
            try:
                response = self.responses.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise SdoCommunicationError("No SDO response received") from None
            if (response[0] & 0xE0 in (RESPONSE_UPLOAD, RESPONSE_DOWNLOAD, RESPONSE_ABORTED)
                    and self._want is not None and response[1:4] != self._want):
                continue  # the late answer to an earlier request
            if response[0] & 0xE0 == RESPONSE_ABORTED:
                raise SdoAbortedError(struct.unpack_from("<L", response, 4)[0])
            return response


class Sdo:
    """Expedited/segmented SDO transfers through a canopen ``SdoClient``.

    ``check`` runs before each transfer (the driver raises there if its
    receive thread died); ``names`` gives an object's name for messages.
    """

    def __init__(self, client: SdoClient, node_id: int, check=lambda: None,
                 names=lambda index: ""):
        self.client, self.node_id, self._check, self._names = client, node_id, check, names

    def _what(self, index: int, sub: int) -> str:
        name = self._names(index)
        return f"{where(index, sub)}" + (f" ({name})" if name else "")

    def attempt(self, index: int, sub: int) -> tuple[bytes | None, int | None]:
        """``(raw value, None)``, or ``(None, abort code)`` when the node refuses (any abort,
        "does not exist" included); no answer still raises ``DeviceConnectionError``."""
        self._check()
        try:
            return bytes(self.client.upload(index, sub)), None
        except SdoAbortedError as exc:
            return None, exc.code
        except SdoCommunicationError as exc:
            self._check()
            raise NoAnswer(f"node {self.node_id}: no answer to SDO read of "
                           f"{where(index, sub)} ({exc})") from None

    def upload(self, index: int, sub: int) -> bytes | None:
        """The raw value, or ``None`` when the node says the object does not exist."""
        raw, code = self.attempt(index, sub)
        if code is None or code in ABSENT:
            return raw
        raise DeviceError(f"node {self.node_id}: SDO read of {self._what(index, sub)} "
                          f"refused: {abort_text(code)}")

    def read(self, index: int, sub: int, fmt: str) -> int:
        raw = self.upload(index, sub)
        if raw is None:
            raise DeviceError(f"node {self.node_id}: SDO read of {self._what(index, sub)} "
                              f"refused: {abort_text(0x06020000)}")
        size = struct.calcsize(fmt)
        return struct.unpack(fmt, raw[:size].ljust(size, b"\0"))[0]

    def write(self, index: int, sub: int, fmt: str, value: int) -> None:
        self._check()
        try:
            self.client.download(index, sub, struct.pack(fmt, value))
        except SdoAbortedError as exc:
            raise DeviceError(f"node {self.node_id}: drive refused writing {hexval(value, fmt)} "
                              f"to {self._what(index, sub)}: {abort_text(exc.code)}; "
                              "refusing to enable") from None
        except SdoCommunicationError as exc:
            self._check()
            raise NoAnswer(f"node {self.node_id}: no answer to SDO write of "
                           f"{where(index, sub)} ({exc})") from None

    def write_checked(self, index: int, sub: int, fmt: str, value: int) -> None:
        """Write, then read back: a drive that ignores a write is caught here."""
        self.write(index, sub, fmt, value)
        back = self.read(index, sub, fmt)
        if back != value:
            raise UserError(f"node {self.node_id}: object {self._what(index, sub)} reads back "
                            f"{hexval(back, fmt)} after writing {hexval(value, fmt)}: "
                            "refusing to enable")
