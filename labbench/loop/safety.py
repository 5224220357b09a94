"""Safety envelope of the haptic loop: its settings, flag bits and trip reasons.

The arithmetic of the envelope runs inline in ``labbench.loop.chain.HapticLoop.step``
(one call per sample must stay cheap); this module holds what is configured and
what is reported. Settings come from the rig: ``force_limit_n``,
``position_limits_m`` and ``velocity_limit_m_s`` from ``[rig]``, the rest from an
optional ``[safety]`` table (see docs/loop.md).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from labbench.errors import UserError, unknown_name

# Bits of the page channel "flags" (one int per sample; 0 = nothing happened).
CLAMP = 1  # force clamp engaged (|command| held at force_limit_n)
RATE = 2  # force-rate limit engaged
GATED = 4  # enable gate: device not enabled yet, command held at zero
FADE = 8  # energy observer over its limit: force fading to zero
TRIPPED = 16  # a trip zeroed the force (position, velocity, energy, watchdog, stop)
SEQ_GAP = 32  # the device skipped sequence numbers before this sample
DEVICE = 64  # the device reported nonzero health flags with this sample
OVERRUN = 128  # the loop period before this sample exceeded 1.5 T (paced devices)

FLAG_NAMES = {
    CLAMP: "clamp", RATE: "rate", GATED: "gated", FADE: "fade", TRIPPED: "tripped",
    SEQ_GAP: "seq_gap", DEVICE: "device", OVERRUN: "overrun",
}


def flag_names(flags: int) -> list[str]:
    """Names of the bits set in one ``flags`` value."""
    return [name for bit, name in FLAG_NAMES.items() if flags & bit]


@dataclass(frozen=True)
class SafetyConfig:
    """Limits of the safety envelope (SI at the handle).

    ``force_limit_n``: clamp on |command|. ``force_rate_limit_n_per_s``: largest
    change of command per second. ``velocity_limit_m_s``: trip when the velocity
    estimate exceeds it. ``position_limits_m``: (low, high) window; outside it trips.
    ``energy_limit_j``: trip (fade to zero over ``energy_fade_s``) when the energy
    the VE has generated exceeds it (passivity observer, see ``labbench.loop.chain``).
    ``nominal_damping_ns_m``: device damping credited as dissipation by that
    observer (0 = strict). ``watchdog_s``: zero force when no sample arrives within
    it, or (paced devices) when one loop period exceeds it.
    ``enable_force_threshold_n``: the device is enabled only at a sample where
    the command, and every later command already in the VE delay line (up to the
    undelayed VE force plus excitation), is at most this large.
    """

    force_limit_n: float = 5.0
    force_rate_limit_n_per_s: float = 10000.0
    velocity_limit_m_s: float = 2.0
    position_limits_m: tuple = (-0.1, 0.1)
    energy_limit_j: float = 0.05
    energy_fade_s: float = 0.05
    nominal_damping_ns_m: float = 0.0
    watchdog_s: float = 0.05
    enable_force_threshold_n: float = 0.2

    def __post_init__(self):
        for f in fields(self):
            if f.name == "position_limits_m":
                continue
            v = getattr(self, f.name)
            if not _is_number(v) or not math.isfinite(v):
                raise UserError(f"safety {f.name} must be a finite number, got {v!r}")
            minimum_ok = v >= 0 if f.name in _NON_NEGATIVE else v > 0
            hi, unit = _MAX[f.name]
            if not minimum_ok or v > hi:
                low = "[0" if f.name in _NON_NEGATIVE else "(0"
                raise UserError(f"safety {f.name} must be in {low}, {hi:g}] {unit}, got {v!r}")
            object.__setattr__(self, f.name, float(v))
        lim = self.position_limits_m
        if (not isinstance(lim, (list, tuple)) or len(lim) != 2
                or not all(_is_number(x) and abs(x) <= _MAX_POSITION_M for x in lim)
                or not lim[0] < lim[1]):
            raise UserError(f"safety position_limits_m must be (low, high) with low < high, each "
                            f"within +-{_MAX_POSITION_M:g} m, got {lim!r}")
        object.__setattr__(self, "position_limits_m", (float(lim[0]), float(lim[1])))

    @classmethod
    def from_rig(cls, rig, **overrides) -> SafetyConfig:
        """Limits of ``rig`` ([rig] fields plus its optional [safety] table), then ``overrides``."""
        settings = {
            "force_limit_n": rig.force_limit_n,
            "position_limits_m": tuple(rig.position_limits_m),
            "velocity_limit_m_s": rig.velocity_limit_m_s,
            "nominal_damping_ns_m": getattr(rig, "nominal_damping_ns_m", 0.0),
        }
        table = rig.section("safety")
        known = {f.name for f in fields(cls)} - {"force_limit_n", "position_limits_m", "velocity_limit_m_s"}
        for name in table:
            if name not in known:
                raise UserError(f"{rig.source}: [safety] {unknown_name('field', name, known)}")
        settings.update(table)
        settings.update(overrides)
        try:
            return cls(**settings)
        except UserError as exc:
            raise UserError(f"{rig.source}: {exc}") from None
        except TypeError as exc:  # unknown override keyword
            raise UserError(f"bad safety setting: {exc}") from None

    def as_dict(self) -> dict:
        d = asdict(self)
        d["position_limits_m"] = list(self.position_limits_m)
        return d


# A simulator whose host stalls still gets its samples, late: it is declared dead only
# after this long without one (its plant advances per sample, not per wall second).
SIM_SAMPLE_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class WatchdogPolicy:
    """What the loop's watchdog does, and for which kind of device (start record ``watchdog``).

    ``applies``: "hardware" or "simulator". ``period_limit_s``: a paced loop period longer
    than it zeroes the force and trips (inf: never; a late period is still counted as an
    overrun in the timing and flagged ``OVERRUN`` on its sample). ``sample_timeout_s``: no
    sample within it trips.

    On hardware a stalled host leaves a real handle under a stale force: the watchdog trips
    at ``watchdog_s``. On a simulator the plant advances per sample, so a host stall (seen
    here: 82 ms on a busy 2-core machine) harms nothing but would cost the run: it is
    recorded and the run goes on.
    """

    applies: str
    period_limit_s: float
    sample_timeout_s: float

    @classmethod
    def for_device(cls, safety: SafetyConfig, simulated: bool) -> WatchdogPolicy:
        if simulated:
            return cls("simulator", math.inf, max(safety.watchdog_s, SIM_SAMPLE_TIMEOUT_S))
        return cls("hardware", safety.watchdog_s, safety.watchdog_s)

    def as_dict(self) -> dict:
        inf = math.isinf(self.period_limit_s)
        return {"applies": self.applies, "period_limit_s": None if inf else self.period_limit_s,
                "sample_timeout_s": self.sample_timeout_s,
                "late_period": "recorded, run goes on" if inf else "trips"}


_NON_NEGATIVE = {"nominal_damping_ns_m", "enable_force_threshold_n"}
# Physical upper bound of each limit (no haptic bench is beyond them; 1e308 is a typo).
_MAX = {
    "force_limit_n": (1000.0, "N"),
    "force_rate_limit_n_per_s": (1e9, "N/s"),  # above 1000 N per 10 us sample: no limit
    "velocity_limit_m_s": (1000.0, "m/s"),
    "energy_limit_j": (1000.0, "J"),
    "energy_fade_s": (10.0, "s"),
    "nominal_damping_ns_m": (1e4, "N s/m"),
    "watchdog_s": (10.0, "s"),
    "enable_force_threshold_n": (1000.0, "N"),
}
_MAX_POSITION_M = 1000.0


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)
