"""One entry point for data in: a CSV file or a recorded labbench session.

CSV layout: optional leading ``# key=value`` lines (metadata), one header row,
then numeric rows; columns ``t`` [s], ``force`` [N], ``position`` [m] in any
order, other columns ignored. Sampling must be uniform.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from labbench.errors import UserError

REQUIRED = ("t", "force", "position")
MIN_SAMPLES = 64
# Relative tolerance on the sample interval: CSV time stamps are usually
# printed with a few digits, so rounding must not count as jitter.
UNIFORM_RTOL = 1e-3


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
    _check_uniform(arrays["t"], source)
    return Recording(arrays["t"], arrays["force"], arrays["position"], dict(meta or {}), source)


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


def load_recording(path) -> Recording:
    """Load a CSV (see module doc) or a labbench session; a clear UserError otherwise."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    if path.suffix.lower() != ".csv":
        # lazy: sessions are another module's business
        from labbench.session_content import load_analysis_arrays
        from labbench.session_format import looks_like_session

        if looks_like_session(path):
            return recording_from_arrays(**load_analysis_arrays(path), source=str(path))
    return _load_csv(path)


def _load_csv(path: Path) -> Recording:
    src = str(path)
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            lines = fh.read().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{src}: cannot read as a CSV text file ({exc.__class__.__name__})") from None
    meta: dict = {}
    i = 0
    while i < len(lines) and (lines[i].startswith("#") or not lines[i].strip()):
        text = lines[i].lstrip("#").strip()
        if "=" in text:
            key, value = (s.strip() for s in text.split("=", 1))
            meta[key] = _meta_value(value)
        i += 1
    if i >= len(lines):
        raise UserError(f"{src}: no header row (expected columns {', '.join(REQUIRED)})")
    rows = list(csv.reader(lines[i:]))
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise UserError(f"{src}: missing column(s) {', '.join(missing)} (header: {','.join(header)})")
    cols = [header.index(c) for c in REQUIRED]
    data = np.empty((len(rows) - 1, 3))
    for r, row in enumerate(rows[1:]):
        try:
            data[r] = [float(row[c]) for c in cols]
        except (ValueError, IndexError):
            raise UserError(f"{src}: line {i + r + 2} is not a row of numbers: {','.join(row)[:80]!r}") from None
    return recording_from_arrays(data[:, 0], data[:, 1], data[:, 2], meta, src)


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
