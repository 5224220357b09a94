"""The Campaign page: a spec's points run one after another on the connected device
(``labbench campaign`` in the window, docs/campaign.md).

**Open spec...** reads a spec; the window plans it on the device chosen on the left (the
rig, its identified plant, its last commissioning) and the page shows the plan: points,
already done, time, the largest force and stiffness, the plant. **Start** asks the window,
which runs each point through the same Start as any run (pre-check, commissioning gate,
E-STOP, a session per point; on real hardware it asks once first); **Stop** ends the
campaign after stopping the running point, which then runs again next time; **points: at
most N** runs N of the points still to run. The table and the live chart
(``labbench.gui.campaign_chart``: the Z-width, rate vs accuracy, the row under the mouse
named) fill in as rows are written; **Open session** replays the selected point's session.
"""
from __future__ import annotations

from html import escape
from pathlib import Path

from PySide6 import QtCore, QtGui, QtWidgets

from labbench.gui.campaign_chart import CampaignChart
from labbench.gui.tables import row_list
from labbench.readout.numfmt import fmt

COLUMNS = ("#", "point", "status", "result", "predicted", "error", "session")


def row_cells(r: dict) -> list[str]:
    """One table row of a campaign row: what it measured beside the prediction."""
    if r.get("zw.k_max") is not None or r.get("zw.k_max_above") is not None:
        measured = (f"K_max {fmt(r['zw.k_max'])} N/m" if r.get("zw.k_max") is not None
                    else f"K_max > {fmt(r['zw.k_max_above'])} N/m")
        predicted = f"{fmt(r.get('pred.k_max'))} N/m"
        error = "-" if r.get("zw.rel_error") is None else f"{fmt(100 * r['zw.rel_error'], 3)} %"
    elif r.get("acc.ed_median") is not None:
        measured = f"ED error {fmt(100 * r['acc.ed_median'], 3)} %"
        predicted = f"{fmt(100 * r.get('pred.ed_median', 0.0), 3)} %"
        error = f"{fmt(100 * r.get('acc.ed_in_band', 0.0), 3)} % in band"
    else:
        measured, predicted, error = r.get("verdict") or "-", "-", r.get("error") or "-"
    session = Path(r["session"]).name if r.get("session") else "-"
    return [str(r.get("index")), point_label(r), str(r.get("status")), measured, predicted,
            error if r.get("status") == "ok" else (r.get("error") or error), session]


def read_table(directory) -> tuple[list[dict], list]:
    """The campaign table's rows ([] before it has any) and the charts they make
    (``labbench.campaign.figures.charts``: their theory curves take a second or so); no Qt:
    the window runs it off the GUI thread."""
    from labbench.campaign import figures
    from labbench.sweep import charts, table as tables

    if not tables.is_table(directory):
        return [], []
    tab = tables.read_table(directory)
    rows = figures.table_rows(charts.columns(tab)) if tab.num_rows else []
    return rows, figures.charts(rows)


def point_label(r: dict) -> str:
    import json

    try:
        p = json.loads(r.get("params_json") or "{}")
    except ValueError:
        return "-"
    return ", ".join(f"{k} = {v}" for k, v in {**p.get("tags", {}), **p.get("params", {})}.items())


