"""Charts of a sweep table: maps, lines, failure regions (matplotlib, Agg canvas, no pyplot).

A chart is a small table of options (a spec's ``[[chart]]`` or the CLI's)::

    kind = "map"        # points at (x, y) coloured by ``color`` (a stability map: truth.stable)
    kind = "lines"      # y (one column or a list) against x, one line per value of ``series``
    kind = "failure"    # where a method fails: ``metric`` above ``threshold``, its own
                        # warnings (``warnings`` > 0), or no result (status not ok)
    x, y                # column names (parameters, res.*, truth.*, times)
    color, series, metric, threshold, warnings
    facet               # one panel per value of this column
    where = { col = value }   # only the rows with these values
    log_x, log_y, log_color   # log axes (default: chosen from the data's span)
    file                # the PNG/SVG/PDF written (default <kind>-<n>.png in the table)
    title

Rows whose status is not "ok" are drawn as crosses on maps and lines (they are
part of the answer: where a run was refused as unstable, where it failed).
"""
from __future__ import annotations

import numpy as np

from labbench.errors import UserError, unknown_name
from labbench.readout.escape import literal_mpl

KINDS = ("map", "lines", "failure")
KEYS = ("kind", "x", "y", "color", "series", "metric", "threshold", "warnings", "facet", "where",
        "log_x", "log_y", "log_color", "file", "title")
NEEDS = {"map": ("x", "y"), "lines": ("x", "y"), "failure": ("x", "y", "metric", "threshold")}
CATEGORIES = (("ok", "tab:green"), ("error above threshold", "tab:orange"),
              ("own warnings", "gold"), ("no result", "tab:red"))


def check_chart(c: dict, where: str) -> None:
    """One UserError for a chart table that cannot be drawn from any table."""
    for k in c:
        if k not in KEYS:
            raise UserError(f"{where} {unknown_name('key', k, KEYS)}")
    kind = c.get("kind")
    if kind not in KINDS:
        raise UserError(f"{where} kind must be one of {', '.join(KINDS)}, got {kind!r}")
    for k in NEEDS[kind]:
        if k not in c:
            raise UserError(f"{where} kind {kind} needs {k}")
    for k in ("x", "color", "series", "metric", "warnings", "facet", "file", "title"):
        if k in c and not isinstance(c[k], str):
            raise UserError(f"{where} {k} must be text, got {c[k]!r}")
    ys = c.get("y")
    if not (isinstance(ys, str) or (isinstance(ys, list) and ys and all(isinstance(y, str) for y in ys))):
        raise UserError(f"{where} y must be a column name or a list of them")
    if isinstance(ys, list) and kind != "lines":
        raise UserError(f"{where} a list of y is for kind lines")
    if "threshold" in c and (isinstance(c["threshold"], bool)
                             or not isinstance(c["threshold"], (int, float))):
        raise UserError(f"{where} threshold must be a number")
    if "where" in c and not isinstance(c["where"], dict):
        raise UserError(f"{where} where must be a table {{column = value}}")
    for k in ("log_x", "log_y", "log_color"):
        if k in c and not isinstance(c[k], bool):
            raise UserError(f"{where} {k} must be true or false")


def columns(table) -> dict[str, list]:
    """A pyarrow table as ``{name: list of values}``."""
    return {n: table[n].to_pylist() for n in table.column_names}


def columns_named(chart: dict) -> list[str]:
    """The table columns a (``check_chart``-valid) chart draws from."""
    ys = chart["y"] if isinstance(chart["y"], list) else [chart["y"]]
    named = [chart[k] for k in ("x", "color", "series", "metric", "warnings", "facet") if k in chart]
    return list(dict.fromkeys([*named, *ys, *(chart.get("where") or {})]))


