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
