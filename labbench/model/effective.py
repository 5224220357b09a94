"""Effective impedances of a closed-loop impedance Z = F/V (paper sec. 2.2, Figure 2).

Signs follow docs/conventions.md (Z = F/V, s = jw):
ED = Re Z, ES = -w Im Z, EM = Im Z / w; with theta the phase of Z unwrapped
from the lowest frequency, EJF = -Re Z / w^2 where theta is in [90, 270] deg
and EIF = -w^2 Re Z where theta is in [-270, -90] deg.
ES is the physically meaningful reading where Im Z < 0, EM where Im Z > 0;
both are returned signed at every frequency, with masks saying where each applies.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EffectiveImpedances:
    w: np.ndarray  # rad/s
    ES: np.ndarray  # N/m
    ED: np.ndarray  # N s/m
    EM: np.ndarray  # kg
    EJF: np.ndarray  # N s^2/m (zero outside its phase range)
    EIF: np.ndarray  # N/(m s) (zero outside its phase range)
    theta_deg: np.ndarray  # unwrapped phase of Z

    @property
    def stiffness_region(self) -> np.ndarray:
        return self.ES > 0

    @property
    def mass_region(self) -> np.ndarray:
        return self.EM > 0


def effective_impedances(w, Z) -> EffectiveImpedances:
    """Decompose Z(jw) into effective stiffness, damping, mass, jerk and integral feedback."""
    w = np.asarray(w, dtype=float)
    Z = np.asarray(Z, dtype=complex)
    theta = np.degrees(np.unwrap(np.angle(Z)))
    re, im = Z.real, Z.imag
    jerk = (theta >= 90) & (theta <= 270)
    integral = (theta >= -270) & (theta <= -90)
    return EffectiveImpedances(
        w=w,
        ES=-w * im,
        ED=re,
        EM=im / w,
        EJF=np.where(jerk, -re / w**2, 0.0),
        EIF=np.where(integral, -(w**2) * re, 0.0),
        theta_deg=theta,
    )


def measured_ws_star(w, ES) -> float | None:
    """Stiffness bandwidth read off a curve: first w where ES falls through zero.

    Linear interpolation between the bracketing points; None when ES never
    goes from positive to non-positive on the grid.
    """
    w = np.asarray(w, float)
    ES = np.asarray(ES, float)
    idx = np.flatnonzero((ES[:-1] > 0) & (ES[1:] <= 0))
    if idx.size == 0:
        return None
    i = idx[0]
    return float(w[i] + (w[i + 1] - w[i]) * ES[i] / (ES[i] - ES[i + 1]))


def measured_wb_star(w, ED, b: float, n_low: int = 3, reference: float | None = None) -> float | None:
    """Damping bandwidth read off a curve: first w where ED has fallen half-way
    from its low-frequency value to ``b``: ``reference`` (a measurement's rendered
    ED(0), ``labbench.model.predictions.measured``), else the median of the ``n_low`` lowest points
    (a curve without noise or leakage: the theory's).

    None when the low-frequency ED is not above b (no virtual damping to lose)
    or it never falls that far on the grid.
    """
    w = np.asarray(w, float)
    ED = np.asarray(ED, float)
    ok = np.isfinite(ED)
    w, ED = w[ok], ED[ok]
    if ED.size < n_low + 1:
        return None
    ed_low = float(np.median(ED[:n_low])) if reference is None else reference
    if ed_low <= b:
        return None
    half = b + 0.5 * (ed_low - b)
    idx = np.flatnonzero((ED[:-1] > half) & (ED[1:] <= half))
    if idx.size == 0:
        return None
    i = idx[0]
    return float(w[i] + (w[i + 1] - w[i]) * (ED[i] - half) / (ED[i] - ED[i + 1]))


def focus_limits(values, w, band: tuple[float, float], pad: float = 0.25) -> tuple[float, float] | None:
    """Y limits that show ``values`` (ED, say) readably over ``band`` [rad/s] of ``w``: from
    0 (or below it, when the values are) to their extreme there, ``pad`` beyond. A damping
    of 1.1 N s/m rendered below 40 rad/s must not share its axis with a roll-off to -50 at
    Nyquist (issue 30): what falls outside leaves the axes. None when no finite value lies in
    the band."""
    v = np.asarray(values, float)
    w = np.asarray(w, float)
    sel = (w >= band[0]) & (w <= band[1]) & np.isfinite(v)
    if not sel.any():
        return None
    lo, hi = min(0.0, float(v[sel].min())), max(0.0, float(v[sel].max()))
    span = hi - lo or max(abs(hi), 1.0)
    return lo - (pad * span if lo < 0 else 0.0), hi + pad * span
