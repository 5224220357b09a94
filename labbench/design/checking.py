"""Predict, then measure: a design's predictions beside a campaign's measurements, in one
table and one figure (``labbench design --compare``, docs/design.md).

The campaigns of docs/examples/design-noise.toml (white-noise ETFE at one K over a grid of B
and w0: the rendered K and B, the force noise the loop commands) and design-zwidth.toml (the
stability probe over the same grid: K_max) run on the device; this module joins their rows by
(B, w0) and sets the design's numbers (``labbench.design.tradeoffs``, one model each) beside them: K_max,
rendered K and B, the command's force noise, and per w0 the Z-width under the noise limit,
measured (``labbench.design.tradeoffs.zwidth`` of the measured K_max and noise) and predicted (the same
rule on the predicted ones), with the w0 each finds best.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field


from labbench.design.tradeoffs import MODELS, Designer, zwidth
from labbench.errors import UserError

COLUMNS = (  # (key, heading, unit scale, unit)
    ("k_max", "K_max", 1.0, "N/m"),
    ("rendered_K", "rendered K", 1.0, "N/m"),
    ("rendered_B", "rendered B", 1.0, "N s/m"),
    ("noise", "force noise", 1e3, "mN"),
)


def _num(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) \
        and math.isfinite(v) else None


def _pair(row: dict, key: str) -> tuple[float | None, float | None]:
    """An interval of a row: a list under ``key``, or flattened by the sweep table into
    ``key.0`` and ``key.1``."""
    v = row.get(key)
    if isinstance(v, (list, tuple)) and len(v) == 2:
        return _num(v[0]), _num(v[1])
    return _num(row.get(f"{key}.0")), _num(row.get(f"{key}.1"))


@dataclass
class Row:
    """One (B, w0): ``predicted`` and ``measured`` values by ``COLUMNS`` key, with the
    measurement's 95 % interval in ``ci`` (None where the campaigns hold none)."""

    B: float
    w0: float
    predicted: dict = field(default_factory=dict)
    measured: dict = field(default_factory=dict)
    ci: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"B": self.B, "w0": self.w0, "predicted": self.predicted,
                "measured": self.measured, "ci95": {k: list(v) for k, v in self.ci.items()}}


@dataclass
class Check:
    """The whole comparison at one K and T on a device of damping ``b``: ``rows`` per
    (B, w0), the Z-width per w0 (``zwidth``: w0 ->
    {"predicted", "measured", "b_limit_predicted", "b_limit_measured"}), the best w0 of each,
    the grid step between them, and the models (``MODELS``)."""

    K: float
    T: float
    b: float
    noise_limit_n: float | None
    rows: list[Row]
    zwidth: dict
    best_predicted: float | None
    best_measured: float | None
    steps_apart: int | None
    models: dict

    def as_dict(self) -> dict:
        return {"K": self.K, "T": self.T, "b": self.b, "noise_limit_n": self.noise_limit_n,
                "rows": [r.as_dict() for r in self.rows],
                "zwidth": {str(k): v for k, v in self.zwidth.items()},
                "best_w0_predicted": self.best_predicted, "best_w0_measured": self.best_measured,
                "grid_steps_apart": self.steps_apart, "models": self.models}


def check(designer: Designer, campaign_rows: list[dict]) -> Check:
    """Join the campaigns' ``campaign_rows`` (dicts of a campaign table's columns; rows not
    ``ok`` are passed over) by (B, w0) and set the design's predictions beside them."""
    etfe = [r for r in campaign_rows if r.get("status") == "ok" and "res.force_noise.rms_n" in r
            and _num(r.get("res.force_noise.rms_n")) is not None]
    probe = [r for r in campaign_rows if r.get("status") == "ok" and "zw.k_max" in r]
    if not etfe and not probe:
        raise UserError("the tables hold no finished ETFE or stability-probe rows of a campaign "
                        "(docs/examples/design-noise.toml, design-zwidth.toml)")
    Ks = {_num(r.get("ve.K")) for r in etfe}
    if len(Ks) > 1:
        raise UserError(f"the ETFE rows render more than one K ({sorted(Ks)}): the noise of "
                        "one design is read at one K")
    K = Ks.pop() if Ks else 50.0
    Ts = {_num(r.get("rig.sample_time_s")) for r in etfe + probe}
    if len(Ts) > 1:
        raise UserError(f"the rows ran at more than one sample time ({sorted(Ts)})")
    T = Ts.pop()
    by = {}
    for r, is_etfe in [(r, True) for r in etfe] + [(r, False) for r in probe]:
        key = (_num(r.get("ve.B")), _num(r.get("ve.w0_rad_s")))
        if None in key:
            continue
        row = by.setdefault(key, Row(*key))
        if is_etfe:
            fn = _num(r.get("res.force_noise.rms_n"))
            row.measured.update(noise=fn, rendered_K=_num(r.get("res.rendered.K")),
                                rendered_B=_num(r.get("res.rendered.B")))
            row.ci.update(noise=_pair(r, "res.force_noise.ci95"),
                          rendered_K=_pair(r, "res.rendered.K_ci95"),
                          rendered_B=_pair(r, "res.rendered.B_ci95"))
        else:
            row.measured["k_max"] = _num(r.get("zw.k_max"))
            row.ci["k_max"] = (_num(r.get("zw.ci_lo")), _num(r.get("zw.ci_hi")))
    rows = sorted(by.values(), key=lambda r: (r.w0, r.B))
    for row in rows:
        p = designer.evaluate(K, row.B, row.w0, T)
        row.predicted = {"k_max": p.k_max, "rendered_K": p.rendered_K, "rendered_B": p.rendered_B,
                         "noise": p.noise_command}
    zw, best_p, best_m, apart = _zwidths(rows, designer.targets.noise_limit_n)
    models = {"k_max": MODELS["k_max"], "rendered_K": MODELS["rendered_K"],
              "rendered_B": MODELS["rendered_B"], "noise": MODELS["noise_command"],
              "zwidth": MODELS["zwidth"]}
    return Check(K, T, designer.device.plant.b, designer.targets.noise_limit_n, rows, zw,
                 best_p, best_m, apart, models)


