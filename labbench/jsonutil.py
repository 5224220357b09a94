"""JSON for records, results and the CLI: strict (no NaN/Infinity), numpy-aware."""
from __future__ import annotations

import math

import numpy as np


def json_safe(obj):
    """numpy arrays/scalars -> lists/floats, non-finite floats -> None (strict JSON)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj
