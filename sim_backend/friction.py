"""Coulomb friction and cogging inside one zero-order-hold step of a mass-damper.

``m x'' + b x' = u - Fc sign(x') - F_cog(x)`` with u held over a stretch of the step,
and sticking (x' = 0) while |u - F_cog(x)| <= Fc.

Friction alone (``held_step``): between velocity reversals the friction force is a
constant, so each piece is the exact linear solution; in the stretch in which the
velocity reaches zero the time of rest is solved analytically and the handle then
sticks or slides off in the direction of the force (Karnopp-style stick/slip, solved
rather than approximated with a velocity dead band). Under a constant force the
velocity reverses at most once: after a reversal it has the sign of the net force and
tends monotonically to its terminal value, so one reversal per held stretch is all
there is to find. A step whose force changes within it (the device's fractional delay
holds the previous command first) is two such stretches, each exact.

Cogging (``Cogging``): a motor's detent force, periodic in position, ``F_cog(x) = A
sin(2 pi x / p)`` (stable detents at x = n p). It depends on where the handle is, so no
closed form exists; each stretch is cut into substeps over which the cogging force is
held at its value at the substep's predicted midpoint, and each substep is the exact
friction step above with that force added (the exponential midpoint rule: exact for the
linear part and the friction, second order in the substep for the cogging,
Hochbruck & Ostermann, "Exponential integrators", Acta Numerica 19, 2010). The substeps
are short enough that the handle's phase in the cogging period, and the cogging
spring's own oscillation, advance at most ``Cogging.PHASE_STEP`` radians in one.
"""
from __future__ import annotations

import math


def free_motion(v0: float, force: float, t: float, m: float, b: float) -> tuple[float, float]:
    """Displacement and end velocity after ``t`` seconds under a constant ``force``.

    Solution of ``m v' + b v = force`` (b = 0 reduces to constant acceleration).
    """
    if b > 0.0:
        beta = b / m
        v_inf = force / b
        decay = -math.expm1(-beta * t)  # 1 - exp(-beta t), accurate for small t
        return v_inf * t + (v0 - v_inf) * decay / beta, v_inf + (v0 - v_inf) * (1.0 - decay)
    return v0 * t + 0.5 * force / m * t * t, v0 + force / m * t


def time_to_rest(v0: float, force: float, m: float, b: float) -> float:
    """Time at which the velocity under ``force`` (opposing v0) reaches zero."""
    if b > 0.0:
        return math.log1p(-v0 * b / force) * m / b
    return -v0 * m / force


def reversing_step(x0: float, v0: float, u: float, fc: float, T: float, m: float, b: float
                   ) -> tuple[float, float]:
    """State after a stretch of length T in which the velocity v0 != 0 reaches zero.

    Slides with friction opposing v0 until the velocity is zero, then either sticks
    (|u| <= fc) or slides off in the direction of u for the rest of the stretch.
    The caller has established that the velocity does reach zero within T.
    """
    f1 = u - fc if v0 > 0.0 else u + fc
    t_rest = min(time_to_rest(v0, f1, m, b), T)
    dx, _ = free_motion(v0, f1, t_rest, m, b)
    x = x0 + dx
    if abs(u) <= fc:
        return x, 0.0
    f2 = u - fc if u > 0.0 else u + fc
    dx, v = free_motion(0.0, f2, T - t_rest, m, b)
    return x + dx, v


def held_step(x: float, v: float, u: float, fc: float, h: float, m: float, b: float
              ) -> tuple[float, float]:
    """State after ``h`` seconds under the constant force ``u`` with Coulomb friction ``fc``
    (module doc): stuck, sliding on, or reversing once within the stretch."""
    if v == 0.0 and -fc <= u <= fc:
        return x, 0.0
    ue = u - fc if v > 0.0 or (v == 0.0 and u > 0.0) else u + fc
    dx, vn = free_motion(v, ue, h, m, b)
    if (v > 0.0 and vn <= 0.0) or (v < 0.0 and vn >= 0.0):
        return reversing_step(x, v, u, fc, h, m, b)
    return x + dx, vn


class Cogging:
    """The detent force ``A sin(2 pi x / p)`` the plant feels against its motion
    (``amplitude_n`` A [N], ``period_m`` p [m] at the handle) and the substeps a stretch
    needs (module doc)."""

    PHASE_STEP = 0.05  # rad: the most the cogging phase or its own oscillation turns per substep
    MAX_SUBSTEPS = 1000

    def __init__(self, amplitude_n: float, period_m: float, m: float):
        self.amplitude, self.period = amplitude_n, period_m
        self.k = 2.0 * math.pi / period_m  # rad per metre
        # the detent's small-motion stiffness A k and its natural frequency on the mass
        self.w_detent = math.sqrt(amplitude_n * self.k / m)
        self.m = m

    def force(self, x: float) -> float:
        return self.amplitude * math.sin(self.k * x)

    def substeps(self, v: float, h: float, push_n: float) -> int:
        """Substeps for a stretch of ``h`` s starting at velocity ``v`` under forces of at
        most ``push_n`` N besides the detent's: the speed it can reach within the stretch
        bounds the phase it sweeps."""
        speed = abs(v) + (push_n + self.amplitude) * h / self.m
        turn = h * max(self.k * speed, self.w_detent)
        return min(max(math.ceil(turn / self.PHASE_STEP), 1), self.MAX_SUBSTEPS)


def cogged_step(x: float, v: float, u: float, fc: float, h: float, m: float, b: float,
                cogging: Cogging) -> tuple[float, float]:
    """State after ``h`` seconds under the constant force ``u``, Coulomb friction ``fc``
    and ``cogging``: substeps with the detent force held at each one's predicted
    midpoint (module doc). A handle at rest stays so while |u - F_cog(x)| <= fc, exactly."""
    n = cogging.substeps(v, h, abs(u) + fc)
    dt = h / n
    for _ in range(n):
        f = u - cogging.force(x + 0.5 * dt * v)
        x, v = held_step(x, v, f, fc, dt, m, b)
    return x, v
