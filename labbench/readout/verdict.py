"""A verdict on every result: ``ok``, ``doubtful`` or ``failed``, with the reasons in words.

Each analysis judges its own result against what the record itself shows (the
noise it carries, parameters at their bounds, residual structure, coherence and
band widths) and says so; the CLI prints the verdict beside the numbers, the JSON
carries ``verdict = {"level", "reasons"}``, the report's summary and the window show
it, and ``--strict`` makes a ``failed`` result exit with ``STRICT_EXIT``.

``doubtful``: the number may be right but the record cannot vouch for it (say what
would settle it); ``failed``: the number is not to be used.

What a level judges (issue 30): whether what is stated, a value *with its interval*, can be
trusted: a bias the interval does not hold, a misfit, an effect the model leaves out. How
precise a number is, is its interval's to say, not the level's: a wide interval that holds
the truth is ``ok``, and the verdict's ``notes`` say how precise it is against a target
(``precision``). A frequency-domain result states its ``band`` (rad/s): the level refers to
that band, the one the analysis was asked about; what limits the result outside it (the
encoder's quantisation above some frequency, too short a record below another) goes in
``notes`` and never raises the level.
"""
from __future__ import annotations

from collections.abc import Iterable
import math
from dataclasses import dataclass

OK, DOUBTFUL, FAILED = "ok", "doubtful", "failed"
LEVELS = (OK, DOUBTFUL, FAILED)  # in order of worsening
STRICT_EXIT = 3  # a result's verdict was "failed" under --strict (2: bad input, 1: device)
MAX_REASONS = 20  # a verdict read from a file keeps at most this many reasons
# A number is vouched for to an accuracy target when its 99.9 % interval lies within it:
# the 95 % interval stretched by z(0.9995) / z(0.975) = 3.29 / 1.96. A calibrated interval
# then misses its target unflagged in at most 0.1 % of records (at 95 % it would be up to 5 %).
VOUCH_STRETCH = 3.2905 / 1.9600
# A bias the interval does not hold is worth a finding beyond this many standard errors: up
# to half of one a 95 % interval still covers 91 % (radial bias of a circular complex error,
# non-central chi-square with 2 dof; 92 % for a real one).
BIAS_SE = 0.5


@dataclass(frozen=True)
class Verdict:
    """``level`` and the ``reasons`` behind it; ``band`` (lo, hi) rad/s: where the level
    holds (None: not a frequency-domain result); ``notes``: limits that do not raise it."""

    level: str = OK
    reasons: tuple[str, ...] = ()
    band: tuple[float, float] | None = None
    notes: tuple[str, ...] = ()

    def __post_init__(self):
        if self.level not in LEVELS:
            raise ValueError(f"verdict level {self.level!r} is not one of {', '.join(LEVELS)}")

    @property
    def failed(self) -> bool:
        return self.level == FAILED

    def as_dict(self) -> dict:
        d = {"level": self.level, "reasons": list(self.reasons)}
        if self.band is not None:
            d["band_rad_s"] = list(self.band)
        if self.notes:
            d["notes"] = list(self.notes)
        return d

    def head(self, units=None) -> str:
        """``ok`` or ``ok over 2-340 rad/s`` (``units``: ``labbench.readout.units.DisplayUnits``)."""
        if self.band is None:
            return self.level
        from labbench.readout.numfmt import band_text

        return f"{self.level} over {band_text(self.band, units)}"

    def line(self, units=None) -> str:
        """``ok``, ``ok over 2-340 rad/s (note)`` or ``doubtful: reason; reason (note)``; the
        frequencies of reasons and notes in the display ``units`` too."""
        from labbench.readout.numfmt import frequencies_in

        text = self.head(units)
        if self.reasons:
            text += ": " + "; ".join(frequencies_in(r, units) for r in self.reasons)
        if self.notes:
            text += " (" + "; ".join(frequencies_in(n, units) for n in self.notes) + ")"
        return text