class CampaignView(QtWidgets.QWidget):
    """Buttons emit requests; the window plans, runs and reports back with ``show_*``."""

    open_requested = QtCore.Signal(str)  # a spec file
    start_requested = QtCore.Signal()
    stop_requested = QtCore.Signal()
    session_requested = QtCore.Signal(str)

    def __init__(self, parent=None):
        super().__init__(parent)
        self.open_button = QtWidgets.QPushButton("Open spec...")
        self.start_button = QtWidgets.QPushButton("Start campaign")
        self.stop_button = QtWidgets.QPushButton("Stop campaign")
        self.session_button = QtWidgets.QPushButton("Open session")
        for b in (self.start_button, self.stop_button, self.session_button):
            b.setEnabled(False)
        self.plan_label = QtWidgets.QLabel("open a spec (docs/examples/z-width.toml, "
                                           "rate-vs-accuracy.toml, or your own)")
        self.plan_label.setWordWrap(True)
        self.plan_label.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        self.state_label = QtWidgets.QLabel("")
        self.state_label.setWordWrap(True)
        self.table = row_list(COLUMNS)
        self.table.horizontalHeader().setSectionResizeMode(
            QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        self.chart = CampaignChart()
        self.chart.setMinimumHeight(200)
        self.chart.row_hovered.connect(self._show_hovered)
        self.chart.row_clicked.connect(lambda i: i >= 0 and self.table.selectRow(i))
        self.limit = QtWidgets.QSpinBox()  # a slice of a long campaign from the page
        self.limit.setRange(0, 1_000_000)
        self.limit.setSpecialValueText("points: all")
        self.limit.setPrefix("points: at most ")
        self.limit.setToolTip("how many of the points still to run Start campaign runs now (the "
                              "rest at the next Start, as after Stop); all: every one")

        top = QtWidgets.QHBoxLayout()
        for b in (self.open_button, self.limit, self.start_button, self.stop_button):
            top.addWidget(b)
        top.addWidget(self.state_label, 1)
        split = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        below = QtWidgets.QWidget()
        bl = QtWidgets.QVBoxLayout(below)
        bl.setContentsMargins(0, 0, 0, 0)
        bl.addWidget(self.table, 1)
        bl.addWidget(self.session_button, 0, QtCore.Qt.AlignmentFlag.AlignLeft)
        split.addWidget(self.chart)
        split.addWidget(below)
        self.split = split
        lay = QtWidgets.QVBoxLayout(self)
        lay.addLayout(top)
        lay.addWidget(self.plan_label)
        lay.addWidget(split, 1)

        self._sized = False  # the chart given two thirds at the first show
        self.rows: list[dict] = []
        self.planned = False
        self.running = False
        self._can_start = False
        self.open_button.clicked.connect(self._choose_spec)
        self.start_button.clicked.connect(self.start_requested)
        self.stop_button.clicked.connect(self.stop_requested)
        self.session_button.clicked.connect(self._open_session)
        self.table.itemSelectionChanged.connect(self._sync)
        self.table.itemDoubleClicked.connect(lambda _item: self._open_session())

    def showEvent(self, event) -> None:  # noqa: N802 - Qt override
        super().showEvent(event)
        if not self._sized:
            self._sized = True
            total = sum(self.split.sizes())
            self.split.setSizes([2 * total // 3, total - 2 * total // 3])

    # ----- what the window tells the page --------------------------------------------------
    def show_plan(self, lines: list[str] | None, error: str = "") -> None:
        """The plan's lines (``labbench.campaign.plan.describe``), or why there is none."""
        self.planned = lines is not None
        self.plan_label.setText(escape(error) if error else
                                "<br>".join(escape(x).replace("  ", "&nbsp;&nbsp;") for x in lines))
        self.plan_label.setStyleSheet("QLabel { color: #b00020; }" if error else "")
        self._sync()

    def show_state(self, text: str) -> None:
        self.state_label.setText(text)

    def set_running(self, running: bool) -> None:
        self.running = running
        self._sync()

    def show_table(self, table: tuple[list[dict], list]) -> None:
        """The campaign's rows so far and their charts (``read_table``), in the table and on
        the chart."""
        rows, charts = table
        keep = self.selected_session()
        self.rows = rows
        self.table.setRowCount(len(rows))
        for i, r in enumerate(rows):
            for j, text in enumerate(row_cells(r)):
                item = QtWidgets.QTableWidgetItem(text)
                if j == 2 and r.get("status") != "ok":
                    item.setForeground(QtGui.QBrush(QtGui.QColor("#b00020")))
                self.table.setItem(i, j, item)
            if keep and r.get("session") == keep:
                self.table.selectRow(i)
        self.chart.show(charts, rows)
        self._sync()

    def _show_hovered(self, i: int) -> None:
        """The row under the mouse, under the chart (as the table writes it)."""
        if 0 <= i < len(self.rows):
            cells_ = row_cells(self.rows[i])
            self.chart.caption.setText("; ".join(f"{c}: {v}" for c, v in zip(COLUMNS, cells_)))

    def follow(self, state) -> None:
        """Start only when a run could start (and a plan is there); Stop while running."""
        self._can_start = state.can_start
        self._sync()

    # ----- the page's own ------------------------------------------------------------------
    def selected_session(self) -> str | None:
        rows = self.table.selectionModel().selectedRows() if self.table.selectionModel() else []
        if not rows or rows[0].row() >= len(self.rows):
            return None
        return self.rows[rows[0].row()].get("session")

    def _sync(self) -> None:
        self.start_button.setEnabled(self.planned and self._can_start and not self.running)
        self.stop_button.setEnabled(self.running)
        self.open_button.setEnabled(not self.running)
        self.limit.setEnabled(not self.running)
        self.session_button.setEnabled(bool(self.selected_session()))

    def _choose_spec(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Open a campaign spec", "",
                                                        "spec (*.toml);;all files (*)")
        if path:
            self.open_requested.emit(path)

    def _open_session(self) -> None:
        path = self.selected_session()
        if path:
            self.session_requested.emit(path)
