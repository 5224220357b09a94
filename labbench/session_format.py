"""The session file format: one crash-safe, append-only file per run holding the record stream.

Layout (all integers little-endian)::

    b"LBSESSION 1\\n"                       magic line: format name and version
    chunk*                                  one chunk per record, in stream order

    chunk = header(24 bytes) + json + data
    header = b"REC:" | json_len u32 | data_len u32 | seq u64 | crc32 u32
    crc32  = zlib.crc32 over header[:20] + json + data

``json`` is the record as UTF-8 JSON. A page record's ``data`` dict is not in the
JSON: its arrays follow as raw bytes, described in the JSON by ``"arrays": [{"name",
"dtype", "shape"}]`` (numeric dtypes only, always little-endian). ``seq`` counts
chunks from 0. Nothing is ever unpickled or evaluated.

Crash safety: each chunk goes to the kernel in a single ``os.write`` as soon as the
record arrives, so a killed process loses only records it had not yet emitted; a
background thread ``fsync``s at least twice a second for power loss. The reader
stops at the first short, corrupt or out-of-sequence chunk and says so in
``SessionReader.problem``: every record before it reads back intact.
"""
from __future__ import annotations

import json
import os
import re
import struct
import threading
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from labbench import records
from labbench.errors import UserError

MAGIC = b"LBSESSION 1\n"
SUFFIX = ".lbsession"
_HEADER = struct.Struct("<4sIIQI")
_MARKER = b"REC:"
_MAX_JSON = 64 << 20  # a longer JSON part means a corrupt header
_NUMERIC_KINDS = "biuf"


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot store {type(obj).__name__} in a session record")


def encode_record(record: dict, seq: int) -> bytes:
    """One chunk (header + JSON + raw page arrays) for ``record``."""
    head = dict(record)
    blobs: list[bytes] = []
    if record.get("kind") == records.PAGE:
        arrays = []
        for name, value in record["data"].items():
            a = np.asarray(value)
            if a.dtype.kind not in _NUMERIC_KINDS:
                raise ValueError(f"page channel {name!r} has non-numeric dtype {a.dtype}")
            a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
            arrays.append({"name": name, "dtype": a.dtype.str, "shape": list(a.shape)})
            blobs.append(a.tobytes())
        head["data"] = None
        head["arrays"] = arrays
    body = json.dumps(head, default=_json_default, separators=(",", ":")).encode()
    data = b"".join(blobs)
    prefix = _HEADER.pack(_MARKER, len(body), len(data), seq, 0)[:20]
    crc = zlib.crc32(data, zlib.crc32(body, zlib.crc32(prefix)))
    return prefix + struct.pack("<I", crc) + body + data


def _decode_page(head: dict, data: bytes) -> dict:
    out, offset = {}, 0
    buf = memoryview(bytearray(data))  # writable arrays, one copy
    for spec in head.pop("arrays"):
        dtype = np.dtype(spec["dtype"])
        if dtype.kind not in _NUMERIC_KINDS:
            raise ValueError(f"non-numeric dtype {dtype}")
        n = int(np.prod(spec["shape"], dtype=np.int64))
        nbytes = n * dtype.itemsize
        if offset + nbytes > len(buf):
            raise ValueError("array data shorter than declared")
        out[spec["name"]] = np.frombuffer(buf[offset:offset + nbytes], dtype=dtype).reshape(
            spec["shape"])
        offset += nbytes
    if offset != len(buf):
        raise ValueError("array data longer than declared")
    head["data"] = out
    return head


def _check_session_file(path) -> Path:
    p = Path(path)
    if not p.exists():
        raise UserError(f"session file not found: {p}")
    if p.is_dir():
        raise UserError(f"{p} is a directory, not a session file")
    if not looks_like_session(p):
        raise UserError(f"{p} is not a labbench session (no {MAGIC[:-1].decode()!r} header)")
    return p


def looks_like_session(path) -> bool:
    """True when the file starts with the session magic line."""
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


