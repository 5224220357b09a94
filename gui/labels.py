"""Labels that keep their room: a fixed number of text lines whatever they say, so a
longer message never moves what is below it (Start, the pages); what does not fit is in
the tooltip."""
from __future__ import annotations

from PySide6 import QtCore, QtGui, QtWidgets


def fixed_lines(label: QtWidgets.QLabel, lines: int) -> QtWidgets.QLabel:
    """A label ``lines`` text lines tall whatever it says (word-wrapped; what does not fit
    is in its tooltip): text changes never move what is below it."""
    label.setWordWrap(True)
    label.setFixedHeight(lines * QtGui.QFontMetrics(label.font()).lineSpacing() + 4)
    label.setAlignment(QtCore.Qt.AlignmentFlag.AlignLeft | QtCore.Qt.AlignmentFlag.AlignTop)
    return label


def set_text(label: QtWidgets.QLabel, text: str) -> None:
    """Text and the same as tooltip (a fixed-height label may not show all of it)."""
    label.setText(text)
    label.setToolTip(text)