def _zwidths(rows: list[Row], limit):
    """Per w0 with K_max and noise measured at every B: the Z-width both ways, each w0's
    best, and how many grid steps of w0 lie between the two bests."""
    out = {}
    for w0 in sorted({r.w0 for r in rows}):
        grp = sorted((r for r in rows if r.w0 == w0), key=lambda r: r.B)
        meas = [(r.measured.get("k_max"), r.measured.get("noise")) for r in grp]
        if len(grp) < 2 or any(k is None or n is None for k, n in meas):
            continue
        Bs = [r.B for r in grp]
        pa, pb = zwidth(Bs, [r.predicted["k_max"] for r in grp],
                        [r.predicted["noise"] if r.predicted["noise"] is not None else math.inf
                         for r in grp], limit)
        ma, mb = zwidth(Bs, [k for k, _ in meas], [n for _, n in meas], limit)
        out[w0] = {"predicted": pa, "measured": ma, "b_limit_predicted": pb,
                   "b_limit_measured": mb}
    if not out:
        return out, None, None, None
    grid = sorted(out)
    best_p = max(grid, key=lambda w: out[w]["predicted"])
    best_m = max(grid, key=lambda w: out[w]["measured"])
    return out, best_p, best_m, abs(grid.index(best_p) - grid.index(best_m))


def table_lines(c: Check) -> list[str]:
    """The comparison as text: one line per (B, w0), then the Z-width per w0."""
    from labbench.readout.numfmt import fmt

    head = f"{'w0 rad/s':>9} {'B N s/m':>8}"
    for _, name, _, unit in COLUMNS:
        head += f" | {name + ' (' + unit + ')':>31}"
    lines = [f"Predicted vs measured at K = {fmt(c.K)} N/m, T = {fmt(c.T)} s "
             "(predicted / measured [95 % interval])", head]
    for r in c.rows:
        line = f"{fmt(r.w0):>9} {fmt(r.B):>8}"
        for key, _, scale, _ in COLUMNS:
            p, m = r.predicted.get(key), r.measured.get(key)
            lo, hi = r.ci.get(key, (None, None))
            cell = f"{_s(p, scale)} / {_s(m, scale)}"
            if lo is not None and hi is not None:
                cell += f" [{_s(lo, scale)}, {_s(hi, scale)}]"
            line += f" | {cell:>31}"
        lines.append(line)
    if c.zwidth:
        limit = "no noise limit" if c.noise_limit_n is None else \
            f"command noise within {fmt(1e3 * c.noise_limit_n)} mN"
        lines += ["", f"Z-width under the noise limit ({limit}; N^2 s/m^2): predicted / measured"]
        for w0, z in c.zwidth.items():
            mark = "".join([" <- predicted best" if w0 == c.best_predicted else "",
                            " <- measured best" if w0 == c.best_measured else ""])
            lines.append(f"  w0 {fmt(w0):>6} rad/s: {fmt(z['predicted']):>8} / "
                         f"{fmt(z['measured']):>8}  (B up to {fmt(z['b_limit_predicted'])} / "
                         f"{fmt(z['b_limit_measured'])} N s/m){mark}")
        lines.append(f"best w0: predicted {fmt(c.best_predicted)}, measured "
                     f"{fmt(c.best_measured)} rad/s ({c.steps_apart} grid step(s) apart)")
    return lines


def _s(v, scale) -> str:
    from labbench.readout.numfmt import fmt

    return "-" if v is None else fmt(v * scale, 4)
