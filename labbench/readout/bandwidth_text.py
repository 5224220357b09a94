"""A bandwidth and its prediction as one line of text, in the display units."""
from __future__ import annotations

import math

from labbench.model import predictions
from labbench.readout.numfmt import fmt
from labbench.readout.units import SI


def predicted_text(which: str, bw: predictions.Bandwidths, unit=None, digits: int = 4) -> str:
    """``sampled theory 72.57 rad/s; paper w0: 125``: the prediction, the closed form
    labelled beside it. ``unit``: ``labbench.readout.units.DisplayUnits`` (None: SI, rad/s)."""
    unit = unit if unit is not None else SI
    text = f"{bw.model} theory {_shown(bw.predicted(which), unit, digits)} {unit.frequency}"
    closed = bw.closed_form(which)
    if closed is not None and math.isfinite(closed):
        text += f"; {predictions.CLOSED_FORM[which]}: {_shown(closed, unit, digits)}"
    return text


def label(which: str, measured: float | None, bw: predictions.Bandwidths | None, unit=None,
          digits: int = 4) -> str:
    """One line for a measured bandwidth and its prediction: ``w_s* = 24.07 rad/s
    (sampled theory 24.07 rad/s; paper eq. 5: 23.06)``; ``bw`` None: measured only."""
    unit = unit if unit is not None else SI
    text = f"{predictions.SYMBOLS[which]} = {_shown(measured, unit, digits)} {unit.frequency}"
    return text if bw is None else f"{text} ({predicted_text(which, bw, unit, digits)})"


def _shown(v, unit, digits: int) -> str:
    return fmt(unit.frequency_of(v), digits)
