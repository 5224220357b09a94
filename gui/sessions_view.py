"""Sessions browser: the recorded runs of a folder, told apart by what they rendered (VE,
K, B), how long they ran and what their analysis said (the worst verdict), filterable;
replay, re-analyse (with progress and Cancel), export."""
from __future__ import annotations

import re
import time
from pathlib import Path

from PySide6 import QtCore, QtGui, QtWidgets

from labbench.gui.labels import never_widens, set_text
from labbench.gui.tables import row_list
from labbench.gui.verdict_view import COLOURS
from labbench.readout.numfmt import fmt

COLUMNS = ("date", "protocol", "device", "VE", "K [N/m]", "B [N s/m]", "duration [s]",
           "status", "verdict", "samples", "rig", "file")
NUMBERS = ("K [N/m]", "B [N s/m]", "duration [s]", "samples")  # the filter matches them whole


def matches(row: tuple[str, ...], words: list[str]) -> bool:
    """Whether a row holds every word: a number column equal to it ("200" is K = 200, not
    2000 samples), or any other cell containing it (case aside); a number, only whole in
    those too ("2026" is a date's year; "200" is not in a file stamped 20:05:12)."""
    cells_ = [c.lower() for c in row]
    exact = {c for name, c in zip(COLUMNS, cells_) if name in NUMBERS}
    text = " ".join(c for name, c in zip(COLUMNS, cells_) if name not in NUMBERS)
    tokens = set(re.findall(r"[a-z0-9]+", text))
    return all(w in exact or (w in tokens if _number(w) else w in text) for w in words)


def _number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def cells(s) -> tuple[str, ...]:
    """The row of a ``SessionSummary`` as a person reads it (blank: not recorded, or not
    applicable: an open-loop run, VE "none", has no K, B)."""
    date = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(s.time)) if s.time else "?"
    ve = s.ve or ("none" if s.protocol else "")  # a run's start names no VE: it rendered none
    k = fmt(s.K) if s.K is not None else ""
    verdict = s.verdict or ""
    if k and s.protocol == "stability":  # a probe's VE is where it starts, not its K_max
        k, verdict = _probe(k, s.boundary, verdict)
    return (date, s.protocol or "?", s.device or "?", ve, k,
            fmt(s.B) if s.B is not None else "",
            f"{s.duration_s:.1f}" if s.duration_s is not None else "",
            s.status + (f", {s.overruns} overrun{'s' if s.overruns > 1 else ''}" if s.overruns else ""),
            verdict, str(s.n_samples), s.rig_name or "?", Path(s.path).name)


def _probe(k: str, boundary, verdict: str) -> tuple[str, str]:
    """A stability probe's K and verdict cells: its measured boundary (K_max, in the K column;
    td_max beside the agreement) and the agreement as its readout words it (the parenthesis
    of the friction-aware one, why it agrees, is left to the readout)."""
    if boundary is None:
        return f"from {k}", verdict or "no boundary measured"
    var, measured, against = boundary
    said = ""
    if against is not None:
        label, text = against
        said = f"{label.removeprefix('measured ')}: {text.split(' (')[0]}"
    if var == "K":
        return f"K_max {measured.split(' ')[0]} (from {k})", verdict or said
    return k, verdict or f"td_max {measured.split(' (')[0]}" + (f"; {said}" if said else "")


