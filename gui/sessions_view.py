"""Sessions browser: recorded runs (date, rig, protocol, status); replay, re-analyse, export."""
from __future__ import annotations

import time
from pathlib import Path

from PySide6 import QtCore, QtWidgets

COLUMNS = ("date", "rig", "protocol", "status", "samples", "file")


class SessionsView(QtWidgets.QWidget):
    """Emits requests with the selected session path; the window runs them off the GUI thread."""

    refresh_requested = QtCore.Signal()
    replay_requested = QtCore.Signal(str, object)  # path, speed (1.0, 10.0 or None = as fast as read)
    reanalyse_requested = QtCore.Signal(str, str)  # path, estimator
    export_requested = QtCore.Signal(str, str)  # path, "hdf5" | "csv" | "report"

    def __init__(self, directory: Path, estimators=("default",), parent=None):
        super().__init__(parent)
        self.directory = Path(directory)
        self.dir_label = QtWidgets.QLabel()
        choose = QtWidgets.QPushButton("Folder...")
        refresh = QtWidgets.QPushButton("Refresh")
        self.table = QtWidgets.QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.setSelectionBehavior(QtWidgets.QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QtWidgets.QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.doubleClicked.connect(lambda *_: self._emit_replay(1.0))
        self.estimator = QtWidgets.QComboBox()
        self.estimator.addItems(list(estimators))
        self.estimator.setToolTip("ETFE estimator used by Re-analyse")

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
        row = QtWidgets.QHBoxLayout()
        for text, slot in buttons:
            b = QtWidgets.QPushButton(text)
            b.clicked.connect(slot)
            row.addWidget(b)
            self.buttons[text] = b
            if text == "Re-analyse":
                row.addWidget(self.estimator)
        row.addStretch(1)
        lay = QtWidgets.QVBoxLayout(self)
        lay.addLayout(top)
        lay.addWidget(self.table, 1)
        lay.addLayout(row)
        choose.clicked.connect(self._choose)
        refresh.clicked.connect(self.refresh_requested)
        self.paths: list[str] = []
        self._set_dir_label()

    def _set_dir_label(self):
        self.dir_label.setText(str(self.directory))

    def _choose(self):
        from labbench.gui.dialogs import choose_folder

        d = choose_folder(self, "Session folder", str(self.directory))
        if d:
            self.directory = Path(d)
            self._set_dir_label()
            self.refresh_requested.emit()

    def set_sessions(self, summaries) -> None:
        """``summaries``: SessionSummary list (newest shown first)."""
        rows = sorted(summaries, key=lambda s: s.time or 0.0, reverse=True)
        self.table.setRowCount(len(rows))
        self.paths = [str(s.path) for s in rows]
        for i, s in enumerate(rows):
            date = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(s.time)) if s.time else "?"
            cells = (date, s.rig_name or "?", s.protocol or "?", s.status, str(s.n_samples),
                     Path(s.path).name)
            for j, text in enumerate(cells):
                self.table.setItem(i, j, QtWidgets.QTableWidgetItem(text))
        self.table.resizeColumnsToContents()
        if rows:
            self.table.selectRow(0)

    def selected(self) -> str | None:
        rows = self.table.selectionModel().selectedRows()
        return self.paths[rows[0].row()] if rows else None

    def select_path(self, path: str) -> None:
        if path in self.paths:
            self.table.selectRow(self.paths.index(path))

    def _emit_replay(self, speed):
        if p := self.selected():
            self.replay_requested.emit(p, speed)

    def _emit_reanalyse(self):
        if p := self.selected():
            self.reanalyse_requested.emit(p, self.estimator.currentText())

    def _emit_export(self, fmt: str):
        if p := self.selected():
            self.export_requested.emit(p, fmt)
