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


def never_widens(label: QtWidgets.QLabel, lines: int = 2) -> QtWidgets.QLabel:
    """A ``fixed_lines`` label whose text never sets the window's width: a long word (an
    exported file's path) is cut at the label's edge, whole in the tooltip (``set_text``).
    A path in a plain label widened the window from 1280 to 1922 px past the screen."""
    fixed_lines(label, lines)
    label.setMinimumWidth(1)  # not the longest word's width (QLabel's minimum size hint)
    return label


def set_text(label: QtWidgets.QLabel, text: str) -> None:
    """Text and the same as tooltip (a fixed-height label may not show all of it)."""
    label.setText(text)
    label.setToolTip(text)


class Elided(QtWidgets.QLabel):
    """A label ``lines`` text lines tall that never shows part of a line: the text
    word-wrapped into them, the last cut with an ellipsis where it runs on (``fixed_lines``
    shows the top of the line after its last); its width comes from the layout, never from
    the text. ``text()`` is the whole text; the tooltip is the caller's (``set_text``)."""

    def __init__(self, text: str = "", lines: int = 1, parent=None):
        super().__init__(parent)
        self._lines, self._whole = lines, ""
        self.setFixedHeight(lines * self.fontMetrics().lineSpacing() + 2)
        self.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Fixed)
        self.setAlignment(QtCore.Qt.AlignmentFlag.AlignLeft | (
            QtCore.Qt.AlignmentFlag.AlignVCenter if lines == 1 else QtCore.Qt.AlignmentFlag.AlignTop))
        self.setText(text)

    def text(self) -> str:  # noqa: D102 - the whole text, not what fits
        return self._whole

    def setText(self, text: str) -> None:  # noqa: N802 - Qt's name
        self._whole = text
        self._fit()

    def resizeEvent(self, event) -> None:  # noqa: N802 - Qt override
        super().resizeEvent(event)
        self._fit()

    def _fit(self) -> None:
        width = max(self.contentsRect().width(), 1)
        layout = QtGui.QTextLayout(self._whole, self.font())
        layout.beginLayout()
        shown = []
        while len(shown) < self._lines:
            line = layout.createLine()
            if not line.isValid():
                break
            line.setLineWidth(width)
            start = line.textStart()
            if len(shown) == self._lines - 1:  # the last line shown: the rest, cut to fit
                shown.append(self.fontMetrics().elidedText(
                    self._whole[start:], QtCore.Qt.TextElideMode.ElideRight, width))
            else:
                shown.append(self._whole[start:start + line.textLength()].rstrip())
        layout.endLayout()
        super().setText("\n".join(shown))
