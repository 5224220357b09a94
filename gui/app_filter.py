"""An event filter on the whole application: every widget's events pass it first (Qt's
``QObject.installEventFilter`` on the ``QApplication``), so one object can guard a rule
window-wide, dialogs included."""
from __future__ import annotations

from PySide6 import QtCore, QtWidgets


class AppFilter(QtCore.QObject):
    """Installs itself on the QApplication when made; ``remove`` takes it off again."""

    def __init__(self, parent=None):
        super().__init__(parent)
        QtWidgets.QApplication.instance().installEventFilter(self)

    def remove(self) -> None:
        app = QtWidgets.QApplication.instance()
        if app is not None:
            app.removeEventFilter(self)
