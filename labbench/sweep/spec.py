"""Sweep specs: a TOML file naming what varies, read into the list of points to compute.

```toml
[sweep]
name = "stability map"      # free text
kind = "run"                # "run": a protocol on a simulator through labbench.runner (default);
                            # "analysis": an analysis of an exact record (labbench.sweep.exact)
protocol = "stability"      # kind run: a registered protocol (labbench.registry)
device = "sim"              # kind run: a simulated backend (default sim)
analysis = "etfe"           # kind analysis: "etfe" or "identify"
record = "closed-loop"      # kind analysis: "closed-loop" (etfe) or "chirp" (identify)
sample = "grid"             # "grid" (default), "random" or "lhs" (Latin hypercube) over [ranges]
points = 200                # random / lhs: how many samples
sample_seed = 0             # random / lhs: which ones
repeat = 1                  # kind analysis: the analysis time is the best of this many

[fixed]                     # the same for every point
ratio = 1.05

[grid]                      # every combination of these values
td_s = [0.0, 0.001, 0.002]

[[cases.ve]]                # a case group: an axis whose values are sets of parameters;
label = "spring"            # "label" becomes the value of a column named after the group
ve = "spring"

[ranges]                    # random / lhs: a range {lo, hi[, log][, integer]} or a list of choices
K = { lo = 10.0, hi = 1000.0, log = true }

[[chart]]                   # charts drawn from the table (labbench.sweep.charts)
kind = "map"
x = "td_s"
y = "K"
```

Points are the product of the grid axes and case groups, in the order they are
written, crossed with the ``points`` samples of ``[ranges]`` (random or lhs).
A point is its parameters; its key is a hash of the spec's kind, target and
those parameters (never of its position in the list), so a rerun, a grown grid
or another order finds the points already in a table.
"""
from __future__ import annotations

import hashlib
import json
import math
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from itertools import product
from pathlib import Path

import numpy as np

from labbench.errors import UserError, unknown_name
from labbench.input_files import read_text

KINDS = ("run", "analysis")
SAMPLES = ("grid", "random", "lhs")
ANALYSES = {"etfe": "closed-loop", "identify": "chirp"}  # analysis -> the record it reads
TABLES = ("sweep", "fixed", "grid", "cases", "ranges", "chart")
SWEEP_KEYS = ("name", "kind", "protocol", "device", "analysis", "record", "sample", "points",
              "sample_seed", "repeat")
MAX_POINTS = 1_000_000
MAX_SPEC_BYTES = 1 << 20
MAX_REPEAT = 100


@dataclass(frozen=True)
class Point:
    """One point of a sweep: its place in the spec's order, its tags (case labels) and the
    parameters it runs with."""

    index: int
    params: dict
    tags: dict = field(default_factory=dict)

    def key(self, spec: "Spec") -> str:
        return point_key(spec.target, self.params, self.tags)


@dataclass(frozen=True)
class Spec:
    name: str
    kind: str
    protocol: str | None
    device: str
    analysis: str | None
    sample: str
    n_samples: int
    sample_seed: int
    repeat: int
    fixed: dict
    grid: dict  # name -> list of values
    cases: dict  # group -> list of (label, params)
    ranges: dict  # name -> {"lo", "hi", "log", "integer"} or {"choices": [...]}
    charts: list
    source: str = "<dict>"

    @property
    def target(self) -> dict:
        """What every point runs: the part of the spec its key depends on besides its params."""
        if self.kind == "run":
            return {"kind": "run", "protocol": self.protocol, "device": self.device}
        return {"kind": "analysis", "analysis": self.analysis}

    def as_dict(self) -> dict:
        """The spec as plain data (what a worker is sent; ``spec_from_dict`` reads it back)."""
        sweep = {"name": self.name, **self.target, "sample": self.sample,
                 "sample_seed": self.sample_seed}
        if self.kind == "analysis":
            sweep["repeat"] = self.repeat
        if self.sample != "grid":
            sweep["points"] = self.n_samples
        return {"sweep": sweep,
                "fixed": self.fixed, "grid": self.grid,
                "cases": {g: [{"label": lab, **p} for lab, p in v] for g, v in self.cases.items()},
                "ranges": {k: r.get("choices", r) for k, r in self.ranges.items()},
                "chart": self.charts}

    def points(self) -> list[Point]:
        """Every point, in the spec's order (see the module doc), as a list."""
        return list(self.iter_points())

    def iter_points(self) -> Iterator[Point]:
        """Every point, in the spec's order, made as it is asked for: a 10^6-point spec
        starts at once in little memory (the list took 22 s and 800 MB)."""
        axes = [[({}, {name: v}) for v in values] for name, values in self.grid.items()]
        axes += [[({group: label}, params) for label, params in cases]
                 for group, cases in self.cases.items()]
        draws = _Draws(self.ranges, self.n_samples, self.sample, self.sample_seed)
        index = 0
        for combo in product(*axes):
            for draw in draws:
                params, tags = dict(self.fixed), {}
                for t, p in combo:
                    tags.update(t)
                    params.update(p)
                params.update(draw)
                yield Point(index, params, tags)
                index += 1

    def name_samples(self) -> Iterator[Point]:
        """One point of every distinct set of parameter names, without enumerating the
        points: only the case groups make the names differ."""
        grid = {name: values[0] for name, values in self.grid.items()}
        draw = next(iter(_Draws(self.ranges, self.n_samples, self.sample, self.sample_seed)))
        shapes = []  # per case group: its first case of each distinct set of names
        for group, cases in self.cases.items():
            first = {}
            for label, params in cases:
                first.setdefault(frozenset(params), (group, label, params))
            shapes.append(list(first.values()))
        for combo in product(*shapes):
            params, tags = {**self.fixed, **grid}, {}
            for group, label, p in combo:
                tags[group] = label
                params.update(p)
            yield Point(0, {**params, **draw}, tags)

    def count(self) -> int:
        n = max(self.n_samples, 1) if self.sample != "grid" else 1
        for values in self.grid.values():
            n *= len(values)
        for cases in self.cases.values():
            n *= len(cases)
        return n


