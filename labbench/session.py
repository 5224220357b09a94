"""Session files: one crash-safe, append-only file per run holding the record stream.

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
import math
import os
import re
import struct
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labbench import records
from labbench.errors import UserError
from labbench.ve import VirtualEnvironment

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


def protocol_name(start: dict) -> str:
    proto = start.get("protocol")
    if isinstance(proto, dict):  # {"name": ...} or a protocol's describe(): {"protocol": ...}
        return str(proto.get("name") or proto.get("protocol") or "run")
    return str(proto or "run")


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
        return f"{stamp}_{_slug(protocol_name(start))}_{_slug(uid)}{SUFFIX}"

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


@dataclass(frozen=True)
class SessionSummary:
    path: Path
    uid: str | None
    time: float | None
    rig_name: str | None
    protocol: str | None
    status: str  # the stop record's status, or "incomplete"
    n_samples: int


def summarize(path) -> SessionSummary:
    """Header facts of one session without decoding its sample arrays."""
    start, stop, n = None, None, 0
    with SessionReader(path, decode_pages=False) as reader:
        for rec in reader:
            kind = rec.get("kind")
            if kind == records.START and start is None:
                start = rec
            elif kind == records.PAGE:
                shapes = list(rec["data"].values())
                n += int(shapes[0][0]) if shapes and shapes[0] else 0
            elif kind == records.STOP:
                stop = rec
    start = start or {}
    rig = start.get("rig") if isinstance(start.get("rig"), dict) else {}
    return SessionSummary(
        path=Path(path),
        uid=start.get("uid"),
        time=start.get("time"),
        rig_name=rig.get("name"),
        protocol=protocol_name(start) if start else None,
        status=str(stop.get("status")) if stop else "incomplete",
        n_samples=n,
    )


def list_sessions(directory) -> list[SessionSummary]:
    """Every session file directly in ``directory``, oldest first."""
    d = Path(directory)
    if not d.is_dir():
        raise UserError(f"not a directory: {d}")
    found = [summarize(p) for p in sorted(d.iterdir()) if p.is_file() and looks_like_session(p)]
    return sorted(found, key=lambda s: (s.time or 0.0, str(s.path)))


def session_ve(start: dict) -> VirtualEnvironment | None:
    """The VE a run started with, from its start record.

    Accepts a VE dict (``VirtualEnvironment.as_dict``) under ``start["ve"]`` or the
    protocol's ``ve``, or a protocol config with ``ve`` = kind and ``K``, ``B``,
    ``w0_rad_s``, ``td_s``. ``None`` when the record names no VE.
    """
    proto = start.get("protocol") if isinstance(start.get("protocol"), dict) else {}
    for candidate in (start.get("ve"), proto.get("ve")):
        if isinstance(candidate, dict):
            return VirtualEnvironment.from_dict(candidate)
    if not isinstance(proto.get("ve"), str):
        return None
    rig = start.get("rig") if isinstance(start.get("rig"), dict) else {}
    w0 = proto.get("w0_rad_s")
    return VirtualEnvironment(
        proto["ve"], K=float(proto.get("K", 0.0)), B=float(proto.get("B", 0.0)),
        w0=math.inf if w0 is None else float(w0),
        T=float(proto.get("sample_time_s") or rig.get("sample_time_s") or 0.001),
        td=float(proto.get("td_s", 0.0)))


def load_session(path) -> tuple[dict, dict, dict[str, np.ndarray], list[dict], dict | None, str | None]:
    """(start, descriptor, channels, events, stop, problem) of a session, pages joined."""
    reader = read_session(path)
    start, desc, stop, events, pages = {}, {}, None, [], []
    with reader:
        for rec in reader:
            kind = rec.get("kind")
            if kind == records.START:
                start = rec
            elif kind == records.DESCRIPTOR:
                desc = rec
            elif kind == records.PAGE:
                pages.append(rec)
            elif kind == records.EVENT:
                events.append(rec)
            elif kind == records.STOP:
                stop = rec
    return start, desc, records.concat_pages(pages), events, stop, reader.problem


def analysis_meta(start: dict, desc: dict) -> dict:
    """Metadata keys of the analysis format (docs/analysis.md): fs, ve, K, B, w0, td, protocol."""
    rig = start.get("rig") if isinstance(start.get("rig"), dict) else {}
    T = desc.get("sample_time_s") or rig.get("sample_time_s")
    ve = session_ve(start)
    meta = {"protocol": protocol_name(start)}
    if T:
        meta["fs"] = 1.0 / float(T)
    if ve is not None:
        meta.update(ve=ve.kind, K=ve.K, B=ve.B, td=ve.td)
        if math.isfinite(ve.w0):
            meta["w0"] = ve.w0
    for key in ("uid", "seed"):
        if start.get(key) is not None:
            meta[key] = start[key]
    if rig.get("name"):
        meta["rig"] = rig["name"]
    return meta


def load_analysis_arrays(path) -> dict:
    """``dict(t, force, position, meta)`` for the analysis.

    ``force`` is the exogenous force (the "excitation" channel), ``position`` the
    sampled position; ``meta`` has fs, ve, K, B, w0, td, protocol (docs/analysis.md).
    """
    start, desc, ch, _events, _stop, _problem = load_session(path)
    if ch["t"].size == 0:
        raise UserError(f"session {path} holds no samples")
    return {
        "t": ch["t"].astype(float),
        "force": ch["excitation"].astype(float),
        "position": ch["position"].astype(float),
        "meta": analysis_meta(start, desc),
    }


def replay(path, consumers, speed: float | None = None, stop: threading.Event | None = None,
           clock=time.monotonic, sleep=time.sleep) -> SessionReader:
    """Feed a session's stream to ``consumers`` (``records.fan_out``), as recorded.

    ``speed`` None: as fast as possible; otherwise a page is delivered when its last
    sample falls due at ``speed`` times real time (an event at its ``t``). Setting
    ``stop`` ends the replay early. Returns the reader (its ``problem`` tells of a
    damaged tail).
    """
    if speed is not None and not speed > 0:
        raise UserError(f"replay speed must be positive, got {speed}")
    reader = read_session(path)

    def paced():
        t_first, wall0 = None, None
        for rec in reader:
            if stop is not None and stop.is_set():
                break
            t = _stream_time(rec)
            if speed is not None and t is not None:
                if t_first is None:
                    t_first, wall0 = t, clock()
                delay = wall0 + (t - t_first) / speed - clock()
                if delay > 0 and stop is None:
                    sleep(delay)
                elif delay > 0 and stop.wait(delay):
                    break
            yield rec

    with reader:
        records.fan_out(paced(), consumers)
    return reader


def _stream_time(rec: dict) -> float | None:
    if rec.get("kind") == records.PAGE and len(rec["data"]["t"]):
        return float(rec["data"]["t"][-1])
    if rec.get("kind") == records.EVENT and rec.get("t") is not None:
        return float(rec["t"])
    return None


class StreamSummary:
    """Consumer that condenses a stream: identity, samples, drops, events, status, timing."""

    def __init__(self):
        self.start: dict = {}
        self.stop: dict | None = None
        self.events: list[dict] = []
        self.n_records = self.n_pages = self.n_samples = self.dropped = 0
        self.t_first = self.t_last = None
        self.max_abs_command_n = 0.0
        self._last_seq = None

    def __call__(self, rec: dict) -> None:
        self.n_records += 1
        kind = rec.get("kind")
        if kind == records.START:
            self.start = rec
        elif kind == records.PAGE:
            d = rec["data"]
            n = len(d["t"])
            if n == 0:
                return
            self.n_pages += 1
            self.n_samples += n
            seq = np.asarray(d["seq"], dtype=np.int64)
            prev = self._last_seq if self._last_seq is not None else seq[0] - 1
            steps = np.diff(np.concatenate([[prev], seq]))
            self.dropped += int(np.sum(np.clip(steps - 1, 0, None)))
            self._last_seq = int(seq[-1])
            self.t_first = float(d["t"][0]) if self.t_first is None else self.t_first
            self.t_last = float(d["t"][-1])
            self.max_abs_command_n = max(self.max_abs_command_n,
                                         float(np.max(np.abs(d["command"]))))
        elif kind == records.EVENT:
            self.events.append(rec)
        elif kind == records.STOP:
            self.stop = rec

    def as_dict(self) -> dict:
        rig = self.start.get("rig") if isinstance(self.start.get("rig"), dict) else {}
        stop = self.stop or {}
        return {
            "uid": self.start.get("uid"),
            "protocol": protocol_name(self.start) if self.start else None,
            "rig": rig.get("name"),
            "status": stop.get("status", "incomplete"),
            "reason": stop.get("reason", ""),
            "records": self.n_records,
            "pages": self.n_pages,
            "samples": self.n_samples,
            "dropped_samples": self.dropped,
            "duration_s": (self.t_last - self.t_first) if self.n_samples else 0.0,
            "max_abs_command_n": self.max_abs_command_n,
            "events": [{"t": e.get("t"), "name": e.get("name"), "reason": e.get("reason")}
                       for e in self.events],
            "timing": stop.get("timing"),
        }
