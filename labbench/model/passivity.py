"""Passive and stable: the bounds a Z-width is read against.

A haptic display can be stable without being passive (Diolaiti, Niemeyer, Barbagli &
Salisbury, "Stability of haptic rendering: discretization, quantization, time delay, and
Coulomb effects", IEEE TRO 22(2), 2006): stability asks whether the loop with the
handle left alone decays; passivity asks whether it can ever give a hand that holds it
more energy than it took. The stable bound is ``labbench.model.linear.k_max`` (exact) and
``k_max_approx`` (b + B > K (T/2 + td), the paper's form of Diolaiti's linear
condition); this module holds the passive ones.

**Sampled-data passivity** (Colgate & Schenkel, "Passivity of a class of sampled-data
systems: application to haptic interfaces", J. Robotic Systems 14(1), 1997). The hand
feels the continuous mass-damper m, b and a force held over each sample, computed by a
discrete VE ``H(z)`` from the sampled position. Over one step the held force f_k does
work -f_k (x_{k+1} - x_k) on the hand's side; for motion at frequency w, summing that
work and the energy the damper dissipates, b integral v^2, over a period and asking that
it never be negative for any motion gives their condition

    b >= (T / 2) Re[(1 - e^{-jwT}) H(e^{jwT})] / (1 - cos wT)     for 0 < w <= pi / T.

Two cases fix its scale. A spring H = K: Re[(1 - z^-1) K] = K (1 - cos wT), so the
right side is K T / 2 at every w: b >= K T / 2 (the zero-order hold lags the spring by
half a sample; its leak K T / 2 v^2 must be paid by the damping). A backward-difference
damper H = B (1 - z^-1) / T: Re[(1 - z^-1)^2] = -2 cos wT (1 - cos wT), so the right
side is -B cos wT, largest (|B|) at the Nyquist frequency, where the difference turns
the damper into a negative one. Together: **b > K T / 2 + |B|**, Colgate & Schenkel's
line, ``colgate_line``. A damper helps stability (the paper's b + B) and hurts
passivity (b - |B|): the gap between the two envelopes of a Z-width.

``passive_k_max`` evaluates the condition itself for the VE the loop renders: the
velocity low-pass of ``labbench.model.ve`` (``H = K + B (1 - a)(1 - z^-1) / (T (1 - a z^-1))``),
the VE's td as z^-n, and the device's delay ``latency`` as z^-d ((1 - alpha) + alpha z^-1)
for latency = (d + alpha) T: the force over the step averaged, exact for the work when
the velocity is constant over the step (the fractional part is an approximation; whole
samples are exact). At w -> 0 a whole delay d gives b >= K T (2 d + 1) / 2, i.e.
b > K (T / 2 + d T): the delay's loss, as in the stable bound's approximation.

**Quantisation and Coulomb friction** (Abbott & Okamura, "Effects of position
quantization and sampling rate on virtual-wall passivity", IEEE TRO 21(5), 2005). With
an encoder of resolution Delta the spring sees the position up to one count late: moving
across one count the spring's force lags by up to K Delta, an energy of up to
K Delta^2 / 2 given back per count crossed, while Coulomb friction f_c takes f_c Delta
per count. At slow motion (where the viscous terms vanish) the wall stays passive only
if f_c Delta >= K Delta^2 / 2: **K <= 2 f_c / Delta**, ``quantisation_bound``. Their
result needs both bounds (two modes, each able to be active): K <= min(2 b / T, 2 f_c /
Delta). A frictionless handle with a quantised encoder (the simulators' truth) has no
passive stiffness at all by this bound, however stable it is.
"""
from __future__ import annotations

import math

import numpy as np

from labbench.model.linear import latency_split
from labbench.model.ve import Plant, VirtualEnvironment

N_GRID = 20000  # frequencies from pi / (T N_GRID) to pi / T


def colgate_line(b: float, B: float, T: float) -> float:
    """Largest K with b > K T / 2 + |B| (Colgate & Schenkel 1997; module doc); 0 when the
    virtual damping alone uses up the device's (|B| >= b)."""
    return max(2.0 * (b - abs(B)) / T, 0.0)


def passive_k_max(plant: Plant, ve: VirtualEnvironment, latency: float = 0.0) -> float:
    """Largest K for which the sampled-data condition of Colgate & Schenkel holds at every
    frequency up to Nyquist for this VE's B, filter and td, with the device's ``latency``
    (module doc); 0.0 when no K > 0 does.

    The right side is affine in K, ``K g(w) + h(w)``, so K <= (b - h) / g wherever g > 0,
    and where g <= 0 the damper part alone must already satisfy h <= b.
    """
    T = ve.T
    w = np.linspace(math.pi / (T * N_GRID), math.pi / T, N_GRID)
    zinv = np.exp(-1j * w * T)
    d, alpha = latency_split(latency, T)
    delay = zinv ** (ve.delay_samples + d) * ((1 - alpha) + alpha * zinv)
    a = ve.filter_pole
    velocity = (1 - a) * (1 - zinv) / (T * (1 - a * zinv))  # 0 when B = 0 is rendered
    scale = (T / 2) / (1 - np.cos(w * T))
    g = scale * np.real((1 - zinv) * delay)
    h = scale * np.real((1 - zinv) * delay * ve.B * velocity)
    if np.any((g <= 0) & (h > plant.b)):
        return 0.0
    pos = g > 0
    return max(float(np.min((plant.b - h[pos]) / g[pos])), 0.0)


def quantisation_bound(coulomb_n: float | None, metres_per_count: float) -> float | None:
    """Abbott & Okamura's K <= 2 f_c / Delta (module doc); None when f_c is not known."""
    if coulomb_n is None or not metres_per_count > 0:
        return None
    return 2.0 * max(float(coulomb_n), 0.0) / metres_per_count
