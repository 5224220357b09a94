"""Live ETFE at constant cost per update: H1 spectra accumulated segment by segment.

Z = F / (jw X) from Welch-averaged spectra (Welch 1967; Bendat & Piersol, Random
Data, sec. 9.1): each time the record grows past a new segment (Hann window,
linear detrend, 50 % overlap, exactly as ``labbench.analysis.etfe``'s
``h1-welch`` and ``scipy.signal.csd`` cut it), that segment's DFTs are added to
the sums S_ff = sum |F|^2, S_xx = sum |X|^2, S_fx = sum conj(F) X. Nothing is
recomputed: adding a block of samples costs its copy plus, once per half
segment, two FFTs of one segment, whatever the record's length; only the last two longest segments
are kept.

Segments of several lengths (``LEVELS``) are summed side by side: a short one
gives an estimate within seconds, a long one the resolution the low frequencies
need. ``estimate()`` uses the longest level with at least ``MIN_SEGMENTS``
segments (the shortest with one, early on), averages its bins over bands of
constant relative width on the log grid of ``labbench.analysis.etfe`` (as
``h1-log`` does on the full record), and gives the 95 % radius from the H1
statistics with the averages counted: segments x bins per band / 1.5 (the Hann
window's equivalent noise bandwidth in bins; adjacent bins are correlated).

The run's final estimate is still ``labbench.analysis.etfe.etfe`` on the whole
record with the run's estimator; this one is for watching a run.
"""
from __future__ import annotations

import numpy as np
from scipy import signal

from labbench.analysis.etfe import (
    LOW_COHERENCE,
    EtfeResult,
    _band_sum,
    _grid,
    _h1_err,
)
from labbench.errors import UserError

NAME = "live-welch"
LEVELS = (2**11, 2**13, 2**15)  # 2 s, 8 s, 33 s at 1 kHz
MIN_SEGMENTS = 3
HANN_ENBW_BINS = 1.5


