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

import errno
import json
import math
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
from labbench.errors import RecordingError, UserError
from labbench.input_files import open_regular

MAGIC = b"LBSESSION 1\n"
SUFFIX = ".lbsession"
_HEADER = struct.Struct("<4sIIQI")
_MARKER = b"REC:"
_MAX_JSON = 16 << 20  # a longer JSON part means a corrupt header
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


def _page_layout(head: dict, data_len: int) -> list[tuple[str, np.dtype, int]]:
    """(name, dtype, length) of each array of a page, checked against the record contract:
    1-D arrays of numeric dtypes, every channel of ``records.CHANNELS``, equal lengths,
    sizes adding up to the data part exactly."""
    specs = head.pop("arrays", None)
    if not isinstance(specs, list):
        raise ValueError("page without an array list")
    layout, total = [], 0
    for spec in specs:
        if not isinstance(spec, dict) or not isinstance(spec.get("name"), str):
            raise ValueError("array without a name")
        name, shape = spec["name"], spec.get("shape")
        dtype = np.dtype(spec.get("dtype")) if isinstance(spec.get("dtype"), str) else None
        if dtype is None or dtype.kind not in _NUMERIC_KINDS or dtype.fields is not None:
            raise ValueError(f"channel {name!r}: not a numeric dtype")
        if (not isinstance(shape, list) or len(shape) != 1 or not _is_int(shape[0])
                or not 0 <= shape[0] <= data_len):
            raise ValueError(f"channel {name!r}: shape {shape!r} is not one length")
        total += shape[0] * dtype.itemsize
        layout.append((name, dtype, shape[0]))
    names = [n for n, _, _ in layout]
    missing = [c for c in records.CHANNELS if c not in names]
    if missing or len(set(names)) != len(names):
        raise ValueError(f"page lacks channel(s) {missing}" if missing else "page repeats a channel")
    if len({n for _, _, n in layout}) > 1:
        raise ValueError("page channels of different lengths")
    if total != data_len:
        raise ValueError(f"array data {'shorter' if total > data_len else 'longer'} than declared")
    return layout


def _decode_page(head: dict, data: bytes) -> dict:
    out, offset = {}, 0
    buf = memoryview(bytearray(data))  # writable arrays, one copy
    for name, dtype, n in _page_layout(head, len(data)):
        nbytes = n * dtype.itemsize
        out[name] = np.frombuffer(buf[offset:offset + nbytes], dtype=dtype)
        offset += nbytes
    head["data"] = out
    return head


# Type of each known field of a record (when present): what readers rely on. A session
# whose checksums are valid but whose content is not (a hostile or buggy writer) stops
# being read at that record, like a damaged tail.
_NUMBER, _INT, _NONE = "number", "int", type(None)
_FIELDS = {
    records.START: {"uid": (str,), "time": (_NUMBER,), "software": (str,), "rig": (dict,),
                    "protocol": (dict, str), "seed": (_INT, _NONE), "device": (dict,),
                    "plant": (dict,), "safety": (dict,)},
    records.DESCRIPTOR: {"sample_time_s": (_NUMBER,), "channels": (dict,)},
    records.PAGE: {"index": (_INT,)},
    records.EVENT: {"t": (_NUMBER, _NONE), "name": (str,), "reason": (str, _NONE)},
    records.STOP: {"status": (str,), "reason": (str, _NONE), "cause": (str, _NONE),
                   "time": (_NUMBER,), "n_samples": (_INT,),
                   "results": (dict,), "timing": (dict, _NONE)},
}
_RANGES = {"time": (0.0, 1e11), "sample_time_s": (1e-9, 1.0), "t": (-1e11, 1e11),
           "n_samples": (0, 1 << 48), "seed": (0, 1 << 64), "index": (0, 1 << 48)}
MAX_DEPTH = 32  # nesting of a record's JSON: results tables are a few levels deep


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _fits(value, kinds) -> bool:
    for k in kinds:
        if k is _NUMBER and isinstance(value, (int, float)) and not isinstance(value, bool):
            return math.isfinite(value)
        if k is _INT and _is_int(value):
            return True
        if isinstance(k, type) and isinstance(value, k):
            return True
    return False


