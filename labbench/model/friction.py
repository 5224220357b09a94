"""Coulomb friction in the closed loop, by statistical linearisation.

A device's Coulomb friction ``Fc sign(v)`` is no linear term, so the paper's loop
(``labbench.model.linear``) has no place for it. Under a random velocity it acts on
average like the damper that leaves the smallest mean-square error,

    b_eq = E[v Fc sign(v)] / E[v^2] = Fc E|v| / E[v^2]

(statistical linearisation: R. C. Booton, "Nonlinear control systems with random
inputs", IRE Trans. Circuit Theory 1(1), 1954; A. Gelb & W. E. Vander Velde,
*Multiple-Input Describing Functions and Nonlinear System Design*, McGraw-Hill 1968,
ch. 2, the random-input describing function). For a Gaussian velocity of standard
deviation sigma_v, E|v| = sqrt(2 / pi) sigma_v and

    b_eq = Fc sqrt(2 / pi) / sigma_v.

For a Gaussian excitation Bussgang's theorem makes that gain also the best linear
approximation (Pintelon & Schoukens, *System Identification: A Frequency Domain
Approach*, 2nd ed. 2012, sec. 3.4), which is what an ETFE converges to: the loop's
impedance with ``b + b_eq`` in place of ``b``, through the exact sampled model.

sigma_v depends on b_eq itself (more damping, less motion), so ``linearise`` solves the
two together under the run's own excitation (the self-consistent solution of the
random-input describing function, Gelb & Vander Velde sec. 2.5): the velocity the
linearised loop has on the recorded excitation force, ``velocity_response``, gives
sigma_v; b_eq sigma_v(b + b_eq) = Fc sqrt(2 / pi) rises monotonically in b_eq to the
excitation's rms force (a heavy damper moves as F / b_eq), so it has one root when
``Fc sqrt(2 / pi)`` is below that rms, and none when friction holds the handle (the
linearisation then does not apply: ``Linearised.holds`` False).

The velocity at the sample instants of the held plant per command, ``V / U``
(``labbench.model.linear.held_plant``: a row of ``(zI - Ad)^-1 G(z)``, fractional
device delays included), through the loop: ``V / F_exo = (V / U) / (1 + G P)`` with
``G P`` the loop gain of ``labbench.model.linear.loop_parts``. Where td is not whole
samples the paper's continuous model stands in: ``V / F_exo = 1 / Z``.

What it leaves out: sticking (when |u| < Fc at rest the handle holds, which no damper
does) and a velocity far from Gaussian; ``velocity_rms`` on the record beside the
prediction shows how well it holds (``labbench.analysis.friction``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from labbench.errors import UserError
from labbench.model import linear
from labbench.model.ve import Plant, VirtualEnvironment

SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)  # E|v| / sigma_v of a zero-mean Gaussian
B_EQ_MAX = 1e4  # N s/m, the largest damping a Plant takes (labbench.model.ve.RANGES)


def equivalent_damping(coulomb_n: float, v) -> float:
    """Booton's equivalent damping Fc E|v| / E[v^2] [N s/m] of the velocity samples ``v``
    (any distribution; module doc). 0 without friction; inf for a handle that never moved."""
    v = np.asarray(v, float)
    if coulomb_n == 0:
        return 0.0
    ms = float(np.mean(v**2))
    return math.inf if ms == 0 else float(coulomb_n * np.mean(np.abs(v)) / ms)


def gaussian_equivalent_damping(coulomb_n: float, sigma_v: float) -> float:
    """Fc sqrt(2 / pi) / sigma_v [N s/m]: ``equivalent_damping`` of a Gaussian velocity of
    standard deviation ``sigma_v`` [m/s] (module doc)."""
    if coulomb_n == 0:
        return 0.0
    return math.inf if sigma_v <= 0 else coulomb_n * SQRT_2_OVER_PI / sigma_v


def velocity_response(plant: Plant, ve: VirtualEnvironment, w, latency: float = 0.0) -> np.ndarray:
    """V / F_exo at ``w`` [rad/s], w > 0: the handle's velocity at the sample instants per
    exogenous force, through the exact sampled loop (module doc; the paper's eq. 2 where
    td is not whole samples); ``latency`` [s]: the device's own delay on the whole command."""
    w = np.asarray(w, float)
    if not linear.whole_samples(ve):
        return 1.0 / linear.z_paper(plant, ve, w, latency)
    P, V = linear.held_plant(plant, ve.T, w, latency)
    return V / (1 + linear.loop_parts(plant, ve, w, latency)[1] * P)


MAX_GROUPS = 1 << 14  # spectral groups a velocity sum evaluates the loop at (``_spectrum``)


