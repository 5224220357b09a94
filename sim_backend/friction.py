"""Coulomb friction inside one zero-order-hold step of a mass-damper.

``m x'' + b x' = u - Fc sign(x')`` with u held over the step, and sticking
(x' = 0) while |u| <= Fc. Between velocity reversals the friction force is a
constant, so each piece is the exact linear solution; this module handles the
step in which the velocity reaches zero (Karnopp-style stick/slip, solved
analytically rather than with a velocity dead band).
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
    """State after one step of length T in which the velocity v0 != 0 reaches zero.

    Slides with friction opposing v0 until the velocity is zero, then either sticks
    (|u| <= fc) or slides off in the direction of u for the rest of the step.
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
