"""Plain parameter records shared by theory, the loop, protocols and analysis.

Signs and units follow docs/conventions.md: SI at the handle, VE force opposes
the exogenous force (plant ``m x'' + b x' = f_exo - f_ve``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

from labbench.errors import UserError

VE_KINDS = ("spring", "damper", "spring-damper", "none")


@dataclass(frozen=True)
class Plant:
    """Device mass ``m`` [kg] and viscous damping ``b`` [N s/m] at the handle."""

    m: float
    b: float

    def __post_init__(self):
        _finite("m", self.m)
        _finite("b", self.b)
        if self.m <= 0:
            raise UserError(f"mass m must be positive, got {self.m} kg")
        if self.b < 0:
            raise UserError(f"damping b must be >= 0, got {self.b} N s/m")
        _within("mass m", self.m, RANGES["m"])
        _within("damping b", self.b, RANGES["b"])


@dataclass(frozen=True)
class VirtualEnvironment:
    """Virtual spring / damper / spring-damper rendered from sampled position.

    ``kind``: one of VE_KINDS ("none" = open loop, no VE force).
    ``K`` [N/m], ``B`` [N s/m]; ``w0`` [rad/s] velocity low-pass cut-off
    (``math.inf`` = no filter); ``T`` [s] sample time; ``td`` [s] external delay.
    Kinds that do not use K or B force them to zero, so ``K``/``B`` are always
    the gains actually applied.
    """

    kind: str = "none"
    K: float = 0.0
    B: float = 0.0
    w0: float = math.inf
    T: float = 0.001
    td: float = 0.0

    def __post_init__(self):
        if self.kind not in VE_KINDS:
            raise UserError(f"unknown VE {self.kind!r}; choose one of {', '.join(VE_KINDS)}")
        for name in ("K", "B", "T", "td"):
            _finite(name, getattr(self, name))
        if not (self.w0 > 0):
            raise UserError(f"w0 must be positive (or absent for no filter), got {self.w0} rad/s")
        if self.T <= 0:
            raise UserError(f"sample time T must be positive, got {self.T} s")
        if self.td < 0:
            raise UserError(f"delay td must be >= 0, got {self.td} s")
        if self.K < 0 or self.B < 0:
            raise UserError("virtual gains K and B must be >= 0")
        for name in ("K", "B", "T", "td"):
            _within(name, getattr(self, name), RANGES[name])
        if math.isfinite(self.w0):
            _within("w0", self.w0, RANGES["w0"])
        if round(self.td / self.T, 6) > MAX_DELAY_SAMPLES:
            raise UserError(f"td = {self.td:g} s is {self.td / self.T:.3g} samples of T = {self.T:g} s;"
                            f" at most {MAX_DELAY_SAMPLES} (the sampled model grows with the delay)")
        if self.kind in ("damper", "none"):
            object.__setattr__(self, "K", 0.0)
        if self.kind in ("spring", "none"):
            object.__setattr__(self, "B", 0.0)

    @property
    def delay(self) -> float:
        """Total loop delay T/2 + td [s] of the paper's continuous model (eq. 2)."""
        return self.T / 2 + self.td

    @property
    def delay_samples(self) -> int:
        """td as a whole number of samples; a clear error otherwise."""
        n = round(self.td / self.T)
        if abs(n * self.T - self.td) > 1e-9 * max(self.T, self.td):
            raise UserError(
                f"td = {self.td} s is not a whole number of samples of T = {self.T} s"
            )
        return n

    @property
    def filter_pole(self) -> float:
        """a = exp(-w0 T) of the velocity low-pass (0 without filter)."""
        return 0.0 if math.isinf(self.w0) else math.exp(-self.w0 * self.T)

    def with_(self, **changes) -> "VirtualEnvironment":
        return replace(self, **changes)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["w0"] = None if math.isinf(self.w0) else self.w0
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "VirtualEnvironment":
        d = dict(d)
        if d.get("w0") is None:
            d["w0"] = math.inf
        return cls(**d)


# Physical range of each parameter (lowest, highest, unit): beyond them no haptic device or
# VE exists, and the matrices of the theory overflow or become singular (1e308, 1e-320).
RANGES = {
    "m": (1e-6, 1e3, "kg"), "b": (0.0, 1e4, "N s/m"),
    "K": (0.0, 1e7, "N/m"), "B": (0.0, 1e5, "N s/m"), "w0": (1e-3, 1e7, "rad/s"),
    "T": (1e-9, 1.0, "s"), "td": (0.0, 1.0, "s"),
}
MAX_DELAY_SAMPLES = 250  # td / T: the exact sampled model has one state per delay sample


def _within(name: str, value: float, bounds: tuple) -> None:
    lo, hi, unit = bounds
    if not lo <= value <= hi:
        raise UserError(f"{name} must be within [{lo:g}, {hi:g}] {unit}, got {value:g}")


def _finite(name: str, value: float) -> None:
    try:
        ok = not isinstance(value, bool) and math.isfinite(float(value))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise UserError(f"{name} must be a finite number, got {value!r}")


# The paper's Phantom Premium 1.5 fit (Table 1, l2): the simulator's plant and the
# nominal plant of a rig file that names none.
DEFAULT_PLANT = Plant(0.094, 0.10)
