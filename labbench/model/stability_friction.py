"""Stability of the sampled loop on a device with Coulomb friction: the boundary depends on
how far the handle swings.

The linear boundary (``labbench.model.linear.k_max``) is where the loop's least damped
oscillation neither grows nor decays: the energy the sampled VE feeds it each cycle (the
hold and the delays lag the spring: K (T/2 + td) of negative damping, to first order) equals
what the device's damping b takes out. Coulomb friction f_c takes out a fixed 4 f_c X per
cycle of an oscillation of amplitude X, whatever its speed, while a damper takes
pi b w X^2: to an oscillation of amplitude X at w rad/s friction is a damper of

    b_eq = 4 f_c / (pi w X)

(the describing function of a relay acting on the velocity w X: Gelb & Vander Velde,
*Multiple-Input Describing Functions and Nonlinear System Design*, 1968, ch. 2; the energy
per cycle is exact for a sinusoidal motion, the approximation is that the motion stays
one). ``equivalent_damping``.

So above the linear boundary there is an amplitude X* at which friction's damping just
covers the deficit: smaller oscillations decay, larger ones grow (an unstable limit cycle,
the region Diolaiti, Niemeyer, Barbagli & Salisbury, "Stability of haptic rendering:
discretization, quantization, time delay, and Coulomb effects", IEEE T-RO 22(2), 2006,
find by energy and describing-function arguments: a device can render stably, for small
motions, stiffnesses its linear model calls unstable). ``limit_cycle_amplitude``:

    X* = 4 f_c / (pi w (b* - b))

with b* the device damping at which the linear sampled loop of that VE would be marginally
stable (``damping_needed``) and w the frequency of its marginal oscillation
(``marginal_frequency``). Read the other way, for motions of amplitude X the boundary lies
at the K where b* - b = b_eq: ``friction_boundary``, the stiffness at which an oscillation
of amplitude X neither grows nor decays: what a stability probe whose steps start an
oscillation of amplitude X measures (``labbench.protocols.stability_probe``).

The encoder step: for amplitudes of many counts (X >> Delta) it changes the loop's gain by
a share of order Delta / X and is left out here. At amplitudes of a few counts it is what
decides: Abbott & Okamura ("Effects of position quantization and sampling rate on
virtual-wall passivity", IEEE T-RO 21(5), 2005) show friction absorbs the energy the
quantised spring gives back only while K <= 2 f_c / Delta
(``labbench.model.passivity.quantisation_bound``); stiffer walls buzz in small limit cycles
however stable the large motions are. Both bounds are reported side by side.

Checked against the simulator (``tests/test_stability_friction.py``, the probe on a plant
with Coulomb friction and a quantised encoder: the measured boundary against
``friction_boundary`` at the amplitude the probe's steps had).
"""
from __future__ import annotations

import math

import numpy as np

from labbench.model import linear
from labbench.model.ve import RANGES, Plant, VirtualEnvironment

B_TOL = 1e-4  # relative tolerance of damping_needed
K_TOL = 1e-3  # relative tolerance of friction_boundary


def equivalent_damping(coulomb_n: float, w_rad_s: float, amplitude_m: float) -> float:
    """Damping [N s/m] Coulomb friction ``coulomb_n`` acts as on a sinusoidal motion of
    ``amplitude_m`` at ``w_rad_s``: 4 f_c / (pi w X) (module doc); inf at zero amplitude."""
    if coulomb_n <= 0:
        return 0.0
    if amplitude_m <= 0 or w_rad_s <= 0:
        return math.inf
    return 4.0 * coulomb_n / (math.pi * w_rad_s * amplitude_m)


def damping_needed(plant: Plant, ve: VirtualEnvironment, latency: float = 0.0) -> float | None:
    """Smallest device damping b* [N s/m] with which the exact sampled loop of this VE is
    stable (the plant's mass kept); ``plant.b`` or less when it already is (then the
    plant's b is returned). None when no damping up to ``labbench.model.ve.RANGES``'s largest
    stabilises it."""
    def stable(b: float) -> bool:
        return linear.stability(Plant(plant.m, b), ve, latency).stable

    lo = plant.b
    if stable(lo):
        return lo
    top = RANGES["b"][1]
    hi = max(2.0 * lo, 1e-3)
    while not stable(hi):
        if hi >= top:
            return None
        lo, hi = hi, min(2.0 * hi, top)
    while hi - lo > B_TOL * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if stable(mid) else (mid, hi)
    return hi


