"""The design's figures (``labbench design --plot``): the trade-off over B and w0 from the
models, and a design's predictions beside a campaign's measurements (``labbench.design.checking``).

Matplotlib's object API on the Agg canvas (no pyplot state, no Qt), as ``labbench.readout.figures``.
"""
from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from labbench.design.tradeoffs import DesignPoint


def _canvas(size) -> Figure:
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _log_x(ax, ticks) -> None:
    """A log axis of a few w0, labelled at them in plain numbers."""
    from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator, ScalarFormatter

    ax.set_xscale("log")
    ax.xaxis.set_major_locator(FixedLocator(list(ticks)))
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_locator(NullLocator())
    ax.xaxis.set_minor_formatter(NullFormatter())


def _style(ax, xlabel: str, ylabel: str) -> None:
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)


def tradeoff_figure(points: list[DesignPoint], recommendation: dict | None,
                    noise_limit_n: float | None, noise_of: str = "command") -> Figure:
    """K_max, the limited force noise and w_b* against B, one colour per w0 (the first K and T
    of the grid), and the recommendation's objective against w0."""
    K, T = points[0].K, points[0].T
    pts = [p for p in points if p.K == K and p.T == T]
    fig = _canvas((10.0, 7.2))
    axes = fig.subplots(2, 2)
    w0s = sorted({p.w0 for p in pts})
    noise_key = "noise_felt" if noise_of == "felt" else "noise_command"
    panels = ((axes[0, 0], "k_max", 1.0, "K_max, exact sampled (N/m)"),
              (axes[0, 1], noise_key, 1e3, f"{noise_of} force noise, felt band (mN rms)"),
              (axes[1, 0], "wb_star", 1.0, "w_b*, exact sampled (rad/s)"))
    for n, w0 in enumerate(w0s):
        grp = sorted((p for p in pts if p.w0 == w0), key=lambda p: p.B)
        B = [p.B for p in grp]
        for ax, key, scale, _ in panels:
            y = [np.nan if getattr(p, key) is None else getattr(p, key) * scale for p in grp]
            ax.plot(B, y, "o-", ms=3, lw=1.2, color=f"C{n % 10}", label=f"w0 = {w0:g} rad/s")
    if noise_limit_n is not None:
        axes[0, 1].axhline(1e3 * noise_limit_n, color="k", ls="--", lw=1, label="noise limit")
    for ax, _, _, label in panels:
        _style(ax, "virtual damping B (N s/m)", label)
    axes[0, 0].legend(fontsize=6.5)
    axes[0, 1].legend(fontsize=6.5)
    ax = axes[1, 1]
    if recommendation and recommendation.get("by_w0"):
        rows = recommendation["by_w0"]
        ax.plot([r["w0"] for r in rows],
                [np.nan if r["value"] is None else r["value"] for r in rows], "o-", color="C0")
        if recommendation.get("w0") is not None:
            ax.axvline(recommendation["w0"], color="0.3", ls="--", lw=1,
                       label=f"recommended w0 = {recommendation['w0']:g} rad/s")
            ax.legend(fontsize=7)
        _log_x(ax, [r["w0"] for r in rows])
        what = ("Z-width under the noise limit (N^2 s/m^2)" if recommendation["objective"]
                == "zwidth" else "w_b* under the noise limit (rad/s)")
    else:
        what = "(one w0: no recommendation)"
    _style(ax, "velocity filter cut-off w0 (rad/s)", what)
    fig.suptitle(f"Three-way trade-off at K = {K:g} N/m, T = {T:g} s", fontsize=9)
    return fig


def check_figure(c) -> Figure:
    """A ``labbench.design.checking.Check`` in one figure: K_max, force noise and rendered B
    against B (one colour per w0: lines predicted, points measured with their 95 % intervals),
    and the Z-width against w0."""
    fig = _canvas((10.0, 7.2))
    axes = fig.subplots(2, 2)
    panels = ((axes[0, 0], "k_max", 1.0, "K_max (N/m)"),
              (axes[0, 1], "noise", 1e3, "command force noise, 10-500 Hz (mN rms)"),
              (axes[1, 0], "rendered_B", 1.0, "rendered B - (b + B) (N s/m)"))
    # the rendered damping as its departure from the damping designed (b + B)
    offset = {"rendered_B": lambda r: c.b + r.B}
    w0s = sorted({r.w0 for r in c.rows})
    for n, w0 in enumerate(w0s):
        grp = sorted((r for r in c.rows if r.w0 == w0), key=lambda r: r.B)
        color = f"C{n % 10}"
        B = np.array([r.B for r in grp])
        for ax, key, scale, _ in panels:
            base = offset.get(key, lambda r: 0.0)
            p = np.array([np.nan if r.predicted.get(key) is None else
                          (r.predicted[key] - base(r)) * scale for r in grp])
            ax.plot(B, p, "-", color=color, lw=1.2, label=f"w0 {w0:g} predicted")
            pts = [(r.B, r.measured[key] - base(r),
                    tuple(None if v is None else v - base(r) for v in r.ci.get(key, (None, None))))
                   for r in grp if r.measured.get(key) is not None]
            if pts:
                x = np.array([q[0] for q in pts])
                y = np.array([q[1] for q in pts]) * scale
                lo = np.array([q[2][0] if q[2][0] is not None else q[1] for q in pts]) * scale
                hi = np.array([q[2][1] if q[2][1] is not None else q[1] for q in pts]) * scale
                ax.errorbar(x, y, yerr=[np.maximum(y - lo, 0), np.maximum(hi - y, 0)], fmt="o",
                            color=color, ms=4, capsize=2, label=f"w0 {w0:g} measured")
    if c.noise_limit_n is not None:
        axes[0, 1].axhline(1e3 * c.noise_limit_n, color="k", ls="--", lw=1, label="noise limit")
    for ax, _, _, label in panels:
        _style(ax, "virtual damping B (N s/m)", label)
    axes[0, 0].legend(fontsize=6, ncol=2)
    ax = axes[1, 1]
    if c.zwidth:
        ws = list(c.zwidth)
        ax.plot(ws, [c.zwidth[w]["predicted"] for w in ws], "-", color="C0", label="predicted")
        ax.plot(ws, [c.zwidth[w]["measured"] for w in ws], "o", color="C1", label="measured")
        for w, style, name in ((c.best_predicted, ":", "predicted best"),
                               (c.best_measured, "--", "measured best")):
            if w is not None:
                ax.axvline(w, color="0.3", ls=style, lw=1, label=f"{name} w0 = {w:g}")
        _log_x(ax, ws)
        ax.legend(fontsize=7)
    _style(ax, "velocity filter cut-off w0 (rad/s)", "Z-width under the noise limit (N^2 s/m^2)")
    fig.suptitle(f"Design predicted vs measured: K = {c.K:g} N/m, T = {c.T:g} s", fontsize=9)
    return fig