def draw(cols: dict[str, list], chart: dict):
    """The figure of ``chart`` (``check_chart``-valid) from the table's columns (matplotlib is
    imported here: reading a spec, which checks its charts, does not need it)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    check_chart(chart, "chart")
    for name in columns_named(chart):
        _need(cols, name)
    rows = _where(cols, chart.get("where") or {})
    facets = [None]
    if "facet" in chart:
        facets = list(dict.fromkeys(cols[chart["facet"]][i] for i in rows))
    fig = Figure(figsize=(min(4.8 * len(facets) + 1.2, 16), 4.4), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(facets), squeeze=False)[0]
    for ax, value in zip(axes, facets):
        sel = rows if value is None else [i for i in rows if cols[chart["facet"]][i] == value]
        {"map": _map, "lines": _lines, "failure": _failure}[chart["kind"]](ax, fig, cols, sel, chart)
        if value is not None:
            ax.set_title(literal_mpl(f"{chart['facet']} = {value}"), fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    if chart.get("title"):
        fig.suptitle(literal_mpl(chart["title"]), fontsize=10)
    return fig


def write(cols: dict[str, list], chart: dict, path, force: bool = False):
    """Draw ``chart`` into ``path`` (.png, .svg or .pdf), atomically."""
    from pathlib import Path

    from labbench.readout.figures import FORMATS
    from labbench.safe_write import output_path, replacing

    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise UserError(f"chart {path}: use a .png, .svg or .pdf file name")
    output_path(path, force=force)
    fig = draw(cols, chart)
    with replacing(path, force=force) as tmp:
        fig.savefig(tmp, dpi=110, format=path.suffix[1:].lower())
    return path


def _need(cols: dict, name: str) -> None:
    if name not in cols:
        raise UserError(f"the table has no column {name!r}; columns: {', '.join(cols)}")


def _where(cols: dict, where: dict) -> list[int]:
    n = len(cols.get("key", []))
    rows = list(range(n))
    for k, v in where.items():
        rows = [i for i in rows if cols[k][i] == v]
    return rows


def _numbers(values) -> np.ndarray:
    return np.array([np.nan if not isinstance(v, (int, float)) or isinstance(v, bool) else v
                     for v in values], float)


def _axis(ax, which: str, values: np.ndarray, chart: dict, name: str) -> None:
    flag = chart.get(f"log_{which}")
    finite = values[np.isfinite(values)]
    if flag is None:
        flag = bool(finite.size) and finite.min() > 0 and finite.max() / finite.min() > 50
    if flag:
        (ax.set_xscale if which == "x" else ax.set_yscale)("log")
    (ax.set_xlabel if which == "x" else ax.set_ylabel)(literal_mpl(name), fontsize=8)
    ax.tick_params(labelsize=7)


def _ok(cols: dict, sel: list[int]) -> np.ndarray:
    status = cols.get("status", ["ok"] * len(cols.get("key", [])))
    return np.array([status[i] == "ok" for i in sel], bool)


def _xy(cols, sel, chart, y):
    x = _numbers([cols[chart["x"]][i] for i in sel])
    return x, _numbers([cols[y][i] for i in sel])


def _map(ax, fig, cols, sel, chart):
    y = chart["y"]
    x, yv = _xy(cols, sel, chart, y)
    ok = _ok(cols, sel)
    if "color" in chart:
        raw = [cols[chart["color"]][i] for i in sel]
        c = _numbers(raw) if not all(isinstance(v, bool) for v in raw if v is not None) else \
            np.array([np.nan if v is None else float(v) for v in raw])
        finite = c[np.isfinite(c)]
        log = chart.get("log_color")
        if log is None:
            log = bool(finite.size) and finite.min() > 0 and finite.max() / finite.min() > 50
        from matplotlib.colors import LogNorm, Normalize

        norm = (LogNorm(finite.min(), finite.max()) if log and finite.size
                else Normalize(*(finite.min(), finite.max()) if finite.size else (0, 1)))
        good = ok & np.isfinite(c)
        sc = ax.scatter(x[good], yv[good], c=c[good], cmap="viridis", norm=norm, s=36)
        fig.colorbar(sc, ax=ax, shrink=0.85).set_label(literal_mpl(chart["color"]), fontsize=8)
        ax.scatter(x[ok & ~np.isfinite(c)], yv[ok & ~np.isfinite(c)], marker="o",
                   facecolors="none", edgecolors="0.5", s=36, label="no value")
    else:
        ax.scatter(x[ok], yv[ok], s=36, label="ok")
    if (~ok).any():
        ax.scatter(x[~ok], yv[~ok], marker="x", color="tab:red", s=36, label="not ok (status)")
    _axis(ax, "x", x, chart, chart["x"])
    _axis(ax, "y", yv, chart, y)
    if (~ok).any() or "color" in chart and not np.isfinite(c).all():
        ax.legend(fontsize=7)


def _lines(ax, fig, cols, sel, chart):
    ys = chart["y"] if isinstance(chart["y"], list) else [chart["y"]]
    groups = {None: sel}
    if "series" in chart:
        groups = {}
        for i in sel:
            groups.setdefault(cols[chart["series"]][i], []).append(i)
    all_x, all_y = [], []
    for n, (g, idx) in enumerate(groups.items()):
        for m, y in enumerate(ys):
            x, yv = _xy(cols, idx, chart, y)
            order = np.argsort(x, kind="stable")
            x, yv, ok = x[order], yv[order], _ok(cols, idx)[order]
            label = ", ".join(str(s) for s in (g, y if len(ys) > 1 else None) if s is not None)
            color = f"C{(n * len(ys) + m) % 10}"
            ax.plot(x[ok], yv[ok], "o-", color=color, ms=4, lw=1.2, label=literal_mpl(label) or None)
            if (~ok).any():
                ax.plot(x[~ok], np.where(np.isfinite(yv[~ok]), yv[~ok], np.nan), "x", color=color)
            all_x.append(x)
            all_y.append(yv)
    _axis(ax, "x", np.concatenate(all_x), chart, chart["x"])
    _axis(ax, "y", np.concatenate(all_y), chart, ys[0] if len(ys) == 1 else "value")
    if len(groups) > 1 or len(ys) > 1:
        ax.legend(fontsize=7)


def _failure(ax, fig, cols, sel, chart):
    x, yv = _xy(cols, sel, chart, chart["y"])
    metric = _numbers([cols[chart["metric"]][i] for i in sel])
    ok = _ok(cols, sel)
    warned = np.zeros(len(sel), bool)
    if "warnings" in chart:
        warned = _numbers([cols[chart["warnings"]][i] for i in sel]) > 0
    over = ~(metric <= float(chart["threshold"]))  # a missing metric counts as over
    category = np.where(~ok, 3, np.where(over, 1, np.where(warned, 2, 0)))
    for k, (label, color) in enumerate(CATEGORIES):
        m = category == k
        if m.any():
            ax.scatter(x[m], yv[m], color=color, s=40, marker="x" if k == 3 else "o",
                       label=literal_mpl(f"{label} ({int(m.sum())})"))
    _axis(ax, "x", x, chart, chart["x"])
    _axis(ax, "y", yv, chart, chart["y"])
    ax.legend(fontsize=7, title=literal_mpl(f"{chart['metric']} vs {chart['threshold']:g}"),
              title_fontsize=7)


def default_file(chart: dict, n: int) -> str:
    return chart.get("file") or f"{chart['kind']}-{n}.png"