def marginal_frequency(plant: Plant, ve: VirtualEnvironment, latency: float = 0.0) -> float:
    """Angular frequency [rad/s] of the loop's least stable pole (|angle z| / T): the
    oscillation that grows, or decays slowest."""
    lam = np.linalg.eigvals(linear.closed_loop(plant, ve, latency).A)
    z = lam[np.argmax(np.abs(lam))]
    return abs(float(np.angle(z))) / ve.T


def _deficit(plant: Plant, ve: VirtualEnvironment, latency: float) -> tuple[float, float] | None:
    """(b* - b, marginal frequency at b*) of this VE; None when no damping stabilises it."""
    need = damping_needed(plant, ve, latency)
    if need is None:
        return None
    return need - plant.b, marginal_frequency(Plant(plant.m, need), ve, latency)


def limit_cycle_amplitude(plant: Plant, ve: VirtualEnvironment, coulomb_n: float,
                          latency: float = 0.0) -> float:
    """X* [m]: oscillations smaller than this decay, larger ones grow (module doc).
    inf where the linear loop is stable (every amplitude decays); 0 without friction on a
    linearly unstable loop, or where no damping would stabilise it."""
    gap = _deficit(plant, ve, latency)
    if gap is None or coulomb_n <= 0:
        return 0.0 if gap is None or gap[0] > 0 else math.inf
    deficit, w = gap
    if deficit <= 0:
        return math.inf
    return 4.0 * coulomb_n / (math.pi * w * deficit)


def friction_boundary(plant: Plant, ve: VirtualEnvironment, coulomb_n: float, amplitude,
                      latency: float = 0.0, k_cap: float | None = None) -> float | None:
    """The stiffness at which an oscillation of ``amplitude`` neither grows nor decays on a
    device with Coulomb friction ``coulomb_n`` (module doc): K where b* - b equals the
    friction's equivalent damping at the marginal frequency. ``amplitude``: metres, or a
    function of K giving them (a probe's pulse swings less on a stiffer spring).

    The linear ``k_max`` without friction; ``math.inf`` when the friction still covers the
    deficit at ``k_cap`` (default the largest K of ``labbench.model.ve.RANGES``): the boundary
    lies beyond it. None for a VE without a spring.
    """
    k_lin = linear.k_max(plant, ve, latency=latency)
    if k_lin is None or coulomb_n <= 0 or not math.isfinite(k_lin) or k_lin <= 0:
        return k_lin
    size = amplitude if callable(amplitude) else (lambda _K: amplitude)

    def holds(K: float) -> bool:
        gap = _deficit(plant, ve.with_(K=K), latency)
        if gap is None:
            return False
        deficit, w = gap
        return deficit <= equivalent_damping(coulomb_n, w, size(K))

    top = RANGES["K"][1] if k_cap is None else k_cap
    lo = k_lin
    if holds(top):
        return math.inf
    hi = min(2.0 * lo, top)
    while holds(hi):
        lo, hi = hi, min(2.0 * hi, top)
    while hi - lo > K_TOL * lo:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if holds(mid) else (lo, mid)
    return 0.5 * (lo + hi)


def planned_boundary(plant: Plant, ve: VirtualEnvironment, coulomb_n: float, plan,
                     friction_cap: float, latency: float = 0.0) -> float | None:
    """The friction-aware boundary a stability probe plans for: ``friction_boundary`` at the
    swing its pulses start at each K (``plan``: a ``labbench.model.pulse.PulsePlan``), with
    ``math.inf`` beyond ``friction_cap`` x the linear boundary (the probe's safety cap)."""
    k_lin = linear.k_max(plant, ve, latency=latency)
    if k_lin is None or not 0 < k_lin < math.inf:
        return k_lin
    return friction_boundary(plant, ve, coulomb_n, lambda K: plan.swing(plant.m, K, ve.B),
                             latency, k_cap=friction_cap * k_lin)
