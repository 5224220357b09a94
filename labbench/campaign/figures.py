"""The campaign's own charts, drawn from its table: the Z-width and the rate-vs-accuracy chart.

What a chart shows is data (``Chart``: panels of ``Series``, each point naming its table
row), made once here (``zwidth_chart``, ``rate_chart``) and drawn by two hands: matplotlib's
object API on the Agg canvas (``figure``, as ``labbench.sweep.charts``) for the PNGs and the
report, pyqtgraph for the window's Campaign page (``labbench.gui.campaign_chart``), so the
page shows every panel and point the PNG does. A campaign table holds a Z-width when its
rows are stability probes over K (``zwidth_figure``), a rate study when they are ETFE runs
at more than one sample time (``rate_figure``); ``write_figures`` draws whichever the table
holds into it (``zwidth.png``, ``rate.png``).
"""
from __future__ import annotations

import functools
import json
import math
import textwrap
from dataclasses import dataclass, field
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


@dataclass
class Series:
    """One thing a panel draws: a ``line`` through (x, y), ``points`` (the i-th of table row
    ``rows[i]``; ``lo``/``hi``: the ends of its error bars, nan: none), or a ``level``, a
    horizontal line at y[0]. Styles in matplotlib's terms: colour ("C0", "0.3", "tab:red"),
    line style ("-", "--", ":", "-." or (offset, (on, off, ...))), marker ("o", "^", "D",
    "x")."""

    kind: str
    label: str | None
    x: np.ndarray
    y: np.ndarray
    colour: str
    style: str | tuple = "-"
    width: float = 1.0
    marker: str = "o"
    size: float = 6.0
    face: str | None = None  # a point's inside: None filled with its colour, "white", "none"
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    faint_bars: bool = False  # thin, half-transparent error bars (a prediction's range)
    rows: tuple = ()


@dataclass
class Panel:
    """One axes of a chart: its series, axis labels and scales."""

    title: str
    xlabel: str
    ylabel: str
    series: list[Series] = field(default_factory=list)
    xlog: bool = False
    ylog: bool = False
    xticks: tuple = ()  # ticks at these x only (the sample times of a rate study)
    y_from_zero: bool = False
    legend: str = "best"


@dataclass
class Chart:
    """What a campaign's figure shows, drawn by matplotlib into its PNG (``figure``) and by
    the window's Campaign page (``labbench.gui.campaign_chart``): ``panels`` in a grid of
    ``columns``, a title, and a foot (the rig's facts) below."""

    name: str  # "zwidth" | "rate"
    title: str
    panels: list[Panel]
    columns: int = 1
    foot: str = ""
    size: tuple = (8.0, 5.6)


def _idx_col(rows: list[tuple[int, dict]], name: str) -> np.ndarray:
    return np.array([_num(r.get(name)) for _, r in rows])


def zwidth_chart(rows: list[dict]) -> Chart | None:
    """K_max against B, one series per velocity filter: the measured boundary with its 95 %
    interval (filled: above the sampled-data passive bound, stable but not passive; hollow:
    passive too; a triangle: no step grew, K_max above it), the exact sampled boundary, the
    paper's approximation, Colgate & Schenkel's line, the passive envelope of the filtered
    VE and Abbott & Okamura's quantisation bound; with the device's friction known, the
    friction-aware boundary over B at the swing the probe plans there (a curve) and at the
    swing each point's steps started from (diamonds, over the swings of its steps); the
    rig's facts below. None: ``rows`` are no stability probes over K."""
    if not any("zw.k_max" in r for r in rows):
        return None
    panel = Panel("", "virtual damping B (N s/m)", "stiffness K (N/m)", y_from_zero=True,
                  legend="upper left")
    series: dict = {}
    for i, r in enumerate(rows):
        series.setdefault(r.get("ve.w0_rad_s"), []).append((i, r))
    b_top = max(_num(r.get("ve.B")) for r in rows) or 1.0
    for n, (w0, group) in enumerate(sorted(series.items(), key=lambda kv: (kv[0] is None, kv[0] or 0))):
        color = f"C{n}"
        name = f"w0 = {fmt(w0)} rad/s" if w0 is not None else "no filter"
        panel.series += _theory_curves(group[0][1], w0, b_top, color, name, first=n == 0)
        panel.series += _friction_curve(group, w0, b_top, color, name)
        panel.series += _measured(group, color, name)
        panel.series += _friction_aware(group, color, name)
    q = _num(rows[0].get("pred.k_passive_quantised"))
    if math.isfinite(q):
        panel.series.append(Series(
            "level", f"passive, quantisation and friction 2 fc/Δ = {fmt(q)} N/m (Abbott & Okamura)",
            np.array([]), np.array([q]), "0.4", (0, (1, 3))))
    return Chart("zwidth", "Z-width: largest stable K against B, measured on the device and "
                 "predicted", [panel], foot=rig_line(rows[0]))


