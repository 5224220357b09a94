"""The stiffness and damping a display really renders: the low-frequency limits of its
effective stiffness ES and damping ED, read off a measured closed-loop impedance Z.

Below its bandwidths a rendered VE is K / (jw) + B_felt + jw M_felt (paper eq. 2 expanded
about w = 0: ES(w) = K - M w^2 + ..., ED(w) = b + B - K tau + O(w^2)); the stiffness the
hand feels is ES(0), the damping ED(0) (the device's own b included, delay's effect too).
Re Z and Im Z * w are even in w, so each is fitted as a polynomial in w^2 over the band
where the VE holds (``band``: up to w_s*, where ES crosses zero, and half of w_b*, where
ED has fallen half-way to b; Colonnese et al. sec. 3):

    Re Z = B + c1 w^2 + c2 w^4,      -w Im Z = K - M w^2 + c3 w^4,

weighted by the ETFE's own standard errors. The 95 % intervals are the sandwich of the
weighted fit with the ETFE's error correlation between frequencies (neighbouring bands share
DFT bins: ``EtfeResult.error_corr``), widened by the truncation bias: the change when the
last term is dropped (on the exact sampled model over this band the three-term limits are
within 1e-4 of the true ones, and the change bounds that 10-100 times over).

The same fit to the exact sampled theory over the same frequencies gives the prediction
to hold it against (``theory``), and the theory's own limit (``labbench.model.linear``) is kept
beside it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from labbench.analysis.etfe import EtfeResult

MIN_FREQUENCIES = 8  # three coefficients per part, and some to spare
WB_SHARE = 0.5  # the band ends at this share of w_b* (ED half-way to b there: not its limit)
Z95 = 1.959964  # the intervals pool many frequencies: normal quantile
ROUND_OFF = 1e-12  # relative error of Z that floating point leaves on noise-free data


@dataclass(frozen=True)
class LowFrequency:
    """ES(0) = K [N/m] and ED(0) = B [N s/m] with 95 % intervals, from ``n_freq``
    frequencies in ``band_rad_s``."""

    K: float
    K_ci95: tuple[float, float]
    B: float
    B_ci95: tuple[float, float]
    band_rad_s: tuple[float, float]
    n_freq: int

    def reaching(self, other: LowFrequency) -> LowFrequency:
        """These limits with intervals grown to hold ``other``'s values, each with an
        interval as wide as this one's."""
        def hull(v, ci, o):
            return min(ci[0], o - (v - ci[0])), max(ci[1], o + (ci[1] - v))
        return LowFrequency(self.K, hull(self.K, self.K_ci95, other.K), self.B,
                            hull(self.B, self.B_ci95, other.B), self.band_rad_s, self.n_freq)

    def as_dict(self) -> dict:
        return {"K": self.K, "K_ci95": list(self.K_ci95), "B": self.B, "B_ci95": list(self.B_ci95),
                "band_rad_s": list(self.band_rad_s), "n_freq": self.n_freq}


def band(lo: float, ws_star: float | None, wb_star: float | None, T: float,
         top: float) -> tuple[float, float]:
    """The band the limits are read from: from ``lo`` up to w_s* and ``WB_SHARE`` of w_b*
    (either None: no such bound), a tenth of Nyquist and ``top`` [rad/s]."""
    bounds = [top, 0.1 * math.pi / T]
    if ws_star:
        bounds.append(ws_star)
    if wb_star:
        bounds.append(WB_SHARE * wb_star)
    return float(lo), float(min(bounds))