class SessionReader:
    """Iterator over the records of a session file.

    Stops cleanly at a torn or corrupt tail; afterwards ``problem`` says what was
    found there (``None`` for a clean end of file), ``n_records`` how many records
    were read and ``good_bytes`` where the intact part of the file ends.
    """

    def __init__(self, path, decode_pages: bool = True):
        self.path = _check_session_file(path)
        self.problem: str | None = None
        self.n_records = 0
        self.good_bytes = len(MAGIC)
        self._decode = decode_pages
        try:
            self._f = open(self.path, "rb")  # noqa: SIM115 - kept open while iterating; close()
        except OSError as exc:
            raise UserError(f"cannot read session {self.path}: {exc.strerror}") from None
        self._f.seek(len(MAGIC))

    def __iter__(self) -> Iterator[dict]:
        return self

    def __next__(self) -> dict:
        if self._f is None:
            raise StopIteration
        try:
            rec = self._read_one()
        except OSError as exc:
            rec, self.problem = None, f"read error: {exc}"
        if rec is None:
            self.close()
            raise StopIteration
        self.n_records += 1
        self.good_bytes = self._f.tell()
        return rec

    def _stop(self, why: str) -> None:
        self.problem = f"{why} at byte {self.good_bytes} after {self.n_records} records"

    def _read_one(self) -> dict | None:
        raw = self._f.read(_HEADER.size)
        if not raw:
            return None
        if len(raw) < _HEADER.size:
            return self._stop("torn chunk header")
        marker, json_len, data_len, seq, crc = _HEADER.unpack(raw)
        if marker != _MARKER or json_len > _MAX_JSON:
            return self._stop("corrupt chunk header")
        if self._f.tell() + json_len + data_len > os.fstat(self._f.fileno()).st_size:
            return self._stop("torn chunk")  # checked before reading: a lying length allocates nothing
        body = self._f.read(json_len)
        data = self._f.read(data_len)
        if len(body) < json_len or len(data) < data_len:
            return self._stop("torn chunk")
        if zlib.crc32(data, zlib.crc32(body, zlib.crc32(raw[:20]))) != crc:
            return self._stop("checksum mismatch")
        if seq != self.n_records:
            return self._stop(f"chunk sequence {seq} where {self.n_records} was due")
        try:
            head = json.loads(body)
            if not isinstance(head, dict):
                raise TypeError("record is not an object")
            if head.get("kind") == records.PAGE:
                if self._decode:
                    head = _decode_page(head, data)
                else:
                    head["data"] = {a["name"]: tuple(a["shape"]) for a in head.pop("arrays")}
        except (ValueError, TypeError, KeyError) as exc:
            return self._stop(f"undecodable record ({exc})")
        return head

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_session(path) -> SessionReader:
    """The record stream of a session file (page data as numpy arrays).

    Raises ``UserError`` at once for a missing file or one that is not a session.
    """
    return SessionReader(path)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9-]+", "-", str(text)).strip("-") or "run"


class SessionWriter:
    """Record consumer that writes one session file per run.

    The file is created when the start record arrives, in ``directory`` (made if
    missing), named ``<YYYYmmdd-HHMMSS>_<protocol>_<uid8>.lbsession`` unless
    ``name`` is given; ``path`` is ``None`` until then. ``close()`` is idempotent;
    use as a context manager. Safe to call from the acquisition thread: a record
    costs one ``os.write``; ``fsync`` runs on a helper thread every
    ``fsync_interval_s``.
    """

    def __init__(self, directory, name: str | None = None, fsync_interval_s: float = 0.5):
        self.directory = Path(directory)
        if self.directory.exists() and not self.directory.is_dir():
            raise UserError(f"session directory {self.directory} is a file")
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"cannot create session directory {self.directory}: "
                            f"{exc.strerror}") from None
        self.name = name
        self.path: Path | None = None
        self._fd: int | None = None
        self._seq = 0
        self._closed = False
        self._dirty = False
        self._lock = threading.Lock()
        self._interval = fsync_interval_s
        self._stop_flush = threading.Event()
        self._flusher: threading.Thread | None = None

    def _file_name(self, start: dict) -> str:
        if self.name:
            return self.name if Path(self.name).suffix else self.name + SUFFIX
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(start.get("time", time.time())))
        uid = str(start.get("uid", ""))[:8] or "nouid"
        return f"{stamp}_{_slug(records.protocol_name(start))}_{_slug(uid)}{SUFFIX}"

    def _open(self, start: dict) -> None:
        if start.get("kind") != records.START:
            raise ValueError(f"a session begins with a start record, got {start.get('kind')!r}")
        path = self.directory / self._file_name(start)
        try:
            self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            raise UserError(f"session file already exists: {path}") from None
        except OSError as exc:
            raise UserError(f"cannot create session file {path}: {exc.strerror}") from None
        self.path = path
        self._write(MAGIC)
        self._flusher = threading.Thread(target=self._flush_loop, name="session-fsync",
                                         daemon=True)
        self._flusher.start()

    def _write(self, buf: bytes) -> None:
        view = memoryview(buf)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]

    def _flush_loop(self) -> None:
        while not self._stop_flush.wait(self._interval):
            if self._dirty:
                self._dirty = False
                os.fsync(self._fd)

    def __call__(self, record: dict) -> None:
        with self._lock:
            if self._closed:
                raise RuntimeError("session writer is closed")
            if self._fd is None:
                self._open(record)
            chunk = encode_record(record, self._seq)
            self._write(chunk)
            self._seq += 1
            self._dirty = True

    def close(self) -> None:
        """Flush to disk and close; safe to call more than once."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._flusher is not None:
            self._stop_flush.set()
            self._flusher.join(timeout=5.0)
        if self._fd is not None:
            try:
                os.fsync(self._fd)
            finally:
                os.close(self._fd)
                self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
