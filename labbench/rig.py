"""Rig files: a validated TOML description of one bench.

Common fields (all SI at the handle) live in ``[rig]``; each backend reads its
own table (``[sim]``, ``[canopen]``, ``[serial]``) through its own validator, so
a driver's settings stay next to the driver. Every bad field gives one clear
``UserError`` naming the file and the field.

Calibration: encoder counts -> metres is ``2*pi*lever_arm_m / counts_per_rev``
for a rotary joint (a linear encoder gives ``counts_per_rev`` = counts per metre
and ``lever_arm_m`` = 1/(2*pi)); force at the handle -> joint torque is
``force * lever_arm_m``. ``position_sign`` (1 or -1) is the sign a driver gives the
encoder's counts so that a positive force moves the handle to positive positions
(``labbench run commission`` checks it): position = ``position_per_count * count``.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from labbench import scales
from labbench.errors import UserError, unknown_name
from labbench.input_files import read_text
from labbench.loop.realtime import RealtimeConfig
from labbench.loop.safety import SafetyConfig
from labbench.model.ve import DEFAULT_PLANT, Plant


@dataclass(frozen=True)
class Rig:
    name: str = "simulated Phantom-like joint"
    sample_time_s: float = 0.001
    counts_per_rev: float = 4096 * 4
    lever_arm_m: float = 0.1
    position_sign: int = 1
    force_limit_n: float = 5.0
    position_limits_m: tuple[float, float] = (-0.1, 0.1)
    velocity_limit_m_s: float = 2.0
    # Nominal device model at the handle (the paper's Phantom-like joint): used for
    # stability pre-checks and credited as dissipation by the loop's energy observer.
    nominal_mass_kg: float = DEFAULT_PLANT.m
    nominal_damping_ns_m: float = DEFAULT_PLANT.b
    # The rig's own extra loop delay [s] beyond the VE's td (amplifier, transport, filters),
    # as measured by ``labbench analyze etfe --fit`` (its td_s); None: not measured. The
    # stability pre-check and theory overlays use it. ``measured_td_from``: where it came from.
    measured_td_s: float | None = None
    measured_td_from: str = ""
    # When and where the rig last passed ``labbench run commission``'s direction check
    # (written by ``--write-rig``); "": never. Real hardware renders no spring or damper
    # before it (``labbench.commissioning.gate``).
    direction_checked: str = ""
    sections: dict = field(default_factory=dict)  # backend tables, validated by the backend
    source: str = "<defaults>"

    @property
    def metres_per_count(self) -> float:
        return 2 * math.pi * self.lever_arm_m / self.counts_per_rev

    @property
    def position_per_count(self) -> float:
        """Handle metres per encoder count, signed (``position_sign``): what a driver
        multiplies a count by."""
        return self.position_sign * self.metres_per_count

    @property
    def nominal_plant(self):
        """The nominal model as a ``labbench.model.ve.Plant``."""
        return Plant(self.nominal_mass_kg, self.nominal_damping_ns_m)

    def section(self, name: str) -> dict:
        return dict(self.sections.get(name, {}))

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "sample_time_s": self.sample_time_s,
            "counts_per_rev": self.counts_per_rev,
            "lever_arm_m": self.lever_arm_m,
            "position_sign": self.position_sign,
            "force_limit_n": self.force_limit_n,
            "position_limits_m": list(self.position_limits_m),
            "velocity_limit_m_s": self.velocity_limit_m_s,
            "nominal_mass_kg": self.nominal_mass_kg,
            "nominal_damping_ns_m": self.nominal_damping_ns_m,
            "measured_td_s": self.measured_td_s,
            "measured_td_from": self.measured_td_from,
            "direction_checked": self.direction_checked,
            "sections": self.sections,
            "source": self.source,
        }


# [rig] numbers: (lowest, highest, unit); a lowest of 0 is excluded except for damping.
# Upper bounds are physical: no haptic bench is beyond them, and a typo (1e308) is caught.
# The numbers that scale a command (lever arm, counts per revolution) are labbench.scales'.
_BOUNDS = {
    "sample_time_s": (1e-5, 1.0, "s"),  # 100 kHz .. 1 Hz; the loop keeps every sample in memory
    "force_limit_n": (0.0, 1000.0, "N"),
    "velocity_limit_m_s": (0.0, 1000.0, "m/s"),
    "nominal_mass_kg": (1e-6, 1000.0, "kg"),
    "nominal_damping_ns_m": (0.0, 1e4, "N s/m"),
    "measured_td_s": (0.0, 1.0, "s"),
}
_ZERO_OK = ("nominal_damping_ns_m", "measured_td_s")
MAX_POSITION_M = 1000.0
MAX_NAME = 200
MAX_RIG_FILE_BYTES = 1 << 20  # a rig file is a page of TOML; larger is not a rig file


def _tables() -> tuple[str, ...]:
    """Tables a rig file may hold: [rig], [safety], [realtime], [preflight] (the timing
    preflight, ``labbench.loop.preflight``), [campaign] (``labbench.rig``), and one
    per device backend (its name)."""
    from labbench.registry import device_names  # names only: no backend is imported

    return ("rig", "safety", "realtime", "preflight", "campaign", *device_names())


def rig_from_dict(d: dict, source: str = "<dict>") -> Rig:
    """Validate a parsed rig table (``{"rig": {...}, "sim": {...}, ...}``).

    Unknown tables and fields are errors naming the nearest valid one; numbers
    must lie within ``_BOUNDS``; [safety] and [realtime] are validated here too
    (``labbench.loop.safety.SafetyConfig``, ``labbench.loop.realtime.RealtimeConfig``), so a
    bad limit stops before any device is opened.
    """
    tables = _tables()
    for k, v in d.items():
        if k not in tables:
            raise UserError(f"{source}: {unknown_name('table', k, tables)}")
        if not isinstance(v, dict):
            raise UserError(f"{source}: [{k}] must be a table, got {type(v).__name__}")
    common = dict(d.get("rig", {}))
    known = set(Rig.__dataclass_fields__) - {"sections", "source"}
    for name in common:
        if name not in known:
            raise UserError(f"{source}: [rig] {unknown_name('field', name, known)}")
    for name, (lo, hi, unit) in _BOUNDS.items():
        if name in common:
            v = common[name]
            ok = scales.is_number(v)
            closed = lo > 0 or name in _ZERO_OK  # the lowest value itself allowed
            if not ok or not ((v >= lo if closed else v > lo) and v <= hi):
                low = f"[{lo:g}" if closed else f"({lo:g}"
                raise UserError(f"{source}: [rig] {name} must be a number in {low}, {hi:g}] {unit}, "
                                f"got {v!r}")
            common[name] = float(v)
    for table, name in scales.SCALES:
        if table == "rig" and name in common:
            common[name] = scales.check("rig", name, common[name], source)
    if "position_limits_m" in common:
        lim = common["position_limits_m"]
        if (not isinstance(lim, list) or len(lim) != 2
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                           and abs(x) <= MAX_POSITION_M for x in lim) or not lim[0] < lim[1]):
            raise UserError(f"{source}: [rig] position_limits_m must be [low, high] with low < high, "
                            f"each within +-{MAX_POSITION_M:g} m")
        common["position_limits_m"] = (float(lim[0]), float(lim[1]))
    if "position_sign" in common and (common["position_sign"] not in (1, -1)
                                      or isinstance(common["position_sign"], (bool, float))):
        raise UserError(f"{source}: [rig] position_sign must be 1 or -1, got {common['position_sign']!r}")
    if "name" in common and (not isinstance(common["name"], str) or len(common["name"]) > MAX_NAME):
        raise UserError(f"{source}: [rig] name must be a string of at most {MAX_NAME} characters")
    for name in ("measured_td_from", "direction_checked"):
        if name in common and (not isinstance(common[name], str) or len(common[name]) > MAX_NAME):
            raise UserError(f"{source}: [rig] {name} must be a string of at most {MAX_NAME} characters")
    sections = {k: v for k, v in d.items() if k != "rig"}
    rig = Rig(**common, sections=sections, source=source)
    SafetyConfig.from_rig(rig)  # raises for a bad [safety] table
    RealtimeConfig.from_rig(rig)  # and for a bad [realtime] one
    from labbench.loop.preflight import PreflightConfig

    PreflightConfig.from_rig(rig)  # and for a bad [preflight] one
    CampaignSettings.from_rig(rig)  # and for a bad [campaign] one
    from labbench.registry import rig_table_check

    for name in sections:  # a backend's own table ([sim], [canopen], [serial]), by its checker
        check = rig_table_check(name)
        if check is not None:
            check(rig)
    return rig


def check_recorded(d: dict, where: str) -> None:
    """A start record's ``rig`` (``Rig.as_dict``) as labbench writes it: its ``[rig]`` fields
    of the right types and within their ranges, as ``rig_from_dict`` checks a file's. Names
    this labbench does not know are left alone (an older or newer writer's), and so are the
    backend tables (a session is read on machines without the rig's EDS). UserError else."""
    known = set(Rig.__dataclass_fields__) - {"sections", "source"}
    rig_from_dict({"rig": {k: v for k, v in d.items() if k in known and v is not None}}, where)


def load_rig(path: str | Path | None) -> Rig:
    """Read a rig file (a regular file of at most 1 MiB); ``None`` gives the default simulated rig."""
    if path is None:
        return Rig()
    p = Path(path)
    text = read_text(p, "rig file", MAX_RIG_FILE_BYTES)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{p}: not valid TOML: {exc}") from None
    except RecursionError:
        raise UserError(f"{p}: not valid TOML: nested too deeply") from None
    return rig_from_dict(data, source=str(p))


CAMPAIGN_TABLE = "campaign"
MAX_PAUSE_S = 600.0
HARDWARE_PAUSE_S = 2.0


@dataclass(frozen=True)
class CampaignSettings:
    """The rig's ``[campaign]`` table: what a campaign does between its points on this bench.

    ```toml
    [campaign]
    pause_s = 2.0      # force zero, device closed, this long before the next point opens it
    ```

    ``pause_s`` [s] (0-600; default 2 s on real hardware, 0 on a simulator): after a point
    the runner has commanded zero force, disabled and closed the device; the campaign waits
    this long (a handle still swinging settles, a drive cools, the operator sees the pause)
    before it opens the device for the next point. A stop request ends the wait at once.
    """

    pause_s: float

    @classmethod
    def from_rig(cls, rig, simulated: bool = False) -> CampaignSettings:
        """The rig's ``[campaign]`` table over the defaults (class doc); one UserError naming
        the file and the field."""
        table = rig.section(CAMPAIGN_TABLE)
        for name in table:
            if name != "pause_s":
                raise UserError(f"{rig.source}: [{CAMPAIGN_TABLE}] {unknown_name('field', name, ('pause_s',))}")
        pause = table.get("pause_s", 0.0 if simulated else HARDWARE_PAUSE_S)
        ok = scales.is_number(pause)
        if not ok or not 0 <= pause <= MAX_PAUSE_S:
            raise UserError(f"{rig.source}: [{CAMPAIGN_TABLE}] pause_s must be a number of seconds in "
                            f"[0, {MAX_PAUSE_S:g}], got {pause!r}")
        return cls(float(pause))