def fit(w: np.ndarray, Z: np.ndarray, se: np.ndarray | None = None,
        corr: np.ndarray | None = None, where: tuple[float, float] | None = None) -> LowFrequency | None:
    """ES(0) and ED(0) of ``Z`` on ``w`` within ``where`` (the module doc); ``se``: the
    standard error sqrt(E |dZ|^2) per frequency (None: exact data, unit weights, intervals
    of the truncation bias alone); ``corr``: the complex correlation of the errors of G =
    1 / (jw Z) between all frequencies of ``w`` (None: independent). None when fewer than
    ``MIN_FREQUENCIES`` frequencies lie in the band."""
    w, Z = np.asarray(w, float), np.asarray(Z, complex)
    lo, hi = where if where is not None else (w[0], w[-1])
    sel = np.flatnonzero((w >= lo) & (w <= hi) & np.isfinite(Z))
    if len(sel) < MIN_FREQUENCIES:
        return None
    ws, Zs = w[sel], Z[sel]
    if se is None:
        sd = np.ones(len(sel))
        cov = None
    elif corr is None:  # independent errors: the covariance's diagonal, sd^2 / 2 (below), as a
        # vector (as n x n matrices over the bins of a paper estimate of 1800 s it took 2 GB)
        sd = np.maximum(np.asarray(se, float)[sel], ROUND_OFF * np.abs(Zs))
        cov = sd**2 / 2
    else:  # a noise-free record's errors are floating-point round-off, not zero
        sd = np.maximum(np.asarray(se, float)[sel], ROUND_OFF * np.abs(Zs))
        rho = np.asarray(corr)[np.ix_(sel, sel)]
        # errors of Z from those of G: dZ = -Z dG / G, Z / G = jw Z^2 (phase u); circular, so
        # Re and Im parts each carry half of Re E[dZ_i conj(dZ_l)]
        u = 1j * Zs**2 / np.maximum(np.abs(Zs) ** 2, 1e-300)
        gamma = rho * np.outer(sd * u, np.conj(sd * u))
        cov = np.real(gamma) / 2
    x = ws**2
    cov_k = None if cov is None else cov * ws**2 if cov.ndim == 1 else cov * np.outer(ws, ws)
    K, K_half = _limit(x, -ws * Zs.imag, ws * sd, cov_k)
    B, B_half = _limit(x, Zs.real, sd, cov)
    return LowFrequency(K, (K - K_half, K + K_half), B, (B - B_half, B + B_half),
                        (float(ws[0]), float(ws[-1])), len(sel))


def _limit(x: np.ndarray, y: np.ndarray, sd: np.ndarray, cov: np.ndarray | None) -> tuple[float, float]:
    """y(0) of a weighted quadratic fit in x = w^2 and its 95 % half-width: the sandwich of the
    fit with the error covariance ``cov`` (None: none; a vector: the variances of independent
    errors) plus the truncation bias, the change of
    y(0) from the linear fit."""
    scale = x.max()
    t = x / scale  # conditioning: t in (0, 1]
    wts = 1.0 / sd**2
    est = []
    for order in (2, 1):
        A = np.vander(t, order + 1, increasing=True)
        H = np.linalg.solve(A.T @ (A * wts[:, None]), (A * wts[:, None]).T)
        est.append((float(H[0] @ y), H[0]))
    (y0, h0), (y1, _) = est
    half = abs(y0 - y1)
    if cov is not None:  # a matrix, or a vector: its diagonal (independent errors)
        var = h0**2 @ cov if cov.ndim == 1 else h0 @ cov @ h0
        half += Z95 * math.sqrt(max(float(var), 0.0))
    return y0, half


def measured(res: EtfeResult, where: tuple[float, float]) -> LowFrequency | None:
    """``fit`` of an ETFE over ``where`` with its own errors and their correlation. Where a
    force sensor's noise may sit in the record (``EtfeResult.Z_force``), the intervals also
    reach the limits of the reading with the noise in the force, as its bands do, that
    reading's interval taken as wide as this one's (same bins, same noise)."""
    corr = res.error_corr() if res.error_corr is not None else None
    got = fit(res.w, res.Z, res.Z_se, corr, where)
    if got is None or res.Z_force is None:
        return got
    other = fit(res.w, res.Z_force, res.Z_se, corr, where)
    return got if other is None else got.reaching(other)


def reading_band(res: EtfeResult, ve, plant, latency: float = 0.0,
                 asked: tuple[float, float] | None = None) -> tuple[float, float]:
    """The band the rendered K, B of ``res`` are read from (``band``): the analysis band
    (``asked``, within what the record resolves) below the VE's predicted bandwidths."""
    from labbench.model import predictions
    from labbench.analysis.etfe import analysis_band

    bw = predictions.bandwidths(plant, ve, latency)
    lo, top = analysis_band(asked, res.w)
    return band(lo, bw.ws_star, bw.wb_star, ve.T, top)


def rendered_impedance(res: EtfeResult, ve, plant, latency: float = 0.0,
                       asked: tuple[float, float] | None = None) -> dict | None:
    """What the display rendered (``measured``) beside what was commanded and what the exact
    sampled theory predicts for it (the same fit to its curve over the same frequencies, and
    its true limit), as recorded in a run's results under ``rendered``; None when the band
    holds too few frequencies (a record too short for the VE's bandwidths)."""
    from labbench.model import linear
    from labbench.analysis.compare import theory_curves

    where = reading_band(res, ve, plant, latency, asked)
    got = measured(res, where) if where[1] > where[0] else None
    if got is None:
        return None
    curves = theory_curves(plant, ve, res.w, latency)
    th = fit(res.w, curves["Z"], where=where)
    ed0 = linear.low_frequency(plant, ve, curves["model"], latency)[0]
    return {**got.as_dict(),
            "theory": {"model": curves["model"], "K": th.K, "B": th.B, "K_limit": ve.K, "B_limit": ed0},
            "commanded": {"K": ve.K, "B": ve.B, "b": plant.b}}
