"""The force noise a record's command carries: what of the command is not the loop's linear
response to its own excitation, its spectrum and its RMS in a band, with a 95 % interval.

The command of a closed loop driven by a recorded excitation f is U = H F + T + V at every
DFT bin of the whole record: H the loop's (unknown, smooth) response, T the transient (the
record's ends: smooth in frequency too) and V the noise, whatever its cause (the encoder step,
the amplifier's noise through the loop, friction's stick-slip). The local polynomial method
(Pintelon, Schoukens, Vandersteen & Barbe, "Estimation of nonparametric noise and FRF models
for multivariable systems, Part I: theory", Mech. Syst. Signal Process. 24(3), 2010) fits H and
T as polynomials of degree ``ORDER`` over 2R + 1 neighbouring bins and takes the residual's
power, divided by its degrees of freedom q = 2R + 1 - 2(ORDER + 1), as |V|^2 there. Unlike
the coherence of a Welch estimate (S_uu (1 - gamma^2)), it is not biased by the leakage of a
loop whose response outlasts a segment: on a spring of 50 N/m with B = 0 (a 2 s ring-down)
a 4 s Welch segment read the 0.55 mN of quantisation noise as 0.57 mN, 1 s segments as 0.79.
Where the excitation has no power (outside its band) only T is fitted.

The windows do not overlap, so each gives an independent estimate, sigma^2 chi^2_{2q} / 2q
for complex Gaussian V; the band power is their weighted sum, its 95 % interval the
chi-square one with Satterthwaite's degrees of freedom (Satterthwaite, Biometrics Bull. 2(6),
1946).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from labbench.errors import UserError

HALF_WIDTH = 7  # R: 15 bins per window
ORDER = 2
MIN_SAMPLES = 256
NO_EXCITATION = 1e-10  # window's excitation power below this share of the band's median: T only


@dataclass(frozen=True)
class MeasuredNoise:
    """``rms_n`` in ``band_hz`` with ``ci95`` (N); ``f_hz``, ``psd`` (one-sided N^2/Hz at each
    window's centre); ``dof``: the band power's Satterthwaite degrees of freedom."""

    band_hz: tuple[float, float]
    rms_n: float
    ci95: tuple[float, float]
    dof: float
    f_hz: np.ndarray
    psd: np.ndarray

    def as_dict(self, spectrum: bool = False) -> dict:
        out = {"band_hz": list(self.band_hz), "rms_n": self.rms_n, "ci95": list(self.ci95),
               "dof": self.dof, "method": "local polynomial residual of command on excitation"}
        if spectrum:
            out.update(f_hz=self.f_hz.tolist(), psd=self.psd.tolist())
        return out


def measure(command, excitation, T: float, band_hz: tuple[float, float]) -> MeasuredNoise:
    """The noise in ``command`` [N] not explained linearly by ``excitation`` [N], both sampled
    every ``T`` s (module doc); RMS over ``band_hz`` (capped at the Nyquist frequency)."""
    u = np.asarray(command, float)
    f = np.asarray(excitation, float)
    if u.shape != f.shape or u.ndim != 1:
        raise UserError("command and excitation must be two 1-D records of the same length")
    if len(u) < MIN_SAMPLES:
        raise UserError(f"a force-noise estimate needs at least {MIN_SAMPLES} samples, "
                        f"got {len(u)}")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(f))):
        raise UserError("command and excitation must be finite")
    N = len(u)
    nyq = 0.5 / T
    lo, hi = float(band_hz[0]), min(float(band_hz[1]), nyq)
    if not 0 <= lo < hi:
        raise UserError(f"band must be 0 <= low < high <= {nyq:g} Hz, got {band_hz!r}")
    U, F = np.fft.rfft(u), np.fft.rfft(f)
    df = 1.0 / (N * T)
    R = HALF_WIDTH
    width = 2 * R + 1
    first = max(int(math.ceil(lo / df)) + R, R + 1)
    centres = np.arange(first, len(U) - R, width)
    centres = centres[(centres - R) * df <= hi]
    if not len(centres):
        raise UserError(f"the band {lo:g}-{hi:g} Hz holds too few frequencies of a "
                        f"{N * T:g} s record")
    idx = centres[:, None] + np.arange(-R, R + 1)[None, :]
    r = np.arange(-R, R + 1, dtype=float) / R
    powers = np.vander(r, ORDER + 1, increasing=True)  # (width, ORDER + 1)
    Fw, Uw = F[idx], U[idx]
    ex = np.mean(np.abs(Fw) ** 2, axis=1)
    excited = ex > NO_EXCITATION * max(float(np.median(ex)), 1e-300)
    sigma2 = np.empty(len(centres))
    for mask, with_h in ((excited, True), (~excited, False)):
        if not mask.any():
            continue
        T_cols = np.broadcast_to(powers, (int(mask.sum()), width, ORDER + 1))
        cols = np.concatenate([Fw[mask][:, :, None] * powers[None], T_cols], axis=2) \
            if with_h else T_cols.astype(complex)
        q = width - cols.shape[2]
        coef, *_ = _lstsq(cols, Uw[mask])
        resid = Uw[mask] - np.einsum("kij,kj->ki", cols, coef)
        sigma2[mask] = np.sum(np.abs(resid) ** 2, axis=1) / q
    dof_window = 2 * np.where(excited, width - 2 * (ORDER + 1), width - (ORDER + 1))
    psd = 2 * T * sigma2 / N  # E|V_k|^2 = N var for white noise of that level
    # each window stands for the bins it spans that lie in the band
    in_band = np.sum((idx * df >= lo) & (idx * df <= hi), axis=1)
    c = in_band * df
    power = float(np.sum(c * psd))
    terms = c * psd
    nu = 2 * power**2 / float(np.sum(terms**2 * 2 / dof_window)) if power > 0 else 0.0
    if nu > 0:
        ci = (math.sqrt(power * nu / stats.chi2.ppf(0.975, nu)),
              math.sqrt(power * nu / stats.chi2.ppf(0.025, nu)))
    else:
        ci = (0.0, 0.0)
    return MeasuredNoise(band_hz=(lo, hi), rms_n=math.sqrt(power), ci95=ci, dof=nu,
                         f_hz=centres * df, psd=psd)


def _lstsq(A: np.ndarray, y: np.ndarray):
    """Batched least squares of y[k] ~ A[k] theta[k] through a QR of each A[k] (columns are
    scaled alike: r in [-1, 1])."""
    Q, Rm = np.linalg.qr(A)
    rhs = np.einsum("kij,ki->kj", Q.conj(), y)
    return (np.linalg.solve(Rm, rhs[..., None])[..., 0],)
