"""The protocol contract: what every protocol is and shares (config fields, segments,
the stability precheck). Protocols live in ``labbench.protocols`` or in other packages
(registered through ``labbench.registry``); the runner knows only this module.

A protocol is plain data (a frozen config dataclass, SI units in the field
names) plus steps: ``segments()`` is a generator of ``Segment`` (a VE and the
exogenous force to apply with it); the runner sends each segment's outcome
back, so a protocol like the stability probe can decide its next step from
the last one. ``analyze(data, meta)`` turns the recorded channels into results.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Generator
from dataclasses import MISSING, asdict, dataclass, field, fields

import numpy as np

from labbench.errors import UnstableVEError, UserError
from labbench.model.ve import DEFAULT_PLANT, VE_KINDS, Plant, VirtualEnvironment

# Longest single recording [s]: the loop keeps a run's channels in memory (8 x 8 bytes a sample).
MAX_DURATION_S = 1800.0
# Most samples in one run: 10 million x 8 channels x 8 bytes = 640 MB held in memory.
MAX_SAMPLES = 10_000_000
SAMPLE_TIME_RANGE_S = (1e-5, 1.0)  # 100 kHz .. 1 Hz
MAX_FORCE_N = 1000.0  # largest excitation force a protocol may ask for (no bench exceeds it)



# --------------------------------------------------------------------- what each setting means
# Fields many protocols share, described once: (meaning, SI unit, choices). A protocol's own
# fields describe themselves with ``setting(...)``, which also overrides an entry here.
SHARED_FIELDS = {
    "ve": ("the virtual environment rendered", "", VE_KINDS),
    "K": ("virtual stiffness", "N/m", None),
    "B": ("virtual damping", "N s/m", None),
    "w0_rad_s": ("cut-off of the first-order low-pass on the velocity estimate that the "
                 "virtual damping acts on; none: no filter", "rad/s", None),
    "td_s": ("extra delay of the VE force beyond the sample-and-hold, a whole number of "
             "sample times", "s", None),
    "sample_time_s": ("sample time of the haptic loop (the rig's; the CLI sets it)", "s", None),
    "plant_m_kg": ("device mass for the stability precheck and the theory overlay; none: "
                   "an identified one (the CLI's --plant-from) or the rig's nominal", "kg", None),
    "plant_b": ("device damping for the precheck and the theory overlay; none: as for "
                "plant_m_kg", "N s/m", None),
    "plant_coulomb_n": ("device Coulomb friction for the friction-aware theory; none: the "
                        "chirp-ID's with --plant-from, a simulator's own, else estimated from "
                        "the record", "N", None),
    "plant_coulomb_ci95": ("95 % interval lo,hi of plant_coulomb_n (a chirp-ID's); none: "
                           "exact", "N", None),
    "allow_unstable": ("render a VE the precheck finds unstable (simulated devices only)", "",
                       None),
}


def setting(default, help: str, unit: str = "", choices=None):
    """A config field with its description: ``help`` (what it means, and what none means
    where none is allowed), its SI ``unit``, ``choices`` (a tuple, or a function returning
    one where the list lives in a module imported late). ``field_help`` turns it into the
    CLI's --help and the GUI's tooltips, so each description is written once."""
    return field(default=default, metadata={"help": help, "unit": unit, "choices": choices})


def _description(f) -> tuple[str, str, tuple | None]:
    if "help" in f.metadata:
        meaning, unit, options = f.metadata["help"], f.metadata["unit"], f.metadata["choices"]
    else:
        meaning, unit, options = SHARED_FIELDS.get(f.name, ("", "", None))
    return meaning, unit, options() if callable(options) else options


def field_choices(config_cls) -> dict[str, tuple]:
    """Field name -> its allowed values, for the fields that have a fixed set."""
    return {f.name: c for f in fields(config_cls) if (c := _description(f)[2])}


def field_help(config_cls) -> dict[str, str]:
    """Field name -> one line for a person: meaning [unit]; its choices; its default
    (the CLI's --help, the GUI's tooltips). An undescribed field reads as ""."""
    from labbench.readout.numfmt import fmt

    out = {}
    for f in fields(config_cls):
        meaning, unit, options = _description(f)
        if not meaning:
            out[f.name] = ""
            continue
        head, sep, rest = meaning.partition(";")  # the unit after the meaning's first clause
        parts = [head + (f" [{unit}]" if unit else "") + sep + rest]
        if options:
            parts.append("one of " + ", ".join(options))
        if f.default is not MISSING:
            d = f.default
            shown = ("on" if d else "off") if isinstance(d, bool) else (
                "none" if d is None else ",".join(map(str, d)) if isinstance(d, tuple) else fmt(d, 6))
            parts.append(f"default {shown}")
        out[f.name] = "; ".join(parts)
    return out


def number(name: str, value, unit: str, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, none_ok: bool = False):
    """Validate one numeric config field; one UserError naming field, value and unit."""
    if value is None and none_ok:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise UserError(f"{name} must be a number [{unit}], got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise UserError(f"{name} must be finite [{unit}], got {value!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise UserError(f"{name} must be {'>' if lo_open else '>='} {lo:g} {unit}, got {v:g}")
    if hi is not None and v > hi:
        raise UserError(f"{name} must be <= {hi:g} {unit}, got {v:g}")
    return v


def integer(name: str, value, lo: int | None = None, none_ok: bool = False):
    if value is None and none_ok:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            raise UserError(f"{name} must be a whole number, got {value!r}")
    if lo is not None and value < lo:
        raise UserError(f"{name} must be >= {lo}, got {value}")
    return int(value)


def choice(name: str, value, options: tuple[str, ...]):
    if not isinstance(value, str) or value not in options:
        close = difflib.get_close_matches(str(value), options, n=1) if isinstance(value, str) else []
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise UserError(f"{name} must be one of {', '.join(options)}, got {value!r}{hint}")
    return value


class Config:
    """Mixin for frozen config dataclasses: ``check()`` validates, ``as_dict()`` serialises."""

    def __post_init__(self):
        names = {f.name for f in fields(self)}
        if "sample_time_s" in names:  # before anything divides by it
            lo, hi = SAMPLE_TIME_RANGE_S
            self._set("sample_time_s", number("sample_time_s", self.sample_time_s, "s", lo=lo, hi=hi))
        self.check()
        if "sample_time_s" in names and "duration_s" in names:  # before anything is allocated
            n = self.duration_s / self.sample_time_s
            if n > MAX_SAMPLES:
                raise UserError(f"duration_s {self.duration_s:g} s at {self.sample_time_s:g} s per "
                                f"sample is {n:.3g} samples; at most {MAX_SAMPLES:.0e} fit in memory")

    def check(self) -> None:  # pragma: no cover - every config overrides it
        raise NotImplementedError

    def _set(self, name: str, value) -> None:
        object.__setattr__(self, name, value)

    def as_dict(self) -> dict:
        d = asdict(self)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}

    @classmethod
    def from_options(cls, protocol: str, options: dict):
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise UserError(f"unknown option(s) for {protocol}: {', '.join(unknown)}; "
                            f"known: {', '.join(sorted(known))}")
        return cls(**options)


def check_ve_fields(cfg) -> None:
    """Shared VE fields of a config: ve kind, K, B, w0_rad_s, td_s (via VirtualEnvironment)."""
    cfg._set("K", number("K", cfg.K, "N/m", lo=0))
    cfg._set("B", number("B", cfg.B, "N s/m", lo=0))
    cfg._set("w0_rad_s", number("w0_rad_s", cfg.w0_rad_s, "rad/s", lo=0, lo_open=True, none_ok=True))
    cfg._set("td_s", number("td_s", cfg.td_s, "s", lo=0))


def make_ve(kind: str, K: float, B: float, w0_rad_s: float | None, T: float, td_s: float):
    ve = VirtualEnvironment(kind, K, B, math.inf if w0_rad_s is None else w0_rad_s, T, td_s)
    ve.delay_samples  # noqa: B018 - raises UserError when td is not whole samples
    return ve


def check_plant_fields(cfg) -> None:
    cfg._set("plant_m_kg", number("plant_m_kg", cfg.plant_m_kg, "kg", lo=0, lo_open=True, none_ok=True))
    cfg._set("plant_b", number("plant_b", cfg.plant_b, "N s/m", lo=0, none_ok=True))
    if hasattr(cfg, "plant_coulomb_n"):  # labbench.model.device_friction reads them
        from labbench.model import device_friction

        fc = cfg.plant_coulomb_n
        cfg._set("plant_coulomb_n", None if fc is None else device_friction.checked(fc, "plant_coulomb_n"))
        ci = cfg.plant_coulomb_ci95
        if ci is not None and cfg.plant_coulomb_n is None:
            raise UserError("plant_coulomb_ci95 needs plant_coulomb_n")
        if isinstance(ci, (list, tuple)):  # the CLI gives words: "0.019,0.021"
            ci = tuple(number("plant_coulomb_ci95", float(x) if _numeric(x) else x, "N") for x in ci)
        cfg._set("plant_coulomb_ci95", device_friction.checked_ci(ci, cfg.plant_coulomb_n,
                                                                  "plant_coulomb_ci95"))


def _numeric(x) -> bool:
    try:
        float(x)
    except (TypeError, ValueError):
        return False
    return isinstance(x, str)


def nominal_plant(rig=None, m: float | None = None, b: float | None = None) -> Plant:
    """The plant a protocol assumes: given m, b first (e.g. identified), then the
    rig's nominal model (``Rig.nominal_plant``), then the paper's Phantom fit."""
    base = rig.nominal_plant if rig is not None else DEFAULT_PLANT
    return Plant(base.m if m is None else float(m), base.b if b is None else float(b))


@dataclass(frozen=True)
class Segment:
    """One stretch of a run: the VE rendered and the exogenous force per sample [N]."""

    label: str
    ve: VirtualEnvironment
    excitation: np.ndarray
    # A safety trip ends the run unless the protocol expects trips (the stability probe).
    trip_expected: bool = False
    role: str = "probe"  # "probe": measured data; "home": repositioning between steps
    # what the progress line says of it (the label, recorded in full, when empty)
    shown: str = ""


@dataclass
class SegmentOutcome:
    """What the runner sends back to ``segments()`` after a segment."""

    status: str  # run_loop status: "completed", "tripped", "aborted", "fault"
    reason: str
    data: dict  # channel -> array of this segment only


class ProtocolBase:
    """Base class: subclasses set ``name`` and ``Config`` (their config dataclass) and
    implement the steps; an instance holds its validated ``config``."""

    name: str = ""
    Config: type = None  # the frozen config dataclass (a ``Config`` subclass)
    # The device's own delay [s] on this run (``labbench.model.device_delay``), set by ``precheck``
    # before ``check_plan`` and ``segments``: what a protocol that plans from the exact
    # boundary (the stability probe) must know of the rig.
    device_delay_s: float = 0.0
    # The device's Coulomb friction on this run (``labbench.model.device_friction``), set by the
    # run's checks (``labbench.runner.checks``) before ``check_plan``; None: not resolved yet.
    device_friction = None

    def __init__(self, config):
        self.config = config

    @property
    def ve(self) -> VirtualEnvironment:
        """The VE the protocol starts with (checked against the stability boundary)."""
        raise NotImplementedError

    @property
    def n_samples(self) -> int:
        """Planned samples (an upper bound for adaptive protocols; used for progress)."""
        raise NotImplementedError

    @property
    def allow_unstable(self) -> bool:
        return bool(getattr(self.config, "allow_unstable", False))

    @property
    def seed(self) -> int | None:
        return getattr(self.config, "seed", None)

    def plant(self, rig=None) -> Plant:
        return nominal_plant(rig, getattr(self.config, "plant_m_kg", None),
                             getattr(self.config, "plant_b", None))

    def vetted_ves(self, plant: Plant) -> list[VirtualEnvironment]:
        """Every VE the protocol will render before it learns anything (precheck checks them)."""
        return [self.ve]

    def check_plan(self, plant: Plant, rig=None) -> dict:
        """Protocol-specific checks beyond stability (e.g. predicted excursion); extra numbers."""
        return {}

    def segments(self, plant: Plant) -> Generator[Segment, SegmentOutcome, None]:
        """The run's steps; ``plant`` is the one the precheck used."""
        raise NotImplementedError

    def analyze(self, data: dict[str, np.ndarray], meta: dict) -> dict:
        raise NotImplementedError

    def describe(self) -> dict:
        return {"protocol": self.name, **self.config.as_dict()}

    def report_sections(self, session):
        """This protocol's part of a report on ``session`` (a
        ``labbench.report.session.ReportSession`` of a run of this protocol): a
        ``labbench.report.blocks.ReportSections`` with the verdict rows for page 1,
        curves for its overlay figure, flags and the detail blocks. This default
        lists the run's scalar results."""
        from labbench.report.blocks import ReportSections, key_values

        items = [(k, v) for k, v in session.results.items() if not isinstance(v, (dict, list))]
        return ReportSections(details=[key_values("Results", items)] if items else [])


