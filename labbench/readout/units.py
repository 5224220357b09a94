"""Display units: what a person reads (mm, deg, Hz) while everything stored stays SI.

``DisplayUnits`` converts SI values for display only: lengths m -> mm, angles
rad -> deg, frequencies rad/s -> Hz. The CLI takes ``--units mm,deg,Hz`` (any
subset, any order); files written by labbench (sessions, exports, JSON) never
change units.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from labbench.errors import UserError

# unit -> (kind, factor from SI)
UNITS = {"m": ("length", 1.0), "mm": ("length", 1e3),
         "rad": ("angle", 1.0), "deg": ("angle", 180.0 / math.pi),
         "rad/s": ("frequency", 1.0), "Hz": ("frequency", 1.0 / (2 * math.pi))}


@dataclass(frozen=True)
class DisplayUnits:
    length: str = "m"
    angle: str = "rad"
    frequency: str = "rad/s"

    @classmethod
    def parse(cls, text: str | None) -> DisplayUnits:
        """``"mm,Hz"`` -> DisplayUnits(length="mm", frequency="Hz"); one UserError otherwise."""
        chosen: dict[str, str] = {}
        for token in (t.strip() for t in (text or "").split(",")):
            if not token:
                continue
            unit = next((u for u in UNITS if u.lower() == token.lower()), None)
            if unit is None:
                raise UserError(f"unknown display unit {token!r}; choose from {', '.join(UNITS)}")
            kind = UNITS[unit][0]
            if kind in chosen and chosen[kind] != unit:
                raise UserError(f"two {kind} units: {chosen[kind]} and {unit}")
            chosen[kind] = unit
        return cls(**chosen)

    def _convert(self, kind: str, value):
        unit = getattr(self, kind)
        return None if value is None else value * UNITS[unit][1]

    def length_of(self, metres):
        return self._convert("length", metres)

    def angle_of(self, radians):
        return self._convert("angle", radians)

    def frequency_of(self, rad_s):
        return self._convert("frequency", rad_s)


SI = DisplayUnits()
