"""A verdict on every result: ``ok``, ``doubtful`` or ``failed``, with the reasons in words.

Each analysis judges its own result against what the record itself shows (the
noise it carries, parameters at their bounds, residual structure, coherence and
band widths) and says so; the CLI prints the verdict beside the numbers, the JSON
carries ``verdict = {"level", "reasons"}``, the report's summary and the window show
it, and ``--strict`` makes a ``failed`` result exit with ``STRICT_EXIT``.

``doubtful``: the number may be right but the record cannot vouch for it (say what
would settle it); ``failed``: the number is not to be used.
"""
from __future__ import annotations

from collections.abc import Iterable
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
    level: str = OK
    reasons: tuple[str, ...] = ()

    def __post_init__(self):
        if self.level not in LEVELS:
            raise ValueError(f"verdict level {self.level!r} is not one of {', '.join(LEVELS)}")

    @property
    def failed(self) -> bool:
        return self.level == FAILED

    def as_dict(self) -> dict:
        return {"level": self.level, "reasons": list(self.reasons)}

    def line(self) -> str:
        """``ok`` or ``doubtful: reason; reason``."""
        return self.level if not self.reasons else f"{self.level}: {'; '.join(self.reasons)}"


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


def judge(findings: Iterable[tuple[str, str]]) -> Verdict:
    """The verdict of ``(level, reason)`` findings: the worst level; the reasons of every
    finding worse than ok, in order (an ``ok`` finding's reason is dropped)."""
    level, reasons = OK, []
    for lvl, reason in findings:
        if lvl not in LEVELS:
            raise ValueError(f"verdict level {lvl!r} is not one of {', '.join(LEVELS)}")
        if lvl != OK:
            reasons.append(reason)
            if LEVELS.index(lvl) > LEVELS.index(level):
                level = lvl
    return Verdict(level, tuple(reasons))


def worst(verdicts: Iterable[Verdict | None]) -> Verdict:
    """One verdict for several results: the worst level, every reason (Nones ignored)."""
    level, reasons = OK, []
    for v in verdicts:
        if v is not None:
            reasons.extend(v.reasons)
            level = max(level, v.level, key=LEVELS.index)
    return Verdict(level, tuple(reasons))


def from_dict(d) -> Verdict | None:
    """A recorded verdict back; None when ``d`` is not one (a session file's content is
    not trusted: unknown levels and non-string reasons are not taken)."""
    if not isinstance(d, dict) or d.get("level") not in LEVELS:
        return None
    reasons = d.get("reasons")
    if not isinstance(reasons, list):
        reasons = []
    return Verdict(d["level"], tuple(r for r in reasons[:MAX_REASONS] if isinstance(r, str)))


def strict_exit(verdicts: Iterable[Verdict | None], strict: bool) -> int:
    """The exit code a command returns after printing its results: ``STRICT_EXIT`` when
    ``strict`` and any verdict failed, else 0."""
    return STRICT_EXIT if strict and any(v is not None and v.failed for v in verdicts) else 0
