"""One entry point for data in: a CSV file or a recorded labbench session.

CSV layout: optional leading ``# key=value`` lines (metadata), one header row,
then numeric rows; columns ``t`` [s], ``force`` [N], ``position`` [m] in any
order, other columns ignored. Sampling must be uniform.
"""
from __future__ import annotations

import csv
import io
import itertools
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from labbench.errors import UserError
from labbench.input_files import open_regular

REQUIRED = ("t", "force", "position")
MIN_SAMPLES = 64
# Relative tolerance on the sample interval: CSV time stamps are usually
# printed with a few digits, so rounding must not count as jitter.
UNIFORM_RTOL = 1e-3
# Largest magnitude of each column: beyond any bench (and squares of 1e308 overflow).
MAX_ABS = {"t": (1e9, "s"), "force": (1e6, "N"), "position": (1e3, "m")}
CHUNK_ROWS = 1 << 18  # CSV rows parsed at a time
BLOCK_CHARS = 1 << 18  # characters read at a time (a chunk is cut at a block's end)
MAX_CSV_BYTES = 4 << 30  # 4 GiB: ~100 million rows
MAX_LINE_CHARS = 1 << 16  # of any line
MAX_META_LINES = 10_000
MAX_BLANK_LINES = 10_000  # among the rows
# Rows of one CSV: 33.5 million (805 MiB as three columns; a run records at most 10^7
# samples, an hour at 10 kHz is 3.6 x 10^7): a file of short rows ("0,0,0") could otherwise
# ask for more memory than the machine has.
MAX_ROWS = 1 << 25


@dataclass
class Recording:
    """Uniformly sampled force (exogenous, N) and position (m) with metadata."""

    t: np.ndarray
    force: np.ndarray
    position: np.ndarray
    meta: dict = field(default_factory=dict)
    source: str = "<arrays>"

    @property
    def fs(self) -> float:
        """Sample rate [Hz] from the mean interval."""
        return (len(self.t) - 1) / float(self.t[-1] - self.t[0])

    @property
    def T(self) -> float:
        return 1.0 / self.fs

    def __len__(self) -> int:
        return len(self.t)


def recording_from_arrays(t, force, position, meta=None, source: str = "<arrays>") -> Recording:
    """Validate arrays (finite, same length, enough samples, uniform t) into a Recording."""
    arrays = {}
    for name, values in (("t", t), ("force", force), ("position", position)):
        try:
            a = np.asarray(values, dtype=float).ravel()
        except (TypeError, ValueError):
            raise UserError(f"{source}: column {name!r} is not numeric") from None
        arrays[name] = a
    n = len(arrays["t"])
    if any(len(a) != n for a in arrays.values()):
        raise UserError(f"{source}: t, force and position have different lengths")
    if n < MIN_SAMPLES:
        raise UserError(f"{source}: only {n} samples; need at least {MIN_SAMPLES}")
    for name, a in arrays.items():
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise UserError(f"{source}: non-finite {name} at sample {bad[0]} (row {bad[0] + 1})")
        limit, unit = MAX_ABS[name]
        bad = np.flatnonzero(np.abs(a) > limit)
        if bad.size:
            raise UserError(f"{source}: {name} = {a[bad[0]]:g} {unit} at sample {bad[0]} is beyond "
                            f"+-{limit:g} {unit}, no bench's range")
    _check_uniform(arrays["t"], source)
    rec = Recording(arrays["t"], arrays["force"], arrays["position"], dict(meta or {}), source)
    fs = rec.meta.get("fs")
    if fs is not None and not (isinstance(fs, float) and abs(fs - rec.fs) <= UNIFORM_RTOL * rec.fs):
        raise UserError(f"{source}: metadata fs={fs} contradicts the time column "
                        f"({rec.fs:.6g} Hz); correct or remove it")
    return rec


def _check_uniform(t: np.ndarray, source: str) -> None:
    dt = np.diff(t)
    step = float(np.median(dt))
    if not step > 0:
        raise UserError(f"{source}: time column t is not increasing")
    bad = np.flatnonzero(np.abs(dt - step) > UNIFORM_RTOL * step)
    if bad.size:
        k = bad[0] + 1
        raise UserError(
            f"{source}: sampling is not uniform at data row {k + 1} (t = {t[k]:.9g} s; "
            f"expected step {step:.6g} s, got {dt[k - 1]:.6g} s)"
        )


