"""The JSON shapes the report reads from a session's records, enforced once at load.

A session file with valid checksums can still carry a field of the wrong type (a
buggy or hostile writer: a string where the pre-check object is due, a number
where a list of counts is). The session reader checks the records' top-level
fields; the report reads deeper, so ``conform`` walks the paths it reads and
leaves out what does not have the shape it needs, saying so
(``ReportSession.malformed``, a flag on page 1), instead of raising somewhere in
a table.

A shape is ``NUMBER``, ``OPTIONAL`` (a number or null: a fit that gave none),
``INT`` (or null), ``COUNT`` (a whole number, never null), ``TEXT`` (or null),
``INTERVAL`` (a list of two numbers or nulls), ``INTS``/``NUMBERS`` (lists of them),
``list`` or ``dict`` (any contents), ``{key: shape}`` (an object; the keys listed are
checked when present, ``"*"`` stands for every key, and the keys named under
``REQUIRED`` must be there: an object without one does not fit) or ``[shape]`` (a list,
each element checked).
"""
from __future__ import annotations

NUMBER, OPTIONAL, INT = "number", "number or null", "integer or null"
COUNT, TEXT, INTERVAL = "whole number", "text or null", "interval [lo, hi]"
INTS, NUMBERS = [INT], [NUMBER]
REQUIRED = "required keys"  # in an object's shape: the keys it cannot do without

_PLANT = {"m": NUMBER, "b": NUMBER}  # a model to compute with: both numbers
_FIT = {"m": OPTIONAL, "b": OPTIONAL, "coulomb": OPTIONAL, "ci95": {"*": INTERVAL},
        "flags": list, "selection": dict, "rms_residual": OPTIONAL, "explained": NUMBER,
        "model": TEXT}
_VE = {REQUIRED: ("kind",), "kind": TEXT, "K": NUMBER, "B": NUMBER, "w0": OPTIONAL,
       "T": NUMBER, "td": NUMBER}
START = {
    "rig": {"sections": {"*": dict}, "sample_time_s": NUMBER},
    "device": {"details": dict},
    "plant": _PLANT,
    "precheck": {"plant": _PLANT, "checks": [{REQUIRED: ("ve",), "ve": _VE,
                                             "k_max": OPTIONAL, "k_max_approx": OPTIONAL}]},
    "safety": dict,
}
_REALTIME = {"affinity": INTS, "refused": list, "unavailable": list, "priority": INT}
STOP = {
    "timing": {"T_s": OPTIONAL, "histogram": {"edges_T": NUMBERS, "counts": [COUNT]},
               "worst": dict, "realtime": _REALTIME, "overruns": INT},
    "results": {"plant": _PLANT, "identification": {"*": _FIT}, "etfe": dict,
                "loop_fit": dict, "theory": dict, "bandwidths": dict},
}


def _is(value, leaf: str) -> bool:
    if value is None:
        return leaf not in (NUMBER, COUNT, INTERVAL)
    if isinstance(value, bool):
        return False
    if leaf in (NUMBER, OPTIONAL):
        return isinstance(value, (int, float))
    if leaf in (INT, COUNT):
        return isinstance(value, int)
    if leaf == INTERVAL:
        return isinstance(value, list) and len(value) == 2 and all(_is(v, OPTIONAL) for v in value)
    return isinstance(value, str)


def _kind(shape) -> str:
    if isinstance(shape, dict) and shape.get(REQUIRED):
        return f"an object with {', '.join(shape[REQUIRED])}"
    if isinstance(shape, dict) or shape is dict:
        return "an object"
    if isinstance(shape, list) or shape is list:
        return "a list"
    return f"a {shape}"


def _fits(value, shape) -> bool:
    if isinstance(shape, dict):
        return isinstance(value, dict) and all(k in value for k in shape.get(REQUIRED, ()))
    if shape is dict:
        return isinstance(value, dict)
    if shape is list or isinstance(shape, list):
        return isinstance(value, list)
    return _is(value, shape)


def conform(value, shape, where: str, problems: list[str]):
    """``value`` less what does not fit ``shape`` (a copy where changed); each part left
    out is named in ``problems`` (``where`` the path so far)."""
    if isinstance(shape, dict):
        out = dict(value)
        for key, item in list(out.items()):
            sub = shape.get(key, shape.get("*")) if key != REQUIRED else None
            if sub is None:
                continue
            if _fits(item, sub):
                item = conform(item, sub, f"{where}.{key}", problems)
            if _fits(item, sub):  # again: a required key of the wrong shape is left out
                out[key] = item
            else:
                problems.append(f"{where}.{key}: {type(item).__name__} where {_kind(sub)} is due")
                del out[key]
        return out
    if isinstance(shape, list):
        (element,) = shape
        kept = [c for i, v in enumerate(value) if _fits(v, element)
                and _fits(c := conform(v, element, f"{where}[{i}]", problems), element)]
        if len(kept) < len(value):
            problems.append(f"{where}: {len(value) - len(kept)} element(s) not {_kind(element)}")
        return kept
    return value
