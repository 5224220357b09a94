"""Mass-damper plant at the handle, advanced exactly over one zero-order-hold step.

``m x'' + b x' = u`` with u constant over each step of length T. The linear
step is the exact discretisation (matrix exponential of the augmented system,
Franklin, Powell & Workman, Digital Control of Dynamic Systems, sec. 4.3), so a
simulation of the loop equals the exact sampled-data model of ``labbench.model.linear``.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from labbench.model.linear import zoh_matrices


class MassDamperPlant:
    """Linear plant state [x, v]; ``step(force)`` holds the force for one T."""

    def __init__(self, m: float, b: float, T: float, x0: float = 0.0, v0: float = 0.0):
        self.m, self.b, self.T = m, b, T
        self.Ad, self.Bd = zoh_matrices(m, b, T)
        self.state = np.array([x0, v0], dtype=float)

    @property
    def position(self) -> float:
        return float(self.state[0])

    @property
    def velocity(self) -> float:
        return float(self.state[1])

    def step(self, force: float) -> None:
        self.state = self.Ad @ self.state + self.Bd * force


class PrescribedMotion:
    """A handle moved by hand, not by the force: ``position = motion(k T)`` at step k
    (``step`` ignores the force); for boards that only stream their count."""

    def __init__(self, motion: Callable[[float], float], T: float):
        self.motion, self.T, self.k = motion, T, 0
        self.position = float(motion(0.0))

    def step(self, force: float) -> None:
        self.k += 1
        self.position = float(self.motion(self.k * self.T))