def _check_fields(head: dict) -> None:
    kind = head.get("kind")
    if kind not in records.KINDS:
        raise ValueError(f"unknown record kind {str(kind)[:40]!r}")
    for name, kinds in _FIELDS[kind].items():
        if name in head:
            v = head[name]
            if not _fits(v, kinds):
                raise ValueError(f"{kind} field {name!r} has a wrong type or value")
            lo_hi = _RANGES.get(name)
            if lo_hi is not None and v is not None and not lo_hi[0] <= v <= lo_hi[1]:
                raise ValueError(f"{kind} field {name!r} = {v!r} out of range")
    try:
        _CONTENT.get(kind, lambda _h: None)(head)
    except UserError as exc:  # as a file's: one line naming the field
        raise NotAsWritten(f"{kind} record not as labbench writes it: {exc}") from None


class NotAsWritten(ValueError):
    """A record whose checksum holds but whose content labbench would not have written."""


def _start_content(head: dict) -> None:
    """The start record's rig, safety limits and device as the runner writes them: numbers
    within the ranges a rig file's are held to (a session edited with its checksums
    recomputed, force limit 1e308 or sample time "abc", was read without a word)."""
    from dataclasses import fields

    from labbench.rig import check_recorded
    from labbench.loop.safety import SafetyConfig

    if isinstance(head.get("rig"), dict):
        check_recorded(head["rig"], "rig")
    safety = head.get("safety")
    if isinstance(safety, dict):
        known = {f.name for f in fields(SafetyConfig)}
        try:
            SafetyConfig(**{k: v for k, v in safety.items() if k in known})
        except TypeError as exc:
            raise UserError(f"safety: {exc}") from None
    device = head.get("device")
    if isinstance(device, dict):
        for name, (lo, hi) in _DEVICE_RANGES.items():
            v = device.get(name)
            if v is not None and not (_fits(v, (_NUMBER,)) and lo <= v <= hi):
                raise UserError(f"device {name} = {str(v)[:40]} is not a number in "
                                f"[{lo:g}, {hi:g}]")


def _stop_content(head: dict) -> None:
    """A stop record's status and cause are among those the runner writes."""
    if "status" in head and head["status"] not in records.STATUSES:
        raise UserError(f"status {str(head['status'])[:40]!r} is none of "
                        f"{', '.join(records.STATUSES)}")
    cause = head.get("cause")
    if cause is not None and cause not in records.CAUSES:
        raise UserError(f"cause {str(cause)[:40]!r} is none of {', '.join(records.CAUSES)}")


_CONTENT = {records.START: _start_content, records.STOP: _stop_content}
_DEVICE_RANGES = {"sample_time_s": (1e-9, 1.0), "force_limit_n": (0.0, 1000.0),
                  "device_delay_s": (0.0, 1.0)}


def _depth_ok(obj, limit: int) -> bool:
    stack = [(obj, 1)]
    while stack:
        o, d = stack.pop()
        if d > limit:
            return False
        if isinstance(o, dict):
            stack.extend((v, d + 1) for v in o.values())
        elif isinstance(o, list):
            stack.extend((v, d + 1) for v in o)
    return True


def decode_json(body: bytes) -> dict:
    """A record's JSON object, nested at most ``MAX_DEPTH`` deep, known fields type-checked."""
    try:
        head = json.loads(body)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None
    if not isinstance(head, dict):
        raise TypeError("record is not an object")
    if body.count(b"[") + body.count(b"{") > MAX_DEPTH and not _depth_ok(head, MAX_DEPTH):
        raise ValueError(f"JSON nested deeper than {MAX_DEPTH}")
    _check_fields(head)
    return head


def _check_session_file(path) -> Path:
    p = Path(path)
    with open_regular(p, "session file") as f:  # a FIFO or device is refused, not read
        try:
            magic = f.read(len(MAGIC))
        except OSError as exc:
            raise UserError(f"cannot read session file {p}: {exc.strerror}") from None
    if magic != MAGIC:
        raise UserError(f"{p} is not a labbench session (no {MAGIC[:-1].decode()!r} header)")
    return p