def point_key(target: dict, params: dict, tags: dict) -> str:
    """16 hex digits of the SHA-256 of the canonical JSON of target, params and tags (numbers
    as floats, so 50 and 50.0 are one point)."""
    body = json.dumps({"target": target, "params": _canonical(params), "tags": tags},
                      sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(body.encode()).hexdigest()[:16]


def _canonical(params: dict) -> dict:
    return {k: float(v) if isinstance(v, int) and not isinstance(v, bool) else v
            for k, v in params.items()}


def load_spec(path) -> Spec:
    """Read and validate a spec file (a regular file of at most 1 MiB)."""
    p = Path(path)
    text = read_text(p, "sweep spec", MAX_SPEC_BYTES)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{p}: not valid TOML: {exc}") from None
    except RecursionError:
        raise UserError(f"{p}: not valid TOML: nested too deeply") from None
    return spec_from_dict(data, source=str(p))


def spec_from_dict(d: dict, source: str = "<dict>") -> Spec:
    """Validate a parsed spec; one UserError naming the file and the field."""
    if not isinstance(d, dict):
        raise UserError(f"{source}: a spec is a table")
    if "campaign" in d:  # the _spec.json of a table labbench campaign wrote
        c = d["campaign"]
        device = c.get("device") if isinstance(c, dict) else None
        raise UserError(f"{source}: a campaign's table: its points ran on {device or 'a device'} "
                        "one after another; run them again with labbench campaign "
                        "(docs/campaign.md)")
    for k in d:
        if k not in TABLES:
            raise UserError(f"{source}: {unknown_name('table', k, TABLES)}")
    sw = _table(d, "sweep", source)
    for k in sw:
        if k not in SWEEP_KEYS:
            raise UserError(f"{source}: [sweep] {unknown_name('field', k, SWEEP_KEYS)}")
    kind = _choice(sw.get("kind", "run"), KINDS, f"{source}: [sweep] kind")
    protocol = device = analysis = None
    if kind == "run":
        from labbench.registry import device_names, protocol_names

        if "protocol" not in sw:
            raise UserError(f"{source}: [sweep] protocol is missing (kind run: one of "
                            f"{', '.join(protocol_names())})")
        protocol = _choice(sw["protocol"], tuple(protocol_names()), f"{source}: [sweep] protocol")
        sims = tuple(n for n in device_names() if n.startswith("sim") or n.endswith("-sim"))
        device = _choice(sw.get("device", "sim"), sims,
                         f"{source}: [sweep] device (a sweep runs simulators only)")
        for k in ("analysis", "record", "repeat"):
            if k in sw:
                raise UserError(f"{source}: [sweep] {k} is for kind analysis")
    else:
        analysis = _choice(sw.get("analysis"), tuple(ANALYSES), f"{source}: [sweep] analysis")
        record = sw.get("record", ANALYSES[analysis])
        if record != ANALYSES[analysis]:
            raise UserError(f"{source}: [sweep] record: analysis {analysis} reads a "
                            f"{ANALYSES[analysis]!r} record, got {record!r}")
        for k in ("protocol", "device"):
            if k in sw:
                raise UserError(f"{source}: [sweep] {k} is for kind run")
    name = sw.get("name", Path(source).stem)
    if not isinstance(name, str) or len(name) > 200:
        raise UserError(f"{source}: [sweep] name must be text of at most 200 characters")
    sample = _choice(sw.get("sample", "grid"), SAMPLES, f"{source}: [sweep] sample")
    n_samples = _whole(sw.get("points", 0 if sample == "grid" else None), f"{source}: [sweep] points",
                       0 if sample == "grid" else 1, MAX_POINTS)
    if sample == "grid" and n_samples:
        raise UserError(f"{source}: [sweep] points is for sample random or lhs")
    sample_seed = _whole(sw.get("sample_seed", 0), f"{source}: [sweep] sample_seed", 0, 2**63 - 1)
    repeat = _whole(sw.get("repeat", 1), f"{source}: [sweep] repeat", 1, MAX_REPEAT)

    fixed = _params(_table(d, "fixed", source), f"{source}: [fixed]")
    grid = {}
    for k, v in _table(d, "grid", source).items():
        if not isinstance(v, list) or not v:
            raise UserError(f"{source}: [grid] {k} must be a non-empty list of values")
        grid[k] = [_scalar(x, f"{source}: [grid] {k}") for x in v]
        if len(set(map(_hashable, grid[k]))) != len(grid[k]):
            raise UserError(f"{source}: [grid] {k} lists a value twice")
    cases = {}
    for group, items in _table(d, "cases", source).items():
        where = f"{source}: [[cases.{group}]]"
        if not isinstance(items, list) or not items or not all(isinstance(c, dict) for c in items):
            raise UserError(f"{where} must be a list of tables")
        got = []
        for i, c in enumerate(items):
            c = dict(c)
            label = c.pop("label", str(i))
            if not isinstance(label, str):
                raise UserError(f"{where} label must be text, got {label!r}")
            got.append((label, _params(c, f"{where} {label!r}")))
        labels = [lab for lab, _ in got]
        if len(set(labels)) != len(labels):
            raise UserError(f"{where}: two cases have the same label")
        cases[group] = got
    ranges = {k: _range(v, f"{source}: [ranges] {k}") for k, v in _table(d, "ranges", source).items()}
    if sample == "grid" and ranges:
        raise UserError(f"{source}: [ranges] needs sample = \"random\" or \"lhs\"")
    if sample != "grid" and not ranges:
        raise UserError(f"{source}: sample {sample} needs a [ranges] table")
    _no_clash(source, fixed, grid, cases, ranges)
    charts = d.get("chart", [])
    if not isinstance(charts, list) or not all(isinstance(c, dict) for c in charts):
        raise UserError(f"{source}: [[chart]] must be a list of tables")
    spec = Spec(name, kind, protocol, device or "sim", analysis, sample, n_samples, sample_seed,
                repeat, fixed, grid, cases, ranges, charts, source)
    if spec.count() > MAX_POINTS:
        raise UserError(f"{source}: {spec.count()} points; at most {MAX_POINTS} in one sweep")
    from labbench.sweep.charts import check_chart

    for c in charts:
        check_chart(c, f"{source}: [[chart]]")
    return spec


def _table(d: dict, name: str, source: str) -> dict:
    v = d.get(name, {})
    if not isinstance(v, dict):
        raise UserError(f"{source}: [{name}] must be a table")
    return v


def _choice(v, options: tuple, where: str) -> str:
    if v not in options:
        raise UserError(f"{where} must be one of {', '.join(options)}, got {v!r}")
    return v


def _whole(v, where: str, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise UserError(f"{where} must be a whole number in [{lo}, {hi}], got {v!r}")
    return v


def _scalar(v, where: str):
    if isinstance(v, float) and not math.isfinite(v):
        raise UserError(f"{where}: {v!r} is not a finite number")
    if isinstance(v, (bool, int, float, str)):
        return v
    raise UserError(f"{where}: values are numbers, true/false or text, got {v!r}")


def _hashable(v):
    return (type(v) is bool, v)


def _params(t: dict, where: str) -> dict:
    return {k: _scalar(v, f"{where} {k}") for k, v in t.items()}


def _range(v, where: str) -> dict:
    if isinstance(v, list):
        if not v:
            raise UserError(f"{where}: an empty list of choices")
        return {"choices": [_scalar(x, where) for x in v]}
    if not isinstance(v, dict):
        raise UserError(f"{where} must be {{lo, hi[, log][, integer]}} or a list of choices")
    for k in v:
        if k not in ("lo", "hi", "log", "integer"):
            raise UserError(f"{where}: {unknown_name('field', k, ('lo', 'hi', 'log', 'integer'))}")
    lo, hi = v.get("lo"), v.get("hi")
    for name, x in (("lo", lo), ("hi", hi)):
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise UserError(f"{where}: {name} must be a finite number, got {x!r}")
    log, integer = v.get("log", False), v.get("integer", False)
    if not isinstance(log, bool) or not isinstance(integer, bool):
        raise UserError(f"{where}: log and integer are true or false")
    if not lo < hi:
        raise UserError(f"{where}: lo ({lo:g}) must be below hi ({hi:g})")
    if log and lo <= 0:
        raise UserError(f"{where}: a log range needs lo > 0, got {lo:g}")
    return {"lo": float(lo), "hi": float(hi), "log": log, "integer": integer}


def _no_clash(source: str, fixed: dict, grid: dict, cases: dict, ranges: dict) -> None:
    """A parameter is set in one place only (fixed, one grid axis, one case group, a range)."""
    seen = {k: "[fixed]" for k in fixed}
    for name, where in ([(k, "[grid]") for k in grid] + [(k, "[ranges]") for k in ranges]):
        if name in seen:
            raise UserError(f"{source}: {name} is set in both {seen[name]} and {where}")
        seen[name] = where
    for group, items in cases.items():
        keys = {k for _, p in items for k in p}
        if group in seen or group in keys:
            raise UserError(f"{source}: case group {group!r} has the name of a parameter")
        for k in keys:
            if k in seen:
                raise UserError(f"{source}: {k} is set in both {seen[k]} and [[cases.{group}]]")
            seen[k] = f"[[cases.{group}]]"


class _Draws:
    """The sampled part of each point: one empty draw for a grid; else ``n`` draws, uniform
    (random) or one per stratum of every range (lhs: McKay, Beckman & Conover 1979). The
    uniform numbers are drawn at once (8 bytes a draw and range), the draws made from them
    as they are asked for, as often as asked."""

    def __init__(self, ranges: dict, n: int, sample: str, seed: int):
        self.columns = []
        self.grid = sample == "grid"
        if self.grid:
            return
        rng = np.random.default_rng(seed)
        for name, r in ranges.items():  # one stream per range, in the spec's order
            u = rng.random(n)
            if sample == "lhs":
                u = (rng.permutation(n) + u) / n
            self.columns.append((name, r, u))
        self.n = n

    def __iter__(self) -> Iterator[dict]:
        if self.grid:
            yield {}
            return
        for i in range(self.n):
            yield {name: _value(r, float(u[i])) for name, r, u in self.columns}


def _value(r: dict, u: float):
    if "choices" in r:
        c = r["choices"]
        return c[min(int(u * len(c)), len(c) - 1)]
    lo, hi = r["lo"], r["hi"]
    v = math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))) if r["log"] else lo + u * (hi - lo)
    return int(min(max(round(v), math.ceil(lo)), math.floor(hi))) if r["integer"] else v
