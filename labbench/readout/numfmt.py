"""Numbers for people: the one formatter of the CLI, the report and the window.

``fmt`` writes a bare number to a few significant digits. ``fmt_ci`` writes a value with its
95 % interval to the digits the interval supports (the usual rule of metrology, GUM
JCGM 100:2008 sec. 7.2.6: the uncertainty to two significant digits, the value to the same
decimal place); an interval narrower than ``EXACT_REL`` of the number's scale is not
12 digits of noise but "exact to the model's precision". ``band_text`` writes a frequency
band in the display units.
"""
from __future__ import annotations

import math
import re

import numpy as np

# An interval this narrow relative to its number's scale says the data are the model's own
# (a noise-free simulator): more digits would be floating-point noise, not information.
EXACT_REL = 1e-6
EXACT = "exact to the model's precision"


def fmt(v, digits: int = 4) -> str:
    """``digits`` significant digits; rounding noise below 1e-12 shows as 0; None as a
    dash; booleans as yes/no; lists in brackets; dicts as key=value."""
    if v is None:
        return "-"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(v):
            return str(float(v))
        return f"{round(float(v), 12) + 0.0:.{digits}g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(fmt(x, digits) for x in v) + "]"
    if isinstance(v, dict):
        return ", ".join(f"{k}={fmt(x, digits)}" for k, x in v.items())
    return str(v)


def _finite(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) \
        and math.isfinite(x)


def at_place(values, place: int) -> list[str]:
    """Each of ``values`` rounded to the decimal ``place`` (10**place): plainly when that is
    short, else all in scientific notation with one exponent (the largest's), so they line up."""
    xs = [round(float(x), -place) + 0.0 for x in values]
    top = max(abs(x) for x in xs)
    if -10 <= place < 0 and top < 1e7:
        return [f"{x:.{-place}f}" for x in xs]
    if 0 <= place and top < 1e9:
        return [f"{x:.0f}" for x in xs]
    e = math.floor(math.log10(top)) if top else place
    return [f"{x / 10.0**e:.{max(e - place, 0)}f}e{e:+03d}" for x in xs]


def fmt_ci(value, lo=None, hi=None, unit: str = "", scale=None, digits: int = 4) -> str:
    """``200.3 N/m (199.1 to 201.5)``: ``value`` and its interval ``lo``-``hi`` to the
    digits the interval supports (two significant digits of its larger half-width);
    ``0.094 kg (exact to the model's precision)`` when the half-width is below ``EXACT_REL``
    of ``scale`` (default: the value itself); no interval: ``fmt`` to ``digits``."""
    u = f" {unit}" if unit else ""
    if not _finite(value):
        return fmt(value) + (u if value is not None else "")
    if not (_finite(lo) and _finite(hi)):
        return fmt(value, digits) + u
    half = max(value - lo, hi - value, 0.0)
    ref = abs(scale) if _finite(scale) and scale else max(abs(value), abs(lo), abs(hi))
    if ref == 0 or half <= EXACT_REL * ref:
        place = math.floor(math.log10(EXACT_REL * ref)) if ref else 0
        return f"{fmt(round(float(value), -place), 6)}{u} ({EXACT})"
    v, a, b = at_place((value, lo, hi), math.floor(math.log10(half)) - 1)
    return f"{v}{u} ({a} to {b})"


def digits_beside(value, lo, hi, other) -> int:
    """Significant digits that write ``other`` to the decimal place ``fmt_ci`` writes
    ``value`` with its interval ``lo``-``hi`` (at least 4): a prediction beside a measurement
    ("exact sampled: 200 N/m" beside "measured: 200.0355 N/m (200.0345 to 200.0365)" read as
    0.018 % apart where the two differ by 3e-7)."""
    if not all(_finite(x) for x in (value, lo, hi, other)) or other == 0:
        return 4
    half = max(value - lo, hi - value, 0.0)
    if half <= EXACT_REL * max(abs(value), abs(lo), abs(hi)):
        return 4
    place = math.floor(math.log10(half)) - 1
    return max(4, math.floor(math.log10(abs(other))) - place + 1)


def plain(x: float, digits: int = 3) -> str:
    """``x`` to ``digits`` significant digits without an exponent (3120, 0.367)."""
    if not _finite(x) or x == 0:
        return fmt(x)
    place = math.floor(math.log10(abs(x))) - digits + 1
    return at_place((x,), place)[0].rstrip("0").rstrip(".") if -10 < place < 0 else \
        at_place((x,), place)[0] if place >= 0 else fmt(x, digits)


def band_text(band, units=None) -> str:
    """``2-3120 rad/s`` (or in Hz with ``units.frequency`` = Hz): three significant digits."""
    units = _units(units)
    lo, hi = (units.frequency_of(b) for b in band)
    return f"{plain(lo)}-{plain(hi)} {units.frequency}"


def frequency_text(w: float, units=None) -> str:
    """``42.7 rad/s`` (or in Hz), as ``band_text`` writes a band's edges."""
    units = _units(units)
    return f"{plain(units.frequency_of(w))} {units.frequency}"


_NUM = r"\d+(?:\.\d+)?(?:e[+-]?\d+)?"
_SPAN = rf"{_NUM}(?:-{_NUM})?"
# "2.09-6.81, 40-50 and 2 more rad/s", "between 1 and 1571 rad/s", "42.7 rad/s"
_FREQUENCIES = re.compile(rf"(?<![\w.])(between {_NUM} and {_NUM}|{_SPAN}(?:, {_SPAN})*)"
                          rf"(?P<more> and \d+ more)? rad/s\b")


def frequencies_in(text: str, units=None) -> str:
    """``text`` (a verdict's reason or note, a readout's row) with every frequency written
    in rad/s in the display units: "leakage at 2.09-6.81 rad/s" -> "at 0.333-1.08 Hz"."""
    units = _units(units)
    if units.frequency == "rad/s" or "rad/s" not in text:
        return text

    def convert(m):
        numbers = re.sub(_NUM, lambda n: plain(units.frequency_of(float(n.group()))), m.group(1))
        return f"{numbers}{m.group('more') or ''} {units.frequency}"

    return _FREQUENCIES.sub(convert, text)


def _units(units):
    if units is None:
        from labbench.readout.units import SI as units
    return units
