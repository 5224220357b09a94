"""No value changes under a passing mouse wheel (issue 43).

Qt's drop-down lists, spin boxes and sliders take the wheel whenever the pointer is over
them, focused or not (a QComboBox even takes the keyboard focus from the wheel): rolling
the wheel to scroll the Protocol panel changed the estimator under the pointer, and the
next runs used it. Here such a widget changes its value by the wheel only once it has the
keyboard focus (a click or Tab gave it); otherwise the wheel scrolls the panel it sits in.

One filter on the application: it sees every widget polished (and turns a wheel-focus
policy into a click-or-Tab one) and every wheel event before the widget does.
"""
from __future__ import annotations

from PySide6 import QtCore, QtWidgets

from labbench.gui.app_filter import AppFilter

VALUE_WIDGETS = (QtWidgets.QComboBox, QtWidgets.QAbstractSpinBox, QtWidgets.QAbstractSlider)


def takes_wheel(widget) -> bool:
    """A widget whose value the wheel would change (a scroll bar scrolls: it is one's job)."""
    return isinstance(widget, VALUE_WIDGETS) and not isinstance(widget, QtWidgets.QScrollBar)


def scroller_of(widget) -> QtWidgets.QAbstractScrollArea | None:
    """The nearest scroll area around ``widget`` that can scroll vertically (else the nearest)."""
    nearest = None
    w = widget.parentWidget()
    while w is not None:
        if isinstance(w, QtWidgets.QAbstractScrollArea):
            nearest = nearest or w
            if w.verticalScrollBar().maximum() > 0:
                return w
        w = w.parentWidget()
    return nearest


class WheelGuard(AppFilter):
    """Installed on the QApplication (once, by the window)."""

    def eventFilter(self, obj, event) -> bool:  # noqa: N802 - Qt override
        kind = event.type()
        if kind == QtCore.QEvent.Type.Polish and takes_wheel(obj):
            if obj.focusPolicy() == QtCore.Qt.FocusPolicy.WheelFocus:
                obj.setFocusPolicy(QtCore.Qt.FocusPolicy.StrongFocus)
            return False
        if kind != QtCore.QEvent.Type.Wheel or not takes_wheel(obj) or obj.hasFocus():
            return False
        area = scroller_of(obj)
        if area is not None:  # the panel scrolls as if the widget were not there
            bar = area.verticalScrollBar() if event.angleDelta().y() else area.horizontalScrollBar()
            QtWidgets.QApplication.sendEvent(bar, event)
        event.accept()
        return True