def load_recording(path, warn=None) -> Recording:
    """Load a CSV (see module doc) or a labbench session; a clear UserError otherwise.
    ``warn(line)``: a session read up to a damaged record says so."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    if path.suffix.lower() != ".csv":
        # lazy: sessions are another module's business
        from labbench.sessions.session_content import load_analysis_arrays
        from labbench.sessions.session_format import looks_like_session

        if looks_like_session(path):
            return recording_from_arrays(**load_analysis_arrays(path, warn), source=str(path))
    return _load_csv(path)


def _load_csv(path: Path) -> Recording:
    """Metadata and header line by line, then the numbers in chunks of ``CHUNK_ROWS`` rows
    (numpy's parser) from blocks of ``BLOCK_CHARS`` (``_data_lines``): memory stays near
    twice the three arrays, whatever the file holds."""
    src = str(path)
    with open_regular(path, "CSV file", MAX_CSV_BYTES) as raw:
        text = io.TextIOWrapper(raw, encoding="utf-8", newline="")
        try:
            meta, header, line_no = _csv_head(text, src)
            cols = [header.index(c) for c in REQUIRED]
            parts = [_parse_rows(lines, cols, before, src)
                     for before, lines in _data_lines(text, line_no, src)]
        except UnicodeDecodeError as exc:
            raise UserError(f"{src}: not UTF-8 text (byte {exc.start} of a block)") from None
        except OSError as exc:
            raise UserError(f"{src}: cannot read ({exc.strerror or exc})") from None
    # one contiguous array per column, joined from the chunks (columns of a 2-D array would be
    # strided views, copied again by the validation: a third copy)
    t, force, position = (np.concatenate([c[:, j] for c in parts]) if parts else np.empty(0)
                          for j in range(3))
    del parts
    return recording_from_arrays(t, force, position, meta, src)


def _csv_head(text, src: str) -> tuple[dict, list[str], int]:
    """(metadata, lower-case header, number of lines read) of a CSV stream."""
    meta: dict = {}
    for line_no in itertools.count(1):
        line = text.readline(MAX_LINE_CHARS + 1)
        if len(line) > MAX_LINE_CHARS:
            raise UserError(f"{src}: line {line_no} is longer than {MAX_LINE_CHARS} characters")
        if not line:
            raise UserError(f"{src}: no header row (expected columns {', '.join(REQUIRED)})")
        if line.startswith("#") or not line.strip():
            if line_no > MAX_META_LINES:
                raise UserError(f"{src}: more than {MAX_META_LINES} comment lines before the header")
            body = line.lstrip("#").strip()
            if "=" in body:
                key, value = (x.strip() for x in body.split("=", 1))
                meta[key] = _meta_value(value)
            continue
        header = [h.strip().lower() for h in next(csv.reader([line]))]
        missing = [c for c in REQUIRED if c not in header]
        if missing:
            raise UserError(f"{src}: missing column(s) {', '.join(missing)} "
                            f"(header: {','.join(header)[:200]})")
        return meta, header, line_no
    raise AssertionError("unreachable")


def _data_lines(text, before: int, src: str):
    """(lines before it, ``CHUNK_ROWS`` lines or a few more) of a CSV stream's data, read
    ``BLOCK_CHARS`` characters at a time, every line checked as it comes: a NUL, a line
    longer than ``MAX_LINE_CHARS``, more than ``MAX_BLANK_LINES`` blank lines or
    ``MAX_ROWS`` lines is one UserError at once. (A line was read whole: a 1 GiB file ending
    in NULs took 30.7 s and 2.2 GB before a MemoryError.)"""
    lines: list[str] = []
    rest, seen, blank = "", before, 0
    while block := text.read(BLOCK_CHARS):
        nul = block.find("\x00")
        if nul >= 0:
            at = seen + len(lines) + (rest + block[:nul]).count("\n") + 1
            raise UserError(f"{src}: line {at} holds a NUL byte: not a CSV of numbers")
        pieces = (rest + block).split("\n")
        rest = pieces.pop()
        if len(rest) > MAX_LINE_CHARS or any(len(p) > MAX_LINE_CHARS for p in pieces):
            k = next((i for i, p in enumerate(pieces) if len(p) > MAX_LINE_CHARS), len(pieces))
            raise UserError(f"{src}: line {seen + len(lines) + k + 1} is longer than "
                            f"{MAX_LINE_CHARS} characters")
        blank += sum(not p.strip() for p in pieces)
        if blank > MAX_BLANK_LINES:
            raise UserError(f"{src}: more than {MAX_BLANK_LINES} blank lines among the rows")
        lines += pieces
        if seen + len(lines) - before > MAX_ROWS:
            raise UserError(f"{src}: more than {MAX_ROWS} rows; at most {MAX_ROWS} are read "
                            f"({MAX_ROWS * 24 >> 20} MiB of samples)")
        if len(lines) >= CHUNK_ROWS:  # a chunk and the rest of its block (< BLOCK_CHARS)
            chunk, lines = lines, []
            yield seen, chunk
            seen += len(chunk)
            del chunk
    if rest:
        lines.append(rest)
    if lines:
        yield seen, lines


def _parse_rows(lines: list[str], cols: list[int], before: int, src: str) -> np.ndarray:
    """The ``cols`` of a chunk of data lines (line ``before + 1`` is the first) as floats."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # numpy warns (not raises) on an empty chunk
            return np.loadtxt(lines, delimiter=",", usecols=cols, dtype=float, ndmin=2,
                              comments=None, quotechar='"')
    except (ValueError, UserWarning):
        pass
    for k, line in enumerate(lines):  # the slow path only finds the line to name
        row = line.rstrip("\r\n").split(",")
        try:
            [float(row[c]) for c in cols]
        except (ValueError, IndexError):
            raise UserError(f"{src}: line {before + k + 1} is not a row of numbers: "
                            f"{line.strip()[:80]!r}") from None
    raise UserError(f"{src}: rows {before + 1}-{before + len(lines)} are not rows of numbers")


def _meta_value(text: str):
    """Numbers become floats (``inf`` too); anything else stays a string."""
    try:
        value = float(text)
    except ValueError:
        return text
    return value if math.isfinite(value) or math.isinf(value) else text


def position_quantum(x: np.ndarray) -> float | None:
    """Encoder step [m] if all positions sit on one grid, else None.

    The candidate step is the smallest non-zero change between samples; the
    record counts as quantised when every position is a whole number of steps
    from the first (within 1e-3 step).
    """
    x = np.asarray(x, float)
    if len(x) > 4096 and position_quantum(x[:: len(x) // 2048]) is None:
        return None  # cheap rejection on a subsample; a grid holds on every subsample
    d = np.abs(np.diff(x))
    d = d[d > 0]
    if d.size == 0:
        return None
    q = float(d.min())
    steps = (x - x[0]) / q
    if np.max(np.abs(steps)) > 2**40 or np.max(np.abs(steps - np.round(steps))) > 1e-3:
        return None
    return q
