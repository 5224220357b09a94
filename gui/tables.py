"""Tables that list things a person picks one of (sessions, a campaign's points)."""
from __future__ import annotations

from PySide6 import QtWidgets


def row_list(columns: list[str]) -> QtWidgets.QTableWidget:
    """A read-only table of ``columns`` whose rows are picked whole, one at a time, without
    row numbers."""
    table = QtWidgets.QTableWidget(0, len(columns))
    table.setHorizontalHeaderLabels(columns)
    table.verticalHeader().setVisible(False)
    table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
    view = QtWidgets.QAbstractItemView
    table.setSelectionBehavior(view.SelectionBehavior.SelectRows)
    table.setSelectionMode(view.SelectionMode.SingleSelection)
    return table
