"""Sweeps tab: run a sweep spec (the engine of ``labbench sweep``, with progress and Cancel),
or open a table one wrote; its points on a map, the row of the point under the mouse, and
a point opened as a session (the one the sweep kept, or the point re-run now).

**Open spec...** takes a ``SPEC.toml`` (docs/sweep.md); **Run sweep** computes its points
missing from its table (``<sessions folder>/../sweeps/<spec>.sweep``, as the command
line's default ``sweeps/<spec>.sweep`` beside ``sessions/``) in a child process
(``labbench.gui.sweep_runner``), the map filling in as rows come; **Cancel** stops it as
Ctrl-C stops the command (the finished rows kept; Run again computes the rest). **Open
table...** takes a ``NAME.sweep`` folder, read whole when opened or reloaded (so a sweep
still running elsewhere can be watched). x, y and colour are picked among its columns,
first as the spec's first chart draws them, else its varied parameters against a varied
result; axes are labelled with units. Rows whose status is not "ok" are red crosses, as
on the sweep's own charts (``labbench.sweep.charts``). Hovering a point shows its row;
clicking selects it for the buttons.

Re-running a point is ``labbench.sweep.point.compute_row`` with its session
recorded: the same pure task a worker ran, so its row must equal the table's
(the times aside). The view says whether it does, then asks for the session.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from labbench.gui.keep_alive import keep_plots
from labbench.gui.labels import never_widens, set_text
from labbench.gui.live_plots import no_si_prefix
from labbench.gui.sweep_runner import SweepRun
from labbench.gui.worker import Mailbox, describe_error, run_in_background
from labbench.readout.numfmt import fmt

NONE = "(none)"
NOT_OK_BRUSH = "#d62728"
NO_VALUE_BRUSH = "#bbbbbb"
CMAP = pg.colormap.get("viridis")
# categories: matplotlib's tab10 without its red (red is "not ok")
CATEGORY_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2",
                    "#7f7f7f", "#bcbd22", "#17becf")
POLL_MS = 100  # how often the mailbox of a re-run or a sweep under way is read
REREAD_S = 1.0  # how often the table of a sweep under way is read again
NOTHING_OPEN = ("no sweep open: Open spec... runs a sweep spec (SPEC.toml) here; Open table... "
                "shows a NAME.sweep folder that labbench sweep wrote")
LOG_SPAN = 50  # an axis of positive values spanning more than this ratio starts as log
SHADES = 64  # of the colour map


def numeric(values: list) -> bool:
    """A column that can be an axis: numbers (or none), at least one."""
    kinds = [v for v in values if v is not None]
    return bool(kinds) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                               for v in kinds)


def as_float(values: list) -> np.ndarray:
    return np.array([np.nan if v is None else float(v) for v in values], float)


def wide_positive(values: np.ndarray) -> bool:
    v = values[np.isfinite(values)]
    return bool(v.size and v.min() > 0 and v.max() / v.min() > LOG_SPAN)


def colours(values: list) -> tuple[list, str]:
    """A brush per value and a one-line legend: numbers on viridis (log when they span
    over LOG_SPAN), anything else (text, yes/no) one colour per distinct value. Brushes
    are shared (SHADES of viridis): the scatter renders each distinct brush once."""
    if numeric(values):
        v = as_float(values)
        log = wide_positive(v)
        u = np.log10(v) if log else v
        lo, hi = np.nanmin(u), np.nanmax(u)
        t = (u - lo) / (hi - lo) if hi > lo else np.zeros_like(u)
        shade = np.rint(np.nan_to_num(t, nan=-1.0) * (SHADES - 1)).astype(int)
        palette = [pg.mkBrush(c) for c in CMAP.getLookupTable(nPts=SHADES, alpha=False)]
        grey = pg.mkBrush(NO_VALUE_BRUSH)
        brushes = [palette[k] if k >= 0 else grey for k in shade.tolist()]
        scale = "log " if log else ""
        return brushes, (f"{scale}colour: dark blue {fmt(np.nanmin(v))} .. yellow "
                         f"{fmt(np.nanmax(v))}; grey: no value")
    levels = list(dict.fromkeys(fmt(v) for v in values))
    table = {lev: pg.mkBrush(CATEGORY_COLOURS[i % len(CATEGORY_COLOURS)])
             for i, lev in enumerate(levels)}
    legend = ", ".join(f"<span style='color:{table[lev].color().name()}'>&#9679;</span> {lev}"
                       for lev in levels[:12])
    return [table[fmt(v)] for v in values], legend


def column_label(name: str, variable: str | None = None) -> str:
    """A table column as a person reads it, with its unit: ``res.loop_fit.ci95.m.0`` ->
    "loop fit: m, 95 % low [kg]", ``truth.k_max`` -> "truth: K_max [N/m]",
    ``K_frac_k_max`` -> "K / K_max"; a stability probe's boundary in the unit of the
    ``variable`` it probed (its rows' ``res.variable``: K in N/m, td in s)."""
    from labbench.gui.protocol_panel import _unit

    parts = name.split(".")
    where = {"res": "", "truth": "truth: "}.get(parts[0])
    if where is not None:
        parts = parts[1:]
    else:
        where = ""
    end = ""
    if len(parts) >= 2 and parts[-1] in ("0", "1", "n"):
        end = {"0": " low", "1": " high", "n": " (count)"}[parts.pop()]
    if len(parts) >= 2 and parts[-2] == "ci95":
        end = ", 95 %" + end
        parts = parts[:-2] + parts[-1:]
    key = parts[-1] if parts else name
    group = " ".join(p.replace("_", " ") for p in parts[:-1])
    unit, word = COLUMN_UNITS.get(key, (None, None))
    if key in BOUNDARY_COLUMNS:
        unit, word = BOUNDARY_UNITS.get(variable, ""), key.replace("_", " ")
    if unit is None:
        unit, _low, word = _unit(key)
    if end.endswith("(count)"):
        unit = ""
    text = f"{where}{group + ': ' if group else ''}{word}{end}"
    return f"{text} [{unit}]" if unit else text


# a stability probe's results in the unit of its probed variable (res.variable)
BOUNDARY_COLUMNS = ("measured_boundary", "measured_crossing", "exact_boundary",
                    "approx_boundary", "measured_ci95", "bracket")
BOUNDARY_UNITS = {"K": "N/m", "td": "s"}
# result keys whose unit the name's suffix does not say: key -> (unit, words)
COLUMN_UNITS = {
    "m": ("kg", "m"), "b": ("N s/m", "b"), "K": ("N/m", "K"), "B": ("N s/m", "B"),
    "k_max": ("N/m", "K_max"), "k_max_approx": ("N/m", "K_max (paper's approximation)"),
    "K_frac_k_max": ("", "K / K_max"), "coulomb": ("N", "Coulomb friction"),
    "offset": ("N", "force offset"), "rms_residual": ("N", "rms force residual"),
    "explained": ("", "force variance explained (fraction)"),
    **{k: ("rad/s", k.replace("_star", "*").replace("_", " "))
       for k in ("ws_star", "wb_star", "ws_star_measured", "ws_star_predicted", "ws_star_eq5",
                 "wb_star_measured", "wb_star_predicted", "wb_star_w0")},
    **{k: ("", k.replace("_", " ") + " (fraction)")
       for k in ("median_rel", "max_rel", "m_rel", "b_rel", "worst_rel", "fit_m_rel",
                 "fit_b_rel", "residual_rms")},
}


class SweepView(QtWidgets.QWidget):
    """``open_spec(file)`` and Run, or ``open_table(folder)``; then pick axes.
    ``session_requested`` carries the path of a session to show (the window replays it)."""

    session_requested = QtCore.Signal(str)

    def __init__(self, session_dir, parent=None):
        super().__init__(parent)
        self.session_dir = Path(session_dir)  # where re-run points are recorded
        self.folder: Path | None = None
        self.cols: dict[str, list] = {}
        self.spec: dict | None = None
        self.spec_path: Path | None = None  # the spec Run runs
        self.run: SweepRun | None = None
        self.hovered: int | None = None
        self.selected: int | None = None
        self._rerun_of: dict = {}  # the table's row of the point being re-run
        self._reread = 0.0  # when the running sweep's table was read last
        self._parts_read = -1  # how many part files it had then
        self.mailbox = Mailbox()
        self.poll = QtCore.QTimer(self)
        self.poll.setInterval(POLL_MS)
        self.poll.timeout.connect(self._drain)

        self.table_label = QtWidgets.QLabel(NOTHING_OPEN)
        self.table_label.setWordWrap(True)
        self.open_spec_button = QtWidgets.QPushButton("Open spec...")
        self.open_spec_button.setToolTip("a sweep spec (SPEC.toml, docs/sweep.md): run it here")
        self.open_spec_button.clicked.connect(self._choose_spec)
        self.open_table_button = QtWidgets.QPushButton("Open table...")
        self.open_table_button.setToolTip("a NAME.sweep folder that labbench sweep (or this tab) wrote")
        self.open_table_button.clicked.connect(self._choose_table)
        self.reload_button = QtWidgets.QPushButton("Reload")
        self.reload_button.setToolTip("read the table again (a sweep still running adds rows)")
        self.reload_button.clicked.connect(lambda: self.folder and self.open_table(self.folder))
        self.workers = QtWidgets.QSpinBox()
        self.workers.setRange(0, 256)
        self.workers.setValue(os.cpu_count() or 1)
        self.workers.setPrefix("workers: ")
        self.workers.setToolTip("local worker processes, as labbench sweep --workers "
                                "(0: computed in one process, no Dask)")
        self.limit = QtWidgets.QSpinBox()  # a slice of a long spec from the page
        self.limit.setRange(0, 1_000_000)
        self.limit.setSpecialValueText("points: all")
        self.limit.setPrefix("points: at most ")
        self.limit.setToolTip("how many of the points still to compute Run computes now (the "
                              "rest at the next Run, as after Cancel); all: every one")
        self.run_button = QtWidgets.QPushButton("Run sweep")
        self.run_button.clicked.connect(self.run_spec)
        self.cancel_button = QtWidgets.QPushButton("Cancel")
        self.cancel_button.setToolTip("stop after the points under way; the finished rows stay "
                                      "in the table and Run computes the rest")
        self.cancel_button.clicked.connect(self.cancel_run)
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setTextVisible(False)
        self.progress_text = never_widens(QtWidgets.QLabel(""), 2)
        self.x, self.y, self.color = (QtWidgets.QComboBox() for _ in range(3))
        self.log_x, self.log_y = QtWidgets.QCheckBox("log"), QtWidgets.QCheckBox("log")
        self._picked = False  # the person chose the axes: a reload keeps them
        for w in (self.x, self.y, self.color):
            w.currentIndexChanged.connect(self._axes_picked)
        for w in (self.log_x, self.log_y):
            w.toggled.connect(self.redraw)

        self.plot = pg.PlotWidget()
        self.plot.showGrid(x=True, y=True, alpha=0.3)
        for side in ("bottom", "left"):  # the numbers as they are: no "(x0.001)" scaling
            no_si_prefix(self.plot.getAxis(side))
        self.points = pg.ScatterPlotItem(size=9, hoverable=True, tip=None, hoverSize=14,
                                         hoverPen=pg.mkPen("k", width=2))
        self.points.sigHovered.connect(self._on_hover)
        self.points.sigClicked.connect(self._on_click)
        self.plot.addItem(self.points)
        keep_plots(self.plot)
        self.legend = QtWidgets.QLabel()
        self.legend.setWordWrap(True)

        self.row_title = QtWidgets.QLabel("hover a point to see its row; click to select it")
        self.row_view = QtWidgets.QTableWidget(0, 2)
        self.row_view.setHorizontalHeaderLabels(("column", "value"))
        self.row_view.horizontalHeader().setStretchLastSection(True)
        self.row_view.verticalHeader().setVisible(False)
        self.row_view.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.open_button = QtWidgets.QPushButton("Open session")
        self.open_button.setToolTip("the session the sweep kept for this point (--keep-sessions)")
        self.open_button.clicked.connect(self.open_selected)
        self.rerun_button = QtWidgets.QPushButton("Re-run as session")
        self.rerun_button.setToolTip(f"compute this point again, recording its session in "
                                     f"{self.session_dir}, then open it")
        self.rerun_button.clicked.connect(self.rerun_selected)
        self.note = QtWidgets.QLabel()
        self.note.setWordWrap(True)

        top = QtWidgets.QHBoxLayout()
        for w in (self.open_spec_button, self.open_table_button, self.reload_button):
            top.addWidget(w)
        top.addWidget(self.table_label, 1)
        running = QtWidgets.QHBoxLayout()
        for w in (self.workers, self.limit, self.run_button, self.cancel_button):
            running.addWidget(w)
        running.addWidget(self.progress, 1)
        axes = QtWidgets.QHBoxLayout()
        for text, combo, log in (("x", self.x, self.log_x), ("y", self.y, self.log_y),
                                 ("colour", self.color, None)):
            axes.addWidget(QtWidgets.QLabel(f"{text}:"))
            axes.addWidget(combo, 1)
            if log is not None:
                axes.addWidget(log)
        left = QtWidgets.QVBoxLayout()
        left.addLayout(axes)
        left.addWidget(self.plot, 1)
        left.addWidget(self.legend)
        right = QtWidgets.QVBoxLayout()
        right.addWidget(self.row_title)
        right.addWidget(self.row_view, 1)
        buttons = QtWidgets.QHBoxLayout()
        buttons.addWidget(self.open_button)
        buttons.addWidget(self.rerun_button)
        right.addLayout(buttons)
        body = QtWidgets.QSplitter()
        for lay in (left, right):
            w = QtWidgets.QWidget()
            w.setLayout(lay)
            body.addWidget(w)
        body.setSizes([800, 420])
        outer = QtWidgets.QVBoxLayout(self)
        outer.addLayout(top)
        outer.addLayout(running)
        outer.addWidget(self.progress_text)
        outer.addWidget(body, 1)
        outer.addWidget(self.note)
        self._sync_buttons()

    # ----- a spec, run here ---------------------------------------------------------------
    def _choose_spec(self):
        from labbench.gui.dialogs import choose_file

        start = str(self.spec_path.parent) if self.spec_path else str(Path.cwd())
        path = choose_file(self, "Sweep spec (SPEC.toml, docs/sweep.md)", start,
                           "sweep spec (*.toml);;any file (*)")
        if path:
            self.open_spec(path)

    def table_of(self, spec_path) -> Path:
        """Where Run writes a spec's table: ``sweeps/<spec>.sweep`` beside the sessions
        folder (the command line's default, beside ``sessions/``)."""
        from labbench.sweep.table import SUFFIX

        return self.session_dir.parent / "sweeps" / f"{Path(spec_path).stem}{SUFFIX}"

    def open_spec(self, path) -> bool:
        """Read spec ``path`` (False and the reason shown when it is not one); show its
        table if it has one already, and offer Run."""
        from labbench.sweep.spec import load_spec
        from labbench.sweep.table import done_keys, is_table

        try:
            spec = load_spec(path)
            n = len({p.key(spec) for p in spec.points()})
        except Exception as exc:  # noqa: BLE001 - a bad spec is a message, not a crash
            self._say(f"{path}: {describe_error(exc)}", error=True)
            return False
        self.spec_path = Path(path)
        table = self.table_of(path)
        done = len(done_keys(table)) if is_table(table) else 0
        if done:
            self.open_table(table)
        what = spec.protocol or spec.analysis
        self.table_label.setText(f"spec {self.spec_path.name}: {spec.name}, {n} points of "
                                 f"{spec.kind} {what}; table {table}")
        self._show_progress(done, n, "" if not done else "already in the table; Run computes the rest")
        self._say(f"spec {self.spec_path.name} read: press Run sweep")
        self._sync_buttons()
        return True

    def run_spec(self) -> None:
        """Compute the spec's points missing from its table, in a child process."""
        if self.spec_path is None or self.run is not None:
            return
        table = self.table_of(self.spec_path)
        table.parent.mkdir(parents=True, exist_ok=True)
        self._parts_read = -1
        self.run = SweepRun(self.spec_path, table, self.workers.value(),
                            lambda kind, value: self.mailbox.put(f"sweep {kind}", value),
                            limit=self.limit.value())
        self.poll.start()
        self._say(f"running {self.spec_path.name} into {table} ...")
        self._sync_buttons()

    def cancel_run(self) -> None:
        if self.run is not None:
            self.run.cancel()
            self.cancel_button.setEnabled(False)
            self._say("cancelling: the points under way finish first ...")

    def _show_progress(self, done: int, total: int, text: str = "") -> None:
        self.progress.setValue(int(1000 * done / total) if total else 0)
        set_text(self.progress_text, f"{done} of {total} points" + (f", {text}" if text else ""))

    def _on_run_progress(self, p: dict) -> None:
        eta = p.get("eta_s")
        self._show_progress(p["done"], p["total"], f"{p['failed']} not ok, {p['elapsed_s']:.0f} s"
                            + (f", about {eta:.0f} s left" if eta is not None else ""))
        self._fill_in()

    def _fill_in(self) -> None:
        """The map fills in as rows reach the table (the child writes them at least once a
        second, ``sweep_runner.FILL_S``): read again once it has new parts, at most every
        REREAD_S (a poll that found nothing new did not count: the rows of a sweep of five
        0.4 s points, written at 1.2 s, waited for its end)."""
        from labbench.sweep.table import is_table, parts

        now = time.monotonic()
        if self.run is None or now - self._reread < REREAD_S:
            return
        table = self.table_of(self.spec_path)
        if is_table(table) and len(parts(table)) != self._parts_read:
            self._reread, self._parts_read = now, len(parts(table))
            self.open_table(table)

    def _on_run_end(self, kind: str, value) -> None:
        self.run = None
        self._sync_buttons()
        if kind == "error":
            self._say(f"sweep failed: {value}", error=True)
            return
        done = value["before"] + value["computed"]
        why = value.get("reason") if value["stopped"] else ""
        state = ("stopped: " + why if why else "stopped") if value["stopped"] else "complete"
        self._show_progress(done, value["total"], f"{value['failed']} not ok, {state}")
        self.open_table(value["table"])
        self._say(f"sweep {state}: {done} of {value['total']} points in {value['table']} "
                  f"({value['computed']} computed now in {value['wall_s']:.0f} s)"
                  + ("; Run computes the rest" if value["stopped"] else ""))

    def close_run(self) -> None:
        """The window closes: a sweep under way stops as Cancel stops it."""
        if self.run is not None:
            self.run.close()
            self.run = None

    # ----- the table ------------------------------------------------------------------------
    def _choose_table(self):
        from labbench.gui.dialogs import choose_folder

        start = str(self.folder.parent) if self.folder else str(Path.cwd())
        d = choose_folder(self, "Sweep table: a NAME.sweep folder (labbench sweep writes one)", start)
        if d:
            self.open_table(d)

    def open_table(self, folder) -> bool:
        """Read the table in ``folder``; False (and the reason shown) when it is none."""
        from labbench.errors import UserError
        from labbench.sweep import charts, table

        folder = Path(folder)
        try:
            if not table.is_table(folder):
                raise UserError(f"{folder} is not a sweep table (labbench sweep writes one)")
            cols = charts.columns(table.read_table(folder))
            try:
                spec = table.read_spec(folder)
            except UserError:
                spec = None  # rows without their spec: shown, not re-run
        except Exception as exc:  # noqa: BLE001 - an unreadable table is a message, not a crash
            self._say(describe_error(exc), error=True)
            return False
        keep = (self.x.currentData(), self.y.currentData(), self.color.currentData()) \
            if folder == self.folder and self._picked else None
        self._picked = self._picked and folder == self.folder
        self.folder, self.cols, self.spec = folder, cols, spec
        self.hovered = self.selected = None
        n = len(cols.get("key", []))
        name = (spec or {}).get("sweep", {}).get("name", folder.stem)
        if self.run is None:
            self.table_label.setText(f"table {folder}: {name}, {n} rows")
        self._fill_axes(keep)
        self._show_row(None)
        if self.run is None:
            self._say(f"{n} rows read from {folder.name}")
        return True

    def _fill_axes(self, keep) -> None:
        names = [c for c in self.cols if c != "key" and numeric(self.cols[c])]
        colour = [NONE] + [c for c in self.cols if c not in ("key", "params_json", "error")]
        x, y, c = keep or self._default_axes(names)
        for combo, items, pick in ((self.x, names, x), (self.y, names, y),
                                   (self.color, colour, c)):
            combo.blockSignals(True)
            combo.clear()
            for item in items:
                combo.addItem(column_label(item, self._variable()) if item != NONE else NONE, item)
            index = combo.findData(pick)
            combo.setCurrentIndex(index if index >= 0 else 0)
            combo.blockSignals(False)
        self._axes_changed()

    def _variable(self) -> str | None:
        """The variable a stability sweep's probes stepped, where all its rows say one."""
        found = {v for v in self.cols.get("res.variable", []) if v is not None}
        return found.pop() if len(found) == 1 else None

    def _default_axes(self, names: list[str]) -> tuple[str, str, str]:
        """The spec's first chart with numeric x and y (a lines chart's first y; a failure
        chart's metric), else the first varied parameter (not a seed, if another varies)
        against the first varied result (``truth.*``, then ``res.*``)."""
        for c in (self.spec or {}).get("chart", []):
            y = c.get("y") if c.get("kind") != "failure" else c.get("metric")
            y = y[0] if isinstance(y, list) and y else y
            if c.get("x") in names and y in names:
                return c["x"], y, c.get("color") or c.get("series") or "status"
        varied = [n for n in names if len(set(self.cols[n])) > 1]
        params = []
        if self.cols.get("params_json"):
            params = [p for p in json.loads(self.cols["params_json"][0])["params"] if p in varied]
        params.sort(key=lambda p: "seed" in p)  # a seed last: what varies on purpose first
        results = [n for n in varied if n.startswith("truth.")] + \
                  [n for n in varied if n.startswith("res.")]
        others = [n for n in varied if n not in params and n not in results and n != "index"]
        pick = [*dict.fromkeys(params[:1] + results[:1] + params[1:] + others + names)][:2]
        pick += ["", ""]
        colour = params[1] if len(params) > 1 else "status"
        return pick[0], pick[1], colour

    def _axes_picked(self, *_):
        self._picked = True
        self._axes_changed()

    def _axes_changed(self, *_):
        for axis, combo, box in (("x", self.x, self.log_x), ("y", self.y, self.log_y)):
            box.blockSignals(True)
            box.setChecked(self._log_default(axis, combo.currentData()))
            box.blockSignals(False)
        self.redraw()

    def _log_default(self, axis: str, name: str) -> bool:
        """As the spec's charts draw this column on this axis, else log when its positive
        values span more than LOG_SPAN."""
        for c in (self.spec or {}).get("chart", []):
            if c.get(axis) == name and f"log_{axis}" in c:
                return bool(c[f"log_{axis}"])
        return wide_positive(as_float(self.cols.get(name, [])))

    # ----- the map -------------------------------------------------------------------------
    def redraw(self, *_):
        """Plot the rows with a value on both axes (a positive one on a log axis)."""
        xname, yname = self.x.currentData(), self.y.currentData()
        if xname not in self.cols or yname not in self.cols:
            self.points.setData([], [])
            return
        x, y = as_float(self.cols[xname]), as_float(self.cols[yname])
        logs = (self.log_x.isChecked(), self.log_y.isChecked())
        keep = np.isfinite(x) & np.isfinite(y)
        for v, log in ((x, logs[0]), (y, logs[1])):
            if log:
                keep &= v > 0
        rows = np.flatnonzero(keep)
        px = np.log10(x[rows]) if logs[0] else x[rows]
        py = np.log10(y[rows]) if logs[1] else y[rows]
        status = self.cols.get("status", ["ok"] * len(x))
        ok = np.array([status[i] == "ok" for i in rows], bool)
        legend = "red crosses: status not ok"
        if self.color.currentData() in self.cols:
            brushes, legend = colours([self.cols[self.color.currentData()][i] for i in rows])
            legend += "; red crosses: status not ok"
        else:
            brushes = [pg.mkBrush("#1f5fa8")] * len(rows)
        red = pg.mkBrush(NOT_OK_BRUSH)
        brushes = [b if good else red for b, good in zip(brushes, ok)]
        symbols = ["o" if good else "x" for good in ok]
        self.plot.getPlotItem().setLogMode(*logs)
        self.points.setData(x=px, y=py, data=rows, brush=brushes, symbol=symbols,
                            pen=pg.mkPen(None))
        self.plot.setLabel("bottom", column_label(xname, self._variable()))
        self.plot.setLabel("left", column_label(yname, self._variable()))
        self.plot.getPlotItem().enableAutoRange()
        hidden = len(x) - len(rows)
        self.legend.setText(legend + (f"; {hidden} rows without a value to plot" if hidden else ""))

    def _on_hover(self, _item, points, _ev):
        self.hovered = int(points[0].data()) if len(points) else None
        self._show_row(self.hovered if self.hovered is not None else self.selected)

    def _on_click(self, _item, points, _ev):
        if len(points):
            self.select(int(points[0].data()))

    def select(self, row: int) -> None:
        self.selected = row
        self._show_row(row)
        self._sync_buttons()

    def row(self, i: int) -> dict:
        return {name: values[i] for name, values in self.cols.items()}

    def _show_row(self, i: int | None) -> None:
        if i is None:
            self.row_view.setRowCount(0)
            self.row_title.setText("hover a point to see its row; click to select it")
            return
        r = self.row(i)
        how = "selected" if i == self.selected and self.hovered is None else "under the mouse"
        self.row_title.setText(f"point {r.get('index', i)} ({how})")
        self.row_view.setRowCount(len(r))
        for j, (name, value) in enumerate(r.items()):
            self.row_view.setItem(j, 0, QtWidgets.QTableWidgetItem(name))
            self.row_view.setItem(j, 1, QtWidgets.QTableWidgetItem(fmt(value, 6)))

    # ----- a point as a session -------------------------------------------------------------
    def _kept_session(self) -> Path | None:
        if self.selected is None:
            return None
        p = self.row(self.selected).get("session")
        return Path(p) if p else None

    def _sync_buttons(self) -> None:
        busy = bool(self._rerun_of)
        self.open_button.setEnabled(self._kept_session() is not None and not busy)
        runs = (self.spec or {}).get("sweep", {}).get("kind") == "run"
        self.rerun_button.setEnabled(self.selected is not None and runs and not busy)
        running = self.run is not None
        self.run_button.setEnabled(self.spec_path is not None and not running)
        self.cancel_button.setEnabled(running)
        self.workers.setEnabled(not running)
        self.limit.setEnabled(not running)
        for w in (self.open_spec_button, self.open_table_button):
            w.setEnabled(not running)
        if self.spec is not None and not runs:
            self.rerun_button.setToolTip("an analysis sweep's points are analyses of exact "
                                         "records, not runs: there is no session to record")

    def open_selected(self) -> None:
        path = self._kept_session()
        if path is None:
            return
        if not path.is_file():
            self._say(f"the session {path} is not there (moved or deleted?); "
                      "Re-run as session records it again", error=True)
            return
        self.session_requested.emit(str(path))

    def rerun_selected(self) -> None:
        """Compute the selected point again with its session recorded (on a worker thread)."""
        if self.selected is None or self.spec is None:
            return
        from labbench.sweep.point import compute_row

        r = self.row(self.selected)
        point = {"index": r["index"], **json.loads(r["params_json"])}
        self.session_dir.mkdir(parents=True, exist_ok=True)
        run_in_background(self.mailbox, "rerun", compute_row, self.spec, point,
                          str(self.session_dir))
        self._rerun_of = r
        self.poll.start()
        self._sync_buttons()
        self._say(f"re-running point {r['index']} ...")

    def _drain(self) -> None:
        for kind, value in self.mailbox.drain():
            if kind == "sweep progress":
                self._on_run_progress(value)
            elif kind in ("sweep done", "sweep error"):
                self._on_run_end(kind.split()[1], value)
            elif value[0] == "rerun":  # ("result" | "error", ("rerun", row or message))
                old, self._rerun_of = self._rerun_of, {}
                self._sync_buttons()
                if kind == "error":
                    self._say(f"re-run failed: {value[1]}", error=True)
                else:
                    self._rerun_done(old, value[1])
        self._fill_in()  # between progress messages too: a row flushed after the last one
        if self.run is None and not self._rerun_of:
            self.poll.stop()

    def _rerun_done(self, old: dict, row: dict) -> None:
        from labbench.sweep.point import TIME_COLUMNS

        differ = [k for k in dict.fromkeys([*old, *row])
                  if k not in (*TIME_COLUMNS, "session") and old.get(k) != row.get(k)]
        same = ("its row equals the table's (times aside)" if not differ else
                f"its row differs from the table's in {', '.join(differ[:8])}")
        if not row.get("session"):
            self._say(f"re-run of point {row['index']}: {row['status']}, no session recorded "
                      f"({row.get('error')}); {same}", error=True)
            return
        self._say(f"re-run of point {row['index']}: session {row['session']}; {same}",
                  error=bool(differ))
        self.session_requested.emit(row["session"])

    def _say(self, text: str, error: bool = False) -> None:
        self.note.setText(text)
        self.note.setStyleSheet("QLabel { color: #b00020; }" if error else "")