class _Level:
    """The H1 sums of one segment length; work arrays made once (no allocation per segment)."""

    def __init__(self, n: int):
        self.n, self.hop = n, n // 2
        self.window = signal.get_window("hann", n)  # periodic, as scipy.signal.welch
        self._t = np.arange(n) - (n - 1) / 2  # centred sample index, for the detrend
        self._tt = float(self._t @ self._t)
        self._buf = np.empty(n)
        self._F, self._X, self._c = (np.empty(n // 2 + 1, complex) for _ in range(3))
        self._r = np.empty(n // 2 + 1)
        self.next = 0  # first sample of the next segment
        self._half = False  # its force transformed, the position not yet
        self.count = 0
        self.sff = np.zeros(n // 2 + 1)
        self.sxx = np.zeros(n // 2 + 1)
        self.sfx = np.zeros(n // 2 + 1, complex)
        self._warm()

    def _warm(self) -> None:
        """Fault in every work array's pages and build the FFT's plan now: done lazily, by
        the first segment, they made that update several times dearer than the others."""
        for a in (self._buf, self._F, self._X, self._c, self._r, self.sff, self.sxx, self.sfx):
            a.fill(0)
        np.fft.rfft(self._buf, out=self._F)

    def step(self, f: np.ndarray, x: np.ndarray) -> None:
        """Half of the work on the segment ``f``, ``x`` (n samples each): the force's
        transform, then (next call) the position's and the sums. Half steps keep the
        dearest update at one transform."""
        F, X, c, r = self._F, self._X, self._c, self._r
        if not self._half:
            np.fft.rfft(self._tapered(f), out=F)
            self._half = True
            return
        self._half = False
        np.fft.rfft(self._tapered(x), out=X)
        for spectrum, total in ((F, self.sff), (X, self.sxx)):
            np.multiply(spectrum.real, spectrum.real, out=r)
            total += r
            np.multiply(spectrum.imag, spectrum.imag, out=r)
            total += r
        np.conjugate(F, out=c)
        c *= X
        self.sfx += c
        self.count += 1
        self.next += self.hop

    def _tapered(self, y: np.ndarray) -> np.ndarray:
        """y less its least-squares line, times the window. The line in closed form, as
        ``scipy.signal.detrend(type="linear")`` fits it (that one calls LAPACK: 10x slower).
        No BLAS either: a threaded dot product spin-waits for its worker threads, which
        another process's load can keep off the CPU for ms (measured: 4 ms for 2^15 points)."""
        out = self._buf
        np.multiply(self._t, y, out=out)
        np.multiply(self._t, out.sum() / self._tt, out=out)
        np.subtract(y, out, out=out)
        out -= out.mean()
        out *= self.window
        return out


class LiveEtfe:
    """Accumulates force and position block by block; ``estimate()`` at any time.

    ``add(..., budget=n)`` makes at most about n samples' worth of transforms in that
    call (the oldest segment first; at least one transform when one is due), leaving
    the rest to later calls: segments of all lengths fall due together every
    longest hop, and one call should not pay for all of them. ``budget=None`` (default)
    brings every sum up to date.
    """

    def __init__(self, fs: float, levels: tuple[int, ...] = LEVELS):
        if not fs > 0:
            raise UserError(f"sample rate must be positive, got {fs!r}")
        self.fs = float(fs)
        self.levels = [_Level(n) for n in sorted(levels)]
        self._cap = 2 * max(levels)  # kept: from the oldest segment not yet summed on
        self._f = np.empty(self._cap)
        self._x = np.empty(self._cap)
        self._offset = 0  # record index of self._f[0]
        self.n = 0  # samples added

    def add(self, force, position, budget: int | None = None) -> None:
        """Append equal-length blocks of the exogenous force [N] and position [m]."""
        f = np.asarray(force, float).ravel()
        x = np.asarray(position, float).ravel()
        if len(f) != len(x):
            raise UserError(f"force and position blocks differ in length ({len(f)}, {len(x)})")
        step = self._cap // 2
        for i in range(0, len(f), step):  # a long block in pieces that fit the buffer
            self._append(f[i:i + step], x[i:i + step])
        self._work(budget)

    def _append(self, f: np.ndarray, x: np.ndarray) -> None:
        if self.n + len(f) - self._offset > self._cap:  # drop what every level has summed
            self._work(None)
            keep = min(lv.next for lv in self.levels)
            a, b = keep - self._offset, self.n - self._offset
            self._f[:b - a] = self._f[a:b]
            self._x[:b - a] = self._x[a:b]
            self._offset = keep
        a = self.n - self._offset
        self._f[a:a + len(f)] = f
        self._x[a:a + len(f)] = x
        self.n += len(f)

    def _work(self, budget: int | None) -> None:
        spent = 0
        while True:
            due = [lv for lv in self.levels if lv.next + lv.n <= self.n]
            if not due:
                return
            lv = min(due, key=lambda level: level.next)
            if budget is not None and spent and spent + lv.n > budget:
                return
            a = lv.next - self._offset
            lv.step(self._f[a:a + lv.n], self._x[a:a + lv.n])
            spent += lv.n

    def level(self) -> _Level | None:
        """The level ``estimate`` uses (None before the shortest has one segment)."""
        ready = [lv for lv in self.levels if lv.count >= MIN_SEGMENTS]
        if ready:
            return ready[-1]
        return self.levels[0] if self.levels[0].count else None

    def raw(self, level: _Level) -> tuple[np.ndarray, np.ndarray]:
        """(w, Z) on every bin of ``level`` but DC: the Welch H1 estimate itself."""
        k = np.arange(1, level.n // 2 + 1)
        w = 2 * np.pi * self.fs * k / level.n
        return w, level.sff[k] / (1j * w * level.sfx[k])

    def estimate(self) -> EtfeResult | None:
        """Z on the log grid from the sums so far; None before one segment."""
        level = self.level()
        if level is None:
            return None
        k, half = _grid(level.n // 2 + 1)
        w = 2 * np.pi * self.fs * k / level.n
        sff = _band_sum(level.sff, k, half)
        sxx = _band_sum(level.sxx, k, half)
        sfx = _band_sum(level.sfx, k, half)
        with np.errstate(divide="ignore", invalid="ignore"):  # no force or no motion in a band
            Z = sff / (1j * w * sfx)
            coh = np.clip(np.abs(sfx) ** 2 / (sff * sxx), 0, 1)
        n_avg = level.count * (2 * half + 1) / HANN_ENBW_BINS
        se, err = _h1_err(Z, coh, n_avg)
        return EtfeResult(NAME, w, Z, coh, err, se, coh < LOW_COHERENCE, force_power=sff / (2 * half + 1))
