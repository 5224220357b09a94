"""Numbers for people: the one formatter of the CLI, the report and the GUI."""
from __future__ import annotations

import math

import numpy as np


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
