"""The E-STOP keys: one rule for the whole application, dialogs and pop-up lists included.

While a device is connected (or connecting, or a run or replay goes on), **Esc** is E-STOP
wherever the keyboard focus is: the main window, a file dialog, a completion list, a
drop-down list, a message box. It never closes a dialog or a list then (dialogs close by
their buttons, lists by clicking away), so the same key cannot mean "close" in one place
and "stop" in the next. **Space** is E-STOP too, except while typing in a text field.
With no device and nothing running, both keys keep their usual meaning.

One event filter on the application sees every key press before any widget (a dialog's
own Esc handling, a completer's event filter, a shortcut) does: Qt runs the
application's filters first for every object. A ``QShortcut`` could not give this rule:
a dialog accepts Esc as an override and a completer's pop-up eats it, so Esc latched the
E-STOP in one state of a dialog and closed it in another (issue 31).
"""
from __future__ import annotations

from typing import Callable

from PySide6 import QtCore, QtWidgets

from labbench.gui.app_filter import AppFilter

KEYS = "Esc / Space"
ARMED_HINT = "E-STOP: Esc everywhere (dialogs too); Space outside text fields"
# the keyboard is in a text field: there a space is text (issue 43: the line said Space
# stopped everywhere; typed in the Sessions filter during a run, it typed a space)
ARMED_TYPING_HINT = "E-STOP: Esc (Space types a space in this text field)"
UNARMED_HINT = "E-STOP keys (Esc; Space outside text fields) once a device is connected"


def hint(armed: bool) -> str:
    """The rule as it holds now, where the keyboard is."""
    if not armed:
        return UNARMED_HINT
    return ARMED_TYPING_HINT if typing_in(QtWidgets.QApplication.focusWidget()) else ARMED_HINT
RULE = ("While a device is connected, Esc (and Space outside a text field) is E-STOP wherever "
        "the keyboard is: the window, file dialogs, completion and drop-down lists. It then never "
        "closes a dialog or a list: close those with their buttons or by clicking away. With no "
        "device, both keys do what they usually do.")


def typing_in(widget) -> bool:
    """A field where a space is text: an editable line, text box, spin box or list."""
    if isinstance(widget, QtWidgets.QComboBox):
        return widget.isEditable()
    if isinstance(widget, (QtWidgets.QLineEdit, QtWidgets.QTextEdit, QtWidgets.QPlainTextEdit)):
        return not widget.isReadOnly()
    return isinstance(widget, QtWidgets.QAbstractSpinBox)


class EStopKeys(AppFilter):
    """Installed on the QApplication: Esc, and Space outside text fields, call ``stop``
    (once per press) while ``armed()``; the key goes no further then."""

    def __init__(self, armed: Callable[[], bool], stop: Callable[[], None], parent=None):
        super().__init__(parent)
        self.armed, self.stop = armed, stop

    def eventFilter(self, obj, event) -> bool:  # noqa: N802 - Qt override
        kind = event.type()
        if kind not in (QtCore.QEvent.Type.KeyPress, QtCore.QEvent.Type.ShortcutOverride):
            return False
        key = event.key()
        if key == QtCore.Qt.Key.Key_Space:
            if typing_in(QtWidgets.QApplication.focusWidget()):
                return False
        elif key != QtCore.Qt.Key.Key_Escape:
            return False
        if not self.armed():
            return False
        if kind == QtCore.QEvent.Type.ShortcutOverride:
            event.accept()  # "the focus widget takes this key": no shortcut fires, the press follows
            return True
        if not event.isAutoRepeat():
            self.stop()
        return True
