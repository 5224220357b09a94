"""Rig files: a validated TOML description of one bench.

Common fields (all SI at the handle) live in ``[rig]``; each backend reads its
own table (``[sim]``, ``[canopen]``, ``[serial]``) through its own validator, so
a driver's settings stay next to the driver. Every bad field gives one clear
``UserError`` naming the file and the field.

Calibration: encoder counts -> metres is ``2*pi*lever_arm_m / counts_per_rev``
for a rotary joint (a linear encoder gives ``counts_per_rev`` = counts per metre
and ``lever_arm_m`` = 1/(2*pi)); force at the handle -> joint torque is
``force * lever_arm_m``.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from labbench.errors import UserError
from labbench.ve import DEFAULT_PLANT, Plant


@dataclass(frozen=True)
class Rig:
    name: str = "simulated Phantom-like joint"
    sample_time_s: float = 0.001
    counts_per_rev: float = 4096 * 4
    lever_arm_m: float = 0.1
    force_limit_n: float = 5.0
    position_limits_m: tuple[float, float] = (-0.1, 0.1)
    velocity_limit_m_s: float = 2.0
    # Nominal device model at the handle (the paper's Phantom-like joint): used for
    # stability pre-checks and credited as dissipation by the loop's energy observer.
    nominal_mass_kg: float = DEFAULT_PLANT.m
    nominal_damping_ns_m: float = DEFAULT_PLANT.b
    sections: dict = field(default_factory=dict)  # backend tables, validated by the backend
    source: str = "<defaults>"

    @property
    def metres_per_count(self) -> float:
        return 2 * math.pi * self.lever_arm_m / self.counts_per_rev

    @property
    def nominal_plant(self):
        """The nominal model as a ``labbench.ve.Plant``."""
        return Plant(self.nominal_mass_kg, self.nominal_damping_ns_m)

    def section(self, name: str) -> dict:
        return dict(self.sections.get(name, {}))

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "sample_time_s": self.sample_time_s,
            "counts_per_rev": self.counts_per_rev,
            "lever_arm_m": self.lever_arm_m,
            "force_limit_n": self.force_limit_n,
            "position_limits_m": list(self.position_limits_m),
            "velocity_limit_m_s": self.velocity_limit_m_s,
            "nominal_mass_kg": self.nominal_mass_kg,
            "nominal_damping_ns_m": self.nominal_damping_ns_m,
            "sections": self.sections,
            "source": self.source,
        }


_POSITIVE = ("sample_time_s", "counts_per_rev", "lever_arm_m", "force_limit_n", "velocity_limit_m_s",
             "nominal_mass_kg")
_NON_NEGATIVE = ("nominal_damping_ns_m",)


def rig_from_dict(d: dict, source: str = "<dict>") -> Rig:
    """Validate a parsed rig table (``{"rig": {...}, "sim": {...}, ...}``)."""
    common = dict(d.get("rig", {}))
    known = set(Rig.__dataclass_fields__) - {"sections", "source"}
    unknown = set(common) - known
    if unknown:
        raise UserError(f"{source}: unknown field(s) in [rig]: {', '.join(sorted(unknown))}")
    for name in _POSITIVE + _NON_NEGATIVE:
        if name in common:
            v = common[name]
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            if not ok or not (v > 0 or (name in _NON_NEGATIVE and v == 0)):
                kind = "a number >= 0" if name in _NON_NEGATIVE else "a positive number"
                raise UserError(f"{source}: [rig] {name} must be {kind}, got {v!r}")
            common[name] = float(v)
    if "position_limits_m" in common:
        lim = common["position_limits_m"]
        if (not isinstance(lim, list) or len(lim) != 2
                or not all(isinstance(x, (int, float)) for x in lim) or not lim[0] < lim[1]):
            raise UserError(f"{source}: [rig] position_limits_m must be [low, high] with low < high")
        common["position_limits_m"] = (float(lim[0]), float(lim[1]))
    if "name" in common and not isinstance(common["name"], str):
        raise UserError(f"{source}: [rig] name must be a string")
    sections = {k: v for k, v in d.items() if k != "rig"}
    for k, v in sections.items():
        if not isinstance(v, dict):
            raise UserError(f"{source}: [{k}] must be a table")
    return Rig(**common, sections=sections, source=source)


def load_rig(path: str | Path | None) -> Rig:
    """Read a rig file; ``None`` gives the default simulated rig."""
    if path is None:
        return Rig()
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise UserError(f"rig file not found: {p}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read rig file {p}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{p}: not valid TOML: {exc}") from None
    return rig_from_dict(data, source=str(p))
