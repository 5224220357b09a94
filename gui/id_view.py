"""Identification view: measured vs model force, the l2 / l1 table with intervals, the model chosen."""
from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtWidgets

from gui.live_plots import COLOURS


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v):
        return f"[{v[0]:.4g}, {v[1]:.4g}]"
    return str(v)


class IdView(QtWidgets.QWidget):
    def __init__(self, parent=None):
        super().__init__(parent)
        self.plot = pg.PlotWidget()
        self.plot.setLabel("left", "force", units="N")
        self.plot.setLabel("bottom", "time", units="s")
        self.plot.showGrid(x=True, y=True, alpha=0.3)
        self.plot.addLegend(offset=(-10, 5))
        self.plot.setClipToView(True)
        self.plot.setDownsampling(auto=True, mode="peak")
        self.measured = self.plot.plot(pen=pg.mkPen(COLOURS["excitation"], width=1), name="measured")
        self.model = self.plot.plot(pen=pg.mkPen(COLOURS["theory"], width=1), name="model")
        self.chosen = QtWidgets.QLabel("no identification yet: run chirp-ID, or open a session and press Re-analyse")
        self.chosen.setWordWrap(True)
        self.table = QtWidgets.QTableWidget(0, 0)
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        split = QtWidgets.QSplitter()
        split.addWidget(self.plot)
        side = QtWidgets.QWidget()
        lay = QtWidgets.QVBoxLayout(side)
        lay.addWidget(self.chosen)
        lay.addWidget(self.table, 1)
        split.addWidget(side)
        split.setSizes([700, 400])
        QtWidgets.QVBoxLayout(self).addWidget(split)
        self.results: dict = {}

    def show_results(self, results: dict[str, dict], chosen: str,
                     t=None, f_measured=None, f_model=None) -> None:
        """``results``: method name -> ``IdResult.as_dict()``; one table column per method."""
        self.results = results
        keys: list[str] = []
        for res in results.values():
            for k, v in res.items():
                if k not in keys and not isinstance(v, (dict, np.ndarray)) and not (
                        isinstance(v, list) and len(v) > 2):
                    keys.append(k)
        self.table.setRowCount(len(keys))
        self.table.setColumnCount(len(results))
        self.table.setHorizontalHeaderLabels(list(results))
        self.table.setVerticalHeaderLabels(keys)
        for col, res in enumerate(results.values()):
            for row, k in enumerate(keys):
                self.table.setItem(row, col, QtWidgets.QTableWidgetItem(_fmt(res.get(k, ""))))
        self.table.resizeColumnsToContents()
        self.chosen.setText(chosen)
        if t is not None:
            self.measured.setData(t, f_measured)
            self.model.setData(t, f_model if f_model is not None else [])