def looks_like_session(path) -> bool:
    """True when ``path`` is a regular file starting with the session magic line."""
    try:
        with open_regular(path, "session file") as f:
            return f.read(len(MAGIC)) == MAGIC
    except (UserError, OSError):
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
        self.not_as_written = False  # the problem is content labbench would not write
        self.n_records = 0
        self.good_bytes = len(MAGIC)
        self._decode = decode_pages
        self._f = open_regular(self.path, "session file")  # kept open while iterating; close()
        self._f.seek(len(MAGIC))
        self._size = 0  # file size last seen

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
        self.good_bytes += self._chunk_len
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
        end = self.good_bytes + _HEADER.size + json_len + data_len
        if end > self._size:  # checked before reading: a lying length allocates nothing
            self._size = os.fstat(self._f.fileno()).st_size  # a live session grows
            if end > self._size:
                return self._stop("torn chunk")
        body = self._f.read(json_len)
        data = self._f.read(data_len)
        if len(body) < json_len or len(data) < data_len:
            return self._stop("torn chunk")
        if zlib.crc32(data, zlib.crc32(body, zlib.crc32(raw[:20]))) != crc:
            return self._stop("checksum mismatch")
        if seq != self.n_records:
            return self._stop(f"chunk sequence {seq} where {self.n_records} was due")
        try:
            head = decode_json(body)
            if head.get("kind") == records.PAGE:
                if self._decode:
                    head = _decode_page(head, data)
                else:
                    head["data"] = {name: (n,) for name, _, n in _page_layout(head, data_len)}
            elif data_len:
                raise ValueError(f"{head['kind']} record with a data part")
        except (ValueError, TypeError, KeyError) as exc:
            self.not_as_written = isinstance(exc, NotAsWritten)
            return self._stop(f"undecodable record ({exc})")
        self._chunk_len = _HEADER.size + json_len + data_len
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


# what stopped a recording, in words (errno -> "... recorded up to <words>")
_UP_TO = {errno.ENOSPC: "the disk filling",
          getattr(errno, "EDQUOT", -1): "the disk quota running out",
          errno.EFBIG: "the file size limit", errno.EROFS: "the file system turning read-only",
          errno.EACCES: "permission being refused", errno.EPERM: "permission being refused",
          errno.EIO: "a disk input/output error"}


def session_folder(directory) -> Path:
    """The sessions folder (created with its parents if missing) once a new file can be made
    in it; else one UserError. Checked before a device is enabled: a read-only folder gave
    a traceback at the end of the run."""
    from labbench.safe_write import writable_folder, why

    if not str(directory).strip():
        raise UserError("empty session folder name")
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise UserError(f"session directory {d} is a file")
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create session directory {d}: {why(exc)}") from None
    return writable_folder(d, "sessions folder")


