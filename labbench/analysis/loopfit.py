"""Fit the exact sampled closed-loop model to a measured impedance: plant m, b and the
rig's extra loop delay td (``labbench analyze etfe --fit``).

Model: ``labbench.theory.z_sampled(Plant(m, b), ve, w, latency=td)``, the exact
sampled loop of the VE in the metadata (its own software delay ``ve.td``
included, whole samples) with an actuator latency ``td`` >= 0 on the whole
command, continuous in td (fractions of a sample: the held command split over
two samples, ``labbench.theory`` module doc). With ``fit_ve`` the rendered K
and B are free too (the VE's law and filter stay those of the metadata).

Weighted complex least squares (``scipy.optimize.least_squares``, trust region
with bounds m > 0, b >= 0, td >= 0): residual ``(Z - Z_model) / sigma`` at
every estimated frequency with coherence >= 0.8 below FIT_W_MAX x Nyquist,
sigma = Z_err / sqrt(ln 20) (the ETFE's 95 % radius of a circular complex
error). The phase of a delay wraps, so the cost has local minima in td: td
starts from the best point of a grid over 0-TD_GRID_MAX samples (quarter
samples, m and b at their start values).

95 % intervals: Gauss-Newton covariance ``s^2 (J^T J)^-1`` with s^2 the
residual variance (so a misfit or a mis-stated Z_err widens them rather than
being ignored), inflated by ``(1 + rho) / (1 - rho)`` for the lag-one
correlation rho of the standardised residuals along frequency (neighbouring
ETFE bands share DFT bins), ``theta +- t(0.975, dof) * se``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

from labbench import theory
from labbench.analysis.etfe import LOW_COHERENCE, R95, EtfeResult
from labbench.errors import UserError
from labbench.ve import Plant, VirtualEnvironment

FIT_W_MAX = 0.5  # fraction of the Nyquist frequency: above it the sampled loop's Z
# swings by orders of magnitude and a few near-Nyquist bins would set the fit
W_MIN = 1.0  # rad/s: below it records rarely resolve anything
TD_GRID_MAX, TD_GRID_STEP = 10.0, 0.25  # samples
MIN_POINTS = 10


@dataclass
class LoopFit:
    m: float
    b: float
    td_s: float
    ci95: dict  # name -> (lo, hi)
    K: float | None = None  # rendered stiffness and damping (fit_ve)
    B: float | None = None
    td_meta_s: float = 0.0  # the VE's own td from the metadata (in the model, not fitted)
    residual_rms: float = 0.0  # rms |Z - Z_model| / |Z| over the fitted frequencies
    chi2_dof: float = 0.0  # weighted residual variance (1 when Z_err is right and the model fits)
    n_freq: int = 0
    band_rad_s: tuple = ()
    Z_model: np.ndarray | None = field(default=None, repr=False)

    def as_dict(self) -> dict:
        d = {"m": self.m, "b": self.b, "td_s": self.td_s,
             "ci95": {k: list(v) for k, v in self.ci95.items()},
             "td_meta_s": self.td_meta_s, "loop_delay_s": self.td_meta_s + self.td_s,
             "residual_rms": self.residual_rms, "chi2_dof": self.chi2_dof, "n_freq": self.n_freq,
             "band_rad_s": list(self.band_rad_s)}
        if self.K is not None:
            d.update(K=self.K, B=self.B)
        return d


def fit_loop(res: EtfeResult, ve: VirtualEnvironment, start: Plant, fit_ve: bool = False) -> LoopFit:
    """Fit m, b, td (and K, B with ``fit_ve``) to the measured Z (see module doc).

    ``start``: initial plant (e.g. identified from the record); ``ve``: the VE of
    the metadata, whose T, w0, kind and td are taken as they are.
    """
    if ve.kind == "none" and fit_ve:
        raise UserError("--fit-ve needs a VE in the metadata (ve=spring, damper or spring-damper)")
    w_max = FIT_W_MAX * math.pi / ve.T
    use = (~res.low_coherence) & (res.w >= W_MIN) & (res.w <= w_max) & (res.Z_err > 0)
    use &= np.isfinite(res.Z) & np.isfinite(res.Z_err)
    if use.sum() < MIN_POINTS:
        raise UserError(f"only {int(use.sum())} coherent frequencies between {W_MIN:g} and "
                        f"{w_max:.4g} rad/s: not enough to fit the loop (need {MIN_POINTS})")
    w, Z = res.w[use], res.Z[use]
    sigma = res.Z_err[use] / R95
    names = ["m", "b", "td_s"] + (["K", "B"] if fit_ve else [])
    scale = np.array([start.m, start.b if start.b > 0 else start.m, ve.T]
                     + ([max(ve.K, 1.0), max(ve.B, 1e-2)] if fit_ve else []))

    def model(p):
        th = p * scale
        v = ve.with_(K=th[3], B=th[4]) if fit_ve else ve
        return theory.z_sampled(Plant(th[0], th[1]), v, w, latency=th[2])

    def residual(p):
        r = (Z - model(p)) / sigma
        return np.concatenate([r.real, r.imag])

    lower = np.array([1e-6, 0.0, 0.0] + ([0.0, 0.0] if fit_ve else []))
    p0 = np.array([1.0, start.b / scale[1], 0.0] + ([ve.K / scale[3], ve.B / scale[4]] if fit_ve else []))
    grid = np.arange(0.0, TD_GRID_MAX + TD_GRID_STEP / 2, TD_GRID_STEP)
    p0[2] = grid[int(np.argmin([np.sum(residual(np.r_[p0[:2], td, p0[3:]]) ** 2) for td in grid]))]
    best = optimize.least_squares(residual, p0, bounds=(lower, np.inf), x_scale="jac", method="trf")
    theta = best.x * scale
    J = best.jac / scale  # d residual / d theta
    n_res, p = len(best.fun), len(theta)
    dof = max(n_res - p, 1)
    s2 = 2 * best.cost / dof
    r = best.fun[: len(w)] + 1j * best.fun[len(w):]
    rho = _lag1(r)
    inflate = (1 + rho) / (1 - rho) if rho > 0 else 1.0
    cov = s2 * inflate * np.linalg.pinv(J.T @ J)
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    t = stats.t.ppf(0.975, dof)
    ci = {k: (float(c - t * e), float(c + t * e)) for k, c, e in zip(names, theta, se)}
    Zm = model(best.x)
    return LoopFit(
        m=float(theta[0]), b=float(theta[1]), td_s=float(theta[2]), ci95=ci,
        K=float(theta[3]) if fit_ve else None, B=float(theta[4]) if fit_ve else None,
        td_meta_s=ve.td, residual_rms=float(np.sqrt(np.mean(np.abs((Z - Zm) / Z) ** 2))),
        chi2_dof=float(s2), n_freq=int(use.sum()), band_rad_s=(float(w[0]), float(w[-1])), Z_model=Zm)


def _lag1(r: np.ndarray) -> float:
    """Lag-one correlation of a complex residual sequence (real part of the normalised sum)."""
    r = r - r.mean()
    den = float(np.sum(np.abs(r) ** 2))
    return float(np.real(np.sum(r[1:] * np.conj(r[:-1]))) / den) if den > 0 else 0.0