def zwidth_figure(cols: dict) -> Figure | None:
    """``zwidth_chart`` of the table's columns, drawn (None: no Z-width in it)."""
    chart = zwidth_chart(table_rows(cols))
    return figure(chart) if chart else None


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


@functools.lru_cache(maxsize=64)
def _curves(plant: Plant, w0, T: float, td: float, latency: float, b_top: float) -> tuple:
    """(B, exact, passive, approximation, Colgate's line) over 0..1.05 b_top; kept, since a
    window redraws its chart with every new row."""
    Bs = np.linspace(0.0, 1.05 * b_top, N_CURVE)
    ves = [_ve_at(B, w0, T, td) for B in Bs]
    return (Bs, np.array([linear.k_max(plant, ve, latency=latency) for ve in ves]),
            np.array([passivity.passive_k_max(plant, ve, latency) for ve in ves]),
            np.array([linear.k_max_approx(plant, ve, latency) for ve in ves]),
            np.array([passivity.colgate_line(plant.b, B, T) for B in Bs]))


def _theory_curves(r: dict, w0, b_top: float, color: str, name: str, first: bool) -> list[Series]:
    plant, latency, T, td = _loop(r, w0)
    Bs, exact, passive, approx, line = _curves(plant, w0, T, td, latency, b_top)
    out = [Series("line", f"stable, exact sampled ({name})", Bs, exact, color, "-", 1.3),
           Series("line", f"passive, sampled-data condition ({name})", Bs, passive, color, "--")]
    if first:
        out += [Series("line", "stable, paper's approximation (b + B) / (T/2 + td)", Bs, approx,
                       "0.3", ":"),
                Series("line", "passive, Colgate & Schenkel b > K T/2 + |B|", Bs, line, "0.3", "-.")]
    return out


def _measured(group: list[tuple[int, dict]], color: str, name: str) -> list[Series]:
    at = np.array([i for i, _ in group])
    B, k = _idx_col(group, "ve.B"), _idx_col(group, "zw.k_max")
    lo, hi = _idx_col(group, "zw.ci_lo"), _idx_col(group, "zw.ci_hi")
    above, passive = _idx_col(group, "zw.k_max_above"), _idx_col(group, "pred.k_passive")
    has = np.isfinite(k)
    # above the passive bound by more than the measurement's own interval
    active = has & (np.where(np.isfinite(lo), lo, k) > passive)

    def points(keep, label, y=k, **style) -> Series:
        return Series("points", label, B[keep], y[keep], color, rows=tuple(at[keep].tolist()),
                      **style)

    out = [points(active, f"measured K_max, 95 % interval ({name}): stable, not passive",
                  lo=lo[active], hi=hi[active])]
    if (has & ~active).any():
        out.append(points(has & ~active, f"measured K_max ({name}): within the passive bound",
                          face="white", lo=lo[has & ~active], hi=hi[has & ~active]))
    up = np.isfinite(above)
    if up.any():
        out.append(points(up, f"no step grew: K_max above ({name})", y=above, marker="^", size=7))
    bad = np.array([r.get("status") not in ("ok", None) for _, r in group]) & ~has & ~up
    if bad.any():
        out.append(Series("points", "point not ok (see its row)", B[bad],
                          _idx_col(group, "pred.k_max")[bad], "tab:red", marker="x", size=7,
                          rows=tuple(at[bad].tolist())))
    return out


