"""The half-sine force pulse that starts each step of the stability probe, and the swing it
starts: sized to a share of the rig's tightest limit, so the free response is large against
the encoder step and small against the limits.

A half-sine of peak P and length tau gives the impulse I = 2 P tau / pi; on the free
mass-spring m x'' = -K x (damping and the sampling aside) it starts an oscillation of
velocity amplitude I / m and position amplitude I / sqrt(K m), whose VE force K x + B v has
amplitude (I / m) sqrt(K m + B^2) (x and v in quadrature). A pulse not short against the
period 2 pi sqrt(m / K) gives less: its spectrum at w = sqrt(K / m) relative to its area,
cos(w tau / 2) / (1 - (w tau / pi)^2) (the Fourier transform of a half-sine; any table of
pulse spectra).

``PulsePlan`` holds what the swing follows from (the probe's ``swing`` share, ``pulse_s``, a
fixed ``pulse_n`` if given, the rig's limits), so the swing, and the friction-aware boundary
it sets (``labbench.model.stability_friction.planned_boundary``), can be computed again for
any K and B from a campaign's table (``labbench.campaign.figures``) as the probe plans it.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class PulsePlan:
    """``share`` of the tightest limit the free response uses; the pulse's length
    ``pulse_s`` [s]; its peak ``pulse_n`` [N] when fixed (None: sized by ``share``); the
    rig's force limit [N], the nearer edge of its position window [m] and its velocity limit
    [m/s]."""

    share: float
    pulse_s: float
    force_n: float
    position_m: float
    velocity_m_s: float
    pulse_n: float | None = None

    def peak(self, m: float, K: float, B: float) -> float:
        """Peak [N] of the pulse: ``pulse_n``, else the one whose free response spends
        ``share`` of the tightest limit (module doc), held below ``share`` x the force limit."""
        if self.pulse_n is not None:
            return self.pulse_n
        km = K * m
        impulse = self.share * min(self.position_m * math.sqrt(km), self.velocity_m_s * m,
                                   self.force_n * m / math.sqrt(km + B**2))
        return min(impulse * math.pi / (2 * self.pulse_s), self.share * self.force_n)

    def swing(self, m: float, K: float, B: float) -> float:
        """Position amplitude [m] the pulse starts on the mass-spring m, K: the impulse's
        I / sqrt(K m) times the half-sine's spectrum at sqrt(K / m) relative to its area
        (module doc). Damping, friction and sampling are left out: a plan, not a
        measurement."""
        tau = self.pulse_s
        w = math.sqrt(K / m)
        r = w * tau / math.pi
        shape = math.pi / 4 if abs(r - 1) < 1e-9 else math.cos(w * tau / 2) / (1 - r * r)
        impulse = 2 * self.peak(m, K, B) * tau / math.pi
        return abs(impulse * shape) / math.sqrt(K * m)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> PulsePlan:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})