class SessionWriter:
    """Record consumer that writes one session file per run.

    The file is created when the start record arrives, in ``directory`` (made if
    missing, checked for writing at once: ``session_folder``), named
    ``<YYYYmmdd-HHMMSS>_<protocol>_<uid8>.lbsession`` unless ``name`` is given; ``path``
    is ``None`` until then. It is created exclusively (never through a link at its name)
    with the user's umask. ``close()`` is idempotent; use as a context manager. Safe to
    call from the acquisition thread: a record costs one ``os.write``; ``fsync`` runs on a
    helper thread every ``fsync_interval_s``.

    A write the system refuses (full disk, file size limit, permission, read-only) raises
    ``RecordingError`` once, saying how much was recorded; the file is cut back to its
    last whole record (readable, without a stop record: incomplete) and later records
    are dropped. ``error`` keeps the OSError.
    """

    def __init__(self, directory, name: str | None = None, fsync_interval_s: float = 0.5):
        self.directory = session_folder(directory)
        self.name = name
        self.path: Path | None = None
        self.error: OSError | None = None
        self._reported = False  # the RecordingError was raised
        self._attempt: Path | None = None  # the file name tried
        self._fd: int | None = None
        self._seq = 0
        self._good = 0  # bytes of whole records in the file
        self._samples = 0  # samples in the pages written whole
        self._T: float | None = None
        self._closed = False
        self._dirty = False
        self._lock = threading.Lock()
        self._interval = fsync_interval_s
        self._stop_flush = threading.Event()
        # started now, not with the file: a thread started inside the loop's real-time
        # grant would inherit the loop's own priority (labbench.loop.realtime raises the
        # threads that exist when it is entered just below it)
        self._flusher = threading.Thread(target=self._flush_loop, name="session-fsync",
                                         daemon=True)
        self._flusher.start()

    def _file_name(self, start: dict) -> str:
        if self.name:
            return self.name if Path(self.name).suffix else self.name + SUFFIX
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(start.get("time", time.time())))
        uid = str(start.get("uid", ""))[:8] or "nouid"
        return f"{stamp}_{_slug(records.protocol_name(start))}_{_slug(uid)}{SUFFIX}"

    def _open(self, start: dict) -> None:
        if start.get("kind") != records.START:
            raise ValueError(f"a session begins with a start record, got {start.get('kind')!r}")
        path = self._attempt = self.directory / self._file_name(start)
        # 0o666 less the umask, as any program's file; O_EXCL | O_NOFOLLOW: never through a
        # link planted at the name (an existing name is refused); O_BINARY (Windows): no
        # newline translation
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
                           | getattr(os, "O_BINARY", 0), 0o666)
        self.path = path
        self._write(MAGIC)
        self._good = len(MAGIC)

    def _write(self, buf: bytes) -> None:
        view = memoryview(buf)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]

    def _flush_loop(self) -> None:
        while not self._stop_flush.wait(self._interval):
            if self._dirty:
                self._dirty = False
                try:
                    os.fsync(self._fd)
                except OSError as exc:  # the next record says so (__call__)
                    self.error = self.error or exc

    def __call__(self, record: dict) -> None:
        with self._lock:
            if self._closed:
                raise RuntimeError("session writer is closed")
            if self.error is not None:
                if self._reported:
                    return  # said once: what follows is dropped (the run is stopping)
                raise self._failed(self.error)
            try:
                if self._fd is None:
                    self._open(record)
                self._write(encode_record(record, self._seq))
            except OSError as exc:
                raise self._failed(exc) from None
            self._seq += 1
            self._good = os.lseek(self._fd, 0, os.SEEK_CUR)
            self._dirty = True
            kind = record.get("kind")
            if kind == records.DESCRIPTOR:
                self._T = record.get("sample_time_s")
            elif kind == records.PAGE:
                self._samples += len(record["data"]["t"])

    def _failed(self, exc: OSError) -> RecordingError:
        """The one error of a refused write: the file cut back to its whole records."""
        self.error, self._reported = exc, True
        if self._fd is not None:
            try:
                os.ftruncate(self._fd, self._good)  # a shorter file needs no space
            except OSError:
                pass  # the reader stops at the torn record just as well
        return RecordingError(self.failure())

    def failure(self) -> str | None:
        """What a refused write left, in one line (None while all is well)."""
        if self.error is None:
            return None
        from labbench.safe_write import why

        if self.path is None:
            return (f"nothing recorded: cannot create session file {self._attempt}: "
                    f"{why(self.error)}")
        kept = (f"{self._samples * self._T:.1f} s" if self._T else f"{self._samples} samples")
        words = _UP_TO.get(self.error.errno, f"a write error ({self.error.strerror or self.error})")
        return (f"{kept} recorded up to {words}; the session {self.path} is readable, "
                "marked incomplete")

    def close(self) -> None:
        """Flush to disk and close; safe to call more than once. A refused flush is kept in
        ``error`` (``failure()``), not raised."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._stop_flush.set()
        self._flusher.join(timeout=5.0)
        if self._fd is not None:
            try:
                os.fsync(self._fd)
            except OSError as exc:
                self.error = self.error or exc
            finally:
                os.close(self._fd)
                self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