def _friction_curve(group: list[tuple[int, dict]], w0, b_top: float, color: str,
                    name: str) -> list[Series]:
    """The friction-aware boundary over B as the probe plans it: at each B, where an
    oscillation of the swing its pulse starts at that K neither grows nor decays
    (``pred.k_max_friction_plan``: the friction believed, the safety cap and the pulse plan;
    ``labbench.model.stability_friction.planned_boundary``), through each row's
    ``pred.k_max_friction``; not drawn beyond the probe's safety cap. One curve for each
    plan the series holds (a campaign over the friction believed has several)."""
    plans: dict = {}
    for _, r in group:
        if isinstance(r.get("pred.k_max_friction_plan"), str):
            plans.setdefault(r["pred.k_max_friction_plan"], []).append(r)
    out = []
    for text, rows in plans.items():
        plant, latency, T, td = _loop(rows[0], w0)
        Bs = np.union1d(np.linspace(0.0, 1.05 * b_top, N_FRICTION),
                        [_num(r.get("ve.B")) for r in rows if math.isfinite(_num(r.get("ve.B")))])
        k = _planned_curve(text, plant, w0, T, td, latency, tuple(Bs))
        fc = json.loads(text)["coulomb_n"]
        out.append(Series("line", f"stable with friction {fmt(fc)} N, at the swing the probe "
                          f"plans at each B ({name}): describing function", Bs, k, color,
                          (0, (6, 2, 1, 2)), 1.2))
    return out


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


def _friction_aware(group: list[tuple[int, dict]], color: str, name: str) -> list[Series]:
    """Each point's friction-aware boundary at the swing its steps started from
    (``zw.k_friction``, with its range): what its measurement is compared with."""
    at = np.array([i for i, _ in group])
    B, k = _idx_col(group, "ve.B"), _idx_col(group, "zw.k_friction")
    lo, hi = _idx_col(group, "zw.k_friction_lo"), _idx_col(group, "zw.k_friction_hi")
    has = np.isfinite(k)
    if not has.any():
        return []
    return [Series("points", f"stable with friction, at the swing the steps started from "
                   f"({name}): compared with the measured", B[has], k[has], color, marker="D",
                   size=9, face="none", lo=lo[has], hi=hi[has], faint_bars=True,
                   rows=tuple(at[has].tolist()))]


def rate_rows(cols: dict) -> list[dict]:
    rows = [r for r in table_rows(cols) if r.get("acc.ed_median") is not None]
    return rows if len({r.get("rig.sample_time_s") for r in rows}) > 1 else []


def rate_chart(rows: list[dict]) -> Chart | None:
    """Against the sample time T: the median and max rendering error of ED and ES over
    2-100 rad/s, w_s* and w_b*, and K_max, each measured (points) and predicted by the exact
    sampled theory (lines). None: ``rows`` hold no ETFE runs at more than one T."""
    shown = [(i, r) for i, r in enumerate(rows) if r.get("acc.ed_median") is not None]
    if len({r.get("rig.sample_time_s") for _, r in shown}) < 2:
        return None
    shown.sort(key=lambda ir: ir[1]["rig.sample_time_s"])
    at = tuple(i for i, _ in shown)
    T = 1e3 * _idx_col(shown, "rig.sample_time_s")

    def pair(label_line, label_points, pred, meas, colour, marker="o", scale=1.0, width=1.5):
        return [Series("line", label_line, T, scale * _idx_col(shown, pred), colour, "-", width),
                Series("points", label_points, T, scale * _idx_col(shown, meas), colour,
                       marker=marker, rows=at)]

    panels = []
    for which, title in (("ed", "ED: |ED - (b + B)| / (b + B)"), ("es", "ES: |ES - (K - m w^2)| / K")):
        p = Panel(f"rendering error of {title}", "sample time T (ms)",
                  "error over 2-100 rad/s (%)")
        for n, (stat, mark) in enumerate((("median", "o"), ("max", "s"))):
            p.series += pair(f"{stat}, predicted", f"{stat}, measured", f"pred.{which}_{stat}",
                             f"acc.{which}_{stat}", f"C{n}", mark, 100.0, 1.2)
        panels.append(p)
    p = Panel("stiffness and damping bandwidths", "sample time T (ms)", "bandwidth (rad/s)")
    for n, (key, label) in enumerate((("ws_star", "w_s*"), ("wb_star", "w_b*"))):
        p.series += pair(f"{label} predicted", f"{label} measured",
                         f"res.bandwidths.{key}_predicted", f"res.bandwidths.{key}_measured", f"C{n}")
    panels.append(p)
    p = Panel("largest stable K of this VE", "sample time T (ms)", "K_max (N/m)", ylog=True)
    p.series += pair("predicted (rig's plant and delay)", "from the measured loop (closed-loop fit)",
                     "pred.k_max", "acc.k_max_fit", "C0")
    panels.append(p)
    for p in panels:
        p.xlog, p.xticks = True, tuple(T)
    r = shown[0][1]
    return Chart("rate", f"Rate vs accuracy: {r.get('ve.kind')} K = {fmt(r.get('ve.K'))} N/m, "
                 f"B = {fmt(r.get('ve.B'))} N s/m, w0 = {fmt(r.get('ve.w0_rad_s'))} rad/s on "
                 f"{r.get('device')}", panels, columns=2, size=(8.0, 6.0))