def _spectrum(excitation, T: float) -> tuple[np.ndarray, np.ndarray, int]:
    """(w, P, n): the excitation's one-sided power |F_k|^2 (DC left out, a Nyquist bin
    counted once, the others twice: Parseval's weights), summed over groups of
    neighbouring bins at most ``MAX_GROUPS`` of them (w: each group's mean frequency), and
    the record's length n. The velocity response changes little across a group (0.2 rad/s
    at 1800 s of 1 kHz), so a long record costs what 16 s do."""
    f = np.asarray(excitation, float)
    if f.ndim != 1 or len(f) < 2 or not np.all(np.isfinite(f)):
        raise UserError("the excitation must be a finite force sequence of two samples or more")
    n = len(f)
    P = np.abs(np.fft.rfft(f)[1:]) ** 2 * 2.0
    if n % 2 == 0:
        P[-1] /= 2.0
    w = 2 * np.pi * np.fft.rfftfreq(n, T)[1:]
    size = -(-len(P) // MAX_GROUPS)
    if size > 1:
        edges = np.arange(0, len(P), size)
        P, w = np.add.reduceat(P, edges), np.add.reduceat(w, edges) / np.diff(np.append(edges, len(w)))
    return w, P, n


def _rms(H: np.ndarray, P: np.ndarray, n: int) -> float:
    """rms over the n samples of the response H to a force of power spectrum P (Parseval)."""
    return float(math.sqrt(np.sum(np.abs(H) ** 2 * P)) / n)


def velocity_rms(plant: Plant, ve: VirtualEnvironment, excitation, latency: float = 0.0) -> float:
    """rms [m/s] of the velocity the linear loop has on the force sequence ``excitation``
    (one sample per ``ve.T``; periodic extension: the edges of a long record weigh nothing)."""
    w, F, n = _spectrum(excitation, ve.T)
    return _rms(velocity_response(plant, ve, w, latency), F, n)


@dataclass(frozen=True)
class Linearised:
    """The loop with Coulomb friction ``coulomb_n`` [N] as the damper ``b_eq`` [N s/m] it
    acts as at the velocity it leaves, rms ``velocity_rms`` [m/s] (module doc); ``plant``:
    the device with ``b + b_eq``. ``holds`` False: no such damper exists (friction holds
    the handle: Fc sqrt(2/pi) is not below the excitation's rms force); b_eq is then inf
    and ``plant`` the linear one."""

    coulomb_n: float
    b_eq: float
    velocity_rms: float
    plant: Plant
    holds: bool = True

    def as_dict(self) -> dict:
        return {"coulomb_n": self.coulomb_n, "b_eq": self.b_eq if self.holds else None,
                "velocity_rms": self.velocity_rms, "holds": self.holds}


def linearise(plant: Plant, ve: VirtualEnvironment, coulomb_n: float, excitation,
              latency: float = 0.0) -> Linearised:
    """The self-consistent equivalent damping of Coulomb friction ``coulomb_n`` [N] in the
    loop of ``plant`` and ``ve`` driven by the force sequence ``excitation`` (module doc):
    b_eq = Fc sqrt(2 / pi) / sigma_v(b + b_eq), solved by Brent's method."""
    if not (coulomb_n >= 0 and math.isfinite(coulomb_n)):
        raise UserError(f"Coulomb friction must be a number >= 0 N, got {coulomb_n!r}")
    w, F, n = _spectrum(excitation, ve.T)
    if coulomb_n == 0:
        return Linearised(0.0, 0.0, _rms(velocity_response(plant, ve, w, latency), F, n), plant)

    def sigma(beq: float) -> float:
        return _rms(velocity_response(Plant(plant.m, plant.b + beq), ve, w, latency), F, n)

    target = coulomb_n * SQRT_2_OVER_PI
    hi = max(target / max(sigma(0.0), 1e-300), 1e-6)
    while hi * sigma(hi) < target:  # beq sigma(b + beq) rises to the force's rms (module doc)
        if hi >= B_EQ_MAX - plant.b:
            return Linearised(coulomb_n, math.inf, 0.0, plant, holds=False)
        hi = min(10.0 * hi, B_EQ_MAX - plant.b)
    beq = optimize.brentq(lambda x: x * sigma(x) - target, 0.0, hi, xtol=1e-9, rtol=1e-7)
    return Linearised(coulomb_n, float(beq), sigma(beq), Plant(plant.m, plant.b + beq))


def white_noise_velocity_rms(plant: Plant, ve: VirtualEnvironment, std_n: float,
                             band_rad_s: tuple[float, float] | None = None,
                             latency: float = 0.0, n: int = 1 << 16) -> float:
    """rms [m/s] of the velocity the linear loop has under white noise of standard
    deviation ``std_n`` [N], flat over ``band_rad_s`` (None: up to the Nyquist frequency):
    the expectation of ``velocity_rms`` for such a force, on a grid of ``n`` / 2 bins."""
    w = np.linspace(0.0, math.pi / ve.T, n // 2 + 1)[1:]
    lo, hi = band_rad_s if band_rad_s is not None else (0.0, math.pi / ve.T)
    inside = (w >= lo) & (w <= hi)
    if not inside.any():
        return 0.0
    # a flat spectrum of variance std^2 over the band: sigma_v^2 = std^2 mean |H|^2 there
    H = velocity_response(plant, ve, w[inside], latency)
    return float(std_n * math.sqrt(np.mean(np.abs(H) ** 2)))


def excitation_for(plant: Plant, ve: VirtualEnvironment, coulomb_n: float, b_eq_max: float,
                   band_rad_s: tuple[float, float] | None = None, latency: float = 0.0) -> float:
    """The white-noise standard deviation [N] at which Coulomb friction ``coulomb_n`` acts as
    no more than ``b_eq_max`` [N s/m] of damping (module doc): the loop with b + b_eq_max
    must move at sigma_v = Fc sqrt(2 / pi) / b_eq_max, and its velocity is proportional to
    the excitation."""
    if coulomb_n == 0:
        return 0.0
    if not b_eq_max > 0:
        raise UserError(f"the largest equivalent damping must be positive, got {b_eq_max!r}")
    per_newton = white_noise_velocity_rms(Plant(plant.m, plant.b + b_eq_max), ve, 1.0, band_rad_s, latency)
    return coulomb_n * SQRT_2_OVER_PI / b_eq_max / per_newton
