"""Paper-style static figures: Bode and effective-impedance panels (paper Figures 4-8).

Matplotlib through its object API on the Agg canvas (no pyplot state, no Qt),
so reports, the CLI and worker threads can all call it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from labbench.model.effective import effective_impedances, focus_limits
from labbench.errors import UserError
from labbench.readout.escape import literal_mpl
from labbench.safe_write import output_path, replacing

FORMATS = (".png", ".svg", ".pdf")
STYLES = ("line", "points")


@dataclass
class Curve:
    """One frequency response Z(jw) to draw.

    ``w`` [rad/s], ``Z`` = F/V [N s/m] complex; ``style`` "line" (theory) or
    "points" (measured); ``Z_err`` the 95 % radius |dZ| per frequency, drawn as
    a band on the magnitude and on ES, ED, EM.
    """

    label: str
    w: np.ndarray
    Z: np.ndarray
    style: str = "line"
    Z_err: np.ndarray | None = None
    color: str | None = None  # None: the next colour of the cycle


def paper_figure(curves: list[Curve], path=None, title: str | None = None,
                 marks: dict | None = None, inputs=(), force: bool = False) -> Figure:
    """Write Bode magnitude (dB), phase (deg) and ES, ED, EM panels of each curve.

    ES is drawn where Im Z < 0 and EM where Im Z > 0, zero elsewhere (paper
    sec. 2.2, Figure 2). ``marks`` maps a label to a frequency [rad/s] drawn as
    a dashed vertical line on every panel, e.g. ``{"ws*": 23.1, "wb*": 125}``.
    Returns the figure. With ``path`` it is also written, in the format of the
    suffix (.png, .svg, .pdf), by ``labbench.safe_write.replacing``: never onto one
    of ``inputs``, an existing one replaced only with ``force``, its folder never
    created.
    """
    if path is not None:
        path = Path(path)
        if path.suffix.lower() not in FORMATS:
            raise UserError(f"figure {path}: use a .png, .svg or .pdf file name")
        output_path(path, inputs, force)  # before the drawing
    for c in curves:
        if c.style not in STYLES:
            raise ValueError(f"curve style {c.style!r}; choose one of {', '.join(STYLES)}")

    fig = Figure(figsize=(11, 7.5), layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(6, 2)
    mag = fig.add_subplot(grid[0:3, 0])
    phase = fig.add_subplot(grid[3:6, 0], sharex=mag)
    es = fig.add_subplot(grid[0:2, 1], sharex=mag)
    ed = fig.add_subplot(grid[2:4, 1], sharex=mag)
    em = fig.add_subplot(grid[4:6, 1], sharex=mag)

    for i, c in enumerate(curves):
        w, Z, eff, stiff = _arrays(c)
        fmt = dict(color=c.color or f"C{i}", label=literal_mpl(c.label))
        fmt.update(dict(lw=1.5) if c.style == "line" else dict(ls="none", marker=".", ms=3))
        mag.semilogx(w, 20 * np.log10(np.abs(Z)), **fmt)
        phase.semilogx(w, eff.theta_deg, **fmt)
        es.semilogx(w, np.where(stiff, eff.ES, 0.0), **fmt)
        ed.semilogx(w, eff.ED, **fmt)
        em.semilogx(w, np.where(stiff, 0.0, eff.EM), **fmt)
        if c.Z_err is not None:
            dz = np.asarray(c.Z_err, float)
            band = dict(color=c.color or f"C{i}", alpha=0.2, lw=0)
            absz = np.abs(Z)
            mag.fill_between(w, 20 * np.log10(np.maximum(absz - dz, 1e-3 * absz)),
                             20 * np.log10(absz + dz), **band)
            es_val = np.where(stiff, eff.ES, 0.0)
            es.fill_between(w, es_val - w * dz, es_val + w * dz, where=stiff, **band)
            ed.fill_between(w, eff.ED - dz, eff.ED + dz, **band)
            em_val = np.where(stiff, 0.0, eff.EM)
            em.fill_between(w, em_val - dz / w, em_val + dz / w, where=~stiff, **band)

    for ax, ylabel in ((mag, "|Z| (dB re 1 N s/m)"), (phase, "phase of Z (deg)"),
                       (es, "ES (N/m)"), (ed, "ED (N s/m)"), (em, "EM (kg)")):
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        for j, wm in enumerate((marks or {}).values()):
            if wm is not None and np.isfinite(wm):
                ax.axvline(wm, color="0.3", ls=(0, (4, 2 + 2 * j)), lw=1)
    for name, wm in (marks or {}).items():
        if wm is not None and np.isfinite(wm):
            mag.annotate(name, (wm, 1.0), xycoords=("data", "axes fraction"),
                         xytext=(3, -12), textcoords="offset points", fontsize=9)
    for ax in (phase, em):
        ax.set_xlabel("frequency (rad/s)")
    handles, labels = mag.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 4), fontsize=9)
    if title:
        fig.suptitle(literal_mpl(title))
    if path is not None:
        with replacing(path, inputs, force) as tmp:
            try:
                fig.savefig(tmp, dpi=120)
            except OSError as exc:
                raise UserError(f"cannot write figure {path}: {exc.strerror or exc}") from None
    return fig


def effective_figure(curves: list[Curve], size=(7.2, 2.15),
                     focus: tuple[float, float] | None = None) -> Figure:
    """ES, ED and EM side by side (paper Figures 5-8 without the Bode panels), for a
    summary page: lines for theory, points for measurements, ES where Im Z < 0 and EM
    where Im Z > 0 as in ``paper_figure``. Overlay several runs by giving their curves
    one ``color`` each. ``focus`` [rad/s]: the band whose ED the damping axis shows
    readably (``labbench.model.effective.focus_limits``; the roll-off beyond leaves the axes).
    Returns the figure."""
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    es, ed, em = fig.subplots(1, 3, sharex=True)
    for i, c in enumerate(curves):
        w, Z, eff, stiff = _arrays(c)
        style = dict(color=c.color or f"C{i}", label=literal_mpl(c.label))
        # theory thin and under, measured points on top: both stay visible in one colour
        style.update(dict(lw=1.0, alpha=0.75, zorder=2) if c.style == "line"
                     else dict(ls="none", marker="o", ms=2.2, mew=0, zorder=3))
        es.semilogx(w, np.where(stiff, eff.ES, 0.0), **style)
        ed.semilogx(w, eff.ED, **style)
        em.semilogx(w, np.where(stiff, 0.0, eff.EM), **style)
    if focus is not None:
        limits = [focus_limits(effective_impedances(c.w, c.Z).ED, c.w, focus) for c in curves]
        limits = [x for x in limits if x is not None]
        if limits:
            ed.set_ylim(min(x[0] for x in limits), max(x[1] for x in limits))
    for ax, ylabel in ((es, "ES (N/m)"), (ed, "ED (N s/m)"), (em, "EM (kg)")):
        ax.set_ylabel(ylabel, fontsize=8)
        ax.set_xlabel("frequency (rad/s)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = es.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 3), fontsize=7)
    return fig


def _arrays(c) -> tuple:
    """(w, Z, effective impedances, where the curve is stiffness-like) of one curve."""
    w = np.asarray(c.w, float)
    Z = np.asarray(c.Z, complex)
    return w, Z, effective_impedances(w, Z), Z.imag < 0
