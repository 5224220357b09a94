"""The physical range of every rig number that scales a command (or the position a VE's force
is computed from), in one table: a value outside it is a typo or a wrong unit, refused when
the rig file is read, before any device is opened.

A force at the handle reaches the motor as ``F * lever_arm_m`` of joint torque, divided by the
torque one unit of the drive's set point makes (``[canopen]``: per-mille of the motor's rated
torque, or mA / A times the motor's torque constant; ``[serial]``: N or N m as a float); the
VE's force is K x + B v of a position ``count * 2 pi lever_arm_m / counts_per_rev``. The
host clamps every command at ``force_limit_n``, in newtons, *before* it is converted: a scale
off by orders of magnitude turns that limit into a set point the drive saturates (any nonzero
force becomes the drive's largest current) or into one unit that is already beyond the limit.
So each scale is bounded by what real motors, drives and encoders are, with a margin of about
5 either side, and the driver refuses a combination whose one unit exceeds the force limit or
whose force limit its set point cannot hold (``labbench.drivers.canopen_check``).

Where the bounds come from (makers' catalogues, rounded outward):

* ``lever_arm_m`` [m], joint torque per handle force, any reduction included (a capstan or a
  gear of ratio n divides the arm by n): 1e-4 m is a 0.1 m arm behind a 1000:1 reduction (the
  strongest harmonic and multi-stage gearheads stop near 160:1 .. 500:1); a linear axis is
  1 / (2 pi) = 0.159 m; 10 m is far beyond any handle a hand holds on a bench (2 m).
* ``counts_per_rev`` [counts per joint revolution; per metre on a linear axis]: 4 is one
  quadrature line (Hall sensors give 6 per electrical turn); 1e10 is beyond a 32-bit absolute
  encoder (2^32 = 4.3e9 counts/rev) and a 0.1 nm linear scale (1e10 counts/m).
* ``[canopen] rated_torque_mnm`` [mN m] (the unit of CiA 402's per-mille set point 0x6071):
  0.01 mN m is below the smallest coreless micromotors (a 4 mm motor is rated near 0.05 mN m);
  1e7 mN m = 10 kN m is beyond the largest direct-drive torque motors (a few kN m).
* ``[canopen] torque_constant_nm_per_a`` [N m/A]: 1e-4 N m/A is below a 4-6 mm coreless motor
  (about 0.5-1 mN m/A); 100 N m/A is beyond the largest frameless torque motors (tens of N m/A).
* ``[canopen] rated_current_ma`` [mA]: 1 mA is below any motor drive's rated current; 1e6 mA
  = 1 kA is beyond the largest servo drives (a few hundred A).

``sample_time_s`` (the velocity's 1/T) and ``force_limit_n`` itself are bounded in
``labbench.rig`` with the other ``[rig]`` numbers; a set point's unit is one of a fixed list
(``[canopen.modes] unit``, ``[serial] command_units``), not a number.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from labbench.errors import UserError


def is_number(x) -> bool:
    """A finite int or float, not a bool (TOML and JSON give bools where numbers belong)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


@dataclass(frozen=True)
class Bound:
    lo: float
    hi: float
    unit: str
    what: str  # what the number is, in words
    unset: float | None = None  # a value meaning "not given" (0 in [canopen]), allowed too

    def check(self, value, where: str) -> float:
        """``value`` as a float when it lies in [lo, hi] (or is ``unset``), else one UserError
        naming ``where``, the range and why it is physical."""
        if is_number(value) and (value == self.unset or self.lo <= value <= self.hi):
            return float(value)
        unset = f" (or {self.unset:g}: not given)" if self.unset is not None else ""
        raise UserError(f"{where} must be a number in [{self.lo:g}, {self.hi:g}] {self.unit}"
                        f"{unset}, got {value!r}: {self.what} beyond that range is no real "
                        "device's (labbench/scales.py)")


# (table, field) -> its physical range. Every number on the way from a force to a motor's set
# point, or from an encoder count to the position a VE's force is made from.
SCALES = {
    ("rig", "lever_arm_m"): Bound(1e-4, 10.0, "m", "a joint torque per handle force"),
    ("rig", "counts_per_rev"): Bound(4.0, 1e10, "counts", "an encoder's counts per revolution"),
    ("sim", "lever_arm_m"): Bound(1e-4, 10.0, "m", "a joint torque per handle force"),
    ("sim", "counts_per_rev"): Bound(4.0, 1e10, "counts", "an encoder's counts per revolution"),
    ("canopen", "rated_torque_mnm"): Bound(0.01, 1e7, "mN m", "a motor's rated torque", 0.0),
    ("canopen", "torque_constant_nm_per_a"): Bound(1e-4, 100.0, "N m/A",
                                                   "a motor's torque constant", 0.0),
    ("canopen", "rated_current_ma"): Bound(1.0, 1e6, "mA", "a motor's rated current", 0.0),
}


def check(table: str, name: str, value, source: str) -> float:
    """``SCALES[(table, name)].check`` with the message's place: ``<source>: [table] name``."""
    return SCALES[(table, name)].check(value, f"{source}: [{table}] {name}")
