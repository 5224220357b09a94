"""The campaign's own charts, drawn from its table: the Z-width and the rate-vs-accuracy chart.

Matplotlib's object API on the Agg canvas (as ``labbench.sweep.charts``). A campaign table
holds a Z-width when its rows are stability probes over K (``zwidth_figure``), a rate
study when they are ETFE runs at more than one sample time (``rate_figure``);
``write_figures`` draws whichever the table holds into it (``zwidth.png``, ``rate.png``).
"""
from __future__ import annotations

import functools
import json
import math
import textwrap
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from labbench.model import linear
from labbench.model import passivity
from labbench.readout.escape import literal_mpl
from labbench.readout.numfmt import fmt
from labbench.model.ve import Plant, VirtualEnvironment

N_CURVE = 41  # B values of each theory curve
N_FRICTION = 21  # of the friction-aware curve (each point a search over K: ~20 ms)


def table_rows(cols: dict) -> list[dict]:
    """The table's columns (``labbench.sweep.charts.columns``) as one dict per row."""
    names = list(cols)
    return [dict(zip(names, vals)) for vals in zip(*(cols[n] for n in names))]


def _num(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan


def zwidth_rows(cols: dict) -> list[dict]:
    """Every row of a table of stability probes over K (its rows have the zw.* columns)."""
    return table_rows(cols) if "zw.k_max" in cols else []


def zwidth_figure(cols: dict) -> Figure | None:
    """K_max against B, one series per velocity filter: the measured boundary with its 95 %
    interval (filled: above the sampled-data passive bound, stable but not passive; hollow:
    passive too; a triangle: no step grew, K_max above it), the exact sampled boundary, the
    paper's approximation, Colgate & Schenkel's line, the passive envelope of the filtered
    VE and Abbott & Okamura's quantisation bound; with the device's friction known, the
    friction-aware boundary over B at the swing the probe plans there (a curve) and at the
    swing each point's steps started from (diamonds, over the swings of its steps); the
    rig's facts below."""
    rows = zwidth_rows(cols)
    if not rows:
        return None
    fig = Figure(figsize=(8.0, 5.6), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    series: dict = {}
    for r in rows:
        series.setdefault(r.get("ve.w0_rad_s"), []).append(r)
    b_top = max(_num(r.get("ve.B")) for r in rows) or 1.0
    for n, (w0, group) in enumerate(sorted(series.items(), key=lambda kv: (kv[0] is None, kv[0] or 0))):
        color = f"C{n}"
        name = f"w0 = {fmt(w0)} rad/s" if w0 is not None else "no filter"
        _theory_curves(ax, group[0], w0, b_top, color, name, first=n == 0)
        _friction_curve(ax, group, w0, b_top, color, name)
        _measured(ax, group, color, name)
        _friction_aware(ax, group, color, name)
    q = _num(rows[0].get("pred.k_passive_quantised"))
    if math.isfinite(q):
        ax.axhline(q, color="0.4", lw=1, ls=(0, (1, 3)),
                   label=literal_mpl(f"passive, quantisation and friction 2 fc/Δ = {fmt(q)} N/m "
                                     "(Abbott & Okamura)"))
    ax.set_xlabel("virtual damping B (N s/m)\n\n" + "\n".join(textwrap.wrap(
        literal_mpl(rig_line(rows[0])), 120)), fontsize=7)
    ax.set_ylabel("stiffness K (N/m)", fontsize=8)
    ax.set_ylim(bottom=0)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6.5, loc="upper left")
    ax.set_title("Z-width: largest stable K against B, measured on the device and predicted",
                 fontsize=9)
    return fig


def rig_line(r: dict) -> str:
    """What the literature asks a Z-width to state: rate, resolution, filter, damping."""
    T = _num(r.get("rig.sample_time_s"))
    coulomb = r.get("commission.coulomb_n")
    commission = ("commissioning: " + (f"Coulomb {fmt(coulomb)} N" if coulomb is not None
                                       else "no Coulomb friction fitted")
                  if r.get("commission.session") else "no commissioning session found")
    return (f"{r.get('device')}, rig {r.get('rig.name')}: T = {fmt(T * 1e3)} ms "
            f"({fmt(1 / T)} Hz), encoder {fmt(_num(r.get('rig.metres_per_count')) * 1e6)} um/count "
            f"({fmt(r.get('rig.counts_per_rev'))} counts/rev), plant m = {fmt(r.get('plant.m'))} kg, "
            f"b = {fmt(r.get('plant.b'))} N s/m ({r.get('plant.from')}), device delay "
            f"{fmt(_num(r.get('rig.device_delay_s')) * 1e3)} ms; {commission}")


def _loop(r: dict, w0) -> tuple[Plant, float, float, float]:
    """(plant, device delay, T, td) of a row's loop: what every curve over B is drawn for
    (the VE at damping B: ``spring-damper`` K = 1 with filter ``w0``, T and td)."""
    latency, td = _num(r.get("rig.device_delay_s")), _num(r.get("ve.td_s"))
    return (Plant(float(r["plant.m"]), float(r["plant.b"])),
            latency if math.isfinite(latency) else 0.0, float(r["rig.sample_time_s"]),
            td if math.isfinite(td) else 0.0)


def _ve_at(B: float, w0, T: float, td: float) -> VirtualEnvironment:
    return VirtualEnvironment("spring-damper", 1.0, B, math.inf if w0 is None else w0, T, td)


def _theory_curves(ax, r: dict, w0, b_top: float, color: str, name: str, first: bool) -> None:
    plant, latency, T, td = _loop(r, w0)
    Bs = np.linspace(0.0, 1.05 * b_top, N_CURVE)
    ves = [_ve_at(B, w0, T, td) for B in Bs]
    exact = [linear.k_max(plant, ve, latency=latency) for ve in ves]
    passive = [passivity.passive_k_max(plant, ve, latency) for ve in ves]
    ax.plot(Bs, exact, "-", color=color, lw=1.3, label=literal_mpl(f"stable, exact sampled ({name})"))
    ax.plot(Bs, passive, "--", color=color, lw=1.0,
            label=literal_mpl(f"passive, sampled-data condition ({name})"))
    if first:
        approx = [linear.k_max_approx(plant, ve, latency) for ve in ves]
        ax.plot(Bs, approx, ":", color="0.3", lw=1.0,
                label="stable, paper's approximation (b + B) / (T/2 + td)")
        line = [passivity.colgate_line(plant.b, B, T) for B in Bs]
        ax.plot(Bs, line, "-.", color="0.3", lw=1.0,
                label="passive, Colgate & Schenkel b > K T/2 + |B|")


def _measured(ax, group: list[dict], color: str, name: str) -> None:
    B = np.array([_num(r.get("ve.B")) for r in group])
    k = np.array([_num(r.get("zw.k_max")) for r in group])
    lo = np.array([_num(r.get("zw.ci_lo")) for r in group])
    hi = np.array([_num(r.get("zw.ci_hi")) for r in group])
    above = np.array([_num(r.get("zw.k_max_above")) for r in group])
    passive = np.array([_num(r.get("pred.k_passive")) for r in group])
    has = np.isfinite(k)
    err = np.vstack([np.where(np.isfinite(lo), k - lo, 0), np.where(np.isfinite(hi), hi - k, 0)])
    ax.errorbar(B[has], k[has], yerr=err[:, has], fmt="none", ecolor=color, capsize=3, lw=1)
    # above the passive bound by more than the measurement's own interval
    active = has & (np.where(np.isfinite(lo), lo, k) > passive)
    ax.plot(B[active], k[active], "o", color=color, ms=6,
            label=literal_mpl(f"measured K_max, 95 % interval ({name}): stable, not passive"))
    if (has & ~active).any():
        ax.plot(B[has & ~active], k[has & ~active], "o", mfc="white", color=color, ms=6,
                label=literal_mpl(f"measured K_max ({name}): within the passive bound"))
    up = np.isfinite(above)
    if up.any():
        ax.plot(B[up], above[up], "^", color=color, ms=7,
                label=literal_mpl(f"no step grew: K_max above ({name})"))
    bad = np.array([r.get("status") not in ("ok", None) for r in group]) & ~has & ~up
    if bad.any():
        y = np.array([_num(r.get("pred.k_max")) for r in group])
        ax.plot(B[bad], y[bad], "x", color="tab:red", ms=7, label="point not ok (see its row)")


def _friction_curve(ax, group: list[dict], w0, b_top: float, color: str, name: str) -> None:
    """The friction-aware boundary over B as the probe plans it: at each B, where an
    oscillation of the swing its pulse starts at that K neither grows nor decays
    (``pred.k_max_friction_plan``: the friction believed, the safety cap and the pulse plan;
    ``labbench.model.stability_friction.planned_boundary``), through each row's
    ``pred.k_max_friction``; not drawn beyond the probe's safety cap. One curve for each
    plan the series holds (a campaign over the friction believed has several)."""
    plans: dict = {}
    for r in group:
        if isinstance(r.get("pred.k_max_friction_plan"), str):
            plans.setdefault(r["pred.k_max_friction_plan"], []).append(r)
    for text, rows in plans.items():
        plant, latency, T, td = _loop(rows[0], w0)
        Bs = np.union1d(np.linspace(0.0, 1.05 * b_top, N_FRICTION),
                        [_num(r.get("ve.B")) for r in rows if math.isfinite(_num(r.get("ve.B")))])
        k = _planned_curve(text, plant, w0, T, td, latency, tuple(Bs))
        fc = json.loads(text)["coulomb_n"]
        ax.plot(Bs, k, ls=(0, (6, 2, 1, 2)), color=color, lw=1.2,
                label=literal_mpl(f"stable with friction {fmt(fc)} N, at the swing the probe plans "
                                  f"at each B ({name}): describing function"))


@functools.lru_cache(maxsize=32)
def _planned_curve(text: str, plant: Plant, w0, T: float, td: float, latency: float,
                   Bs: tuple) -> np.ndarray:
    """``planned_boundary`` at each of ``Bs`` (nan beyond the cap); kept, since a window
    redraws its chart with every new row (about 20 ms a point)."""
    from labbench.model.pulse import PulsePlan
    from labbench.model.stability_friction import planned_boundary

    basis = json.loads(text)
    plan = PulsePlan.from_dict(basis["pulse"])
    k = [planned_boundary(plant, _ve_at(B, w0, T, td), basis["coulomb_n"], plan,
                          basis["friction_cap"], latency) for B in Bs]
    return np.array([x if x is not None and math.isfinite(x) else math.nan for x in k])


def _friction_aware(ax, group: list[dict], color: str, name: str) -> None:
    """Each point's friction-aware boundary at the swing its steps started from
    (``zw.k_friction``, with its range): what its measurement is compared with."""
    B = np.array([_num(r.get("ve.B")) for r in group])
    k = np.array([_num(r.get("zw.k_friction")) for r in group])
    lo = np.array([_num(r.get("zw.k_friction_lo")) for r in group])
    hi = np.array([_num(r.get("zw.k_friction_hi")) for r in group])
    has = np.isfinite(k)
    if not has.any():
        return
    ax.plot(B[has], k[has], "D", color=color, mfc="none", ms=9,
            label=literal_mpl(f"stable with friction, at the swing the steps started from "
                              f"({name}): compared with the measured"))
    ranged = has & np.isfinite(lo) & np.isfinite(hi)
    ax.errorbar(B[ranged], k[ranged], yerr=np.vstack([k - lo, hi - k])[:, ranged], fmt="none",
                ecolor=color, capsize=2, lw=0.6, alpha=0.6)


def rate_rows(cols: dict) -> list[dict]:
    rows = [r for r in table_rows(cols) if r.get("acc.ed_median") is not None]
    return rows if len({r.get("rig.sample_time_s") for r in rows}) > 1 else []


def rate_figure(cols: dict) -> Figure | None:
    """Against the sample time T: the median and max rendering error of ED and ES over
    2-100 rad/s, w_s* and w_b*, and K_max, each measured (points) and predicted by the exact
    sampled theory (lines)."""
    rows = sorted(rate_rows(cols), key=lambda r: r["rig.sample_time_s"])
    if not rows:
        return None
    T = np.array([1e3 * r["rig.sample_time_s"] for r in rows])
    fig = Figure(figsize=(8.0, 6.0), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2)

    def col(name):
        return np.array([_num(r.get(name)) for r in rows])

    for ax, which, title in ((axes[0, 0], "ed", "ED: |ED - (b + B)| / (b + B)"),
                             (axes[0, 1], "es", "ES: |ES - (K - m w^2)| / K")):
        for stat, mark in (("median", "o"), ("max", "s")):
            line, = ax.plot(T, 100 * col(f"pred.{which}_{stat}"), "-", lw=1.2,
                            label=f"{stat}, predicted")
            ax.plot(T, 100 * col(f"acc.{which}_{stat}"), mark, color=line.get_color(),
                    label=f"{stat}, measured")
        ax.set_title(literal_mpl(f"rendering error of {title}"), fontsize=8)
        ax.set_ylabel("error over 2-100 rad/s (%)", fontsize=8)
    ax = axes[1, 0]
    for key, label in (("ws_star", "w_s*"), ("wb_star", "w_b*")):
        line, = ax.plot(T, col(f"res.bandwidths.{key}_predicted"), "-", label=f"{label} predicted")
        ax.plot(T, col(f"res.bandwidths.{key}_measured"), "o", color=line.get_color(),
                label=f"{label} measured")
    ax.set_ylabel("bandwidth (rad/s)", fontsize=8)
    ax.set_title("stiffness and damping bandwidths", fontsize=8)
    ax = axes[1, 1]
    line, = ax.plot(T, col("pred.k_max"), "-", label="predicted (rig's plant and delay)")
    ax.plot(T, col("acc.k_max_fit"), "o", color=line.get_color(),
            label="from the measured loop (closed-loop fit)")
    ax.set_yscale("log")
    ax.set_ylabel("K_max (N/m)", fontsize=8)
    ax.set_title("largest stable K of this VE", fontsize=8)
    for ax in axes.flat:
        ax.set_xscale("log")
        ax.set_xticks(T, [fmt(t) for t in T])
        ax.minorticks_off()
        ax.set_xlabel("sample time T (ms)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6.5)
    fig.suptitle(literal_mpl(f"Rate vs accuracy: {rows[0].get('ve.kind')} K = {fmt(rows[0].get('ve.K'))} "
                             f"N/m, B = {fmt(rows[0].get('ve.B'))} N s/m, w0 = "
                             f"{fmt(rows[0].get('ve.w0_rad_s'))} rad/s on {rows[0].get('device')}"),
                 fontsize=9)
    return fig


FIGURES = (("zwidth.png", zwidth_figure), ("rate.png", rate_figure))


def write_figures(directory) -> list[Path]:
    """The figures the table at ``directory`` holds, written beside it in its charts folder
    (``labbench.sweep.table.charts_folder``: Parquet readers take every file inside the
    table for a part), replacing earlier ones."""
    from labbench.safe_write import output_folder, replacing
    from labbench.sweep import charts, table as tables

    tab = tables.read_table(directory)
    if not tab.num_rows:
        return []
    cols = charts.columns(tab)
    out = []
    for name, make in FIGURES:
        fig = make(cols)
        if fig is None:
            continue
        path = output_folder(tables.charts_folder(directory)) / name
        with replacing(path, force=True) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        out.append(path)
    return out
