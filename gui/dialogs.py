"""The window's file dialogs: Qt's own, never the desktop's native ones.

A native dialog (GTK, a portal) takes the keyboard outside Qt, where the application's
E-STOP keys (``labbench.gui.estop_keys``) cannot see Esc; Qt's own dialog is part of the
application, so Esc is E-STOP in it as everywhere else while a device is connected.
"""
from __future__ import annotations

from PySide6 import QtWidgets

OWN = QtWidgets.QFileDialog.Option.DontUseNativeDialog


def choose_folder(parent, title: str, start: str) -> str:
    """A folder the person picks ("" when cancelled)."""
    return QtWidgets.QFileDialog.getExistingDirectory(
        parent, title, start, OWN | QtWidgets.QFileDialog.Option.ShowDirsOnly)


def choose_file(parent, title: str, start: str, filters: str) -> str:
    """A file the person picks ("" when cancelled); ``filters`` as Qt writes them,
    e.g. "sweep spec (*.toml)"."""
    return QtWidgets.QFileDialog.getOpenFileName(parent, title, start, filters, options=OWN)[0]