def rate_figure(cols: dict) -> Figure | None:
    """``rate_chart`` of the table's columns, drawn (None: no rate study in it)."""
    chart = rate_chart(table_rows(cols))
    return figure(chart) if chart else None


def charts(rows: list[dict]) -> list[Chart]:
    """The charts ``rows`` (a campaign table's, in its order) make: a Z-width, a rate study."""
    return [c for c in (zwidth_chart(rows), rate_chart(rows)) if c is not None]


def figure(chart: Chart) -> Figure:
    """``chart`` drawn by matplotlib (its PNG, the report's figure)."""
    fig = Figure(figsize=chart.size, layout="constrained")
    FigureCanvasAgg(fig)
    nrows = -(-len(chart.panels) // chart.columns)
    axes = np.atleast_1d(fig.subplots(nrows, chart.columns)).ravel()
    for ax, panel in zip(axes, chart.panels):
        for s in panel.series:
            _draw(ax, s)
        xlabel = panel.xlabel
        if chart.foot:
            xlabel += "\n\n" + "\n".join(textwrap.wrap(literal_mpl(chart.foot), 120))
        ax.set_xlabel(xlabel, fontsize=7 if chart.foot else 8)
        ax.set_ylabel(panel.ylabel, fontsize=8)
        if panel.xlog:
            ax.set_xscale("log")
        if panel.ylog:
            ax.set_yscale("log")
        if panel.xticks:
            ax.set_xticks(panel.xticks, [fmt(t) for t in panel.xticks])
            ax.minorticks_off()
        if panel.y_from_zero:
            ax.set_ylim(bottom=0)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6.5, loc=panel.legend)
        if panel.title:
            ax.set_title(literal_mpl(panel.title), fontsize=8)
    if len(chart.panels) == 1:
        axes[0].set_title(literal_mpl(chart.title), fontsize=9)
    else:
        fig.suptitle(literal_mpl(chart.title), fontsize=9)
    return fig


def _draw(ax, s: Series) -> None:
    label = literal_mpl(s.label) if s.label else None
    if s.kind == "level":
        ax.axhline(s.y[0], color=s.colour, lw=s.width, ls=s.style, label=label)
        return
    if s.kind == "line":
        ax.plot(s.x, s.y, ls=s.style, color=s.colour, lw=s.width, label=label)
        return
    if s.lo is not None and s.hi is not None:
        bars = np.isfinite(s.lo) | np.isfinite(s.hi)
        if s.faint_bars:
            bars = np.isfinite(s.lo) & np.isfinite(s.hi)
        err = np.vstack([np.where(np.isfinite(s.lo), s.y - s.lo, 0),
                         np.where(np.isfinite(s.hi), s.hi - s.y, 0)])
        ax.errorbar(s.x[bars], s.y[bars], yerr=err[:, bars], fmt="none", ecolor=s.colour,
                    capsize=2 if s.faint_bars else 3, lw=0.6 if s.faint_bars else 1,
                    alpha=0.6 if s.faint_bars else 1)
    ax.plot(s.x, s.y, s.marker, ls="none", color=s.colour, ms=s.size,
            mfc=s.face or s.colour, label=label)


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