def unvouched(name: str, value: float, interval: tuple[float, float], target: float,
               unit: str = "") -> tuple[str, str]:
    """A finding: doubtful when ``value``'s 95 % ``interval``, stretched to 99.9 %
    (``VOUCH_STRETCH``), reaches beyond +-``target`` of it (the record cannot vouch for the
    number to that accuracy), else ok."""
    lo, hi = interval
    reach = VOUCH_STRETCH * max(value - lo, hi - value)
    return (DOUBTFUL if not reach <= target else OK,
            f"{name} not pinned to its accuracy target +-{target:.2g}{unit}: 95 % interval "
            f"[{lo:.4g}, {hi:.4g}], +-{reach:.2g}{unit} at 99.9 %")


def holds(value: float, interval: tuple[float, float], truth: float, target: float) -> bool:
    """What an ``ok`` promises of a number with a 95 % ``interval``: it lies within ``target``
    (absolute) of the ``truth``, or its interval stretched to 99.9 % (``VOUCH_STRETCH``) holds
    the truth. A number that does neither misled whoever read it; the benchmarks and tests
    count an ``ok`` on such a number as a silent failure, and anything but ``ok`` on one
    that holds as a false alarm."""
    if abs(value - truth) <= target:
        return True
    lo, hi = interval
    return value - VOUCH_STRETCH * (value - lo) <= truth <= value + VOUCH_STRETCH * (hi - value)


def precision(name: str, value: float, interval: tuple[float, float], target: float,
              unit: str = "") -> str | None:
    """A note when ``value``'s 95 % ``interval``, stretched to 99.9 % (``VOUCH_STRETCH``),
    reaches beyond +-``target`` of it: the record cannot pin the number to that target (its
    interval says how far it can); None when it can."""
    level, reason = unvouched(name, value, interval, target, unit)
    return None if level == OK else reason


def judge(findings: Iterable[tuple[str, str]], band: tuple[float, float] | None = None,
          notes: Iterable[str | None] = ()) -> Verdict:
    """The verdict of ``(level, reason)`` findings: the worst level; the reasons of every
    finding worse than ok, in order (an ``ok`` finding's reason is dropped); ``band`` and
    ``notes`` (Nones dropped) as given."""
    level, reasons = OK, []
    for lvl, reason in findings:
        if lvl not in LEVELS:
            raise ValueError(f"verdict level {lvl!r} is not one of {', '.join(LEVELS)}")
        if lvl != OK:
            reasons.append(reason)
            if LEVELS.index(lvl) > LEVELS.index(level):
                level = lvl
    return Verdict(level, tuple(reasons), _band(band), tuple(n for n in notes if n))


def _band(band) -> tuple[float, float] | None:
    return None if band is None else (float(band[0]), float(band[1]))


def worst(verdicts: Iterable[Verdict | None]) -> Verdict:
    """One verdict for several results: the worst level, every reason (Nones ignored)."""
    level, reasons, notes = OK, [], []
    for v in verdicts:
        if v is not None:
            reasons.extend(v.reasons)
            notes.extend(v.notes)
            level = max(level, v.level, key=LEVELS.index)
    return Verdict(level, tuple(reasons), None, tuple(notes))


def from_dict(d) -> Verdict | None:
    """A recorded verdict back; None when ``d`` is not one (a session file's content is
    not trusted: unknown levels and non-string reasons are not taken)."""
    if not isinstance(d, dict) or d.get("level") not in LEVELS:
        return None
    return Verdict(d["level"], _strings(d.get("reasons")), _read_band(d.get("band_rad_s")),
                   _strings(d.get("notes")))


def _strings(x) -> tuple[str, ...]:
    return tuple(r for r in x[:MAX_REASONS] if isinstance(r, str)) if isinstance(x, list) else ()


def _read_band(x) -> tuple[float, float] | None:
    """A recorded band back: two finite numbers, lo < hi; else None."""
    if not (isinstance(x, list) and len(x) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in x)):
        return None
    lo, hi = float(x[0]), float(x[1])
    return (lo, hi) if math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi else None


def strict_exit(verdicts: Iterable[Verdict | None], strict: bool) -> int:
    """The exit code a command returns after printing its results: ``STRICT_EXIT`` when
    ``strict`` and any verdict failed, else 0."""
    return STRICT_EXIT if strict and any(v is not None and v.failed for v in verdicts) else 0