def precheck(protocol: ProtocolBase, plant: Plant, rig=None, delay=None) -> dict:
    """Check the protocol's VE(s) against the exact sampled stability boundary.

    Uses ``labbench.model.linear.stability`` (spectral radius of the exact sampled loop)
    and ``k_max`` / ``k_max_approx`` for the numbers shown, with the device's own
    delay (``delay``, a ``labbench.model.device_delay.DeviceDelay``; None: the rig's, by
    ``device_delay.resolve(rig)``) as the loop's actuator latency, so K_max is the
    one the rig has. Raises UnstableVEError (a UserError) for an unstable VE unless the protocol's
    ``allow_unstable`` is set (the runner allows that on a simulator only). Returns
    the numbers for the start record (``device_delay`` says which delay was used and
    where it came from). A protocol that knows the device's Coulomb friction
    (``plant_coulomb_n``) gets Abbott & Okamura's quantisation bound 2 f_c / Delta beside each
    K_max (``k_passive_quantised``), and a refusal says how small an oscillation friction
    still stops (``labbench.model.stability_friction.limit_cycle_amplitude``).
    """
    from labbench.model import device_delay
    from labbench.model import linear, passivity
    from labbench.model.stability_friction import limit_cycle_amplitude

    extra = delay if delay is not None else device_delay.resolve(rig)
    latency = extra.s
    report = {"plant": {"m": plant.m, "b": plant.b}, "device_delay": extra.as_dict(), "checks": []}
    fc = getattr(protocol.config, "plant_coulomb_n", None)
    for ve in protocol.vetted_ves(plant):
        st = linear.stability(plant, ve, latency)
        km = linear.k_max(plant, ve, latency=latency)
        ka = linear.k_max_approx(plant, ve, latency)
        entry = {"ve": ve.as_dict(), "stable": bool(st.stable),
                 "spectral_radius": float(st.spectral_radius), "k_max": km, "k_max_approx": ka}
        if fc and rig is not None and km is not None:
            entry["k_passive_quantised"] = passivity.quantisation_bound(fc, rig.metres_per_count)
        report["checks"].append(entry)
        if not st.stable and not protocol.allow_unstable:
            bound = f"K_max = {km:.4g} N/m (exact sampled)" if km is not None else "no stable K"
            approx = f", paper approx. {ka:.4g} N/m" if ka is not None else ""
            if fc and km is not None:
                x_star = limit_cycle_amplitude(plant, ve, fc, latency)
                approx += (f"; friction {fc:g} N stops oscillations below {x_star * 1e3:.3g} mm "
                           "only: larger ones grow") if 0 < x_star < math.inf else ""
            raise UnstableVEError(
                f"refusing unstable {ve.kind} VE K = {ve.K:g} N/m, B = {ve.B:g} N s/m, "
                f"td = {ve.td * 1e3:g} ms (+ {latency * 1e3:g} ms device delay) "
                f"on m = {plant.m:g} kg, b = {plant.b:g} N s/m: "
                f"spectral radius {st.spectral_radius:.6f} >= 1; {bound}{approx}")
    report["stable"] = all(c["stable"] for c in report["checks"])
    protocol.device_delay_s = latency
    report.update(protocol.check_plan(plant, rig))
    return report
