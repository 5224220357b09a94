"""Sweeps tab: a sweep table's points on a map, the row of the point under the mouse, and a
point opened as a session (the one the sweep kept, or the point re-run now).

A table is the folder ``labbench sweep`` writes (``labbench.sweep.table``), read
whole when opened or reloaded (so a sweep still running can be watched). x, y and
colour are picked among its columns; rows whose status is not "ok" are red
crosses, as on the sweep's own charts (``labbench.sweep.charts``). Hovering a
point shows its row; clicking selects it for the buttons.

Re-running a point is ``labbench.sweep.point.compute_row`` with its session
recorded: the same pure task a worker ran, so its row must equal the table's
(the times aside). The view says whether it does, then asks for the session.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from labbench.gui.keep_alive import keep_plots
from labbench.gui.worker import Mailbox, describe_error, run_in_background
from labbench.numfmt import fmt

NONE = "(none)"
NOT_OK_BRUSH = "#d62728"
NO_VALUE_BRUSH = "#bbbbbb"
CMAP = pg.colormap.get("viridis")
# categories: matplotlib's tab10 without its red (red is "not ok")
CATEGORY_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2",
                    "#7f7f7f", "#bcbd22", "#17becf")
POLL_MS = 100  # how often a re-run's mailbox is read
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


class SweepView(QtWidgets.QWidget):
    """``open_table(folder)``, then pick axes; ``session_requested`` carries the path of a
    session to show (the window replays it)."""

    session_requested = QtCore.Signal(str)

    def __init__(self, session_dir, parent=None):
        super().__init__(parent)
        self.session_dir = Path(session_dir)  # where re-run points are recorded
        self.folder: Path | None = None
        self.cols: dict[str, list] = {}
        self.spec: dict | None = None
        self.hovered: int | None = None
        self.selected: int | None = None
        self._rerun_of: dict = {}  # the table's row of the point being re-run
        self.mailbox = Mailbox()
        self.poll = QtCore.QTimer(self)
        self.poll.setInterval(POLL_MS)
        self.poll.timeout.connect(self._drain)

        self.table_label = QtWidgets.QLabel("no sweep table open")
        open_button = QtWidgets.QPushButton("Open table...")
        open_button.clicked.connect(self._choose)
        self.reload_button = QtWidgets.QPushButton("Reload")
        self.reload_button.setToolTip("read the table again (a sweep still running adds rows)")
        self.reload_button.clicked.connect(lambda: self.folder and self.open_table(self.folder))
        self.x, self.y, self.color = (QtWidgets.QComboBox() for _ in range(3))
        self.log_x, self.log_y = QtWidgets.QCheckBox("log"), QtWidgets.QCheckBox("log")
        for w in (self.x, self.y, self.color):
            w.currentTextChanged.connect(self._axes_changed)
        for w in (self.log_x, self.log_y):
            w.toggled.connect(self.redraw)

        self.plot = pg.PlotWidget()
        self.plot.showGrid(x=True, y=True, alpha=0.3)
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
        top.addWidget(open_button)
        top.addWidget(self.reload_button)
        top.addWidget(self.table_label, 1)
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
        outer.addWidget(body, 1)
        outer.addWidget(self.note)
        self._sync_buttons()

    # ----- the table ------------------------------------------------------------------------
    def _choose(self):
        start = str(self.folder.parent) if self.folder else str(Path.cwd())
        d = QtWidgets.QFileDialog.getExistingDirectory(self, "Sweep table (NAME.sweep)", start)
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
        keep = (self.x.currentText(), self.y.currentText(), self.color.currentText()) \
            if folder == self.folder else None
        self.folder, self.cols, self.spec = folder, cols, spec
        self.hovered = self.selected = None
        n = len(cols.get("key", []))
        name = (spec or {}).get("sweep", {}).get("name", folder.stem)
        self.table_label.setText(f"{folder}: {name}, {n} rows")
        self._fill_axes(keep)
        self._show_row(None)
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
            combo.addItems(items)
            combo.setCurrentText(pick if pick in items else (items[0] if items else ""))
            combo.blockSignals(False)
        self._axes_changed()

    def _default_axes(self, names: list[str]) -> tuple[str, str, str]:
        """The spec's first chart with numeric x and y, else its first two numeric
        parameters, else the first two numeric columns."""
        for c in (self.spec or {}).get("chart", []):
            ys = c.get("y") if isinstance(c.get("y"), str) else None
            if c.get("x") in names and ys in names:
                return c["x"], ys, c.get("color") or c.get("metric") or "status"
        params = []
        if self.cols.get("params_json"):
            params = [p for p in json.loads(self.cols["params_json"][0])["params"]
                      if p in names and len(set(self.cols[p])) > 1]
        pick = [*dict.fromkeys(params + [n for n in names if n != "index"] + names)][:2]
        pick += ["", ""]
        return pick[0], pick[1], "status"

    def _axes_changed(self, *_):
        for axis, combo, box in (("x", self.x, self.log_x), ("y", self.y, self.log_y)):
            box.blockSignals(True)
            box.setChecked(self._log_default(axis, combo.currentText()))
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
        xname, yname = self.x.currentText(), self.y.currentText()
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
        if self.color.currentText() in self.cols:
            brushes, legend = colours([self.cols[self.color.currentText()][i] for i in rows])
            legend += "; red crosses: status not ok"
        else:
            brushes = [pg.mkBrush("#1f5fa8")] * len(rows)
        red = pg.mkBrush(NOT_OK_BRUSH)
        brushes = [b if good else red for b, good in zip(brushes, ok)]
        symbols = ["o" if good else "x" for good in ok]
        self.plot.getPlotItem().setLogMode(*logs)
        self.points.setData(x=px, y=py, data=rows, brush=brushes, symbol=symbols,
                            pen=pg.mkPen(None))
        self.plot.setLabel("bottom", xname)
        self.plot.setLabel("left", yname)
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
        busy = self.poll.isActive()
        self.open_button.setEnabled(self._kept_session() is not None and not busy)
        runs = (self.spec or {}).get("sweep", {}).get("kind") == "run"
        self.rerun_button.setEnabled(self.selected is not None and runs and not busy)
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
        for kind, (tag, value) in self.mailbox.drain():
            if tag != "rerun":
                continue
            self.poll.stop()
            self._sync_buttons()
            if kind == "error":
                self._say(f"re-run failed: {value}", error=True)
            else:
                self._rerun_done(value)

    def _rerun_done(self, row: dict) -> None:
        from labbench.sweep.point import TIME_COLUMNS

        old = self._rerun_of
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