class SessionsView(QtWidgets.QWidget):
    """Emits requests with the selected session path; the window runs them off the GUI thread."""

    refresh_requested = QtCore.Signal()
    replay_requested = QtCore.Signal(str, object)  # path, speed (1.0, 10.0 or None = as fast as read)
    reanalyse_requested = QtCore.Signal(str, str)  # path, estimator
    cancel_requested = QtCore.Signal()  # the re-analysis under way
    export_requested = QtCore.Signal(str, str)  # path, "hdf5" | "csv" | "report"

    def __init__(self, directory: Path, estimators=("default",), parent=None):
        super().__init__(parent)
        self.directory = Path(directory)
        self.dir_label = never_widens(QtWidgets.QLabel(), 1)
        choose = QtWidgets.QPushButton("Folder...")
        refresh = QtWidgets.QPushButton("Refresh")
        self.filter = QtWidgets.QLineEdit()
        self.filter.setPlaceholderText("filter: words every row shown has (numbers whole), "
                                       "e.g. etfe 200 failed")
        self.filter.setClearButtonEnabled(True)
        self.count = QtWidgets.QLabel("")
        self.table = row_list(COLUMNS)
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.doubleClicked.connect(lambda *_: self._emit_replay(1.0))
        self.estimator = QtWidgets.QComboBox()
        self.estimator.addItems(list(estimators))
        self.estimator.setToolTip("ETFE estimator used by Re-analyse")
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setTextVisible(False)
        self.progress_line = never_widens(QtWidgets.QLabel(""))
        self.cancel_button = QtWidgets.QPushButton("Cancel")
        self.cancel_button.setToolTip("stop the re-analysis; what the window shows stays as it was")
        self.cancel_button.setEnabled(False)
        self.cancel_button.clicked.connect(self.cancel_requested)

        buttons = [("Replay 1x", lambda: self._emit_replay(1.0)),
                   ("Replay fast", lambda: self._emit_replay(None)),
                   ("Re-analyse", self._emit_reanalyse),
                   ("Export HDF5", lambda: self._emit_export("hdf5")),
                   ("Export CSV", lambda: self._emit_export("csv")),
                   ("Export report", lambda: self._emit_export("report"))]
        self.buttons = {}
        top = QtWidgets.QHBoxLayout()
        top.addWidget(QtWidgets.QLabel("folder:"))
        top.addWidget(self.dir_label, 1)
        top.addWidget(choose)
        top.addWidget(refresh)
        find = QtWidgets.QHBoxLayout()
        find.addWidget(self.filter, 1)
        find.addWidget(self.count)
        row = QtWidgets.QHBoxLayout()
        for text, slot in buttons:
            b = QtWidgets.QPushButton(text)
            b.clicked.connect(slot)
            row.addWidget(b)
            self.buttons[text] = b
            if text == "Re-analyse":
                row.addWidget(self.estimator)
        row.addStretch(1)
        busy = QtWidgets.QHBoxLayout()
        busy.addWidget(self.progress, 1)
        busy.addWidget(self.progress_line, 3)
        busy.addWidget(self.cancel_button)
        lay = QtWidgets.QVBoxLayout(self)
        lay.addLayout(top)
        lay.addLayout(find)
        lay.addWidget(self.table, 1)
        lay.addLayout(row)
        lay.addLayout(busy)
        choose.clicked.connect(self._choose)
        refresh.clicked.connect(self.refresh_requested)
        self.filter.textChanged.connect(lambda *_: self._apply_filter())
        self.paths: list[str] = []
        self._analysing = False
        self._idle = True
        self._set_dir_label()

    def _set_dir_label(self):
        set_text(self.dir_label, str(self.directory))

    def _choose(self):
        from labbench.gui.dialogs import choose_folder

        d = choose_folder(self, "Session folder", str(self.directory))
        if d:
            self.directory = Path(d)
            self._set_dir_label()
            self.refresh_requested.emit()

    def set_sessions(self, summaries) -> None:
        """``summaries``: SessionSummary list (newest shown first); the selection and the
        filter stay."""
        was = self.selected()
        rows = sorted(summaries, key=lambda s: s.time or 0.0, reverse=True)
        self.table.setRowCount(len(rows))
        self.paths = [str(s.path) for s in rows]
        for i, s in enumerate(rows):
            for j, text in enumerate(cells(s)):
                item = QtWidgets.QTableWidgetItem(text)
                if COLUMNS[j] == "verdict" and text in COLOURS:
                    item.setForeground(QtGui.QBrush(QtGui.QColor(COLOURS[text])))
                self.table.setItem(i, j, item)
        self.table.resizeColumnsToContents()
        self._apply_filter()
        if was in self.paths:
            self.select_path(was)
        elif rows:
            self._select_first_shown()

    def shown_rows(self) -> list[list[str]]:
        """The rows the filter lets through, as shown (for tests)."""
        return [[self.table.item(r, c).text() for c in range(len(COLUMNS))]
                for r in range(self.table.rowCount()) if not self.table.isRowHidden(r)]

    def _apply_filter(self) -> None:
        words = self.filter.text().lower().split()
        shown = 0
        for r in range(self.table.rowCount()):
            row = tuple(self.table.item(r, c).text() for c in range(len(COLUMNS)))
            hide = not matches(row, words)
            self.table.setRowHidden(r, hide)
            shown += not hide
        total = self.table.rowCount()
        self.count.setText(f"{shown} of {total} sessions" if words else f"{total} sessions")
        if self.selected() is None:
            self._select_first_shown()

    def _select_first_shown(self) -> None:
        for r in range(self.table.rowCount()):
            if not self.table.isRowHidden(r):
                self.table.selectRow(r)
                return
        self.table.clearSelection()

    def selected(self) -> str | None:
        rows = [i for i in self.table.selectionModel().selectedRows()
                if not self.table.isRowHidden(i.row())]
        return self.paths[rows[0].row()] if rows else None

    def select_path(self, path: str) -> None:
        if path in self.paths:
            self.table.selectRow(self.paths.index(path))

    # ----- what the window tells the page ---------------------------------------------------
    def follow(self, state) -> None:
        """The run's state (``RunState``): Replay and Re-analyse while nothing streams in
        (the Live page shows the run or replay under way)."""
        self._idle = state.activity == "idle"
        self._sync()

    def show_analysis(self, frac: float, text: str) -> None:
        """A re-analysis under way (``frac`` 0..1): its progress, and Cancel."""
        self._analysing = True
        self.progress.setValue(int(1000 * min(max(frac, 0.0), 1.0)))
        set_text(self.progress_line, text)
        self._sync()

    def analysis_ended(self, text: str, frac: float) -> None:
        self._analysing = False
        self.progress.setValue(int(1000 * frac))
        set_text(self.progress_line, text)
        self._sync()

    def show_export(self, text: str) -> None:
        """An export under way (a report takes 10-30 s): the bar busy, what is written."""
        if not self._analysing:  # a re-analysis' own progress keeps the bar
            self.progress.setRange(0, 0)
        set_text(self.progress_line, text)

    def export_ended(self, text: str) -> None:
        if not self._analysing:
            self.progress.setRange(0, 1000)
            self.progress.setValue(1000)
        set_text(self.progress_line, text)

    def _sync(self) -> None:
        self.cancel_button.setEnabled(self._analysing)
        for name in ("Replay 1x", "Replay fast", "Re-analyse"):
            self.buttons[name].setEnabled(self._idle and not self._analysing)

    def _emit_replay(self, speed):
        if (p := self.selected()) and self.buttons["Replay 1x"].isEnabled():
            self.replay_requested.emit(p, speed)

    def _emit_reanalyse(self):
        if p := self.selected():
            self.reanalyse_requested.emit(p, self.estimator.currentText())

    def _emit_export(self, fmt: str):
        if p := self.selected():
            self.export_requested.emit(p, fmt)
