"""The JSON shapes the report reads from a session's records, enforced once at load.

A session file with valid checksums can still carry a field of the wrong type (a
buggy or hostile writer: a string where the pre-check object is due, a number
where a list of counts is). The session reader checks the records' top-level
fields; the report reads deeper, so ``conform`` walks the paths it reads and
leaves out what does not have the shape it needs, saying so
(``ReportSession.malformed``, a flag on page 1), instead of raising somewhere in
a table.

A shape is ``NUMBER``, ``OPTIONAL`` (a number or null: a fit that gave none),
``INT`` (or null), ``INTS``/``NUMBERS`` (lists of them), ``list`` or
``dict`` (any contents), ``{key: shape}`` (an object; the keys listed are checked
when present, ``"*"`` stands for every key) or ``[shape]`` (a list, each element
checked).
"""
from __future__ import annotations

NUMBER, OPTIONAL, INT = "number", "number or null", "integer or null"
INTS, NUMBERS = [INT], [NUMBER]

_PLANT = {"m": NUMBER, "b": NUMBER}  # a model to compute with: both numbers
_FIT = {"m": OPTIONAL, "b": OPTIONAL, "coulomb": OPTIONAL, "ci95": {"*": list}, "flags": list,
        "selection": dict, "rms_residual": OPTIONAL, "explained": NUMBER}
START = {
    "rig": {"sections": {"*": dict}, "sample_time_s": NUMBER},
    "device": {"details": dict},
    "plant": _PLANT,
    "precheck": {"plant": _PLANT, "checks": [{"ve": dict, "k_max": OPTIONAL,
                                             "k_max_approx": OPTIONAL}]},
    "safety": dict,
}
_REALTIME = {"affinity": INTS, "refused": list, "unavailable": list, "priority": INT}
STOP = {
    "timing": {"T_s": OPTIONAL, "histogram": {"edges_T": NUMBERS, "counts": INTS},
               "worst": dict, "realtime": _REALTIME, "overruns": INT},
    "results": {"plant": _PLANT, "identification": {"*": _FIT}, "etfe": dict,
                "loop_fit": dict, "theory": dict, "bandwidths": dict},
}


def _is(value, leaf: str) -> bool:
    if value is None:
        return leaf != NUMBER
    if isinstance(value, bool):
        return False
    if leaf in (NUMBER, OPTIONAL):
        return isinstance(value, (int, float))
    if leaf == INT:
        return isinstance(value, int)
    return isinstance(value, str)


def _kind(shape) -> str:
    if isinstance(shape, dict) or shape is dict:
        return "an object"
    if isinstance(shape, list) or shape is list:
        return "a list"
    return f"a {shape}"


def _fits(value, shape) -> bool:
    if shape is dict or isinstance(shape, dict):
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
            sub = shape.get(key, shape.get("*"))
            if sub is None:
                continue
            if not _fits(item, sub):
                problems.append(f"{where}.{key}: {type(item).__name__} where {_kind(sub)} is due")
                del out[key]
            else:
                out[key] = conform(item, sub, f"{where}.{key}", problems)
        return out
    if isinstance(shape, list):
        (element,) = shape
        kept = [conform(v, element, f"{where}[{i}]", problems)
                for i, v in enumerate(value) if _fits(v, element)]
        if len(kept) < len(value):
            problems.append(f"{where}: {len(value) - len(kept)} element(s) not {_kind(element)}")
        return kept
    return value
